"""Tile tasks: each reads its own windows from the zarr store, calls the ops
kernels and writes its core.  Registration runs per tile; ingest per block
of tiles (see ``pipeline.detection._plan._block_grid``), a :class:`tiles.Tile`
of the coarser grid; labelling and masks per group of neighbouring blocks
(:func:`block_groups`).  Top-level functions with plain
arguments, so any dask scheduler (threads, processes, distributed) can run
them."""

import functools
import threading
import time
from dataclasses import dataclass

import numpy as np
import zarr

from rsmb import ops
from rsmb import tiles
from rsmb.ops._timing import StageClock
from rsmb.ops.registration._start import SHARED_ROWS
from rsmb.tiles import ingest_core, read_padded
from rsmb.tiles._stitch import TileLabels

__all__ = []


def _specs(grid, dims, margin=0):
    """The run's arrays: outputs, scratch, and the ingested inputs (the reference
    with ``margin`` pixels around the capture grid)."""
    h, w = grid.shape
    t = grid.tile
    ny, nx = grid.grid_shape
    spec = tiles.ArraySpec
    return {
        # sensor frame: the capture's pixels as the rolling shutter recorded them (pixel dimensions only)
        "registered": spec((h, w), "float32", (t, t), ("row", "col"), float("nan")),
        "change_score": spec((h, w), "float32", (t, t), ("row", "col"), 0.0),
        "change_mask": spec((h, w), "uint8", (t, t), ("row", "col")),
        "parallax_mask": spec((h, w), "uint8", (t, t), ("row", "col")),
        "trajectory": spec((h, dims), "float32", (t, dims), ("row", "pose_axis"), float("nan")),
        "tile_trajectory": spec((h, nx, dims), "float32", (h, nx, dims), ("row", "tile_x", "pose_axis"), float("nan")),
        "tile_row_state": spec((h, nx), "uint8", (h, nx), ("row", "tile_x")),
        "gain": spec((ny, nx), "float32", (ny, nx), ("tile_y", "tile_x"), float("nan")),
        "tile_agreement": spec((ny, nx), "float32", (ny, nx), ("tile_y", "tile_x"), float("nan")),
        # ground frame: the reference grid (x, y and spatial_ref when georeferenced)
        "change_mask_reference": spec((h, w), "uint8", (t, t), ("y", "x"), ops.NO_EVIDENCE),
        "change_score_reference": spec((h, w), "float32", (t, t), ("y", "x"), float("nan")),
        "parallax_mask_reference": spec((h, w), "uint8", (t, t), ("y", "x"), ops.NO_EVIDENCE),
        # scratch, one chunk per tile, deleted when the run finishes
        "work/tile_rows": spec((h, nx, dims + 1), "float32", (t, 1, dims + 1), ("y", "tile_x", "column"),
                               float("nan"), compressed=False),
        "work/tile_summary": spec((ny, nx, _SUMMARY), "float64", (1, 1, _SUMMARY), ("tile_y", "tile_x", "value"),
                                  compressed=False),
        "work/labels": spec((h, w), "int32", (t, t), ("row", "col"), compressed=False),
        "work/explained": spec((h, w), "float32", (t, t), ("row", "col"), 0.0, compressed=False),
        "work/slow": spec((h, 3), "float32", (h, 3), ("y", "slow"), float("nan"), compressed=False),
        "work/tile_layers": spec((ny, nx, LAYER_SLOTS, len(LAYER_FIELDS)), "float64",
                                 (1, 1, LAYER_SLOTS, len(LAYER_FIELDS)), ("tile_y", "tile_x", "layer", "field"),
                                 float("nan"), compressed=False),
        "ingest/reference": spec((h + 2 * margin, w + 2 * margin), "float32", (t, t), ("y", "x"), float("nan"), compressed=False),
        "ingest/distorted": spec((h, w), "float32", (t, t), ("y", "x"), float("nan"), compressed=False),
    }


