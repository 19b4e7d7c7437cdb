"""Accuracy of registration and change detection on synthetic pairs with known
truth, mirroring the paper's experiments (issue: core method, item 3)."""

import numpy as np
import pytest

from rsmb import ops

SEARCH = {"tx": 20.0, "ty": 20.0, "rz": 3.0}


def _params(axes=("tx", "ty", "rz"), **kw):
    """The defaults (automatic steps: 1 px, 3 steps wide) on ``axes``."""
    n = len(axes)
    return ops.RegistrationParams(axes=axes, half_width=(None,) * n, step=(None,) * n,
                                  search=[SEARCH[a] for a in axes], **kw)


def _run(pair, params):
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera, params=params)
    changes = ops.detect_changes(reg, pair.distorted, camera=pair.camera)
    return reg, changes


def _trajectory_rmse(reg, pair):
    idx = [ops.POSE_AXES.index(a) for a in reg.axes]
    rows = reg.valid.mean(axis=1) > 0.5  # rows whose content is (mostly) in the reference
    err = reg.trajectory[rows] - pair.trajectory[rows][:, idx]
    return dict(zip(reg.axes, np.sqrt(np.mean(err ** 2, axis=0))))


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("axes", [("tx", "ty"), ("tx", "ty", "rz")])
def test_nonuniform_translation_trajectory_and_no_false_change(seed, axes):
    # supplement Fig. 15: tx in [-15, 15], ty in [0, 10] px, blur of H/16 row periods
    pair = ops.synthesize_pair((256, 256), motion="translation", changes=0, noise=0.002, seed=seed)
    assert np.ptp(pair.trajectory[:, 0]) > 10  # the motion is really non-uniform
    reg, changes = _run(pair, _params(axes))
    rmse = _trajectory_rmse(reg, pair)
    assert rmse["tx"] <= 0.2 and rmse["ty"] <= 0.2, rmse
    pwc = ops.confusion(changes.mask, pair.change_mask).pwc
    assert pwc <= 0.3
    assert abs(reg.gain - 1.0) < 0.01


@pytest.mark.parametrize("seed", [0, 1])
def test_inplane_motion_with_changes(seed):
    pair = ops.synthesize_pair((256, 256), motion="inplane", changes=8, noise=0.002, seed=seed)
    reg, changes = _run(pair, _params())
    counts = ops.confusion(changes.mask, pair.change_mask)
    assert counts.f_measure >= 0.95, counts.as_dict()
    ref = ops.confusion(changes.mask_reference, pair.change_mask_reference)
    assert ref.f_measure >= 0.9, ref.as_dict()
    rmse = _trajectory_rmse(reg, pair)
    assert rmse["tx"] < 0.5 and rmse["ty"] < 0.5 and rmse["rz"] < 0.3, rmse


@pytest.mark.parametrize("seed", [0, 1])
def test_yaw_rotation_curved_lines(seed):
    # yaw (ry) bends straight lines under a rolling shutter; the default pose
    # space (tx, ty, rz) approximates it row by row
    pair = ops.synthesize_pair((256, 256), motion="yaw", changes=8, noise=0.002, seed=seed)
    assert np.ptp(pair.trajectory[:, ops.POSE_AXES.index("ry")]) > 1.0
    _, changes = _run(pair, _params())
    counts = ops.confusion(changes.mask, pair.change_mask)
    assert counts.f_measure >= 0.9, counts.as_dict()


@pytest.mark.parametrize("seed", [0, 1])
def test_global_shutter_blur(seed):
    pair = ops.synthesize_pair((256, 256), motion="inplane", shutter="global", changes=8, noise=0.002, seed=seed)
    centroid = pair.trajectory[0]
    assert np.allclose(pair.trajectory, centroid)  # one pose for every row
    reg, changes = _run(pair, _params(shutter="global"))
    counts = ops.confusion(changes.mask, pair.change_mask)
    assert counts.f_measure >= 0.95, counts.as_dict()
    idx = [ops.POSE_AXES.index(a) for a in reg.axes]
    assert np.abs(reg.trajectory[0] - centroid[idx]).max() < 0.5


@pytest.mark.parametrize("gain", [0.7, 1.3])
def test_gain_recovered(gain):
    pair = ops.synthesize_pair((256, 256), motion="inplane", gain=gain, changes=8, noise=0.002, seed=0)
    reg, changes = _run(pair, _params())
    assert abs(reg.gain - gain) / gain <= 0.03
    counts = ops.confusion(changes.mask, pair.change_mask)
    assert counts.f_measure >= 0.9, counts.as_dict()


