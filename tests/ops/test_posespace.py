"""Tests of ops._posespace: the grids N(c, b, s) on one global lattice."""

import numpy as np
import pytest

from rsmb.ops import ParameterError, PoseSpace, RSMBError


@pytest.fixture
def space():
    return PoseSpace(("tx", "ty", "rz"), (3.0, 2.0, 1.0), (1.0, 1.0, 0.5))


def test_counts_and_size(space):
    assert space.counts == (7, 5, 5)
    assert space.size == 7 * 5 * 5
    assert PoseSpace(("rx",), 0.0, 0.1).counts == (1,)
    assert PoseSpace(("s",), 0.1, 0.1).counts == (3,)


def test_scalar_half_width_and_step_broadcast():
    sp = PoseSpace(("tx", "ty"), 2, 1)
    assert sp.half_width == (2.0, 2.0)
    assert sp.step == (1.0, 1.0)
    assert sp.counts == (5, 5)
    assert isinstance(sp.axes, tuple)


def test_offsets_centred_and_complete(space):
    off = space.offsets()
    assert off.shape == (space.size, 3)
    assert np.issubdtype(off.dtype, np.integer)
    # every combination exactly once
    assert len({tuple(o) for o in off}) == space.size
    # symmetric about zero on each axis, zero in the middle
    for d, n in enumerate(space.counts):
        assert off[:, d].min() == -(n // 2) and off[:, d].max() == n // 2
    np.testing.assert_array_equal(off.sum(axis=0), 0)
    np.testing.assert_array_equal(off[space.size // 2], 0)


def test_snap_to_lattice(space):
    np.testing.assert_array_equal(space.snap([2.3, -1.6, 0.76]), [2, -2, 2])
    np.testing.assert_array_equal(space.snap([0.0, 0.0, 0.0]), [0, 0, 0])
    np.testing.assert_array_equal(space.snap([-7.0, 4.4, -1.2]), [-7, 4, -2])
    assert space.snap([0.1, 0.1, 0.1]).dtype == np.int64


def test_grid_poses_are_lattice_index_times_step(space):
    center = [2.3, -1.6, 0.76]
    index, poses = space.grid(center)
    np.testing.assert_array_equal(index, space.snap(center) + space.offsets())
    np.testing.assert_allclose(poses, index * np.array(space.step))
    # the grid is N(snap(c), b, s): centred on the snapped centre, spanning +-b
    snapped = space.snap(center) * np.array(space.step)
    np.testing.assert_allclose(poses.mean(axis=0), snapped, atol=1e-12)
    np.testing.assert_allclose(poses.min(axis=0), snapped - np.array(space.half_width))
    np.testing.assert_allclose(poses.max(axis=0), snapped + np.array(space.half_width))
    assert sorted(np.unique(poses[:, 2])) == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])


def test_grids_of_nearby_centres_share_the_lattice(space):
    _, a = space.grid([0.2, 0.1, 0.1])
    _, b = space.grid([1.4, -0.3, 0.4])
    shared = {tuple(p) for p in a} & {tuple(p) for p in b}
    assert len(shared) == 6 * 5 * 4  # overlaps of 7/7, 5/5, 5/5 grids moved by (1, 0, 1) steps


def test_lattice_poses(space):
    np.testing.assert_allclose(space.lattice_poses([[1, -2, 3]]), [[1.0, -2.0, 1.5]])


def test_widened_keeps_axes_and_steps(space):
    wide = space.widened((5.0, 2.0, 2.0))
    assert wide.axes == space.axes and wide.step == space.step
    assert wide.half_width == (5.0, 2.0, 2.0)
    assert wide.counts == (11, 5, 9)
    assert space.half_width == (3.0, 2.0, 1.0)  # unchanged (frozen)


@pytest.mark.parametrize("axes", [(), ("tx", "yaw"), ("tx", "tx")])
def test_bad_axes(axes):
    with pytest.raises(ParameterError, match="axes") as info:
        PoseSpace(axes, 1.0, 1.0)
    assert isinstance(info.value, ValueError) and isinstance(info.value, RSMBError)


@pytest.mark.parametrize("half_width, step, axis", [
    ((1.0, 1.0), (1.0, 0.0), "rz"),
    ((1.0, 1.0), (-1.0, 1.0), "tx"),
    ((-1.0, 1.0), (1.0, 1.0), "tx"),
])
def test_bad_steps_or_half_widths_name_the_axis(half_width, step, axis):
    with pytest.raises(ParameterError, match=f"axis {axis}"):
        PoseSpace(("tx", "rz"), half_width, step)


def test_widened_validates():
    sp = PoseSpace(("tx",), 1.0, 1.0)
    with pytest.raises(ParameterError):
        sp.widened(-2.0)