_HIST = (ops.RESIDUAL_BINS, ops.SCORE_BINS)
#: Depth layers a tile records (the largest), and what it records of each.
LAYER_SLOTS = 32
LAYER_FIELDS = ("row", "col", "pixels", "depth", "explained", "rmse")
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


def resume_safe(group):
    """An interrupted run keeps its partial store when some tile finished, so that
    ``--resume`` can continue it; otherwise the partial store is removed."""
    try:
        return bool(_tile_done(group).any())
    except Exception:  # noqa: BLE001 - store already gone or unreadable
        return False


@dataclass(frozen=True)
class RunStore:
    """The partial store of one run, as the tasks see it: its path and the run
    key.  The key names the inputs and parameters and with them the layout of
    every array, so a process opens each array of a run once and keeps it (an
    open costs milliseconds; a tile task is a few of them)."""

    path: str
    key: str
    reference_offset: int = 0  # the reference array holds capture pixel (r, c) at (r + offset, c + offset)
    intensity: ops.IntensityScale | None = None  # the inputs' common scale, known once ingested

    def read(self, name, rows, cols):
        """Window ``rows``, ``cols`` of the capture grid of the ingested image
        ``name`` ("reference" or "capture") on the common scale, NaN where
        clipped, no-data or beyond the array."""
        return self.on_scale(self.ingested(name, rows, cols), name)

    def ingested(self, name, rows, cols):
        """The same window as ingested: before the common scale (its clip
        levels apply here), NaN where no-data or beyond the array."""
        if name == "reference":
            m = self.reference_offset
            return read_padded(_array(self, "ingest/reference"), slice(rows.start + m, rows.stop + m),
                               slice(cols.start + m, cols.stop + m))
        return read_padded(_array(self, "ingest/distorted"), rows, cols)

    def on_scale(self, values, name):
        """Ingested ``values`` of image ``name`` on the common scale, NaN where clipped."""
        return values if self.intensity is None else self.intensity.apply(values, name)


_OPENING = threading.Lock()


def _array(store, name):
    """The array ``name`` of the run's store, opened once per process and
    run (not once per thread that asks first): a store that gains its common
    intensity scale is the same store."""
    with _OPENING:
        return _open_array(store.path, store.key, name)


@functools.lru_cache(maxsize=32)
def _open_array(path, key, name):  # ``key``: the run, whose key fixes every array's layout
    # the array's own metadata only: opening the group first reads its metadata and probes for zarr v2's.
    # A compressed array's chunks are written even when they equal the fill value: zarr would otherwise
    # compare each chunk with it first, a whole pass over the chunk (slowest on the uint8 masks) that costs
    # more than compressing and writing the few that turn out empty.  Uncompressed scratch arrays are
    # read and written as their chunk files (:func:`tiles.chunk_files`: a window reads only the rows of
    # each chunk it needs), which keep the comparison: an empty chunk there (the reference's margin
    # beyond the image) is a whole chunk's bytes.
    array = zarr.open_array(store=path, path=name, mode="r+", zarr_format=3)
    return array.with_config({"write_empty_chunks": True}) if array.compressors else tiles.chunk_files(array)


def cpu_timed(func, *args):
    """``(func(*args), CPU-seconds of the calling thread)``: a task's own CPU
    time, wherever the scheduler runs it."""
    start = time.thread_time()
    out = func(*args)
    return out, time.thread_time() - start


def ingest_task(store, name, read, block, offset, overview=None):
    """Ingest one block of the array ``name`` from ``read(rows, cols)`` (see
    :func:`tiles.ingest_core`).  Returns its WindowStats and, given
    ``overview`` (factor, phase), its part of the overview's cells."""
    return ingest_core(read, block, _array(store, name), offset, overview)


