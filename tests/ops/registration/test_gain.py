"""The gain slope's compiled fit and fold against the rules written out in numpy."""

from types import SimpleNamespace

import numpy as np
import pytest

from rsmb.ops import optimal_chi
from rsmb.ops.registration._gain import _column_offsets, _fold_gain, _gain_slope


def _numpy_rule(out, dist, delta, iterations=8):
    """Iteratively reweighted Huber regression of ``dist - registered`` on
    ``registered * u`` over the valid pixels of every other row."""
    valid = out.valid & np.isfinite(out.registered)
    u = _column_offsets(dist.shape[1])
    sample = valid.copy()
    sample[1::2] = False
    reg = out.registered[sample].astype(np.float64)
    y = dist[sample] - reg
    z = reg * np.broadcast_to(u, dist.shape)[sample]
    b = 0.0
    for _ in range(iterations):
        w = np.minimum(1.0, delta / np.maximum(np.abs(y - b * z), 1e-12))
        b = float(np.sum(w * z * y)) / float(np.sum(w * z * z))
    return 1.0 + b * u


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_fit_is_the_huber_rule(seed):
    rng = np.random.default_rng(seed)
    h, w = 64, 96
    registered = rng.uniform(0.2, 0.8, (h, w)).astype(np.float32)
    slope = rng.uniform(-2e-3, 2e-3)
    dist = (registered * (1.0 + slope * _column_offsets(w)) + rng.normal(0, 0.01, (h, w))).astype(np.float32)
    dist[rng.random((h, w)) < 0.05] += 0.5  # outliers the Huber weights turn down
    valid = rng.random((h, w)) > 0.1
    registered[rng.random((h, w)) < 0.05] = np.nan
    out = SimpleNamespace(registered=registered, valid=valid)
    got = _gain_slope(out, dist, 0.02)
    want = _numpy_rule(out, dist, 0.02)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    assert abs(got[-1] - got[0] - slope * (w - 1)) < 0.1 * abs(slope * (w - 1)) + 2e-3


def test_no_fit_on_too_few_pixels_or_without_a_slope_to_weigh():
    out = SimpleNamespace(registered=np.ones((8, 8), np.float32), valid=np.zeros((8, 8), bool))
    assert _gain_slope(out, np.ones((8, 8), np.float32), 0.02) is None
    out = SimpleNamespace(registered=np.zeros((16, 16), np.float32), valid=np.ones((16, 16), bool))
    assert _gain_slope(out, np.ones((16, 16), np.float32), 0.02) is None


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_compiled_fold_is_the_rule(dtype):
    rng = np.random.default_rng(7)
    h, w = 32, 48
    registered = rng.uniform(0.0, 1.0, (h, w)).astype(np.float32)
    registered[rng.random((h, w)) < 0.1] = np.nan
    valid = rng.random((h, w)) > 0.2
    dist = rng.uniform(0.0, 1.0, (h, w)).astype(dtype)
    factor = 1.0 + 1e-3 * _column_offsets(w)
    ok = valid & np.isfinite(registered)
    want_registered = np.where(ok, registered * factor, registered).astype(np.float32)
    want_chi = optimal_chi(np.where(ok, dist - want_registered, 0.0), lambda_chi=2 * 0.03).astype(np.float32)
    before = registered.copy()
    out = SimpleNamespace(registered=registered, valid=valid, chi=None)
    _fold_gain(out, dist, factor, 0.03)
    np.testing.assert_array_equal(out.registered, want_registered)
    np.testing.assert_array_equal(out.chi, want_chi)
    np.testing.assert_array_equal(registered, before)  # a new array: the one it was given is kept
