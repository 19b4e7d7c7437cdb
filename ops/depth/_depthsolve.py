"""Rows' weights and the dense depth map, estimated in turn (METHOD.md section
3, item 8, extended).

The depth-layer step keeps the rows' weights of the registered plane.  Where a
row holds several depths the registration smeared its weights over several
poses to fit them all at once, so every depth re-rendered with those weights
stays as blurred as the plane's.  With the depth map fixed, eq. 13 is solved
again per row with ``F_i`` built at each pixel's own depth (column ``k`` at
pixel ``j``: the reference sampled at pose ``tau_k`` with its translations and
scale times that pixel's relative inverse depth ``q_j``, rotations as they
are), and the depth step is run again with the new weights.

Rule: a round is kept only when eq. 13's total objective of the final model
(the Huber loss of ``g`` minus the re-rendered reference plus
``lambda_w`` times the weights' sum, over the pixels both models cover)
decreases; the first round that does not is dropped and the rounds stop.
Pixels of components found to be depth layers are left out of the re-solve
(the depth map does not hold their depth), and so are pixels still above the
change threshold (change candidates carry no evidence of the motion).  Later
rounds' depth maps may give a depth only to pixels the first one gave one or
left below the threshold: fitting the rows to the depths taken would otherwise
make a new object that took a depth by chance more consistent with it, round
after round, until it is explained away.  Symmetrically, what the first round
found to be parallax stays parallax in later rounds.  Only tiles whose depth map took a
depth on at least :attr:`AlternateParams.min_share` of their pixels pay for
it, and only rows holding such pixels are solved again.
"""

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from .._camera import full_poses
from ._depthmap import _geometry, _RowPoses, depth_map
from ._layers import LayerParams, depth_layers, rims_along, sees_a_layer_elsewhere
from .._oracle import _huber_loss, optimal_chi
from ..changes._changes import over_threshold
from ..registration._rowproblem import _centroid, _Solver
from ..registration._rowsolve import MAX_ADD, MAX_OUTER, TOL, _solve_huber_nn
from .._warp import _bilinear, _inverse_map, _point, _point_on_row, _row_map

__all__ = ["AlternateParams", "depth_step"]


@dataclass(frozen=True)
class AlternateParams:
    """Tuning of the rounds of :func:`depth_step`.

    Attributes
    ----------
    rounds : int
        Most rounds of (re-solve the rows at their depths, depth step again); 0: none.
    min_share : float
        Rounds run only when the depth map took a depth on at least this
        fraction of the valid pixels.
    tol, max_outer, max_add : the row solver's settings.
    """

    rounds: int = 2
    min_share: float = 0.05
    tol: float = TOL
    max_outer: int = MAX_OUTER
    max_add: int = MAX_ADD


def depth_step(registration, reference, distorted, *, camera, threshold, space, lambda_w, lambda_chi,
               reference_origin_yx=(0, 0), distorted_origin_yx=(0, 0), params=None):
    """The depth-layer step with the rows' weights and the depth map estimated in turn.

    Parameters
    ----------
    registration : Registration
    reference : ndarray, shape (Hr, Wr), float32
        The reference window the registration used (NaN for no-data).
    distorted : ndarray, shape (H, W), float32
        The capture window.
    camera : Camera
    threshold : float
        The change threshold (intensity units).
    space : PoseSpace
        The row neighbourhood ``N(c, b, s)`` of the registration (resolved steps):
        each re-solved row searches it around its centroid, widened to cover the
        poses it already weights.
    lambda_w, lambda_chi : float
        eq. 13's weights.
    reference_origin_yx, distorted_origin_yx : tuple of int
    params : AlternateParams, optional

    Returns
    -------
    LayerResult, DepthMapResult, dict
        The depth-layer components' result (``registered``, ``chi`` and
        ``parallax`` those of the whole step), the dense map of the kept round,
        and ``rounds`` (kept), ``objectives`` (eq. 13 per round, the first before
        any), ``rows`` (re-solved in the last round).
    """
    params = params or AlternateParams()
    windows = dict(camera=camera, threshold=threshold, reference_origin_yx=reference_origin_yx,
                   distorted_origin_yx=distorted_origin_yx, lambda_chi=lambda_chi)
    g = np.asarray(distorted, np.float32)
    layers, dense = _one_step(registration, reference, g, windows)
    info = {"rounds": 0, "objectives": [], "rows": 0}
    taken = dense.inverse_depth != 1.0
    # later rounds: no new depth for what the first round left a change candidate
    allowed = taken | (np.abs(g - layers.registered) <= threshold)
    first = layers.parallax
    if params.rounds <= 0 or taken.sum() < params.min_share * max(int(registration.valid.sum()), 1):
        return layers, dense, info
    objective = _objective(registration, layers.registered, g, lambda_w, lambda_chi)
    info["objectives"].append(objective[0])
    for _ in range(params.rounds):
        rows = np.nonzero(taken.any(axis=1))[0]
        unexplained = ~(np.abs(g - layers.registered) <= threshold)  # change candidates: no evidence of motion
        moved = _resolve_rows(registration, reference, g, dense.inverse_depth,
                              (layers.parallax & ~dense.explained) | unexplained,
                              rows, camera, space, lambda_w, lambda_chi, reference_origin_yx, distorted_origin_yx,
                              params)
        new_layers, new_dense = _one_step(moved, reference, g, windows, allowed)
        new_layers.parallax |= first  # nor may they make a change of what the first round explained
        new = _objective(moved, new_layers.registered, g, lambda_w, lambda_chi, objective[1])
        old = _objective(registration, layers.registered, g, lambda_w, lambda_chi, new[1])
        info["objectives"].append(new[0])
        info["rows"] = len(rows)
        if not new[0] < old[0]:
            break
        registration, layers, dense, objective = moved, new_layers, new_dense, new
        info["rounds"] += 1
        taken = dense.inverse_depth != 1.0
    return layers, dense, info


