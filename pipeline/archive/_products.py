"""What a survey capture's folder holds beside its store, written from the
store after its detection (:func:`write_capture_products`): the ground-frame
rasters as Cloud-Optimised GeoTIFFs, ``changes.gpkg``, ``thumbnail.png`` and
``report/``; in a night with reports, by a process of its own.

A report is matplotlib's figures: about half a second of Python a capture
that holds the interpreter's lock.  Written by a driver thread of the night's
process, it stalls the Python of every other thread there: the captures' tile
tasks between their compiled kernels, zarr's I/O threads, the other drivers.
:class:`ProductProcess` writes a capture's products in one child process
instead (a Python of its own, started with the night, so that its imports run
beside the first captures' detection), one capture at a time.  Without
reports, the rest (mostly GDAL's calls, which let go of the lock) gains
nothing there and is written by the driver threads (:class:`Here`).

The child is started without multiprocessing (which would import the caller's
``__main__`` again) and in a session of its own: a Ctrl-C at the terminal
reaches the night only, which kills the child when it stops (the captures it
could be writing are abandoned, nothing of theirs is placed).  The child says
it is ready once its modules are imported, then reads one request per line on
its stdin (JSON) and answers one line on a pipe of its own: the changes found,
their area and the mask as the history reads it (:func:`observe`, geometries
as WKB), or the error's one-line reason as the night records it
(:func:`failure_reason`).  It ends when its stdin closes: at the night's end,
or when the night's process ends in any way.
"""

import json
import logging
import os
import subprocess
import sys
import threading
from pathlib import Path

from rsmb import tiles
from rsmb.ops import InputError, RSMBError
from rsmb.ops._errors import one_line

__all__ = ["Here", "ProductProcess", "failure_reason", "observe", "write_capture_products"]

log = logging.getLogger("rsmb")

#: Seconds the night's end waits for the child to finish its last capture and
#: exit before it is killed.
CLOSE_TIMEOUT = 60.0


def write_capture_products(store, folder, last_change, report=True):
    """Write a capture's products from its finished ``store`` into ``folder``:
    the ground-frame COGs (the reference grid on the capture's nominal
    transform), ``changes.gpkg`` (dated ``last_change``, a POSIX time),
    ``thumbnail.png`` and, with ``report``, ``report/``.

    Returns
    -------
    (int, float)
        The changes (polygons) written and their area, square metres.
    """
    from ..detection._outputs import write_products
    from ._survey_html import write_thumbnail

    store, folder = Path(store), Path(folder)
    group = tiles.open_result_store(store)
    geo = tiles.GeoInfo.from_attrs(group.attrs.asdict())
    write_products(store, folder, geo)
    features = tiles.change_polygons(group["change_mask_reference"], group["change_score_reference"], geo)
    tiles.write_changes_gpkg(folder / "changes.gpkg", features, geo.crs, last_change=last_change)
    write_thumbnail(group, folder / "thumbnail.png")
    if report:
        from ..report._report import write_report

        write_report(store, folder / "report")
    return len(features), float(sum(f.area_m2 for f in features))


def observe(folder):
    """:func:`._history.read_observation` of the ground-frame mask the
    products placed in ``folder``, for the history as the capture ends, or
    None when it cannot be read now (the night's end reads it again and
    reports what it finds)."""
    from ._history import MASK_NAME, read_observation

    try:
        return read_observation(Path(folder) / MASK_NAME)
    except Exception:  # noqa: BLE001 - the history step owns this file's errors
        return None


def failure_reason(exc):
    """The one line a night records for a capture that failed with ``exc``:
    an rsmb error's own message, else its type and message."""
    return one_line(exc) if isinstance(exc, RSMBError) else f"{type(exc).__name__}: {one_line(exc)}"


class Here:
    """:class:`ProductProcess`'s :meth:`write`, :meth:`close` and
    :meth:`kill` in the calling thread (a night without reports, or of one
    capture: nothing of its Python to take out of the night's process)."""

    def __init__(self, report=True, imports=None):
        self.report = report
        self.imports = imports

    def write(self, store, folder, last_change, capture):
        """The products of ``store`` in ``folder`` (:func:`write_capture_products`)
        for ``capture`` (its path, in messages): returns their changes, area
        and :func:`observe`.  A report drawn here waits for ``imports`` (the
        night's thread importing matplotlib, :func:`._survey_map.preload`):
        two threads never import matplotlib at once (a package whose modules
        import each other can be seen half-initialised by the second)."""
        if self.report and self.imports is not None:
            self.imports.join()
        return (*write_capture_products(store, folder, last_change, self.report), observe(folder))

    def close(self):
        pass

    def kill(self):
        pass


