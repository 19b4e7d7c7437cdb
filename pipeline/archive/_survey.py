"""``rsmb survey``: a night of georeferenced captures against a reference mosaic.

DESIGN.md, "Survey archives" (a contract: scripts read it).  The captures the
glob finds are paired with the reference set by footprint and run through
:func:`detect`, several at once on one runner (one executor or cluster for the
night, so the cores stay busy while a capture finishes its tail; a capture's
products and report are written outside the ``parallel`` captures being
detected, so the next capture's tasks run meanwhile; in a night with reports,
by a process of their own: :mod:`pipeline.archive._products`).  Per capture,
under ``OUT_DIR/captures/<path relative to the glob's fixed prefix>/`` (the
capture's file name, suffix included, is its folder's: names mirror the
captures' tree, where no file holds another, so ``a.tif`` and ``a/b.tif``,
``a.tif`` and ``a.png``, or a capture named like the survey's own
``nights/``, cannot share a folder): ``changes.zarr``, ``changes.gpkg``
(layer ``changes``), the masks and score as Cloud-Optimised GeoTIFFs,
``thumbnail.png`` and ``report/``.  A folder is built under
``OUT_DIR/.partial/`` and renamed into place, so it appears complete or not
at all.  The driver holds the survey's lock (``ledger.sqlite.lock``) before it
touches anything in ``OUT_DIR``: a second night on the folder is refused and
changes nothing.  A folder of the earlier layout (capture folders beside the
ledger, without suffix) is moved into this one on first use
(:func:`_migrate_layout`).  The ledger (:mod:`pipeline.archive._ledger`), written by this driver only,
decides what runs: a capture done with the same key is skipped, a failed one
retried, a changed one redone.  One bad capture never stops the night: it is
``failed`` with a one-line reason and the others finish.
"""

import contextlib
import dataclasses
import datetime as _dt
import glob
import json
import logging
import os
import shutil
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

from rsmb import ops
from rsmb import tiles
from rsmb.ops import InputError, ParameterError, RSMBError
from rsmb.ops._errors import one_line

from ..detection._detect import detect
from ..detection._plan import VERSION, DetectConfig, whole_image_side
from ._history import MASK_NAME
from ._ledger import LEDGER_NAME, SETTLE, FileStat, Ledger, RunKey
from ._products import Here, ProductProcess, failure_reason
from .._scheduler import WORKER_TIMEOUT, check_scheduler, open_runner

__all__ = ["SurveyResult", "CaptureResult", "survey", "find_captures", "check_output"]

log = logging.getLogger("rsmb")

PARTIAL = ".partial"
#: The folder of the captures' folders inside a survey's folder.
CAPTURES = "captures"
#: Default tile side of a survey: a capture of about a megapixel is one tile,
#: so it pays the per-tile start once; the night's concurrency, not the tiles
#: of one capture, keeps the cores busy.
SURVEY_TILE = 1024
#: Seconds a stopped night waits for its running captures before it abandons them.
GRACE = 5.0
_WILDCARDS = set("*?[")


@dataclass(frozen=True)
class CaptureResult:
    """One capture of a night (an entry of ``--json``'s ``captures``).

    Attributes
    ----------
    capture : str
        The capture's path.
    status : {"done", "skipped", "failed", "would run", "would skip"}
        The last two with ``dry_run``.
    reason : str
        Why it ran (new, retried, what changed), was skipped or failed (one
        line).
    reference : list of str
        The reference files read for it (under its footprint).
    output : str or None
        Its folder.
    vectors : str or None
        Its ``changes.gpkg``.
    changes : int or None
        Changes (polygons) found.
    changed_m2 : float or None
        Their area, square metres.
    seconds : float
    """

    capture: str
    status: str
    reason: str
    reference: list = field(default_factory=list)
    output: str | None = None
    vectors: str | None = None
    changes: int | None = None
    changed_m2: float | None = None
    seconds: float = 0.0