def _one_step(registration, reference, g, windows, allowed=None):
    """Components tested as depth layers, then the dense depth map of the rest
    (on ``allowed`` pixels)."""
    layers = depth_layers(registration, reference, g, **windows)
    layered = dataclasses.replace(registration, registered=layers.registered, chi=layers.chi)
    dense = depth_map(layered, reference, g, allowed=allowed, **windows)
    # no change candidate borrows a layer's values at another depth than the layer's
    candidates = (dense.inverse_depth != 1.0) & registration.valid & ~(np.abs(g - layered.registered) <= windows["threshold"])
    borrowed = sees_a_layer_elsewhere(layers, registration, candidates, dense.inverse_depth,
                                      **{k: windows[k] for k in ("camera", "reference_origin_yx",
                                                                 "distorted_origin_yx")})
    if borrowed.any():
        dense.registered[borrowed] = layered.registered[borrowed]
        dense.chi[borrowed] = layered.chi[borrowed]
        dense.inverse_depth[borrowed] = 1.0
        dense.explained &= ~borrowed
    layers.registered, layers.chi = dense.registered, dense.chi
    layers.parallax = layers.parallax | dense.explained
    # a candidate's rims along the structures the depth map explains are their
    # remnant, as a layer's are: no evidence (chi 0), in parallax
    left = over_threshold(dense.chi, registration.valid, windows["threshold"]) & ~layers.parallax
    rims = rims_along(left, dense.explained, LayerParams().min_area)
    if rims.any():
        dense.chi[rims] = 0.0
        layers.parallax = layers.parallax | rims
    return layers, dense


def _objective(registration, registered, g, lambda_w, lambda_chi, common=None):
    """eq. 13 of a model (its registered image and rows' weights), on the capture
    divided by the column gain, over its finite pixels (and ``common``'s);
    returns (value, the pixels counted)."""
    gain = 1.0 if registration.column_gain is None else registration.column_gain[None, :]
    cover = registration.valid & np.isfinite(registered)
    if common is not None:
        cover &= common
    r = ((g - np.where(cover, registered, 0.0)) / gain)[cover]
    weights = sum(float(w.sum()) for _, w in registration.row_weights.values())
    return _huber_loss(r, 0.5 * lambda_chi) + lambda_w * weights, cover


