"""Tests of ops.changes._changes: thresholds from histograms, change masks, and masks carried
back to the reference grid, answers known by construction."""

import numpy as np
import pytest

from rsmb import ops
from rsmb.ops import (
    Camera,
    ChangeParams,
    ParameterError,
    RSMBError,
    change_candidates,
    change_mask,
    change_score,
    change_threshold,
    changes_to_reference,
    confusion,
    optimal_chi,
    score_histogram,
)
from rsmb.ops.changes._changes import _RESIDUAL_EDGES, _SCORE_EDGES

SHAPE = (48, 64)
BIN_RATIO = float(_RESIDUAL_EDGES[-1] / _RESIDUAL_EDGES[-2])  # log bins: ~1.5 % wide


@pytest.fixture
def blobs():
    """A mask with a few separated rectangles and a disc."""
    mask = np.zeros(SHAPE, bool)
    mask[5:12, 8:20] = True
    mask[30:40, 40:46] = True
    yy, xx = np.mgrid[:SHAPE[0], :SHAPE[1]]
    mask |= (yy - 20) ** 2 + (xx - 50) ** 2 <= 16
    return mask


# ---------------------------------------------------------------- changes_to_reference


def test_identity_trajectory_returns_the_same_mask(blobs):
    camera = Camera.for_shape(SHAPE)
    out = changes_to_reference(blobs, np.zeros((SHAPE[0], 3)), axes=("tx", "ty", "rz"), camera=camera,
                               reference_shape=SHAPE)
    assert out.dtype == np.uint8 and out.shape == SHAPE
    np.testing.assert_array_equal(out.astype(bool), blobs)


@pytest.mark.parametrize("tx, ty", [(3, 0), (-4, 2), (5, -3)])
def test_constant_translation_shifts_the_mask_back(blobs, tx, ty):
    """Reference pixel p lands at p + t in the capture: out[v, u] = mask[v + ty, u + tx]."""
    camera = Camera.for_shape(SHAPE)
    trajectory = np.broadcast_to([float(tx), float(ty)], (SHAPE[0], 2))
    out = changes_to_reference(blobs, trajectory, axes=("tx", "ty"), camera=camera, reference_shape=SHAPE)
    expected = np.zeros(SHAPE, bool)
    src = blobs[max(ty, 0):SHAPE[0] + min(ty, 0), max(tx, 0):SHAPE[1] + min(tx, 0)]
    expected[max(-ty, 0):max(-ty, 0) + src.shape[0], max(-tx, 0):max(-tx, 0) + src.shape[1]] = src
    np.testing.assert_array_equal(out.astype(bool), expected)


def test_to_ground_carries_mask_score_and_parallax_and_marks_what_was_not_seen(blobs):
    """A constant translation (tx, ty) = (5, -3): ground pixel (v, u) is seen
    at capture pixel (v - 3, u + 5).  The three arrays follow it; no evidence
    (a NaN score) stays 255 / NaN, and ground pixels seen outside the capture
    have no evidence."""
    tx, ty = 5, -3
    rng = np.random.default_rng(4)
    score = rng.random(SHAPE).astype(np.float32)
    score[20:26, 0:30] = np.nan
    sensor = ops.evidence_mask(blobs, score)
    assert set(np.unique(sensor)) == {0, 1, 255} and (sensor[blobs] == 1).all()
    parallax = np.where(np.isfinite(score), (rng.random(SHAPE) < 0.1), 255).astype(np.uint8)
    trajectory = np.broadcast_to([float(tx), float(ty)], (SHAPE[0], 2))
    ground = ops.to_ground(sensor, score, parallax, trajectory, axes=("tx", "ty"), camera=Camera.for_shape(SHAPE),
                           reference_shape=SHAPE)
    v, u = np.mgrid[:SHAPE[0], :SHAPE[1]]
    r, c = v + ty, u + tx
    seen = (r >= 0) & (r < SHAPE[0]) & (c >= 0) & (c < SHAPE[1])
    rr, cc = np.clip(r, 0, SHAPE[0] - 1), np.clip(c, 0, SHAPE[1] - 1)
    np.testing.assert_array_equal(ground.mask, np.where(seen, sensor[rr, cc], 255))
    np.testing.assert_array_equal(ground.parallax, np.where(seen, parallax[rr, cc], 255))
    np.testing.assert_array_equal(ground.score, np.where(seen, score[rr, cc], np.nan))
    assert ground.mask.dtype == np.uint8 and ground.score.dtype == np.float32
    assert np.array_equal(ground.mask == 255, np.isnan(ground.score))


