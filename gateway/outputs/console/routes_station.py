"""The console's station routes: one station live and its history.

    GET  /api/station/<id>                  snapshot: decimated series from slot 0, markers, events
    GET  /api/station/<id>/stream           Server-Sent Events: snapshot, then changes (~4/s)
    POST /api/station/<id>/command {command, ...}   start | stop | ack | setpoint | hook_replaced |
                                            shelve | unshelve | out_of_service | in_service
    GET  /api/station/<id>/tests            recorded tests
    GET  /api/station/<id>/hooks            the successive hooks and their lives (hooks.jsonl)
    GET  /api/station/<id>/journal          the ISA-18.2 alarm journal (every transition, who, when)
    GET  /api/station/<id>/tests/<test>/fig7.png        the report's Fig. 7 of a test
    GET  /api/station/<id>/tests/<test>/files/<name>    log.csv.gz, log.meta.yaml, events.jsonl, result.json
"""
from __future__ import annotations

import asyncio
import logging
import math
import os
import socket

from aiohttp import web

from ...core.command_intake import intake, rejected_event_data
from ...core.command_rules import CODE, Rejection, reply_code
from ...core.records import CommandKind
from ...plumbing import safeout
from ...plumbing.ratelog import RateLog
from ...plumbing.threadloop import call_soon_on, submit_to
from . import auth
from .common import MAX_BODY, MAX_CLIENTS, SEND_BUFFER, WRITE_TIMEOUT_S, HttpError, cut, err, json_reply
from .context import Client, ConsoleContext
from .feed import StationFeed, hook_history, journal_from_disk
from .guard import Busy
from .recorded import DOWNLOADS, find_png, list_tests, report_process

log = logging.getLogger("hookwatch.console")


