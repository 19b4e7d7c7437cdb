"""What a survey capture's folder holds beside its store, written from the
store after its detection (:func:`write_capture_products`): the ground-frame
rasters as Cloud-Optimised GeoTIFFs, ``changes.gpkg``, ``thumbnail.png`` and
``report/``; in a night with reports, by a process of its own.

A report is matplotlib's figures: about half a second of Python a capture
that holds the interpreter's lock.  Written by a driver thread of the night's
process, it stalls the Python of every other thread there: the captures' tile
tasks between their compiled kernels, zarr's I/O threads, the other drivers.
:class:`ProductProcess` writes a capture's products in one child process
instead (a Python of its own, started at the night's start and warm by the
first capture's turn), one capture at a time, in the order the drivers ask.
Without reports, the rest (mostly GDAL's calls, which let go of the lock)
gains nothing there and is written by the driver threads (:class:`Here`).

The child is started without multiprocessing (which would import the caller's
``__main__`` again) and in a session of its own (a Ctrl-C at the terminal
stops the night, whose driver decides what the child still does).  It reads
one request per line on its stdin (JSON) and answers one line on a pipe of its
own: the changes found, their area and the mask as the history reads it
(:func:`read_observation`, geometries as WKB), or the error's one-line reason
as the night records it.  It ends when its stdin closes: at the night's end, or when
the night's process ends in any way.
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

__all__ = ["Here", "ProductProcess", "read_observation", "write_capture_products"]

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


def read_observation(folder):
    """:func:`._history.read_observation` of the ground-frame mask the
    products placed in ``folder``, for the history as the capture ends, or
    None when it cannot be read now (the night's end reads it again and
    reports what it finds)."""
    from ._history import MASK_NAME, read_observation

    try:
        return read_observation(Path(folder) / MASK_NAME)
    except Exception:  # noqa: BLE001 - the history step owns this file's errors
        return None


class Here:
    """:class:`ProductProcess`'s :meth:`write` and :meth:`close` in the
    calling thread (a night of one capture: nothing runs beside its
    products)."""

    def __init__(self, report=True):
        self.report = report

    def write(self, store, folder, last_change):
        """The products of ``store`` in ``folder`` (:func:`write_capture_products`):
        returns their changes, area and :func:`read_observation`."""
        return (*write_capture_products(store, folder, last_change, self.report), read_observation(folder))

    def close(self):
        pass


class ProductProcess(Here):
    """:func:`write_capture_products` in a child process, started by the
    first capture that asks (a night whose captures all fail before their
    products starts none).

    :meth:`write` blocks its thread until the capture's products are written
    and raises :class:`~rsmb.ops.InputError` with the reason when that failed.
    A child that cannot be started or that dies is not started again: the
    night's process then writes the products itself (a warning says so
    once); the capture whose products the child was writing when it died
    fails (it runs again next night)."""

    def __init__(self):
        super().__init__(report=True)
        self._lock = threading.Lock()
        self._child = None
        self._answers = None
        self._tried = False

    def write(self, store, folder, last_change):
        with self._lock:
            if not self._tried:
                self._tried = True
                self._start()
            if self._child is not None:
                answer = self._ask({"store": str(store), "folder": str(folder), "last_change": last_change})
                if "reason" in answer:
                    raise InputError(answer["reason"])
                return answer["changes"], answer["area_m2"], _decoded(answer["observation"])
        return super().write(store, folder, last_change)  # no child

    def _start(self):
        read, write = os.pipe()
        level = logging.getLogger("rsmb").getEffectiveLevel()
        try:
            self._child = subprocess.Popen(
                [sys.executable, "-c", f"from {__name__} import serve; serve({write}, {level}, {os.getpid()})"],
                stdin=subprocess.PIPE, pass_fds=(write,), start_new_session=True, text=True)
        except OSError as exc:
            log.warning("survey: cannot start the products' process (%s): the night's process writes them",
                        one_line(exc))
        finally:
            os.close(write)
        if self._child is None:
            os.close(read)
        else:
            self._answers = os.fdopen(read, "r", encoding="utf-8")

    def close(self):
        """End the child: its stdin closed, its last capture finished."""
        with self._lock:
            child, self._child = self._child, None
        if child is None:
            return
        try:
            child.stdin.close()
        except OSError:
            pass
        try:
            child.wait(CLOSE_TIMEOUT)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        self._answers.close()

    def _ask(self, request):
        """The child's answer to ``request``.  A child gone before it
        answered (killed, out of memory) is not asked again, and the capture
        fails: what it wrote of the products is unknown."""
        try:
            self._child.stdin.write(json.dumps(request) + "\n")
            self._child.stdin.flush()
            line = self._answers.readline()
        except (OSError, ValueError):
            line = ""
        if line:
            return json.loads(line)
        self._child.kill()
        code = self._child.wait()
        self._answers.close()
        self._child = None
        log.warning("survey: the products' process ended (exit code %s): the night's process writes the next "
                    "captures' products", code)
        raise InputError(f"{request['store']}: the products' process ended (exit code {code}) while it wrote this "
                         f"capture's products: it runs again next night")


def serve(answers_fd, level, night_pid):
    """The child's loop: one capture's products per request line on stdin,
    one answer line on ``answers_fd``; ends at the end of stdin.
    ``night_pid``, the night's process, names it on its command line."""
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(message)s", stream=sys.stderr)
    logging.getLogger("rsmb").setLevel(level)
    answers = os.fdopen(answers_fd, "w", encoding="utf-8")
    sys.stdout = sys.stderr  # nothing but answers on the answers' pipe
    from ..report import _report  # noqa: F401 - imported before the first capture asks

    for line in sys.stdin:
        request = json.loads(line)
        try:
            changes, area = write_capture_products(request["store"], request["folder"], request["last_change"])
            answer = {"changes": changes, "area_m2": area, "observation": _encoded(read_observation(request["folder"]))}
        except Exception as exc:  # noqa: BLE001 - the night records it as the capture's failure
            reason = one_line(exc) if isinstance(exc, RSMBError) else f"{type(exc).__name__}: {one_line(exc)}"
            answer = {"reason": reason}
        try:
            answers.write(json.dumps(answer) + "\n")
            answers.flush()
        except BrokenPipeError:  # the night's process is gone
            return


def _encoded(observation):
    """A :func:`read_observation` as JSON: its geometries as WKB in hex."""
    if observation is None:
        return None
    import shapely

    cover, changes, crs = observation
    return [shapely.to_wkb(cover, hex=True), [shapely.to_wkb(c, hex=True) for c in changes], crs]


def _decoded(value):
    """The :func:`read_observation` that :func:`_encoded` made ``value`` of."""
    if value is None:
        return None
    import shapely

    cover, changes, crs = value
    return shapely.from_wkb(cover), [shapely.from_wkb(c) for c in changes], crs