@dataclass(frozen=True)
class SurveyResult:
    """A night: its captures and counts (the ``--json`` output), and where its
    summary and index were written."""

    captures: list
    done: int
    skipped: int
    failed: int
    night: str | None = None
    summary: str | None = None
    index: str | None = None
    interrupted: bool = False

    def as_dict(self):
        """The DESIGN.md ``--json`` shape."""
        return {"captures": [tiles.jsonable(c) for c in self.captures], "done": self.done,
                "skipped": self.skipped, "failed": self.failed}


def _fixed_prefix(pattern):
    """The leading directories of a glob pattern that hold no wildcard."""
    parts = Path(pattern).parts
    fixed = []
    for part in parts[:-1]:
        if _WILDCARDS & set(part):
            break
        fixed.append(part)
    return Path(*fixed) if fixed else Path(".")


def find_captures(pattern, out_dir):
    """Files the glob ``pattern`` finds (``**`` recurses), sorted, outside
    ``out_dir``: a list of (absolute path, its path relative to the
    pattern's fixed prefix, suffix kept: the name of its folder under
    ``OUT_DIR/captures/``).  A file is outside ``out_dir`` by its resolved
    path (symlinks and ``..`` followed): a survey never takes its own
    products for captures, however the glob reaches them."""
    prefix = os.path.abspath(_fixed_prefix(pattern))
    out = os.path.realpath(out_dir)
    found, folders = [], {}  # folder -> its real path: one realpath per folder, not per file
    for name in sorted(glob.glob(os.fspath(pattern), recursive=True)):
        path = os.path.abspath(name)
        folder, base = os.path.split(path)
        if folder not in folders:
            folders[folder] = os.path.realpath(folder)
        real = os.path.realpath(path) if os.path.islink(path) else os.path.join(folders[folder], base)
        if real == out or real.startswith(out + os.sep) or not os.path.isfile(path):
            continue
        found.append((Path(path), Path(os.path.relpath(path, prefix))))
    return found


def _check_invocation(references, captures, out_dir, scheduler):
    """Bad invocations (exit 2) before anything runs or is written: no glob,
    references that are missing, unreadable or not georeferenced, an output
    folder that cannot be written or that holds other things than a survey (a
    folder is a survey's when it has a ledger), a bad scheduler."""
    if not os.fspath(captures).strip():
        raise ParameterError(f"captures: expected a glob pattern of the night's captures, got {captures!r}")
    prefix = _fixed_prefix(captures)
    if not prefix.is_dir():  # a mistyped or unmounted folder is not an empty night
        raise InputError(f"--captures: {prefix} is not a folder (the glob {os.fspath(captures)!r} searches it); "
                         f"a night of no captures needs an existing, empty folder")
    if not references:
        raise InputError("REFERENCE: expected at least one georeferenced reference file")
    for path in references:
        shape, geo = tiles.probe_header(path)
        if not tiles.is_georeferenced(geo):
            raise InputError(f"{path}: the reference is not georeferenced (a survey pairs captures by footprint)")
    check_output(out_dir)
    check_scheduler(scheduler)


