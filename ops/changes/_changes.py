"""From the change term to change masks in both grids (METHOD.md section 3, steps 4-5).

The score of a pixel starts from ``|chi|``: the part of its residual that the warped and
blurred reference cannot explain beyond the Huber knee ``lambda_chi / 2``.

Thresholds are computed from histograms that tiles can add up, so that a
mosaic gets one threshold for the whole image:

- ``"noise"`` (default): ``k`` robust standard deviations of the registration
  residual (``1.4826 * median |g - F w|``), never below ``floor``.  It adapts to
  how well the capture could be registered and does not depend on what changed.
- ``"kapur"``: Kapur's maximum-entropy threshold of the histogram of the non-zero
  scores, as in the paper, never below ``floor``.  On captures whose changes have
  very different contrasts it tends to split the changes themselves.
- a number: a fixed score threshold.

The score is ``|chi|`` less an *interpolation allowance*: the row solver
renders sub-pixel poses by linear interpolation (bilinear pre-warps, weights
shared between whole-pixel shifts), whose error is bounded by ``1/8`` of the
image's second difference along each axis (``h^2 |f''| / 8`` at a half-pixel
offset).  A real capture's optics interpolate differently, so at the sharp
edges and thin lines of a real photograph the residual of a perfect
registration reaches that bound; ``interpolation * (|f_xx| + |f_yy|)`` of the
registered image is taken off ``|chi|`` (:func:`change_score`).  A new object
has its contrast on its own pixels, where the reference is mostly smooth: it
keeps its score.  (A misregistration leaves a residual that follows the first
derivative, not the second: it is not hidden.)

Pixels above ``hysteresis`` times the threshold that touch a pixel above it are
kept too (this recovers the blurred borders of changed objects), then connected
components smaller than ``min_area`` pixels are removed.
"""

import math
import numbers
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numba
import numpy as np
from scipy import ndimage
from skimage import measure

from .._camera import pose_homographies
from .._errors import ParameterError
from ._threshold import kapur_threshold_histogram

__all__ = ["ChangeParams", "ScoreHistogram", "score_histogram", "change_threshold", "residual_median", "change_score",
           "RESIDUAL_BINS", "SCORE_BINS", "change_candidates",
           "label_components", "keep_components", "large_components", "fill_holes", "change_mask", "changes_to_reference",
           "reference_lookup", "sample_at", "NO_EVIDENCE", "evidence_mask", "GroundFrame", "to_ground",
           "ChangeResult", "detect_changes"]

THRESHOLD_METHODS = ("noise", "kapur")
_RESIDUAL_EDGES = np.concatenate([[0.0], np.geomspace(1e-6, 4.0, 1024)])
_SCORE_EDGES = np.linspace(0.0, 2.0, 513)
#: Bins of :class:`ScoreHistogram`'s two histograms.
RESIDUAL_BINS, SCORE_BINS = len(_RESIDUAL_EDGES) - 1, len(_SCORE_EDGES) - 1


