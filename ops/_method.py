"""The method on one tile, or one small image, from its two windows to its
change score (METHOD.md section 3): the order of the steps lives here, once,
so that a library user and ``rsmb detect`` get the same answer.

1. Put both windows on the common intensity scale (clipped pixels NaN).
2. Register the capture's rows against the reference (eq. 13 per row).
3. Re-ground the rows that followed something nearer than the ground; give
   back their model to the pixels the row solves left out only because the
   search grid touched a clipped pixel (their weighted poses do not).
4. Depth layers, the dense depth map and the rows re-solved at depth.
5. The change score; the pixels the plane left without a model (clipped ones)
   scored on their model interval; parallax is never change, and what its
   depth explained still bounds its neighbours' half-maximum test.

The tiled pipeline reads the windows, calls :func:`run_method` per tile and
writes what it returns; the threshold of the whole mosaic and the masks come
after, from the summed histograms (:func:`method_changes` does those steps
for a single window).
"""

from dataclasses import dataclass, field, replace

import numpy as np

from ._oracle import optimal_chi
from ._timing import StageClock
from .changes._changes import (
    ChangeParams,
    ChangeResult,
    change_mask,
    change_score,
    change_threshold,
    changes_to_reference,
    score_histogram,
)
from .changes._bounds import ModelBounds, bounded_score, model_bounds
from .depth._depthsolve import depth_step
from .depth._layers import LayerResult
from .registration._params import RegistrationParams
from .registration._register import register
from .registration._reground import reground

__all__ = ["MethodResult", "run_method", "method_changes"]


@dataclass(frozen=True)
class MethodResult:
    """What :func:`run_method` finds on one window.

    Attributes
    ----------
    registration : Registration
        The rows' solution (after re-grounding), in the window's pixels.
    registered : ndarray, shape (H, W), float32
        The model: the reference warped and blurred to look like the capture,
        depth layers re-rendered at their depth, on the common scale.
    score : ndarray, shape (H, W), float32
        The change score, NaN where there is no evidence (0 on parallax).
    parallax : ndarray of bool, shape (H, W)
        Pixels explained as depth, not change.
    components : list of dict
        The depth layers found (see :class:`LayerResult`).
    histogram : ScoreHistogram
        Residual and score histograms of the window (they add up over tiles).
    timings : dict
        CPU-seconds of the calling thread per stage (``<stage>_s``).
    explained : ndarray, shape (H, W), float32, or None
        The score the parallax pixels had at the ground's depth (the
        re-grounded registration's), 0 elsewhere; None when no pixel is
        parallax.  The masks' half-maximum test measures the neighbours of
        parallax against it (:func:`change_candidates`).
    """

    registration: object
    registered: np.ndarray
    score: np.ndarray
    parallax: np.ndarray
    components: list = field(default_factory=list)
    histogram: object = None
    timings: dict = field(default_factory=dict)
    explained: np.ndarray = None


