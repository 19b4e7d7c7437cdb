"""``rsmb detect``: tiled RSMB registration and change detection of one capture.

Registration runs one task per tile.  The stages that mostly move data (ingest,
labelling, masks) run one task per block of tiles, about 1024 px on a side (see
:func:`_block_grid`): per zarr call and per window edge they cost the same
whatever the tile, so small tiles would pay them many times over.

1. ingest both images into the store, chunked by tile, one task per block for
   both (a tile task reads its core and halo: at most nine chunks);
2. register every tile (resumable: finished tiles are marked in the store);
3. fuse the per-row trajectories of tiles sharing rows, re-solve tiles whose
   path disagrees with their band's around the others' path;
4. one change threshold for the whole image from summed tile histograms;
5. label change candidates per block (its score read with the margin the
   local half-maximum test needs), merge labels across seams, keep components
   that reach the threshold and the minimum area;
6. per block, the mask of its window from the kept labels, small holes filled,
   its core written, and its changes in the reference grid from the fused
   trajectory (blocks with no kept label under their window are skipped);
7. attributes, GeoTIFFs on request, and an atomic rename of the store.
"""

import dataclasses
import hashlib
import json
import logging
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from rsmb import ops
from rsmb import tiles
from rsmb.ops import ChangeParams, InputError, RegistrationParams

from . import _tasks
from ._scheduler import open_runner

__all__ = ["DetectConfig", "detect", "default_overlap", "default_tile", "VERSION"]

VERSION = "0.1.0"
log = logging.getLogger("rsmb")


@dataclass(frozen=True)
class DetectConfig:
    """Everything that decides the result of :func:`detect`.

    Attributes
    ----------
    registration : RegistrationParams
    changes : ChangeParams
    tile : int or None
        Core tile side in pixels; None picks :func:`default_tile`.
    overlap : int or None
        Halo in pixels; None derives it from the search range (see
        :func:`default_overlap`).
    focal : float or None
        Focal length in pixels of the whole image (default 1.2 x larger side).
    agreement : float
        A tile whose path differs from its band's by more than this (px: the
        95th percentile over its rows of the displacement of the row ends), and
        by more than three times the band's median, is re-solved around the
        others' path.
    """

    registration: RegistrationParams = field(default_factory=RegistrationParams)
    changes: ChangeParams = field(default_factory=ChangeParams)
    tile: int | None = None
    overlap: int | None = None
    focal: float | None = None
    agreement: float = 2.0


def default_tile(shape):
    """1024-px tiles when the image holds at least 4 x 4 of them, else 512: large
    tiles pay the per-tile start (wide search, start block) a quarter as often
    (8192^2: 0.90 against 0.66 MP/s), small ones keep both cores busy on small
    images (2048^2 in four tiles leaves a core idle while the slowest finishes).
    Depends on the shape only, so a ``--resume`` finds the same grid."""
    return 1024 if min(shape) >= 4 * 1024 else 512


def default_overlap(params, camera, shape):
    """Halo (px) that holds every displacement the wide search allows anywhere in
    the image, plus the row neighbourhood: the extreme poses of the search box
    are applied to the image corners."""
    axes = params.axes
    search = np.asarray(params.search)
    corners = np.array([[0, 0, 1], [shape[1] - 1, 0, 1], [0, shape[0] - 1, 1], [shape[1] - 1, shape[0] - 1, 1.0]]).T
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * len(axes), indexing="ij")).reshape(len(axes), -1).T
    hom = ops.pose_homographies(signs * search, camera, axes=axes, inverse=True)
    pts = hom @ corners
    pts = pts[:, :2] / pts[:, 2:3]
    reach = float(np.abs(pts - corners[None, :2]).max())
    hw = max([params.half_width[d] for d, a in enumerate(axes) if a in ("tx", "ty")] + [0.0])
    return int(np.ceil(reach + 3 * hw)) + 8


def _expected_cost(tile, camera):
    """Relative registration cost of a tile: its area times the distance of its
    farthest pixel from the principal point (rotation moves far pixels more, so
    their neighbourhoods and blur are larger: corner tiles run about three times
    longer than central ones).  The longest tiles are started first."""
    (r0, r1), (c0, c1) = [(s.start, s.stop) for s in tile.core]
    far = np.hypot(max(abs(c0 - camera.center_xy[0]), abs(c1 - camera.center_xy[0])),
                   max(abs(r0 - camera.center_xy[1]), abs(r1 - camera.center_xy[1])))
    return (r1 - r0) * (c1 - c0) * far