def test_sample_at_is_the_fancy_index_with_fill_outside():
    """Any lookup, on a window wider than tall and not contiguous: each
    ground pixel takes ``values[rows, cols]``, ``fill`` where rows is -1."""
    rng = np.random.default_rng(11)
    values = rng.random((40, 70)).astype(np.float32)[:, ::2]  # (40, 35), a strided view
    rows = rng.integers(-1, 40, (23, 31)).astype(np.int32)
    cols = np.where(rows >= 0, rng.integers(0, 35, rows.shape), -1).astype(np.int32)
    out = ops.sample_at(values, rows, cols, fill=np.float32(np.nan))
    expected = np.where(rows >= 0, values[np.maximum(rows, 0), np.maximum(cols, 0)], np.nan)
    np.testing.assert_array_equal(out, expected)
    assert out.dtype == np.float32 and out.shape == rows.shape


def test_rolling_shutter_trajectory_shifts_each_row_by_its_own_pose(blobs):
    """tx growing by 0.37 px per row: reference row v is carried by row v's pose."""
    camera = Camera.for_shape(SHAPE)
    slope = 0.37  # never a half pixel on rows 0..47, so rounding is unambiguous
    trajectory = np.zeros((SHAPE[0], 2))
    trajectory[:, 0] = slope * np.arange(SHAPE[0])
    out = changes_to_reference(blobs, trajectory, axes=("tx", "ty"), camera=camera, reference_shape=SHAPE)
    expected = np.zeros(SHAPE, bool)
    for v in range(SHAPE[0]):
        cols = np.arange(SHAPE[1]) + int(np.rint(slope * v))
        ok = cols < SHAPE[1]
        expected[v, ok] = blobs[v, cols[ok]]
    np.testing.assert_array_equal(out.astype(bool), expected)


def test_rolling_shutter_vertical_motion_finds_the_landing_row():
    """ty = 0.1 px per row: reference row v lands where r = v + 0.1 r, i.e. r = v / 0.9
    (a fixed point: the pose depends on the row the point lands in)."""
    camera = Camera.for_shape(SHAPE)
    trajectory = np.zeros((SHAPE[0], 2))
    trajectory[:, 1] = 0.1 * np.arange(SHAPE[0])
    rows = np.zeros(SHAPE, bool)
    rows[::3] = True  # every third distorted row changed: the landing row is visible
    out = changes_to_reference(rows, trajectory, axes=("tx", "ty"), camera=camera, reference_shape=SHAPE)
    checked = 0
    for v in range(SHAPE[0]):
        r = v / 0.9
        if r > SHAPE[0] - 1 or 0.4 < r % 1 < 0.6:
            continue  # leaves the capture, or too close to a rounding tie
        np.testing.assert_array_equal(out[v].astype(bool), rows[int(np.rint(r))])
        checked += 1
    assert checked > 30


def test_windows_in_a_larger_image(blobs):
    """A distorted window and a reference window at their origins in the whole image
    give the whole-image answer cut to the reference window."""
    whole_shape = (80, 100)
    camera = Camera.for_shape(whole_shape)
    d_origin, r_origin = (10, 20), (5, 12)
    mask_whole = np.zeros(whole_shape, bool)
    mask_whole[d_origin[0]:d_origin[0] + SHAPE[0], d_origin[1]:d_origin[1] + SHAPE[1]] = blobs
    traj_whole = np.zeros((whole_shape[0], 3))
    traj_whole[:, 0], traj_whole[:, 1], traj_whole[:, 2] = 2.0, -1.0, 0.8
    whole = changes_to_reference(mask_whole, traj_whole, axes=("tx", "ty", "rz"), camera=camera,
                                 reference_shape=whole_shape)
    ref_shape = (50, 70)
    window = changes_to_reference(blobs, traj_whole[d_origin[0]:d_origin[0] + SHAPE[0]], axes=("tx", "ty", "rz"),
                                  camera=camera, reference_shape=ref_shape, reference_origin_yx=r_origin,
                                  distorted_origin_yx=d_origin)
    np.testing.assert_array_equal(window, whole[r_origin[0]:r_origin[0] + ref_shape[0],
                                                r_origin[1]:r_origin[1] + ref_shape[1]])
    assert window.any()