@dataclass(frozen=True)
class ChangeParams:
    """Tuning of change masks.

    Attributes
    ----------
    threshold : {"noise", "kapur"} or float
        How the score threshold is chosen (see the module docstring).
    k : float
        Robust standard deviations of the residual for ``"noise"``.
    floor : float
        Smallest automatic threshold, intensities in [0, 1].
    min_area : int
        Smallest connected change kept, in pixels.
    hysteresis : float
        Pixels above ``hysteresis * threshold`` connected to a changed pixel are
        changed too; 1 disables it.
    half_max_window : int
        A changed pixel must also score at least ``half_max`` times the largest
        score within this window (px): motion blur mixes a changed object with
        its surroundings linearly, so about half its contrast marks where it
        covers half a pixel, which is where the truth of a blurred change is
        drawn.  Should exceed twice the blur length; 1 disables it.
    half_max : float
        That fraction; a little under one half because the score is the
        residual less the Huber knee and object interiors are textured
        (calibrated on synthetic pairs, see the benchmark).
    layers : bool
        Test candidate changes against depth layers (:func:`ops.depth_layers`):
        one that registers at some relative depth is parallax, not change.
    interpolation : float
        The interpolation allowance of :func:`change_score`: this times the
        registered image's absolute second differences along rows and
        columns, summed.  ``1/8`` is the bound of linear interpolation's error
        at a half-pixel offset; 0 disables it.
    """

    threshold: object = "noise"
    k: float = 6.0
    floor: float = 0.05
    min_area: int = 20
    hysteresis: float = 0.5
    half_max_window: int = 15
    half_max: float = 0.42
    layers: bool = True
    interpolation: float = 0.125

    def __post_init__(self):
        t = self.threshold
        if isinstance(t, str):
            if t not in THRESHOLD_METHODS:
                try:
                    t = float(t)
                except ValueError:
                    raise ParameterError(f"threshold: expected one of {THRESHOLD_METHODS} or a number, got {t!r}") from None
        elif not isinstance(t, numbers.Real) or isinstance(t, bool):
            raise ParameterError(f"threshold: expected one of {THRESHOLD_METHODS} or a number, got {t!r}")
        if not isinstance(t, str) and not t > 0:
            raise ParameterError(f"threshold: expected a positive number, got {t!r}")
        object.__setattr__(self, "threshold", t if isinstance(t, str) else float(t))
        if not 0 < self.hysteresis <= 1:
            raise ParameterError(f"hysteresis: expected a fraction in (0, 1], got {self.hysteresis}")
        if self.min_area < 0:
            raise ParameterError(f"min_area: expected >= 0 pixels, got {self.min_area}")
        if not self.interpolation >= 0:
            raise ParameterError(f"interpolation: expected a fraction >= 0, got {self.interpolation!r}")

    @property
    def margin(self):
        """Pixels around a window that :func:`change_candidates` reads to decide
        the window's own pixels (half the half-maximum window, and one more)."""
        return self.half_max_window // 2 + 1


@dataclass(frozen=True)
class ScoreHistogram:
    """Histograms of ``|residual|`` and of non-zero scores; tiles add them up.

    Attributes
    ----------
    residual : ndarray of int64, shape (RESIDUAL_BINS,)
        Counts of ``|g - F w|`` on log-spaced bins from 1e-6 to 4.
    score : ndarray of int64, shape (512,)
        Counts of non-zero ``|chi|`` on linear bins from 0 to 2.
    """

    residual: np.ndarray
    score: np.ndarray

    def __add__(self, other):
        return ScoreHistogram(self.residual + other.residual, self.score + other.score)


def score_histogram(residual, score, valid):
    """Histograms of one window (tile) for :func:`change_threshold`.

    Parameters
    ----------
    residual, score : ndarray, shape (H, W)
        ``g - F w`` and ``|chi|``.
    valid : ndarray of bool, shape (H, W)
    """
    residual_counts = np.zeros(RESIDUAL_BINS, np.int64)
    score_counts = np.zeros(SCORE_BINS, np.int64)
    residual = np.asarray(residual)
    if residual.dtype != np.float32:
        residual = residual.astype(np.float64, copy=False)
    bits = residual.view(np.int32 if residual.dtype == np.float32 else np.int64)
    _histograms(residual, bits, _FLOAT_LAYOUT[residual.dtype.itemsize], np.asarray(score), np.asarray(valid, bool),
                _RESIDUAL_EDGES, _SCORE_EDGES, _RESIDUAL_GUESS, residual_counts, score_counts)
    return ScoreHistogram(residual_counts, score_counts)


#: Cells per octave of :data:`_RESIDUAL_GUESS` (narrower than a residual bin):
#: the leading 8 bits of a float's fraction.
_GUESS_CELLS = 256