def _run_key(ref_info, dist_info, config, grid):
    text = json.dumps(tiles.jsonable({"reference": ref_info.sha256, "distorted": dist_info.sha256,
                                      "config": config, "grid": [grid.shape, grid.tile, grid.halo],
                                      "version": VERSION}), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


BLOCK = 1024  # px: the side the ingest, label and mask tasks aim for


def _block_grid(grid):
    """Blocks of tiles for ingest, labelling and masks: about :data:`BLOCK` px on a
    side and at least two per axis when there are four tiles or more (both cores
    stay busy).  Those tasks cost a few zarr calls (about 1 ms each) and read
    a margin or halo around their core: per block, not per small tile.  At
    8192 x 8192 with 512-px tiles, 64 blocks instead of 256 tiles."""
    ny, nx = grid.grid_shape
    return grid.coarsened(max(1, min(BLOCK // grid.tile, ny // 2, nx // 2)))


def _specs(grid, dims):
    h, w = grid.shape
    t = grid.tile
    ny, nx = grid.grid_shape
    spec = tiles.ArraySpec
    return {
        "registered": spec((h, w), "float32", (t, t), ("y", "x"), float("nan")),
        "change_score": spec((h, w), "float32", (t, t), ("y", "x"), 0.0),
        "change_mask": spec((h, w), "uint8", (t, t), ("y", "x")),
        "change_mask_reference": spec((h, w), "uint8", (t, t), ("y", "x")),
        "trajectory": spec((h, dims), "float32", (t, dims), ("y", "pose_axis"), float("nan")),
        "tile_trajectory": spec((h, nx, dims), "float32", (h, nx, dims), ("y", "tile_x", "pose_axis"), float("nan")),
        "tile_row_state": spec((h, nx), "uint8", (h, nx), ("y", "tile_x")),
        "gain": spec((ny, nx), "float32", (ny, nx), ("tile_y", "tile_x"), float("nan")),
        "tile_agreement": spec((ny, nx), "float32", (ny, nx), ("tile_y", "tile_x"), float("nan")),
        # scratch, one chunk per tile, deleted when the run finishes
        "work/tile_rows": spec((h, nx, dims + 1), "float32", (t, 1, dims + 1), ("y", "tile_x", "column"),
                               float("nan"), compressed=False),
        "work/tile_summary": spec((ny, nx, _SUMMARY), "float64", (1, 1, _SUMMARY), ("tile_y", "tile_x", "value"),
                                  compressed=False),
        "work/labels": spec((h, w), "int32", (t, t), ("y", "x"), compressed=False),
        "ingest/reference": spec((h, w), "float32", (t, t), ("y", "x"), float("nan"), compressed=False),
        "ingest/distorted": spec((h, w), "float32", (t, t), ("y", "x"), float("nan"), compressed=False),
    }


_HIST = (ops.RESIDUAL_BINS, ops.SCORE_BINS)
_SUMMARY = sum(_HIST) + 3  # per tile: both histograms, gain, seconds; 1 when done


def _tile_results(group):
    """Per-tile results of stage 1 from the scratch arrays: trajectories (H, nx, D),
    row states (H, nx), summed histogram, residual histograms (ny, nx, bins),
    gains (ny, nx)."""
    rows = group["work/tile_rows"][:]
    summary = group["work/tile_summary"][:]
    hist = ops.ScoreHistogram(summary[..., :_HIST[0]].sum((0, 1)).astype(np.int64),
                              summary[..., _HIST[0]:sum(_HIST)].sum((0, 1)).astype(np.int64))
    states = np.nan_to_num(rows[..., -1]).astype(np.uint8)
    return rows[..., :-1].astype(np.float64), states, hist, summary[..., :_HIST[0]], summary[..., -3]


def _tile_done(group):
    """(ny, nx) bool: tiles whose registration finished."""
    return group["work/tile_summary"][..., -1] == 1


def _row_end_points(tile):
    """Global (x, y) of the two ends of every core row of ``tile``: (rows, 2, 2)."""
    rows = np.arange(tile.core[0].start, tile.core[0].stop, dtype=np.float64)
    left = np.stack([np.full_like(rows, tile.core[1].start), rows], -1)
    right = np.stack([np.full_like(rows, tile.core[1].stop - 1), rows], -1)
    return np.stack([left, right], 1)


def _disagreement(path, reference, tile, camera, axes):
    """Per row, the largest displacement (px) between two paths at the row ends
    (NaN where either path is unknown)."""
    ok = np.isfinite(path).all(1) & np.isfinite(reference).all(1)
    out = np.full(len(ok), np.nan)
    if not ok.any():
        return out
    pts = _row_end_points(tile)[ok]
    ha = ops.pose_homographies(path[ok], camera, axes=axes)
    hb = ops.pose_homographies(reference[ok], camera, axes=axes)
    homog = np.concatenate([pts, np.ones(pts.shape[:2] + (1,))], -1)
    pa = np.einsum("rij,rpj->rpi", ha, homog)
    pb = np.einsum("rij,rpj->rpi", hb, homog)
    out[ok] = np.linalg.norm(pa[..., :2] / pa[..., 2:] - pb[..., :2] / pb[..., 2:], axis=-1).max(-1)
    return out


def _fuse(paths, states):
    """Per-row median over tiles of solved rows; rows no tile solved take the
    median of whatever the tiles have, then interpolation."""
    good = np.where((states == 1)[..., None], paths, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows are handled below
        fused = np.nanmedian(good, axis=1)
        fallback = np.nanmedian(paths, axis=1)
    fused = np.where(np.isnan(fused), fallback, fused)
    rows = np.arange(fused.shape[0])
    for d in range(fused.shape[1]):
        bad = np.isnan(fused[:, d])
        if bad.all():
            fused[:, d] = 0.0
        elif bad.any():
            fused[bad, d] = np.interp(rows[bad], rows[~bad], fused[~bad, d])
    return fused


def _agreement(paths, states, grid, camera, axes):
    fused = _fuse(paths, states)
    ny, nx = grid.grid_shape
    agree = np.full((ny, nx), np.nan)  # RMS displacement from the fused path, px
    worst = np.full((ny, nx), np.nan)  # its 95th percentile over rows: a stretch of wrong rows
    for tile in grid:
        ty, tx = tile.index
        rows = tile.core[0]
        d = _disagreement(np.where((states[rows, tx] == 1)[:, None], paths[rows, tx], np.nan),
                          fused[rows], tile, camera, axes)
        if np.isfinite(d).any():
            agree[ty, tx] = np.sqrt(np.nanmean(d ** 2))
            worst[ty, tx] = np.nanpercentile(d, 95)
    return fused, agree, worst


def _outliers(worst, residual_level, tolerance):
    """Tiles to re-solve: in each band of two or more tiles, those whose path
    strays from the fused one by more than ``tolerance`` px and by more than
    three times the band's typical strayness (tiles fit their rows a little
    differently; a tile on a large change or a periodic texture strays far).
    With two tiles that both stray, the one that fits worse is taken."""
    out = []
    for ty in range(worst.shape[0]):
        row = worst[ty]
        if row.size < 2 or not np.isfinite(row).any():
            continue
        # a median of two is their mean: with two tiles only the tolerance can judge
        limit = tolerance if row.size == 2 else max(tolerance, 3.0 * float(np.nanmedian(row)))
        bad = [tx for tx in range(row.size) if not row[tx] <= limit]
        if row.size == 2 and len(bad) == 2:
            bad = [int(np.nanargmax(residual_level[ty]))]
        if len(bad) < row.size:
            out.extend((ty, tx) for tx in bad)
    return out


def _ingest(runner, group, run, ref_info, dist_info, blocks):
    if group.attrs.get("ingest_complete"):
        log.info("ingest: already complete (resume)")
        return
    sources = [("ingest/reference", ref_info.path), ("ingest/distorted", dist_info.path)]
    stats = runner.map("ingest", _tasks.ingest_task, [(run, sources, dist_info.shape, b) for b in blocks])
    for k, info in enumerate((ref_info, dist_info)):
        tiles.check_stats(sum((s[k] for s in stats[1:]), stats[0][k]), info.path)
    group.attrs["ingest_complete"] = True


def detect(reference, distorted, output, *, config=None, scheduler="threads", workers=None, overwrite=False,
           resume=False, geotiff=None):
    """Register ``distorted`` against ``reference`` and write the change store.

    Parameters
    ----------
    reference, distorted : str or path-like
        Images (GeoTIFF, PNG/JPEG, NPY or a zarr array) of the same size.
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

    Returns
    -------
    dict
        Summary: timings, threshold, tile counts, gain range, output path.

    Raises
    ------
    InputError
        Unusable inputs (unreadable, empty, constant, NaN, different sizes) or an
        existing output without ``overwrite``.
    """
    t_start = time.perf_counter()
    config = config or DetectConfig()
    ref_info = tiles.probe_image(reference)
    dist_info = tiles.probe_image(distorted)
    if ref_info.shape != dist_info.shape:
        raise InputError(f"{dist_info.path}: size {dist_info.shape} differs from the reference "
                         f"{ref_info.path} {ref_info.shape}; give images of the same size")
    shape = dist_info.shape
    camera = ops.Camera.for_shape(shape, focal=config.focal)
    params = config.registration.resolved(camera)
    halo = config.overlap if config.overlap is not None else default_overlap(params, camera, shape)
    grid = tiles.TileGrid(shape, config.tile or default_tile(shape), halo)
    axes = params.axes
    key = _run_key(ref_info, dist_info, config, grid)
    blocks = _block_grid(grid)
    group = tiles.create_result_store(output, _specs(grid, len(axes)), {"run_key": key}, overwrite=overwrite,
                                      resume=resume)
    store = str(tiles.partial_path(output))
    run = _tasks.RunStore(store, key)
    if resume and group.attrs.get("run_key") != key:
        raise InputError(f"{output}: the interrupted run had other inputs or parameters; run without --resume")
    timings = {}
    try:
        with open_runner(scheduler, workers=workers) as runner:
            log.info("%s: %d x %d px, %d tiles of %d px, halo %d px, scheduler %s", dist_info.path, shape[0],
                     shape[1], len(grid), grid.tile, grid.halo, scheduler)
            t0 = time.perf_counter()
            _ingest(runner, group, run, ref_info, dist_info, blocks)
            timings["ingest_s"] = time.perf_counter() - t0

            t0 = time.perf_counter()
            done = _tile_done(group)
            todo = sorted((t for t in grid if not done[t.index]), key=lambda t: -_expected_cost(t, camera))
            if resume:
                log.info("resume: %d of %d tiles already registered", len(grid) - len(todo), len(grid))
            stats = runner.map("register", _tasks.register_task, [(run, t, camera, params) for t in todo])
            timings["register_s"] = time.perf_counter() - t0
            timings["tiles_registered"] = len(todo)
            if stats:
                timings["kernel_s_sum"] = float(sum(s["kernel_s"] for s in stats))
                timings["read_s_sum"] = float(sum(s["read_s"] for s in stats))
                timings["write_s_sum"] = float(sum(s["write_s"] for s in stats))

            t0 = time.perf_counter()
            paths, states, hist, residual_hists, gains = _tile_results(group)
            fused, agree, worst = _agreement(paths, states, grid, camera, axes)
            resolve = _outliers(worst, ops.residual_median(residual_hists), config.agreement)
            if resolve:
                log.info("re-solving %d tile(s) whose path disagrees with their band: %s", len(resolve), resolve)
                args = []
                for ty, tx in resolve:
                    tile = grid[ty, tx]
                    rows = tile.core[0]
                    others = np.delete(paths[rows], tx, axis=1)
                    prior = _fuse(others, np.delete(states[rows], tx, axis=1))
                    args.append((run, tile, camera, params, prior))
                runner.map("re-solve", _tasks.register_task, args)
                paths, states, hist, _, gains = _tile_results(group)
                fused, agree, worst = _agreement(paths, states, grid, camera, axes)
            group["trajectory"][:] = fused.astype(np.float32)
            group["tile_trajectory"][:] = paths.astype(np.float32)
            group["tile_row_state"][:] = states
            group["gain"][:] = gains.astype(np.float32)
            group["tile_agreement"][:] = agree.astype(np.float32)
            timings["fuse_s"] = time.perf_counter() - t0

            t0 = time.perf_counter()
            threshold = ops.change_threshold(hist, params=config.changes)
            labelled = runner.map("label", _tasks.label_task,
                                  [(run, b, shape, threshold, config.changes) for b in blocks])
            summaries = {s.index: s for s, _ in labelled}
            offsets, root, area, peak = tiles.merge_tile_labels(summaries, blocks.grid_shape)
            keep_global = ops.keep_components(area, peak, threshold, params=config.changes)
            kept = {}  # block index -> keep flag per local label, for blocks that keep any
            for b in blocks:
                n = len(summaries[b.index].area)
                keep = keep_global[root[offsets[b.index]:offsets[b.index] + n]].copy()
                keep[0] = False
                if keep.any():
                    kept[b.index] = (b.core, keep)
            stored_path = fused.astype(np.float32).astype(np.float64)  # as the store holds it
            args = []
            for b in blocks:
                window = b.grown(grid.halo, shape)
                pieces = [kept[i] for i in blocks.covering(window) if i in kept]
                if pieces:
                    args.append((run, b, window, pieces, stored_path[window[0]], camera, axes, config.changes))
            masked = runner.map("masks", _tasks.mask_task, args)
            changed = sum(n for n, _ in masked)
            timings["changes_s"] = time.perf_counter() - t0
            timings["changes_compute_s_sum"] = float(sum(c for _, c in labelled + masked))
            tasks_per_tile = runner.tasks_run / len(grid)

        timings["total_s"] = time.perf_counter() - t_start
        summary = {
            "output": str(output),
            "shape": list(shape),
            "tiles": list(grid.grid_shape),
            "tile_size": grid.tile,
            "halo": grid.halo,
            "threshold": threshold,
            "changed_pixels": int(changed),
            "changed_fraction": changed / float(shape[0] * shape[1]),
            "components": int(keep_global.sum()),
            "gain_min": float(np.nanmin(gains)),
            "gain_max": float(np.nanmax(gains)),
            "resolved_tiles": [list(t) for t in resolve],
            "tile_agreement_px_max": float(np.nanmax(agree)) if np.isfinite(agree).any() else None,
            "tasks_per_tile": tasks_per_tile,
            "megapixels_per_s": shape[0] * shape[1] / 1e6 / timings["total_s"],
            "timings": timings,
        }
        attrs = {
            "rsmb_version": VERSION,
            "run_key": key,
            "parameters": dataclasses.asdict(config),
            "pose_axes": list(axes),
            "pose_units": [ops.AXIS_UNITS[a] for a in axes],
            "tile_grid": {"shape": list(shape), "tile": grid.tile, "halo": grid.halo, "block": blocks.tile,
                          "tiles": list(grid.grid_shape), "row_edges": grid.row_edges.tolist(),
                          "col_edges": grid.col_edges.tolist()},
            "camera": {"focal_px": camera.focal, "center_xy": list(camera.center_xy)},
            "inputs": {"reference": {"path": ref_info.path, "sha256": ref_info.sha256},
                       "distorted": {"path": dist_info.path, "sha256": dist_info.sha256}},
            "scheduler": scheduler,
            "summary": summary,
            **dist_info.geo.to_attrs(),
        }
        if not ref_info.geo.is_empty:
            attrs["reference_georeferencing"] = ref_info.geo.to_attrs()
        group.attrs.update(tiles.jsonable(attrs))
        group["trajectory"].attrs.update({"pose_axes": list(axes), "units": [ops.AXIS_UNITS[a] for a in axes]})
        for name in ("work", "ingest"):
            del group[name]
        final = tiles.finalize_result_store(store, output, overwrite=overwrite)
        if geotiff is not None:
            _write_geotiffs(final, geotiff, ref_info, dist_info)
        log.info("wrote %s: %d changed px (threshold %.3f), %.2f MP/s", final, changed, threshold,
                 summary["megapixels_per_s"])
        return summary
    except BaseException as error:
        # an interruption keeps what a --resume can continue; unusable inputs do not
        if isinstance(error, InputError) or not _resume_safe(group):
            tiles.abort_result_store(store)
        raise


def _resume_safe(group):
    """An interrupted run keeps its partial store when some tile finished, so that
    ``--resume`` can continue it; otherwise the partial store is removed."""
    try:
        return bool(_tile_done(group).any())
    except Exception:  # noqa: BLE001 - store already gone or unreadable
        return False


def _write_geotiffs(store, directory, ref_info, dist_info):
    from pathlib import Path

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    group = tiles.open_result_store(store)
    tiles.write_geotiff(directory / "change_mask.tif", group["change_mask"], dist_info.geo)
    tiles.write_geotiff(directory / "change_mask_reference.tif", group["change_mask_reference"], ref_info.geo)
    tiles.write_geotiff(directory / "change_score.tif", group["change_score"], dist_info.geo)
