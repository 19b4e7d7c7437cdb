"""``rsmb detect``: tiled RSMB registration and change detection of one capture.

Registration runs one task per tile.  The stages that mostly move data (ingest,
labelling, masks) run per block of tiles, about 1024 px on a side (see
:func:`_block_grid`): per zarr call and per window edge they cost the same
whatever the tile, so small tiles would pay them many times over.  Labelling
and masks take a group of neighbouring blocks of a block row per task
(:func:`_tasks.block_groups`), which reads the group's window once.

:func:`detect` reads as its stages:

1. :func:`._plan._plan`: inputs probed, grid and run key derived (nothing
   written; the configuration, summary and defaults live in ``_plan.py``);
2. :func:`_ingest`: both images into the store, chunked by tile, one task per
   block (a tile task reads its core and halo: at most nine chunks);
3. :func:`_register_tiles`: one start search per band of tiles
   (:func:`_band_starts`), then every tile (resumable: finished tiles are
   marked in the store);
4. :func:`_fuse_paths`: the per-row trajectories of tiles sharing rows fused,
   tiles whose path disagrees with their band's re-solved around the others';
5. :func:`_change_masks`: one change threshold for the whole image from summed
   tile histograms; change candidates labelled per block (its score read with
   the margin the local half-maximum test needs, a group of blocks at once),
   labels merged across seams, components kept that reach the threshold and
   the minimum area; per block, the mask of its window from the kept labels
   (again by groups), small holes filled, no
   evidence marked 255, its core written, and its mask, score and parallax
   mask in the reference grid (the ground frame) from the fused trajectory;
6. :func:`_finish`: attributes, an atomic rename of the store, GeoTIFFs on
   request.
"""

import contextlib
import dataclasses
import functools
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np

from rsmb import ops
from rsmb import tiles
from rsmb.ops import InputError
from rsmb.ops.depth._layers import MIN_COVERED, MIN_EXPLAINED

from . import _tasks
from ._tasks import _specs, _tile_done, _tile_results
from ._fuse import _agreement, _fuse, _outliers
from ._outputs import _check_outputs, _finished, ground_geo, write_products
from ._overview import overview_specs, slow_stage
from ._plan import VERSION, DetectConfig, DetectResult, _plan
from .._scheduler import WORKER_TIMEOUT, check_scheduler, open_runner
from ..report._previews import preview_arrays, write_previews

__all__ = ["detect"]

log = logging.getLogger("rsmb")


def _expected_cost(tile, camera):
    """Relative registration cost of a tile: its area times the distance of its
    farthest pixel from the principal point (rotation moves far pixels more, so
    their neighbourhoods and blur are larger: corner tiles run longer than
    central ones).  The longest tiles are started first."""
    (r0, r1), (c0, c1) = [(s.start, s.stop) for s in tile.core]
    far = np.hypot(max(abs(c0 - camera.center_xy[0]), abs(c1 - camera.center_xy[0])),
                   max(abs(r0 - camera.center_xy[1]), abs(r1 - camera.center_xy[1])))
    return (r1 - r0) * (c1 - c0) * far


def _ingest(runner, group, run, plan, timings):
    """Stage 2: both inputs into the store, one task per block of each: the
    capture on its own grid, the reference resampled onto it (with a margin
    around it when georeferenced).  Returns the run's store with the two
    images' common intensity scale and clip levels (:func:`ops.intensity_scale`),
    recorded in the ``intensity`` attribute, and the blocks' parts of the
    overviews the slow part is found on (see :func:`slow_stage`; None when
    resumed after the ingest or when no slow part is asked for)."""
    t0 = time.perf_counter()
    cells = None
    if group.attrs.get("ingest_complete"):
        log.info("ingest: already complete (resume)")
        scale = ops.IntensityScale.from_dict(group.attrs["intensity"])
    else:
        m, specs = plan.margin, overview_specs(plan) or {}
        capture = functools.partial(tiles.read_clipped, plan.distorted.path, plan.shape)
        jobs = [(run, "ingest/distorted", capture, b, (0, 0), specs.get("capture")) for b in plan.blocks]
        jobs += [(run, "ingest/reference", plan.pairing.reference_window, b, (m, m), specs.get("reference"))
                 for b in plan.reference_blocks]
        stats, parts = zip(*runner.map("ingest", _tasks.ingest_task, jobs))
        n = len(plan.blocks)
        if specs:
            cells = {"capture": list(parts[:n]), "reference": list(parts[n:])}
        names = (", ".join(r.path for r in plan.references), plan.distorted.path)
        capture_stats, reference_stats = sum(stats[1:n], stats[0]), sum(stats[n + 1:], stats[n])
        tiles.check_stats(capture_stats, names[1], pixels=plan.shape[0] * plan.shape[1])
        tiles.check_stats(reference_stats, names[0])
        scale = ops.intensity_scale(reference_stats, capture_stats, names=names)
        group.update_attributes({"intensity": tiles.jsonable(scale.as_dict()), "ingest_complete": True})
    timings["ingest_s"] = time.perf_counter() - t0
    return dataclasses.replace(run, intensity=scale), cells