#: Where a float's binary exponent and fraction lie in its bits, by its size
#: in bytes: (exponent shift, exponent mask, exponent bias, shift that leaves
#: the fraction's leading log2(_GUESS_CELLS) bits), IEEE 754 binary32 and binary64.
_FLOAT_LAYOUT = {4: (23, 0xFF, 127, 23 - 8), 8: (52, 0x7FF, 1023, 52 - 8)}


def _residual_guesses(edges, cells=_GUESS_CELLS):
    """Where a residual's bin search starts (:func:`_histograms`), by its
    binary exponent and leading mantissa (``math.frexp``: ``r = m 2**e``,
    ``m`` in [0.5, 1)): for each octave ``e`` from the first positive
    edge's to the last edge's, split into ``cells`` cells of ``m``, the bin
    of the cell's lower end.  A start, not the answer: the search walks from
    it to the bin the edges themselves give."""
    e_lo = math.frexp(edges[1])[1]
    e_hi = math.frexp(edges[-1])[1]
    e, k = np.meshgrid(np.arange(e_lo, e_hi + 1), np.arange(cells), indexing="ij")
    lower = np.ldexp(0.5 + 0.5 * k / cells, e)
    guess = np.searchsorted(edges, lower, side="right") - 1
    return np.clip(guess, 0, len(edges) - 2).astype(np.int64).ravel(), int(e_lo)


_RESIDUAL_GUESS = _residual_guesses(_RESIDUAL_EDGES)


@numba.njit(nogil=True, cache=True)
def _histograms(residual, bits, layout, score, valid, residual_edges, score_edges, residual_guess, residual_counts,
                score_counts):
    """:func:`score_histogram`'s counts in one pass, as ``np.histogram`` counts
    them: ``|residual|`` clipped to the last residual edge, the score's positive
    values clipped to the last score edge; bins closed on the left, the last
    one on both sides; NaN is not counted.  A value's bin is found from where
    its binary exponent and mantissa put it (``residual_guess``:
    :func:`_residual_guesses`, read from the residual's ``bits`` as
    ``layout`` (:data:`_FLOAT_LAYOUT`) places them: no logarithm per pixel) or
    the score's even spacing does, then checked against the edges themselves."""
    height, width = valid.shape
    r_last, s_last = residual_edges[-1], score_edges[-1]
    r_first = residual_edges[1]
    table, e_lo = residual_guess
    exp_shift, exp_mask, exp_bias, frac_shift = layout
    last = residual_edges.shape[0] - 2
    s_per_unit = (score_edges.shape[0] - 1) / (s_last - score_edges[0])
    for i in range(height):
        for j in range(width):
            if not valid[i, j]:
                continue
            r = abs(np.float64(residual[i, j]))
            if r == r:
                guess = last
                if r >= r_last:
                    r = r_last
                elif r >= r_first:
                    b = bits[i, j]  # r = m 2**e, m in [0.5, 1) (math.frexp's e and m) from the bits
                    e = ((b >> exp_shift) & exp_mask) - exp_bias + 1
                    guess = table[(e - e_lo) * _GUESS_CELLS + ((b >> frac_shift) & (_GUESS_CELLS - 1))]
                    guess += r >= residual_edges[guess + 1]  # a cell meets two bins at most: no branch
                else:
                    guess = 0
                residual_counts[_bin(residual_edges, r, guess)] += 1
            c = np.float64(score[i, j])
            if c > 0:
                c = min(c, s_last)
                score_counts[_bin(score_edges, c, int((c - score_edges[0]) * s_per_unit))] += 1


@numba.njit(nogil=True, cache=True)
def _bin(edges, value, guess):
    """The bin of ``value`` (within the edges) among ``edges``: the last edge
    at most ``value`` (``np.searchsorted(edges, value, 'right') - 1``), the
    last bin closed on both sides; searched from ``guess``."""
    last = edges.shape[0] - 2
    k = min(max(guess, 0), last)
    while k > 0 and value < edges[k]:
        k -= 1
    while k < last and value >= edges[k + 1]:
        k += 1
    return k