def test_fixed_point_stops_early_with_the_same_answer():
    """The lookup stops once the row it lands in repeats (every later iteration
    would repeat the last one): the same mask as always iterating."""
    from rsmb.ops import pose_homographies

    rng = np.random.default_rng(3)
    mask = rng.random((90, 120)) > 0.7
    camera = Camera.for_shape(mask.shape)
    rows = np.arange(mask.shape[0])
    trajectory = np.stack([4 * np.sin(rows / 9.0), 3 * np.cos(rows / 13.0), 1.5 * np.sin(rows / 30.0)], -1)
    iterations = 4
    out = changes_to_reference(mask, trajectory, axes=("tx", "ty", "rz"), camera=camera, reference_shape=(80, 110),
                               reference_origin_yx=(4, 6), iterations=iterations)
    # every pixel iterated ``iterations`` times, in numpy
    hom = pose_homographies(trajectory, camera, axes=("tx", "ty", "rz"))
    yg, xg = np.mgrid[4:84, 6:116].astype(np.float64)
    row = yg.copy()
    for _ in range(iterations):
        h = hom[np.clip(np.round(row).astype(int), 0, mask.shape[0] - 1)]
        den = h[..., 2, 0] * xg + h[..., 2, 1] * yg + h[..., 2, 2]
        xs = (h[..., 0, 0] * xg + h[..., 0, 1] * yg + h[..., 0, 2]) / den
        row = (h[..., 1, 0] * xg + h[..., 1, 1] * yg + h[..., 1, 2]) / den
    ri, ci = np.round(row).astype(int), np.round(xs).astype(int)
    inside = (ri >= 0) & (ri < mask.shape[0]) & (ci >= 0) & (ci < mask.shape[1])
    expected = np.where(inside, mask[np.clip(ri, 0, 89), np.clip(ci, 0, 119)], False)
    np.testing.assert_array_equal(out.astype(bool), expected)
    assert 0.2 < expected.mean() < 0.4


# ---------------------------------------------------------------- change_threshold


def _residual_case(seed, sigma):
    rng = np.random.default_rng(seed)
    residual = rng.normal(0.0, sigma, SHAPE)
    score = np.maximum(np.abs(residual) - 0.01, 0.0)
    valid = np.ones(SHAPE, bool)
    valid[:, :4] = False
    return residual, score, valid


@pytest.mark.parametrize("seed, sigma, k", [(0, 0.01, 6.0), (1, 0.03, 4.0), (2, 0.002, 10.0)])
def test_noise_threshold_is_k_robust_sigmas(seed, sigma, k):
    residual, score, valid = _residual_case(seed, sigma)
    hist = score_histogram(residual, score, valid)
    t = change_threshold(hist, params=ChangeParams(k=k, floor=0.0))
    median = float(np.median(np.abs(residual[valid])))
    # the histogram gives the upper edge of the median's bin
    ratio = t / (k * 1.4826 * median)
    assert 1.0 <= ratio <= BIN_RATIO * (1 + 1e-9)
    assert BIN_RATIO < 1.016


def test_noise_threshold_of_summed_tiles_is_that_of_the_whole():
    residual, score, valid = _residual_case(3, 0.02)
    whole = score_histogram(residual, score, valid)
    parts = [score_histogram(residual[:, s], score[:, s], valid[:, s]) for s in (slice(0, 25), slice(25, None))]
    total = parts[0] + parts[1]
    np.testing.assert_array_equal(total.residual, whole.residual)
    np.testing.assert_array_equal(total.score, whole.score)
    assert change_threshold(total) == change_threshold(whole)


@pytest.mark.parametrize("dtype, strided", [(np.float32, False), (np.float64, False), (np.float32, True),
                                             (np.float64, True), (np.int16, False)])