def check_output(out_dir, *, option="-o"):
    """Raise :class:`InputError` unless ``out_dir`` can be a survey's folder:
    new, empty, or an earlier survey's (it holds ``ledger.sqlite``), in a
    place that can be written.  A folder of other files is refused: a survey
    never writes its captures' folders among someone else's files.  The
    message calls the folder ``option``."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: {option} must be a directory, this is a file")
    if out.is_dir() and not _is_survey(out) and any(out.iterdir()):
        raise InputError(f"{out}: {option} is a folder of other files, not a survey's (no {LEDGER_NAME}); give a "
                         f"new or empty folder, or the folder of earlier nights")
    if not _is_survey(out):  # an earlier night's folder is proven by taking its lock, which writes nothing new
        tiles.check_writable(out / LEDGER_NAME)


def _is_survey(out):
    """A survey's folder: it holds the ledger, or the lock a night takes
    before creating it."""
    return (out / LEDGER_NAME).exists() or (out / f"{LEDGER_NAME}.lock").exists()


def _parameters(config, shape=None):
    """The parameters of a capture's ledger key: ``config`` as detect runs it
    on a capture of ``shape`` ('auto' steps and half-widths resolved for its
    camera), so that equal runs key alike however they were asked for
    (:func:`survey`'s default config, the command's 'auto')."""
    if shape is not None:
        camera = ops.Camera.for_shape(shape, focal=config.focal)
        config = dataclasses.replace(config, registration=config.registration.resolved(camera))
    return tiles.jsonable({"config": config, "kernels": ops.KERNEL_VERSION})


def survey(references, captures, out_dir, *, config=None, scheduler="threads", workers=None, parallel=None,
           dry_run=False, worker_timeout=WORKER_TIMEOUT, report=True, settle=SETTLE, stop=None):
    """Run a night: every capture the glob ``captures`` finds, against the
    georeferenced reference set ``references`` (DESIGN.md, "Survey archives").

    Parameters
    ----------
    references : sequence of str or path-like
        Georeferenced reference files (a mosaic: the first file with data wins).
    captures : str
        A glob pattern (``**`` recurses).
    out_dir : str or path-like
        The survey's folder: one folder per capture, ``ledger.sqlite``,
        ``nights/<UTC time>.json`` and ``index.html``.  New, empty, or the
        folder of earlier nights (:func:`check_output`).
    config : DetectConfig, optional
        Its ``tile`` defaults to :data:`SURVEY_TILE`.
    scheduler, workers, worker_timeout
        As for :func:`detect`; one runner serves the whole night.
    parallel : int, optional
        Captures detected at once; default one more than the cores of this
        machine.  A capture's products and report (its own Python work) are
        written outside that count, beside the next captures' detection, so
        the workers always have tasks while captures finish.
    dry_run : bool
        Say what would run and why; write nothing.
    report : bool
        Write each capture's ``report/``.
    settle : float
        Seconds: a capture modified less long ago is still being written and
        waits for the next night (``skipped``, reason ``still being
        written``; nothing recorded).  A capture whose size or modification
        time changes during its detection is not recorded done (``failed``,
        retried next night).
    stop : threading.Event, optional
        Set it to stop the night (the command sets it on SIGINT and SIGTERM):
        queued captures are not run, running ones have a few seconds
        (:data:`GRACE`) to finish and are abandoned after, every finished one
        is recorded done, and the summary and index are written.  The result's
        ``interrupted`` is then True.

    Returns
    -------
    SurveyResult

    Raises
    ------
    InputError, ParameterError
        A bad invocation, before anything runs (a bad capture is not one: it
        is ``failed`` in the result).
    """
    config = config or DetectConfig()
    fit_tile = config.tile is None  # not asked for: fitted to a capture smaller than it, without a note
    if fit_tile:  # captures run side by side: one large tile each keeps the cores busy
        config = dataclasses.replace(config, tile=SURVEY_TILE)
    references = [os.path.abspath(r) for r in tiles.expand_references(references)]
    out = Path(out_dir).absolute()
    _check_invocation(references, captures, out, scheduler)
    found = find_captures(captures, out)
    night = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H-%M-%SZ")
    log.info("survey: %d capture(s) found by %s, %d reference file(s)", len(found), captures, len(references))
    if dry_run:
        return _dry_run(found, out, references, config, settle)
    out.mkdir(parents=True, exist_ok=True)
    with Ledger(out / LEDGER_NAME) as ledger:  # its lock first: nothing in the folder is touched before
        shutil.rmtree(out / PARTIAL, ignore_errors=True)  # folders a killed night left half-built
        _migrate_layout(out, ledger)
        halt = stop if isinstance(stop, _Stop) else _Stop(stop)
        observed = {}  # each placed capture's mask, read for the history as the capture ends
        halt.listening = True  # a first signal from here on stops the night in order, its end included
        try:
            results = _night(ledger, found, out, references, night, config, settle,
                             dict(scheduler=scheduler, workers=workers, parallel=parallel,
                                  worker_timeout=worker_timeout, report=report, observed=observed,
                                  fit_tile=fit_tile), halt)
            result = SurveyResult(results, *(sum(r.status == s for r in results)
                                             for s in ("done", "skipped", "failed")),
                                  night=night, interrupted=halt.event.is_set())
            summary = _write_night(out, result)
            # the runner is closed: no task of a failed capture can still be writing its scratch
            shutil.rmtree(out / PARTIAL, ignore_errors=True)
            from ._night_end import close_night
            from ._survey_html import write_index

            record = close_night(out, ledger, night, references, observed=observed)  # history, STAC catalog, map
            index = write_index(out, ledger.captures(), prefix=_fixed_prefix(captures).absolute(), record=record)
        finally:
            halt.listening = False  # what runs after the night (a workflow's next step) is interrupted at once
    return dataclasses.replace(result, summary=str(summary), index=str(index), interrupted=halt.event.is_set())


class _Fingerprints:
    """sha256 and shape of files, read once and remembered in the ledger by
    size, modification time and inode (:class:`FileStat`): a file whose
    ``stat`` is unchanged is not read again.  New fingerprints are kept in
    :attr:`new` until :meth:`save`."""

    def __init__(self, ledger):
        self.ledger = ledger
        self.known = ledger.file_stats() if ledger is not None else {}
        self.new = []
        self.hashed = 0  # files read tonight

    def get(self, path, st=None):
        """(sha256, shape) of ``path``; ``st`` its ``os.stat`` if known."""
        path = str(path)
        try:
            st = st or os.stat(path)
        except OSError as exc:
            raise InputError(f"{path}: cannot read file ({one_line(exc)})") from None
        known = self.known.get(path)
        if known is not None and known.same_file(st):
            return known.sha256, known.shape
        info = tiles.probe_image(path)
        self.hashed += 1
        try:
            after = os.stat(path)
        except OSError:
            after = None
        stat = FileStat(path, st.st_size, st.st_mtime_ns, st.st_ino, info.sha256, tuple(info.shape))
        if after is not None and stat.same_file(after):  # a file that changed while read is not remembered
            self.known[path] = stat
            self.new.append(stat)
        return info.sha256, tuple(info.shape)

    def save(self):
        if self.ledger is not None and not self.ledger.readonly:
            self.ledger.remember_files(self.new)
        self.new = []


def _decide_all(ledger, found, references, config, settle):
    """Every capture's fate tonight, in the order found: a list of (capture,
    name, what, detail) with what one of ``wait`` (detail: the reason),
    ``fail`` (an RSMBError), ``skip`` (the Decision) and ``run`` ((RunKey,
    Decision, its stat)).  A night with nothing new reads no file: a stat per
    capture and reference (:class:`_Fingerprints`)."""
    prints = _Fingerprints(ledger)
    reference_shas = [prints.get(r)[0] for r in references]
    history = ledger.history_by_capture() if ledger is not None else {}
    now, fates, parameters = time.time(), [], {}  # parameters by image shape: resolved once per shape
    for capture, name in found:
        try:
            st = os.stat(capture)
            age = now - st.st_mtime
            if age < settle:
                fates.append((capture, name, "wait", f"still being written (modified {max(age, 0.0):.0f} s ago, "
                                                     f"within --settle {settle:g} s): waits for the next night"))
                continue
            sha, shape = prints.get(capture, st)
            if shape not in parameters:
                parameters[shape] = _parameters(config, shape)
            key = RunKey.build(sha, reference_shas, references, parameters[shape], VERSION)
        except RSMBError as exc:  # unreadable: the ledger still hears of it
            fates.append((capture, name, "fail", (exc, RunKey.build("unreadable", reference_shas, references,
                                                                     _parameters(config), VERSION))))
            continue
        decision = Ledger.decide_from(history.get(str(capture), []), key)
        fates.append((capture, name, "skip" if decision.action == "skip" else "run", (key, decision, st)))
    prints.save()
    log.info("survey: %d file(s) read and hashed, the others known by their stat", prints.hashed)
    return fates


def _dry_run(found, out, references, config, settle):
    """What would run, and why (new, changed, retry, settling, skip):
    read-only (the ledger, if there is one; no fingerprint is saved)."""
    ledger = Ledger(out / LEDGER_NAME, readonly=True) if (out / LEDGER_NAME).exists() else None
    # a night running on the folder now: its running captures are not interrupted ones
    holder = tiles.lock_holder(out / f"{LEDGER_NAME}.lock")
    if holder:
        log.warning("survey: %s: a night is running on this folder now (%s): this dry run shows what a night "
                    "started after it would do", out, holder)
    results = []
    try:
        for capture, name, what, detail in _decide_all(ledger, found, references, config, settle):
            if what == "wait":
                results.append(CaptureResult(str(capture), "would wait", detail))
            elif what == "fail":
                results.append(CaptureResult(str(capture), "would run", f"and fail: {one_line(detail[0])}"))
            else:
                decision = detail[1]
                reason = decision.reason
                if holder and decision.previous is not None and decision.previous.status == "running":
                    reason = f"running now in the night on this folder ({holder}), started {decision.previous.started}"
                results.append(CaptureResult(str(capture), f"would {what}", reason,
                                             output=str(out / CAPTURES / name)))
    finally:
        if ledger:
            ledger.close()
    return SurveyResult(results, 0, sum(r.status == "would skip" for r in results), 0)


def _night(ledger, found, out, references, night, config, settle, run, stop):
    """Decide every capture, run those to run (:func:`_run_all`), record each
    in the ledger as it ends.  Returns CaptureResults in the order found."""
    results, todo = {}, []
    for capture, name, what, detail in _decide_all(ledger, found, references, config, settle):
        if what == "wait":  # nothing recorded: next night decides it afresh
            results[capture] = CaptureResult(str(capture), "skipped", detail)
            log.info("survey: %s: %s", name, detail)
        elif what == "fail":
            exc, key = detail
            results[capture] = _fail(ledger, ledger.start(str(capture), key, night=night), capture, exc, 0.0)
            log.error("survey: %s: failed before it ran: %s", name, results[capture].reason)
        elif what == "skip":
            decision = detail[1]
            previous = decision.previous.outputs
            results[capture] = CaptureResult(str(capture), "skipped", decision.reason, previous.get("reference", []),
                                             previous.get("output"), previous.get("vectors"),
                                             previous.get("changes"), previous.get("changed_m2"))
        else:
            key, decision, st = detail
            log.info("survey: %s: %s", name, decision.reason)
            todo.append((capture, name, ledger.start(str(capture), key, night=night), decision.reason, st))
    if todo:  # a night with nothing to run opens no scheduler (no cluster jobs, no connection)
        from ._survey_map import preload

        # the map at the night's end draws with matplotlib: imported now, beside the captures
        imports = threading.Thread(target=preload, name="rsmb-map-imports", daemon=True)
        imports.start()
        results.update(_run_all(ledger, todo, out, references, config, dict(run, imports=imports), stop))
        imports.join()
    return [results[capture] for capture, _ in found]


class _Stop:
    """How a night is stopped (SIGINT/SIGTERM through the command): ``event``
    is set by whoever stops it (``signum`` says why); the driver then cancels
    the queued captures, waits up to ``grace`` seconds for the running ones
    and abandons the rest (``abandoned`` set: they place nothing after)."""

    def __init__(self, event=None, grace=GRACE):
        self.event = event or threading.Event()
        self.abandoned = threading.Event()
        self.grace = grace
        self.signum = None
        self.listening = False  # a night is running that stops in order (else a signal interrupts at once)

    @property
    def why(self):
        import signal

        return signal.Signals(self.signum).name if self.signum else "a stop request"


def _run_all(ledger, todo, out, references, config, run, stop):
    """Run the captures of ``todo`` (``parallel`` at once on one runner) and
    record each in the ledger as it ends: capture -> CaptureResult.  When
    ``stop.event`` is set: queued captures are cancelled (``skipped``, their
    attempt closed ``failed``: interrupted), running ones get ``stop.grace``
    seconds to finish (done ones recorded as such), the others are abandoned
    (``failed``: interrupted).  The runner of an interrupted night is left to
    the process's exit (its tasks may still be running)."""
    results, total = {}, len(todo)
    cores = os.cpu_count() or 1
    parallel = run["parallel"] or cores + 1
    # a slot per capture being detected; the driver has threads to spare for
    # captures writing their products and report meanwhile
    slots = threading.Semaphore(parallel)
    stack = contextlib.ExitStack()
    runner = stack.enter_context(open_runner(run["scheduler"], workers=run["workers"], shared=True, progress=False,
                                             worker_timeout=run["worker_timeout"]))
    log.info("survey: %d capture(s) to run, %d at once, on %s", total, parallel, runner.describe())
    driver = ThreadPoolExecutor(parallel + cores + 1)
    # a night's reports (matplotlib: Python that holds the interpreter's lock) stall the other captures' tasks:
    # with them, the products are written by a process of their own when other captures run beside them
    products = (ProductProcess(run["imports"]).start() if run["report"] and total > 1
                else Here(run["report"], run["imports"]))
    stack.callback(products.close)
    interrupted = False
    try:
        futures = {driver.submit(_run_capture, capture, name, out, references, config, runner, products, slots,
                                 st, stop, run["observed"], run["fit_tile"]): (capture, name, run_id, why)
                   for capture, name, run_id, why, st in todo}
        pending, count, deadline = set(futures), 0, None
        while pending:
            if stop.event.is_set() and deadline is None:
                interrupted = True
                deadline = time.monotonic() + stop.grace
                pending -= _cancel_queued(ledger, futures, pending, stop, results)
            if deadline is not None and time.monotonic() >= deadline:
                _abandon(ledger, futures, pending, stop, results)
                runner.stop()  # their detections start no task more beside the night's end
                break
            done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
            for future in done:
                count += 1
                _record(ledger, futures[future], future, f"[{count}/{total}]", results, stop)
    except BaseException:
        driver.shutdown(wait=False, cancel_futures=True)
        stop.abandoned.set()
        runner.stop()
        products.kill()
        raise
    if interrupted:
        driver.shutdown(wait=False, cancel_futures=True)
        # the runner and its tasks end with the process: kept from the garbage collector, whose closing
        # of the runner's context would wait for its running tasks here
        _LEFT_RUNNING.append(stack)
        products.kill()  # the captures it could be writing are abandoned: nothing of theirs is placed
    else:
        driver.shutdown(wait=True)
        stack.close()
    return results