def overview_task(store, name, block, factor, phase):
    """One block's part of the cells of the overview of the ingested image
    ``name`` ("reference" or "capture"), read from the store
    (:func:`tiles.cell_sums`): what the ingest gives when the run resumes
    after it."""
    array = _array(store, "ingest/reference" if name == "reference" else "ingest/distorted")
    rows, cols = block.core
    return tiles.cell_sums(array[rows, cols], (rows.start, cols.start), factor, phase)


def _slow_prior(store, tile, params):
    """The tile's rows of the slow path found on the overview (``work/slow``),
    or None (none found, or none asked for)."""
    if not params.slow_axes:
        return None
    found = _array(store, "work/slow")[tile.core[0]].astype(np.float64)
    if not np.isfinite(found).all():
        return None
    return ops.SlowPath(found[:, :2], found[:, 2])


def start_task(store, band, camera, params):
    """Stage 1a: the start a band of tiles (``band``: the tiles of one grid
    row, which hold the same capture rows) shares: :func:`ops.find_start` on
    the windows of its most textured tile, the one whose middle rows (those
    the start search covers, :data:`SHARED_ROWS` either side) have the largest mean absolute difference
    between neighbouring pixels of a row, no-data counted as flat.  The
    choice looks at every tile of the band, done or not, so a ``--resume``
    finds the same start.  Returns an :class:`ops.StartPose` or None."""
    def texture(tile):
        rows = tile.core[0]
        mid = (rows.start + rows.stop) // 2
        window = store.read("capture", slice(max(rows.start, mid - SHARED_ROWS), min(rows.stop, mid + SHARED_ROWS)),
                            tile.core[1])
        return float(np.nansum(np.abs(np.diff(window, axis=1)))) / window.size

    tile = max(band, key=texture)  # the first of equals: the leftmost
    capture = store.read("capture", *tile.core)
    return ops.find_start(store.read("reference", *tile.window), np.nan_to_num(capture), camera=camera, params=params,
                          reference_origin_yx=tile.window_origin, distorted_origin_yx=tile.core_origin,
                          distorted_valid=np.isfinite(capture), slow=_slow_prior(store, tile, params))


def register_task(store, tile, camera, params, changes, prior=None, band_start=None):
    """Stage 1: read one tile's windows, run the method on them
    (:func:`ops.run_method`; ``band_start``: its band's start, from :func:`start_task`)
    and write its core outputs.  The tile's summary row
    (histograms, gain, seconds, and 1 in its last column) is written last: it
    marks the tile complete for ``--resume``.

    Returns
    -------
    dict
        Seconds spent (read, kernel, write: wall time), the tile's gain, and
        ``stages``: CPU-seconds of this task's thread per stage (``read``,
        ``slow``, ``start``, ``rows``, ``reanchor``, ``gain_slope``,
        ``reground``, ``depth``, ``score``, ``write``), and ``shared_start``:
        1 when the tile's rows started from its band's start.
    """
    start = time.perf_counter()
    clock = StageClock()
    ty, tx = tile.index
    h, w = tile.core_shape
    with clock.stage("read"):
        reference = store.ingested("reference", *tile.window)
        capture = store.ingested("capture", *tile.core)
    read = time.perf_counter() - start
    found = ops.run_method(reference, capture, camera=camera, params=params, changes=changes,
                           intensity=store.intensity, reference_origin_yx=tile.window_origin,
                           distorted_origin_yx=tile.core_origin, prior=prior, slow=_slow_prior(store, tile, params),
                           start=band_start)
    result, hist = found.registration, found.histogram
    tile.check_core(found.registered)
    write_start = time.perf_counter()
    with clock.stage("write"):
        registered = found.registered if store.intensity is None else store.intensity.to_input(found.registered)
        _array(store, "registered")[tile.core] = registered  # in the capture's units
        _array(store, "change_score")[tile.core] = found.score
        _array(store, "parallax_mask")[tile.core] = found.parallax.astype(np.uint8)
        _array(store, "work/explained")[tile.core] = (np.zeros((h, w), np.float32) if found.explained is None
                                                      else found.explained)  # a chunk of 0 (nothing explained) is no file
        _array(store, "work/tile_layers")[ty, tx] = _layer_table(found.components, tile)
        _array(store, "work/tile_rows")[tile.core[0], tx] = np.concatenate(
            [result.trajectory, result.row_state[:, None]], axis=1).astype(np.float32)
        seconds = time.perf_counter() - start
        _array(store, "work/tile_summary")[ty, tx] = np.concatenate(
            [hist.residual, hist.score, [result.gain, seconds, 1.0]])
    stages = {k[:-2]: v for k, v in {**found.timings, **clock.seconds}.items() if k.endswith("_s")}
    return {"index": tile.index, "seconds": seconds, "read_s": read, "write_s": time.perf_counter() - write_start,
            "kernel_s": write_start - start - read, "pixels": h * w, "gain": result.gain, "stages": stages,
            "shared_start": int(result.timings.get("shared_start", 0))}


