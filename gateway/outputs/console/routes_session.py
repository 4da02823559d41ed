"""The console's session routes: who is logged in, login (lockout, hashing budget), logout.

    GET  /api/session                       who is logged in (+ CSRF token)
    POST /api/login  {user, password}       → session cookie + CSRF token
    POST /api/logout
"""
from __future__ import annotations

import logging
import math

from aiohttp import web

from . import auth
from .common import COOKIE, HttpError, err, json_reply
from .context import ConsoleContext

log = logging.getLogger("hookwatch.console")


class SessionRoutes:
    def __init__(self, ctx: ConsoleContext):
        self.ctx = ctx

    def add_to(self, r: web.UrlDispatcher) -> None:
        r.add_get("/api/session", self.h_session)
        r.add_post("/api/login", self.h_login)
        r.add_post("/api/logout", self.h_logout)

    async def h_session(self, request):
        s = self.ctx.session(request)
        if s is None:
            return json_reply({"user": None, "read": self.ctx.may_read(request)})
        return json_reply({"user": s.user, "csrf": s.csrf, "read": True})

    async def h_login(self, request):
        ctx = self.ctx
        try:
            data = await ctx.json_body(request)
        except HttpError as e:
            return err(e.status, e.reason)
        user, pw = data.get("user"), data.get("password")
        if not isinstance(user, str) or not isinstance(pw, str) or not auth.USER_RE.match(user) \
                or len(pw) > auth.PASSWORD_MAX:
            return err(400, "user and password required")
        remote = request.remote or "?"
        # checked and counted in one step (no await in between): a burst gets no more tries
        pair, addr = f"ua:{remote} {user}", f"a:{remote}"
        left = ctx.lockout.attempt({pair: ctx.settings.lockout_attempts,
                                    addr: ctx.settings.login_failures_per_address})
        if left > 0:
            ctx.refusals.warn("locked out " + remote, "login of %r from %s refused: locked out "
                              "(%.0f s left)", user, remote, left)
            return err(429, f"too many failed logins; try again in {left:.0f} s",
                       headers={"Retry-After": str(int(left) + 1)})
        # the hashing budget (after the lockout, which costs no hash): none beyond it; checked
        # here and taken below, with no await in between. Not a try: the attempt is taken back
        wait = ctx.hasher.wait(user)
        if wait > 0:
            ctx.lockout.forgive(one=(pair, addr))
            ctx.hasher.refused += 1
            ctx.refusals.warn("hash budget", "login of %r from %s refused: over the password-"
                              "hashing budget (%d refused so far)", user, remote, ctx.hasher.refused)
            return err(429, "too many logins right now; try again shortly",
                       headers={"Retry-After": str(max(1, math.ceil(wait)))})
        try:
            users = auth.load_users(ctx.settings.users_file)
        except auth.UsersError as e:
            ctx.lockout.forgive(one=(pair, addr))
            log.error("console: %s", e)
            return err(500, "users file unreadable; see the gateway log")
        # an unknown user name: the same work as a real check, so the answer time does not tell
        # which users exist; one hash of the budget either way
        ctx.hasher.take(user)
        ok = await ctx.hasher.verify(pw, users.get(user))
        if not ok:
            ctx.refusals.warn("failed login " + remote, "failed login of %r from %s", user, remote)
            return err(401, "wrong user or password")
        ctx.lockout.forgive(clear=(pair,), one=(addr,))
        ctx.sessions.drop(request.cookies.get(COOKIE))
        token, s = ctx.sessions.create(user, remote)
        log.info("console: %s logged in from %s", user, remote)
        resp = json_reply({"user": user, "csrf": s.csrf})
        resp.set_cookie(COOKIE, token, httponly=True, samesite="Strict", path="/",
                        secure=bool(ctx.settings.cert_file), max_age=int(ctx.settings.session_ttl_s))
        return resp

    async def h_logout(self, request):
        self.ctx.sessions.drop(request.cookies.get(COOKIE))
        resp = json_reply({"user": None})
        resp.del_cookie(COOKIE, path="/")
        return resp
