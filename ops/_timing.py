"""CPU-seconds per stage of a kernel, so that every change is measured where it acts.

The clock is the calling thread's CPU time (:func:`time.thread_time`): tasks
running side by side on threads are not charged one another's work, and a
compiled kernel that releases the GIL is charged to the thread that called it.
"""

import contextlib
import time

__all__ = []


class StageClock:
    """CPU-seconds by stage name, written into ``seconds`` (a dict, ``<name>_s``
    keys).  A stage entered inside another is charged to itself only: the
    outer one pauses meanwhile, so the stages add up to the time spent."""

    def __init__(self, seconds=None):
        self.seconds = {} if seconds is None else seconds
        self._stack = []
        self._since = 0.0

    def _charge(self, now):
        key = f"{self._stack[-1]}_s"
        self.seconds[key] = self.seconds.get(key, 0.0) + now - self._since
        self._since = now

    @contextlib.contextmanager
    def stage(self, name):
        now = time.thread_time()
        if self._stack:
            self._charge(now)
        self._stack.append(name)
        self._since = now
        try:
            yield
        finally:
            self._charge(time.thread_time())
            self._stack.pop()


class _Untimed:
    """A clock that records nothing (for solvers run outside a timed stage)."""

    @staticmethod
    def stage(name):
        return contextlib.nullcontext()


UNTIMED = _Untimed()
