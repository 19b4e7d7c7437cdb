"""Tests of pipeline.bench._baseline: the global homographies (ECC, ORB) and dense flow
(DIS) the benchmark sets beside rsmb recover a known warp."""

import cv2
import numpy as np
import pytest

from rsmb.ops import aerial_scene
from rsmb.pipeline.bench._baseline import dis_flow, ecc_homography, opencv_threads, orb_homography


@pytest.fixture(scope="module")
def pair():
    reference = aerial_scene((256, 256), seed=3).astype(np.float32)
    truth = np.array([[np.cos(0.02), -np.sin(0.02), 4.3], [np.sin(0.02), np.cos(0.02), -2.6], [0, 0, 1]])
    distorted = cv2.warpPerspective(reference, truth, (256, 256), flags=cv2.INTER_CUBIC)
    return reference, distorted, truth


def _rmse(a, b, margin=24):
    inner = (slice(margin, -margin),) * 2
    return float(np.sqrt(np.nanmean((a[inner] - b[inner]) ** 2)))


# ECC aligns intensities (subpixel); ORB keypoints sit on pyramid levels, about a pixel
@pytest.mark.parametrize("method, within_px", [(ecc_homography, 0.3), (orb_homography, 1.0)])
def test_homographies_recover_the_warp(pair, method, within_px):
    reference, distorted, truth = pair
    result = method(reference, distorted)
    # the matrix maps a distorted pixel to the reference, over the whole image
    points = np.stack([*np.meshgrid(np.linspace(0, 255, 9), np.linspace(0, 255, 9)), np.ones((9, 9))]).reshape(3, -1)
    expected, found = np.linalg.inv(truth) @ points, result.homography @ points
    assert np.abs(found[:2] / found[2] - expected[:2] / expected[2]).max() < within_px
    assert _rmse(result.registered, distorted) < 0.1 * _rmse(reference, distorted)


def test_orb_without_features_gives_nan_not_a_guess():
    flat = np.full((64, 64), 0.5, np.float32)
    result = orb_homography(flat, flat)
    assert result.homography is None and np.isnan(result.registered).all()


def test_dis_flow_registers_the_pair(pair):
    reference, distorted, _ = pair
    registered = dis_flow(reference, distorted)
    assert registered.shape == distorted.shape and registered.dtype == np.float32
    assert _rmse(registered, distorted) < 0.5 * _rmse(reference, distorted)


def test_baselines_are_timed_on_the_cores_rsmb_has_and_leave_opencv_as_they_found_it():
    # the rsmb command runs OpenCV on one thread; a baseline timed beside it gets rsmb's cores
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with opencv_threads(2) as threads:
            assert cv2.getNumThreads() == 2 and threads == 2
        assert cv2.getNumThreads() == 1
        with pytest.raises(RuntimeError), opencv_threads(3):
            raise RuntimeError("a baseline that fails")
        assert cv2.getNumThreads() == 1
    finally:
        cv2.setNumThreads(before)