def change_threshold(histogram, *, params=ChangeParams()):
    """Score threshold of :class:`ChangeParams` from (summed) histograms.

    Returns
    -------
    float
        In score units (intensities in [0, 1]).
    """
    if not isinstance(params.threshold, str):
        return float(params.threshold)
    if params.threshold == "kapur":
        t = kapur_threshold_histogram(histogram.score, _SCORE_EDGES)
        return float(max(t if np.isfinite(t) else params.floor, params.floor))
    if histogram.residual.sum() == 0:
        return float(params.floor)
    return float(max(params.k * 1.4826 * float(residual_median(histogram.residual)), params.floor))


def residual_median(counts):
    """Median ``|residual|`` of residual histograms (the upper edge of the median
    bin, about 1 % resolution).

    Parameters
    ----------
    counts : ndarray, shape (..., RESIDUAL_BINS)
        ``ScoreHistogram.residual`` counts, one histogram or a stack (e.g. per tile).

    Returns
    -------
    ndarray, shape (...)
    """
    cum = np.cumsum(counts, axis=-1)
    index = (cum < 0.5 * cum[..., -1:]).sum(axis=-1)
    return _RESIDUAL_EDGES[np.minimum(index + 1, len(_RESIDUAL_EDGES) - 1)]


def change_score(chi, registered, *, params=ChangeParams()):
    """The change score: ``|chi|`` less the interpolation allowance
    ``params.interpolation * (|f_xx| + |f_yy|)`` of the registered image ``f``
    (second differences; see the module docstring), never below 0.

    Parameters
    ----------
    chi : ndarray, shape (H, W)
        The change term of eq. 13.
    registered : ndarray, shape (H, W)
        The registered image ``F w`` (NaN where unknown), same units as ``chi``.

    Returns
    -------
    ndarray of float32, shape (H, W)
        Local (3-pixel second differences, borders replicated): a window
        (tile) gives the score of the whole image except on its outermost
        pixels.
    """
    chi = np.asarray(chi, dtype=np.float32)
    if params.interpolation <= 0:
        return np.abs(chi)
    registered = np.asarray(registered, dtype=np.float32)
    if chi.ndim != 2 or chi.shape != registered.shape:
        raise ParameterError(f"change_score: expected chi and registered of one (H, W) shape, got {chi.shape} "
                             f"and {registered.shape}")
    out = np.empty(chi.shape, np.float32)
    _allowed_score(chi, registered, np.float32(params.interpolation), out)
    return out


@numba.njit(nogil=True, cache=True)
def _allowed_score(chi, image, k, out):
    """:func:`change_score` in one pass: ``max(|chi| - k * (|f_xx| + |f_yy|),
    0)`` in float32 (NaN kept), ``f`` the registered ``image`` with 3-pixel
    second differences, a neighbour beyond the image or unknown (NaN: a hole
    in the model, a failed row) replaced by the pixel itself, as the image's
    borders are replicated, and no allowance where the pixel itself is
    unknown.  (Taking unknown as 0 would give the pixels around every hole an
    allowance of their own value and hide their changes.)"""
    h, w = image.shape
    two, zero = np.float32(2.0), np.float32(0.0)
    for i in range(h):
        for j in range(w):
            c = image[i, j]
            allowance = zero
            if math.isfinite(c):
                b = image[i - 1, j] if i > 0 else c
                a = image[i + 1, j] if i < h - 1 else c
                b = b if math.isfinite(b) else c
                a = a if math.isfinite(a) else c
                along_y = abs((b - two * c) + a)
                b = image[i, j - 1] if j > 0 else c
                a = image[i, j + 1] if j < w - 1 else c
                b = b if math.isfinite(b) else c
                a = a if math.isfinite(a) else c
                allowance = along_y + abs((b - two * c) + a)
            x = abs(chi[i, j]) - k * allowance
            out[i, j] = x if (x >= zero or x != x) else zero


