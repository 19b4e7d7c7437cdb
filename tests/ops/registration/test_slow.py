"""The slow out-of-plane part of the path (camera yaw and pitch, METHOD.md
section 7): found on the window, baked into the pre-warped reference, and the
rows registered on it.  Pairs are rendered with the independent cubic renderer,
never with the solver's own warp kernel."""

import numpy as np
import pytest

from rsmb import ops
from rsmb.ops.registration import _slow
from rsmb.ops.synthetic._synth import readout_path

SHAPE = (384, 384)
EXPOSURE = 24.0


YAW_PITCH = dict(rx=(-2.5, 2.0), ry=(2.5, -2.0), tx=(-4.0, 4.0, 2.0), ty=(0.0, 5.0), rz=(-1.0, 1.0))


def _pair(seed=3, changes=6, **axes):
    path = readout_path(SHAPE[0], EXPOSURE, phase=1.0, **axes)  # the axes' wobbles a radian apart
    return ops.synthesize_pair(SHAPE, path=path, exposure=EXPOSURE, changes=changes, noise=0.002,
                               seed=seed, interpolation="cubic")


@pytest.fixture(scope="module")
def yaw_pitch():
    return _pair(**YAW_PITCH)


def test_yaw_and_pitch_are_found_on_the_window(yaw_pitch):
    pair = yaw_pitch
    path = ops.estimate_slow(pair.reference, pair.distorted, pair.valid, camera=pair.camera,
                             reference_origin_yx=(0, 0), distorted_origin_yx=(0, 0))
    assert path is not None
    rows = pair.valid.mean(axis=1) > 0.5
    error = path.rotation[rows] - pair.trajectory[rows][:, [3, 4]]
    assert np.abs(error).mean(axis=0).max() < 0.25, np.abs(error).mean(axis=0)


def test_the_threshold_is_in_the_captures_pixels():
    """A yaw of +-0.8 deg bends this window's rows by less than SLOW_MIN_PX: as
    the capture itself it is negligible, but as a 4x overview of a capture 4
    times larger the same bend is 4 times as many of that capture's pixels,
    and the path is kept (and right)."""
    pair = _pair(changes=0, ry=(-0.8, 0.8))
    found = [ops.estimate_slow(pair.reference, pair.distorted, pair.valid, camera=pair.camera,
                               reference_origin_yx=(0, 0), distorted_origin_yx=(0, 0), scale=scale)
             for scale in (1, 4)]
    assert found[0] is None and found[1] is not None
    rows = pair.valid.mean(axis=1) > 0.5
    assert np.abs(found[1].rotation[rows, 1] - pair.trajectory[rows, 4]).mean() < 0.1


@pytest.mark.parametrize("motion", ["inplane", "translation"])
def test_in_plane_motion_has_no_slow_part(motion):
    pair = ops.synthesize_pair(SHAPE, motion=motion, exposure=EXPOSURE, changes=6, noise=0.002, seed=4,
                               interpolation="cubic")
    path = ops.estimate_slow(pair.reference, pair.distorted, pair.valid, camera=pair.camera,
                             reference_origin_yx=(0, 0), distorted_origin_yx=(0, 0))
    assert path is None


def _f_measure(pair, params):
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera, params=params)
    changes = ops.detect_changes(reg, pair.distorted, camera=pair.camera)
    valid = reg.valid & pair.valid
    return ops.confusion(changes.mask, pair.change_mask, valid=valid).f_measure, reg


def test_the_defaults_register_yaw_and_pitch(yaw_pitch):
    """Yaw and pitch of +-2.5 deg over the readout with in-plane motion: the
    defaults detect the changes; without the slow part the row ends stay
    pixels off and the bends are reported as change."""
    f_default, reg = _f_measure(yaw_pitch, ops.RegistrationParams())
    f_in_plane, _ = _f_measure(yaw_pitch, ops.RegistrationParams(slow_axes=()))
    assert reg.axes == ("tx", "ty", "rz", "rx", "ry")
    assert f_default >= 0.9 and f_default > f_in_plane + 0.1, (f_default, f_in_plane)


def test_a_given_slow_path_is_used_as_it_is(yaw_pitch):
    pair = yaw_pitch
    truth = ops.SlowPath(pair.trajectory[:, [3, 4]], pair.trajectory[:, 1])
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera, slow=truth)
    np.testing.assert_allclose(reg.trajectory[:, 3:], truth.rotation)
    none = ops.register(pair.reference, pair.distorted, camera=pair.camera, slow=None)
    assert not none.trajectory[:, 3:].any()
    with pytest.raises(ops.ParameterError, match="slow"):
        ops.register(pair.reference, pair.distorted, camera=pair.camera, slow="yes")


def test_a_path_found_on_a_coarser_image_maps_onto_the_rows():
    coarse = ops.SlowPath(np.array([[0.0, 1.0], [1.0, 3.0]]), np.array([2.0, 4.0]))
    # coarse row j covers fine rows 4j .. 4j + 3: its centre is 4j + 1.5
    fine = coarse.at_rows([1.5, 3.5, 5.5, 7.0], factor=4)
    np.testing.assert_allclose(fine.rotation, [[0.0, 1.0], [0.5, 2.0], [1.0, 3.0], [1.0, 3.0]])
    np.testing.assert_allclose(fine.ty, [8.0, 12.0, 16.0, 16.0])


def test_bulk_shifts_follow_a_sheared_window():
    """The pre-alignment of the flow follows a rolling-shutter shear of tens
    of pixels over the rows, band by band."""
    scene = ops.aerial_scene((520, 520), seed=9)
    shear = np.round(np.linspace(-18, 18, 256)).astype(int)
    capture = np.stack([scene[100 + i + 6, 100 + s:100 + s + 256] for i, s in enumerate(shear)])
    shifts = _slow._bulk_shifts(scene, capture, np.ones(capture.shape, bool), 100, 100)
    band_centres = slice(32, 224)
    assert np.abs(shifts[band_centres, 0] - 6).max() <= 1
    assert np.abs(shifts[band_centres, 1] - shear[band_centres]).max() <= 3
