"""Who may give commands from the console: a users file, sessions, CSRF tokens, lockout.

Users file (JSON, written by ``hookwatch user add``; mode 0600)::

    {"version": 1, "users": {"alice": {"kdf": "scrypt", "n": 16384, "r": 8, "p": 1,
                                       "salt": "<32 hex>", "hash": "<64 hex>", "created": "..."}}}

Passwords are hashed with ``hashlib.scrypt`` (RFC 7914) with a fresh 16-byte random salt per user,
N = 2**14, r = 8, p = 1 (16 MiB of memory and about 50 ms of CPU per try on a small box), a 32-byte
key; hashes are compared in constant time. The parameters are stored with each user, so they can
be raised later without invalidating existing users.

Sessions live in memory only (a gateway restart logs everyone out): a random 256-bit token in an
HttpOnly, SameSite=Strict cookie (Secure under TLS), plus a separate random CSRF token that every
POST must echo in the ``X-CSRF-Token`` header.

Lockout (:meth:`Lockout.attempt`): every login attempt is counted *before* its password is
checked, in the same step as the check of the lockout (nothing runs in between), so a burst of
concurrent logins gets no more tries than a sequence. Attempts are counted per (client address,
user name): ``lockout_attempts`` failures within ``lockout_s`` lock that pair for ``lockout_s`` —
a stranger at another address cannot lock the operator out; and per client address for any
user: ``login_failures_per_address`` failures lock the address. A successful login takes its
own count back and clears its pair.

Hashing budget (:class:`Hasher`): every scrypt of a login (a real check, or the same work for an
unknown user name, so the answer time does not tell which users exist) runs off the console's
loop in **one** worker thread at the lowest CPU priority (nice 19), and only within a budget: a
token bucket of hashes per second over all logins (``console.login_hashes_per_s``, burst
``login_hash_burst``) and one per user name (``login_hashes_per_user_per_s``, burst
``login_hash_burst_per_user``). A login beyond the budget is answered 429 with ``Retry-After``
without hashing (counted, one rate-limited log line): a flood of wrong logins from rotating
addresses costs at most that many hashes a second, in one thread the slot loops preempt, and a
flood on some user names leaves the budget of the others.
"""
from __future__ import annotations

import asyncio
import hashlib
import hmac
import json
import os
import re
import secrets
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from ...plumbing.safeout import write_atomic
from .guard import RateBound

SCRYPT_N = 2 ** 14
SCRYPT_R = 8
SCRYPT_P = 1
SCRYPT_DKLEN = 32
SALT_BYTES = 16
#: user names: letters, digits, '.', '_', '-' (1 to 64)
USER_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
PASSWORD_MIN = 8
PASSWORD_MAX = 1024
#: the most sessions kept at once (oldest dropped first)
MAX_SESSIONS = 256
#: the niceness of the thread that hashes passwords (the lowest priority: the slot loops first)
HASH_NICE = 19


class UsersError(Exception):
    pass


def hash_password(password: str, salt: bytes | None = None, n: int = SCRYPT_N, r: int = SCRYPT_R,
                  p: int = SCRYPT_P) -> dict:
    salt = salt if salt is not None else os.urandom(SALT_BYTES)
    dk = hashlib.scrypt(password.encode("utf-8"), salt=salt, n=n, r=r, p=p, dklen=SCRYPT_DKLEN,
                        maxmem=256 * 1024 * 1024)
    return {"kdf": "scrypt", "n": n, "r": r, "p": p, "salt": salt.hex(), "hash": dk.hex()}


def verify_password(password: str, entry: dict) -> bool:
    try:
        if entry.get("kdf") != "scrypt":
            return False
        salt = bytes.fromhex(entry["salt"])
        want = bytes.fromhex(entry["hash"])
        n, r, p = int(entry["n"]), int(entry["r"]), int(entry["p"])
        if not (2 <= n <= 2 ** 20 and 1 <= r <= 32 and 1 <= p <= 16):
            return False
    except (KeyError, ValueError, TypeError):
        return False
    if len(password) > PASSWORD_MAX:
        return False
    got = hashlib.scrypt(password.encode("utf-8"), salt=salt, n=n, r=r, p=p, dklen=len(want),
                         maxmem=256 * 1024 * 1024)
    return hmac.compare_digest(got, want)


def load_users(path: str) -> dict[str, dict]:
    """The users of ``path``; a missing file means no users (every command is refused)."""
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as e:
        raise UsersError(f"{path}: unreadable users file: {e}") from None
    users = data.get("users") if isinstance(data, dict) else None
    if not isinstance(users, dict):
        raise UsersError(f"{path}: not a hookwatch users file (no 'users' mapping)")
    return {k: v for k, v in users.items() if isinstance(k, str) and isinstance(v, dict)}