def test_histograms_are_numpys_at_every_edge_and_clip_level(dtype, strided):
    """The bins found from the edges' spacing (the residual's bits, as its
    float type lays them out) are np.histogram's, for values exactly on every
    edge, beyond the last one (clipped to it), NaN and off the valid pixels
    (not counted), over ten decades of residual; a strided residual, and an
    integer one, counted as float64."""
    rng = np.random.default_rng(11)
    residual = (rng.standard_normal((64, 128)) * 10.0 ** rng.uniform(-8, 1, (64, 128))).astype(np.float64)
    score = np.abs(rng.standard_normal((64, 64)) * 2.5).astype(np.float32)
    residual.flat[:2 * len(_RESIDUAL_EDGES):2] = _RESIDUAL_EDGES  # on the even columns, which the strided case keeps
    score.flat[:len(_SCORE_EDGES)] = _SCORE_EDGES
    residual.flat[::97], score.flat[::89] = np.nan, np.nan
    if np.issubdtype(dtype, np.integer):
        residual = np.nan_to_num(residual * 1000.0).clip(-30000, 30000)
    residual = residual.astype(dtype)[:, ::2]  # every other column: a view with strides
    if not strided:
        residual = np.ascontiguousarray(residual)
    valid = rng.random((64, 64)) < 0.9
    hist = score_histogram(residual, score, valid)
    r = np.abs(residual[valid].astype(np.float64))
    s = score[valid].astype(np.float64)
    np.testing.assert_array_equal(hist.residual, np.histogram(np.minimum(r[np.isfinite(r)], 4.0), _RESIDUAL_EDGES)[0])
    np.testing.assert_array_equal(hist.score, np.histogram(np.minimum(s[s > 0], 2.0), _SCORE_EDGES)[0])


def test_noise_threshold_never_below_floor():
    residual, score, valid = _residual_case(4, 0.001)
    hist = score_histogram(residual, score, valid)
    assert change_threshold(hist, params=ChangeParams(floor=0.05)) == 0.05
    empty = score_histogram(residual, score, np.zeros(SHAPE, bool))
    assert change_threshold(empty, params=ChangeParams(floor=0.07)) == 0.07


@pytest.mark.parametrize("threshold", [0.2, 3, "0.15"])
def test_numeric_threshold_returned(threshold):
    residual, score, valid = _residual_case(5, 0.02)
    hist = score_histogram(residual, score, valid)
    assert change_threshold(hist, params=ChangeParams(threshold=threshold)) == pytest.approx(float(threshold))


def test_kapur_threshold_separates_two_populations():
    rng = np.random.default_rng(6)
    score = np.where(rng.random(SHAPE) < 0.2, rng.uniform(0.5, 0.6, SHAPE), rng.uniform(0.01, 0.1, SHAPE))
    hist = score_histogram(score, score, np.ones(SHAPE, bool))
    t = change_threshold(hist, params=ChangeParams(threshold="kapur", floor=0.0))
    assert 0.1 <= t <= 0.5
    assert change_threshold(hist, params=ChangeParams(threshold="kapur", floor=0.8)) == 0.8


# ---------------------------------------------------------------- change_mask


def test_change_mask_keeps_a_blob_and_drops_small_components():
    score = np.zeros(SHAPE, np.float32)
    score[10:20, 10:22] = 0.5          # 120 px, kept
    score[30:33, 40:43] = 0.5          # 9 px, below min_area
    score[40, 5] = 0.9                 # one hot pixel
    mask = change_mask(score, 0.2, params=ChangeParams(min_area=20))
    expected = np.zeros(SHAPE, bool)
    expected[10:20, 10:22] = True
    np.testing.assert_array_equal(mask, expected)
    # with a small enough min_area the small one stays
    small = change_mask(score, 0.2, params=ChangeParams(min_area=5))
    assert small[30:33, 40:43].all() and small.sum() == 129


def test_change_mask_hysteresis_drops_large_weak_component():
    """A large component whose peak stays below the threshold is not a change, even
    though every pixel is above hysteresis * threshold."""
    score = np.zeros(SHAPE, np.float32)
    score[5:25, 5:25] = 0.15          # 400 px, peak 0.15 < 0.2
    score[30:40, 40:55] = 0.3         # 150 px, above
    params = ChangeParams(min_area=20, hysteresis=0.5)
    mask = change_mask(score, 0.2, params=params)
    assert not mask[5:25, 5:25].any()
    assert mask[30:40, 40:55].all() and mask.sum() == 150


