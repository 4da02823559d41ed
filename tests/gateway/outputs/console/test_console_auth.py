"""Users file, password hashes, sessions and lockout of the console; reading rules over HTTP
against an in-process console (no stations)."""
from __future__ import annotations

import json
import os
import stat

import pytest

from gateway.outputs.console import auth
from gateway.outputs.console.app import ConsoleServer
from gateway.outputs.console.settings import ConsoleSettings
from kit.console_helpers import Client


def test_users_file_salted_scrypt_mode_0600(tmp_path):
    f = str(tmp_path / "u.json")
    assert auth.add_user(f, "alice", "a long password") is True
    assert auth.add_user(f, "bob", "a long password") is True
    assert stat.S_IMODE(os.stat(f).st_mode) == 0o600
    text = (tmp_path / "u.json").read_text()
    users = json.loads(text)["users"]
    a, b = users["alice"], users["bob"]
    assert a["kdf"] == "scrypt" and a["n"] == 2 ** 14 and a["r"] == 8 and a["p"] == 1
    assert a["salt"] != b["salt"] and a["hash"] != b["hash"]          # salted: same password differs
    assert "a long password" not in text
    assert auth.verify_password("a long password", a)
    assert not auth.verify_password("a long passwort", a)
    assert not auth.verify_password("x", {"kdf": "md5"})
    assert auth.add_user(f, "alice", "another password") is False    # replaced
    assert auth.verify_password("another password", auth.load_users(f)["alice"])
    with pytest.raises(auth.UsersError):
        auth.add_user(f, "../evil", "a long password")
    with pytest.raises(auth.UsersError):
        auth.add_user(f, "carol", "short")
    assert auth.remove_user(f, "bob") and not auth.remove_user(f, "bob")
    (tmp_path / "bad.json").write_text("[1]")
    with pytest.raises(auth.UsersError):
        auth.load_users(str(tmp_path / "bad.json"))


def test_sessions_expire_and_lockout_ends():
    now = [0.0]
    s = auth.Sessions(60, clock=lambda: now[0])
    tok, sess = s.create("alice", "127.0.0.1")
    assert s.get(tok) is sess and s.get("nope") is None and s.get("x" * 500) is None
    now[0] = 59
    assert s.get(tok) is sess          # activity renews
    now[0] = 118
    assert s.get(tok) is sess
    now[0] = 179
    assert s.get(tok) is None
    lk = auth.Lockout(3, 30, clock=lambda: now[0])
    lk.failed("u:a")
    lk.failed("u:a")
    assert lk.locked("u:a") == 0
    lk.failed("u:a")
    assert lk.locked("u:a") == 30 and lk.locked("u:b") == 0
    now[0] += 31
    assert lk.locked("u:a") == 0


@pytest.mark.parametrize("mode,anon", [("none", 401), ("local", 200), ("all", 200)])
def test_reading_rules(tmp_path, mode, anon):
    users = str(tmp_path / "u.json")
    auth.add_user(users, "alice", "a long password")
    srv = ConsoleServer(ConsoleSettings(listen=("127.0.0.1:0",), users_file=users,
                                        read_without_login=mode), {"s1": str(tmp_path / "s1")})
    urls = srv.start()
    try:
        c = Client(urls[0].rstrip("/"))
        assert c.get("/api/fleet")[0] == anon
        assert c.get("/api/station/s1")[0] == anon
        assert c.get("/")[0] == 200                      # the page itself (it asks to log in)
        assert c.login("alice", "a long password")[0] == 200
        assert c.get("/api/fleet")[0] == 200
        st, r, _ = c.post("/api/station/s1/command", {"command": "stop"})
        assert st == 409 and r["code"] == 10              # NO_STATION: not running
    finally:
        srv.stop()


def test_port_in_use_is_a_state_not_a_crash(tmp_path):
    a = ConsoleServer(ConsoleSettings(listen=("127.0.0.1:0",), users_file=str(tmp_path / "u")), {})
    port = a.start()[0].rsplit(":", 1)[1].strip("/")
    b = ConsoleServer(ConsoleSettings(listen=(f"127.0.0.1:{port}",), users_file=str(tmp_path / "u")), {})
    try:
        assert b.start() == [] and "Errno" in (b.error or "")
    finally:
        b.stop()
        a.stop()