#: The runners of interrupted nights (their contexts), left open to the process's exit.
_LEFT_RUNNING = []


def _cancel_queued(ledger, futures, pending, stop, results):
    """A stopped night's captures still queued cancelled: each ``skipped``
    (it runs next night), its attempt closed ``failed``.  Returns the
    cancelled futures."""
    cancelled = {f for f in pending if f.cancel()}
    for future in cancelled:
        capture, name, run_id, why = futures[future]
        results[capture] = _not_run(ledger, run_id, capture, stop)
    log.warning("survey: %s: %d queued capture(s) cancelled, %d under way: those detecting get %g s to finish, "
                "those waiting for a slot are not run", stop.why, len(cancelled), len(pending) - len(cancelled),
                stop.grace)
    return cancelled


def _abandon(ledger, futures, pending, stop, results):
    """The captures still running when a stopped night's grace ran out: set
    abandoned (they place nothing after) and recorded ``failed``."""
    stop.abandoned.set()
    for future in pending:
        capture, name, run_id, why = futures[future]
        results[capture] = _fail(ledger, run_id, capture, InputError(
            f"{capture}: interrupted while running ({stop.why}): it runs again next night"), None)
    log.warning("survey: %d running capture(s) abandoned", len(pending))


def _not_run(ledger, run_id, capture, stop):
    """A capture the stopped night did not start: its attempt closed
    ``failed`` in the ledger, ``skipped`` in the night (it runs next night)."""
    ledger.finish(run_id, "failed", f"interrupted before it ran ({stop.why})")
    return CaptureResult(str(capture), "skipped", f"not run: the night was stopped ({stop.why}); it runs next night")