def change_candidates(score, threshold, *, params=ChangeParams(), explained=None):
    """Pixels that may belong to a change: above ``hysteresis * threshold`` and at
    least ``half_max`` times the largest score, or ``explained`` score, within
    the ``half_max_window`` square around them.

    Local (a window of ``half_max_window // 2`` px around a pixel decides), so a
    tile computes it on its core grown by ``params.margin``.

    Parameters
    ----------
    score : ndarray, shape (H, W)
        ``|chi|``; NaN or 0 where nothing is known.
    threshold : float
        From :func:`change_threshold`.
    explained : ndarray, shape (H, W), optional
        What the depth explained away: the score parallax pixels had at the
        ground's depth, 0 (or NaN) elsewhere (:attr:`MethodResult.explained`).
        Those scores count towards the largest score of the window as a
        change's own do, and nothing else: motion blur spreads a raised
        structure's residual onto its neighbours as it spreads a change's, so
        a neighbour under ``half_max`` of the residual the depth explained is
        its blurred rim, not a change of its own.  The price: a new object of
        less than ``half_max`` of that residual's contrast loses the side of
        it within half the window of the structure (and all of it when the
        rest is under ``min_area``), as it would beside a stronger change.

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    score = np.nan_to_num(np.asarray(score, dtype=np.float32))
    mask = score > params.hysteresis * threshold
    if params.half_max_window > 1:
        kernel = np.ones((params.half_max_window, params.half_max_window), np.uint8)
        peak = score if explained is None else np.maximum(score, np.nan_to_num(np.asarray(explained, np.float32)))
        mask &= score >= params.half_max * cv2.dilate(peak, kernel)  # a maximum filter
    return mask


def label_components(mask, score):
    """8-connected components of ``mask`` with their area and largest score.

    Returns
    -------
    labels : ndarray of int32, shape (H, W)
        0 background, 1..n components (scikit-image's labelling, in raster order).
    area : ndarray of int64, shape (n + 1,)
    peak : ndarray of float32, shape (n + 1,)
        Largest ``score`` of each component (a component is a change when its
        peak reaches the threshold: hysteresis).
    """
    labels, n = measure.label(mask, connectivity=2, return_num=True)
    labels = labels.astype(np.int32)
    # region statistics by bincount: skimage's regionprops_table gives the same
    # numbers about ten times slower (a Python loop over the regions; measured on
    # a candidate mask of 2600 components)
    area = np.bincount(labels.ravel(), minlength=n + 1).astype(np.int64)
    peak = np.zeros(n + 1, dtype=np.float32)
    inside = labels > 0  # ufunc.at over the components' pixels only: it is slow per element
    np.maximum.at(peak, labels[inside], np.nan_to_num(np.asarray(score, np.float32)[inside]))
    return labels, area, peak


def keep_components(area, peak, threshold, *, params=ChangeParams()):
    """Boolean per component (index 0 = background, never kept): large enough and
    reaching the threshold."""
    keep = (area >= params.min_area) & (peak > threshold)
    keep[0] = False
    return keep


def over_threshold(chi, valid, threshold):
    """The valid pixels of a registration whose change term alone exceeds
    ``threshold`` (score units): ``|chi| > threshold`` (bool), before any
    allowance or hysteresis (:func:`change_candidates`).  The one rule the
    re-grounding, the depth layers and their rims start from."""
    return (np.abs(chi) > threshold) & valid


def large_components(mask, min_area, *, connectivity=2, border=False):
    """The components of ``mask`` with at least ``min_area`` pixels: the one
    label-and-area filter of rsmb.

    Parameters
    ----------
    mask : ndarray of bool, shape (H, W)
    min_area : int
        Smallest component kept, pixels.
    connectivity : {1, 2}
        4-connected (1) or 8-connected (2) components (scikit-image's convention).
    border : bool
        Also keep every component that touches the edge of ``mask`` (it may go
        on outside, where its size is unknown).

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    labels, n = measure.label(mask, connectivity=connectivity, return_num=True)
    keep = np.bincount(labels.ravel(), minlength=n + 1) >= min_area
    if border:
        keep[np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])] = True
    keep[0] = False
    return keep[labels]