def _resolve_rows(registration, reference, g, inverse_depth, exclude, rows, camera, space, lambda_w, lambda_chi,
                  reference_origin_yx, distorted_origin_yx, params):
    """A copy of ``registration`` with ``rows`` solved again (eq. 13) with every
    pixel's columns at its own inverse depth, warm-started from their weights;
    the plane (inverse depth 1) re-rendered with the new weights."""
    ref = np.ascontiguousarray(reference, np.float32)
    focal, cx, cy, dy, dx = _geometry(camera, reference_origin_yx, distorted_origin_yx)
    gain = np.ones(g.shape[1]) if registration.column_gain is None else np.asarray(registration.column_gain, np.float64)
    weights = dict(registration.row_weights)
    registered, chi, valid = registration.registered.copy(), registration.chi.copy(), registration.valid.copy()
    axes, solved = space.axes, []
    for i in rows:
        if i not in weights or not len(weights[i][1]):
            continue
        poses, w_now = weights[i]
        index, grid = _grid(space, poses, w_now)
        poses6 = full_poses(grid, axes)
        if registration.slow is not None:
            poses6 = poses6 + registration.slow.pose6(int(i))
        wanted = registration.valid[i] & ~exclude[i]
        if wanted.sum() < _Solver.min_valid(wanted.size):
            continue
        a = np.empty((len(grid), g.shape[1]), np.float32)  # every value written by _build_row_depth
        ok = _build_row_depth(ref, poses6, np.where(wanted, inverse_depth[i], np.nan), focal, cx, cy, i + dy, dx, a)
        use = (ok == 1) & wanted
        if use.sum() < _Solver.min_valid(use.size):
            continue
        a[:, ~use] = 0.0
        g_row = np.where(use, g[i] / gain, 0.0).astype(np.float64)
        w = _warm_start(space, index, poses, w_now)
        _solve_huber_nn(a, g_row, w, float(lambda_w), 0.5 * float(lambda_chi), float(params.tol),
                        int(params.max_outer), int(params.max_add))
        keep = w > 0
        if keep.any():
            weights[i] = (grid[keep], w[keep])
            solved.append(i)
    moved = dataclasses.replace(registration, row_weights=weights)
    # the plane (inverse depth 1) of the re-solved rows, by the depth steps' one renderer
    mask = np.zeros(g.shape, bool)
    mask[solved] = True
    plane = _RowPoses.of(moved, g.shape[0]).render(ref, (focal, cx, cy, dy, dx), 1.0, mask)
    for i in solved:
        row_ok = np.isfinite(plane[i]) & registration.valid[i]
        registered[i] = np.where(row_ok, plane[i], np.nan)
        chi[i] = np.where(row_ok, optimal_chi(g[i] - registered[i], lambda_chi=lambda_chi), 0.0)
        valid[i] = row_ok
    return dataclasses.replace(moved, registered=registered, chi=chi, valid=valid)


def _grid(space, poses, w):
    """The row neighbourhood around the row's centroid, widened to cover its
    weighted poses: lattice indices and poses."""
    step = np.asarray(space.step)
    centre = space.snap(_centroid(poses, w))
    reach = np.abs(np.rint(poses / step).astype(np.int64) - centre).max(axis=0)
    half = np.maximum(np.rint(np.asarray(space.half_width) / step), reach) * step
    return space.widened(tuple(half)).grid(centre * step)


def _warm_start(space, index, poses, w):
    """The row's weights on the grid ``index`` (their lattice points)."""
    out = np.zeros(len(index))
    if not len(index) or not len(poses):
        return out
    index = np.asarray(index, np.int64)
    points = np.rint(poses / np.asarray(space.step)).astype(np.int64)
    lo = index.min(axis=0)
    dims = index.max(axis=0) - lo + 1
    inside = np.all((points >= lo) & (points < lo + dims), axis=1)
    table = np.full(int(np.prod(dims)), -1, np.int64)  # the grid's row of each lattice point of its box
    table[np.ravel_multi_index(tuple((index - lo).T), dims)] = np.arange(len(index))
    at = table[np.ravel_multi_index(tuple((points[inside] - lo).T), dims)]
    on_grid = at >= 0
    np.add.at(out, at[on_grid], np.asarray(w, np.float64)[inside][on_grid])  # in the poses' order, as one loop would
    return out


class _DepthRow(NamedTuple):
    """One capture row's columns to build (:func:`_build_row_depth`): the
    reference window, the poses (K, 6), each pixel's inverse depth (NaN: not
    wanted), the poses ordered by group (``order``; group ``n`` is
    ``order[starts[n]:starts[n + 1]]``: the same ty, s and rotations and
    translations ``tx`` an integer number of pixels apart), the wanted pixels
    ordered by inverse depth (``by_depth``; the pixels of ``depths[n]`` are
    ``by_depth[depth_starts[n]:depth_starts[n + 1]]``), the geometry and the
    row (reference frame)."""

    ref: np.ndarray
    poses6: np.ndarray
    q: np.ndarray
    order: np.ndarray
    starts: np.ndarray
    depths: np.ndarray
    by_depth: np.ndarray
    depth_starts: np.ndarray
    focal: float
    cx: float
    cy: float
    y: float
    dx: float


