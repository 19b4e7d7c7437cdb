"""Tests of ops._forward: the RSMB forward model against independent renderings.

The independent reference samples the source with exact bilinear interpolation
(``scipy.ndimage.map_coordinates``, order 1) at ``H^-1 x`` for every exposure
sample of every row, with ``H`` from :func:`ops.pose_homographies`.
"""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from rsmb.ops import Camera, CameraPath, ParameterError, pose_homographies, render

SHAPE = (72, 96)


def _smooth(shape, seed=0):
    """A smooth float32 image (slopes below 0.01 per pixel)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    img = 0.5 + 0.1 * x / shape[1] - 0.05 * y / shape[0]
    for _ in range(3):
        kx, ky = rng.uniform(-2 * np.pi / 400, 2 * np.pi / 400, 2)
        img += 0.06 * np.sin(kx * x + ky * y + rng.uniform(0, 2 * np.pi))
    return img.astype(np.float32)


def _textured(shape, seed=1):
    """A band-limited random texture (strong gradients: blur and shifts show)."""
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.uniform(0, 1, shape), 1.5)
    img = (img - img.min()) / (img.max() - img.min())
    return img.astype(np.float32)


def _reference_render(source, pose_rows, camera, width, origin_yx=(0, 0)):
    """Row i = mean over samples s of source(H(pose_rows[i, s])^-1 x), exact bilinear.

    Returns (image, valid) with valid False where any sample left the source.
    """
    h_rows = pose_rows.shape[0]
    out = np.zeros((h_rows, width))
    valid = np.ones((h_rows, width), bool)
    hs, ws = source.shape
    x = np.arange(width, dtype=np.float64)
    for i in range(h_rows):
        acc = np.zeros(width)
        for pose in pose_rows[i]:
            # H is in the frame's coordinates; the source is offset by origin
            hinv = pose_homographies(pose, camera, inverse=True)
            p = hinv @ np.stack([x, np.full(width, float(i)), np.ones(width)])
            u = p[0] / p[2] + origin_yx[1]
            v = p[1] / p[2] + origin_yx[0]
            acc += ndimage.map_coordinates(source.astype(np.float64), [v, u], order=1, mode="constant")
            valid[i] &= (u >= 0) & (v >= 0) & (u <= ws - 1) & (v <= hs - 1)
        out[i] = acc / pose_rows.shape[1]
    return out, valid


def _linear_path(start, end, t_end):
    return CameraPath(np.array([0.0, t_end]), np.array([start, end], dtype=np.float64))


def _constant_path(pose):
    return CameraPath(np.array([0.0, 1.0]), np.array([pose, pose], dtype=np.float64))


# ---------------------------------------------------------------- constant path = one warp


@pytest.mark.parametrize("pose", [
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [2.5, -1.25, 0.0, 0.0, 0.0, 0.0],
    [1.3, 0.7, 0.02, 0.3, -0.4, 2.0],
])
def test_constant_path_equals_cv2_warp_perspective(pose):
    src = _smooth(SHAPE)
    camera = Camera.for_shape(SHAPE)
    result = render(src, _constant_path(pose), shape=SHAPE)
    h = pose_homographies(pose, camera)
    expected = cv2.warpPerspective(src, h, (SHAPE[1], SHAPE[0]), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    inside = ndimage.binary_erosion(result.valid, iterations=1) & np.isfinite(expected)
    assert inside.mean() > 0.8
    # OpenCV quantises sub-pixel positions to 1/32 px: ~1e-4 on a smooth image
    np.testing.assert_allclose(result.image[inside], expected[inside], atol=1e-4)
    assert result.image.dtype == np.float32 and result.image.shape == SHAPE
    np.testing.assert_allclose(result.centroid, np.broadcast_to(pose, (SHAPE[0], 6)), atol=1e-12)


@pytest.mark.parametrize("pose", [[1.3, 0.7, 0.02, 0.3, -0.4, 2.0], [-3.2, 2.6, -0.03, -0.5, 0.2, -1.5]])
def test_constant_path_equals_exact_bilinear_warp(pose):
    src = _textured(SHAPE)
    camera = Camera.for_shape(SHAPE)
    result = render(src, _constant_path(pose), shape=SHAPE)
    expected, valid = _reference_render(src, np.broadcast_to(pose, (SHAPE[0], 1, 6)), camera, SHAPE[1])
    np.testing.assert_array_equal(result.valid, valid)
    np.testing.assert_allclose(result.image[valid], expected[valid], atol=2e-6)


def test_identity_path_reproduces_source():
    src = _textured(SHAPE)
    result = render(src, _constant_path(np.zeros(6)), shape=SHAPE, exposure=3.0)
    assert result.valid.all()
    np.testing.assert_allclose(result.image, src, atol=1e-6)


# ---------------------------------------------------------------- rolling shutter, blur


def test_rolling_shutter_centroids_follow_the_path_at_mid_exposure():
    exposure, row_delay = 5.0, 0.8
    start = np.array([-2.0, 1.0, 0.0, 0.0, 0.0, -1.0])
    end = np.array([3.0, -2.0, 0.0, 0.0, 0.0, 2.0])
    t_end = SHAPE[0] * row_delay + exposure
    path = _linear_path(start, end, t_end)
    result = render(_textured(SHAPE), path, shape=SHAPE, row_delay=row_delay, exposure=exposure)
    mid_times = np.arange(SHAPE[0]) * row_delay + exposure / 2
    expected = start + (end - start) * (mid_times / t_end)[:, None]
    np.testing.assert_allclose(result.centroid, expected, atol=1e-10)
    # the rows really differ: rolling shutter
    assert np.ptp(result.centroid[:, 0]) > 4.0


def test_rolling_shutter_blur_equals_mean_of_row_warps():
    exposure, row_delay, samples = 4.0, 1.0, 8
    start = np.array([-2.0, 1.0, 0.0, 0.0, 0.0, -1.0])
    end = np.array([3.0, -2.0, 0.01, 0.2, 0.1, 2.0])
    t_end = SHAPE[0] * row_delay + exposure
    path = _linear_path(start, end, t_end)
    src = _textured(SHAPE)
    result = render(src, path, shape=SHAPE, row_delay=row_delay, exposure=exposure, samples=samples)
    times = np.arange(SHAPE[0])[:, None] * row_delay + exposure * (np.arange(samples) + 0.5) / samples
    expected, valid = _reference_render(src, path(times), Camera.for_shape(SHAPE), SHAPE[1])
    np.testing.assert_array_equal(result.valid, valid)
    np.testing.assert_allclose(result.image[valid], expected[valid], atol=2e-6)


def test_exposure_zero_gives_no_blur():
    """Each row is one sharp warp at the row's start time, whatever ``samples`` says."""
    row_delay = 1.0
    start = np.array([-4.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    end = np.array([4.0, 2.0, 0.0, 0.0, 0.0, 1.0])
    path = _linear_path(start, end, SHAPE[0])
    src = _textured(SHAPE)
    result = render(src, path, shape=SHAPE, row_delay=row_delay, exposure=0.0, samples=24)
    times = np.arange(SHAPE[0], dtype=np.float64)[:, None]
    np.testing.assert_allclose(result.centroid, path(times)[:, 0], atol=1e-12)
    expected, valid = _reference_render(src, path(times), Camera.for_shape(SHAPE), SHAPE[1])
    np.testing.assert_allclose(result.image[valid], expected[valid], atol=2e-6)
    # a blurred capture of the same path is smoother than the sharp one
    fast = _linear_path(start, end + [60.0, 0, 0, 0, 0, 0], SHAPE[0])
    sharp = render(src, fast, shape=SHAPE, row_delay=row_delay, exposure=0.0)
    blurred = render(src, fast, shape=SHAPE, row_delay=row_delay, exposure=20.0)
    both = sharp.valid & blurred.valid
    assert np.abs(np.diff(blurred.image, axis=1))[both[:, 1:]].mean() < \
        0.6 * np.abs(np.diff(sharp.image, axis=1))[both[:, 1:]].mean()


def test_horizontal_translation_blur_is_a_box_filter():
    """tx sweeping 0 -> 4 px over every row's exposure, samples on whole pixels: the
    row is the mean of the source shifted by 0.25, 0.75, ... , 3.75 px."""
    samples = 8
    exposure = 1.0
    # the path restarts for each row: give every row the same motion with a global shutter
    path = _linear_path([0.0] * 6, [4.0, 0, 0, 0, 0, 0], exposure)
    src = _textured(SHAPE)
    result = render(src, path, shape=SHAPE, shutter="global", exposure=exposure, samples=samples)
    shifts = 4.0 * (np.arange(samples) + 0.5) / samples
    expected = np.mean([ndimage.shift(src.astype(np.float64), (0, s), order=1, mode="constant") for s in shifts],
                       axis=0)
    inner = result.valid
    assert inner[:, 4:].all() and not inner[:, :3].any()
    np.testing.assert_allclose(result.image[inner], expected[inner], atol=2e-6)


# ---------------------------------------------------------------- global shutter, gain, origin


def test_global_shutter_rows_share_one_centroid():
    exposure = 6.0
    start = np.array([-2.0, 1.0, 0.0, 0.0, 0.0, -1.0])
    end = np.array([3.0, -2.0, 0.0, 0.0, 0.0, 2.0])
    path = _linear_path(start, end, 20.0)
    src = _textured(SHAPE)
    result = render(src, path, shape=SHAPE, shutter="global", exposure=exposure, samples=6)
    expected_centroid = start + (end - start) * (exposure / 2 / 20.0)
    np.testing.assert_allclose(result.centroid, np.broadcast_to(expected_centroid, (SHAPE[0], 6)), atol=1e-12)
    times = np.broadcast_to(exposure * (np.arange(6) + 0.5) / 6, (SHAPE[0], 6))
    expected, valid = _reference_render(src, path(times), Camera.for_shape(SHAPE), SHAPE[1])
    np.testing.assert_allclose(result.image[valid], expected[valid], atol=2e-6)
    # without exposure, a global shutter is one warp by the pose at t = 0
    sharp = render(src, path, shape=SHAPE, shutter="global")
    np.testing.assert_array_equal(sharp.image, render(src, _constant_path(start), shape=SHAPE).image)


@pytest.mark.parametrize("gain", [0.7, 1.3])
def test_gain_scales_intensities(gain):
    path = _linear_path([-2.0, 1.0, 0, 0, 0, -1.0], [3.0, -2.0, 0, 0, 0, 2.0], 80.0)
    src = _textured(SHAPE)
    one = render(src, path, shape=SHAPE, exposure=3.0)
    scaled = render(src, path, shape=SHAPE, exposure=3.0, gain=gain)
    np.testing.assert_allclose(scaled.image, gain * one.image, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(scaled.valid, one.valid)
    np.testing.assert_array_equal(scaled.centroid, one.centroid)
    assert scaled.image.dtype == np.float32


def test_source_origin_equals_cropped_source():
    """A frame inside a larger source renders the same as the source cropped to the frame."""
    big = _textured((SHAPE[0] + 40, SHAPE[1] + 50), seed=5)
    origin = (17, 23)
    camera = Camera.for_shape(SHAPE)
    path = _linear_path([-2.0, 1.0, 0, 0.1, 0, -1.0], [3.0, -2.0, 0.01, 0, 0.2, 2.0], 80.0)
    whole = render(big, path, shape=SHAPE, camera=camera, source_origin_yx=origin, exposure=3.0, samples=6)
    crop = big[origin[0]:origin[0] + SHAPE[0], origin[1]:origin[1] + SHAPE[1]]
    cropped = render(crop, path, shape=SHAPE, camera=camera, exposure=3.0, samples=6)
    assert whole.valid.all()
    np.testing.assert_allclose(whole.image[cropped.valid], cropped.image[cropped.valid], atol=2e-6)
    np.testing.assert_array_equal(whole.centroid, cropped.centroid)


# ---------------------------------------------------------------- validation


def test_render_rejects_bad_parameters():
    src = _smooth(SHAPE)
    path = _constant_path(np.zeros(6))
    with pytest.raises(ParameterError, match="shutter"):
        render(src, path, shape=SHAPE, shutter="electronic")
    with pytest.raises(ParameterError, match="exposure"):
        render(src, path, shape=SHAPE, exposure=-1.0)
    with pytest.raises(ParameterError, match="row_delay"):
        render(src, path, shape=SHAPE, row_delay=-1.0)


@pytest.mark.parametrize("times, poses", [
    ([0.0, 1.0], np.zeros((2, 5))),
    ([1.0, 0.0], np.zeros((2, 6))),
    ([[0.0, 1.0]], np.zeros((2, 6))),
])
def test_camera_path_validation(times, poses):
    with pytest.raises(ParameterError, match="CameraPath"):
        CameraPath(np.asarray(times), poses)


def test_camera_path_interpolates_linearly_and_clamps():
    path = CameraPath(np.array([0.0, 2.0, 4.0]), np.array([[0.0] * 6, [2.0] * 6, [0.0] * 6]))
    np.testing.assert_allclose(path(np.array([0.5, 3.0])), [[0.5] * 6, [1.0] * 6])
    np.testing.assert_allclose(path(np.array([-1.0, 9.0])), np.zeros((2, 6)))
    assert path(np.zeros((3, 4))).shape == (3, 4, 6)