def _band_starts(runner, run, plan, todo):
    """Stage 3a: one start per band of tiles (a grid row: its tiles hold the
    same capture rows, and camera poses are global) that has two tiles or
    more and some to register, one task each (:func:`_tasks.start_task`).
    Returns {tile row: StartPose or None}; none with a global shutter (its
    tiles' start blocks span their rows)."""
    if plan.params.shutter != "rolling":
        return {}
    bands = {}
    for t in plan.grid:
        bands.setdefault(t.index[0], []).append(t)
    wanted = sorted({t.index[0] for t in todo if len(bands[t.index[0]]) > 1})
    found = runner.map("start", _tasks.start_task, [(run, bands[ty], plan.camera, plan.params) for ty in wanted])
    return dict(zip(wanted, found))


def _register_tiles(runner, group, run, plan, resume, timings):
    """Stage 3: every tile not yet registered, the longest first, each band's
    from the start the band shares (:func:`_band_starts`).  Returns the
    tiles' CPU-seconds per stage, summed (see :func:`_tasks.register_task`)."""
    t0 = time.perf_counter()
    done = _tile_done(group)
    grid = plan.grid
    todo = sorted((t for t in grid if not done[t.index]), key=lambda t: -_expected_cost(t, plan.camera))
    if resume:
        log.info("resume: %d of %d tiles already registered", len(grid) - len(todo), len(grid))
    starts = _band_starts(runner, run, plan, todo)
    stats = runner.map("register", _tasks.register_task,
                       [(run, t, plan.camera, plan.params, plan.config.changes, None, starts.get(t.index[0]))
                        for t in todo])
    timings["register_s"] = time.perf_counter() - t0
    timings["tiles_registered"] = len(todo)
    timings["tiles_shared_start"] = sum(s["shared_start"] for s in stats)
    if stats:
        for name in ("kernel_s", "read_s", "write_s"):
            timings[f"{name}_sum"] = float(sum(s[name] for s in stats))
    stages = {}
    for s in stats:
        for k, v in s["stages"].items():
            stages[k] = stages.get(k, 0.0) + v
    return stages


def _fuse_paths(runner, group, run, plan, timings):
    """Stage 4: fuse the tiles' paths, re-solve the tiles that stray, write the
    path arrays.  Returns (fused path, summed histogram, per-tile gains,
    agreement, re-solved tiles)."""
    t0 = time.perf_counter()
    grid, camera, axes = plan.grid, plan.camera, plan.params.trajectory_axes
    paths, states, hist, residual_hists, gains = _tile_results(group)
    fused, agree, worst = _agreement(paths, states, grid, camera, axes)
    resolve = _outliers(worst, ops.residual_median(residual_hists), plan.config.agreement)
    if resolve:
        log.info("re-solving %d tile(s) whose path disagrees with their band: %s", len(resolve), resolve)
        args = []
        for ty, tx in resolve:
            tile = grid[ty, tx]
            rows = tile.core[0]
            others = np.delete(paths[rows], tx, axis=1)
            prior = _fuse(others, np.delete(states[rows], tx, axis=1))
            args.append((run, tile, camera, plan.params, plan.config.changes, prior))
        runner.map("re-solve", _tasks.register_task, args)
        paths, states, hist, _, gains = _tile_results(group)
        fused, agree, worst = _agreement(paths, states, grid, camera, axes)
    group["trajectory"][:] = fused.astype(np.float32)
    group["tile_trajectory"][:] = paths.astype(np.float32)
    group["tile_row_state"][:] = states
    group["gain"][:] = gains.astype(np.float32)
    group["tile_agreement"][:] = agree.astype(np.float32)
    timings["fuse_s"] = time.perf_counter() - t0
    return fused, hist, gains, agree, resolve


