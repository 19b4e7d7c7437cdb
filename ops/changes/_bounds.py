"""Clipped values are bounds (issue 15): the change score where either image
is clipped.

A pixel at a saturation value says that the scene was *at least* that
bright, a pixel at 0 that it was *at most* that dark: each is a bound, not an
absence of evidence.  So each capture pixel's model is an interval:

- its **model**: the row's weighted poses (the active poses of eq. 13's
  weights, with the blur they describe; never the whole search window)
  applied to the reference with its clipped pixels at their clip levels;
- **open upwards** where those weights touch saturated reference pixels
  (their true value may be any higher), **open downwards** where they touch
  pixels at 0; those pixels enter the model at their clip level with their
  share of the weights, and any share opens that side, because a clipped
  value may lie any distance beyond its level;
- the capture's own clipped pixels likewise: saturated is ``[saturation,
  inf)``, at 0 is ``(-inf, floor]``.

A pixel is change only when the capture's interval lies outside the model's
by the change rule.  In eq. 13's terms the two intervals bound the change
term: ``chi = g - F w`` lies in ``[capture low - model high, capture high -
model low]``, and the change term is the point of that interval nearest 0
(the smallest change the data allow, as the l1 penalty picks it),
soft-thresholded (:func:`optimal_chi`).  A pixel carries **no evidence**
(NaN) only where that interval is the whole line, so that the data bound
the change on neither side: the capture clipped on the side the model is
open (both say only "at least this bright", or both "at most this dark"),
or the model open on both sides (its support clipped at both ends),
whatever the model's value at the clip levels.  Where the interval is
bounded on one side and holds 0 (a capture saturated against a point model
at or above saturation, an unclipped capture inside a half-open model, a
whole support saturated under a brighter capture) the data are consistent
with no change and rule out a change in one direction: 0, as for any
consistent pixel.
"""

import math
from dataclasses import dataclass

import numba
import numpy as np

from .._oracle import optimal_chi
from .._warp import _point_on_row, _row_map
from ..depth._depthmap import _RowPoses, _geometry

__all__ = ["ModelBounds", "model_bounds", "bounded_score"]

#: Share of a pixel's weight on clipped reference pixels above which the model
#: is open on that side (bilinear samples put tiny shares on neighbours).
TOUCH = 1e-3


@dataclass(frozen=True)
class ModelBounds:
    """The model interval of capture pixels (:func:`model_bounds`).

    Attributes
    ----------
    model : ndarray of float32, shape (H, W)
        The weighted poses applied to the reference with clipped pixels at
        their clip levels, times the column gain; NaN off the mask, in rows
        without weights and where a pose leaves valid reference data.
    high_share, low_share : ndarray of float32, shape (H, W)
        Share of the pixel's weight on saturated reference pixels, on pixels
        at 0 (bilinear weights included), in [0, 1].
    """

    model: np.ndarray
    high_share: np.ndarray
    low_share: np.ndarray


def model_bounds(registration, reference, high, low, mask, *, camera, reference_origin_yx=(0, 0),
                 distorted_origin_yx=(0, 0)):
    """The model interval of the capture pixels of ``mask``.

    Parameters
    ----------
    registration : Registration
        Its ``row_weights`` (active poses and weights per row) are the footprint.
    reference : ndarray, shape (Hr, Wr), float32
        The reference window on the common scale, clipped pixels at their
        clip levels, NaN for no-data.
    high, low : ndarray of bool, shape (Hr, Wr)
        Reference pixels at its saturation value, at 0.
    mask : ndarray of bool, shape (H, W)
        Capture pixels to compute.
    camera : Camera
    reference_origin_yx, distorted_origin_yx : tuple of int

    Returns
    -------
    ModelBounds
    """
    rows = _RowPoses.of(registration, mask.shape[0])
    focal, cx, cy, dy, dx = _geometry(camera, reference_origin_yx, distorted_origin_yx)
    state = np.zeros(np.shape(high), np.int8)  # 1 saturated (first), 2 at 0, else 0
    state[np.asarray(low, bool)] = 2
    state[np.asarray(high, bool)] = 1
    shape = np.shape(mask)
    model = np.full(shape, np.nan, np.float32)
    high_share, low_share = np.full(shape, np.nan, np.float32), np.full(shape, np.nan, np.float32)
    if len(rows.poses6):
        _bounds(rows.scene(reference, (focal, cx, cy, dy, dx)), state, np.asarray(mask, np.uint8), model, high_share,
                low_share)
    return ModelBounds(model, high_share, low_share)


