"""The whole-window warp against the row warp it shares its arithmetic with."""

import numpy as np
import pytest

from rsmb.ops._warp import _build_row, _warp_into


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