def _record(ledger, entry, future, progress, results, stop):
    """A finished capture's future recorded in the ledger and ``results``:
    ``done`` with its reason, or ``failed`` with its error; a
    :class:`~rsmb.ops.RunError` (every worker gone) ends the night."""
    capture, name, run_id, why = entry
    try:
        result = future.result()
    except ops.RunError:
        raise  # the night cannot go on (every worker gone): not one capture's fault
    except _NotStarted:  # waiting for a slot when the night was stopped: as a queued capture
        results[capture] = _not_run(ledger, run_id, capture, stop)
        return
    except Exception as exc:  # noqa: BLE001 - one bad capture never stops the night
        results[capture] = _fail(ledger, run_id, capture, exc, None)
        log.error("survey %s %s: failed: %s", progress, name, results[capture].reason)
        return
    result = dataclasses.replace(result, reason=why)
    ledger.finish(run_id, "done", why, tiles.jsonable(result))
    results[capture] = result
    log.info("survey %s %s: done in %.1f s, %d change(s)", progress, name, result.seconds, result.changes)


def _fail(ledger, run_id, capture, exc, seconds):
    reason = failure_reason(exc)
    ledger.finish(run_id, "failed", reason)
    return CaptureResult(str(capture), "failed", reason, seconds=seconds or 0.0)