def fill_holes(mask, *, params=ChangeParams()):
    """Fill holes smaller than ``min_area`` inside changes: 4-connected background
    regions enclosed by one 8-connected change (background that reaches the
    border of ``mask`` is not a hole).  Works object by object, on bounding boxes,
    so its cost follows the changes rather than the window.  (skimage's
    ``image_filled`` fills only what 8-connected background cannot leave; a hole
    here is 4-connected, so a diagonal gap closes it.)"""
    out = mask.copy()
    if params.min_area <= 1 or not mask.any():
        return out
    for region in measure.regionprops(measure.label(mask, connectivity=2)):
        holes = ndimage.binary_fill_holes(region.image) & ~mask[region.slice]
        if holes.any():
            out[region.slice] |= holes & ~large_components(holes, params.min_area, connectivity=1)
    return out


def change_mask(score, threshold, *, params=ChangeParams(), explained=None):
    """Boolean change mask of a whole score image (the tiled pipeline computes the
    same from the pieces :func:`change_candidates`, :func:`label_components`,
    :func:`keep_components` and :func:`fill_holes`, merging labels across seams).

    Parameters
    ----------
    score : ndarray, shape (H, W)
        ``|chi|``, 0 where nothing is known.
    threshold : float
        From :func:`change_threshold`.
    explained : ndarray, shape (H, W), optional
        As :func:`change_candidates`.

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    labels, area, peak = label_components(change_candidates(score, threshold, params=params, explained=explained),
                                          score)
    return fill_holes(keep_components(area, peak, threshold, params=params)[labels], params=params)


@numba.njit(nogil=True, cache=True)
def _lookup(hom, dist_shape, ref_shape, ref_origin, dist_origin, iterations):
    rows = np.full(ref_shape, -1, dtype=np.int32)
    cols = np.full(ref_shape, -1, dtype=np.int32)
    hd, wd = dist_shape
    for v in range(ref_shape[0]):
        yg = v + ref_origin[0]
        for u in range(ref_shape[1]):
            xg = u + ref_origin[1]
            row = yg - dist_origin[0]
            xs = 0.0
            ri = min(max(int(round(row)), 0), hd - 1)
            for _ in range(iterations):
                h = hom[ri]
                den = h[2, 0] * xg + h[2, 1] * yg + h[2, 2]
                xs = (h[0, 0] * xg + h[0, 1] * yg + h[0, 2]) / den
                row = (h[1, 0] * xg + h[1, 1] * yg + h[1, 2]) / den - dist_origin[0]
                nxt = min(max(int(round(row)), 0), hd - 1)
                if nxt == ri:  # a fixed point: further iterations repeat this one exactly
                    break
                ri = nxt
            col = xs - dist_origin[1]
            ri, ci = int(round(row)), int(round(col))
            if 0 <= ri < hd and 0 <= ci < wd:
                rows[v, u] = ri
                cols[v, u] = ci
    return rows, cols


def reference_lookup(trajectory, *, axes, camera, reference_shape, distorted_shape=None, reference_origin_yx=(0, 0),
                     distorted_origin_yx=(0, 0), iterations=4):
    """The distorted pixel each reference pixel is seen at: the ground frame's
    index into the sensor frame.

    Each reference pixel is carried forward by the pose of the row it lands in,
    found by a fixed-point iteration (a rolling-shutter row depends on where the
    point lands), and rounded to the nearest distorted pixel.

    Parameters
    ----------
    trajectory : ndarray, shape (H, D)
        Per-row centroid poses over ``axes`` (global pose coordinates) of the
        distorted window's rows.
    camera : Camera
        Intrinsics of the whole image.
    reference_shape : tuple of int
        (Hr, Wr) of the reference window to fill.
    distorted_shape : tuple of int, optional
        (H, W) of the distorted window; default (H, the reference width).

    Returns
    -------
    rows, cols : ndarray of int32, shape reference_shape
        Pixel of the distorted window, -1 in both where the reference pixel
        lands outside it.
    """
    trajectory = np.asarray(trajectory)
    if distorted_shape is None:
        distorted_shape = (trajectory.shape[0], int(reference_shape[1]))
    hom = pose_homographies(np.nan_to_num(trajectory), camera, axes=axes)
    return _lookup(np.ascontiguousarray(hom), tuple(int(v) for v in distorted_shape),
                   tuple(int(v) for v in reference_shape), np.asarray(reference_origin_yx, dtype=np.float64),
                   np.asarray(distorted_origin_yx, dtype=np.float64), int(iterations))


def sample_at(values, rows, cols, *, fill):
    """``values[rows, cols]`` with ``fill`` where the index is -1 (see
    :func:`reference_lookup`): a sensor-frame array carried to the ground frame.

    Parameters
    ----------
    values : ndarray, shape (H, W)
    rows, cols : ndarray of int, shape (Hr, Wr)
    fill : scalar
        Value where the reference pixel lands outside ``values``.

    Returns
    -------
    ndarray, shape (Hr, Wr), dtype of ``values``
    """
    return _gather(values, *_flat_index(rows, cols, np.shape(values)[1]), fill)


def _flat_index(rows, cols, width):
    """Indices of :func:`reference_lookup` into a raveled array of ``width``
    columns (0 where outside), and where they are outside: computed once for
    every array carried by the same lookup."""
    outside = rows < 0
    flat = rows.astype(np.intp) * int(width) + cols
    flat[outside] = 0
    return flat, outside


def _gather(values, flat, outside, fill):
    """``values`` at raveled indices ``flat``, ``fill`` where ``outside``
    (one ``np.take``: a boolean-masked fancy index costs several passes)."""
    out = np.take(np.ascontiguousarray(values).reshape(-1), flat)
    out[outside] = fill
    return out


def changes_to_reference(mask, trajectory, *, axes, camera, reference_shape, reference_origin_yx=(0, 0),
                         distorted_origin_yx=(0, 0), iterations=4, fill=0):
    """Mark the reference pixels that the estimated poses carry onto changed pixels.

    Each reference pixel takes the mask value of the distorted pixel it is seen
    at (:func:`reference_lookup`).

    Parameters
    ----------
    mask : ndarray of bool or uint8, shape (H, W)
        Changes in the distorted grid (uint8 may hold 255: no evidence).
    trajectory : ndarray, shape (H, D)
        Per-row centroid poses over ``axes`` (global pose coordinates).
    camera : Camera
        Intrinsics of the whole image.
    reference_shape : tuple of int
        (Hr, Wr) of the reference window to fill.
    fill : int
        Value of reference pixels seen outside ``mask``.

    Returns
    -------
    ndarray of uint8, shape reference_shape
    """
    mask = np.asarray(mask, dtype=np.uint8)
    rows, cols = reference_lookup(trajectory, axes=axes, camera=camera, reference_shape=reference_shape,
                                  distorted_shape=mask.shape, reference_origin_yx=reference_origin_yx,
                                  distorted_origin_yx=distorted_origin_yx, iterations=iterations)
    return sample_at(mask, rows, cols, fill=np.uint8(fill))


#: The mask value of a pixel with no evidence (no-data, not seen, a NaN score),
#: in the store as in the GeoTIFFs: distinct from 0, "no change".
NO_EVIDENCE = 255


def evidence_mask(mask, score):
    """A change mask with its pixels of no evidence marked.

    Parameters
    ----------
    mask : ndarray of bool, shape (H, W)
        The changes.
    score : ndarray, shape (H, W)
        The change score; NaN: no evidence.

    Returns
    -------
    ndarray of uint8, shape (H, W)
        1 where ``mask``, else :data:`NO_EVIDENCE` where the score is NaN, else 0.
    """
    out = np.where(np.isfinite(score), np.uint8(0), np.uint8(NO_EVIDENCE))
    out[np.asarray(mask, dtype=bool)] = 1
    return out


class GroundFrame(NamedTuple):
    """Sensor-frame results carried to the reference grid (see :func:`to_ground`).

    Attributes
    ----------
    mask : ndarray of uint8, shape (Hr, Wr)
        1 change, 0 no change, :data:`NO_EVIDENCE` no evidence or not seen.
    score : ndarray of float32, shape (Hr, Wr)
        The change score; NaN where no evidence or not seen.
    parallax : ndarray of uint8, shape (Hr, Wr)
        1 parallax, 0 not, :data:`NO_EVIDENCE` no evidence or not seen.
    """

    mask: np.ndarray
    score: np.ndarray
    parallax: np.ndarray


def to_ground(mask, score, parallax, trajectory, *, axes, camera, reference_shape, reference_origin_yx=(0, 0),
              distorted_origin_yx=(0, 0)):
    """The change mask, score and parallax mask of a distorted window in the
    reference grid: each reference pixel takes the values of the distorted
    pixel it is seen at (:func:`reference_lookup`; nearest pixel).

    Parameters
    ----------
    mask, parallax : ndarray of uint8, shape (H, W)
        Sensor-frame masks as :func:`evidence_mask` makes them.
    score : ndarray, shape (H, W)
        Sensor-frame change score, NaN: no evidence.
    trajectory : ndarray, shape (H, D)
        Per-row centroid poses of the window's rows over ``axes``.
    camera : Camera
    reference_shape : tuple of int
        (Hr, Wr) of the reference window.

    Returns
    -------
    GroundFrame
        Reference pixels seen outside the window have no evidence.
    """
    rows, cols = reference_lookup(trajectory, axes=axes, camera=camera, reference_shape=reference_shape,
                                  distorted_shape=np.shape(mask), reference_origin_yx=reference_origin_yx,
                                  distorted_origin_yx=distorted_origin_yx)
    index = _flat_index(rows, cols, np.shape(mask)[1])
    return GroundFrame(_gather(np.asarray(mask, np.uint8), *index, np.uint8(NO_EVIDENCE)),
                       _gather(np.asarray(score, np.float32), *index, np.float32(np.nan)),
                       _gather(np.asarray(parallax, np.uint8), *index, np.uint8(NO_EVIDENCE)))


@dataclass(frozen=True)
class ChangeResult:
    """Changes of one whole window (see :func:`detect_changes`).

    Attributes
    ----------
    score : ndarray, shape (H, W), float32
        ``|chi|``.
    mask : ndarray of bool, shape (H, W)
        Changes in the distorted grid.
    mask_reference : ndarray of bool, shape (H, W)
        Changes in the reference grid.
    threshold : float
    """

    score: np.ndarray
    mask: np.ndarray
    mask_reference: np.ndarray
    threshold: float


def detect_changes(registration, distorted, *, camera, params=ChangeParams()):
    """Change masks of a whole image from its :class:`ops.Registration` alone
    (no re-grounding, depth layers or clipped pixels: the whole method's
    masks are :func:`ops.method_changes` of :func:`ops.run_method`).

    Parameters
    ----------
    registration : Registration
        Of ``distorted`` against a reference of the same shape (origins 0).
    distorted : ndarray, shape (H, W)
    camera : Camera

    Returns
    -------
    ChangeResult
    """
    score = change_score(registration.chi, registration.registered, params=params)
    residual = np.where(registration.valid, distorted - registration.registered, 0.0)
    threshold = change_threshold(score_histogram(residual, score, registration.valid), params=params)
    mask = change_mask(score, threshold, params=params)
    ref = changes_to_reference(mask, registration.trajectory, axes=registration.axes, camera=camera,
                               reference_shape=mask.shape)
    return ChangeResult(score, mask, ref > 0, threshold)
