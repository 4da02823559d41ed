"""The one thread → loop hand-over, and the one bounded loop → thread stream.

Every boundary between an asyncio loop and another thread in hookwatch goes through this module:

- :class:`ThreadLoop` is an asyncio loop on its own daemon thread (the MQTT pump calls a
  station's loop with :meth:`ThreadLoop.submit`; the Modbus TCP server runs on one). From any
  thread, :meth:`submit` runs a coroutine on the loop (``run_coroutine_threadsafe``) and
  :meth:`call_soon` schedules a plain call (``call_soon_threadsafe``).
- :func:`submit_to` / :func:`call_soon_on` are the same hand-over onto any running loop (a
  station's own loop), returning ``None`` / ``False`` instead of raising when the loop is gone.
- :class:`Mailbox` carries a stream from a slot loop to another thread: bounded, never blocking the
  producer; when full, the oldest item is dropped and counted. It is the one hand-over of work
  between threads (tests/test_architecture.py: no other ``queue.Queue`` or ``Condition``).
"""
from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import threading
from collections.abc import Callable, Coroutine, Hashable
from typing import Any, Generic, TypeVar

T = TypeVar("T")
ItemT = TypeVar("ItemT")


def submit_to(loop: asyncio.AbstractEventLoop | None,
              coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T] | None:
    """Run ``coro`` on ``loop`` (owned by another thread); None if that loop is not running."""
    if loop is None or loop.is_closed():
        coro.close()
        return None
    try:
        return asyncio.run_coroutine_threadsafe(coro, loop)
    except RuntimeError:        # closed between the check and the call
        coro.close()
        return None


def call_soon_on(loop: asyncio.AbstractEventLoop | None, fn: Callable[..., Any], *args: Any) -> bool:
    """Call ``fn(*args)`` on ``loop`` (owned by another thread); False if that loop is gone."""
    if loop is None or loop.is_closed():
        return False
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:
        return False
    return True


class ThreadLoop:
    """An asyncio loop on its own daemon thread: the one thread→loop hand-over."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()

    def start(self) -> None:
        """Start the thread and its loop; returns once the loop runs."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._main, name=self.name, daemon=True)
        self._thread.start()
        self._ready.wait()

    def _main(self) -> None:
        loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        self._loop = loop
        loop.call_soon(self._ready.set)
        try:
            loop.run_forever()
        finally:
            try:
                pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
                for t in pending:
                    t.cancel()
                if pending:
                    loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
                loop.run_until_complete(loop.shutdown_asyncgens())
                loop.run_until_complete(loop.shutdown_default_executor())
            finally:
                loop.close()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the loop (its pending tasks are cancelled) and join the thread."""
        loop, th = self._loop, self._thread
        if loop is None or th is None:
            return
        try:
            loop.call_soon_threadsafe(loop.stop)
        except RuntimeError:
            pass
        if th is not threading.current_thread():
            th.join(timeout)

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        if self._loop is None:
            raise RuntimeError(f"ThreadLoop {self.name} is not started")
        return self._loop

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def thread(self) -> threading.Thread | None:
        return self._thread

    def submit(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
        """Run ``coro`` on the loop from any thread (``run_coroutine_threadsafe``)."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    def call_soon(self, fn: Callable[..., Any], *args: Any) -> None:
        """Call ``fn(*args)`` on the loop from any thread (``call_soon_threadsafe``)."""
        self.loop.call_soon_threadsafe(fn, *args)