@numba.njit(nogil=True, cache=True)
def _bounds(scene, state, mask, model, high_share, low_share):
    """:func:`model_bounds` in one pass: each pixel's weighted poses (the
    :class:`_Scene` at the plane) sample the reference bilinearly (as
    :func:`ops.model_values` does) and the clipped ``state`` (1 saturated, 2
    at 0) with the same weights; NaN where a pose leaves valid reference data."""
    height, width = model.shape
    ref, poses6, weights, offsets, gain = scene.ref, scene.poses6, scene.weights, scene.offsets, scene.gain
    hr, wr = ref.shape
    per_column = gain.shape[0] == width
    most = 0
    for i in range(height):
        most = max(most, offsets[i + 1] - offsets[i])
    maps = np.empty((most, 11))  # a row's poses' maps reduced to the row (_row_map), once per row
    for i in range(height):
        s0, s1 = offsets[i], offsets[i + 1]
        if s0 == s1:
            continue
        reduced = False
        for j in range(width):
            if mask[i, j] == 0:
                continue
            if not reduced:
                for k in range(s0, s1):
                    row = _row_map(scene.maps[k], poses6[k, 0], poses6[k, 1], 1.0 + poses6[k, 2], i + scene.dy,
                                   scene.cx, scene.cy)
                    for t in range(11):
                        maps[k - s0, t] = row[t]
                reduced = True
            acc, total, up, down, ok = 0.0, 0.0, 0.0, 0.0, True
            for k in range(s0, s1):
                m = maps[k - s0]
                u, v = _point_on_row((m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8], m[9], m[10]),
                                     j + scene.dx)
                if not (u >= 0.0 and v >= 0.0 and u <= wr - 1 and v <= hr - 1):
                    ok = False
                    break
                iu, iv = min(int(u), wr - 2), min(int(v), hr - 2)
                fu, fv = u - iu, v - iv
                val, hi, lo = 0.0, 0.0, 0.0
                for a in range(2):
                    for b in range(2):
                        c = (fv if a else 1.0 - fv) * (fu if b else 1.0 - fu)
                        val += c * ref[iv + a, iu + b]
                        s = state[iv + a, iu + b]
                        if s == 1:
                            hi += c
                        elif s == 2:
                            lo += c
                if math.isnan(val):
                    ok = False
                    break
                w = weights[k]
                acc += w * val
                total += w
                up += w * hi
                down += w * lo
            if ok and total > 0.0:
                model[i, j] = acc * (gain[j] if per_column else 1.0)
                high_share[i, j] = min(max(up / total, 0.0), 1.0)
                low_share[i, j] = min(max(down / total, 0.0), 1.0)


def bounded_score(capture, bounds, capture_high, capture_low, *, lambda_chi):
    """The signed change term of capture pixels against their model interval
    (see the module docstring): the gap between the two intervals
    soft-thresholded as eq. 13's ``chi`` (:func:`optimal_chi`), positive where
    the capture is brighter, 0 where they meet, NaN where they say nothing.

    Elementwise: the arrays may be any one shape, such as the pixels of a
    window that need the interval, gathered.

    Parameters
    ----------
    capture : ndarray, shape (H, W)
        The capture on the common scale (clipped pixels at their values).
    bounds : ModelBounds
        Its arrays of the same shape as ``capture``.
    capture_high, capture_low : ndarray of bool, shape (H, W)
        Capture pixels at its saturation value, at its floor.
    lambda_chi : float

    Returns
    -------
    ndarray of float32, shape (H, W)
        NaN where the model is unknown (NaN) or the intervals say nothing.
    """
    g = np.asarray(capture, np.float64)
    m = np.asarray(bounds.model, np.float64)
    up = np.nan_to_num(bounds.high_share) > TOUCH
    down = np.nan_to_num(bounds.low_share) > TOUCH
    cap_high, cap_low = np.asarray(capture_high, bool), np.asarray(capture_low, bool)
    with np.errstate(invalid="ignore"):
        # chi = g - F w lies in [capture low - model high, capture high - model low]
        lowest = np.where(cap_low | up, -np.inf, g - m)
        highest = np.where(cap_high | down, np.inf, g - m)
        gap = np.where(lowest > 0, lowest, np.where(highest < 0, highest, 0.0))  # its point nearest 0
    silent = (cap_low | up) & (cap_high | down)  # the whole line: the data bound chi on neither side
    take = np.isfinite(m) & np.isfinite(g) & ~silent
    chi = np.full(m.shape, np.nan, np.float32)
    chi[take] = optimal_chi(gap[take], lambda_chi=lambda_chi)
    return chi