def test_change_mask_hysteresis_keeps_weak_border_of_a_strong_blob():
    score = np.zeros(SHAPE, np.float32)
    score[10:30, 10:30] = 0.15        # weak halo (blurred border)
    score[15:25, 15:25] = 0.3         # strong core
    mask = change_mask(score, 0.2, params=ChangeParams(min_area=20, hysteresis=0.5, half_max_window=1))
    np.testing.assert_array_equal(mask, score > 0)
    # hysteresis disabled: only the core
    core = change_mask(score, 0.2, params=ChangeParams(min_area=20, hysteresis=1.0, half_max_window=1))
    np.testing.assert_array_equal(core, score > 0.2)


def test_the_rim_of_what_the_depth_explained_is_not_a_change_of_its_own():
    """A structure the depth explains (score 0 as parallax, 0.6 at the ground's
    depth) leaves a blurred rim that scores 0.22, under half of 0.6: measured
    against what was explained, the rim is not a change; a new object of the
    same score far from it still is, and so is one whose own score reaches
    half of the explained residual beside it."""
    score = np.zeros(SHAPE, np.float32)
    explained = np.zeros(SHAPE, np.float32)
    explained[10:20, 10:20] = 0.6     # parallax: its score is 0
    score[8:22, 20:24] = 0.22         # its rim, beside it
    score[40:50, 40:50] = 0.22        # a new object far away
    score[8:22, 6:10] = 0.3           # a new object against the structure, half its residual
    params = ChangeParams(min_area=20, hysteresis=0.5)
    alone = change_mask(score, 0.2, params=params)
    assert alone[8:22, 20:24].all()  # without the explained residual, the rim is a change
    mask = change_mask(score, 0.2, params=params, explained=explained)
    assert not mask[8:22, 20:24].any()
    assert mask[40:50, 40:50].all() and mask[8:22, 6:10].all()
    np.testing.assert_array_equal(change_candidates(score, 0.2, params=params, explained=np.zeros(SHAPE)),
                                  change_candidates(score, 0.2, params=params))


def test_a_faint_object_beside_what_the_depth_explained_loses_its_near_side():
    """The rule's price, as documented: an object of 0.22 (under half of the
    0.6 the depth explained beside it) keeps only its pixels more than half
    the window (7 px) from the structure."""
    score = np.zeros(SHAPE, np.float32)
    explained = np.zeros(SHAPE, np.float32)
    explained[10:30, 10:20] = 0.6
    score[10:30, 20:40] = 0.22        # against the structure, 20 px wide
    mask = change_mask(score, 0.2, params=ChangeParams(min_area=20, hysteresis=0.5), explained=explained)
    assert not mask[10:30, 20:27].any() and mask[10:30, 27:40].all()


def test_change_mask_fills_small_holes():
    score = np.zeros(SHAPE, np.float32)
    score[10:30, 10:30] = 0.5
    score[18:20, 18:20] = 0.0  # a 4 px hole
    mask = change_mask(score, 0.2, params=ChangeParams(min_area=20))
    assert mask[10:30, 10:30].all() and mask.sum() == 400


def test_fill_holes_fills_only_small_enclosed_background():
    from rsmb.ops import fill_holes

    mask = np.zeros((40, 60), bool)
    mask[5:25, 5:25] = True
    mask[8:11, 8:11] = False  # 9 px hole: filled
    mask[12:22, 12:22] = False  # 100 px hole: kept
    mask[15:17, 15:17] = True  # an island inside it: the hole is its 96 background px
    mask[0:10, 40:50] = True
    mask[0:3, 44:46] = False  # 6 px notch open to the border: not a hole
    mask[30:36, 30:36] = True
    mask[32, 30:36] = False  # a gap that cuts the square in two: not enclosed
    out = fill_holes(mask, params=ChangeParams(min_area=20))
    expected = mask.copy()
    expected[8:11, 8:11] = True
    np.testing.assert_array_equal(out, expected)
    out = fill_holes(mask, params=ChangeParams(min_area=97))
    expected[12:22, 12:22] = True  # 96 background px < 97
    np.testing.assert_array_equal(out, expected)


