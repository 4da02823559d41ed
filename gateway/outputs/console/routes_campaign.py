"""The console's campaign routes: the report (Tables 3–6, Figs. 7–9) over the ended tests of
chosen stations, made by ``hookwatch report`` as a low-priority child, and its files.

    POST /api/campaign {stations: [...]}    → {ok, tests, url}
    GET  /api/campaign/<cid>/<path>         report.html, report.md, problems.txt, *.csv, figures/*.png
"""
from __future__ import annotations

import asyncio
import logging
import os
import re
import shutil

from aiohttp import web

from .common import HttpError, err, json_reply
from .context import ConsoleContext
from .guard import Busy
from .recorded import list_tests, report_process

log = logging.getLogger("hookwatch.console")

CAMPAIGN_FILE_RE = re.compile(r"^(report\.html|report\.md|problems\.txt|[A-Za-z0-9_.-]+\.csv|"
                              r"figures/[A-Za-z0-9_.-]+\.png)$")
CAMPAIGN_TYPES = {".html": "text/html; charset=utf-8", ".md": "text/markdown; charset=utf-8",
                  ".txt": "text/plain; charset=utf-8", ".csv": "text/csv; charset=utf-8",
                  ".png": "image/png"}


class CampaignRoutes:
    def __init__(self, ctx: ConsoleContext):
        self.ctx = ctx
        self._campaign_busy = False
        self._campaign_n = 0

    def add_to(self, r: web.UrlDispatcher) -> None:
        r.add_post("/api/campaign", self.h_campaign_run)
        r.add_get("/api/campaign/{cid}/{path:.+}", self.h_campaign_file)

    async def h_campaign_run(self, request):
        """Run the report (Tables 3–6, Figs. 7–9) over the ended tests of the chosen stations."""
        try:
            data = await self.ctx.json_body(request)
        except HttpError as e:
            return err(e.status, e.reason)
        stations = data.get("stations")
        if not isinstance(stations, list) or not stations or len(stations) > len(self.ctx.records) \
                or not all(isinstance(x, str) and x in self.ctx.records for x in stations):
            return err(400, f"stations: a list of station names from {sorted(self.ctx.records)}")
        if self._campaign_busy:
            return err(429, "a campaign report is already being made; try again when it is done")
        self._campaign_busy = True
        self._campaign_n += 1
        cid = f"c{self._campaign_n}"
        base = os.path.join(self.ctx.cache, cid)
        loop = asyncio.get_running_loop()
        try:
            n = await loop.run_in_executor(None, _campaign_inputs, self.ctx.records, sorted(set(stations)),
                                           os.path.join(base, "in"))
            if n == 0:
                return err(409, "no ended tests in the chosen stations")
            try:
                rc, err_text = await self.ctx.reports.run("campaign:" + cid, lambda: report_process(
                    [os.path.join(base, "in"), "--out", os.path.join(base, "out")], 600))
            except Busy as e:
                return self.ctx.refuse(request, 503, "report queue", "too many reports being made; "
                                       f"try again in {e.retry_after} s",
                                       headers={"Retry-After": str(e.retry_after)})
            if rc is None:
                return err(504, "the report took longer than 10 minutes")
            if not os.path.isfile(os.path.join(base, "out", "report.html")):
                return err(500, "no report: " + err_text)
        finally:
            self._campaign_busy = False
        log.info("console: campaign report %s over %s (%d tests) by %s", cid, ", ".join(stations), n,
                 getattr(self.ctx.session(request), "user", "?"))
        return json_reply({"ok": True, "tests": n, "url": f"/api/campaign/{cid}/report.html"})

    async def h_campaign_file(self, request):
        cid, path = request.match_info["cid"], request.match_info["path"]
        if not re.match(r"^c[0-9]{1,6}$", cid) or not CAMPAIGN_FILE_RE.match(path):
            return err(404, "no such file")
        f = os.path.join(self.ctx.cache, cid, "out", path)
        if not os.path.isfile(f):
            return err(404, "no such file")
        return web.FileResponse(f, headers={"Content-Type": CAMPAIGN_TYPES[os.path.splitext(f)[1]]})


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _campaign_inputs(records: dict[str, str], stations: list[str], into: str) -> int:
    """Hard-link (or copy) the ended tests of ``stations`` under ``into``; the count of tests."""
    n = 0
    for sid in stations:
        d = records[sid]
        for t in list_tests(d):
            if "result.json" not in t["files"] or "log.csv.gz" not in t["files"]:
                continue      # a running or broken test is not part of a campaign
            src = os.path.join(d, t["test_id"])
            dst = os.path.join(into, sid, t["test_id"])
            os.makedirs(dst, exist_ok=True)
            for name in ("log.csv.gz", "log.meta.yaml", "result.json"):
                if os.path.isfile(os.path.join(src, name)):
                    _link_or_copy(os.path.join(src, name), os.path.join(dst, name))
            n += 1
    return n