class StationRoutes:
    def __init__(self, ctx: ConsoleContext):
        self.ctx = ctx

    def add_to(self, r: web.UrlDispatcher) -> None:
        r.add_get("/api/station/{sid}", self.h_station)
        r.add_get("/api/station/{sid}/stream", self.h_stream)
        r.add_post("/api/station/{sid}/command", self.h_command)
        r.add_get("/api/station/{sid}/tests", self.h_tests)
        r.add_get("/api/station/{sid}/hooks", self.h_hooks)
        r.add_get("/api/station/{sid}/journal", self.h_journal)
        r.add_get("/api/station/{sid}/tests/{tid}/fig7.png", self.h_fig7)
        r.add_get("/api/station/{sid}/tests/{tid}/files/{name}", self.h_file)

    # ----------------------------------------------------------------- live
    async def h_station(self, request):
        try:
            f = self.ctx.feed(request)
        except HttpError as e:
            return err(e.status, e.reason)
        return json_reply(f.snapshot())

    async def h_stream(self, request):
        ctx = self.ctx
        try:
            f = ctx.feed(request)
        except HttpError as e:
            return err(e.status, e.reason)
        # connect churn is bounded per address and in all: each connect costs a snapshot
        wait = ctx.stream_rate.take(request.remote or "?") or ctx.stream_rate_all.take()
        if wait > 0:
            return ctx.refuse(request, 429, "stream rate", "too many live-stream connects; "
                              f"try again in {math.ceil(wait)} s",
                              headers={"Retry-After": str(math.ceil(wait))})
        if sum(len(c) for c in ctx.clients.values()) >= MAX_CLIENTS:
            return err(503, f"too many live clients (at most {MAX_CLIENTS})")
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-store", "X-Accel-Buffering": "no"})
        await resp.prepare(request)
        _small_send_buffer(request.transport)
        c = Client()
        f.drain()
        first = ("data: " + safeout.dumps(f.snapshot()) + "\n\n").encode()
        ctx.clients[f.name].add(c)
        try:
            await asyncio.wait_for(resp.write(first), WRITE_TIMEOUT_S)
            while True:
                data = await c.q.get()
                if data is None:
                    break
                await asyncio.wait_for(resp.write(data), WRITE_TIMEOUT_S)
        except TimeoutError:
            ctx.drop(f.name, c, "write timed out")
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            ctx.clients[f.name].discard(c)
            if c.dropped and request.transport is not None:
                request.transport.close()
        return resp

    # ----------------------------------------------------------------- commands
    #: refused commands: one log line per kind per minute, with the count (gateway/plumbing/ratelog.py)
    refusal_log = RateLog(log)

    async def h_command(self, request):
        """A command from the console: the body through the one bounded intake
        (gateway/core/command_intake.py: size, depth, strict types, bounded strings), then the
        station's validation through its refusal gate (bounded ``command_rejected`` events)."""
        try:
            f = self.ctx.feed(request)
            body = await request.read()
        except HttpError as e:
            return err(e.status, e.reason)
        except web.HTTPRequestEntityTooLarge:
            return err(413, f"request body larger than {MAX_BODY} bytes")
        s = self.ctx.session(request)
        if s is None:
            return err(401, "log in first")
        source = f"console:{s.user}"
        cmd = intake(None, body, source)
        st, loop = f.station, f.loop
        if isinstance(cmd, Rejection):
            if st is not None and loop is not None:
                name = cmd.reason.split(":", 1)[0]
                call_soon_on(loop, st.refused, rejected_event_data(name, cmd, source))
            return self._reply(f, s, "command", cmd, status=400)
        kind = cmd.kind.value
        hook = cmd.kind == CommandKind.HOOK_REPLACED
        if st is None or loop is None:
            return self._reply(f, s, kind, Rejection(False, f"station {f.name} is not running", None,
                                                     CODE["NO_STATION"]))
        try:
            fut = submit_to(loop, st.submit(cmd))   # the one hand-over (gateway/plumbing/threadloop.py)
            if fut is None:
                raise RuntimeError("its loop is closed")
            reply = await asyncio.wait_for(asyncio.wrap_future(fut), 5.0)
        except (TimeoutError, RuntimeError) as e:
            reply = Rejection(False, f"the station did not answer ({type(e).__name__})", None,
                              CODE["NO_STATION"])
        if hook and reply.ok:
            log.info("console: %s: hook replaced by %s (new hook %s)", f.name, s.user,
                     cut(str(cmd.args.get("sample_id", "(derived)"))))
        return self._reply(f, s, kind, reply)

    def _reply(self, f: StationFeed, s: auth.Session, kind: str, reply, status: int = 409) -> web.Response:
        """The answer: 200 accepted; 409 refused by the station; 400 refused by the intake (the
        request itself is malformed); ``reason`` and ``code`` as over MQTT and the PLC."""
        code = reply_code(reply)
        if reply.ok:
            log.info("console: command %s on %s by %s: accepted", kind, f.name, s.user)
        else:
            self.refusal_log.warning(("command", kind, int(code)), "console: command %s on %s by %s: refused: %s",
                                     kind, f.name, s.user, reply.reason)
        return json_reply({"ok": bool(reply.ok), "reason": reply.reason, "code": code},
                          status=200 if reply.ok else status)

    # ----------------------------------------------------------------- history
    async def h_tests(self, request):
        try:
            d = self.ctx.station_dir(request)
        except HttpError as e:
            return err(e.status, e.reason)
        tests = await asyncio.get_running_loop().run_in_executor(None, list_tests, d)
        return json_reply({"station": request.match_info["sid"], "tests": tests})

    async def h_hooks(self, request):
        """The station's successive hooks with their lives, newest first (hooks.jsonl, bounded)."""
        try:
            d = self.ctx.station_dir(request)
        except HttpError as e:
            return err(e.status, e.reason)
        refused = self.ctx.file_reads(request)
        if refused is not None:
            return refused
        hooks = await asyncio.get_running_loop().run_in_executor(None, hook_history, d)
        return json_reply({"station": request.match_info["sid"], "hooks": hooks})

    async def h_journal(self, request):
        """The alarm journal of a station: every ISA-18.2 transition with who and when, oldest
        first (what the recorded tests hold, then what the console saw live; bounded)."""
        try:
            f = self.ctx.feed(request)
        except HttpError as e:
            return err(e.status, e.reason)
        f.drain()
        if not f.journal_seeded:
            f.journal_seeded = True
            try:
                old = await asyncio.get_running_loop().run_in_executor(
                    None, journal_from_disk, self.ctx.records[f.name])
            except OSError as e:
                log.warning("console: %s: recorded alarm journal unreadable: %s", f.name, e)
                old = []
            f.drain()
            f.seed_journal(old)
        return json_reply({"station": f.name, "journal": list(f.journal)})

    async def h_file(self, request):
        try:
            td = self.ctx.test_dir(request)
        except HttpError as e:
            return err(e.status, e.reason)
        name = request.match_info["name"]
        if name not in DOWNLOADS or not os.path.isfile(os.path.join(td, name)):
            return err(404, f"no file {name!r}")
        tid = os.path.basename(td)
        return web.FileResponse(os.path.join(td, name), headers={
            "Content-Type": DOWNLOADS[name],
            "Content-Disposition": f'attachment; filename="{tid}-{name}"'})

    async def _fig7_job(self, td: str, out: str) -> tuple[str | None, str]:
        png = find_png(out)
        if png is not None:
            return png, ""
        rc, err_text = await report_process([td, "--out", out], 120)
        png = find_png(out)
        return png, ("timeout" if rc is None else err_text)

    async def h_fig7(self, request):
        try:
            td = self.ctx.test_dir(request)
        except HttpError as e:
            return err(e.status, e.reason)
        if not os.path.isfile(os.path.join(td, "result.json")):
            return err(409, "the test is still running; its figure comes when it has ended")
        key = request.match_info["sid"] + "__" + os.path.basename(td)
        out = os.path.join(self.ctx.cache, key)
        png = find_png(out)
        if png is None:
            # the report runs as its own process at low priority (no figure delays a slot), at
            # most console.report_jobs at once; requests for the same figure share its process
            try:
                png, why = await self.ctx.reports.run("fig7:" + key, lambda: self._fig7_job(td, out))
            except Busy as e:
                return self.ctx.refuse(request, 503, "report queue", "too many reports being made; "
                                       f"try again in {e.retry_after} s",
                                       headers={"Retry-After": str(e.retry_after)})
            if png is None:
                return err(504 if why == "timeout" else 500, "the figure took too long"
                           if why == "timeout" else "no figure: " + why)
        return web.FileResponse(png, headers={"Content-Type": "image/png"})


def _small_send_buffer(transport) -> None:
    """Bound what the kernel and the transport hold for one live client: a client that stops
    reading fills them within seconds, its queue fills, and it is dropped."""
    if transport is None:
        return
    sock = transport.get_extra_info("socket")
    try:
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        transport.set_write_buffer_limits(high=SEND_BUFFER)
    except (OSError, AttributeError, NotImplementedError):
        pass