def _change_masks(runner, run, plan, fused, hist, timings):
    """Stage 5: one threshold, labels per block merged across seams, masks in
    both grids.  Returns (threshold, changed pixels, components kept, pixels
    without evidence)."""
    t0 = time.perf_counter()
    shape, blocks, changes = plan.shape, plan.blocks, plan.config.changes
    threshold = ops.change_threshold(hist, params=changes)
    groups = _tasks.block_groups(blocks, least=runner.runner.local_workers())
    labelled = [out for outs in runner.map("label", _tasks.label_task, [(run, g, shape, threshold, changes)
                                                                        for g in groups]) for out in outs]
    summaries = {s.index: s for s, _, _ in labelled}
    offsets, root, area, peak = tiles.merge_tile_labels(summaries, blocks.grid_shape)
    keep_global = ops.keep_components(area, peak, threshold, params=changes)
    kept = {}  # block index -> keep flag per local label, for blocks that keep any
    for b in blocks:
        n = len(summaries[b.index].area)
        keep = keep_global[root[offsets[b.index]:offsets[b.index] + n]].copy()
        keep[0] = False
        if keep.any():
            kept[b.index] = (b.core, keep)
    stored_path = fused.astype(np.float32).astype(np.float64)  # as the store holds it
    args = []
    for group in groups:  # every block: its no-evidence marks and its ground frame
        jobs = []
        for b in group:
            window = b.grown(plan.grid.halo, shape)
            jobs.append((b, window, [kept[i] for i in blocks.covering(window) if i in kept]))
        rows = jobs[0][1][0]  # the windows' rows: one block row's
        args.append((run, jobs, stored_path[rows], plan.camera, plan.params.trajectory_axes, changes))
    masked = [out for outs in runner.map("masks", _tasks.mask_task, args) for out in outs]
    timings["changes_s"] = time.perf_counter() - t0
    timings["changes_compute_s_sum"] = float(sum(c for _, c, _ in labelled) + sum(c for _, c in masked))
    return threshold, sum(n for n, _ in masked), int(keep_global.sum()), sum(n for _, _, n in labelled)


class _Counted:
    """A runner that counts the tasks it was given (runs may share a runner)
    and sums their CPU-seconds by label (``cpu``)."""

    def __init__(self, runner):
        self.runner, self.tasks, self.cpu = runner, 0, {}

    def map(self, label, func, argument_lists):
        argument_lists = list(argument_lists)
        self.tasks += len(argument_lists)
        done = self.runner.map(label, functools.partial(_tasks.cpu_timed, func), argument_lists)
        self.cpu[label] = self.cpu.get(label, 0.0) + sum(c for _, c in done)
        return [out for out, _ in done]


#: The stages of ``timings["cpu_s"]``, in the order a run meets them: CPU-seconds summed over tasks.
CPU_STAGES = ("ingest", "overview_slow", "read", "start", "rows", "reanchor", "gain_slope", "reground",
              "depth", "score", "write", "tile_resolve", "change_masks")


def _cpu_stages(runner, tile_stages):
    """``timings["cpu_s"]``: CPU-seconds per stage summed over the run's tasks
    (each task's own thread; on a distributed cluster too): the tiles' stages
    (``tile_stages``, summed by :func:`_register_tiles`), and per task label the
    stages run outside the tiles."""
    cpu = runner.cpu
    out = {"ingest": cpu.get("ingest", 0.0),
           "overview_slow": cpu.get("overview", 0.0) + cpu.get("slow", 0.0) + tile_stages.get("slow", 0.0)}
    out.update({k: tile_stages.get(k, 0.0) for k in CPU_STAGES if k not in ("ingest", "overview_slow")})
    out["start"] += cpu.get("start", 0.0)  # the bands' start tasks
    out["tile_resolve"] = cpu.get("re-solve", 0.0)
    out["change_masks"] = cpu.get("label", 0.0) + cpu.get("masks", 0.0)
    out["total"] = float(sum(out.values()))
    return out