class ProductProcess(Here):
    """:func:`write_capture_products` in a child process, started with the
    night (:meth:`start`: it imports its modules while the first captures are
    detected), one capture at a time.

    :meth:`write` blocks its thread until the capture's products are written
    and raises :class:`~rsmb.ops.InputError` with the reason when that failed.
    A child that cannot be started, or dies before it is ready, leaves the
    products to the night's process (a warning says so once); a child that
    dies while it writes a capture's products fails that capture (it runs
    again next night: what was written is unknown) and leaves the next ones
    to the night's process.  :meth:`kill` ends it at once (a stopped night:
    the capture it was writing is abandoned); then every :meth:`write`
    raises."""

    def __init__(self, imports=None):
        super().__init__(report=True, imports=imports)
        self._lock = threading.Lock()
        self._child = None
        self._answers = None
        self._ready = False
        self._killed = False

    def start(self):
        """Start the child; returns self."""
        read = write = None
        try:
            read, write = os.pipe()
            level = logging.getLogger("rsmb").getEffectiveLevel()
            # -P: the working directory does not shadow rsmb's modules
            self._child = subprocess.Popen(
                [sys.executable, "-P", "-c", f"from {__name__} import serve; serve({write}, {level}, {os.getpid()})"],
                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, pass_fds=(write,), start_new_session=True,
                text=True)
            self._answers = os.fdopen(read, "r", encoding="utf-8")
        except Exception as exc:  # noqa: BLE001 - the night's process writes the products instead
            if read is not None and self._answers is None:
                os.close(read)
            self._give_up(f"cannot start it ({one_line(exc)})")
        finally:
            if write is not None:
                os.close(write)
        return self

    def write(self, store, folder, last_change, capture):
        with self._lock:
            if self._killed:
                raise InputError(f"{capture}: the night stopped before its products were written")
            if self._child is not None and not self._ready:
                self._ready = self._answer() == {"ready": True}
                if not self._ready:
                    self._give_up(f"it ended before it was ready (exit code {self._end()})")
            if self._child is not None:
                answer = self._ask({"store": str(store), "folder": str(folder), "last_change": last_change})
                if answer is None:
                    code = self._end()
                    if self._killed:
                        raise InputError(f"{capture}: the night stopped while its products were written")
                    self._give_up(f"it ended (exit code {code}) while it wrote the products of {capture}")
                    raise InputError(f"{capture}: the products' process ended (exit code {code}) while it wrote "
                                     f"this capture's products: it runs again next night")
                if "reason" in answer:
                    raise InputError(answer["reason"])
                return answer["changes"], answer["area_m2"], _decoded(answer["observation"])
        return super().write(store, folder, last_change, capture)  # no child

    def close(self):
        """End the child: its stdin closed once its last capture is written
        (killed when it never wrote one: it may still be importing)."""
        with self._lock:
            if self._child is not None and not self._ready:
                self._child.kill()
            self._end(CLOSE_TIMEOUT)

    def kill(self):
        """End the child now (a stopped night); every later :meth:`write`
        raises.  Does not wait for the capture being written."""
        self._killed = True
        child = self._child
        if child is not None:
            child.kill()  # a write() under way sees the end of its answers and fails that capture
            try:
                child.wait(5.0)
            except subprocess.TimeoutExpired:
                pass

    def _ask(self, request):
        """The child's answer to ``request``, or None when it ended."""
        try:
            self._child.stdin.write(json.dumps(request) + "\n")
            self._child.stdin.flush()
        except OSError:  # its stdin closed: it ended
            return None
        return self._answer()

    def _answer(self):
        """The child's next answer line, decoded, or None when it ended
        (a line cut short or that does not decode is its end too)."""
        try:
            line = self._answers.readline()
            return json.loads(line) if line.endswith("\n") else None
        except (OSError, ValueError):
            return None

    def _end(self, timeout=0.0):
        """The child's stdin and answers closed, the child reaped (killed
        after ``timeout`` seconds: at once by default, a child that stopped
        answering); returns its exit code."""
        child, self._child = self._child, None
        if child is None:
            return None
        for stream in (child.stdin, self._answers):
            try:
                stream.close()
            except OSError:
                pass
        try:
            return child.wait(timeout)
        except subprocess.TimeoutExpired:
            child.kill()
            return child.wait()

    def _give_up(self, why):
        log.warning("survey: the products' process: %s; the night's process writes the next captures' products", why)


def serve(answers_fd, level, night_pid):
    """The child's loop: ``{"ready": true}`` once its modules are imported,
    then one capture's products per request line on stdin, one answer line
    on ``answers_fd``; ends at the end of stdin.  ``night_pid``, the night's
    process, names it on its command line."""
    from .._scheduler import configure_process
    from ..cli import configure_output

    configure_process()  # a process that runs rsmb and nothing else, as the night's: one OpenCV and BLAS thread
    configure_output(level)
    answers = os.fdopen(answers_fd, "w", encoding="utf-8")
    from ..report import _report  # noqa: F401 - imported before the first capture asks

    def say(answer):
        answers.write(json.dumps(answer) + "\n")
        answers.flush()

    try:
        say({"ready": True})
        for line in sys.stdin:
            request = json.loads(line)
            try:
                changes, area = write_capture_products(request["store"], request["folder"], request["last_change"])
                answer = {"changes": changes, "area_m2": area, "observation": _encoded(observe(request["folder"]))}
            except Exception as exc:  # noqa: BLE001 - the night records it as the capture's failure
                answer = {"reason": failure_reason(exc)}
            say(answer)
    except BrokenPipeError:  # the night's process is gone
        return


def _encoded(observation):
    """An :func:`observe` as JSON: its geometries as WKB in hex."""
    if observation is None:
        return None
    import shapely

    cover, changes, crs = observation
    return [shapely.to_wkb(cover, hex=True), [shapely.to_wkb(c, hex=True) for c in changes], crs]


def _decoded(value):
    """The :func:`observe` that :func:`_encoded` made ``value`` of."""
    if value is None:
        return None
    import shapely

    cover, changes, crs = value
    return shapely.from_wkb(cover), [shapely.from_wkb(c) for c in changes], crs
