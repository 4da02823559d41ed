"""The console's fleet routes: the page, the fleet cards, the planner's due list (with the site's
other boxes on ``?site=1``).

    GET  /                                  the page (static, shipped in ``static/``)
    GET  /api/fleet[?site=1]                fleet cards (site=1: with the site's other boxes)
    GET  /api/due[?line=&area=&site=1]      the planner's due list (every station, soonest first;
                                            site=1: the stations of the site's other boxes too)
    GET  /api/due.csv[?line=&area=&site=1]  the same as CSV (cells defused against formulas)
    GET  /api/boxes                         the site's boxes by their config reports (the Boxes page)
    GET  /api/values                        the station values the page shows, with their labels
                                            (the catalog's rows: gateway/core/catalog.py)
"""
from __future__ import annotations

import os
import time
from typing import Any

from aiohttp import web

from ...plumbing import safeout
from .common import FILTER_MAX, STATIC, HttpError, err, json_reply
from .context import ConsoleContext
from .feed import DUE_COLUMNS, due_list, values_json


class FleetRoutes:
    def __init__(self, ctx: ConsoleContext):
        self.ctx = ctx

    def add_to(self, r: web.UrlDispatcher) -> None:
        r.add_get("/", self.h_index)
        r.add_get("/api/fleet", self.h_fleet)
        r.add_get("/api/due", self.h_due)
        r.add_get("/api/due.csv", self.h_due_csv)
        r.add_get("/api/boxes", self.h_boxes)
        r.add_get("/api/values", self.h_values)

    async def h_index(self, request):
        return web.FileResponse(os.path.join(STATIC, "index.html"))

    def _with_site(self, request) -> bool:
        return request.query.get("site") in ("1", "true") and self.ctx.site is not None

    def _cards(self, request) -> list[dict[str, Any]]:
        """This box's fleet cards (``remote`` false), and with ``?site=1`` the site view's
        cards of the site's other boxes (``remote`` true: read-only)."""
        cards = [{**f.summary(), "remote": False} for f in self.ctx.feeds.values()]
        if self._with_site(request):
            assert self.ctx.site is not None
            cards.extend(self.ctx.site.cards())
        return cards

    def _site_info(self) -> dict[str, Any]:
        site = self.ctx.site
        return {"enabled": site is not None, "fed": site is not None and site.filters is not None,
                "stations": site.stations() if site is not None else 0,
                "refused": site.counters["refused"] if site is not None else 0}

    async def h_values(self, request):
        """The catalog's rows the console shows: name (the key of a card's ``values``), label,
        unit, type (docs/console.md)."""
        return json_reply({"values": values_json()})

    async def h_boxes(self, request):
        """Every box of the site as its retained config report says (docs/console.md, Boxes)."""
        site = self.ctx.site
        return json_reply({"time": time.time(), "boxes": site.boxes.rows() if site is not None else [],
                           "site": self._site_info()})

    async def h_fleet(self, request):
        ctx = self.ctx
        return json_reply({"stations": self._cards(request), "site": self._site_info(),
                           "time": time.time(),
                           "console": {"cpu_s": ctx.cpu_s, "dropped_clients": ctx.dropped_clients,
                                       "live_clients": sum(len(c) for c in ctx.clients.values())}})

    def _due_filters(self, request) -> tuple[str | None, str | None]:
        out = []
        for name in ("line", "area"):
            v = request.query.get(name)
            if v is not None and (len(v) > FILTER_MAX or not v.isprintable()):
                raise HttpError(400, f"{name}: at most {FILTER_MAX} printable characters")
            out.append(v if v else None)
        return out[0], out[1]

    def _due(self, request) -> list[dict[str, Any]]:
        line, area = self._due_filters(request)
        for f in self.ctx.feeds.values():
            f.drain()
        return due_list(self._cards(request), line, area)

    async def h_due(self, request):
        """The planner's due list: every station, the soonest due first (docs/console.md)."""
        try:
            rows = self._due(request)
        except HttpError as e:
            return err(e.status, e.reason)
        cards = self._cards(request)
        return json_reply({"time": time.time(), "columns": list(DUE_COLUMNS), "stations": rows,
                           "lines": sorted({c["line"] for c in cards if c.get("line")}),
                           "areas": sorted({c["area"] for c in cards if c.get("area")}),
                           "site": self._site_info()})

    async def h_due_csv(self, request):
        """The due list as CSV (RFC 4180; every cell defused against formulas in any locale:
        gateway.plumbing.safeout.csv_text)."""
        try:
            rows = self._due(request)
        except HttpError as e:
            return err(e.status, e.reason)
        refused = self.ctx.file_reads(request)
        if refused is not None:
            return refused
        text = safeout.csv_text([DUE_COLUMNS, *([r.get(c) for c in DUE_COLUMNS] for r in rows)])
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        return web.Response(body=text.encode("utf-8"), headers={
            "Content-Type": "text/csv; charset=utf-8",
            "Content-Disposition": f'attachment; filename="due-{stamp}.csv"'})