def _pairing_attrs(pairing):
    out = {"mode": pairing.mode, "reason": pairing.reason, "references": list(pairing.references)}
    if pairing.coverage is not None:
        out["coverage"] = pairing.coverage.fraction
        out["read"] = list(pairing.coverage.files)
    return out


def _attributes(plan, result, scheduler):
    """Root attributes of the store (DESIGN.md's output store)."""
    axes, grid, camera = plan.params.trajectory_axes, plan.grid, plan.camera
    attrs = {
        "rsmb_version": VERSION,
        "kernel_version": ops.KERNEL_VERSION,
        "run_key": plan.key,
        "parameters": dataclasses.asdict(plan.config),
        "pose_axes": list(axes),
        "pose_units": [ops.AXIS_UNITS[a] for a in axes],
        "tile_grid": {"shape": list(grid.shape), "tile": grid.tile, "halo": grid.halo, "block": plan.blocks.tile,
                      "tiles": list(grid.grid_shape), "row_edges": grid.row_edges.tolist(),
                      "col_edges": grid.col_edges.tolist()},
        "camera": {"focal_px": camera.focal, "center_xy": list(camera.center_xy)},
        "inputs": {"distorted": {"path": plan.distorted.path, "sha256": plan.distorted.sha256},
                   **{f"reference{'' if k == 0 else f'_{k + 1}'}": {"path": r.path, "sha256": r.sha256}
                      for k, r in enumerate(plan.references)}},
        "pairing": _pairing_attrs(plan.pairing),
        "scheduler": scheduler,
        "summary": result.as_dict(),
        **plan.distorted.geo.to_attrs(),
    }
    if plan.pairing.mode == "pixel" and not plan.references[0].geo.is_empty:
        attrs["reference_georeferencing"] = plan.references[0].geo.to_attrs()
    return tiles.jsonable(attrs)


def _finish(group, store, plan, result, scheduler, overwrite, geotiff, previews):
    """Stage 6: attributes, scratch arrays dropped, the previews
    (``previews``: a :class:`_Beside` making them) written, the store renamed
    into place, GeoTIFFs on request."""
    axes = plan.params.trajectory_axes
    # one metadata write for all of them (``attrs.update`` writes once per key)
    group.update_attributes({**_attributes(plan, result, scheduler), "parallax": tiles.jsonable(
        {"rule": "a candidate change is parallax when at its best relative depth (translations divided by it, "
                 f"rotations kept; {plan.config.changes.layers and 'swept over ' + str(list(ops.LayerParams().depths)) or 'not tested: --no-layers'}) "
                 f"at least {MIN_EXPLAINED:.0%} of its pixels fall below the change threshold "
                 f"and those plus the pixels of ground the layer hid in the reference make up at least "
                 f"{MIN_COVERED:.0%} of it; only its pixels explained at that depth, on the layer's edge or "
                 "disoccluded join parallax_mask, the rest stays a change candidate"
                 + (plan.config.changes.layers and "; parallax pixels take part in their neighbours' half-maximum "
                    "test with their score at the ground's depth" or ""),
         "components": _tasks.layer_components(group)})})
    # only the ground-frame arrays (dims y, x) get map coordinates
    geo = ground_geo(plan.pairing.mode, plan.references[0].geo, plan.distorted.geo)
    tiles.write_spatial_coords(group, geo, plan.shape)
    group["trajectory"].update_attributes({"pose_axes": list(axes), "units": [ops.AXIS_UNITS[a] for a in axes]})
    for name in ("work", "ingest"):
        del group[name]
    # what the report shows of the inputs, which may not stay where they are
    write_previews(group, plan.pairing, previews=previews.result())
    final = tiles.finalize_result_store(store, plan.output, overwrite=overwrite)
    if geotiff is not None:
        write_products(final, geotiff, geo, overwrite=overwrite)
    log.info("wrote %s: %d changed px (threshold %.3f), %.2f MP/s", final, result.changed_pixels, result.threshold,
             result.megapixels_per_s)
    if result.threshold >= POOR_FIT_THRESHOLD:
        log.warning("%s: change threshold %.3f of the scene's range (about 0.05 where the capture registers): "
                    "the residual left on most pixels is that large, so few changes can be found; is the "
                    "reference of this capture's scene?", final, result.threshold)
    agreement = result.tile_agreement_px_max
    if agreement is not None and agreement > DISAGREEMENT_WARNING * plan.config.agreement:
        log.warning("%s: tiles' paths differ from the fused one by up to %.1f px (RMS over their rows; more than %g "
                    "times the %g px re-solve tolerance): the capture's rows were not registered as one camera path "
                    "(its tile_agreement array shows where); those tiles' changes in the ground frame (the *_reference "
                    "arrays, COGs and polygons) may be that far off, and their registration may be wrong", final,
                    agreement, DISAGREEMENT_WARNING, plan.config.agreement)
    if result.no_evidence >= NO_EVIDENCE_WARNING:
        log.warning("%s: no evidence on %.0f %% of the capture's pixels (its change mask says 255 there): too little "
                    "of it could be registered (too small, too little valid, or off the reference)", final,
                    100 * result.no_evidence)


