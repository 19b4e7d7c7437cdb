"""Rows and blocks fit the pixels their model explains: a compact raised
structure (a roof, nearer than the ground, so moved farther) does not pull
the weights or the path after it."""

import numpy as np
import pytest

from rsmb import ops
from rsmb.ops.registration._propagate_kernels import UNEXPLAINED_KNEES, _Settings, _solve_explained
from rsmb.ops.registration._rowsolve import SOLVED, _Columns

LAMBDA_W, DELTA = 1e-3, 0.01


def _row_with_a_roof(seed):
    """Columns of a row at whole-pixel shifts -3..3 of a low-contrast ground
    with a flat bright roof; the capture sees the ground at shift 0 and the
    roof (a quarter of the row) moved 3 px farther, uncovering ground the
    reference does not show."""
    rng = np.random.default_rng(seed)
    n, margin = 160, 8
    ground = 0.4 + np.convolve(rng.normal(0, 0.03, n + 2 * margin), np.ones(3) / 3, "same")
    roof = np.zeros(n + 2 * margin, bool)
    roof[margin + 60:margin + 100] = True
    scene = np.where(roof, 0.85, ground)
    shifts = np.arange(-3, 4)
    a = np.stack([scene[margin - s:margin - s + n] for s in shifts]).astype(np.float32)
    hidden = 0.4 + rng.normal(0, 0.03, n + 2 * margin)
    g = np.where(np.roll(roof, 3), 0.85, np.where(roof, hidden, ground))[margin:margin + n]
    return a, g, shifts


def _solve(a, g, knees):
    k, n = a.shape
    cols = _Columns(a, np.arange(k), np.zeros(k, np.int64), np.ones(n, bool), np.empty_like(a), np.zeros(k, bool))
    settings = _Settings(LAMBDA_W, DELTA, 1e-7, 100, 8, 16, knees * DELTA)
    w = np.zeros(k)
    _, status = _solve_explained(cols, g, w, settings, np.empty(n))
    assert status == SOLVED
    return w


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_roof_pulls_eq13_but_not_the_fit_to_the_explained_pixels(seed):
    a, g, shifts = _row_with_a_roof(seed)
    plain = _solve(a, g, np.inf)  # eq. 13 as written: every pixel pulls
    trimmed = _solve(a, g, UNEXPLAINED_KNEES)
    assert (plain @ shifts) / plain.sum() > 1.5  # pulled most of the way to the roof's 3 px
    assert abs((trimmed @ shifts) / trimmed.sum()) < 0.05  # on the ground's 0
    assert trimmed.sum() == pytest.approx(1.0, abs=0.02)


SHAPE, EXPOSURE = (384, 384), 20.0


def _path():
    t = np.linspace(0.0, SHAPE[0] + EXPOSURE + 1.0, 32)
    poses = np.zeros((t.size, 6))
    poses[:, 0] = np.linspace(15.0, 19.0, t.size)
    poses[:, 1] = np.linspace(3.0, 6.0, t.size)
    return ops.CameraPath(t, poses)


def test_the_path_follows_the_ground_among_many_roofs():
    """Twelve roofs cover up to a quarter of some bands of rows and move 1.25
    to 2.5 times as far as the ground: the trajectory stays on the ground's
    (the truth's).  (Fitted to every pixel, the path followed the roofs here,
    off by a median of 15 px.)"""
    pair = ops.synthesize_pair(SHAPE, path=_path(), exposure=EXPOSURE, changes=5, noise=0.002, seed=41,
                               interpolation="cubic", structures=12, depths=(0.4, 0.8))
    assert max(pair.parallax_mask[r:r + 16].mean() for r in range(0, SHAPE[0], 16)) > 0.15
    params = ops.RegistrationParams().resolved(pair.camera)
    reg = ops.register(pair.reference, pair.distorted, camera=pair.camera, params=params)
    solved = reg.row_state == 1
    assert solved.mean() > 0.95
    error = np.hypot(*(reg.trajectory[solved, :2] - pair.trajectory[solved][:, :2]).T)
    assert error.max() < 1.0 and np.median(error) < 0.1, (error.max(), np.median(error))