def _run_capture(capture, name, out, references, config, runner, products, slots, st, stop, observed,
                 fit_tile=False):
    """One capture, built aside and renamed into place: its store, products,
    thumbnail and report.  Runs in a driver thread; its tasks on ``runner``;
    its detection holds one of ``slots`` (a semaphore), its products and
    report none.  A failure leaves nothing behind; so does a capture whose
    size or modification time now differs from ``st`` (its stat when it was
    hashed): it changed during its detection.  A placed capture's mask, read
    for the history here (beside the other captures' detection, not in the
    night's serial end), goes into ``observed`` by its final path.  With
    ``fit_tile`` (the survey's default tile, not asked for) a capture smaller
    than the tile runs as one tile of its size, without the note a tile
    asked for gives."""
    start = time.perf_counter()
    shape, header = tiles.probe_header(capture)
    if fit_tile:
        config = dataclasses.replace(config, tile=min(config.tile, whole_image_side(shape)))
    if not tiles.is_georeferenced(header):
        raise InputError(f"{capture}: not georeferenced (a survey pairs captures with the reference by footprint)")
    aside = out / PARTIAL / "building" / name
    shutil.rmtree(aside, ignore_errors=True)
    aside.mkdir(parents=True)
    try:
        folder = out / CAPTURES / name
        changes, area, mask, read = _build(capture, aside, folder, references, config, runner, products, slots, stop)
        _check_unchanged(capture, st)
        if stop.abandoned.is_set():  # the night gave up on it: it places nothing now
            raise InputError(f"{capture}: interrupted while running ({stop.why})")
        folder.parent.mkdir(parents=True, exist_ok=True)
        tiles.swap_into_place(aside, folder, overwrite=True)  # a capture redone replaces its folder
        if mask is not None:  # the same file, renamed with its folder
            observed[str(folder / MASK_NAME)] = mask
    finally:
        shutil.rmtree(aside, ignore_errors=True)
    return CaptureResult(str(capture), "done", "", list(read), str(folder), str(folder / "changes.gpkg"),
                         changes, area, time.perf_counter() - start)


