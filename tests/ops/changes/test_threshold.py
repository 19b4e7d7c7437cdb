import math

import numpy as np
import pytest

from rsmb import ops
from rsmb.ops._errors import ParameterError
from rsmb.ops.changes._threshold import (
    _kapur_entropy,
    kapur_threshold,
    kapur_threshold_histogram,
)


def _kapur_bruteforce(hist):
    """Loop-over-splits Kapur entropy, straight from the 1985 definition."""
    p = hist / hist.sum()
    out = np.full(len(p) - 1, -np.inf)
    for t in range(len(p) - 1):
        a, b = p[: t + 1], p[t + 1:]
        pa, pb = a.sum(), b.sum()
        if pa <= 0 or pb <= 1e-12:
            continue
        qa, qb = a[a > 0] / pa, b[b > 0] / pb
        out[t] = -(qa * np.log(qa)).sum() - (qb * np.log(qb)).sum()
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_vectorised_entropy_matches_definition(seed):
    rng = np.random.default_rng(seed)
    hist = rng.integers(0, 50, 64).astype(float)
    hist[rng.integers(0, 64, 10)] = 0  # empty bins
    fast = _kapur_entropy(hist)
    slow = _kapur_bruteforce(hist)
    finite = np.isfinite(slow)
    assert np.array_equal(np.isfinite(fast), finite)
    np.testing.assert_allclose(fast[finite], slow[finite], rtol=1e-10, atol=1e-12)


def test_kapur_separates_noise_from_changes():
    """|chi|-like scores: a large near-zero population and a few large values."""
    rng = np.random.default_rng(3)
    background = np.abs(rng.normal(0.0, 0.02, 20000))
    changes = rng.uniform(0.3, 0.6, 600)
    t = kapur_threshold(np.concatenate([background, changes]))
    assert background.max() < 0.3
    assert 0.05 < t < 0.3
    assert np.mean(changes > t) == 1.0
    assert np.mean(background > t) < 0.005  # ~3 sigma of the noise


def test_kapur_two_spikes_threshold_in_the_gap_middle():
    values = np.r_[np.full(100, 0.1), np.full(50, 0.9)]
    t = kapur_threshold(values, bins=100, value_range=(0.0, 1.0))
    # optimum is a plateau over the empty bins: its middle, ~0.5
    assert t == pytest.approx(0.5, abs=0.02)


def test_kapur_histogram_equals_values_version_and_tiles_sum():
    rng = np.random.default_rng(4)
    v = np.concatenate([rng.gamma(2.0, 0.01, 5000), rng.uniform(0.2, 0.4, 300)])
    edges = np.linspace(0.0, 0.5, 129)
    hist = np.histogram(v, edges)[0]
    assert kapur_threshold_histogram(hist, edges) == kapur_threshold(v, bins=128, value_range=(0.0, 0.5))
    halves = np.histogram(v[:2000], edges)[0] + np.histogram(v[2000:], edges)[0]
    assert kapur_threshold_histogram(halves, edges) == kapur_threshold_histogram(hist, edges)


def test_kapur_value_range_clips_tail_into_last_bin():
    rng = np.random.default_rng(5)
    v = np.concatenate([np.abs(rng.normal(0, 0.02, 5000)), np.full(200, 5.0)])
    t = kapur_threshold(v, value_range=(0.0, 1.0))
    assert 0.0 < t < 1.0
    assert np.all(v[-200:] > t)


@pytest.mark.parametrize("values", [np.array([]), np.full(100, 0.3), np.array([np.nan, np.inf]),
                                    np.array([0.2])])
def test_kapur_degenerate_inputs_return_inf(values):
    t = kapur_threshold(values)
    assert t == math.inf
    assert not np.any(values[np.isfinite(values)] > t)


def test_kapur_degenerate_histograms():
    edges = np.linspace(0, 1, 11)
    assert kapur_threshold_histogram(np.zeros(10), edges) == math.inf
    one = np.zeros(10)
    one[3] = 7
    assert kapur_threshold_histogram(one, edges) == math.inf
    assert kapur_threshold(np.full(10, 0.3), value_range=(0.3, 0.3)) == math.inf


def test_kapur_parameter_errors():
    with pytest.raises(ParameterError, match="bins"):
        kapur_threshold([0.1, 0.2], bins=1)
    with pytest.raises(ParameterError, match="value_range"):
        kapur_threshold([0.1, 0.2], value_range=(1.0, 0.0))
    with pytest.raises(ParameterError, match="edges"):
        kapur_threshold_histogram(np.ones(4), np.linspace(0, 1, 4))
    with pytest.raises(ParameterError, match="hist"):
        kapur_threshold_histogram(np.array([1.0, -1.0]), np.linspace(0, 1, 3))


def test_score_histogram_counts_as_numpy_does():
    """The one-pass histograms against np.histogram on the same values: bin
    edges hit exactly, values past the last edge, NaN, invalid pixels."""
    from rsmb.ops.changes._changes import _RESIDUAL_EDGES, _SCORE_EDGES

    rng = np.random.default_rng(7)
    residual = (rng.standard_normal((60, 70)) * 0.05).astype(np.float32)
    score = np.abs(rng.standard_normal((60, 70))).astype(np.float32)
    residual.flat[:40] = _RESIDUAL_EDGES[rng.integers(0, len(_RESIDUAL_EDGES), 40)]
    residual.flat[40:45] = [4.0, 9.0, -7.5, np.nan, 0.0]
    score.flat[:40] = _SCORE_EDGES[rng.integers(0, len(_SCORE_EDGES), 40)]
    score.flat[40:45] = [2.0, 5.0, np.nan, -1.0, 0.0]
    valid = rng.random((60, 70)) > 0.1
    valid.flat[:45] = True
    got = ops.score_histogram(residual, score, valid)
    r = np.abs(residual[valid]).astype(np.float64)
    c = score[valid].astype(np.float64)
    c = c[c > 0]
    np.testing.assert_array_equal(got.residual, np.histogram(np.clip(r, 0, 4.0), _RESIDUAL_EDGES)[0])
    np.testing.assert_array_equal(got.score, np.histogram(np.clip(c, 0, 2.0), _SCORE_EDGES)[0])
    assert got.residual.sum() == valid.sum() - 1  # the NaN is not counted