def run_method(reference, capture, *, camera, params=None, changes=None, intensity=None, reference_origin_yx=(0, 0),
               distorted_origin_yx=(0, 0), prior=None, slow="auto", start=None):
    """The method on one window: register, re-ground, depth, change score.

    Parameters
    ----------
    reference : ndarray, shape (Hr, Wr), float32
        The reference window as ingested (NaN for no-data), covering the
        capture window plus the search margin on every side (NaN beyond the
        image's edges: ``rsmb detect`` reads it so, and the pixels near the
        edges take the same values only then).
    capture : ndarray, shape (H, W), float32
        The capture window as ingested (NaN for no-data).
    camera : Camera
    params : RegistrationParams, optional
    changes : ChangeParams, optional
    intensity : IntensityScale, optional
        The two images' common scale and clip levels (:func:`intensity_scale`);
        None: the windows are on one scale already and nothing is clipped.
    reference_origin_yx, distorted_origin_yx : tuple of int
        Where the windows start in the whole image (pixels).
    prior, slow, start :
        As :func:`register`.

    Returns
    -------
    MethodResult
    """
    params = params or RegistrationParams()
    changes = changes or ChangeParams()
    clock = StageClock()
    origins = dict(reference_origin_yx=reference_origin_yx, distorted_origin_yx=distorted_origin_yx)
    reference, capture = np.asarray(reference, np.float32), np.asarray(capture, np.float32)
    ref = _on_scale(reference, intensity, "reference")
    distorted = _on_scale(capture, intensity, "capture")
    valid = np.isfinite(distorted)
    dist = np.nan_to_num(distorted)  # NaN: no-data
    result = register(ref, dist, camera=camera, params=params, distorted_valid=valid, prior=prior, slow=slow,
                      start=start, **origins)
    with clock.stage("score"):
        window = _window_histogram(result, dist)
    result = reground(result, ref, dist, camera=camera, params=params,
                      threshold=change_threshold(window, params=changes), min_area=changes.min_area,
                      distorted_valid=valid, **origins)
    with clock.stage("score"):
        bounds = _clip_bounds(result, capture, reference, intensity, camera, origins)
        result, point = _fitted_beside_clipped(result, distorted, bounds, params)
        if changes.layers:  # the depth steps' threshold: the window's residuals as re-grounded and fitted
            window = _updated_histogram(window, result, dist, point)
    with clock.stage("depth"):
        layers = _depth(result, ref, dist, camera, params, changes, origins, change_threshold(window, params=changes))
    with clock.stage("score"):
        chi, model, known = layers.chi, layers.registered, result.valid
        bounded = _bounded(capture, intensity, result, bounds, params)
        if bounded is not None:  # the pixels the plane left unscored: their model interval decides
            chi = np.where(result.valid, chi, bounded[0])
            model = np.where(result.valid, model, bounded[1])
            known = result.valid | np.isfinite(bounded[0])
        score = np.where(known, change_score(chi, model, params=changes), np.nan)  # NaN: no evidence
        explained = None
        if layers.parallax.any():
            ground = change_score(result.chi, result.registered, params=changes)
            explained = np.where(layers.parallax, np.nan_to_num(ground), 0.0).astype(np.float32)
        score = np.where(layers.parallax & np.isfinite(score), 0.0, score)  # parallax is never change, clipped or not
        residual = np.where(result.valid, distorted - layers.registered, 0.0)
        hist = score_histogram(residual, score, result.valid)
    timings = {**result.timings, **clock.seconds}
    return MethodResult(result, model, score.astype(np.float32), layers.parallax, layers.components, hist, timings,
                        explained)


def method_changes(result, *, camera, params=None):
    """Change masks of one whole image from its :func:`run_method` result:
    the threshold of its histograms, the components, the reference grid (what
    the tiled pipeline does over the mosaic).

    Returns
    -------
    ChangeResult
    """
    params = params or ChangeParams()
    threshold = change_threshold(result.histogram, params=params)
    mask = change_mask(np.nan_to_num(result.score), threshold, params=params, explained=result.explained)
    reg = result.registration
    ref = changes_to_reference(mask, reg.trajectory, axes=reg.axes, camera=camera, reference_shape=mask.shape)
    return ChangeResult(result.score, mask, ref > 0, threshold)


def _on_scale(values, intensity, name):
    values = np.asarray(values, np.float32)
    return values if intensity is None else intensity.apply(values, name)


def _window_histogram(result, capture):
    """The histograms of the window's own residuals and ``|chi|``, whose
    change threshold the window's steps use (a mosaic's is not known yet)."""
    residual = np.where(result.valid, capture - result.registered, 0.0)
    return score_histogram(residual, np.abs(result.chi), result.valid)


def _updated_histogram(window, result, capture, point):
    """:func:`_window_histogram` of ``result`` from ``window``, that of the
    registration before re-grounding and :func:`_fitted_beside_clipped`:
    the counts add up over pixels, so when no row was re-grounded (the rows
    left as they were) only the newly fitted pixels ``point`` (None: none)
    are added; otherwise the window is counted again."""
    if result.timings.get("regrounded_rows", 0):
        return _window_histogram(result, capture)
    if point is None:
        return window
    residual = (capture[point] - result.registered[point])[None, :]  # valid there: no where needed
    return window + score_histogram(residual, np.abs(result.chi[point])[None, :], np.ones(residual.shape, bool))


def _depth(result, reference, capture, camera, params, changes, origins, threshold):
    """Depth layers, the dense depth map and the rows re-solved at depth
    (:func:`depth_step`) with the window's own ``threshold``; the registration
    as it is when ``changes.layers`` is off."""
    if not changes.layers:
        return LayerResult(np.zeros(result.valid.shape, bool), result.registered, result.chi)
    out, _, _ = depth_step(result, reference, capture, camera=camera, threshold=threshold,
                           space=params.resolved(camera).space, lambda_w=params.lambda_w,
                           lambda_chi=params.lambda_chi, **origins)
    return out


