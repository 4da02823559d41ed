"""gateway/plumbing/osprio.py: SCHED_FIFO for the calling thread only, and a plain reason when not allowed."""
from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

from conftest import ROOT
from gateway.plumbing.osprio import MAX_PRIORITY, realtime_thread, thread_policy


def test_out_of_range_priority_is_refused_and_changes_nothing():
    before = thread_policy()
    assert "outside" in (realtime_thread(0) or "")
    assert "outside" in (realtime_thread(MAX_PRIORITY + 1) or "")
    assert thread_policy() == before


@pytest.mark.skipif(os.geteuid() != 0, reason="SCHED_FIFO needs root here")
def test_only_the_calling_thread_becomes_fifo():
    seen: dict[str, object] = {}

    def slot_thread():
        seen["why"] = realtime_thread(20)
        seen["policy"] = thread_policy()
        seen["prio"] = os.sched_getparam(0).sched_priority

    t = threading.Thread(target=slot_thread)
    t.start()
    t.join()
    assert seen == {"why": None, "policy": "fifo", "prio": 20}
    assert thread_policy() == "other"          # the main thread is untouched


def test_an_unprivileged_user_gets_a_reason_not_an_exception():
    """The child imports as root, then becomes nobody (uid/gid 65534, no groups: its capabilities go
    with uid 0), so the test does not depend on where the checkout or the interpreter lives (a
    checkout under /root, 0700, is out of nobody's reach)."""
    if os.geteuid() != 0:
        pytest.skip("needs root to become an unprivileged user")
    code = ("import os, sys; sys.path.insert(0, sys.argv[1]); from gateway.plumbing.osprio import *; "
            "os.setgroups([]); os.setresgid(65534, 65534, 65534); os.setresuid(65534, 65534, 65534); "
            "assert os.getresuid() == (65534, 65534, 65534); "
            "print(realtime_thread(20)); print(thread_policy())")
    r = subprocess.run([sys.executable, "-c", code, ROOT], capture_output=True, text=True, timeout=30,
                       env={**os.environ, "HOME": "/"})
    assert r.returncode == 0, r.stderr
    why, policy = r.stdout.splitlines()
    assert "not permitted" in why and "LimitRTPRIO=20" in why
    assert policy == "other"