class _Beside:
    """``func(*args)`` run in a thread of its own from :meth:`start` on;
    :meth:`result` waits for it (starting it if need be) and raises what it
    raised.  For work that needs only the inputs, such as the previews (read
    and reduced on one thread): made beside the stages, it takes a core
    while a stage leaves one idle (the slow part's one task) instead of
    adding to the run's serial end.  A daemon: a run that
    fails does not wait for it."""

    def __init__(self, func, *args):
        self._func, self._args = func, args
        self._out, self._error, self._thread = None, None, None

    def start(self):
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="rsmb-beside", daemon=True)
            self._thread.start()
        return self

    def _run(self):
        try:
            self._out = self._func(*self._args)
        except BaseException as error:  # noqa: BLE001 - raised again in the caller's thread by result()
            self._error = error

    def result(self):
        self.start()._thread.join()
        if self._error is not None:
            raise self._error
        return self._out


def _beside_stages(pairing):
    """What the thread beside the stages does (:class:`_Beside`): numba's
    start (loading the first compiled function from its cache starts its
    compiler, under a lock the tasks share: in the first start task, the
    other worker would wait for it), then the input previews
    (:func:`preview_arrays`), which it returns."""
    from rsmb.ops._warp import _warp_into

    _warp_into(np.zeros((2, 2), np.float32), np.zeros((1, 6)), 1.0, 0.0, 0.0, 0.0, 0.0, np.empty((1, 1), np.float32))
    return preview_arrays(pairing)


@contextlib.contextmanager
def _store_lock(output):
    """The exclusive lock of the store ``output``: ``<output>.lock`` beside
    it, held for the run and removed after (:func:`rsmb.tiles.acquire_lock`).
    Another run on the same store is refused, not raced.  Folders made for
    the lock file are removed again when the run fails before it wrote."""
    parent, made = Path(output).parent, []
    if not parent.is_dir():  # (an existing folder is proven by the lock file: no probe file written there)
        tiles.check_writable(output)
    while not parent.exists():
        made.append(parent)
        parent = parent.parent
    Path(output).parent.mkdir(parents=True, exist_ok=True)
    try:
        with tiles.acquire_lock(f"{output}.lock", what="rsmb detect", remove=True) or contextlib.nullcontext():
            yield
    except BaseException:
        for folder in made:  # innermost first; a folder the run filled stays
            try:
                folder.rmdir()
            except OSError:
                break
        raise