def test_change_mask_nan_score_is_no_change():
    score = np.full(SHAPE, np.nan, np.float32)
    score[10:20, 10:20] = 0.5
    mask = change_mask(score, 0.2)
    assert mask.sum() == 100


# ---------------------------------------------------------------- ChangeParams


@pytest.mark.parametrize("kwargs, name", [
    (dict(threshold="otsu"), "threshold"),
    (dict(threshold=True), "threshold"),
    (dict(threshold=None), "threshold"),
    (dict(threshold=0.0), "threshold"),
    (dict(threshold=-0.1), "threshold"),
    (dict(threshold="-1"), "threshold"),
    (dict(hysteresis=0.0), "hysteresis"),
    (dict(hysteresis=1.5), "hysteresis"),
    (dict(min_area=-1), "min_area"),
])
def test_change_params_validation(kwargs, name):
    with pytest.raises(ParameterError, match=name) as info:
        ChangeParams(**kwargs)
    assert isinstance(info.value, ValueError) and isinstance(info.value, RSMBError)


def test_change_params_normalises_numbers():
    assert ChangeParams(threshold="0.25").threshold == 0.25
    assert ChangeParams(threshold=1).threshold == 1.0
    assert isinstance(ChangeParams(threshold=1).threshold, float)
    assert ChangeParams().threshold == "noise"
    assert ChangeParams(threshold="kapur").threshold == "kapur"


@pytest.mark.parametrize("threshold", [np.float32(0.2), np.int64(1)])
def test_change_params_accepts_numpy_scalars(threshold):
    assert ChangeParams(threshold=threshold).threshold == pytest.approx(float(threshold))



