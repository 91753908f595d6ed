"""Threads of the engine: a bounded worker pool and a deadline timer.

:class:`WorkerPool` runs action hooks. Threads are started on demand up to ``max_workers``,
reused for later runs (no thread per action run) and retired after ``idle_timeout`` seconds
without work. When every worker is busy, jobs queue; a job that waited more than
:data:`SLOW_START` seconds for a worker is reported once per busy period (raise ``max_workers``
when actions block for long).

:class:`DeadlineTimer` calls functions at deadlines (stop timeouts) from one thread that sleeps
on a condition until the next deadline; nothing polls.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

__all__ = ["DeadlineTimer", "TimerHandle", "WorkerPool"]

logger = logging.getLogger(__name__)

Job = tuple[Callable[..., Any], tuple[Any, ...], float]

#: A job that waited this long (real seconds) for a free worker is reported.
SLOW_START = 1.0


class WorkerPool:
    """A bounded, growing pool of named worker threads.

    Args:
        max_workers: Upper bound on threads (≥ 1).
        name: Thread name prefix (threads are ``<name>-<n>``).
        idle_timeout: Seconds an idle worker waits for work before it exits.

    Raises:
        ValueError: If ``max_workers`` < 1.
    """

    def __init__(
        self, max_workers: int = 64, *, name: str = "temoto-worker", idle_timeout: float = 30.0
    ) -> None:
        if max_workers < 1:
            raise ValueError(f"max_workers must be at least 1, got {max_workers}")
        self.max_workers = max_workers
        self._name = name
        self._idle_timeout = idle_timeout
        self._jobs: queue.SimpleQueue[Job | None] = queue.SimpleQueue()
        self._mutex = threading.Lock()
        self._idle = 0  # workers waiting for a job that no submit has claimed yet
        self._backlog = 0  # jobs queued while every worker was busy
        self._threads: set[threading.Thread] = set()
        self._counter = itertools.count(1)
        self._closed = False
        self._warned = False  # reported a slow start in this busy period

    @property
    def size(self) -> int:
        """Number of live worker threads."""
        with self._mutex:
            return len(self._threads)

    def submit(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn(*args)`` on a worker. Exceptions are logged, never lost silently.

        Args:
            fn: The function.
            *args: Its arguments.

        Returns:
            None.

        Raises:
            RuntimeError: After :meth:`shutdown`.
        """
        with self._mutex:
            if self._closed:
                raise RuntimeError("worker pool is shut down")
            queued = time.monotonic() if self._claim() else 0.0
        self._jobs.put((fn, args, queued))

    def _claim(self) -> bool:
        """Find a worker for one more job (mutex held): an idle one, a new one, or none.

        Returns:
            Whether the job must wait in the backlog (every worker busy, none may be added).
        """
        if self._idle:
            self._idle -= 1
            return False
        if len(self._threads) < self.max_workers:
            thread = threading.Thread(
                target=self._work, name=f"{self._name}-{next(self._counter)}", daemon=True
            )
            self._threads.add(thread)
            thread.start()
            return False
        self._backlog += 1
        return True

    def submit_many(self, fn: Callable[..., Any], jobs: list[tuple[Any, ...]]) -> None:
        """Run ``fn(*args)`` for every ``args`` of ``jobs``, under one lock for them all.

        As :meth:`submit` for each job (idle workers are claimed, new ones started up to
        ``max_workers``, the rest queued), but the pool's lock is taken once: a fan-out of N
        ready actions is one batch, not N submissions. Nothing is queued if the pool is shut
        down.

        Args:
            fn: The function.
            jobs: Its arguments, one tuple per job.

        Returns:
            None.

        Raises:
            RuntimeError: After :meth:`shutdown` (no job was queued).
        """
        queued = 0.0
        with self._mutex:
            if self._closed:
                raise RuntimeError("worker pool is shut down")
            for _ in jobs:
                if self._claim():
                    queued = queued or time.monotonic()
        put = self._jobs.put
        for args in jobs:
            put((fn, args, queued))

    def _work(self) -> None:
        me = threading.current_thread()
        while True:
            try:
                job = self._jobs.get(timeout=self._idle_timeout)
            except queue.Empty:
                with self._mutex:
                    if self._idle > 0:  # nobody claimed an idle worker: this one may go
                        self._idle -= 1
                        self._threads.discard(me)
                        return
                continue  # a submit claimed us just now; its job is on the way
            if job is None:
                with self._mutex:
                    self._threads.discard(me)
                return
            fn, args, queued = job
            if queued and not self._warned and time.monotonic() - queued > SLOW_START:
                self._warned = True
                logger.warning(
                    "an action waited %.1f s for a free worker: all %d workers are busy"
                    " (raise max_workers if actions block for long)",
                    time.monotonic() - queued,
                    self.max_workers,
                )
            try:
                fn(*args)
            except BaseException:
                logger.exception("uncaught error in worker job %r", fn)
            del job, fn, args
            with self._mutex:
                if self._backlog:
                    self._backlog -= 1
                else:
                    self._idle += 1
                    self._warned = False  # reported a slow start in this busy period

    def shutdown(self, timeout: float | None = 10.0) -> list[str]:
        """Stop accepting work, let queued jobs finish, and join the workers.

        Args:
            timeout: Seconds to wait for all workers together (None: forever).

        Returns:
            Names of workers still busy after the timeout (stuck in user code).
        """
        with self._mutex:
            self._closed = True
            threads = list(self._threads)
        for _ in threads:
            self._jobs.put(None)
        deadline = None if timeout is None else time.monotonic() + timeout
        stuck = []
        for thread in threads:
            thread.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
            if thread.is_alive():
                stuck.append(thread.name)
        return stuck


