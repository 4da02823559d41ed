"""MQTT output of one station, in three layers:

- ``messages.py`` (pure): telemetry aggregation and the messages of records, events, state,
  alarm and replies — (topic, payload, QoS, retain), built from the topic tree in ``schema.py``;
- ``pump.py`` (transport): one thread with the paho client and the on-disk outbox;
- this module: :class:`MqttOutput`, the station output that joins them, and the command intake.

Threads:
- the station's loop calls ``on_record`` / ``on_event`` / ``on_state``: O(1) work (telemetry is
  aggregated in memory; a message is a JSON encode plus a bounded mailbox append), never I/O;
- commands received on ``cmd/…`` (pump thread) are handed to the station's loop
  (``threadloop.submit_to``, the one thread → loop hand-over); the answer goes out on ``reply``
  (MQTT 5: on the request's Response Topic, with its Correlation Data);
- the broker connection reaches the station as ``station.set_uplink("mqtt", ok)`` through the same
  hand-over (so the PLC sees it in ``StationState.mqtt_ok``);
- the end-of-life alarm is read from the station's alarm store (``gateway/station/alarm_store.py``);
  the output keeps no alarm of its own on disk;
- the site's life history (``mqtt.share_lives``, gateway/outputs/mqtt/sitelives.py): the station's
  own lives (its records folder, read on a worker thread at the start and after each test) go out
  as the retained ``<base>/lives``, again after every reconnect; the other stations' lives of the
  site arrive on the pump thread and are handed, unread, to the intake's worker
  (:class:`gateway.outputs.mqtt.site_intake.LivesIntake`: newest snapshot per station wins, paced,
  saved at most once per few seconds), which checks and keeps them (:class:`SiteLives`) and gives
  them to the station through the hand-over (``station.site_lives``, coalesced). A (re)connected station asks
  the site for its lives (``<prefix>/<site>/lives_request``, non-retained: a clustered broker's
  retained store is per node); the station answers others' requests with its lives, at most once
  per ``sitelives.ANSWER_INTERVAL_S`` (:class:`LivesAnswers`, off the station's loop).
"""
from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from concurrent.futures import Future
from typing import Any

from ...core.command_intake import MAX_NAME_CHARS, intake, rejected_event_data, safe
from ...core.command_rules import CODE, Rejection
from ...core.ports import AlarmStoreView, CommandSink, StationLinks
from ...core.records import Command, CommandReply, Event, EventType, SlotRecord, StationState
from ...core.slotwindow import SlotWindow
from ...offline.history import read_history
from ...plumbing.threadloop import call_soon_on, submit_to
from ...station.alarm_store import AlarmStore
from ..broker.outbox import Outbox
from ..broker.settings import SecretError
from . import messages as M
from . import schema as mqtt_schema
from .messages import SOFTWARE, alarm_fields, telemetry_summary
from .pump import MqttPump
from .settings import MqttSettings
from .site_intake import LivesIntake
from .sitelives import STORE_NAME, LivesAnswers, SiteLives, lives_topic, snapshot

__all__ = ["MqttOutput", "MqttSettings", "SecretError", "SOFTWARE", "STATE_REFRESH_S",
           "alarm_fields"]

log = logging.getLogger("hookwatch.mqtt")

STATE_REFRESH_S = 10.0


