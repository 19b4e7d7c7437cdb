"""The ground registered without what is not ground (METHOD.md section 3,
item 8: only the background layer is registered).

A row's eq. 13 is a Huber regression, robust to a few changed pixels, but not
to a large, high-contrast object that moves *coherently*: a roof nearer than
the ground moves by ``1 / rho`` times the camera's translation, so a row
crossing it can put its weights on the roof's pose instead of the ground's,
and where the ground is smooth (little texture to resist) the roof wins.  The
propagation then follows the roof for the rows it spans, the ground of those
rows is misregistered across the whole row, and the misfit becomes false
changes and spoils the depth-layer step.

:func:`reground` finds the rows that candidate changes touch and whose pose
strays from the path of the rows that none touches (interpolated across
them), and solves them again on the ground alone, around that path: the
pixels of the row that the path leaves unexplained (the weights of the
nearest untouched row, the ground's blur, moved onto the path; grown by a
margin for blurred rims) are left out of the fit.  A row whose pixels the
path mostly fails to explain is a real turn of the path and is left as it
is; a re-solved row keeps its new weights when they fit its ground better
than the old ones.  The registered row and its change term are then rendered
over the whole row.
"""

from typing import NamedTuple

import cv2
import numpy as np
from scipy import ndimage

from .._oracle import _huber_loss, optimal_chi
from .._timing import StageClock
from ..changes._changes import large_components, over_threshold
from ._propagate import _px_per_unit
from ._rowproblem import _centroid, _RowProblem, _shift_margin, _Solver, _spread
from ._start import _adapted_half_width

__all__ = ["reground"]

#: A touched row is solved again when its pose moves the window's farthest
#: pixel by more than this (px) away from the path interpolated over the
#: untouched rows (the propagation's own tolerance, ``DRIFT_PX``).
STRAY_PX = 0.75
#: Pixels (along the row) around unexplained ones also left out of the fit (blurred rims).
RIM_PX = 3
#: A row keeps its new weights when their eq. 13 cost on its ground is at most
#: this factor of the old weights'.
ACCEPT = 1.0
#: A row is left as it is when the path explains less than this share of its
#: valid pixels.
MIN_GROUND = 0.5


def reground(registration, reference, distorted, *, camera, params, threshold, min_area=20,
             reference_origin_yx=(0, 0), distorted_origin_yx=(0, 0), distorted_valid=None):
    """Solve again, on the ground alone, the rows that candidate changes pulled off the path.

    Parameters
    ----------
    registration : Registration
        Of ``distorted`` against ``reference`` (:func:`ops.register`); updated
        in place and returned.
    reference : ndarray, shape (Hr, Wr), float32
        The reference window the registration used (NaN for no-data).
    distorted : ndarray, shape (H, W), float32
        The capture window, as the registration fitted it (no-data zeroed).
    camera : Camera
        Intrinsics of the whole image.
    params : RegistrationParams
        The registration's parameters.
    threshold : float
        Change threshold (score units): pixels with ``|chi|`` above it, in
        8-connected components of at least ``min_area`` pixels, are candidates.
    reference_origin_yx, distorted_origin_yx : tuple of int
        The windows' positions in the whole image.
    distorted_valid : ndarray of bool, shape (H, W), optional

    Returns
    -------
    Registration
        With ``registered``, ``chi``, ``valid``, ``trajectory``, ``row_weights``
        and ``row_gain`` replaced on the rows solved again; their numbers in
        ``timings["regrounded_rows"]``, the CPU-seconds spent in
        ``timings["reground_s"]``.
    """
    reg = registration
    reg.timings["regrounded_rows"] = 0
    if params.shutter != "rolling":
        return reg
    with StageClock(reg.timings).stage("reground"):
        return _reground(reg, reference, distorted, camera, params, threshold, min_area, reference_origin_yx,
                         distorted_origin_yx, distorted_valid)


def _reground(reg, reference, distorted, camera, params, threshold, min_area, reference_origin_yx,
              distorted_origin_yx, distorted_valid):
    """:func:`reground`'s work on a rolling-shutter registration ``reg``."""
    params = params.resolved(camera)
    outliers = _outliers(reg, threshold, min_area)
    dims = len(params.axes)
    solved = reg.row_state == 1
    touched = outliers.any(axis=1) & solved
    clean = solved & ~touched
    if not touched.any() or clean.sum() < 2:
        return reg
    rows = np.arange(len(solved))
    prior = np.stack([np.interp(rows, rows[clean], reg.trajectory[clean, d]) for d in range(dims)], axis=1)
    dist = np.asarray(distorted, np.float32)
    if reg.column_gain is not None:  # the rows fitted the capture without its gain slope
        dist = (dist / reg.column_gain).astype(np.float32)
    full_valid = np.ones(dist.shape, bool) if distorted_valid is None else np.asarray(distorted_valid, bool)
    problem = _RowProblem(np.asarray(reference, np.float32), dist, full_valid, camera, reference_origin_yx,
                          distorted_origin_yx, params.axes, params.step, _shift_margin(params, prior),
                          int(np.ceil(3 * _ty_half_width(params))) + 4, reg.slow)
    stray = np.abs(reg.trajectory[:, :dims] - prior) * _px_per_unit(problem)
    todo = np.nonzero(touched & (stray.max(axis=1) > STRAY_PX))[0]
    if not todo.size:
        return reg
    space = params.space.widened(_adapted_half_width(params.space, _blur_spread(reg, clean, dims)))
    run = _Ground(reg, problem, _Solver(problem, params), space, dist, full_valid, params, float(threshold))
    clean_rows = np.nonzero(clean)[0]
    for i in todo:
        nearest = int(clean_rows[np.argmin(np.abs(clean_rows - i))])
        reg.timings["regrounded_rows"] += _resolve_row(run, i, prior[i], nearest)
    return reg


