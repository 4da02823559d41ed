"""gateway/threadloop.py: the one thread → loop hand-over and the bounded loop → thread stream."""
import asyncio
import threading

import pytest

from gateway.threadloop import Mailbox, ThreadLoop, call_soon_on, submit_to


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
        ThreadLoop("never").loop


def test_stop_cancels_pending_tasks():
    tl = ThreadLoop("tl-cancel")
    tl.start()
    cancelled = threading.Event()

    async def forever():
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            cancelled.set()
            raise

    tl.submit(forever())
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
