"""The one definition of an MQTT broker connection, shared by both northbound MQTT clients.

The JSON tree's pump (:mod:`..mqtt.pump`, a station's ``mqtt:`` section) and the Sparkplug edge node
(:mod:`..sparkplug.runtime`, its ``sparkplug:`` section) connect the same way: host, port, client ID,
keep-alive, user and password (never inline: an environment variable or a file), TLS with an
optional client certificate, the reconnect back-off, and the server list (``servers``: the nodes of
a clustered broker, or Sparkplug's server set; one ``host:port`` when not configured). Their
settings derive from :class:`BrokerSettings`; :func:`broker_kwargs` reads those keys from either
configuration section (both derive from ``gateway.config.sections.BrokerConfig``), so the keys a user
writes are the same in both sections and mean the same.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ...config.sections import parse_server

__all__ = ["SecretError", "BrokerSettings", "broker_kwargs"]


class SecretError(Exception):
    """The broker password cannot be read (its environment variable or file is missing)."""


@dataclass(kw_only=True)
class BrokerSettings:
    """Where and how to connect to the MQTT broker."""
    host: str = "127.0.0.1"
    port: int = 1883
    client_id: str | None = None
    keepalive_s: int = 30
    username: str | None = None
    password_env: str | None = None
    password_file: str | None = None
    tls_enabled: bool = False
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    poll_s: float = 0.02              # network loop wait when connected (bounds the latency)
    reconnect_min_s: float = 1.0
    reconnect_max_s: float = 10.0
    #: the brokers to connect to, in order of preference (empty: ``[(host, port)]``)
    servers: list[tuple[str, int]] = field(default_factory=list)

    #: the configuration section the messages name (`mqtt.password_env: …`)
    section: ClassVar[str] = "mqtt"

    def __post_init__(self) -> None:
        if not self.servers:
            self.servers = [(self.host, int(self.port))]
        self.host, self.port = self.servers[0]

    def password(self) -> str | None:
        """The broker password from its environment variable or file (None: no password)."""
        if self.password_env:
            v = os.environ.get(self.password_env)
            if v is None:
                raise SecretError(f"{self.section}.password_env: environment variable {self.password_env} "
                                  "is not set")
            return v
        if self.password_file:
            try:
                with open(self.password_file, encoding="utf-8") as f:
                    return f.read().rstrip("\r\n")
            except OSError as e:
                raise SecretError(f"{self.section}.password_file {self.password_file!r}: {e.strerror}") from None
        return None

    def apply(self, client: Any) -> None:
        """Credentials and TLS on a paho client before CONNECT (SecretError, OSError or ValueError
        when the password or a certificate cannot be read)."""
        if self.username:
            client.username_pw_set(self.username, self.password())
        if self.tls_enabled:
            client.tls_set(ca_certs=self.ca_file, certfile=self.cert_file, keyfile=self.key_file)


def broker_kwargs(section: Any) -> dict[str, Any]:
    """The :class:`BrokerSettings` fields from a configuration section (``mqtt:`` or ``sparkplug:``)."""
    tls = section.tls
    servers: list[tuple[str, int]] = []
    for item in getattr(section, "servers", None) or ():
        hp = parse_server(item, int(section.port))
        if hp is not None and hp not in servers:       # the loader refused malformed ones
            servers.append(hp)
    return dict(servers=servers, host=section.host, port=int(section.port), client_id=section.client_id,
                keepalive_s=int(section.keepalive_s), username=section.username,
                password_env=section.password_env, password_file=getattr(section, "password_file", None),
                tls_enabled=bool(tls.enabled), ca_file=tls.ca_file, cert_file=tls.cert_file,
                key_file=tls.key_file)
