"""A night's capture reports, written by a process of their own.

A report is the driver's own Python work (matplotlib's figures, the page):
written in a driver thread, it holds the interpreter's lock that the night's
tile tasks need between their compiled kernels, and they wait.  A child
process writes them instead; the driver thread that asked waits without
holding the lock.

Rules (README, ``rsmb survey``):

- One report at a time (one child): the report a dying child was writing is
  the one that failed.  A report whose child died (killed, crashed) is
  written again once, into an emptied folder, by a new child; a second death
  fails the capture (``failed``, the reason says so).  Nothing waits forever:
  a dead child breaks the wait at once.
- The child ignores SIGINT (a terminal's Ctrl-C reaches the whole process
  group: the night, not its child, decides what stops), ends when the night's
  process is gone (it checks its parent twice a second), and is killed and
  waited for by :meth:`ReportProcess.close` when a night stops (running
  captures abandoned): no report is written after the night gave up on its
  capture, and no process outlives the night.
- A report is written into the capture's folder built aside: it is placed
  with its capture or not at all.
- A direct child, waited for when it ends: its CPU time counts as the
  night's process's (``RUSAGE_CHILDREN``), as a thread's did.  A new
  interpreter running :func:`_serve`: no program's main module is run again
  in it (as multiprocessing's ``spawn`` would), and no fork of a process
  whose libraries run threads (OpenCV's, BLAS's pools: a fork can inherit
  their locks held).  Requests and answers are pickled over a socket pair.
"""

import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection

from rsmb.ops import RSMBError

__all__ = ["ReportProcess", "ReportProcessDied", "ReportsClosed"]

log = logging.getLogger("rsmb")

#: Seconds between the child's checks that the night's process is still there.
PARENT_CHECK = 0.5


class ReportProcessDied(RSMBError, RuntimeError):
    """The child writing a capture's report ended abruptly, twice."""


class ReportsClosed(RSMBError, RuntimeError):
    """A report was asked for (or was being written) when the night stopped."""


def _write_report(store, out_dir):
    """What the child runs for one capture (module-level: sent by reference)."""
    from ..report._report import write_report

    write_report(store, out_dir)


class _Child:
    """The child process (a new interpreter running :func:`_serve`) and our
    end of its socket."""

    def __init__(self):
        ours, theirs = socket.socketpair()
        self.conn = Connection(ours.detach())
        # it finds rsmb where this process found it (a library user's sys.path included)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p and os.path.isdir(p))}
        serve = f"from {__name__} import _serve; _serve({theirs.fileno()}, {os.getpid()})"
        self._proc = subprocess.Popen([sys.executable, "-c", serve], pass_fds=(theirs.fileno(),), env=env,
                                      stdin=subprocess.DEVNULL)
        theirs.close()  # the child's now: its death ends our reads

    @property
    def pid(self):
        return self._proc.pid

    def end(self, *, kill):
        """The child ended (killed first with ``kill``, else asked to by
        closing its requests) and waited for (no zombie); returns its exit code."""
        if kill:
            self._proc.kill()
        self.conn.close()
        try:
            return self._proc.wait(timeout=None if kill else 60)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            return self._proc.wait()


class ReportProcess:
    """Capture reports written by one child process, one at a time.

    :meth:`write` is called from the night's driver threads; :meth:`close`
    ends the child (``kill=True``: at once, for a night that stops)."""

    def __init__(self):
        self._child = None
        self._closed = False
        self._guard = threading.Lock()  # the child, replaced when one dies
        self._one = threading.Lock()  # one report at a time

    def _current(self):
        with self._guard:
            if self._closed:
                raise ReportsClosed("the night stopped: no report is written")
            if self._child is None:  # on the first report: a night whose captures all fail starts none
                self._child = _Child()
                log.debug("survey: reports written by a child process (pid %d)", self._child.pid)
            return self._child

    def _end(self, child, *, kill):
        with self._guard:
            if self._child is child:
                self._child = None
        return child.end(kill=kill)

    def write(self, store, out_dir):
        """Write the report of ``store`` into ``out_dir`` (new or empty) in
        the child; returns when it is written.  Raises what ``write_report``
        raised; :class:`ReportProcessDied` when the child died twice on it;
        :class:`ReportsClosed` when the night stopped."""
        with self._one:
            for attempt in (1, 2):
                child = self._current()
                try:
                    child.conn.send((_write_report, (os.fspath(store), os.fspath(out_dir))))
                    ok, value = child.conn.recv()  # waits without the interpreter's lock
                except (EOFError, OSError):  # the child is gone
                    code = self._end(child, kill=True)
                    if self._closed:
                        raise ReportsClosed("the night stopped while the report was written") from None
                    shutil.rmtree(out_dir, ignore_errors=True)  # what the dead child had written
                    log.warning("survey: %s: the report process ended abruptly (exit %s; attempt %d of 2)", store,
                                code, attempt)
                    continue
                if not ok:
                    raise value
                return value
        raise ReportProcessDied(f"{store}: the process writing its report ended abruptly twice (killed or "
                                f"crashed): not recorded; it runs again next night")

    def close(self, *, kill=False):
        """End the child: after the reports asked for (``kill=False``), or at
        once (``kill=True``: the report being written is lost with its
        capture's folder aside).  Either way the child is waited for."""
        with self._guard:
            self._closed = True
            child = self._child
        if child is not None:
            self._end(child, kill=kill)


def _serve(fd, parent):
    """The child: requests (a function and its arguments) from the socket
    ``fd``, answered ``(True, result)`` or ``(False, exception)``; ends when
    the night closes its end, or when ``parent`` (the night's pid) is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the night's to handle
    threading.Thread(target=_watch_parent, args=(parent,), name="rsmb-parent-watch", daemon=True).start()
    from .._scheduler import configure_process
    from ..report import _report  # noqa: F401 - loaded before the first request

    configure_process()
    conn = Connection(fd)
    while True:
        try:
            func, args = conn.recv()
        except EOFError:
            return
        try:
            answer = (True, func(*args))
        except Exception as error:  # noqa: BLE001 - sent back, raised in the night's thread
            answer = (False, error)
        try:
            conn.send(answer)  # pickled whole before anything is sent
        except Exception:  # noqa: BLE001 - an answer that does not pickle goes back as text
            conn.send((False, RuntimeError(f"{type(answer[1]).__name__}: {answer[1]}")))


def _watch_parent(parent):
    while os.getppid() == parent:
        time.sleep(PARENT_CHECK)
    os._exit(1)  # the night is gone: nothing would place this report
