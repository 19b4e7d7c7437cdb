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
by the change rule (the gap between them soft-thresholded as eq. 13's
``chi``); it carries **no evidence** (NaN) only where the intervals say
nothing: its whole support clipped, or the capture clipped on the side the
model is open (both say "at least as bright", or both "at most as dark").
"""

from dataclasses import dataclass

import numpy as np

from .._oracle import optimal_chi
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
    geometry = _geometry(camera, reference_origin_yx, distorted_origin_yx)
    ref = np.ascontiguousarray(reference, np.float32)
    data = np.isfinite(ref)
    mask = np.asarray(mask, bool)

    def render(values):
        return rows.render(np.ascontiguousarray(np.where(data, values, np.nan), np.float32), geometry, 1.0, mask)

    model = rows.render(ref, geometry, 1.0, mask)
    total = render(1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        high_share = np.clip(render(np.asarray(high, np.float32)) / total, 0.0, 1.0)
        low_share = np.clip(render(np.asarray(low, np.float32)) / total, 0.0, 1.0)
    return ModelBounds(model, high_share.astype(np.float32), low_share.astype(np.float32))


def bounded_score(capture, bounds, capture_high, capture_low, *, lambda_chi):
    """The signed change term of capture pixels against their model interval
    (see the module docstring): the gap between the two intervals
    soft-thresholded as eq. 13's ``chi`` (:func:`optimal_chi`), positive where
    the capture is brighter, 0 where they meet, NaN where they say nothing.

    Parameters
    ----------
    capture : ndarray, shape (H, W)
        The capture on the common scale (clipped pixels at their values).
    bounds : ModelBounds
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
    model_low = np.where(down, -np.inf, m)
    model_high = np.where(up, np.inf, m)
    cap_lo = np.where(cap_low, -np.inf, g)
    cap_hi = np.where(cap_high, np.inf, g)
    with np.errstate(invalid="ignore"):
        above = cap_lo - model_high  # the capture brighter than the model can be
        below = model_low - cap_hi  # the capture darker than the model can be
        gap = np.where(above > 0, above, np.where(below > 0, -below, 0.0))
    known = np.isfinite(m) & np.isfinite(gap)
    unclipped = 1.0 - np.nan_to_num(bounds.high_share) - np.nan_to_num(bounds.low_share)
    silent = (gap == 0) & ((unclipped <= TOUCH) | (cap_high & up) | (cap_low & down))
    chi = np.full(m.shape, np.nan, np.float32)
    take = known & ~silent
    chi[take] = optimal_chi(gap[take], lambda_chi=lambda_chi)
    return chi