def _layer_table(components, tile):
    """A tile's depth layers as rows of :data:`LAYER_FIELDS` in image pixels,
    the largest :data:`LAYER_SLOTS` of them, NaN in unused slots."""
    table = np.full((LAYER_SLOTS, len(LAYER_FIELDS)), np.nan)
    for k, c in enumerate(sorted(components, key=lambda c: -c["pixels"])[:LAYER_SLOTS]):
        c = dict(c, row=c["row"] + tile.core_origin[0], col=c["col"] + tile.core_origin[1])
        table[k] = [c[f] for f in LAYER_FIELDS]
    return table


def layer_components(group):
    """Every tile's depth layers from the store's scratch table: a list of dicts
    of :data:`LAYER_FIELDS` (image pixels), the largest first."""
    table = group["work/tile_layers"][:].reshape(-1, len(LAYER_FIELDS))
    rows = table[np.isfinite(table[:, 0])]
    out = [dict(zip(LAYER_FIELDS, (float(v) for v in row))) for row in rows]
    for c in out:
        c["pixels"] = int(c["pixels"])
    return sorted(out, key=lambda c: -c["pixels"])


#: Most pixels a group of blocks of a label or mask task spans along its block
#: row (:func:`block_groups`): four blocks of 1024 px; one block however wide.
GROUP_WIDTH = 4096


def block_groups(blocks, width=GROUP_WIDTH, least=2):
    """The blocks of ``blocks`` (a :class:`tiles.TileGrid`) in groups of
    neighbours along a block row whose cores span at most ``width`` px (one
    block at least), narrower where that leaves fewer than ``least`` groups
    (the workers: every one of them busy), down to a block each.  A label or
    mask task reads one window for its group: zarr decodes a whole chunk for
    any part of it, so the halo of each block alone would decode its
    neighbours' chunks again, once per block that reads them.  The width
    bounds a task's memory as a block's size did."""
    while True:
        groups = []
        for ty in range(blocks.grid_shape[0]):
            row = [blocks[ty, tx] for tx in range(blocks.grid_shape[1])]
            group = [row[0]]
            for block in row[1:]:
                if block.core[1].stop - group[0].core[1].start > width:
                    groups.append(group)
                    group = []
                group.append(block)
            groups.append(group)
        if len(groups) >= least or all(len(g) == 1 for g in groups):
            return groups
        width //= 2


def _union(windows):
    """The smallest window (tuple of slices) holding every one of ``windows``."""
    return tuple(slice(min(w[d].start for w in windows), max(w[d].stop for w in windows)) for d in range(2))