def _bounded(capture, intensity, result, bounds, params):
    """The change term of the capture pixels the registration left without a
    model (its row solves leave clipped pixels out, so a pixel whose search
    grid touches one, or a clipped capture pixel, has none): each pixel's
    model interval from its row's active poses and blur (``bounds``:
    :func:`_clip_bounds`), with clipped pixels as bounds
    (:func:`bounded_score`).  Returns (chi, model) on the common scale, NaN
    where there is no evidence, or None when nothing is clipped (no
    intensity scale) or every capture pixel with data has its model.
    ``capture``: the window as ingested."""
    need = _unmodelled(result, capture)
    if bounds is None or not need.any():
        return None
    scaled, cap_high, cap_low = _clipped_on_scale(capture, intensity, intensity.capture_clip)
    # elementwise: scored on the pixels that need it only (a few per cent of the window)
    chi = np.full(need.shape, np.nan, np.float32)
    chi[need] = bounded_score(scaled[need], ModelBounds(bounds.model[need], bounds.high_share[need],
                                                        bounds.low_share[need]), cap_high[need], cap_low[need],
                              lambda_chi=params.lambda_chi)
    return chi, bounds.model


def _clip_bounds(result, capture, reference, intensity, camera, origins):
    """The model interval (:func:`model_bounds`) of every capture pixel with
    data that the registration left without a model, clipped reference pixels
    as bounds; None when nothing is clipped (no intensity scale) or every such
    pixel has its model.  Computed once: it depends only on the rows' active
    poses, which the steps after it do not change.  ``capture``,
    ``reference``: the windows as ingested."""
    need = _unmodelled(result, capture)
    if intensity is None or not need.any():
        return None
    scaled, ref_high, ref_low = _clipped_on_scale(reference, intensity, intensity.reference_clip)
    return model_bounds(result, scaled, ref_high, ref_low, need, camera=camera, **origins)


def _unmodelled(result, capture):
    """Capture pixels with data that the registration left without a model."""
    return ~result.valid & np.isfinite(capture)


def _clipped_on_scale(values, intensity, levels):
    """An image as ingested on the common scale (clipped pixels at their clip
    levels, times the scale's factor), and its pixels at or beyond its clip
    ``levels`` (high, low)."""
    high, low = _at_clip(values, levels)
    return values * np.float32(intensity.scaled(1.0)), high, low


def _fitted_beside_clipped(result, distorted, bounds, params):
    """The registration with the pixels that lost their model only to the
    row solves' search grid given it back.  A row solve leaves out every
    pixel whose search grid touches a clipped reference pixel (a disk as
    wide as the search window around each one), but a pixel whose row's
    weighted poses (its active poses and their blur) touch none, and whose
    capture value is not clipped, has a point model as any fitted pixel
    does: its ``registered``, ``chi`` (eq. 13's, soft-thresholded) and
    ``valid`` are set, so that the depth steps and the score treat it as
    fitted (the depth map charges a pixel without a model the threshold,
    so any depth would seem to explain the pixels around every clipped
    one).  ``distorted``: the capture on the common scale (NaN: clipped or
    no-data); ``bounds``: :func:`_clip_bounds`.  Returns the registration
    and the pixels given their model (None: none, the registration as it was)."""
    if bounds is None:
        return result, None
    point = (~result.valid & np.isfinite(distorted) & np.isfinite(bounds.model) & (bounds.high_share == 0)
             & (bounds.low_share == 0))
    if not point.any():
        return result, None
    registered, chi, valid = result.registered.copy(), result.chi.copy(), result.valid.copy()
    registered[point] = bounds.model[point]
    chi[point] = optimal_chi(distorted[point] - bounds.model[point], lambda_chi=params.lambda_chi)
    valid[point] = True
    return replace(result, registered=registered, chi=chi, valid=valid), point


def _at_clip(values, levels):
    """Pixels at or beyond an image's (floor, saturation) clip levels."""
    low, high = levels
    with np.errstate(invalid="ignore"):
        at_high = values >= np.float32(high) if high is not None else np.zeros(values.shape, bool)
        at_low = values <= np.float32(low) if low is not None else np.zeros(values.shape, bool)
    return at_high, at_low
