"""Tests of ops._camera: intrinsics defaults and pose homographies, answers known by construction."""

import numpy as np
import pytest

from rsmb.ops import POSE_AXES, Camera, ParameterError, RSMBError, full_poses, pose_homographies


def _apply(h, xy):
    """Map points xy (..., 2) by homography h (3, 3)."""
    p = np.concatenate([np.asarray(xy, np.float64), np.ones(np.shape(xy)[:-1] + (1,))], -1)
    q = p @ h.T
    return q[..., :2] / q[..., 2:3]


@pytest.fixture
def camera():
    return Camera.for_shape((120, 200))


@pytest.fixture
def points():
    rng = np.random.default_rng(1)
    return rng.uniform([0, 0], [200, 120], size=(50, 2))


# ---------------------------------------------------------------- Camera


@pytest.mark.parametrize("shape, focal, center", [
    ((120, 200), 240.0, (99.5, 59.5)),
    ((300, 100), 360.0, (49.5, 149.5)),
    ((64, 64), 76.8, (31.5, 31.5)),
])
def test_for_shape_default_focal_and_centre(shape, focal, center):
    cam = Camera.for_shape(shape)
    assert cam.focal == pytest.approx(focal)
    assert cam.center_xy == pytest.approx(center)


def test_for_shape_given_focal():
    cam = Camera.for_shape((10, 20), focal=500)
    assert cam.focal == 500.0
    assert isinstance(cam.focal, float)


@pytest.mark.parametrize("focal", [0.0, -3.0])
def test_for_shape_rejects_bad_focal(focal):
    with pytest.raises(ParameterError, match="focal"):
        Camera.for_shape((10, 20), focal=focal)


# ---------------------------------------------------------------- pose_homographies


def test_identity_pose_is_identity(camera):
    h = pose_homographies(np.zeros(6), camera)
    np.testing.assert_allclose(h, np.eye(3), atol=1e-12)
    h = pose_homographies(np.zeros((4, 2)), camera, axes=("tx", "rz"), origin_yx=(17, 33))
    assert h.shape == (4, 3, 3)
    np.testing.assert_allclose(h, np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-12)


@pytest.mark.parametrize("tx, ty", [(3.0, 0.0), (0.0, -2.5), (1.25, 7.0)])
def test_translation_moves_content_by_exactly_that(camera, points, tx, ty):
    h = pose_homographies([tx, ty], camera, axes=("tx", "ty"))
    np.testing.assert_allclose(_apply(h, points), points + [tx, ty], atol=1e-10)
    # the same in a tile frame: a translation does not care where the tile is
    h = pose_homographies([tx, ty], camera, axes=("tx", "ty"), origin_yx=(40, 70))
    np.testing.assert_allclose(_apply(h, points), points + [tx, ty], atol=1e-10)


def test_inverse_is_the_inverse(camera, points):
    pose = [2.0, -1.5, 0.03, 0.4, -0.6, 1.7]
    h = pose_homographies(pose, camera)
    h_inv = pose_homographies(pose, camera, inverse=True)
    np.testing.assert_allclose(h @ h_inv / (h @ h_inv)[2, 2], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(_apply(h_inv, _apply(h, points)), points, atol=1e-9)
    assert h_inv[2, 2] == pytest.approx(1.0)


def test_batch_shape_and_normalisation(camera):
    rng = np.random.default_rng(2)
    poses = rng.normal(0, [2, 2, 0.02, 0.5, 0.5, 1], size=(3, 5, 6))
    h = pose_homographies(poses, camera)
    assert h.shape == (3, 5, 3, 3)
    np.testing.assert_allclose(h[..., 2, 2], 1.0)
    for idx in np.ndindex(3, 5):
        np.testing.assert_allclose(h[idx], pose_homographies(poses[idx], camera), atol=1e-12)


@pytest.mark.parametrize("origin_yx", [(0, 0), (40, 70), (-13.5, 250.0)])
def test_tile_origin_is_conjugation_by_translation(camera, points, origin_yx):
    """H_tile = T(-o) H T(o): a point's mapping in tile coordinates is the global
    mapping shifted into the tile."""
    pose = [1.5, -2.0, 0.02, 0.7, -0.4, 2.5]
    h_global = pose_homographies(pose, camera)
    h_tile = pose_homographies(pose, camera, origin_yx=origin_yx)
    o_xy = np.array([origin_yx[1], origin_yx[0]], dtype=np.float64)
    tile_points = points - o_xy
    np.testing.assert_allclose(_apply(h_tile, tile_points), _apply(h_global, points) - o_xy, atol=1e-9)
    t = np.array([[1.0, 0, o_xy[0]], [0, 1.0, o_xy[1]], [0, 0, 1.0]])
    expected = np.linalg.inv(t) @ h_global @ t
    np.testing.assert_allclose(h_tile, expected / expected[2, 2], atol=1e-12)
    # and the inverse maps of both frames agree the same way
    h_tile_inv = pose_homographies(pose, camera, origin_yx=origin_yx, inverse=True)
    np.testing.assert_allclose(_apply(h_tile_inv, _apply(h_tile, tile_points)), tile_points, atol=1e-9)


@pytest.mark.parametrize("rz", [-5.0, 1.0, 30.0])
def test_rz_rotates_about_principal_point(camera, rz):
    h = pose_homographies([rz], camera, axes=("rz",))
    c = np.array(camera.center_xy)
    np.testing.assert_allclose(_apply(h, c), c, atol=1e-10)
    # a point 10 px right of the centre turns towards +y by rz
    a = np.deg2rad(rz)
    np.testing.assert_allclose(_apply(h, c + [10.0, 0.0]), c + 10.0 * np.array([np.cos(a), np.sin(a)]), atol=1e-10)
    # distances to the centre are preserved
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 200, (20, 2))
    np.testing.assert_allclose(np.linalg.norm(_apply(h, p) - c, axis=1), np.linalg.norm(p - c, axis=1), atol=1e-9)


