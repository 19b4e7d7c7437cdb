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
    """Stage 1: register one tile and write its core outputs.

    Returns
    -------
    dict
        Seconds spent and the tile's gain.
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
    group["work/tile_summary"][ty, tx] = np.concatenate([hist.residual, hist.score, [result.gain, seconds]])
    group["work/tile_done"][ty, tx] = np.uint8(1)  # last: the tile is complete
    return {"index": tile.index, "seconds": seconds, "read_s": read, "write_s": time.perf_counter() - write_start,
            "kernel_s": write_start - start - read, "pixels": h * w, "gain": result.gain}


def label_task(store, tile, shape, threshold, change_params):
    """Stage 2: label the change candidates of one core (score read with the
    margin the local half-maximum test needs).  Returns (TileLabels, compute
    seconds); the next two stages also return their compute seconds."""
    group = _open(store)
    pad = change_params.half_max_window // 2 + 1
    r0, r1 = max(tile.core[0].start - pad, 0), min(tile.core[0].stop + pad, shape[0])
    c0, c1 = max(tile.core[1].start - pad, 0), min(tile.core[1].stop + pad, shape[1])
    score = group["change_score"][r0:r1, c0:c1]
    start = time.perf_counter()
    candidates = ops.change_candidates(score, threshold, params=change_params)
    core = (slice(tile.core[0].start - r0, tile.core[0].stop - r0), slice(tile.core[1].start - c0, tile.core[1].stop - c0))
    labels, area, peak = ops.label_components(candidates[core], score[core])
    compute = time.perf_counter() - start
    if len(area) > 1:  # unwritten chunks read as 0: a tile without candidates writes nothing
        group["work/labels"][tile.core] = labels
    return TileLabels.from_labels(tile.index, labels, area, peak), compute


def mask_task(store, tile, keep, change_params):
    """Stage 3: keep the labels of components that passed, fill small holes."""
    if not keep.any():
        return 0, 0.0  # change_mask reads 0 where nothing was written
    group = _open(store)
    labels = group["work/labels"][tile.core]
    start = time.perf_counter()
    mask = ops.fill_holes(keep[labels], params=change_params)
    compute = time.perf_counter() - start
    group["change_mask"][tile.core] = mask.astype(np.uint8)
    return int(mask.sum()), compute


def reference_mask_task(store, tile, shape, camera, axes, halo):
    """Stage 4: the tile's changes in the reference grid, from the change mask of
    its window and the fused trajectory."""
    group = _open(store)
    r0, r1 = max(tile.core[0].start - halo, 0), min(tile.core[0].stop + halo, shape[0])
    c0, c1 = max(tile.core[1].start - halo, 0), min(tile.core[1].stop + halo, shape[1])
    mask = group["change_mask"][r0:r1, c0:c1]
    if not mask.any():
        return 0, 0.0
    trajectory = group["trajectory"][r0:r1].astype(np.float64)
    start = time.perf_counter()
    ref = ops.changes_to_reference(mask, trajectory, axes=axes, camera=camera, reference_shape=tile.core_shape,
                                   reference_origin_yx=tile.core_origin, distorted_origin_yx=(r0, c0))
    compute = time.perf_counter() - start
    group["change_mask_reference"][tile.core] = ref
    return int(ref.sum()), compute