def _build_row_depth(ref, poses6, q, focal, cx, cy, y, dx, out):
    """``out`` (K, W): column ``k`` of ``F_i`` at every pixel ``j`` of capture
    row ``y`` (reference frame) sampled at pose ``k`` with translations and
    scale times ``q[j]``; 0 where a pose leaves valid data and at pixels whose
    ``q`` is NaN (not wanted: not sampled).  Returns uint8 (W,), 1 where every
    pose sampled valid data.

    At inverse depth 1 a pose's sample at pixel ``j`` depends on ``x - tx``
    alone, so the poses of a group (:class:`_DepthRow`) share one row of
    samples, shifted by their ``tx``; other depths are sampled pose by pose,
    each pose's map reduced to the row once per inverse depth the row holds."""
    poses6 = np.ascontiguousarray(poses6, np.float64)
    key = np.column_stack([poses6[:, 1:], poses6[:, 0] - np.floor(poses6[:, 0])])
    group = _row_groups(key)
    order = np.argsort(group, kind="stable")
    starts = np.searchsorted(group[order], np.arange(group.max() + 2 if len(group) else 1))
    q = np.asarray(q, np.float64)
    wanted = np.flatnonzero(np.isfinite(q))
    depths, which = np.unique(q[wanted], return_inverse=True)
    by_depth = wanted[np.argsort(which.ravel(), kind="stable")]
    depth_starts = np.searchsorted(q[by_depth], depths, side="left")
    depth_starts = np.append(depth_starts, len(by_depth)).astype(np.int64)
    row = _DepthRow(ref, poses6, q, order, starts, depths, by_depth, depth_starts, float(focal), float(cx),
                    float(cy), float(y), float(dx))
    return _columns_at_depth(row, out)


def _row_groups(key):
    """Group number of each row of ``key`` (K, n): rows of equal values share
    one, numbered in the rows' lexicographic order (for finite keys
    ``np.unique(key, axis=0, return_inverse=True)``'s numbers, by one sort of
    the columns; a row holding NaN is a group of its own).  The caller needs
    the groups, not their numbers."""
    if not len(key):
        return np.zeros(0, np.int64)
    order = np.lexsort(key.T[::-1])
    ranked = key[order]
    new = np.concatenate([[True], np.any(ranked[1:] != ranked[:-1], axis=1)])
    group = np.empty(len(key), np.int64)
    group[order] = np.cumsum(new) - 1
    return group


@numba.njit(nogil=True, cache=True)
def _columns_at_depth(row, out):
    """:func:`_build_row_depth`'s kernel."""
    width = out.shape[1]
    q, poses6 = row.q, row.poses6
    valid = np.zeros(width, np.uint8)
    out[:] = 0.0
    for j in row.by_depth:
        valid[j] = 1
    for g in range(row.starts.shape[0] - 1):
        a, b = row.starts[g], row.starts[g + 1]
        m, _, ty, sc = _inverse_map(poses6[row.order[a]], row.focal, row.cx, row.cy)
        s = sc - 1.0
        hi, lo = -np.inf, np.inf
        for n in range(a, b):
            hi, lo = max(hi, poses6[row.order[n], 0]), min(lo, poses6[row.order[n], 0])
        shared = b - a > 1
        base = np.empty(width + int(hi - lo) if shared else 0)
        for t in range(base.shape[0]):  # x - tx for the group's poses, from the largest tx
            u, v = _point(m, 0.0, ty, sc, t + row.dx - hi, row.y, row.cx, row.cy)
            base[t] = _bilinear(row.ref, u, v)
        for n in range(a, b):
            k = row.order[n]
            tx = poses6[k, 0]
            off = int(np.rint(hi - tx))
            for d in range(row.depths.shape[0]):
                qd = row.depths[d]
                on_row = _row_map(m, tx * qd, ty * qd, 1.0 + s * qd, row.y, row.cx, row.cy)
                for p in range(row.depth_starts[d], row.depth_starts[d + 1]):
                    j = row.by_depth[p]
                    if shared and qd == 1.0:
                        v = base[off + j]
                    else:
                        u, v = _point_on_row(on_row, j + row.dx)
                        v = _bilinear(row.ref, u, v)
                    if np.isnan(v):
                        valid[j] = 0
                        out[k, j] = 0.0
                    else:
                        out[k, j] = v
    return valid
