"""One intensity scale for any bit depth and unit, and clipped pixels as
no-data (ops._intensity): detect on the same pair stored in four ways, and on
a capture brighter than its reference with clipped highlights."""

import cv2
import numpy as np
import pytest

from rsmb import ops
from rsmb.pipeline import DetectConfig, detect, evaluate
from rsmb.pipeline.bench._bench_method import BIT_DEPTHS, clipped_pair

from ..conftest import read_store

SHAPE = (256, 256)


@pytest.fixture(scope="module")
def pair():
    return ops.synthesize_pair(SHAPE, motion="inplane", changes=6, noise=0.002, seed=31, interpolation="cubic")


def test_every_bit_depth_and_unit_gives_the_same_changes(tmp_path, pair):
    masks = {}
    for name, write in BIT_DEPTHS.items():
        d = tmp_path / name.replace(" ", "_").replace(",", "")
        d.mkdir()
        ref = write(d / "reference", np.clip(pair.reference, 0, 1))
        dist = write(d / "distorted", np.clip(pair.distorted, 0, 1))
        detect(ref, dist, d / "o.zarr", config=DetectConfig(tile=128))
        arrays, attrs = read_store(d / "o.zarr")
        masks[name] = arrays["change_mask"] > 0
        assert attrs["intensity"]["capture_clip"] == [None, None], name  # nothing sits at a saturation value
    truth = pair.change_mask
    for a in masks:
        f = ops.confusion(masks[a], truth).f_measure
        assert f >= 0.9, (a, f)
        for b in masks:
            iou = (masks[a] & masks[b]).sum() / (masks[a] | masks[b]).sum()
            assert iou >= 0.98, (a, b, iou)


def test_clipped_highlights_carry_one_sided_evidence(tmp_path):
    """A capture 35 % brighter than its reference whose sensor saturates: a
    fifth of its pixels at 255 (bright fields; the new objects are dark on
    them).  A clipped pixel says only that the scene was at least that bright:
    no-data in the score and never change where the model reaches the
    saturation value (the bright fields), change only where the model stays
    clearly below it.  Their share is in the summary."""
    pair_dir = tmp_path / "pair"
    bright, ref, dist = clipped_pair(pair_dir, SHAPE)
    saturation = np.percentile(bright.distorted, 80)
    assert (bright.distorted[bright.change_mask] < saturation).mean() > 0.95
    result = detect(ref, dist, tmp_path / "o.zarr", config=DetectConfig(tile=128))
    assert 0.19 <= result.clipped_capture <= 0.21
    arrays, _ = read_store(tmp_path / "o.zarr")
    clipped = cv2.imread(str(dist), cv2.IMREAD_UNCHANGED) == 255
    score, mask = arrays["change_score"], arrays["change_mask"] > 0
    # most of the bright fields carry no evidence at all, and those are never change
    assert np.isnan(score[clipped & ~bright.change_mask]).mean() > 0.5
    assert not (mask & clipped & np.isnan(score) & ~bright.change_mask).any()
    scores = evaluate(tmp_path / "o.zarr", pair_dir)
    outside = ~bright.change_mask & bright.valid  # clipped pixels included
    false_pwc = 100.0 * mask[outside].mean()
    assert scores.changes.f_measure >= 0.93 and false_pwc <= 0.3, (scores.changes.f_measure, false_pwc)


def test_a_new_object_that_saturates_is_change(tmp_path):
    """The same capture with bright new objects: they saturate the sensor
    where the model (the darker ground, times the gain) stays well below it,
    and are found although every one of their pixels is clipped."""
    side = int(1.5625 * max(SHAPE))
    scene = (0.1 + 0.45 * ops.aerial_scene((side, side), seed=8)).astype(np.float32)  # bright objects on it
    bright = ops.synthesize_pair(SHAPE, motion="inplane", changes=6, noise=0.002, seed=33, gain=1.35,
                                 interpolation="cubic", scene=scene)
    saturation = 0.9  # above the brightened ground, below the brightened objects
    ref, dist = tmp_path / "reference.png", tmp_path / "distorted.png"
    for path, image in ((ref, bright.reference), (dist, bright.distorted)):
        cv2.imwrite(str(path), np.round(np.clip(image / saturation, 0, 1) * 255).astype(np.uint8))
    clipped = cv2.imread(str(dist), cv2.IMREAD_UNCHANGED) == 255
    assert clipped[bright.change_mask].mean() > 0.5 and clipped[~bright.change_mask].mean() < 0.01
    detect(ref, dist, tmp_path / "o.zarr", config=DetectConfig(tile=128))
    arrays, _ = read_store(tmp_path / "o.zarr")
    mask = arrays["change_mask"] > 0
    found = ops.confusion(mask, bright.change_mask)
    assert found.recall >= 0.85 and found.precision >= 0.9, found.as_dict()


def test_scale_and_clip_levels():
    from rsmb.tiles import WindowStats

    def stats(values):
        values = np.asarray(values, np.float32)
        return WindowStats(values.size, float(values.min()), float(values.max()), int((values == values.min()).sum()),
                           int((values == values.max()).sum()), values)

    rng = np.random.default_rng(0)
    scene = rng.uniform(0.1, 0.9, 10000).astype(np.float32)
    eight = np.round(scene * 255) / 255
    twelve = (np.round(scene * 4095) / 65535).astype(np.float32)  # a 12-bit sensor in 16 bits, as ingested
    for a, b in [(eight, eight), (twelve, twelve)]:
        scale = ops.intensity_scale(stats(a), stats(b))
        assert scale.capture_clip == (None, None)
        np.testing.assert_allclose(scale.apply(a, "capture") / scale.apply(a, "capture").max(),
                                   scene / scene.max(), atol=0.01)
    saturated = np.minimum(eight * 1.35, 1.0)
    scale = ops.intensity_scale(stats(eight), stats(saturated))
    assert scale.capture_clip[1] == 1.0 and scale.reference_clip == (None, None)
    assert np.isnan(scale.apply(saturated, "capture")[saturated == 1.0]).all()
    assert scale.capture_clipped == pytest.approx((saturated == 1.0).mean())
    twelve_saturated = np.minimum(twelve * 1.35, np.float32(4095 / 65535))
    assert ops.intensity_scale(stats(twelve), stats(twelve_saturated)).capture_clip[1] is not None
    radiance = 250.0 + 3000.0 * scene  # float data in other units: no saturation value
    assert ops.intensity_scale(stats(radiance), stats(radiance)).capture_clip == (None, None)
    with pytest.raises(ops.InputError, match="clipped"):
        ops.intensity_scale(stats(eight), stats(np.r_[np.zeros(50), np.ones(50)]))


def test_a_zero_filled_border_is_not_change(tmp_path, pair):
    """0 also fills the edges of images without a nodata value: pixels at the
    floor carry no evidence, even where the model is far above 0."""
    capture = np.clip(pair.distorted, 0, 1)
    capture[:, :24] = 0.0  # a black band, as an orthorectified capture's edge
    ref, dist = tmp_path / "reference.png", tmp_path / "distorted.png"
    for path, image in ((ref, np.clip(pair.reference, 0, 1)), (dist, capture)):
        cv2.imwrite(str(path), np.round(image * 255).astype(np.uint8))
    detect(ref, dist, tmp_path / "o.zarr", config=DetectConfig(tile=128))
    arrays, attrs = read_store(tmp_path / "o.zarr")
    assert attrs["intensity"]["capture_clip"][0] == 0.0
    assert np.isnan(arrays["change_score"][:, :24]).all() and not arrays["change_mask"][:, :24].any()