def detect(reference, distorted, output, *, config=None, scheduler="threads", workers=None, overwrite=False,
           resume=False, geotiff=None, runner=None, worker_timeout=WORKER_TIMEOUT):
    """Register ``distorted`` against ``reference`` and write the change store.

    Parameters
    ----------
    reference : str or path-like, or a sequence of them
        The reference: one image (GeoTIFF, PNG/JPEG, NPY or a zarr array) of
        the capture's size, or, when it and the capture are georeferenced, a
        reference set of any extent, pixel size and CRS (a mosaic of files):
        only its part under the capture's footprint (plus the halo) is read and
        resampled onto the capture's grid.
    distorted : str or path-like
        The capture; its grid is the grid of every output.
    output : str or path-like
        The zarr store to write (see DESIGN.md's output store).
    config : DetectConfig, optional
    scheduler : str
        ``threads``, ``processes``, ``synchronous``, a ``tcp://`` address or a
        scheduler file.
    workers : int, optional
        Worker count of a local scheduler (default: one per core).
    overwrite : bool
        Replace an existing output store.
    resume : bool
        Continue an interrupted run with the same inputs and configuration: only
        tiles not yet registered run.
    geotiff : str or path-like, optional
        Directory where the masks are also written as GeoTIFFs.
    runner : Runner, optional
        An open runner to use instead of opening one for ``scheduler`` (runs
        sharing a runner share its executor or cluster).
    worker_timeout : float
        Seconds a distributed run waits with no worker left before it fails.

    Paths are made absolute before they reach a task: a dask worker may run
    in another working directory.

    Returns
    -------
    DetectResult

    Raises
    ------
    InputError
        Unusable inputs (unreadable, empty, constant, NaN, different sizes when
        not georeferenced, footprints that do not overlap) or an output that
        cannot be written (existing without ``overwrite``, under a file, on a
        read-only file system).
    """
    t_start = time.perf_counter()
    config = config or DetectConfig()
    references, distorted, output, geotiff = _absolute(reference, distorted, output, geotiff)
    plan = _plan(references, distorted, output, config)
    if resume:
        done = _finished(output, plan.key)
        if done is not None:
            return DetectResult(**done)
    check_scheduler(scheduler)
    with _store_lock(output):  # held for the run: nothing of the output is touched before
        _check_outputs(output, geotiff, overwrite)  # (it repairs an overwrite a killed run left half-done)
        group = tiles.create_result_store(output, _specs(plan.grid, len(plan.params.trajectory_axes), plan.margin),
                                          {"run_key": plan.key}, overwrite=overwrite, resume=resume)
        store = str(tiles.partial_path(output))
        run = _tasks.RunStore(store, plan.key, plan.margin)
        if resume and group.attrs.get("run_key") != plan.key:
            raise InputError(f"{output}: the interrupted run had other inputs or parameters; run without --resume")
        timings = {}
        previews = _Beside(_beside_stages, plan.pairing)  # from the inputs alone, beside the stages
        try:
            own = open_runner(scheduler, workers=workers, worker_timeout=worker_timeout) if runner is None else None
            with own or contextlib.nullcontext(runner) as shared:
                log.info("%s: %d x %d px (width x height), %d tiles of %d px, halo %d px, scheduler %s",
                         plan.distorted.path, plan.shape[1], plan.shape[0], len(plan.grid), plan.grid.tile,
                         plan.grid.halo,
                         getattr(shared, "describe", lambda: scheduler)())
                plan, run, found = _stages(_Counted(shared), group, run, plan, resume, timings, previews)
            timings["total_s"] = time.perf_counter() - t_start
            result = _result(group, run, plan, found, timings)
            _finish(group, store, plan, result, scheduler, overwrite, geotiff, previews)
            return result
        except BaseException as error:
            # an interruption keeps what a --resume can continue; unusable inputs do not
            if isinstance(error, InputError) or not _tasks.resume_safe(group):
                tiles.abort_result_store(store)
            raise


def _absolute(reference, distorted, output, geotiff):
    """The run's paths made absolute (a dask worker may run in another working
    directory): the reference files (a mosaic's expanded), the capture, the
    store and the GeoTIFF folder (None stays None)."""
    references = [os.path.abspath(r) for r in tiles.expand_references(
        [reference] if isinstance(reference, (str, os.PathLike)) else reference)]
    return (references, os.path.abspath(distorted), os.path.abspath(output),
            None if geotiff is None else os.path.abspath(geotiff))


