import math

import numpy as np
import pytest

from rsmb.ops._errors import InputError, ParameterError, RSMBError
from rsmb.ops.changes._metrics import ConfusionCounts, confusion, trajectory_rmse


def test_confusion_counts_known_masks():
    truth = np.zeros((4, 5), bool)
    truth[1:3, 1:4] = True  # 6 changed pixels
    predicted = np.zeros((4, 5), bool)
    predicted[1:3, 2:5] = True  # 6 detected, 4 of them right
    c = confusion(predicted, truth)
    assert (c.tp, c.fp, c.fn, c.tn) == (4, 2, 2, 12)
    assert all(type(v) is int for v in (c.tp, c.fp, c.fn, c.tn))
    assert c.precision == pytest.approx(4 / 6)
    assert c.recall == pytest.approx(4 / 6)
    assert c.f_measure == pytest.approx(4 / 6)
    assert c.pwc == pytest.approx(100 * 4 / 20)
    assert c.iou == pytest.approx(4 / 8)


def test_confusion_accepts_01_arrays_and_valid_mask():
    rng = np.random.default_rng(0)
    p = rng.random((30, 40)) > 0.7
    t = rng.random((30, 40)) > 0.8
    v = rng.random((30, 40)) > 0.2
    c = confusion(p.astype(np.uint8), t.astype(np.float32), valid=v.astype(int))
    assert c == confusion(p[v], t[v])
    assert c.total == int(v.sum())
    assert c.tp == int((p & t & v).sum())
    assert c.fn == int((~p & t & v).sum())


def test_pooling_over_tiles_equals_whole():
    rng = np.random.default_rng(1)
    p = rng.random((64, 48)) > 0.6
    t = rng.random((64, 48)) > 0.7
    tiles = [(slice(0, 20), slice(0, 48)), (slice(20, 64), slice(0, 17)), (slice(20, 64), slice(17, 48))]
    pooled = sum((confusion(p[s], t[s]) for s in tiles), ConfusionCounts())
    assert pooled == confusion(p, t)
    assert sum(confusion(p[s], t[s]) for s in tiles) == confusion(p, t)


def test_ratios_are_nan_not_errors_on_empty_denominators():
    none_detected = confusion(np.zeros((3, 3), bool), np.zeros((3, 3), bool))
    assert none_detected.tn == 9
    assert math.isnan(none_detected.precision)
    assert math.isnan(none_detected.recall)
    assert math.isnan(none_detected.f_measure)
    assert math.isnan(none_detected.iou)
    assert none_detected.pwc == 0.0
    empty = ConfusionCounts()
    assert math.isnan(empty.pwc)
    # precision and recall both 0: F-measure has a 0 denominator
    disjoint = ConfusionCounts(tp=0, fp=3, fn=2, tn=5)
    assert disjoint.precision == 0.0 and disjoint.recall == 0.0
    assert math.isnan(disjoint.f_measure)
    assert disjoint.iou == 0.0


def test_as_dict_has_counts_and_ratios():
    d = ConfusionCounts(tp=3, fp=1, fn=1, tn=5).as_dict()
    assert d["tp"] == 3 and d["total"] == 10
    assert d["precision"] == pytest.approx(0.75)
    assert d["f_measure"] == pytest.approx(0.75)
    assert d["pwc"] == pytest.approx(20.0)
    assert set(d) >= {"precision", "recall", "pwc", "f_measure", "iou"}


def test_confusion_is_frozen_and_checks_counts():
    c = ConfusionCounts(tp=np.int64(2))
    assert type(c.tp) is int
    with pytest.raises(AttributeError):
        c.tp = 3
    with pytest.raises(ParameterError, match="fn"):
        ConfusionCounts(fn=-1)


def test_confusion_shape_mismatch_names_arrays():
    with pytest.raises(ParameterError, match=r"predicted.*truth.*\(3, 4\).*\(4, 3\)"):
        confusion(np.zeros((3, 4), bool), np.zeros((4, 3), bool))
    with pytest.raises(ParameterError, match="valid"):
        confusion(np.zeros((3, 4), bool), np.zeros((3, 4), bool), valid=np.ones((3, 3), bool))
    with pytest.raises(InputError, match="predicted"):
        confusion(np.full((2, 2), 0.5), np.zeros((2, 2), bool))
    with pytest.raises(RSMBError):
        confusion(np.zeros(3, bool), np.zeros(4, bool))


def test_trajectory_rmse_known_errors():
    h = 100
    truth = np.stack([np.linspace(-3, 3, h), np.sin(np.arange(h) / 10.0)], axis=1)
    est = truth.copy()
    est[:, 0] += 0.2  # constant bias on tx
    est[::2, 1] -= 0.5  # ty off by -0.5 on even rows, +0.5 on odd rows
    est[1::2, 1] += 0.5
    out = trajectory_rmse(est, truth, axes=("tx", "ty"))
    assert out["tx"]["rmse"] == pytest.approx(0.2)
    assert out["tx"]["max_abs"] == pytest.approx(0.2)
    assert out["tx"]["mean"] == pytest.approx(0.2)
    assert out["ty"]["rmse"] == pytest.approx(0.5)
    assert out["ty"]["max_abs"] == pytest.approx(0.5)
    assert out["ty"]["mean"] == pytest.approx(0.0, abs=1e-12)
    assert out["tx"]["n_rows"] == h


def test_trajectory_rmse_ignores_nan_rows_and_invalid_rows():
    rng = np.random.default_rng(2)
    truth = rng.normal(size=(50, 3))
    est = truth + 0.1
    est[5] = np.nan  # unsolved row
    est[7, 2] = np.nan  # partly missing row
    est[10] += 100.0  # outlier, masked out below
    valid = np.ones(50, bool)
    valid[10] = False
    out = trajectory_rmse(est, truth, axes=["tx", "ty", "rz"], valid_rows=valid)
    for axis in ("tx", "ty", "rz"):
        assert out[axis]["rmse"] == pytest.approx(0.1)
        assert out[axis]["n_rows"] == 47
    nothing = trajectory_rmse(np.full((4, 1), np.nan), np.zeros((4, 1)), axes=["tx"])
    assert math.isnan(nothing["tx"]["rmse"]) and nothing["tx"]["n_rows"] == 0


def test_trajectory_rmse_checks_shapes():
    with pytest.raises(ParameterError, match="axes"):
        trajectory_rmse(np.zeros((5, 2)), np.zeros((5, 2)), axes=["tx"])
    with pytest.raises(ParameterError, match="estimated"):
        trajectory_rmse(np.zeros((5, 2)), np.zeros((4, 2)), axes=["tx", "ty"])
    with pytest.raises(ParameterError, match="valid_rows"):
        trajectory_rmse(np.zeros((5, 2)), np.zeros((5, 2)), axes=["tx", "ty"], valid_rows=np.ones(4, bool))