def _check_unchanged(capture, st):
    """Raise :class:`InputError` when ``capture`` is no longer the file ``st``
    described (size, modification time, inode)."""
    try:
        now = os.stat(capture)
    except OSError as exc:
        raise InputError(f"{capture}: gone during its detection ({one_line(exc)}): not recorded") from None
    if (now.st_size, now.st_mtime_ns, now.st_ino) != (st.st_size, st.st_mtime_ns, st.st_ino):
        raise InputError(f"{capture}: modified during its detection (size or modification time changed): not "
                         f"recorded as done; it runs again next night")


def _build(capture, aside, folder, references, config, runner, products, slots, stop):
    """The capture's products in ``aside`` (to become ``folder``): returns its
    changes (polygons), their area, its mask read for the history (None
    when it could not be read now) and the reference files read.  The
    detection holds one of ``slots`` (a semaphore); a night stopped before it
    got one raises :class:`_NotStarted`.  What the folder holds beside the
    store is written by ``products`` (:class:`._products.ProductProcess`, or
    :class:`._products.Here`)."""
    store = aside / "changes.zarr"
    with _slot(slots, stop):
        summary = detect(references, capture, store, config=config, runner=runner)
    # the store records where it lives once the folder is in place
    tiles.update_attrs(store, {"summary": {**summary.as_dict(), "output": str(folder / "changes.zarr")}})
    # dated by the capture, not the clock: a capture redone gives the same file
    changes, area, mask = products.write(store, aside, os.stat(capture).st_mtime, capture)
    return changes, area, mask, tiles.open_result_store(store).attrs["pairing"].get("read", [])


