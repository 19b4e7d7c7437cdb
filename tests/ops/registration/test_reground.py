"""Rows pulled off the camera path by what is not ground are solved again on
the ground alone (:func:`ops.reground`); a real turn of the path is kept."""

import numpy as np
import pytest

from rsmb import ops

SHAPE, EXPOSURE = (192, 256), 6.0
PARAMS = ops.RegistrationParams(slow_axes=())
BAND = slice(90, 120)


def _path(bump=0.0):
    """tx 4 -> 7 px, ty 2 px; ``bump`` px more tx over rows 90-120 (a fast, real turn)."""
    t = np.linspace(0.0, SHAPE[0] + EXPOSURE + 1.0, 400)
    poses = np.zeros((t.size, 6))
    poses[:, 0] = 4.0 + 3.0 * t / t[-1] + bump * np.exp(-0.5 * ((t - 105.0) / 8.0) ** 2)
    poses[:, 1] = 2.0
    return ops.CameraPath(t, poses)


def _pair(bump=0.0):
    return ops.synthesize_pair(SHAPE, path=_path(bump), exposure=EXPOSURE, changes=3, noise=0.002, seed=61,
                               interpolation="cubic")


def _threshold(reg, distorted):
    residual = np.where(reg.valid, distorted - reg.registered, 0.0)
    return ops.change_threshold(ops.score_histogram(residual, np.abs(reg.chi), reg.valid))


def _tx_error(reg, pair, rows):
    return np.abs(reg.trajectory[rows, 0] - pair.trajectory[rows, 0])


@pytest.fixture(scope="module")
def smooth():
    return _pair()


def test_rows_pulled_off_the_path_are_solved_on_the_ground(smooth):
    pair = smooth
    good = ops.register(pair.reference, pair.distorted, camera=pair.camera, params=PARAMS)
    assert _tx_error(good, pair, slice(10, -10)).max() < 0.5
    # a band of rows that followed something else: 6 px off in tx
    prior = good.trajectory.copy()
    prior[BAND, 0] += 6.0
    pulled = ops.register(pair.reference, pair.distorted, camera=pair.camera, params=PARAMS, prior=prior)
    assert _tx_error(pulled, pair, BAND).min() > 2.0
    before = np.nanmedian(np.abs(pair.distorted - pulled.registered)[BAND])
    out = ops.reground(pulled, pair.reference, pair.distorted, camera=pair.camera, params=PARAMS,
                       threshold=_threshold(pulled, pair.distorted))
    assert out.timings["regrounded_rows"] >= BAND.stop - BAND.start - 2
    assert _tx_error(out, pair, BAND).max() < 0.5
    after = np.nanmedian(np.abs(pair.distorted - out.registered)[BAND])
    assert after < 0.3 * before
    # the changes are still changes, on the ground's registration
    changes = ops.detect_changes(out, pair.distorted, camera=pair.camera)
    counts = ops.confusion(changes.mask, pair.change_mask)
    assert counts.precision >= 0.9 and counts.recall >= 0.9, counts.as_dict()


def test_a_well_registered_capture_is_left_as_it_is(smooth):
    pair = smooth
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera, params=PARAMS)
    before = reg.trajectory.copy(), reg.registered.copy()
    out = ops.reground(reg, pair.reference, pair.distorted, camera=pair.camera, params=PARAMS,
                       threshold=_threshold(reg, pair.distorted))
    assert out.timings["regrounded_rows"] == 0
    np.testing.assert_array_equal(out.trajectory, before[0])
    np.testing.assert_array_equal(out.registered, before[1])


def test_a_real_turn_of_the_path_is_kept():
    pair = _pair(bump=6.0)
    # the truth as the path (the rows solve around it), and a new object on the turn
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera, params=PARAMS,
                       prior=pair.trajectory[:, [0, 1, 5]])
    distorted = pair.distorted.copy()
    distorted[98:112, 60:90] = 0.95
    reg = ops.register(pair.reference, distorted, camera=pair.camera, params=PARAMS, prior=reg.trajectory)
    assert _tx_error(reg, pair, BAND).max() < 0.5
    before = reg.trajectory.copy()
    out = ops.reground(reg, pair.reference, distorted, camera=pair.camera, params=PARAMS,
                       threshold=_threshold(reg, distorted))
    assert _tx_error(out, pair, BAND).max() < 0.5  # still on the turn: not flattened onto the path around it
    assert np.abs(out.trajectory[BAND, 0] - before[BAND, 0]).max() < 0.3


def test_outliers_are_the_large_components_grown_by_the_rim():
    """The candidates that re-grounding masks: the components of at least
    ``min_area`` pixels above the threshold, dilated by a square of
    ``2 * RIM_PX + 1`` px that the window's edge cuts (scipy's
    binary_dilation, border empty), small components and invalid pixels left out."""
    from types import SimpleNamespace

    from scipy import ndimage

    from rsmb.ops.changes._changes import large_components
    from rsmb.ops.registration._reground import RIM_PX, _outliers

    rng = np.random.default_rng(5)
    chi = np.zeros((61, 47), np.float32)
    chi[0:6, 0:5] = 0.5  # a large component in the corner: its rim is cut by two edges
    chi[30:34, 20:26] = -0.4  # a large one inside
    chi[50, 40] = 0.9  # a single pixel: too small
    chi += rng.normal(0.0, 0.01, chi.shape).astype(np.float32)
    valid = np.ones(chi.shape, bool)
    valid[31, :] = False
    reg = SimpleNamespace(chi=chi, valid=valid)
    out = _outliers(reg, 0.1, 10)
    candidates = (np.abs(chi) > 0.1) & valid
    size = 2 * RIM_PX + 1
    expected = ndimage.binary_dilation(large_components(candidates, 10), structure=np.ones((size, size), bool))
    np.testing.assert_array_equal(out, expected)
    assert out.dtype == bool and out[0, 0] and out[35, 28] and not out[50, 40] and out.sum() > 100
