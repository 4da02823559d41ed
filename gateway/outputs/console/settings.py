"""The console's settings (``console:`` of a station file) and its listen addresses."""
from __future__ import annotations

import os

from ...plumbing.doors import DoorLimits


class ConsoleSettings:
    def __init__(self, *, listen=("127.0.0.1:8080",), cert_file=None, key_file=None,
                 users_file: str, read_without_login="local", session_ttl_s=28800.0,
                 lockout_attempts=5, lockout_s=300.0, login_failures_per_address=20,
                 allowed_hosts=(), report_jobs=1, report_queue=8, stream_connects_per_address=30,
                 stream_connects_total=120, door: DoorLimits | None = None, site_view: bool = True,
                 login_hashes_per_s=4.0, login_hash_burst=10, login_hashes_per_user_per_s=1.0,
                 login_hash_burst_per_user=5):
        self.listen = tuple(listen)
        self.cert_file, self.key_file = cert_file, key_file
        self.users_file = users_file
        self.read_without_login = read_without_login
        self.session_ttl_s = float(session_ttl_s)
        self.lockout_attempts = int(lockout_attempts)
        self.lockout_s = float(lockout_s)
        self.login_failures_per_address = int(login_failures_per_address)
        self.allowed_hosts = tuple(allowed_hosts)
        self.report_jobs = int(report_jobs)
        self.report_queue = int(report_queue)
        self.stream_connects_per_address = int(stream_connects_per_address)
        self.stream_connects_total = int(stream_connects_total)
        #: the password-hashing budget (gateway/outputs/console/auth.py, Hasher)
        self.login_hashes_per_s = float(login_hashes_per_s)
        self.login_hash_burst = int(login_hash_burst)
        self.login_hashes_per_user_per_s = float(login_hashes_per_user_per_s)
        self.login_hash_burst_per_user = int(login_hash_burst_per_user)
        #: connection cap, request deadline, idle timeout (console.connections)
        self.door = door or DoorLimits(256, 10.0, 60.0, max_per_address=32)
        #: show the stations of the site's other boxes (console.site_view; gateway/outputs/console/site.py)
        self.site_view = bool(site_view)

    @classmethod
    def from_config(cls, cfg) -> ConsoleSettings:
        c = cfg.console
        users = c.users_file or os.path.join(cfg.recorder.dir, "console-users.json")
        return cls(listen=c.listen, cert_file=c.tls.cert_file, key_file=c.tls.key_file,
                   users_file=users, read_without_login=c.read_without_login,
                   session_ttl_s=c.session_ttl_s, lockout_attempts=c.lockout_attempts,
                   lockout_s=c.lockout_s, login_failures_per_address=c.login_failures_per_address,
                   allowed_hosts=c.allowed_hosts, report_jobs=c.report_jobs,
                   report_queue=c.report_queue,
                   stream_connects_per_address=c.stream_connects_per_address,
                   stream_connects_total=c.stream_connects_total,
                   door=DoorLimits.from_config(c.connections),
                   site_view=bool(c.site_view),
                   login_hashes_per_s=c.login_hashes_per_s, login_hash_burst=c.login_hash_burst,
                   login_hashes_per_user_per_s=c.login_hashes_per_user_per_s,
                   login_hash_burst_per_user=c.login_hash_burst_per_user)


def parse_listen(addr: str) -> tuple[str, int]:
    host, sep, port = str(addr).rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"console.listen {addr!r}: expected host:port")
    return host.strip("[]") or "0.0.0.0", int(port)