def test_rz_in_a_tile_rotates_about_the_whole_image_centre(camera):
    origin_yx = (30, 50)
    h = pose_homographies([4.0], camera, axes=("rz",), origin_yx=origin_yx)
    c_tile = np.array(camera.center_xy) - [origin_yx[1], origin_yx[0]]
    np.testing.assert_allclose(_apply(h, c_tile), c_tile, atol=1e-10)


@pytest.mark.parametrize("ry", [-2.0, 0.5, 3.0])
def test_ry_moves_centre_by_f_tan(camera, ry):
    h = pose_homographies([ry], camera, axes=("ry",))
    c = np.array(camera.center_xy)
    moved = _apply(h, c) - c
    assert moved[0] == pytest.approx(camera.focal * np.tan(np.deg2rad(ry)), rel=1e-9)
    assert moved[1] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("rx", [-2.0, 1.0])
def test_rx_moves_centre_by_f_tan_in_y(camera, rx):
    h = pose_homographies([rx], camera, axes=("rx",))
    c = np.array(camera.center_xy)
    moved = _apply(h, c) - c
    assert moved[1] == pytest.approx(camera.focal * np.tan(np.deg2rad(rx)), rel=1e-9)
    assert moved[0] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("s", [-0.1, 0.05])
def test_scale_about_principal_point(camera, points, s):
    h = pose_homographies([s], camera, axes=("s",))
    c = np.array(camera.center_xy)
    np.testing.assert_allclose(_apply(h, points), c + (1 + s) * (points - c), atol=1e-10)


def test_axes_subset_equals_full_pose(camera):
    h_sub = pose_homographies([[1.0, 2.0]], camera, axes=("rz", "tx"))
    h_full = pose_homographies([[2.0, 0.0, 0.0, 0.0, 0.0, 1.0]], camera)
    np.testing.assert_allclose(h_sub, h_full, atol=1e-12)


# ---------------------------------------------------------------- full_poses


def test_full_poses_places_axes():
    out = full_poses([[1.0, 2.0], [3.0, 4.0]], ("rz", "tx"))
    assert out.shape == (2, 6)
    np.testing.assert_array_equal(out[:, POSE_AXES.index("rz")], [1.0, 3.0])
    np.testing.assert_array_equal(out[:, POSE_AXES.index("tx")], [2.0, 4.0])
    assert np.count_nonzero(out[:, [1, 2, 3, 4]]) == 0


@pytest.mark.parametrize("axes, match", [
    (("tx", "yaw"), "yaw"),
    (("tx", "tx"), r"'tx', 'tx'"),
])
def test_full_poses_bad_axes_named(axes, match):
    with pytest.raises(ParameterError, match=match) as info:
        full_poses(np.zeros(2), axes)
    assert "axes" in str(info.value)
    assert isinstance(info.value, ValueError) and isinstance(info.value, RSMBError)


def test_full_poses_wrong_last_dimension_names_axes():
    with pytest.raises(ParameterError, match=r"\('tx', 'ty'\)") as info:
        full_poses(np.zeros((4, 3)), ("tx", "ty"))
    assert "(4, 3)" in str(info.value)


def test_pose_homographies_passes_axis_errors(camera):
    with pytest.raises(ParameterError, match="roll"):
        pose_homographies([1.0], camera, axes=("roll",))
