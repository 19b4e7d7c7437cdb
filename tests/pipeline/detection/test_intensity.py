"""One intensity scale for any bit depth and unit, and clipped pixels as
bounds (ops._intensity, ops.changes._bounds): detect on the same pair stored
in four ways, on a capture brighter than its reference with clipped
highlights, on new objects over clipped roofs and shadows, and with black
collars (fill, no-data)."""

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
        masks[name] = arrays["change_mask"] == 1
        assert attrs["intensity"]["capture_clip"] == [None, None], name  # nothing sits at a saturation value
    truth = pair.change_mask
    for a in masks:
        f = ops.confusion(masks[a], truth).f_measure
        assert f >= 0.9, (a, f)
        for b in masks:
            iou = (masks[a] & masks[b]).sum() / (masks[a] | masks[b]).sum()
            assert iou >= 0.98, (a, b, iou)


def test_a_bright_field_saturating_under_a_gain_is_not_change(tmp_path):
    """A capture 35 % brighter than its reference whose sensor saturates: a
    fifth of its pixels at 255 (bright fields; the new objects are dark on
    them).  A clipped pixel says only that the scene was at least that
    bright: where the model reaches the saturation value it is consistent
    (never change), and the new dark objects on those fields are found.
    Their share is in the summary."""
    pair_dir = tmp_path / "pair"
    bright, ref, dist = clipped_pair(pair_dir, SHAPE)
    saturation = np.percentile(bright.distorted, 80)
    assert (bright.distorted[bright.change_mask] < saturation).mean() > 0.95
    result = detect(ref, dist, tmp_path / "o.zarr", config=DetectConfig(tile=128))
    assert 0.19 <= result.clipped_capture <= 0.21
    arrays, _ = read_store(tmp_path / "o.zarr")
    clipped = cv2.imread(str(dist), cv2.IMREAD_UNCHANGED) == 255
    mask = arrays["change_mask"] == 1
    field = clipped & ~bright.change_mask & bright.valid
    assert mask[field].mean() < 0.01  # one small rim where the rows' gain falls short of the field
    scores = evaluate(tmp_path / "o.zarr", pair_dir)
    outside = ~bright.change_mask & bright.valid  # clipped pixels included
    false_pwc = 100.0 * mask[outside].mean()
    assert scores.changes.f_measure >= 0.93 and false_pwc <= 0.3, (scores.changes.f_measure, false_pwc)


def _write_png(path, image):
    cv2.imwrite(str(path), np.round(np.clip(image, 0, 1) * 255).astype(np.uint8))
    return path


def test_a_dark_object_on_a_saturated_roof_and_a_bright_one_in_a_black_shadow_are_found(tmp_path):
    """A roof saturated in both images and a shadow at 0 in both; in the
    capture a dark car on the roof and a bright object in the shadow.  The
    reference's clipped pixels bound the scene (at least, at most that
    bright): both objects lie far outside the bound and are change; the rest
    of the roof and the shadow are not."""
    margin, h = 40, SHAPE[0]
    scene = (0.15 + 0.6 * ops.aerial_scene((h + 2 * margin,) * 2, seed=12)).astype(np.float32)
    roof, shadow = (slice(80, 150), slice(70, 150)), (slice(200, 260), slice(190, 260))
    scene[roof] = 1.3  # clipped at 255 in both images
    # a deep shadow: mostly at 0 in both images, a third of its pixels just above (a real shadow is not a
    # uniform block of zeros, which would be fill)
    rng = np.random.default_rng(4)
    scene[shadow] = -0.1 + 0.15 * rng.random(scene[shadow].shape, np.float32)
    changed = scene.copy()
    truth_source = np.zeros(scene.shape, np.float32)
    car, lamp = (slice(105, 121), slice(95, 125)), (slice(220, 240), slice(215, 235))
    changed[car], changed[lamp] = 0.1, 0.9
    truth_source[car], truth_source[lamp] = 1.0, 2.0
    path = ops.motion_path("translation", duration=h + 9.0, seed=2, scale=0.4)
    kw = dict(shape=SHAPE, exposure=8.0, source_origin_yx=(margin, margin), interpolation="cubic")
    capture = ops.render(changed, path, **kw).image
    capture += np.random.default_rng(3).normal(0, 0.002, capture.shape).astype(np.float32)
    objects = ops.render(truth_source, path, **kw).image
    inner = (slice(margin, margin + h),) * 2
    ref = _write_png(tmp_path / "reference.png", scene[inner])
    dist = _write_png(tmp_path / "distorted.png", capture)
    detect(ref, dist, tmp_path / "o.zarr", config=DetectConfig(tile=128))
    arrays, _ = read_store(tmp_path / "o.zarr")
    mask = arrays["change_mask"] == 1
    dark, bright = np.abs(objects - 1.0) < 0.5, objects > 1.5
    # their blurred rims mix in the roof's (the shadow's) true value, which only the bound says: at least 80 %
    assert mask[dark].mean() >= 0.8 and mask[bright].mean() >= 0.8, (mask[dark].mean(), mask[bright].mean())
    found = ops.confusion(mask, dark | bright)
    assert found.precision >= 0.9, found.as_dict()
    # no evidence only where both images are clipped the same way (the roof's and the shadow's insides), not
    # in a wide ring around every clipped pixel
    both = np.zeros(scene.shape, bool)
    both[roof] = both[shadow] = True
    around = cv2.dilate(both[inner].astype(np.uint8), np.ones((25, 25), np.uint8)) > 0
    silent = np.isnan(arrays["change_score"])[20:-20, 20:-20]
    assert silent[~around[20:-20, 20:-20]].mean() < 0.005


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
    mask = arrays["change_mask"] == 1
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


@pytest.mark.parametrize("which", ["capture", "reference"])
def test_an_untagged_black_collar_is_no_data_never_change(tmp_path, pair, which):
    """0 also fills the edges of images without a nodata value (the collar
    of an orthophoto, tapering at a corner): that fill is no-data in either
    image, never change, although the model (or the capture) is far above 0
    there; the scene's own dark pixels elsewhere stay."""
    images = {"reference": np.clip(pair.reference, 0, 1), "capture": np.clip(pair.distorted, 0, 1)}
    yy, xx = np.mgrid[:SHAPE[0], :SHAPE[1]]
    collar = (xx < 24) | (xx + yy < 70)  # a band and a corner triangle
    images[which][collar] = 0.0
    ref = _write_png(tmp_path / "reference.png", images["reference"])
    dist = _write_png(tmp_path / "distorted.png", images["capture"])
    detect(ref, dist, tmp_path / "o.zarr", config=DetectConfig(tile=128))
    arrays, attrs = read_store(tmp_path / "o.zarr")
    assert attrs["intensity"][f"{which}_clip"][0] is None  # no 0 left: the collar is no-data, not clipped
    near = np.zeros(SHAPE, bool)
    near[:, :40] = True  # the collar and what the motion carries from it
    near |= xx + yy < 90
    assert not (arrays["change_mask"][near] == 1).any()
    if which == "capture":
        assert np.isnan(arrays["change_score"][collar]).all()
    found = ops.confusion(arrays["change_mask"] == 1, pair.change_mask, valid=~near)
    assert found.f_measure >= 0.9, found.as_dict()
