"""A dense relative-depth map for the whole residual (METHOD.md section 3,
item 8, extended from change components to every pixel).

The registration fits each row's weights to one plane.  A ground-level scene
has depth everywhere: a nearer tree moves more under the camera's
translations than the plane the row settled on, a farther one less, and the
residual keeps their edges.  With the rows' weights fixed, the reference is
warped and blurred again at a set of relative inverse depths ``q`` (the
translations ``tx``, ``ty`` and the scale ``s`` of every weighted pose
multiplied by ``q``, rotations as they are; ``q = 1`` is the registered plane,
``q = 0`` infinitely far), the per-pixel residual, truncated at the change
threshold, is averaged over a window, and each pixel takes the depth of the
lowest window cost among those it tries (every 4th depth, then the depths
around its best one: :attr:`DepthMapParams.stride`):

- only where that cost is clearly lower than the registered plane's (at most
  :attr:`DepthMapParams.gain` times it): ties and noise keep the plane;
- only where the plane leaves unexplained structure: pixels with no residual
  above half the threshold within the window keep the plane (flat, well
  registered scenes cost nothing);
- everywhere only in a scene with depth: the windows of pixels above the
  threshold (the change candidates) are swept first, and only where a depth
  brings at least :attr:`DepthMapParams.min_share` of the valid pixels from
  above the threshold to below it are the other active pixels swept; else
  they keep the plane (a flat scene's residual is noise no depth explains).

The output is still the model's: at every pixel the reference warped and
blurred by the row's estimated path at one depth, times the row's gain.  New
content (a pasted change) is explained at no depth and stays in ``chi``.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numba
import numpy as np

from .._camera import full_poses
from .._errors import ParameterError
from .._oracle import optimal_chi
from .._warp import _bilinear, _inverse_map, _point_on_row, _row_map

__all__ = ["DepthMapParams", "DepthMapResult", "depth_map", "model_values"]

#: The sweep's per-pixel depth indices (:class:`_Best` ``index``, the fine
#: pass's window ranges): a tile's worth of them is written every tile, so
#: the narrowest integer that holds :attr:`DepthMapParams.max_depths` and
#: the "none" sentinel ``_BIG``.
_INDEX = np.int16
_BIG = 2 ** 14


@dataclass(frozen=True)
class DepthMapParams:
    """Tuning of :func:`depth_map`.

    Attributes
    ----------
    max_inverse_depth : float
        Largest relative inverse depth swept (3: a third of the registered
        plane's distance); the sweep starts at 0 (infinitely far).
    max_depths : int
        Most depths rendered; the step is the one that moves the largest
        translation of the window by one pixel, coarsened to this count.
    stride : int
        Coarse to fine: every ``stride``-th depth is tried at every pixel,
        then each pixel tries the depths within ``stride`` steps of its best
        coarse one (1: every depth everywhere).
    window : int
        Side of the square window the truncated residual is averaged over, px.
    gain : float
        A depth replaces the plane where its window cost is at most this
        fraction of the plane's.
    min_share : float
        Share of the valid pixels that a depth must bring from above the
        threshold to below it for every active pixel to be swept (else only
        the windows of pixels above the threshold).
    min_seed : int
        Pixels above the threshold open a window to sweep only in 8-connected
        groups of at least this many: an isolated pixel or two (noise, an
        interpolation error at an edge) is no structure with a depth, and
        each one's window is swept at every depth.
    """

    max_inverse_depth: float = 3.0
    max_depths: int = 64
    stride: int = 4
    window: int = 7
    gain: float = 0.85
    min_share: float = 0.0005
    min_seed: int = 3

    def __post_init__(self):
        if not 2 <= self.max_depths < _BIG:
            raise ParameterError(f"max_depths: expected 2 to {_BIG - 1} depths, got {self.max_depths!r}")
        if isinstance(self.min_seed, bool) or not (isinstance(self.min_seed, int) and self.min_seed >= 1):
            raise ParameterError(f"min_seed: expected a whole number of pixels >= 1, got {self.min_seed!r}")


@dataclass
class DepthMapResult:
    """Result of :func:`depth_map`.

    Attributes
    ----------
    registered, chi : ndarray, shape (H, W), float32
        The registration's, re-rendered at their depth where one was taken.
    inverse_depth : ndarray, shape (H, W), float32
        Relative inverse depth taken per pixel, 1 (the registered plane) elsewhere.
    explained : ndarray of bool, shape (H, W)
        Pixels above the threshold on the plane that fall below it at their depth.
    depths : int
        Depths rendered (0 when the residual had no structure to explain).
    """

    registered: np.ndarray
    chi: np.ndarray
    inverse_depth: np.ndarray
    explained: np.ndarray
    depths: int = 0


def depth_map(registration, reference, distorted, *, camera, threshold, reference_origin_yx=(0, 0),
              distorted_origin_yx=(0, 0), lambda_chi=0.02, params=None, allowed=None):
    """Re-render a registration per pixel at the depth that explains it best.

    Parameters
    ----------
    registration : Registration
        Of ``distorted`` against ``reference`` (its row weights are re-used).
    reference : ndarray, shape (Hr, Wr), float32
        The reference window the registration used (NaN for no-data).
    distorted : ndarray, shape (H, W), float32
        The capture window (the values the registration fitted).
    camera : Camera
        Intrinsics of the whole image.
    threshold : float
        The change threshold (intensity units): residuals are truncated at it.
    reference_origin_yx, distorted_origin_yx : tuple of int
        The windows' positions in the whole image.
    lambda_chi : float
        eq. 13's weight of ``||chi||_1``, for the change term of re-rendered pixels.
    params : DepthMapParams, optional
    allowed : ndarray of bool, shape (H, W), optional
        Only these pixels may take a depth (default: all).

    Returns
    -------
    DepthMapResult
    """
    params = params or DepthMapParams()
    base = registration.registered
    g = np.asarray(distorted, np.float32)
    tau = float(threshold)
    out = DepthMapResult(base.copy(), registration.chi.copy(), np.ones(g.shape, np.float32),
                         np.zeros(g.shape, bool))
    valid = registration.valid & np.isfinite(base)
    residual = np.where(valid, np.abs(g - base), 0.0).astype(np.float32)
    active = _active(residual, valid, tau, params.window)
    if allowed is not None:
        active &= np.asarray(allowed, bool)
    if not active.any() or not tau > 0:
        return out
    rows = _RowPoses.of(registration, g.shape[0])
    step = 1.0 / max(rows.largest_translation(), 1.0)
    count = int(min(params.max_depths, math.floor(params.max_inverse_depth / step) + 1))
    qs = np.linspace(0.0, params.max_inverse_depth, max(count, 2))
    cost_plane = _window_cost(np.where(valid, residual, tau), tau, params.window)
    scene = rows.scene(reference, _geometry(camera, reference_origin_yx, distorted_origin_yx))
    # the windows of groups of pixels above tau
    candidates = active & _active(residual, valid, 2.0 * tau, params.window, params.min_seed)
    if not candidates.any():
        return out
    take, chosen, depth = _takes(scene, g, candidates, cost_plane, tau, qs, params)
    if _explained(take, chosen, g, residual, tau).sum() >= params.min_share * int(valid.sum()) \
            and (active & ~candidates).any():
        # a scene with depth: swept whole, the candidates again (their fine
        # pass reads their active neighbours' coarse depths)
        take, chosen, depth = _takes(scene, g, active, cost_plane, tau, qs, params)
    out.registered[take] = chosen[take]
    out.inverse_depth[take] = depth[take]
    r = g[take] - chosen[take]
    out.chi[take] = optimal_chi(r, lambda_chi=lambda_chi)
    out.explained = _explained(take, chosen, g, residual, tau)
    out.depths = len(qs)
    return out


def _takes(scene, g, active, cost_plane, tau, qs, params):
    """The sweep (:func:`_sweep`) over the ``active`` pixels: the pixels that
    take a depth (window cost at most ``params.gain`` times the plane's), and
    every active pixel's best value and inverse depth."""
    render_mask = (cv2.dilate(active.astype(np.uint8), np.ones((params.window, params.window), np.uint8)) > 0)
    render_mask = render_mask.astype(np.uint8)
    best = np.full(g.shape, np.inf, np.float32)
    chosen = np.full(g.shape, np.nan, np.float32)
    depth = np.ones(g.shape, np.float32)
    fit = _Fit(np.ascontiguousarray(g), render_mask, active.astype(np.uint8), tau, int(params.window) // 2,
               _runs(render_mask))
    _sweep(scene, fit, qs, int(params.stride), _Best(best, chosen, depth, np.full(g.shape, -1, _INDEX)))
    return active & np.isfinite(chosen) & (best <= params.gain * cost_plane), chosen, depth


def _explained(take, chosen, g, residual, tau):
    """The pixels above the threshold ``tau`` on the plane that a depth took
    and brought below it."""
    return take & (residual > tau) & (np.abs(g - chosen) <= tau)


def model_values(registration, reference, mask, *, camera, reference_origin_yx=(0, 0), distorted_origin_yx=(0, 0)):
    """The registration's model at the pixels of ``mask``, whatever the
    capture holds there: each row's weighted poses applied to the reference
    (the registered plane), times the column gain.

    Parameters
    ----------
    registration : Registration
    reference : ndarray, shape (Hr, Wr), float32
        The reference window the registration used (NaN for no-data).
    mask : ndarray of bool, shape (H, W)
    camera : Camera
    reference_origin_yx, distorted_origin_yx : tuple of int

    Returns
    -------
    ndarray of float32, shape (H, W)
        NaN off ``mask``, in rows without weights and where a pose leaves
        valid reference data.
    """
    scene = _RowPoses.of(registration, mask.shape[0]).scene(
        reference, _geometry(camera, reference_origin_yx, distorted_origin_yx))
    return render_at(scene, 1.0, np.asarray(mask, bool))


def _active(residual, valid, tau, window, min_seed=1):
    """Pixels whose window holds residual above half the threshold ``tau``
    (where the plane leaves structure unexplained), in a group of at least
    ``min_seed`` 8-connected such pixels."""
    seed = (valid & (residual > 0.5 * tau)).astype(np.uint8)
    if min_seed > 1 and seed.any():
        _, labels, stats, _ = cv2.connectedComponentsWithStats(seed, connectivity=8, ltype=cv2.CV_32S)
        large = stats[:, cv2.CC_STAT_AREA] >= min_seed
        large[0] = False
        seed = large[labels].astype(np.uint8)
    return (cv2.dilate(seed, np.ones((window, window), np.uint8)) > 0) & valid


def _window_cost(err, tau, window):
    """Mean over a ``window`` square of the residual truncated at ``tau``."""
    return cv2.boxFilter(np.minimum(err, tau).astype(np.float32), -1, (window, window),
                         borderType=cv2.BORDER_REPLICATE)


def _geometry(camera, reference_origin_yx, distorted_origin_yx):
    """(focal, cx, cy in the reference window, row and column offset of the
    capture window in it)."""
    return (float(camera.focal), float(camera.center_xy[0] - reference_origin_yx[1]),
            float(camera.center_xy[1] - reference_origin_yx[0]),
            float(distorted_origin_yx[0] - reference_origin_yx[0]), float(distorted_origin_yx[1] - reference_origin_yx[1]))


@dataclass
class _RowPoses:
    """Every row's weighted poses, flattened: row ``i`` owns ``poses6[offsets[i]:
    offsets[i + 1]]`` (full poses, the slow rotations added) and their weights."""

    poses6: np.ndarray
    weights: np.ndarray
    offsets: np.ndarray
    gain: np.ndarray

    @classmethod
    def of(cls, registration, height):
        some = next((p for p, _ in registration.row_weights.values()), np.zeros((0, 1)))
        axes = registration.axes[:some.shape[1]]
        rows = [row for row in range(height) if row in registration.row_weights]
        counts = np.zeros(height, np.int64)
        counts[rows] = [len(registration.row_weights[row][1]) for row in rows]
        poses = full_poses(np.concatenate([np.asarray(registration.row_weights[row][0], np.float64).reshape(-1, len(axes))
                                           for row in rows] or [np.zeros((0, len(axes)))]), axes)
        if registration.slow is not None:
            poses = poses + registration.slow.pose6(np.repeat(np.arange(height), counts))  # rotations: not scaled by depth
        weights = np.concatenate([np.asarray(registration.row_weights[row][1], np.float64) for row in rows] or [np.zeros(0)])
        gain = registration.column_gain
        return cls(poses, weights, np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                   np.ones(1) if gain is None else np.asarray(gain, np.float64))

    def largest_translation(self):
        """Largest displacement (px) a weighted pose's translation gives a pixel."""
        if not len(self.poses6):
            return 0.0
        return float(np.max(np.hypot(self.poses6[:, 0], self.poses6[:, 1])))

    def render(self, ref, geometry, q, mask):
        """:func:`render_at` of these poses over ``ref`` (whole capture window)."""
        return render_at(self.scene(ref, geometry), q, mask)

    def scene(self, reference, geometry):
        """The :class:`_Scene` of these poses over ``reference`` with ``geometry``
        (:func:`_geometry`)."""
        focal, cx, cy, dy, dx = geometry
        return _Scene(np.ascontiguousarray(reference, np.float32), _pose_maps(self.poses6, focal, cx, cy),
                      self.poses6, self.weights, self.offsets, self.gain, cx, cy, dy, dx)


class _Runs(NamedTuple):
    """A sparse mask as runs of nonzero pixels along its rows: row ``i`` owns
    runs ``offsets[i]:offsets[i + 1]``, run ``r`` lies on row ``rows[r]`` at
    the columns ``[starts[r], ends[r])``.  The loops over a sparse mask visit
    only these (:func:`_runs`)."""

    offsets: np.ndarray
    rows: np.ndarray
    starts: np.ndarray
    ends: np.ndarray


class _Scene(NamedTuple):
    """What rendering the rows' weighted poses at an inverse depth needs: the
    reference window, every pose's rotation map (:func:`_pose_maps`), poses,
    weights and row offsets (:class:`_RowPoses`), the column gain, the
    principal point in the reference window and the capture window's offset
    in it (px)."""

    ref: np.ndarray
    maps: np.ndarray
    poses6: np.ndarray
    weights: np.ndarray
    offsets: np.ndarray
    gain: np.ndarray
    cx: float
    cy: float
    dy: float
    dx: float


class _Fit(NamedTuple):
    """What the sweep compares renderings with: the capture window, where to
    render, which pixels choose a depth (uint8), the truncation ``tau`` and the
    half side of the cost window (px), and the runs of the render mask
    (:func:`_runs`; the active pixels lie within them)."""

    g: np.ndarray
    render_mask: np.ndarray
    active: np.ndarray
    tau: float
    half: int
    runs: _Runs


class _Best(NamedTuple):
    """The sweep's answer per pixel: lowest window cost, the value and inverse
    depth that gave it, and the index of the best coarse depth (-1: none)."""

    best: np.ndarray
    chosen: np.ndarray
    depth: np.ndarray
    index: np.ndarray


class _Scratch(NamedTuple):
    """One depth's buffers: pixels rendered, truncated residual, rendered
    values, residual summed along rows."""

    want: np.ndarray
    err: np.ndarray
    rendered: np.ndarray
    across: np.ndarray


def render_at(scene, q, mask, origin_yx=(0, 0)):
    """The rows' weighted poses at inverse depth ``q`` (translations and scale
    times ``q``, rotations as they are) applied to the reference, times the
    column gain, at the pixels of ``mask`` (bool, a window of the capture
    window at ``origin_yx``): float32, NaN elsewhere and where a pose leaves
    valid reference data.  The one renderer of the depth steps."""
    out = np.full(mask.shape, np.nan, np.float32)
    mask = np.ascontiguousarray(mask, np.uint8)
    _render_depth(scene, float(q), mask, _runs(mask), out, int(origin_yx[0]), int(origin_yx[1]))
    return out


@numba.njit(nogil=True, cache=True)
def _runs(mask):
    """The :class:`_Runs` of the nonzero pixels of ``mask``."""
    height, width = mask.shape
    offsets = np.zeros(height + 1, np.int64)
    for i in range(height):
        count = 0
        for j in range(width):
            if mask[i, j] != 0 and (j == 0 or mask[i, j - 1] == 0):
                count += 1
        offsets[i + 1] = offsets[i] + count
    rows = np.empty(offsets[height], np.int64)
    starts = np.empty(offsets[height], np.int64)
    ends = np.empty(offsets[height], np.int64)
    for i in range(height):
        r = offsets[i]
        rows[offsets[i]:offsets[i + 1]] = i
        for j in range(width):
            if mask[i, j] != 0 and (j == 0 or mask[i, j - 1] == 0):
                starts[r] = j
            if mask[i, j] != 0 and (j == width - 1 or mask[i, j + 1] == 0):
                ends[r] = j + 1
                r += 1
    return _Runs(offsets, rows, starts, ends)


@numba.njit(nogil=True, cache=True)
def _pose_maps(poses6, focal, cx, cy):
    """The rotation part of every pose's inverse map (:func:`_inverse_map`),
    (N, 9): it does not depend on the depth, which scales only the
    translations and the scale."""
    maps = np.empty((poses6.shape[0], 9))
    for k in range(poses6.shape[0]):
        maps[k] = _inverse_map(poses6[k], focal, cx, cy)[0]
    return maps


@numba.njit(nogil=True, cache=True)
def _render_depth(scene, q, mask, runs, out, r0, c0):
    """``out[i, j]`` = capture row ``r0 + i``'s weighted poses at inverse depth
    ``q`` (translations and scale times ``q``, rotations as they are) applied
    to the reference at column ``c0 + j``, times the column gain, where
    ``mask`` (nonzero only within ``runs``, :func:`_runs`); NaN where a pose
    leaves valid reference data.  Each pose's map is reduced to the row once
    (:func:`_row_map`); each pixel then sums its row's poses in their order
    in a register, and stops at the first pose that leaves valid data."""
    height, width = out.shape
    per_column = scene.gain.shape[0] != 1
    poses6 = scene.poses6
    most = 0
    for i in range(height):
        most = max(most, scene.offsets[r0 + i + 1] - scene.offsets[r0 + i])
    rows = np.empty((most, 11))
    for i in range(height):
        s0, s1 = scene.offsets[r0 + i], scene.offsets[r0 + i + 1]
        r_a, r_b = runs.offsets[i], runs.offsets[i + 1]
        if s0 == s1 or r_a == r_b:
            continue
        for k in range(s0, s1):
            row = _row_map(scene.maps[k], poses6[k, 0] * q, poses6[k, 1] * q, 1.0 + poses6[k, 2] * q,
                           r0 + i + scene.dy, scene.cx, scene.cy)
            for t in range(11):
                rows[k - s0, t] = row[t]
        for r in range(r_a, r_b):
            for j in range(runs.starts[r], runs.ends[r]):
                if mask[i, j] == 0:
                    continue
                x = c0 + j + scene.dx
                acc = 0.0
                for k in range(s0, s1):
                    m = rows[k - s0]
                    u, v = _point_on_row((m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8], m[9], m[10]), x)
                    acc += scene.weights[k] * _bilinear(scene.ref, u, v)  # NaN stays NaN
                    if math.isnan(acc):
                        break
                if not math.isnan(acc):
                    out[i, j] = acc * (scene.gain[c0 + j] if per_column else 1.0)


@numba.njit(nogil=True, cache=True)
def _sweep(scene, fit, qs, stride, best):
    """The depths of ``qs`` (ascending), coarse to fine: every ``stride``-th
    depth (and the last) at every ``fit.active`` pixel, then each active pixel
    the depths within ``stride`` steps of its best coarse one.  A depth is
    rendered where ``fit.render_mask`` (as :func:`_render_depth`) and, in the
    fine pass, where the best coarse depths of the active pixels in the window
    span a range within ``stride`` steps of it; its residual, truncated at
    ``fit.tau`` (``tau`` where not rendered), is averaged over the window
    (side ``2 * fit.half + 1``, borders replicated, as :func:`_window_cost`),
    and an active pixel takes the depth (:class:`_Best`) where its cost is
    lower than every earlier evaluated depth's.  With ``stride`` 1 every depth
    is evaluated everywhere."""
    height, width = fit.g.shape
    count = qs.shape[0]
    scratch = _Scratch(np.zeros((height, width), np.uint8), np.full((height, width), np.float32(fit.tau), np.float32),
                       np.full((height, width), np.nan, np.float32), np.zeros((height, width), np.float64))
    index = best.index  # best coarse depth per active pixel
    for k in range(count):
        if k % stride == 0 or k == count - 1:  # lo, hi unused in the coarse pass
            _one_depth(scene, fit, qs[k], k, index, index, -1, scratch, best)
    if stride <= 1:
        return
    lo, hi = _window_range(index, fit.active, fit.half, fit.runs)
    for k in range(count):
        if not (k % stride == 0 or k == count - 1):
            _one_depth(scene, fit, qs[k], k, lo, hi, stride, scratch, best)


@numba.njit(nogil=True, cache=True)
def _one_depth(scene, fit, q, k, lo, hi, stride, scratch, best):
    """Depth ``k`` (inverse depth ``q``) of :func:`_sweep`.  ``stride`` -1: the
    coarse pass (every pixel of ``fit.render_mask``; ``best.index`` records
    each active pixel's best coarse depth); else only pixels whose window
    holds an active pixel with a best coarse depth within ``stride`` of ``k``
    (``lo``, ``hi``: the window's range of them) are rendered, and only such
    active pixels are evaluated."""
    want, err, rendered, across = scratch
    tau, half, g, runs = fit.tau, fit.half, fit.g, fit.runs
    height, width = err.shape
    area = float((2 * half + 1) * (2 * half + 1))

    for r in range(runs.rows.shape[0]):
        i = runs.rows[r]
        for j in range(runs.starts[r], runs.ends[r]):
            want[i, j] = fit.render_mask[i, j] != 0 and (stride < 0 or (lo[i, j] - stride < k < hi[i, j] + stride))
            if want[i, j]:
                rendered[i, j] = np.nan
    _render_depth(scene, q, want, runs, rendered, 0, 0)
    for r in range(runs.rows.shape[0]):
        i = runs.rows[r]
        for j in range(runs.starts[r], runs.ends[r]):
            if want[i, j] != 0:
                if math.isnan(rendered[i, j]):
                    err[i, j] = tau
                else:
                    e = abs(g[i, j] - rendered[i, j])
                    err[i, j] = tau if e > tau else e  # NaN (no capture data) stays NaN
    for r in range(runs.rows.shape[0]):
        i = runs.rows[r]
        for j in range(runs.starts[r], runs.ends[r]):
            if want[i, j] != 0:
                acc = 0.0
                for d in range(-half, half + 1):
                    acc += err[i, min(max(j + d, 0), width - 1)]
                across[i, j] = acc
    for r in range(runs.rows.shape[0]):
        i = runs.rows[r]
        for j in range(runs.starts[r], runs.ends[r]):
            if fit.active[i, j] == 0 or math.isnan(rendered[i, j]):
                continue
            if stride > 0 and not (best.index[i, j] >= 0 and abs(k - best.index[i, j]) < stride):
                continue
            acc = 0.0
            for d in range(-half, half + 1):
                acc += across[min(max(i + d, 0), height - 1), j]
            cost = acc / area
            if cost < best.best[i, j]:
                best.best[i, j] = cost
                best.chosen[i, j] = rendered[i, j]
                best.depth[i, j] = q
                if stride < 0:
                    best.index[i, j] = k


@numba.njit(nogil=True, cache=True)
def _window_range(index, active, half, runs):
    """Per pixel of the ``runs`` (:func:`_runs`, holding every active pixel and
    its window), the smallest and largest ``index`` of the active pixels in its
    window (lo > hi where there are none, and off the runs)."""
    height, width = index.shape
    big = _BIG
    row_lo = np.full((height, width), big, _INDEX)
    row_hi = np.full((height, width), -big, _INDEX)
    for r in range(runs.rows.shape[0]):
        i = runs.rows[r]
        for j in range(runs.starts[r], runs.ends[r]):
            if active[i, j] != 0 and index[i, j] >= 0:
                for d in range(max(j - half, 0), min(j + half, width - 1) + 1):
                    row_lo[i, d] = min(row_lo[i, d], index[i, j])
                    row_hi[i, d] = max(row_hi[i, d], index[i, j])
    lo = np.full((height, width), big, _INDEX)
    hi = np.full((height, width), -big, _INDEX)
    for r in range(runs.rows.shape[0]):
        i = runs.rows[r]
        for j in range(runs.starts[r], runs.ends[r]):
            for d in range(max(i - half, 0), min(i + half, height - 1) + 1):
                lo[i, j] = min(lo[i, j], row_lo[d, j])
                hi[i, j] = max(hi[i, j], row_hi[d, j])
    return lo, hi