class _Ground(NamedTuple):
    """What solving rows on the ground needs: the registration (updated), the
    row problem and its solver, the row neighbourhood, the capture as the rows
    fitted it, its valid pixels, the parameters and the change threshold."""

    reg: object
    problem: object
    solver: object
    space: object
    dist: np.ndarray
    full_valid: np.ndarray
    params: object
    threshold: float


def _ty_half_width(params):
    return max([params.half_width[d] for d, a in enumerate(params.axes) if a == "ty"] + [0])


def _outliers(reg, threshold, min_area):
    """Candidate changes (components of at least ``min_area`` pixels) grown by :data:`RIM_PX`."""
    candidates = over_threshold(reg.chi, reg.valid, threshold)
    if not candidates.any():
        return candidates
    size = 2 * RIM_PX + 1
    # cv2's square dilation (separable, outside the window counts as empty)
    # gives scipy's binary_dilation with a square of ones at a tenth of the CPU
    grown = cv2.dilate(large_components(candidates, min_area).astype(np.uint8), np.ones((size, size), np.uint8))
    return grown.astype(bool)


def _blur_spread(reg, clean, dims):
    """Median extent (per axis) of the untouched rows' weights around their centroid."""
    spreads = []
    for i in np.nonzero(clean)[0][::4]:
        poses, w = reg.row_weights.get(int(i), (None, None))
        if poses is not None and len(w):
            spreads.append(_spread(poses[:, :dims], w, _centroid(poses[:, :dims], w)))
    return np.median(spreads, axis=0) if spreads else np.zeros(dims)


def _astray(run, i, center, g, nearest):
    """Pixels of row ``i`` that the weights of the nearest untouched row
    ``nearest`` (the ground's blur), moved onto the path at ``center``, leave
    above ``threshold`` (grown by :data:`RIM_PX`): what does not move with the
    ground (a roof the row followed scores low where it was fitted, and high
    here)."""
    poses, w = run.reg.row_weights.get(int(nearest), (None, None))
    out = np.zeros(g.shape, bool)
    if poses is None or not len(w):
        return out
    step = run.problem.steps
    moved = poses + np.round((center - _centroid(poses, w)) / step) * step
    run.problem.dist_valid = run.full_valid
    a, _, valid = run.problem.build([i], np.rint(moved / step).astype(np.int64), moved)
    out = valid & (np.abs(g - (w @ a).astype(np.float64)) > run.threshold)
    return ndimage.binary_dilation(out, structure=np.ones(2 * RIM_PX + 1, bool))


def _resolve_row(run, i, center, nearest):
    """Row ``i`` solved on its ground pixels around ``center``; kept when it fits
    those pixels better than before (returns 1), else left as it was (0)."""
    reg, problem, params = run.reg, run.problem, run.params
    g = run.dist[i].astype(np.float64)
    ground = run.full_valid.copy()
    ground[i] &= ~_astray(run, i, center, g, nearest)
    if ground[i].sum() < MIN_GROUND * max(run.full_valid[i].sum(), 1):
        return 0  # the path does not fit most of the row: a real turn of it, not a pull
    problem.dist_valid, problem.dist_all_valid = ground, False
    index, poses, w, _, fitted = run.solver.solve([i], run.space, center)
    if w.sum() <= 0 or not run.solver.last_converged:
        return 0
    old = reg.registered[i] if reg.column_gain is None else reg.registered[i] / reg.column_gain
    on = fitted & np.isfinite(old)
    keep = w > 0
    problem.dist_valid = run.full_valid  # render the whole row, candidates included
    a, _, valid = problem.build([i], index[keep], poses[keep])
    new = (w[keep] @ a).astype(np.float64)
    old_w = reg.row_weights.get(int(i), (None, np.zeros(0)))[1]
    if not on.any() or _cost(g[on] - new[on], w, run) > ACCEPT * _cost(g[on] - old[on], old_w, run):
        return 0
    gain = 1.0 if reg.column_gain is None else reg.column_gain
    reg.registered[i] = np.where(valid, new * gain, np.nan)
    r = np.where(valid, run.dist[i] * gain - reg.registered[i], 0.0)
    reg.chi[i] = np.where(valid, optimal_chi(r, lambda_chi=params.lambda_chi), 0.0)
    reg.valid[i] = valid
    reg.trajectory[i, :len(params.axes)] = _centroid(poses, w)
    reg.row_weights[int(i)] = (poses[keep], w[keep])
    reg.row_gain[i] = w.sum()
    return 1


def _cost(r, w, run):
    """Eq. 13 with the change term minimised out (Huber loss plus ``lambda_w ||w||_1``)."""
    return _huber_loss(r, run.solver.delta) + run.params.lambda_w * float(np.sum(w))
