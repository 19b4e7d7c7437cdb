"""Clipped values are bounds (ops.changes._bounds, ops.fill_zeros): the model
interval of a capture pixel and the change term against it."""

import numpy as np
import pytest

from rsmb import ops
from rsmb.ops.changes._bounds import TOUCH


def _bounds(model, high=0.0, low=0.0):
    model = np.asarray(model, np.float32)
    return ops.ModelBounds(model, np.full(model.shape, high, np.float32), np.full(model.shape, low, np.float32))


def test_an_unclipped_pixel_is_eq13s_chi():
    g = np.array([[0.5, 0.5, 0.5]], np.float32)
    chi = ops.bounded_score(g, _bounds([[0.5, 0.2, 0.9]]), np.zeros(g.shape, bool), np.zeros(g.shape, bool),
                            lambda_chi=0.02)
    np.testing.assert_allclose(chi, [[0.0, 0.29, -0.39]], atol=1e-6)


def test_a_saturated_support_is_a_lower_bound():
    """The reference saturated under a pixel: the scene was at least that
    bright.  A capture far darker (a dark car on a white roof) is change; a
    brighter one is not; a capture saturated too says nothing."""
    g = np.array([[0.1, 0.95, 1.0]], np.float32)
    at_high = np.array([[False, False, True]])
    chi = ops.bounded_score(g, _bounds([[0.8, 0.8, 0.8]], high=0.6), at_high, np.zeros(g.shape, bool),
                            lambda_chi=0.02)
    np.testing.assert_allclose(chi[0, :2], [-(0.7 - 0.01), 0.0], atol=1e-6)
    assert np.isnan(chi[0, 2])


def test_a_support_at_zero_is_an_upper_bound():
    """The reference at 0 under a pixel: the scene was at most that dark.  A
    bright object in the shadow is change; a darker capture is not; a capture
    at 0 says nothing."""
    g = np.array([[0.9, 0.0, 0.0]], np.float32)
    at_low = np.array([[False, False, True]])
    chi = ops.bounded_score(g, _bounds([[0.05, 0.05, 0.05]], low=0.6), np.zeros(g.shape, bool), at_low,
                            lambda_chi=0.02)
    np.testing.assert_allclose(chi[0, :2], [0.85 - 0.01, 0.0], atol=1e-6)
    assert np.isnan(chi[0, 2])


def test_a_saturated_capture_is_change_only_where_the_model_stays_below():
    """The capture saturated where the reference was not: a new bright roof
    (the model far below saturation) is change; a bright field that
    saturates under a gain (the model reaches saturation) is not; neither
    is no-data."""
    g = np.array([[1.0, 1.0]], np.float32)
    at_high = np.ones(g.shape, bool)
    chi = ops.bounded_score(g, _bounds([[0.4, 1.05]]), at_high, np.zeros(g.shape, bool), lambda_chi=0.02)
    np.testing.assert_allclose(chi, [[0.6 - 0.01, 0.0]], atol=1e-6)


def test_no_evidence_only_where_the_intervals_say_nothing():
    g = np.array([[0.5, 0.5, 0.5]], np.float32)
    none = np.zeros(g.shape, bool)
    both = ops.ModelBounds(np.array([[0.5, 0.5, np.nan]], np.float32), np.array([[0.5, 0.3, 0]], np.float32),
                           np.array([[0.5, 0.0, 0]], np.float32))
    chi = ops.bounded_score(g, both, none, none, lambda_chi=0.02)
    # whole support clipped and the capture inside: nothing known; partly clipped: consistent (0); model unknown
    assert np.isnan(chi[0, 0]) and chi[0, 1] == 0.0 and np.isnan(chi[0, 2])