@pytest.mark.parametrize("seed", [0, 1])
def test_gain_ramp_along_the_rows(seed):
    # the gain goes from 0.75 to 1.25 across every row (one gain per row in eq. 13):
    # the fitted slope is divided out and the rows solved again
    pair = ops.synthesize_pair((256, 256), motion="inplane", gain=(0.75, 1.25), changes=8, noise=0.002, seed=seed)
    reg, changes = _run(pair, _params())
    assert abs(reg.gain - 1.0) <= 0.03
    counts = ops.confusion(changes.mask, pair.change_mask)
    assert counts.f_measure >= 0.9, counts.as_dict()


def test_rsmb_defaults_handle_rolling_shutter_without_blur():
    pair = ops.synthesize_pair((256, 256), motion="wobble", exposure=0.0, changes=6, noise=0.002, seed=4)
    reg, changes = _run(pair, ops.RegistrationParams())
    rmse = _trajectory_rmse(reg, pair)
    assert rmse["tx"] < 0.3 and rmse["ty"] < 0.3, rmse
    assert ops.confusion(changes.mask, pair.change_mask).f_measure >= 0.9


def test_exact_solver_gives_the_same_registration():
    # the cvxpy oracle inside the same propagation: same trajectory on a small image
    pair = ops.synthesize_pair((64, 96), motion="translation", changes=0, noise=0.002, seed=5, scale=0.3)
    params = dict(axes=("tx", "ty"), half_width=(1.0, 1.0), step=(1.0, 1.0), search=(6.0, 6.0), adapt=False)
    fast = ops.register(pair.reference, pair.distorted, params=ops.RegistrationParams(**params))
    exact = ops.register(pair.reference, pair.distorted, params=ops.RegistrationParams(solver="exact", **params))
    rows = fast.valid.mean(axis=1) > 0.5
    assert np.abs(fast.trajectory[rows] - exact.trajectory[rows]).max() < 0.05
    assert np.nanmax(np.abs(fast.registered - exact.registered)) < 2e-3


def test_paper_neighbourhoods_on_a_small_image():
    # the paper's own pose spaces: tx, ty N(c, 3, 1) px, rz N(c, 2, 0.5) deg
    pair = ops.synthesize_pair((256, 256), motion="inplane", changes=8, noise=0.002, seed=2)
    params = ops.RegistrationParams(half_width=(3.0, 3.0, 2.0), step=(1.0, 1.0, 0.5))
    _, changes = _run(pair, params)
    assert ops.confusion(changes.mask, pair.change_mask).f_measure >= 0.95


def test_automatic_steps_move_the_farthest_pixel_by_one_pixel():
    camera = ops.Camera.for_shape((1024, 1024))
    params = ops.RegistrationParams().resolved(camera)
    radius = np.hypot(512, 512)
    assert params.step[:2] == (1.0, 1.0) and params.half_width[:2] == (3.0, 3.0)
    assert np.radians(params.step[2]) * radius == pytest.approx(1.0)
    assert params.half_width[2] == pytest.approx(3 * params.step[2])
    with pytest.raises(ops.ParameterError, match="auto"):
        ops.RegistrationParams().space


def test_prior_trajectory_is_followed():
    pair = ops.synthesize_pair((128, 128), motion="inplane", changes=0, noise=0.002, seed=6)
    idx = [0, 1, 5, 3, 4]  # tx, ty, rz and the slow rx, ry
    reg = ops.register(pair.reference, pair.distorted, params=_params(), prior=pair.trajectory[:, idx])
    rmse = _trajectory_rmse(reg, pair)
    assert max(rmse.values()) < 0.3, rmse
    with pytest.raises(ops.ParameterError, match="prior"):
        ops.register(pair.reference, pair.distorted, params=_params(), prior=np.zeros((3, 3)))


def test_nan_in_the_reference_is_nodata():
    pair = ops.synthesize_pair((128, 128), motion="translation", changes=0, noise=0.002, seed=2)
    reference = pair.reference.copy()
    reference[:20, 30:90] = np.nan
    as_nan = ops.register(reference, pair.distorted, params=_params(("tx", "ty")))
    as_mask = ops.register(np.nan_to_num(reference), pair.distorted, params=_params(("tx", "ty")),
                           reference_valid=np.isfinite(reference))
    assert not as_nan.valid.all()
    np.testing.assert_array_equal(as_nan.registered, as_mask.registered)
    np.testing.assert_array_equal(as_nan.trajectory, as_mask.trajectory)


