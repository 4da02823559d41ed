"""Real-time scheduling for a station's slot-loop thread (Linux ``SCHED_FIFO``).

A station's slot loop sleeps almost all of each 20 ms slot and must wake within a millisecond of
its deadline. Under the default scheduler (CFS) a wake-up waits behind whatever else is runnable on
the box — other stations' workers, their twins, a console scrape — which is what makes the p99
lateness of a full box. With ``SCHED_FIFO`` the slot thread preempts every normal thread the moment
its timer fires, and, being asleep 95 % of the time, costs the others nothing.

Only the calling thread is switched (Linux schedules threads, not processes): the MQTT, IPC and
console threads of the same process stay normal, and so do threads the slot thread starts later
(``SCHED_RESET_ON_FORK``: e.g. the executor that runs record retention). Permitted for root, ``CAP_SYS_NICE``, or up to
``RLIMIT_RTPRIO`` (systemd: ``LimitRTPRIO=``) for other users. A slot loop stuck in a busy loop at
this priority still leaves the kernel's real-time throttling share (5 %) and the other core to the
rest of the box, and the supervisor's watchdog kills it after 5 s without a heartbeat.
"""
from __future__ import annotations

import ctypes
import gc
import os
import signal
from typing import Any

#: the highest priority ``hookwatch run --realtime`` accepts (leave the top to the kernel's threads)
MAX_PRIORITY = 49


def realtime_thread(priority: int) -> str | None:
    """Put the calling thread under ``SCHED_FIFO`` at ``priority`` (1…:data:`MAX_PRIORITY`).

    Returns None on success, else why not (the thread keeps its normal scheduling)."""
    if not 1 <= priority <= MAX_PRIORITY:
        return f"priority {priority} outside 1…{MAX_PRIORITY}"
    setter = getattr(os, "sched_setscheduler", None)
    if setter is None:
        return "this platform has no SCHED_FIFO"
    try:
        # 0: the calling thread (Linux). SCHED_RESET_ON_FORK: a thread this one starts later (an
        # executor's worker, a background writer) begins under normal scheduling instead of
        # inheriting SCHED_FIFO — background work must never run ahead of the box's other threads
        setter(0, os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0), os.sched_param(priority))
    except PermissionError:
        return ("not permitted (needs root, CAP_SYS_NICE or RLIMIT_RTPRIO ≥ "
                f"{priority}: systemd LimitRTPRIO={priority})")
    except OSError as e:
        return str(e)
    return None


def thread_policy() -> str:
    """The calling thread's scheduling policy, as a word (for logs and tests)."""
    getter = getattr(os, "sched_getscheduler", None)
    if getter is None:
        return "unknown"
    pol = getter(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
    return {os.SCHED_OTHER: "other", os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr"}.get(pol, str(pol))


#: prctl(2) option: the signal a process gets when the thread that started it ends
_PR_SET_PDEATHSIG = 1
_prctl: Any
try:        # resolved here, in the parent: the child between fork and exec only calls it
    _prctl = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):     # not Linux
    _prctl = None


def die_with_parent() -> None:
    """For ``subprocess.Popen(preexec_fn=…)``: the child gets SIGTERM when its parent ends, however
    it ends (SIGKILL, a crash, a closed terminal's SIGHUP): a killed ``hookwatch demo`` leaves no
    simulator or broker behind. Linux only (elsewhere, and if prctl is refused, nothing happens).
    Runs in the child between fork and exec: no allocation-heavy work, no locks."""
    if _prctl is None:
        return
    parent = os.getppid()
    if _prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) == 0 and os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGTERM)      # the parent ended before prctl took effect


def freeze_heap() -> None:
    """Move every object alive now into the garbage collector's permanent generation.

    Call it once a station is built (its modules imported, its configuration, drivers and
    outputs made), before its slot loop runs. A full (generation-2) collection walks every
    tracked object of the process while holding the GIL: with the gateway's ~60,000 objects of
    modules and configuration that is a 30–40 ms stall of every thread (measured:
    bench/bench_stall.py), twice a slot, whenever the collector decides. Frozen objects are
    never walked again; what the station allocates from then on is collected as before. Cheap
    (a list splice) and cumulative: each station of a process may call it after its build."""
    gc.freeze()


#: the niceness of the systemd units (deploy/systemd: ``Nice=-5``): every thread of the gateway
#: ahead of the box's ordinary work, so a thread that holds the GIL is not kept off the CPU by a
#: browser or a compile while the SCHED_FIFO slot thread waits for the GIL
DEPLOYED_NICE = -5


def deployed_nice() -> str | None:
    """Lower this process' niceness to :data:`DEPLOYED_NICE` as the units deploy it (threads
    and processes started afterwards inherit it). None on success, else why not."""
    try:
        cur = os.getpriority(os.PRIO_PROCESS, 0)
        if cur > DEPLOYED_NICE:
            os.setpriority(os.PRIO_PROCESS, 0, DEPLOYED_NICE)
    except OSError as e:
        return e.strerror or str(e)
    return None