def test_no_evidence_exactly_where_chi_is_unbounded_both_ways():
    """eq. 13's change term lies in [capture low - model high, capture high -
    model low]: no evidence only where that is the whole line, whatever the
    model's value at the clip levels; elsewhere the point nearest 0,
    soft-thresholded."""
    lam = 0.02
    # capture saturated (1.0) against models open upwards, from far below to above saturation: chi unbounded
    g = np.ones((1, 3), np.float32)
    chi = ops.bounded_score(g, _bounds([[0.3, 0.99, 1.2]], high=0.2), np.ones(g.shape, bool),
                            np.zeros(g.shape, bool), lambda_chi=lam)
    assert np.isnan(chi).all()
    # capture at 0 against models open downwards: the same, mirrored
    g = np.zeros((1, 3), np.float32)
    chi = ops.bounded_score(g, _bounds([[0.0, 0.05, 0.6]], low=0.2), np.zeros(g.shape, bool),
                            np.ones(g.shape, bool), lambda_chi=lam)
    assert np.isnan(chi).all()
    # a model open both ways says nothing, whatever the capture
    g = np.array([[0.0, 0.5, 1.0]], np.float32)
    chi = ops.bounded_score(g, _bounds([[0.5, 0.5, 0.5]], high=0.3, low=0.3), g >= 1.0, g <= 0.0, lambda_chi=lam)
    assert np.isnan(chi).all()
    # a whole support saturated (model [0.8, inf)) under a brighter unclipped capture: chi in (-inf, 0.1], holds
    # 0 (consistent, and rules out a brightening); under a darker one: chi in (-inf, -0.3], change
    g = np.array([[0.9, 0.5]], np.float32)
    none = np.zeros(g.shape, bool)
    chi = ops.bounded_score(g, _bounds([[0.8, 0.8]], high=1.0), none, none, lambda_chi=lam)
    np.testing.assert_allclose(chi, [[0.0, -(0.3 - lam / 2)]], atol=1e-6)
    # a saturated capture against a point model: chi in [1 - m, inf)
    g = np.ones((1, 2), np.float32)
    chi = ops.bounded_score(g, _bounds([[0.995, 0.7]]), np.ones(g.shape, bool), none, lambda_chi=lam)
    np.testing.assert_allclose(chi, [[0.0, 0.3 - lam / 2]], atol=1e-6)


def _scene(shape, seed):
    return (0.1 + 0.6 * ops.aerial_scene(shape, seed=seed)).astype(np.float32)


def test_the_bound_footprint_is_the_active_poses_times_the_blur():
    """One saturated reference pixel: the row solves leave it out, so every
    capture pixel whose search grid touches it loses its fit (a disk as wide
    as the search window), but only the pixels whose row's weighted poses
    (the motion and its blur) touch it have an open model."""
    pair = ops.synthesize_pair((128, 128), motion="translation", changes=0, noise=0.002, seed=4, exposure=6.0,
                               scale=0.3, scene=None)
    reference = pair.reference.copy()
    y, x = 64, 64
    reference[y, x] = 1.0
    high = np.zeros(reference.shape, bool)
    high[y, x] = True
    holed = np.where(high, np.nan, reference)
    reg = ops.register(holed, pair.distorted, camera=pair.camera)
    blind = ~reg.valid
    bounds = ops.model_bounds(reg, reference, high, np.zeros(reference.shape, bool), blind, camera=pair.camera)
    # the model is the registration's (ops.model_values) with the clipped pixel at its level
    np.testing.assert_allclose(bounds.model, ops.model_values(reg, reference, blind, camera=pair.camera), atol=1e-5)
    opened = np.nan_to_num(bounds.high_share) > TOUCH
    assert blind.sum() >= 80 and opened.any()
    assert opened.sum() <= 0.25 * blind.sum(), (opened.sum(), blind.sum())
    # the open pixels are where the motion carries the saturated pixel
    ys, xs = np.nonzero(opened)
    shift = pair.trajectory[ys, :2].mean(axis=0)  # tx, ty of those rows
    assert abs(ys.mean() - shift[1] - y) < 2.5 and abs(xs.mean() - shift[0] - x) < 2.5
    # everywhere else in the blind disk the model is a point: evidence as any fitted pixel
    rest = blind & ~opened & np.isfinite(bounds.model)
    np.testing.assert_allclose(bounds.model[rest], pair.distorted[rest], atol=0.06)


def test_zeros_that_are_fill():
    """A black collar (0 reaching the image edge, or a large square of 0) is
    fill, its thin tips too; scattered dark pixels inside are not."""
    rng = np.random.default_rng(0)
    image = rng.uniform(0.05, 0.9, (200, 200)).astype(np.float32)
    yy, xx = np.mgrid[:200, :200]
    collar = xx + yy < 60  # a corner triangle tapering to the edges
    image[collar] = 0.0
    image[100:140, 100:140] = 0.0  # a hole of no-data inside, untagged
    specks = (rng.random((200, 200)) < 0.01) & (yy > 20) & (xx > 70) & (yy < 180) & (xx < 180) & ~(
        (yy >= 90) & (yy < 150) & (xx >= 90) & (xx < 150))
    image[specks] = 0.0
    image[150:158, 30:38] = 0.0  # a dark 8 x 8 shadow: a bound, not fill
    padded = np.pad(image, 4, constant_values=np.nan)  # beyond the image
    fill = ops.fill_zeros(padded)[4:-4, 4:-4]
    assert fill[collar].all() and fill[100:140, 100:140].all()
    assert not fill[specks].any() and not fill[150:158, 30:38].any()
    # a window grown by the rule's margin decides its core as the whole image does
    m = 24 + 48
    assert (ops.fill_zeros(padded[:4 + 100 + m, :4 + 100 + m])[4:104, 4:104] == fill[:100, :100]).all()


