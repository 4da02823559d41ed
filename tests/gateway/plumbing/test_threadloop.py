"""gateway/plumbing/threadloop.py: the one thread → loop hand-over and the bounded loop → thread stream."""
import asyncio
import threading
import time

import pytest

from gateway.plumbing.threadloop import Mailbox, ThreadLoop, call_soon_on, submit_to


def test_threadloop_runs_coroutines_and_calls_on_its_own_thread():
    tl = ThreadLoop("tl-test")
    tl.start()
    try:
        async def where():
            await asyncio.sleep(0)
            return threading.current_thread().name

        assert tl.submit(where()).result(5) == "tl-test"
        seen = threading.Event()
        tl.call_soon(seen.set)
        assert seen.wait(5)
        assert call_soon_on(tl.loop, seen.clear) and submit_to(tl.loop, where()).result(5) == "tl-test"
    finally:
        tl.stop()
    assert not tl.running
    # a stopped loop: the helpers say so instead of raising, and close the coroutine
    coro = asyncio.sleep(0)
    assert submit_to(tl.loop, coro) is None and coro.cr_frame is None
    assert call_soon_on(tl.loop, print) is False
    with pytest.raises(RuntimeError):
        _ = ThreadLoop("never").loop


def test_stop_cancels_pending_tasks():
    tl = ThreadLoop("tl-cancel")
    tl.start()
    cancelled = threading.Event()

    started = threading.Event()

    async def forever():
        started.set()
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            cancelled.set()
            raise

    tl.submit(forever())
    # a task cancelled before its first step never enters its try block: wait until it runs
    assert started.wait(5)
    tl.stop(5)
    assert cancelled.is_set() and not tl.running


def test_mailbox_is_bounded_never_blocks_and_counts_drops():
    mb = Mailbox(3)
    assert [mb.put_nowait(i) for i in range(5)] == [True, True, True, False, False]
    assert mb.dropped == 2 and len(mb) == 3
    assert mb.drain() == [2, 3, 4] and mb.drain() == []
    got = []
    t = threading.Thread(target=lambda: (mb.wait(5), got.extend(mb.drain())))
    t.start()
    mb.put_nowait("x")
    t.join(5)
    assert got == ["x"]
    with pytest.raises(ValueError):
        Mailbox(0)


def test_a_mailbox_drop_policy_drops_the_oldest_droppable_item_and_stays_bounded():
    """With ``droppable``, a full mailbox gives up its oldest droppable item (a measured value),
    keeps the others (births, replies) in order, and when none is droppable drops the oldest all
    the same: the bound holds whatever comes."""
    mb = Mailbox(4, droppable=lambda it: it[0] == "data")
    for it in [("birth", 0), ("data", 1), ("data", 2), ("reply", 3), ("data", 4), ("death", 5)]:
        mb.put_nowait(it)
    assert mb.drain() == [("birth", 0), ("reply", 3), ("data", 4), ("death", 5)]
    assert mb.dropped == 2
    for i in range(6):
        assert len(mb) <= 4
        mb.put_nowait(("reply", i))
    assert mb.drain() == [("reply", i) for i in range(2, 6)] and mb.dropped == 4


def test_a_mailbox_names_what_it_drops_and_hands_over_one_at_a_time():
    """``on_drop`` hears of each dropped item (a worker's log line names it); ``take`` gives the
    oldest items and leaves the others waiting (a worker handling one at a time keeps the bound on
    what waits), and clears the wake-up only when it empties the mailbox (no spinning consumer,
    no lost wake-up)."""
    gone = []
    mb = Mailbox(3, on_drop=gone.append)
    assert [mb.put_nowait(i) for i in range(5)] == [True, True, True, False, False]
    assert gone == [0, 1] and mb.dropped == 2
    assert mb.take() == [2] and len(mb) == 2 and mb.wait(0)          # more waits: still awake
    assert mb.take(5) == [3, 4] and len(mb) == 0 and not mb.wait(0)  # emptied: asleep
    assert mb.take() == [] and not mb.wait(0)
    got = []

    def worker():
        while len(got) < 20:
            if mb.wait(5):
                got.extend(mb.take())
    t = threading.Thread(target=worker)
    t.start()
    for i in range(20):
        while len(mb) >= 3:               # a producer that waits for room: nothing may be dropped
            time.sleep(0.001)
        mb.put_nowait(i)
    t.join(10)
    assert not t.is_alive() and got == list(range(20)) and gone == [0, 1]


def test_a_keyed_mailbox_keeps_the_newest_item_of_a_key_in_its_place_and_counts_the_replaced():
    """Issue 34: a station's newest lives snapshot replaces the one still waiting."""
    dropped: list[tuple[str, int]] = []
    box: Mailbox[tuple[str, int]] = Mailbox(3, key=lambda it: it[0], on_drop=dropped.append)
    assert box.put_nowait(("a", 1)) and box.put_nowait(("b", 1))
    for i in range(2, 400):
        assert not box.put_nowait(("a", i))          # replaced, never a second "a"
    assert box.drain() == [("a", 399), ("b", 1)]   # in the first one's place
    assert box.dropped == box.replaced == 398 and dropped[0] == ("a", 1) and len(dropped) == 398
    for k in "cdef":                               # more keys than room: the oldest goes
        box.put_nowait((k, 0))
    assert [k for k, _ in box.drain()] == ["d", "e", "f"] and box.replaced == 398 and box.dropped == 399


def test_take_with_ready_leaves_the_items_not_ready_in_their_place():
    box: Mailbox[tuple[str, int]] = Mailbox(8, key=lambda it: it[0])
    for k in "abc":
        box.put_nowait((k, 0))
    assert box.take(1, ready=lambda it: it[0] != "a") == [("b", 0)]
    assert box.take(5, ready=lambda it: False) == [] and box.wait(0)   # still waiting: awake
    box.put_nowait(("a", 1))                       # a newer "a" takes the waiting one's place
    assert box.take(5) == [("a", 1), ("c", 0)] and not box.wait(0)