def _sharp_scene(seed=7):
    """Bright and dark rectangles on grey with an optical blur of 0.7 px (the
    edges of a real photograph), a flat field in the middle."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    scene = np.full((160, 160), 0.4, np.float32)
    for _ in range(40):
        r, c = rng.integers(0, 150, 2)
        h, w = rng.integers(4, 30, 2)
        scene[r:r + h, c:c + w] = rng.choice([0.1, 0.9])
    scene[60:100, 60:100] = 0.4
    return ndimage.gaussian_filter(scene, 0.7)


def _rendered(scene, shift, order, with_object):
    """``scene`` moved by ``shift`` px on both axes, interpolated with a spline
    of ``order`` (1: the solver's linear interpolation; 3: a capture's own
    optics), with or without a new object of contrast 0.3 on the flat field."""
    from scipy import ndimage

    out = ndimage.shift(scene, (shift, shift), order=order, mode="nearest").astype(np.float32)
    truth = np.zeros(scene.shape, bool)
    if with_object:
        truth[72:88, 70:90] = True
        out[truth] += 0.3
    return out, truth


def test_change_score_takes_the_interpolation_allowance_off_chi():
    scene = _sharp_scene()
    registered, _ = _rendered(scene, 0.5, 1, False)  # the right pose, rendered the solver's way
    capture, truth = _rendered(scene, 0.5, 3, True)
    chi = optimal_chi(capture - registered, lambda_chi=0.02)
    plain = change_score(chi, registered, params=ChangeParams(interpolation=0.0))
    np.testing.assert_allclose(plain, np.abs(chi), rtol=1e-6)
    score = change_score(chi, registered)
    assert score.dtype == np.float32 and (score >= 0).all() and (score <= plain + 1e-7).all()
    inner = np.zeros_like(truth)
    inner[74:86, 72:88] = True  # flat around: the new object keeps its score
    np.testing.assert_allclose(score[inner], plain[inner], rtol=1e-6)
    assert plain[~truth].max() > 0.05  # linear against cubic interpolation alone exceeds the threshold's floor
    assert score[~truth].max() < 0.05
    counts = confusion(change_mask(score, 0.05), truth)
    assert confusion(change_mask(plain, 0.05), truth).precision < 0.8
    assert counts.precision >= 0.95 and counts.recall >= 0.95, counts.as_dict()


def test_interpolation_allowance_does_not_hide_a_misregistration():
    scene = _sharp_scene()
    registered, _ = _rendered(scene, 0.0, 1, False)
    capture, truth = _rendered(scene, 0.5, 3, False)  # half a pixel off on both axes
    chi = optimal_chi(capture - registered, lambda_chi=0.02)
    assert change_score(chi, registered).max() > 0.1


def test_a_hole_in_the_model_is_a_border_not_a_dark_pixel():
    """The allowance next to unknown model pixels (a failed row, a hole) is
    the allowance at an image border (the pixel replicated), not a second
    difference against 0, which would hide a change beside every hole."""
    scene = _sharp_scene()
    registered, _ = _rendered(scene, 0.5, 1, False)
    capture, truth = _rendered(scene, 0.5, 3, True)
    chi = optimal_chi(capture - registered, lambda_chi=0.02)
    holed = registered.copy()
    holed[80] = np.nan  # a failed row through the new object
    holed[:, 30:34] = np.nan  # and a hole of columns
    score = change_score(chi, holed)
    # each side of a hole is scored as that side alone would be, its rows (columns) next to the hole a border
    np.testing.assert_allclose(score[81:, 34:], change_score(chi[81:, 34:], registered[81:, 34:]), atol=1e-6)
    np.testing.assert_allclose(score[:80, :30], change_score(chi[:80, :30], registered[:80, :30]), atol=1e-6)
    # the new object keeps its score on the rows beside the failed one (on a flat surround, the full |chi|)
    np.testing.assert_allclose(score[[79, 81], 74:86], np.abs(chi[[79, 81], 74:86]), rtol=1e-6)


def _second_differences(image):
    """The interpolation allowance's rule written with whole arrays:
    ``|f_xx| + |f_yy|`` of ``image`` (3-pixel second differences), a
    neighbour beyond the image or unknown (NaN: a hole in the model, a
    failed row) replaced by the pixel itself, as the image's borders are
    replicated; 0 where the pixel itself is unknown.  (Taking unknown as 0
    would give the pixels around every hole an allowance of their own value
    and hide their changes.)"""
    known = np.isfinite(image)
    centre = np.where(known, image, np.float32(0.0))
    total = np.zeros(image.shape, np.float32)
    for axis in (0, 1):
        padded = np.pad(image, [(1, 1) if a == axis else (0, 0) for a in (0, 1)], mode="edge")
        before = padded[:-2] if axis == 0 else padded[:, :-2]
        after = padded[2:] if axis == 0 else padded[:, 2:]
        before = np.where(np.isfinite(before), before, centre)
        after = np.where(np.isfinite(after), after, centre)
        total += np.abs(before - 2 * centre + after)
    return np.where(known, total, np.float32(0.0))


@pytest.mark.parametrize("seed", range(8))
def test_change_score_is_its_numpy_rule_bit_for_bit(seed):
    """The one-pass kernel against the rule written with whole arrays:
    ``max(|chi| - interpolation * (|f_xx| + |f_yy|), 0)`` in float32, a
    neighbour beyond the window or unknown (NaN, inf) replaced by the pixel,
    0 allowance on an unknown pixel, NaN chi kept; every byte equal, windows
    of one row or column included."""
    rng = np.random.default_rng(seed)
    h, w = [(1, 17), (23, 1), (31, 40), (64, 64)][seed % 4]
    registered = (rng.uniform(-2, 2, (h, w)) * 10.0 ** rng.uniform(-3, 3)).astype(np.float32)
    registered[rng.random((h, w)) < (0.0, 0.05, 0.3)[seed % 3]] = np.nan
    registered[rng.random((h, w)) < 0.02] = np.inf
    chi = rng.normal(0, rng.uniform(0.001, 1), (h, w)).astype(np.float32)
    chi[rng.random((h, w)) < 0.05] = np.nan
    chi[rng.random((h, w)) < 0.05] = -0.0
    params = ChangeParams(interpolation=(0.25, 0.5, 1.0, 1e-3)[seed % 4])
    want = np.maximum(np.abs(chi) - np.float32(params.interpolation) * _second_differences(registered),
                      np.float32(0.0))
    got = change_score(chi, registered, params=params)
    assert got.dtype == np.float32 and got.shape == (h, w) and got.tobytes() == want.tobytes()


def test_change_score_of_unlike_shapes_is_refused():
    with pytest.raises(ParameterError, match="one \\(H, W\\) shape"):
        change_score(np.zeros((4, 5), np.float32), np.zeros((5, 4), np.float32))


def test_model_values_are_the_registered_image_anywhere():
    """The model at pixels the registration did not fit (e.g. clipped ones)
    is what the registered image holds where it did."""
    pair = ops.synthesize_pair((256, 256), motion="inplane", changes=4, noise=0.002, seed=3, interpolation="cubic")
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera)
    model = ops.model_values(reg, pair.reference, np.ones(pair.distorted.shape, bool), camera=pair.camera)
    fitted = reg.valid & np.isfinite(reg.registered)
    assert np.isfinite(model[fitted]).mean() > 0.999
    both = fitted & np.isfinite(model)
    np.testing.assert_allclose(model[both], reg.registered[both], atol=1e-5)


# ------------------------------------------- scikit-image against the scipy versions it replaced


def _old_label_components(mask, score):
    """label_components as it was before scikit-image (scipy.ndimage)."""
    from scipy import ndimage

    labels, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    labels = labels.astype(np.int32)
    area = np.bincount(labels.ravel(), minlength=n + 1).astype(np.int64)
    peak = np.zeros(n + 1, dtype=np.float32)
    if n:
        np.maximum.at(peak, labels.ravel(), np.nan_to_num(np.asarray(score, np.float32)).ravel())
    peak[0] = 0.0
    return labels, area, peak


def _old_fill_holes(mask, min_area):
    """fill_holes as it was: object by object, scipy.ndimage.binary_fill_holes."""
    from scipy import ndimage

    out = mask.copy()
    if min_area <= 1 or not mask.any():
        return out
    labels, _ = ndimage.label(mask, structure=np.ones((3, 3), bool))
    for i, box in enumerate(ndimage.find_objects(labels), 1):
        box = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
        holes = ndimage.binary_fill_holes(labels[box] == i) & ~mask[box]
        if holes.any():
            pieces, _ = ndimage.label(holes)
            small = np.bincount(pieces.ravel()) < min_area
            small[0] = False
            out[box] |= small[pieces]
    return out


def _random_masks():
    """Masks with many components, nested rings and holes of every size,
    touching the borders: smoothed noise at a few levels, seeded."""
    from scipy import ndimage

    for seed in range(4):
        rng = np.random.default_rng(seed)
        field = ndimage.gaussian_filter(rng.standard_normal((157, 203)), 1.5 + seed)
        for level in (-0.05, 0.0, 0.08):
            yield field > level * field.std() * 10, np.abs(field).astype(np.float32)


def test_label_components_and_fill_holes_equal_the_scipy_versions():
    from rsmb.ops import fill_holes, label_components

    count = 0
    for mask, score in _random_masks():
        new, old = label_components(mask, score), _old_label_components(mask, score)
        for a, b in zip(new, old):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
        count += len(new[1]) - 1
        for min_area in (1, 5, 20, 97):
            np.testing.assert_array_equal(fill_holes(mask, params=ChangeParams(min_area=min_area)),
                                          _old_fill_holes(mask, min_area))
    assert count > 100  # the masks had components to compare


def test_large_components_keeps_by_area_connectivity_and_border():
    from rsmb.ops import large_components

    mask = np.zeros((12, 12), bool)
    mask[0:2, 0:2] = True          # 4 px touching the border
    mask[5:7, 5:7] = True          # 4 px inside
    mask[7, 7] = True              # joins the inside square diagonally only
    mask[9:12, 9:12] = True        # 9 px in the corner
    np.testing.assert_array_equal(large_components(mask, 5), mask & ~_box(mask.shape, 0, 2))
    np.testing.assert_array_equal(large_components(mask, 5, connectivity=1), _box(mask.shape, 9, 12))
    np.testing.assert_array_equal(large_components(mask, 5, connectivity=1, border=True),
                                  _box(mask.shape, 9, 12) | _box(mask.shape, 0, 2))
    assert not large_components(np.zeros((4, 4), bool), 1).any()


def _box(shape, lo, hi):
    out = np.zeros(shape, bool)
    out[lo:hi, lo:hi] = True
    return out