@pytest.mark.parametrize("seed", range(4))
def test_zeros_that_are_fill_by_the_rule_on_the_whole_window(seed):
    """fill_zeros (0 regions visited one by one) against its rule written on
    the whole window at once: the seeds (zeros beside no-data or beyond the
    image, zeros in a FILL_SQUARE square of zeros) and every zero joined to
    them through zeros within FILL_REACH steps (8-connected)."""
    from scipy import ndimage

    from rsmb.ops._intensity import FILL_REACH, FILL_SQUARE

    rng = np.random.default_rng(seed)
    image = rng.uniform(0.05, 0.9, (180, 220)).astype(np.float32)
    image[ndimage.binary_dilation(rng.random(image.shape) < 0.004, iterations=int(rng.integers(1, 4)))] = 0.0
    image[rng.random(image.shape) < 0.02] = 0.0  # dark specks
    y, x = rng.integers(0, 150, 2)
    image[y:y + 30, x:x + 30] = 0.0  # a square of zeros, some of it maybe on the border
    image[rng.integers(0, 180, 3), :] = 0.0 if seed % 2 else image[0, 0]  # thin lines reaching the edge
    image[rng.random(image.shape) < 0.003] = np.nan  # no-data
    padded = np.pad(image, 2, constant_values=np.nan)
    zero = padded == 0
    seeds = zero & ndimage.binary_dilation(~np.isfinite(padded), structure=np.ones((3, 3), bool))
    # every FILL_SQUARE square of zeros, found square by square
    full = np.lib.stride_tricks.sliding_window_view(zero, (FILL_SQUARE, FILL_SQUARE)).all(axis=(2, 3))
    for y, x in zip(*np.nonzero(full)):
        seeds[y:y + FILL_SQUARE, x:x + FILL_SQUARE] = True
    want = seeds | ndimage.binary_dilation(seeds, structure=np.ones((3, 3), bool), iterations=FILL_REACH, mask=zero)
    got = ops.fill_zeros(padded)
    assert got.any() and (got != zero).any()  # some zeros are fill, some are not
    np.testing.assert_array_equal(got, want)
    assert not (got & ~zero).any()  # only zeros are fill


def test_a_black_square_leaves_its_neighbours_alone():
    """The pixels around a black square that is fill stay data: no rim of real
    pixels below or right of it becomes fill (an even square's opening
    anchored at one point shifts it by a pixel)."""
    image = np.full((80, 80), 0.5, np.float32)
    image[20:50, 20:50] = 0.0
    fill = ops.fill_zeros(image)
    assert fill[20:50, 20:50].all()
    assert not (fill & (image != 0)).any()


def test_pixels_beside_a_clipped_one_keep_their_fit_through_the_method():
    """A row solve leaves out every pixel whose search grid touches a clipped
    reference pixel; run_method gives back the model of those whose weighted
    poses (motion and blur) do not touch it and whose capture is not
    clipped, so the depth steps see them as fitted (no depth taken around
    the clipped pixels) and they carry evidence: no change on a pair
    without change."""
    pair = ops.synthesize_pair((128, 128), motion="translation", changes=0, noise=0.002, seed=4, exposure=6.0,
                               scale=0.3, scene=None)
    rng = np.random.default_rng(5)
    reference = np.minimum(pair.reference, 0.95).astype(np.float32)
    specks = [(int(y), int(x)) for y, x in rng.integers(24, 104, (6, 2))]
    for y, x in specks:
        reference[y, x] = 1.0  # saturated: clipped, left out of the row solves
    capture = np.minimum(pair.distorted, 0.95).astype(np.float32)  # the capture clips nothing
    scale = ops.IntensityScale(0.0, 0.8, (None, 1.0), (None, None))  # the common scale is the input's
    found = ops.run_method(reference, capture, camera=pair.camera, intensity=scale)
    reg = found.registration
    high = np.zeros(reference.shape, bool)
    high[tuple(np.array(specks).T)] = True
    holed = np.where(high, np.nan, reference)
    plain = ops.register(holed, capture, camera=pair.camera)  # what the row solves alone leave
    bounds = ops.model_bounds(reg, reference, high, np.zeros(reference.shape, bool), np.ones(capture.shape, bool),
                              camera=pair.camera)
    point = np.isfinite(bounds.model) & (bounds.high_share == 0)
    given = point & ~plain.valid
    assert given.sum() >= 200  # the search grid's disks are far wider than the motion's footprint
    assert reg.valid[point].all() and not reg.valid[~np.isfinite(bounds.model) | (bounds.high_share > 0)].any()
    np.testing.assert_allclose(found.registered[given], capture[given], atol=0.06)
    assert np.isfinite(found.score[given]).all()
    assert not found.parallax.any()
    assert not ops.method_changes(found, camera=pair.camera).mask.any()