def label_task(store, blocks, shape, threshold, change_params):
    """Stage 2: label the change candidates of each block's core of a group
    (:func:`block_groups`), its score grown by the margin the local
    half-maximum test needs, with what the depth explained there
    (``work/explained``); the group's score is read once.  Returns per
    block (TileLabels, compute seconds, pixels of the core without evidence:
    NaN score)."""
    windows = [b.grown(change_params.margin, shape) for b in blocks]
    union = _union(windows)
    scores = _array(store, "change_score")[union]
    explained = _array(store, "work/explained")[union]
    out = []
    for block, window in zip(blocks, windows):
        inside = _inside(window, union)
        score = scores[inside]
        start = time.perf_counter()
        candidates = ops.change_candidates(score, threshold, params=change_params, explained=explained[inside])
        core = _inside(block.core, window)
        labels, area, peak = ops.label_components(candidates[core], score[core])
        silent = int(np.isnan(score[core]).sum())
        compute = time.perf_counter() - start
        if len(area) > 1:  # unwritten chunks read as 0: a block without candidates writes nothing
            _array(store, "work/labels")[block.core] = labels
        out.append((TileLabels.from_labels(block.index, labels, area, peak), compute, silent))
    return out


def _inside(part, window):
    """``part`` (slices in image coordinates) relative to ``window``."""
    return tuple(slice(p.start - w.start, p.stop - w.start) for p, w in zip(part, window))


def mask_task(store, jobs, trajectory, camera, axes, change_params):
    """Stage 3: each block's changes of a group (:func:`block_groups`) in both
    frames; ``jobs`` lists per block (block, window, kept), the group's
    windows read once.  The kept labels of the blocks under a block's window
    (core plus halo) make the window's mask, small holes are filled there (a
    hole cut by a seam is filled like any other), pixels with no evidence (a
    NaN score) are marked :data:`ops.NO_EVIDENCE` in it and in the parallax
    mask, their cores are written, and the window carried by the fused
    ``trajectory`` (of the windows' rows, which the group's blocks share)
    gives the block's mask, score and parallax mask in the reference grid
    (:func:`ops.to_ground`).  Every block runs: the no-evidence marks and the
    ground frame are needed whether or not a change is near.

    ``kept`` lists (core, keep flags per local label) of the blocks under the
    window that kept some label.  Returns per block (changed core pixels,
    compute seconds).
    """
    union = _union([window for _, window, _ in jobs])
    all_labels = _array(store, "work/labels")[union] if any(kept for _, _, kept in jobs) else None
    all_scores = _array(store, "change_score")[union]
    all_parallax = _array(store, "parallax_mask")[union]
    out = []
    for block, window, kept in jobs:
        inside = _inside(window, union)
        labels = None if all_labels is None else all_labels[inside]
        score, parallax = all_scores[inside], all_parallax[inside]
        start = time.perf_counter()
        mask = np.zeros(score.shape, dtype=bool)
        for core, keep in kept:
            overlap = tuple(slice(max(c.start, w.start), min(c.stop, w.stop)) for c, w in zip(core, window))
            part = _inside(overlap, window)
            mask[part] = keep[labels[part]]
        if kept:
            mask = ops.fill_holes(mask, params=change_params)
        sensor = ops.evidence_mask(mask, score)
        parallax = np.where(np.isfinite(score), parallax == 1, ops.NO_EVIDENCE).astype(np.uint8)
        ground = ops.to_ground(sensor, score, parallax, trajectory[inside[0]], axes=axes, camera=camera,
                               reference_shape=block.core_shape, reference_origin_yx=block.core_origin,
                               distorted_origin_yx=(window[0].start, window[1].start))
        core = _inside(block.core, window)
        compute = time.perf_counter() - start
        _array(store, "change_mask")[block.core] = sensor[core]
        _array(store, "parallax_mask")[block.core] = parallax[core]
        _array(store, "change_mask_reference")[block.core] = ground.mask
        _array(store, "change_score_reference")[block.core] = ground.score
        _array(store, "parallax_mask_reference")[block.core] = ground.parallax
        out.append((int(mask[core].sum()), compute))
    return out
