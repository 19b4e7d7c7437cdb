"""Tile tasks: each reads its own windows from the zarr store, calls the ops
kernels and writes its core.  Top-level functions with plain arguments, so any
dask scheduler (threads, processes, distributed) can run them."""

import time

import numpy as np
import zarr

import ops
from tiles import ingest_core, read_padded
from tiles._stitch import TileLabels

__all__ = []


def _open(store, mode="r+"):
    return zarr.open_group(store=str(store), mode=mode)


def ingest_task(store, name, path, shape, tile):
    """Ingest one tile of an input image (see :mod:`tiles._ingest`)."""
    return ingest_core(path, shape, tile, _open(store)[name])


def register_task(store, tile, camera, params, prior=None):
    """Stage 1: register one tile and write its core outputs.  The tile's
    summary row (histograms, gain, seconds, and 1 in its last column) is written
    last: it marks the tile complete for ``--resume``.

    Returns
    -------
    dict
        Seconds spent (read, kernel, write) and the tile's gain.
    """
    start = time.perf_counter()
    group = _open(store)
    ty, tx = tile.index
    h, w = tile.core_shape
    reference = read_padded(group["ingest/reference"], *tile.window)
    distorted = group["ingest/distorted"][tile.core]
    read = time.perf_counter() - start
    ref_valid = np.isfinite(reference)
    dist_valid = np.isfinite(distorted)
    result = ops.register(np.nan_to_num(reference), np.nan_to_num(distorted), camera=camera, params=params,
                          reference_origin_yx=tile.window_origin, distorted_origin_yx=tile.core_origin,
                          reference_valid=ref_valid, distorted_valid=dist_valid, prior=prior)
    tile.check_core(result.registered)
    score = np.abs(result.chi)
    residual = np.where(result.valid, distorted - result.registered, 0.0)
    hist = ops.score_histogram(residual, score, result.valid)
    write_start = time.perf_counter()
    group["registered"][tile.core] = result.registered
    group["change_score"][tile.core] = score.astype(np.float32)
    group["work/tile_rows"][tile.core[0], tx] = np.concatenate(
        [result.trajectory, result.row_state[:, None]], axis=1).astype(np.float32)
    seconds = time.perf_counter() - start
    group["work/tile_summary"][ty, tx] = np.concatenate(
        [hist.residual, hist.score, [result.gain, seconds, 1.0]])
    return {"index": tile.index, "seconds": seconds, "read_s": read, "write_s": time.perf_counter() - write_start,
            "kernel_s": write_start - start - read, "pixels": h * w, "gain": result.gain}


def label_task(store, tile, shape, threshold, change_params):
    """Stage 2: label the change candidates of one core (score read with the
    margin the local half-maximum test needs).  Returns (TileLabels, compute
    seconds)."""
    group = _open(store)
    window = tile.grown(change_params.half_max_window // 2 + 1, shape)
    score = group["change_score"][window]
    start = time.perf_counter()
    candidates = ops.change_candidates(score, threshold, params=change_params)
    core = _inside(tile.core, window)
    labels, area, peak = ops.label_components(candidates[core], score[core])
    compute = time.perf_counter() - start
    if len(area) > 1:  # unwritten chunks read as 0: a tile without candidates writes nothing
        group["work/labels"][tile.core] = labels
    return TileLabels.from_labels(tile.index, labels, area, peak), compute


def _inside(part, window):
    """``part`` (slices in image coordinates) relative to ``window``."""
    return tuple(slice(p.start - w.start, p.stop - w.start) for p, w in zip(part, window))


def mask_task(store, tile, window, kept, trajectory, camera, axes, change_params):
    """Stage 3: one tile's changes in both grids.  The kept labels of the tiles
    under its window (core plus halo) make the window's mask, small holes are
    filled there (a hole cut by a seam is filled like any other), the core is
    written, and the window's mask carried by the fused ``trajectory`` (rows of
    the window) gives the tile's changes in the reference grid.

    ``kept`` lists (core, keep flags per local label) of the tiles under the
    window that kept some label (tiles with none are not run: both masks read 0
    where nothing was written).  Returns (changed core pixels, compute seconds).
    """
    group = _open(store)
    labels = group["work/labels"][window]
    start = time.perf_counter()
    mask = np.zeros(labels.shape, dtype=bool)
    for core, keep in kept:
        part = _inside(tuple(slice(max(c.start, w.start), min(c.stop, w.stop)) for c, w in zip(core, window)), window)
        mask[part] = keep[labels[part]]
    mask = ops.fill_holes(mask, params=change_params)
    core_mask = mask[_inside(tile.core, window)]
    ref = ops.changes_to_reference(mask, trajectory, axes=axes, camera=camera, reference_shape=tile.core_shape,
                                   reference_origin_yx=tile.core_origin,
                                   distorted_origin_yx=(window[0].start, window[1].start))
    compute = time.perf_counter() - start
    if core_mask.any():
        group["change_mask"][tile.core] = core_mask.astype(np.uint8)
    if ref.any():
        group["change_mask_reference"][tile.core] = ref
    return int(core_mask.sum()), compute
