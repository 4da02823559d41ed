"""The box's configuration report on MQTT: retained, QoS 1, on
``<prefix>/<site>/box/<box>/config`` (:func:`gateway.outputs.mqtt.schema.box_config_topic`),
with a Will that says ``online: false``; on its own session of the one paho session engine
(:class:`gateway.outputs.broker.paho_session.PahoSession`), on its own thread. Its content is
:func:`gateway.config.site.boxreport.build_report`; the box's :class:`.boxagent.BoxAgent` hands
each new report over (a mailbox of one: the latest wins).
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

import paho.mqtt.client as paho

from ..config.site.boxreport import REPORT_SCHEMA
from ..outputs.broker.paho_session import PahoSession
from ..outputs.broker.settings import BrokerSettings, SecretError
from ..outputs.mqtt.schema import box_config_topic, encode, iso_ms
from ..plumbing.threadloop import Mailbox

__all__ = ["ReportPublisher"]

log = logging.getLogger("hookwatch.config")


class ReportPublisher(PahoSession):
    """The retained report on its own MQTT session (its thread): published on every connect and
    whenever :meth:`update` brings a new one; the Will says ``online: false``; :meth:`stop`
    publishes that itself. The latest report wins (a mailbox of one)."""

    def __init__(self, settings: BrokerSettings, prefix: str, site: str, box: str) -> None:
        super().__init__(settings, f"config report of box {box}", log)
        self.topic = box_config_topic(prefix, site, box)
        self.box, self.site = box, site
        self._box: Mailbox[dict[str, Any]] = Mailbox(1)
        self._latest: dict[str, Any] | None = None
        self._stop = threading.Event()
        self._connected = False
        self.published = 0
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"config-report-{box}")

    def start(self) -> None:
        self._thread.start()

    def update(self, report: dict[str, Any]) -> None:
        self._box.put_nowait(report)

    def _offline(self) -> bytes:
        return encode({"schema": REPORT_SCHEMA, "box": self.box, "site": self.site, "online": False,
                       "time": iso_ms(time.time())})

    def _connect(self) -> paho.Client | None:
        try:
            c = self._paho_client(self.client_id_for(f"hookwatch-box-{self.box}"))
        except (SecretError, OSError, ValueError) as e:
            log.error("config report: broker credentials or TLS: %s; retrying", e)
            self._schedule_retry()
            return None
        c.will_set(self.topic, self._offline(), qos=1, retain=True)
        c.on_connect = self._on_connect
        if not self._open(c):
            return None
        return c

    def _on_connect(self, client: paho.Client, userdata: Any, flags: Any, reason_code: Any,
                    properties: Any) -> None:
        if reason_code.is_failure:
            log.error("config report: broker refused the connection: %s", reason_code)
            return
        self._session_up()
        self._connected = True
        if self._latest is not None:
            client.publish(self.topic, encode(self._latest), qos=1, retain=True)
            self.published += 1

    def _run(self) -> None:
        c: paho.Client | None = None
        while not self._stop.is_set():
            for rep in self._box.drain():
                self._latest = rep
                if c is not None and self._connected:
                    c.publish(self.topic, encode(rep), qos=1, retain=True)
                    self.published += 1
            if c is None:
                if self._attempt_wait() > 0:
                    self._box.wait(min(0.5, self._attempt_wait()))
                    continue
                c = self._connect()
                continue
            if c.loop(timeout=0.2) != paho.MQTT_ERR_SUCCESS:
                log.warning("config report: connection to the broker lost; reconnecting")
                self._drop_socket(c)
                c, self._connected = None, False
                self._schedule_retry()
        if c is not None:
            if self._connected:
                info = c.publish(self.topic, self._offline(), qos=1, retain=True)
                t_end = time.monotonic() + 2.0
                while not info.is_published() and time.monotonic() < t_end:
                    if c.loop(timeout=0.05) != paho.MQTT_ERR_SUCCESS:
                        break
            try:
                c.disconnect()
            except Exception:  # noqa: BLE001 - closing a broken socket
                pass

    def stop(self) -> None:
        self._stop.set()
        self._box.wake()
        if self._thread.is_alive():
            self._thread.join(5)