def test_bounded_score_is_elementwise_so_gathered_pixels_score_as_in_the_window():
    """The method scores only the pixels that need the interval, gathered
    into one dimension: each gets the value it gets in the whole window,
    clipped captures, touched supports, NaN models and silent pixels alike."""
    rng = np.random.default_rng(8)
    shape = (30, 40)
    g = rng.uniform(-0.1, 1.1, shape).astype(np.float32)
    model = rng.uniform(0.0, 1.0, shape).astype(np.float32)
    model[rng.random(shape) < 0.1] = np.nan
    high = np.where(rng.random(shape) < 0.3, rng.random(shape), 0.0).astype(np.float32)
    low = np.where(rng.random(shape) < 0.3, rng.random(shape), 0.0).astype(np.float32)
    bounds = ops.ModelBounds(model, high, low)
    at_high, at_low = g >= 1.0, g <= 0.0
    whole = ops.bounded_score(g, bounds, at_high, at_low, lambda_chi=0.02)
    need = rng.random(shape) < 0.2
    part = ops.bounded_score(g[need], ops.ModelBounds(model[need], high[need], low[need]), at_high[need], at_low[need],
                             lambda_chi=0.02)
    np.testing.assert_array_equal(part, whole[need])
    assert part.dtype == np.float32 and np.isnan(part).any() and (part == 0).any() and (part != 0).any()


def test_the_depth_steps_histogram_is_the_fitted_windows_counted_again():
    """The histograms the depth steps' threshold comes from, updated from the
    window's before re-grounding: the newly fitted pixels added when no row
    was re-grounded, all counted again when one was; either way the counts
    of the window as it is (residuals, ``|chi|``, valid pixels)."""
    from types import SimpleNamespace

    from rsmb.ops._method import _updated_histogram, _window_histogram

    rng = np.random.default_rng(9)
    shape = (24, 50)
    capture = rng.random(shape).astype(np.float32)
    valid = rng.random(shape) < 0.7
    registered = np.where(valid, capture + rng.normal(0, 0.02, shape), np.nan).astype(np.float32)
    chi = np.where(valid, rng.normal(0, 0.05, shape) * (rng.random(shape) < 0.2), 0.0).astype(np.float32)
    before = SimpleNamespace(valid=valid, registered=registered, chi=chi, timings={"regrounded_rows": 0})
    window = _window_histogram(before, capture)
    point = ~valid & (rng.random(shape) < 0.5)
    fitted = SimpleNamespace(valid=valid | point,
                             registered=np.where(point, capture - 0.03, registered).astype(np.float32),
                             chi=np.where(point, 0.02, chi).astype(np.float32), timings={"regrounded_rows": 0})
    expected = _window_histogram(fitted, capture)
    got = _updated_histogram(window, fitted, capture, point)
    np.testing.assert_array_equal(got.residual, expected.residual)
    np.testing.assert_array_equal(got.score, expected.score)
    assert got.residual.sum() == (valid | point).sum() > window.residual.sum()
    assert _updated_histogram(window, before, capture, None) is window
    moved = SimpleNamespace(valid=fitted.valid, registered=fitted.registered.copy(), chi=fitted.chi,
                            timings={"regrounded_rows": 1})
    moved.registered[3] += np.float32(0.3)  # a re-grounded row
    again = _updated_histogram(window, moved, capture, point)
    np.testing.assert_array_equal(again.residual, _window_histogram(moved, capture).residual)
    assert not np.array_equal(again.residual, expected.residual)