@dataclasses.dataclass(frozen=True)
class _Found:
    """What stages 2 to 5 found, for :class:`DetectResult`."""

    threshold: float
    changed: int
    components: int
    silent: int
    gains: np.ndarray
    agree: np.ndarray
    resolve: list
    tasks_per_tile: float


def _stages(runner, group, run, plan, resume, timings, previews):
    """Stages 2 to 5 on ``runner`` (a :class:`_Counted`), in order: the plan
    with the halo the rows need, the run store, and a :class:`_Found`.
    ``previews`` (a :class:`_Beside`) is started after the ingest, whose
    tasks keep every core busy, beside the slow part."""
    run, cells = _ingest(runner, group, run, plan, timings)
    previews.start()
    slow_stage(runner, group, run, plan, timings, cells)
    halo = plan.grid.halo
    plan = plan.for_rows(group["work/slow"][:])  # the halo the rows need, the slow part known
    if plan.grid.halo != halo:
        log.info("halo %d px for the rows (the slow part found needs no more)", plan.grid.halo)
    tile_stages = _register_tiles(runner, group, run, plan, resume, timings)
    fused, hist, gains, agree, resolve = _fuse_paths(runner, group, run, plan, timings)
    threshold, changed, components, silent = _change_masks(runner, run, plan, fused, hist, timings)
    found = _Found(threshold, changed, components, silent, gains, agree, resolve, runner.tasks / len(plan.grid))
    timings["cpu_s"] = _cpu_stages(runner, tile_stages)
    return plan, run, found


#: Multiple of :attr:`DetectConfig.agreement` beyond which a tile's RMS
#: disagreement with the fused path, left after the re-solves, is warned about
#: (a band whose tiles all stray has no consensus to re-solve them around).
DISAGREEMENT_WARNING = 5.0

#: Share of a capture's pixels without evidence from which detect warns that
#: it found almost nothing to register.
NO_EVIDENCE_WARNING = 0.9
#: A change threshold (the common intensity scale: a fraction of the scene's
#: range) from which detect warns that the registration explains little: the
#: threshold follows the residual of most pixels.  Measured: 0.05 (the floor)
#: on registered synthetic and real aerial pairs, 0.11 on the Fastec
#: rolling-shutter capture; captures of another scene than their reference's
#: 0.37 and 0.71 at 256 and 512 px, but 0.16-0.19 at 128-192 px, which pass
#: unwarned: a warning, not a test of the pairing.
POOR_FIT_THRESHOLD = 0.25


def _finite_extreme(extreme, values):
    """``extreme`` (np.nanmin or np.nanmax) of ``values`` as a float, None
    when none is finite (no tile had data for it: JSON has no NaN)."""
    values = np.asarray(values, np.float64)
    return float(extreme(values)) if np.isfinite(values).any() else None


def _result(group, run, plan, found, timings):
    """The run's :class:`DetectResult` from what its stages found."""
    shape, grid, pixels = plan.shape, plan.grid, float(plan.shape[0] * plan.shape[1])
    layers = _tasks.layer_components(group)
    return DetectResult(
        output=str(plan.output), shape=list(shape), tiles=list(grid.grid_shape), tile_size=grid.tile,
        halo=grid.halo, threshold=found.threshold, changed_pixels=int(found.changed),
        changed_fraction=found.changed / pixels, components=found.components,
        gain_min=_finite_extreme(np.nanmin, found.gains), gain_max=_finite_extreme(np.nanmax, found.gains),
        resolved_tiles=[list(t) for t in found.resolve],
        tile_agreement_px_max=_finite_extreme(np.nanmax, found.agree),
        tasks_per_tile=found.tasks_per_tile, megapixels_per_s=pixels / 1e6 / timings["total_s"],
        timings=timings, pairing=plan.pairing.mode,
        reference_coverage=None if plan.pairing.coverage is None else plan.pairing.coverage.fraction,
        failed_rows=int((group["tile_row_state"][:] == 3).sum()),
        clipped_reference=run.intensity.reference_clipped, clipped_capture=run.intensity.capture_clipped,
        no_evidence=found.silent / pixels, parallax_components=len(layers),
        parallax_pixels=int(sum(c["pixels"] for c in layers)))
