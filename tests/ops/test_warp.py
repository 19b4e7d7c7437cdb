"""The whole-window warp against the row warp it shares its arithmetic with;
the gather from pre-warped images against its definition."""

import numpy as np
import pytest

from rsmb.ops._warp import _build_row, _gather_row, _gather_valid, _warp_into


def _poses():
    """In-plane poses (the homography's last row stays (0, 0, 1)), poses out
    of the plane, and a pose per row."""
    per_row = np.zeros((30, 6))
    per_row[:, 3] = np.linspace(-0.6, 0.4, 30)
    per_row[:, 4] = 0.2
    per_row[:, 5] = 0.3
    return {"identity": np.zeros((1, 6)), "rz": np.array([[0.0, 0.0, 0.0, 0.0, 0.0, -0.8]]),
            "txtys": np.array([[2.5, -1.25, 0.03, 0.0, 0.0, 0.4]]),
            "rxry": np.array([[1.0, 0.5, 0.0, 0.35, -0.5, 0.2]]), "per_row": per_row}


@pytest.mark.parametrize("name", sorted(_poses()))
@pytest.mark.parametrize("oy, ox", [(10.0, 5.0), (-8.0, -12.0), (70.0, 40.0)])
def test_warp_into_equals_build_row_bit_for_bit(name, oy, ox):
    """Each row of the window is the row warp of that row's pose, NaN where
    the row warp marks a pixel invalid (beyond the source, or no-data), bit
    for bit: both are the same arithmetic, whatever the fast paths."""
    rng = np.random.default_rng(17)
    src = rng.uniform(0.0, 1.0, (96, 120)).astype(np.float32)
    src[rng.random(src.shape) < 0.02] = np.nan
    poses6 = _poses()[name]
    rows, width = 30, 110
    out = np.empty((rows, width), np.float32)
    focal, cx, cy = 150.0, 57.5, 45.0
    _warp_into(src, poses6, focal, cx, cy, oy, ox, out)
    buf = np.empty((1, width), np.float32)
    for q in range(rows):
        pose = poses6[:1] if len(poses6) == 1 else poses6[q:q + 1]
        valid = _build_row(src, oy + q, ox, pose, focal, cx, cy, buf)
        expected = np.where(valid.astype(bool), buf[0], np.float32(np.nan))
        np.testing.assert_array_equal(out[q].view(np.uint32), expected.view(np.uint32))
    assert 0.0 < np.isnan(out).mean() < 1.0


def _gathered(stack, slot, shift_y, shift_x, y, x0, n, keep):
    """The gather by its definition, pose by pose and pixel by pixel: pose k's
    pixel j is ``stack[slot[k], y - shift_y[k], x0 + j - shift_x[k]]``; a
    pixel is valid where ``keep`` holds and every pose reads a finite value
    inside the images; invalid pixels are 0 in every pose's column."""
    s, h, w = stack.shape
    out = np.zeros((len(slot), n), np.float32)
    valid = keep.copy()
    for k in range(len(slot)):
        r = y - shift_y[k]
        for j in range(n):
            c = x0 + j - shift_x[k]
            if 0 <= r < h and 0 <= c < w and np.isfinite(stack[slot[k], r, c]):
                out[k, j] = stack[slot[k], r, c]
            else:
                valid[j] = False
    out[:, ~valid] = 0.0
    return out, valid


@pytest.mark.parametrize("seed", range(6))
def test_gather_valid_is_the_gather_by_definition(seed):
    """Every pixel equal bit for bit (a copy or 0), validity equal, with
    no-data in the images, poses reading beyond their edges and above or
    below them, and pixels the capture leaves out (``keep``); ``_gather_row``
    is the same with every pixel kept.  Whatever ``out`` held before."""
    rng = np.random.default_rng(seed)
    stack = rng.normal(size=(3, 12, 40)).astype(np.float32)
    stack[rng.random(stack.shape) < (0.0, 0.01, 0.1)[seed % 3]] = np.nan
    k, n = 25, 36
    slot = rng.integers(0, 3, k)
    shift_y = rng.integers(-2, 3, k) if seed != 5 else rng.integers(-9, 10, k)  # seed 5: rows beyond the images
    shift_x = rng.integers(-6, 7, k)
    keep = rng.random(n) > (0.0, 0.05, 0.5)[seed % 3]
    y, x0 = int(rng.integers(2, 10)), int(rng.integers(-3, 8))
    want, want_valid = _gathered(stack, slot, shift_y, shift_x, y, x0, n, keep)
    out = rng.normal(size=(k, n)).astype(np.float32)
    valid = _gather_valid(stack, slot, shift_y, shift_x, y, x0, out, keep)
    np.testing.assert_array_equal(valid.astype(bool), want_valid)
    assert out.tobytes() == want.tobytes()
    out = rng.normal(size=(k, n)).astype(np.float32)
    valid = _gather_row(stack, slot, shift_y, shift_x, y, x0, out)
    want, want_valid = _gathered(stack, slot, shift_y, shift_x, y, x0, n, np.ones(n, bool))
    np.testing.assert_array_equal(valid.astype(bool), want_valid)
    assert out.tobytes() == want.tobytes()