class _NotStarted(Exception):
    """A capture whose detection had not started when the night was stopped."""


@contextlib.contextmanager
def _slot(slots, stop):
    """Hold one of ``slots`` (a semaphore) for a detection; raise
    :class:`_NotStarted` instead when ``stop.event`` is set before it is
    taken: a capture waiting for a slot is queued, not running."""
    while not slots.acquire(timeout=0.2):
        if stop.event.is_set():
            raise _NotStarted
    try:
        if stop.event.is_set():
            raise _NotStarted
        yield
    finally:
        slots.release()


def _write_night(out, result):
    """``OUT_DIR/nights/<night>.json``: the night's summary (as ``--json``)."""
    nights = out / "nights"
    nights.mkdir(exist_ok=True)
    path = nights / f"{result.night}.json"
    tmp = path.with_suffix(".json.partial")
    tmp.write_text(json.dumps(result.as_dict(), indent=2))
    os.replace(tmp, path)
    return path


#: Names of a survey's own files and folders: a capture folder of the old
#: layout that took one of them (``nights.tif`` -> ``nights/``) is not moved.
_OWN = {"nights", "index.html", LEDGER_NAME, CAPTURES, PARTIAL, "stac", "changes.gpkg", "map.png"}


def _migrate_layout(out, ledger):
    """Move the capture folders of the earlier layout (``OUT_DIR/<path, no
    suffix>/``) to ``OUT_DIR/captures/<path with the capture's suffix>/`` and
    record the new paths in the ledger.  Idempotent and cheap when there is
    nothing to move (one query).  A done capture whose old folder is missing,
    nested in a survey's own folder (``nights/`` ...) or whose new place is
    taken is marked failed (reason says so): it is redone tonight."""
    moved = 0
    latest = {r.capture: r for r in ledger.runs(status="done", outside=str(out / CAPTURES))}
    old = [(r, Path(r.outputs["output"])) for r in latest.values()
           if r.outputs.get("output") and not Path(r.outputs["output"]).is_relative_to(out / CAPTURES)]
    # deepest first: a/b's folder leaves a/ before a/ moves
    for row, folder in sorted(old, key=lambda item: -len(item[1].parts)):
        if not folder.is_relative_to(out) or folder == out:
            continue  # the survey folder was moved since: its paths are not ours to rewrite
        relative = folder.relative_to(out)
        target = out / CAPTURES / relative.with_name(relative.name + Path(row.capture).suffix)
        if relative.parts[0] in _OWN or not (folder / "changes.zarr").is_dir() or target.exists():
            ledger.undo_done(row.capture, f"not moved to the layout of {CAPTURES}/ (its old folder {relative} "
                                          f"is missing, a survey's own or its new place taken): redo")
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(folder, target)
        parent = folder.parent
        while parent != out and not any(parent.iterdir()):  # the old tree's emptied folders leave too
            parent.rmdir()
            parent = parent.parent
        outputs = {**row.outputs, "output": str(target), "vectors": str(target / "changes.gpkg")}
        ledger.amend(row.id, outputs=outputs)
        _restamp_store(target / "changes.zarr")
        moved += 1
    if moved:
        log.info("survey: %d capture folder(s) moved to %s/ (the layout where names cannot collide)", moved,
                 out / CAPTURES)


def _restamp_store(store):
    """The store's summary names where it lives now."""
    try:
        summary = dict(tiles.open_result_store(store).attrs.get("summary", {}))
        tiles.update_attrs(store, {"summary": {**summary, "output": str(store)}})
    except Exception:  # noqa: BLE001 - a store that cannot be read still moved; its report says where it was
        log.warning("survey: %s: could not record its new place in the store", store)
