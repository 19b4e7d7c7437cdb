"""The whole capture at a coarser scale, and what it is for: the slow
out-of-plane part of the camera path (rx, ry; :mod:`ops.registration._slow`), found once
per image, where its effects are largest (the image's far corners) and before
any tile is registered.

Each tile then registers on a reference pre-warped by that slow part.  Found
on the image at a coarser scale, it costs the same small amount per image
up to 8192 px on a side (a fixed cost per capture of a survey night; beyond,
the overview grows with the image, at most 8 times coarser); where there is
none (an in-plane capture), the tiles pay nothing.  The fit runs as one task
on the runner, under its one-thread settings.
"""

import logging
import time

import numpy as np

from rsmb import ops
from rsmb import tiles

from . import _tasks

log = logging.getLogger("rsmb")

__all__ = ["overview_factor", "overview_specs", "slow_stage"]

#: The overview's smaller side is at least this many pixels.
OVERVIEW_SIDE = 512

#: The overview is at most this many times coarser than the capture: the
#: slow part's smallest effect worth keeping (``ops.registration._slow.SLOW_MIN_PX``
#: capture pixels) must stay about a tenth of an overview pixel or more, what a
#: dense flow resolves; 16 times coarser it is a twentieth.
OVERVIEW_MAX_FACTOR = 8


def overview_factor(shape):
    """The overview's reduction: the largest power of two that leaves the
    capture's smaller side at least :data:`OVERVIEW_SIDE` px (1 for small
    captures), at most :data:`OVERVIEW_MAX_FACTOR`."""
    factor = 1
    while min(shape) // (2 * factor) >= OVERVIEW_SIDE and 2 * factor <= OVERVIEW_MAX_FACTOR:
        factor *= 2
    return factor


def overview_specs(plan):
    """{"capture": (factor, phase), "reference": (factor, phase)}: how each
    ingested array's overview cells lie (the reference's aligned with the
    capture's through its margin); None when no slow part is asked for."""
    if not plan.params.slow_axes:
        return None
    factor = overview_factor(plan.shape)
    return {"capture": (factor, 0), "reference": (factor, plan.margin % factor)}


def slow_stage(runner, group, run, plan, timings, cells=None):
    """Stage 2b: the slow part of the path (``plan.params.slow_axes``) from the
    overviews of the ingested capture and reference on the common intensity
    scale, written to the store's ``work/slow`` (rx, ry in degrees, ty in px
    per capture row; NaN when there is none).  ``cells``: the overviews'
    :class:`tiles.CellSums` per block as the ingest made them ({"capture":
    [...], "reference": [...]}, in the plan's block order), else (a resumed
    run) made again from the store."""
    t0 = time.perf_counter()
    if not plan.params.slow_axes:
        return
    if not group.attrs.get("slow_complete"):
        group["work/slow"][:] = _find_slow(runner, run, plan, cells)
        group.attrs["slow_complete"] = True
    timings["slow_s"] = time.perf_counter() - t0
    found = group["work/slow"][:]
    if np.isfinite(found).any():
        log.info("slow out-of-plane rotation: rx %.2f..%.2f deg, ry %.2f..%.2f deg", np.nanmin(found[:, 0]),
                 np.nanmax(found[:, 0]), np.nanmin(found[:, 1]), np.nanmax(found[:, 1]))
    else:
        log.info("slow out-of-plane rotation: none found")


def _find_slow(runner, run, plan, cells):
    """(H, 3) float32: rx, ry, ty of every capture row, NaN without a slow part.
    The overviews come from ``cells`` or one task per block; the fit is one
    task of its own (it runs on the scheduler's workers, with their
    one-thread settings)."""
    specs, margin = overview_specs(plan), plan.margin
    blocks = {"capture": plan.blocks, "reference": plan.reference_blocks}
    shapes = {"capture": plan.shape, "reference": (plan.shape[0] + 2 * margin, plan.shape[1] + 2 * margin)}
    if cells is None:
        jobs = [(run, name, b, *specs[name]) for name in ("capture", "reference") for b in blocks[name]]
        parts = runner.map("overview", _tasks.overview_task, jobs)
        n = len(blocks["capture"])
        cells = {"capture": parts[:n], "reference": parts[n:]}
    capture, reference = (run.intensity.cell_means(*tiles.overview_from_sums(cells[name], shapes[name], *specs[name]),
                                                   specs[name][0] ** 2, name) for name in ("capture", "reference"))
    factor, phase = specs["reference"]
    offset = -((margin - phase) // factor)  # the reference overview's cell 0 in capture cells
    return runner.map("slow", _slow_task, [(reference, capture, offset, factor, plan.shape, plan.camera,
                                            plan.params.slow_axes, plan.params.slow_search)])[0]


def _slow_task(reference, capture, offset, factor, shape, cam, axes, search):
    """The slow part found on the overviews (``factor`` times coarser than the
    capture of ``shape``), at every capture row: (H, 3) float32."""
    camera = ops.Camera(cam.focal / factor, tuple((c - 0.5 * (factor - 1)) / factor for c in cam.center_xy))
    valid = np.isfinite(capture)
    out = np.full((shape[0], 3), np.nan, dtype=np.float32)
    if valid.sum() < 0.05 * valid.size:
        return out
    path = ops.estimate_slow(reference, np.nan_to_num(capture), valid, camera=camera,
                             reference_origin_yx=(offset, offset), distorted_origin_yx=(0, 0),
                             axes=axes, limit=2.0 * search, scale=factor)
    if path is not None:
        rows = path.at_rows(np.arange(shape[0]), factor=factor)
        out[:, :2], out[:, 2] = rows.rotation, rows.ty
    return out