class TimerHandle:
    """A scheduled call; :meth:`cancel` prevents it if it has not run yet."""

    __slots__ = ("args", "cancelled", "fn", "when")

    def __init__(self, when: float, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        self.when = when
        self.fn = fn
        self.args = args
        self.cancelled = False

    def cancel(self) -> None:
        """Do not run this call.

        Returns:
            None.
        """
        self.cancelled = True


class DeadlineTimer:
    """Calls functions at real-time deadlines from one named thread (started on first use).

    Args:
        name: The thread name.
    """

    def __init__(self, name: str = "temoto-timer") -> None:
        self._name = name
        self._cond = threading.Condition(threading.Lock())
        self._heap: list[tuple[float, int, TimerHandle]] = []
        self._seq = itertools.count()
        self._thread: threading.Thread | None = None
        self._closed = False

    def call_later(self, seconds: float, fn: Callable[..., Any], *args: Any) -> TimerHandle:
        """Call ``fn(*args)`` after ``seconds`` of real time.

        Args:
            seconds: Real seconds from now.
            fn: The function (must not block: it runs on the timer thread).
            *args: Its arguments.

        Returns:
            A handle to cancel the call.

        Raises:
            RuntimeError: After :meth:`shutdown`.
        """
        handle = TimerHandle(time.monotonic() + seconds, fn, args)
        with self._cond:
            if self._closed:
                raise RuntimeError("timer is shut down")
            heapq.heappush(self._heap, (handle.when, next(self._seq), handle))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
                self._thread.start()
            elif self._heap[0][2] is handle:
                self._cond.notify()
        return handle

    def _run(self) -> None:
        while True:
            with self._cond:
                while True:
                    if self._closed:
                        return
                    if self._heap:
                        when, _, handle = self._heap[0]
                        delay = when - time.monotonic()
                        if handle.cancelled:
                            heapq.heappop(self._heap)
                            continue
                        if delay <= 0:
                            heapq.heappop(self._heap)
                            break
                        self._cond.wait(delay)
                    else:
                        self._cond.wait()
            try:
                handle.fn(*handle.args)
            except BaseException:
                logger.exception("uncaught error in timer callback %r", handle.fn)

    def shutdown(self) -> None:
        """Drop pending calls and join the thread.

        Returns:
            None.
        """
        with self._cond:
            self._closed = True
            self._heap.clear()
            self._cond.notify()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()
