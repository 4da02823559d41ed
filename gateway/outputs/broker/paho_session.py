"""The one paho session engine under both northbound MQTT clients.

The JSON tree's pump (:class:`..mqtt.pump.MqttPump`) and the Sparkplug edge node
(:class:`..sparkplug.node_session.NodeSession`, on its node's thread) each own one paho client. What they
share lives here, once:

- **the server list** (``BrokerSettings.servers``: the nodes of a clustered broker, or Sparkplug's
  server set): the session connects to the current server; a server that cannot be reached moves
  it to the next one *at once*, and only when every server of the list failed in a row does it
  wait (the back-off). A lost connection is retried on the same server after the shortest
  back-off (a broker restarting, or a cluster node gone: then its connect fails and the next one
  is tried), so a clustered broker losing a node costs about ``reconnect_min_s``;
- **the back-off**: doubling from ``reconnect_min_s`` to ``reconnect_max_s``, reset by a
  connection the broker accepted;
- **the client ID per server**: with more than one server, the session on server *i* (1-based)
  uses ``<client id>-<i>``. A clustered broker may keep a session's server-side state on the node
  it was made on: RabbitMQ 3.10 homes a subscriber's queue there, and while that node is down a
  new session under the same client ID on another node is refused (its queue's home node is
  unreachable), so the same ID would lock the station out for as long as the node is away. One
  ID per server keeps each node's state its own; the ``status`` ``session`` counter tells an MES
  which session is the current one. With one server the ID is the configured one, unchanged;
- **the client**: paho 2.x, no queue of its own beyond what is in flight (the engines keep their
  data in their SQLite outbox), credentials and TLS from the settings, a Will set before CONNECT;
- **dropping a session** without DISCONNECT (so that the broker publishes the Will);
- **the hand-over** to the session thread: a :class:`gateway.plumbing.threadloop.Mailbox` (bounded, a
  drop policy of the engine's choice), never a queue of its own.

The engines keep what is theirs: what to publish after CONNACK, what the Will says, the MQTT 5 /
3.1.1 choice (the pump), bdSeq and births (Sparkplug).
"""
from __future__ import annotations

import logging
import socket
import time

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from ...plumbing.backoff import Backoff
from .settings import BrokerSettings

__all__ = ["PahoSession"]


class PahoSession:
    """Server list, back-off, client set-up, connect and drop of one paho session (see above).

    Used by one thread only (the engine's); ``what`` names the session in log lines."""

    def __init__(self, settings: BrokerSettings, what: str, log: logging.Logger) -> None:
        self.bs = settings
        self._what = what
        self._slog = log
        self._client: paho.Client | None = None
        self._sock_open = False
        self._server = 0
        self._failed_in_row = 0
        self._next_attempt = 0.0
        #: the reconnect back-off (gateway/plumbing/backoff.py, the one back-off): doubling from
        #: reconnect_min_s to reconnect_max_s while connects fail, reset by an accepted session
        self._retry = Backoff(settings.reconnect_min_s,
                              max(settings.reconnect_min_s, settings.reconnect_max_s))
        self._unreachable_logged = False
        #: connections the broker accepted / connect attempts that failed (any server)
        self.session_connects = 0
        self.connect_errors = 0

    # ------------------------------------------------------------------ the server list
    @property
    def servers(self) -> list[tuple[str, int]]:
        return self.bs.servers

    @property
    def server(self) -> tuple[str, int]:
        """The server the session connects (or is connected) to."""
        return self.servers[self._server % len(self.servers)]

    def _next_server(self) -> None:
        self._server = (self._server + 1) % len(self.servers)

    def client_id_for(self, base: str) -> str:
        """The client ID on the current server (see the module docstring)."""
        if len(self.servers) == 1:
            return base
        return f"{base}-{self._server % len(self.servers) + 1}"

    # ------------------------------------------------------------------ back-off
    def _schedule_retry(self, max_delay: bool = False) -> None:
        wait = self._retry.failed()
        delay = self.bs.reconnect_max_s if max_delay else wait
        self._next_attempt = time.monotonic() + delay

    def _retry_now(self) -> None:
        self._next_attempt = 0.0

    def _session_up(self) -> None:
        """The broker accepted the connection: the back-off starts again from its shortest."""
        self._retry.reset()
        self._failed_in_row = 0
        self._unreachable_logged = False
        self.session_connects += 1

    def _attempt_wait(self) -> float:
        """Seconds until the next connect attempt is due (≤ 0: now)."""
        return self._next_attempt - time.monotonic()

    # ------------------------------------------------------------------ the client
    def _paho_client(self, client_id: str, *, v5: bool = False) -> paho.Client:
        """A new paho client with credentials and TLS (SecretError, OSError or ValueError when
        they cannot be read); nothing queued beyond what is in flight."""
        c = paho.Client(CallbackAPIVersion.VERSION2, client_id=client_id,
                        clean_session=None if v5 else True,
                        protocol=paho.MQTTv5 if v5 else paho.MQTTv311)
        c.max_queued_messages_set(0)
        self.bs.apply(c)
        return c

    def _open(self, client: paho.Client, *, v5: bool = False) -> bool:
        """CONNECT to the current server (the socket only: CONNACK comes in the network loop).
        False when it cannot be reached: the next server is then due at once, or — every server
        failed in a row — after the back-off."""
        host, port = self.server
        try:
            if v5:      # a clean start and no session expiry, as the clean session of 3.1.1
                client.connect(host, int(port), keepalive=int(self.bs.keepalive_s), clean_start=True)
            else:
                client.connect(host, int(port), keepalive=int(self.bs.keepalive_s))
        except (OSError, ValueError) as e:
            self.connect_errors += 1
            self._failed_in_row += 1
            n = len(self.servers)
            if not self._unreachable_logged:
                more = f"; trying the next of {n} servers" if n > 1 else ""
                self._slog.warning("%s: MQTT broker %s:%s unreachable (%s)%s; data is kept", self._what,
                                   host, port, e, more)
                self._unreachable_logged = True
            self._sock_open = False
            if n > 1:
                self._next_server()
            if n > 1 and self._failed_in_row % n:
                self._retry_now()
            else:
                self._schedule_retry()
            return False
        self._sock_open = True
        return True

    def _drop_socket(self, c: paho.Client) -> None:
        """Close the client's socket without DISCONNECT (the broker publishes the Will)."""
        try:
            sock = c.socket()
            if isinstance(sock, socket.socket):        # ssl.SSLSocket is one too
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                sock.close()
        except Exception:  # noqa: BLE001 - a broken client: it is dropped anyway
            self._slog.debug("%s: error while closing the socket", self._what, exc_info=True)
