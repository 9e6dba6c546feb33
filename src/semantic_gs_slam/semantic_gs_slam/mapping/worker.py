"""The mapping back end's thread: a bounded job queue drained by one worker (``SlamConfig.threaded``).

Jobs are callables run in order. Drop policy: a keyframe job waits up to ``put_timeout_s`` for room, other jobs
never wait; a job that finds no room is not run and :meth:`MappingWorker.submit` returns False (the caller logs
and counts it). The first exception a job raises stops the worker; it is re-raised (as :class:`MappingError`,
the cause chained) by the next :meth:`submit`, :meth:`drain` or :meth:`close`.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

from semantic_gs_slam.errors import MappingError

log = logging.getLogger("semantic_gs_slam")

_STOP = object()


class MappingWorker:
    """One daemon thread running submitted jobs in order from a ``queue.Queue(maxsize)``."""

    def __init__(self, maxsize: int, put_timeout_s: float, name: str = "slam-mapping") -> None:
        self._q: queue.Queue = queue.Queue(maxsize=maxsize)
        self._put_timeout_s = put_timeout_s
        self._lock = threading.Lock()  # guards _error
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            job = self._q.get()  # blocks until a job or _STOP: the thread has nothing else to do
            try:
                if job is _STOP:
                    return
                with self._lock:
                    failed = self._error is not None
                if not failed:  # after a failure the remaining jobs are skipped (their frames stay unmapped)
                    job()
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                log.error("mapping thread failed: %r", exc, exc_info=exc)  # its traceback: the caller gets a copy
                with self._lock:
                    self._error = exc
            finally:
                self._q.task_done()

    @property
    def failed(self) -> bool:
        """Whether a job raised (the worker stopped running jobs)."""
        with self._lock:
            return self._error is not None

    def raise_if_failed(self) -> None:
        """Re-raise a job's exception as :class:`MappingError` (once per failure: the worker stays failed)."""
        with self._lock:
            exc = self._error
        if exc is not None:
            raise MappingError(f"the mapping thread failed: {exc!r}") from exc

    def submit(self, job: Callable[[], None], wait: bool) -> bool:
        """Queue ``job``; ``wait``: wait up to ``put_timeout_s`` for room (keyframes), else none.

        Returns:
            True when queued, False when the queue stayed full (the job is dropped).

        Raises:
            MappingError: an earlier job failed.
        """
        self.raise_if_failed()
        try:
            if wait:
                self._q.put(job, timeout=self._put_timeout_s)
            else:
                self._q.put_nowait(job)
        except queue.Full:
            return False
        return True

    @property
    def pending(self) -> int:
        """Jobs queued or running (approximate: another thread may change it)."""
        return self._q.unfinished_tasks

    def drain(self, timeout: float) -> None:
        """Wait until every queued job has run, at most ``timeout`` seconds (0: only check).

        Raises:
            MappingError: a job failed, or jobs were still pending at the deadline.
        """
        deadline = time.monotonic() + timeout
        while self._q.unfinished_tasks:
            self.raise_if_failed()
            left = deadline - time.monotonic()
            if left <= 0:
                raise MappingError(f"the mapping thread did not drain within {timeout:.1f} s "
                                   f"({self._q.unfinished_tasks} job(s) pending)")
            time.sleep(min(0.005, left))
        self.raise_if_failed()

    def close(self, timeout: float) -> None:
        """Drain (see :meth:`drain`), then stop the thread."""
        try:
            self.drain(timeout)
        finally:
            try:
                self._q.put(_STOP, timeout=max(0.0, timeout))
                self._thread.join(timeout=max(0.1, timeout))
            except queue.Full:
                log.warning("mapping thread left running: its queue stayed full")