def test_start_lattice_is_coarsened_only_where_rz_steps_are_fine():
    """Start candidates compete on rz steps twice the stride only where one step
    moves the window's pixels by a pixel or less (automatic steps), never on a
    coarse lattice such as the paper's 0.5 deg."""
    from rsmb.ops.registration._rowproblem import _RowProblem

    shape = (256, 256)
    camera = ops.Camera.for_shape((2048, 2048))
    image = np.zeros(shape, np.float32)
    axes = ("tx", "ty", "rz")

    def strides(step_rz, origin):
        problem = _RowProblem(image, image, np.ones(shape, bool), camera, origin, origin, axes,
                              (1.0, 1.0, step_rz), 4)
        return problem.rotation_stride(), problem.rotation_stride(2)

    auto = ops.auto_step("rz", camera)
    corner, coarse = strides(auto, (0, 0))
    assert list(corner) == [1, 1, 1] and list(coarse) == [1, 1, 2]
    near, near_coarse = strides(auto, (896, 896))  # next to the principal point: several steps per pixel
    assert near[2] > 1 and near_coarse[2] == 2 * near[2]
    paper, paper_coarse = strides(0.5, (0, 0))
    assert list(paper) == list(paper_coarse) == [1, 1, 1]


def test_rows_stopped_at_the_iteration_limit_are_failed():
    """A row solve that stops at ``max_outer`` before its KKT conditions hold
    is failed (state 3), not solved; its pose is interpolated from the rows
    around it.  With the default limit only the rows whose content left the
    reference fail, and a limit ten times larger changes nothing.  (Rows
    that stop short of the tolerance: :func:`test_failed_rows_carry_no_evidence`.)"""
    pair = ops.synthesize_pair((128, 128), motion="inplane", changes=0, noise=0.002, seed=6)
    default = ops.register(pair.reference, pair.distorted, params=_params())
    outside = default.valid.mean(axis=1) < 0.1
    np.testing.assert_array_equal(default.row_state == 3, outside)
    larger = ops.register(pair.reference, pair.distorted, params=_params(max_outer=1000))
    np.testing.assert_array_equal(larger.row_state, default.row_state)


def test_failed_rows_carry_no_evidence():
    """With a tolerance rounding cannot meet on some rows, their solves stop
    short of the optimality conditions: those rows are failed (state 3) and
    carry no evidence (not valid, registered NaN, no change term, no weights
    to render), so they can paint no stripe of change; the other rows are as
    with the default tolerance."""
    pair = ops.synthesize_pair((128, 128), motion="inplane", changes=3, noise=0.002, seed=6)
    default = ops.register(pair.reference, pair.distorted, params=_params(slow_axes=()))
    strict = ops.register(pair.reference, pair.distorted, params=_params(slow_axes=(), tol=1e-12))
    failed = strict.row_state == 3
    assert (failed & (default.row_state == 1)).sum() >= 5 and (strict.row_state == 1).sum() >= 64
    assert not strict.valid[failed].any()
    assert np.isnan(strict.registered[failed]).all() and not strict.chi[failed].any()
    assert not set(np.nonzero(failed)[0]) & set(strict.row_weights)
    assert np.isfinite(strict.trajectory).all()
    assert strict.valid[strict.row_state == 1].any(axis=1).all()


def test_nan_in_the_capture_is_nodata():
    """NaN pixels of the capture are no-data, exactly as ``distorted_valid``
    False with any value there: not valid, no change, the path unchanged."""
    pair = ops.synthesize_pair((192, 192), motion="inplane", changes=3, noise=0.002, seed=4)
    holes = np.zeros(pair.distorted.shape, bool)
    holes[60:72, 30:120] = True
    holes[150, :] = True
    with_nan = np.where(holes, np.nan, pair.distorted).astype(np.float32)
    as_nan = ops.register(pair.reference, with_nan, camera=pair.camera, params=_params(slow_axes=()))
    as_mask = ops.register(pair.reference, np.where(holes, 0.7, pair.distorted).astype(np.float32),
                           camera=pair.camera, params=_params(slow_axes=()), distorted_valid=~holes)
    assert not as_nan.valid[holes].any() and not as_nan.chi[holes].any()
    assert np.isfinite(as_nan.registered[as_nan.valid]).all() and np.isfinite(as_nan.chi).all()
    np.testing.assert_array_equal(as_nan.row_state, as_mask.row_state)
    np.testing.assert_array_equal(as_nan.trajectory, as_mask.trajectory)
    np.testing.assert_array_equal(as_nan.chi, as_mask.chi)
    rmse = _trajectory_rmse(as_nan, pair)
    assert rmse["tx"] <= 0.3 and rmse["ty"] <= 0.3, rmse