class Mailbox(Generic[ItemT]):
    """A bounded, non-blocking stream from a slot loop to another thread.

    :meth:`put_nowait` never blocks and never fails: when ``maxlen`` items wait, one is dropped
    and counted in :attr:`dropped`. The drop policy says which: the oldest item (the default), or,
    with ``droppable``, the oldest item it accepts (e.g. a measured value, never a birth or a
    command reply) and only when none waits, the oldest one, so the bound holds whatever comes.
    With ``key``, an item whose key equals that of an item still waiting *replaces* it (the newest
    of a key wins: e.g. a station's newest lives snapshot; the one replaced is dropped and counted
    in :attr:`dropped` and :attr:`replaced`), so at most one item per key waits.
    ``on_drop``, if given, hears of each dropped item (in the producer's thread, outside the
    mailbox's lock: it must be quick and must not raise), e.g. to name it in a log line.
    The consumer takes everything with :meth:`drain`, or the oldest few with :meth:`take` (a worker
    that handles one item at a time, so the bound holds for what waits), optionally after
    :meth:`wait`."""

    def __init__(self, maxlen: int, droppable: Callable[[ItemT], bool] | None = None,
                 on_drop: Callable[[ItemT], None] | None = None,
                 key: Callable[[ItemT], Hashable] | None = None) -> None:
        if maxlen < 1:
            raise ValueError("Mailbox maxlen must be at least 1")
        self.maxlen = maxlen
        self.droppable = droppable
        self.on_drop = on_drop
        self.key = key
        #: items replaced by a newer one of the same key (also counted in :attr:`dropped`)
        self.replaced = 0
        self._q: collections.deque[ItemT] = collections.deque()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self.dropped = 0

    def put_nowait(self, item: ItemT) -> bool:
        """Queue ``item``; False when an older item had to be dropped to make room (or, with
        ``key``, was replaced)."""
        gone: list[ItemT] = []
        with self._lock:
            q = self._q
            full = False
            if self.key is not None and self._replace(q, item, gone):
                self.dropped += 1
                self.replaced += 1
            else:
                full = len(q) >= self.maxlen
                if full:
                    gone.append(self._drop_one(q))
                    self.dropped += 1
                q.append(item)
        self._wake.set()
        if gone and self.on_drop is not None:
            self.on_drop(gone[0])
        return not (full or gone)

    def _replace(self, q: collections.deque[ItemT], item: ItemT, gone: list[ItemT]) -> bool:
        """With ``key``: put ``item`` in the place of the waiting item of its key, if any."""
        assert self.key is not None
        k = self.key(item)
        for i, it in enumerate(q):
            if self.key(it) == k:
                gone.append(it)
                q[i] = item
                return True
        return False

    def _drop_one(self, q: collections.deque[ItemT]) -> ItemT:
        pick = self.droppable
        if pick is not None:
            for i, it in enumerate(q):
                if pick(it):
                    del q[i]
                    return it
        return q.popleft()

    def drain(self) -> list[ItemT]:
        """Everything queued, oldest first (empties the mailbox)."""
        with self._lock:
            items = list(self._q)
            self._q.clear()
            self._wake.clear()
        return items

    def take(self, n: int = 1, ready: Callable[[ItemT], bool] | None = None) -> list[ItemT]:
        """The oldest ``n`` items (fewer if fewer wait), oldest first; the others stay. With
        ``ready``, the oldest ``n`` of those it accepts (e.g. a station's snapshot only once its
        last one is long enough ago); the others keep their place (and, with ``key``, are still
        replaced by newer ones). Leaving the mailbox empty clears its wake-up, so a consumer
        looping on :meth:`wait` then :meth:`take` never spins (items that wait but are not ready
        keep it set: such a consumer waits on its own clock)."""
        with self._lock:
            q = self._q
            if ready is None:
                items = [q.popleft() for _ in range(min(n, len(q)))]
            else:
                at = [i for i, x in enumerate(q) if ready(x)][:n]
                items = [q[i] for i in at]
                for i in reversed(at):
                    del q[i]
            if not q:
                self._wake.clear()
        return items

    def wait(self, timeout: float | None = None) -> bool:
        """Block the consumer until something is queued (or :meth:`wake` is called)."""
        return self._wake.wait(timeout)

    def wake(self) -> None:
        self._wake.set()

    def clear_wake(self) -> None:
        self._wake.clear()

    def __len__(self) -> int:
        return len(self._q)