class MqttOutput:
    """Station output (:class:`gateway.core.ports.Output`) publishing the station over MQTT."""

    def __init__(self, settings: MqttSettings, station: StationLinks | None = None,
                 alarms: AlarmStore | None = None) -> None:
        self.s = settings
        self.station = station
        #: where commands go (a CommandSource bound to its CommandSink: the station)
        self.sink: CommandSink | None = station
        self.loop: asyncio.AbstractEventLoop | None = None
        #: the one alarm store: the station's; an output on its own keeps one in memory and feeds it
        self._own_alarms: AlarmStore | None = None
        self.alarms: AlarmStoreView
        if alarms is not None:
            self.alarms = alarms
        elif station is not None:
            self.alarms = station.alarms
        else:
            self.alarms = self._own_alarms = AlarmStore(None, settings.station_id)
        #: the site's lives (None: `mqtt.share_lives` off, or no records folder)
        self.site: SiteLives | None = None
        if settings.share_lives and settings.records_dir:
            self.site = SiteLives(os.path.join(settings.records_dir, STORE_NAME), settings.station_id)
        self._lives_msg: M.Message | None = None
        self._site_lock = threading.Lock()
        self._site_jobs: set[asyncio.Future[None]] = set()
        self.pump = MqttPump(settings, on_link=self._link_changed, on_command=self._command,
                             on_lives=self._lives if self.site is not None else None)
        #: the answers to the site's lives requests (None: not shared)
        self.answers: LivesAnswers | None = None
        #: the site's lives taken off the pump thread and the station's loop (None: not shared)
        self.intake: LivesIntake | None = None
        if self.site is not None:
            self.answers = LivesAnswers(settings.station_id, self._put_lives, self.pump.counters)
            self.intake = LivesIntake(self.site, self._give_station, self.pump.counters)
        self._base = settings.base_topic
        self._lives_request = mqtt_schema.lives_request_topic(self._base)
        # station-loop state
        self._test_id: str | None = None
        self._agg: SlotWindow | None = None
        self._last_state: StationState | None = None
        self._last_state_key: tuple[Any, ...] | None = None
        self._last_state_pub = 0.0

    source = "mqtt"

    def bind(self, sink: CommandSink) -> None:
        """Send the commands received on ``cmd/…`` to ``sink`` (gateway.core.ports.CommandSource)."""
        self.sink = sink

    @property
    def outbox(self) -> Outbox:
        return self.pump.outbox

    @property
    def connected(self) -> bool:
        return self.pump.connected

    @property
    def counters(self) -> dict[str, int]:
        return self.pump.counters

    # ================================================================ output (station loop)
    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        if self.station is not None:
            set_disk = self.station.set_disk
            # the outbox reports from the pump thread: handed over to the station's loop
            loop = self.loop

            def on_disk_state(ok: bool, info: dict[str, Any]) -> None:
                call_soon_on(loop, set_disk, "outbox", ok, info)
            self.outbox.on_disk_state = on_disk_state
            if not self.outbox.disk_ok:
                set_disk("outbox", False, {"reason": "the outbox cannot be written"})
        if self.intake is not None:
            self.intake.start()     # reads the local copy of the site's lives first
        self.pump.start()
        if self.site is not None:
            self._share()

    async def stop(self) -> None:
        if self._site_jobs:         # the lives of a test that ended at the stop go out with the rest
            await asyncio.wait(list(self._site_jobs), timeout=15.0)
        self._flush_telemetry(time.monotonic())
        self.pump.request_stop()
        if self.pump.started:
            await asyncio.get_running_loop().run_in_executor(
                None, self.pump.join, self.s.drain_on_stop_s + 5.0)
        else:
            self.pump.join(0)
        if self.intake is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.intake.close)
        if self.site is not None:
            self.site.close()
        if self.answers is not None:
            self.answers.close()

    def on_record(self, rec: SlotRecord) -> None:
        agg = self._agg
        now = time.monotonic()
        if agg is None:
            agg = self._agg = SlotWindow(now)
        agg.add(rec)
        if now - agg.t0 >= self.s.telemetry_interval_s:
            self._flush_telemetry(now)

    def _flush_telemetry(self, now: float) -> None:
        agg = self._agg
        if agg is None or agg.n == 0:
            return
        self._agg = SlotWindow(now)
        st = self._last_state           # §5a: the headroom of the last window, as in `state`
        summary = telemetry_summary(agg, now, self._test_id, st.headroom if st is not None else None,
                                    st.t_cross if st is not None else None)
        summary.update(mqtt_schema.forecast_fields(st if self._test_id else None))
        self.pump.put(M.telemetry_message(self._base, self.s.station_id, time.time(), summary))

    def on_event(self, ev: Event) -> None:
        if ev.type == EventType.TEST_STARTED:
            self._test_id = ev.test_id
        if self._own_alarms is not None:
            self._own_alarms.on_event(ev)
        for msg in M.event_messages(self._base, ev, self._last_state, self.alarms.record,
                                    self.alarms.warning):
            self.pump.put(msg)
        if ev.type == EventType.TEST_ENDED and ev.test_id is not None and ev.test_id == self._test_id:
            self._test_id = None
        if ev.type == EventType.TEST_ENDED and self.site is not None:
            self._share(ended=ev.test_id)

    def on_state(self, st: StationState) -> None:
        self._last_state = st
        key = M.state_key(st)
        now = time.monotonic()
        if key == self._last_state_key and now - self._last_state_pub < STATE_REFRESH_S:
            return
        self._last_state_key = key
        self._last_state_pub = now
        self.pump.put(M.state_message(self._base, time.time(), st))

    # ================================================================ pump thread → station
    def _link_changed(self, ok: bool) -> None:
        """The broker link changed (pump thread): tell the station on its own loop; connected, the
        station's lives go out again (a broker may have lost its retained messages)."""
        if self.station is not None:
            call_soon_on(self.loop, self.station.set_uplink, "mqtt", ok)
        if ok:
            self._put_lives()

    # ================================================================ the site's lives
    def _share(self, ended: str | None = None) -> None:
        """Read the station's own lives on a
        worker thread, and publish them; never on the station's loop."""
        loop = self.loop
        if loop is None:
            return
        fut = loop.run_in_executor(None, self._share_now, ended)
        self._site_jobs.add(fut)

        def done(f: asyncio.Future[None]) -> None:
            self._site_jobs.discard(f)
            if not f.cancelled() and f.exception() is not None:
                log.warning("%s: the station's lives could not be shared: %s", self.s.station_id,
                            f.exception())
        fut.add_done_callback(done)

    def _share_now(self, ended: str | None) -> None:
        site, folder = self.site, self.s.records_dir
        if site is None or folder is None:
            return
        with self._site_lock:
            own = read_history(folder)
            for _ in range(40):             # the ended test's result.json follows its event
                if ended is None or any(t.test_id == ended for t in own):
                    break
                time.sleep(0.25)
                own = read_history(folder)
            doc = snapshot(self.s.station_id, own, mqtt_schema.iso_ms(time.time()))
            def payload(seq: int, d: dict[str, Any] = doc) -> dict[str, Any]:
                return {**d, "seq": seq}
            msg = M.Message("lives", lives_topic(self._base), payload, qos=1, retain=True)
            self._lives_msg = msg
            self._put_lives()

    def _put_lives(self) -> bool:
        """Publish the station's lives (again); False: not read yet (any thread)."""
        msg = self._lives_msg
        if msg is None:
            return False
        self.pump.put(msg)
        if self.answers is not None:
            self.answers.published()
        return True

    def _lives(self, topic: str, payload: bytes) -> None:
        """A station of the site published its lives, or a gateway asks for them (pump thread)."""
        if topic == self._lives_request:
            if self.answers is not None:
                self.answers.request(payload)
            return
        if self.intake is not None:
            self.intake.put(topic, payload)     # O(1): checked and merged on the intake's worker

    def _give_station(self, tests: tuple[Any, ...]) -> None:
        """The site's lives changed (the intake's worker, at most once per GIVE_INTERVAL_S)."""
        if self.station is not None:
            call_soon_on(self.loop, self.station.site_lives, tests)

    def _command(self, name: str, raw: bytes, response: tuple[str, bytes | None] | None = None,
                 source: str = mqtt_schema.COMMAND_SOURCE) -> None:
        """A message on ``cmd/<name>`` or ``cmd/<door>/<name>`` (pump thread): parse, check, hand to
        the station's loop; ``source`` names the door (``mqtt``, ``mqtt:<door>``: its own command
        budget at the station); the answer goes to ``response`` (MQTT 5 Response Topic,
        Correlation Data) or to ``reply``."""
        cmd = intake(name, raw, source)   # the one bounded intake: size, depth, types, strings
        if isinstance(cmd, Rejection):
            self._reply(safe(name, MAX_NAME_CHARS), cmd.request_id, cmd, response, source)
            self._intake_rejected(name, cmd, source)
            return
        sink = self.sink
        fut = submit_to(self.loop, sink.submit(cmd)) if sink is not None else None
        if fut is None:
            self._reply(name, cmd.request_id, Rejection(False, "the station is not running", cmd.request_id,
                                                        CODE["NO_STATION"]), response, source)
            return

        acc: Command = cmd

        def done(f: Future[CommandReply]) -> None:
            try:
                r = f.result()
            except Exception as e:  # the station failed to carry it out
                r = Rejection(False, f"the station failed: {type(e).__name__}: {e}", acc.request_id,
                              CODE["NO_STATION"])
            self._reply(acc.kind.value, acc.request_id, r, response, acc.source)

        fut.add_done_callback(done)

    def _intake_rejected(self, name: str, rej: Rejection, source: str) -> None:
        """A request refused before it became a command (code 9) is a refusal of the station like
        every other: bounded ``command_rejected`` events, once per kind per window with a count
        (gateway/station/command_desk.py, RefusalGate)."""
        if self.station is None:
            return
        call_soon_on(self.loop, self.station.refused, rejected_event_data(name, rej, source))

    def _reply(self, command: str, request_id: str | None, r: CommandReply,
               response: tuple[str, bytes | None] | None = None,
               source: str = mqtt_schema.COMMAND_SOURCE) -> None:
        self.pump.put(M.reply_message(self._base, self.s.station_id, time.time(), command, request_id, r,
                                      response, source))
