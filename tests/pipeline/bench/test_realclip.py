"""Tests of pipeline.bench._bench_realclip's pair builder (on synthetic images:
tests never read the real photographs) and of DIS's change mask by rsmb's rule."""

import numpy as np
import pytest

from rsmb.ops import aerial_scene
from rsmb.pipeline.bench._bench_realclip import dis_changes, orthophoto_scene, paste_on_extremes, realclip_pair


@pytest.fixture(scope="module")
def images():
    return [aerial_scene((128, 128), seed=s).astype(np.float32) for s in (1, 2, 3)]


def test_the_scene_is_stretched_to_clip_one_percent_at_each_end(images):
    scene = orthophoto_scene(images, 300)
    assert scene.shape == (300, 300)
    assert (scene < 0).mean() == pytest.approx(0.01, abs=0.002)
    assert (scene > 1).mean() == pytest.approx(0.01, abs=0.002)
    # blocks are mirrored images: the first block is the first image, the one below it flipped upside down
    assert np.corrcoef(scene[:128, :128].ravel(), images[0].ravel())[0, 1] > 0.999
    assert np.corrcoef(scene[128:256, :128].ravel(), images[1][::-1].ravel())[0, 1] > 0.999


def test_dark_objects_go_on_the_brightest_areas_and_bright_ones_in_the_darkest():
    rng = np.random.default_rng(0)
    scene = rng.uniform(0.3, 0.7, (256, 256)).astype(np.float32)
    scene[40:80, 40:80] = 1.4  # a saturated roof
    scene[170:210, 150:190] = -0.3  # a shadow at 0
    changed, labels = paste_on_extremes(scene, 2, seed=1, margin=30, size_range=(14, 20))
    dark, bright = labels == 1, labels == 2
    assert dark.any() and bright.any()
    assert (scene[dark] == 1.4).all() and changed[dark].max() < 0.2
    assert (scene[bright] == -0.3).all() and changed[bright].min() > 0.8
    assert (changed[labels == 0] == scene[labels == 0]).all()


def test_the_pair_is_eight_bit_with_truth_in_the_capture_grid(images):
    pair = realclip_pair(images, 256, objects=4, samples=6)
    assert pair.reference.dtype == np.uint8 and pair.capture.dtype == np.uint8
    assert pair.reference.shape == pair.capture.shape == pair.change_mask.shape == (256, 256)
    assert 0.015 < pair.reference_clipped < 0.05
    assert pair.objects == 4 and pair.objects_on_clipped >= 2
    assert pair.change_mask.any() and not (pair.on_clipped & ~pair.change_mask).any()
    # the objects are new in the capture: dark ones on white, bright ones on black
    changed = pair.change_mask
    ref, cap = pair.reference.astype(float), pair.capture.astype(float)
    assert np.abs(cap[changed] - ref[changed]).mean() > 100
    # the border band the motion brings in from outside the reference is not covered; the rest is
    assert 0.6 < pair.covered.mean() < 0.99 and pair.covered[100:156, 100:156].all()


def test_dis_changes_finds_a_new_object_and_little_else():
    reference = aerial_scene((256, 256), seed=4).astype(np.float32)
    capture = np.roll(reference, (2, -3), axis=(0, 1)).copy()
    capture[120:140, 100:130] = 0.95
    mask = dis_changes(reference, capture, factor=1.0)
    truth = np.zeros(mask.shape, bool)
    truth[120:140, 100:130] = True
    assert mask[truth].mean() > 0.8
    inner = (slice(20, -20),) * 2  # DIS has no content to match at the rolled-in edges
    assert mask[inner][~truth[inner]].mean() < 0.01