def add_user(path: str, name: str, password: str) -> bool:
    """Add or replace a user; True when the user was new. Written atomically, mode 0600."""
    if not USER_RE.match(name):
        raise UsersError(f"user name {name!r}: 1 to 64 letters, digits, '.', '_' or '-'")
    if not PASSWORD_MIN <= len(password) <= PASSWORD_MAX:
        raise UsersError(f"password: {PASSWORD_MIN} to {PASSWORD_MAX} characters")
    users = load_users(path)
    new = name not in users
    users[name] = {**hash_password(password), "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    _write(path, users)
    return new


def remove_user(path: str, name: str) -> bool:
    users = load_users(path)
    if users.pop(name, None) is None:
        return False
    _write(path, users)
    return True


def _write(path: str, users: dict) -> None:
    text = json.dumps({"version": 1, "users": users}, indent=1, sort_keys=True) + "\n"
    write_atomic(os.path.abspath(path), text.encode("utf-8"), mode=0o600)


@dataclass
class Session:
    user: str
    csrf: str
    expires: float
    remote: str


class Sessions:
    """In-memory sessions with an idle timeout."""

    def __init__(self, ttl_s: float, clock=time.monotonic):
        self.ttl = ttl_s
        self.clock = clock
        self._s: dict[str, Session] = {}

    def create(self, user: str, remote: str) -> tuple[str, Session]:
        now = self.clock()
        self._expire(now)
        while len(self._s) >= MAX_SESSIONS:
            self._s.pop(next(iter(self._s)))
        token = secrets.token_urlsafe(32)
        s = Session(user, secrets.token_urlsafe(32), now + self.ttl, remote)
        self._s[token] = s
        return token, s

    def get(self, token: str | None) -> Session | None:
        if not token or len(token) > 128:
            return None
        s = self._s.get(token)
        if s is None:
            return None
        now = self.clock()
        if now >= s.expires:
            self._s.pop(token, None)
            return None
        s.expires = now + self.ttl
        return s

    def drop(self, token: str | None) -> None:
        if token:
            self._s.pop(token, None)

    def _expire(self, now: float) -> None:
        for t in [t for t, s in self._s.items() if now >= s.expires]:
            del self._s[t]


class Lockout:
    """Failed logins per key (user name, client address) within a window → locked for a while."""

    def __init__(self, attempts: int, lockout_s: float, clock=time.monotonic, max_keys: int = 4096):
        self.attempts = attempts
        self.lockout_s = lockout_s
        self.clock = clock
        self.max_keys = max_keys
        self._fail: dict[str, list[float]] = {}
        self._until: dict[str, float] = {}

    def locked(self, *keys: str) -> float:
        """Seconds left of the longest lockout among ``keys`` (0 when none is locked)."""
        now = self.clock()
        left = 0.0
        for k in keys:
            u = self._until.get(k)
            if u is not None:
                if u > now:
                    left = max(left, u - now)
                else:
                    del self._until[k]
        return left

    def failed(self, *keys: str) -> None:
        now = self.clock()
        if len(self._fail) > self.max_keys:
            self._fail.clear()
        for k in keys:
            lst = [t for t in self._fail.get(k, []) if now - t < self.lockout_s]
            lst.append(now)
            if len(lst) >= self.attempts:
                self._until[k] = now + self.lockout_s
                lst = []
            self._fail[k] = lst

    def succeeded(self, *keys: str) -> None:
        for k in keys:
            self._fail.pop(k, None)

    def attempt(self, limits: dict[str, int]) -> float:
        """Check and count one attempt in one step: the seconds left of the longest lockout
        among the keys (nothing counted), or 0 after counting the attempt as a failure of every
        key (a key with ``n`` failures within the window is locked — the n-th attempt itself
        still gets its answer). :meth:`forgive` takes it back when the password was right."""
        left = self.locked(*limits)
        if left > 0:
            return left
        now = self.clock()
        if len(self._fail) > self.max_keys:
            self._fail.clear()
        for k, n in limits.items():
            lst = [t for t in self._fail.get(k, []) if now - t < self.lockout_s]
            lst.append(now)
            self._fail[k] = lst
            if len(lst) >= n:
                self._until[k] = now + self.lockout_s
        return 0.0

    def forgive(self, clear: tuple[str, ...] = (), one: tuple[str, ...] = ()) -> None:
        """A login succeeded: forget the failures (and lockout) of ``clear``, and the one
        attempt counted for each of ``one``."""
        for k in clear:
            self._fail.pop(k, None)
            self._until.pop(k, None)
        for k in one:
            lst = self._fail.get(k)
            if lst:
                lst.pop()


def _lowest_priority() -> None:
    """In the hashing thread: nice 19 for this thread only (Linux schedules threads)."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), HASH_NICE)
    except (OSError, AttributeError):     # not permitted or not Linux: normal priority
        pass


class Hasher:
    """Password hashes of logins within a budget, in one low-priority worker thread (see the
    module docstring). Used on the console's loop only (no locks)."""

    def __init__(self, per_s: float, burst: float, per_user_per_s: float, per_user_burst: float,
                 clock=time.monotonic):
        self.all = RateBound(per_s * 60.0, clock, burst=burst)
        self.per_user = RateBound(per_user_per_s * 60.0, clock, burst=per_user_burst)
        #: hashes begun (each one scrypt), and logins refused for the budget
        self.hashes = 0
        self.refused = 0
        self._pool: ThreadPoolExecutor | None = None

    def wait(self, user: str) -> float:
        """0 when a hash for ``user`` is within the budget now (nothing taken); else the seconds
        until it is."""
        return max(self.all.wait(), self.per_user.wait("u:" + user))

    def take(self, user: str) -> None:
        """Take one hash of the budget (after :meth:`wait` said 0, with no await in between)."""
        self.all.take()
        self.per_user.take("u:" + user)

    async def verify(self, password: str, entry: dict | None) -> bool:
        """The password against ``entry`` (None: an unknown user: the same work, then False),
        in the hashing thread; one hash counted."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="hookwatch-login-hash",
                                            initializer=_lowest_priority)
        self.hashes += 1
        loop = asyncio.get_running_loop()
        if entry is None:
            await loop.run_in_executor(self._pool, hash_password, password)
            return False
        return await loop.run_in_executor(self._pool, verify_password, password, entry)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
