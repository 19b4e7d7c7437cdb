"""Evaluation metrics: change-detection confusion counts and trajectory errors.

Change-detection metrics follow the CDnet 2014 convention (METHOD.md section 5):
precision ``TP/(TP+FP)``, recall ``TP/(TP+FN)``, PWC ``100 (FN+FP)/total``,
F-measure ``2 Pr Re / (Pr + Re)``. Counts are plain Python ints so that they can be
pooled over tiles with ``+`` before any ratio is taken; a ratio whose denominator is 0
is ``nan`` and never raises.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rsmb.ops._errors import InputError, ParameterError

__all__ = ["ConfusionCounts", "confusion", "trajectory_rmse"]


def _ratio(num: float, den: float) -> float:
    """``num / den`` as a Python float, ``nan`` when ``den`` is 0."""
    return float(num) / float(den) if den != 0 else math.nan


@dataclass(frozen=True)
class ConfusionCounts:
    """Pixel counts of a binary change map against the truth.

    Attributes
    ----------
    tp, fp, fn, tn : int
        True positives (changed, detected), false positives (unchanged, detected),
        false negatives (changed, missed) and true negatives, in pixels.

    Notes
    -----
    ``a + b`` pools two count sets (e.g. two tiles); ``sum(counts, ConfusionCounts())``
    pools a list. Every ratio property returns ``float('nan')`` when its
    denominator is 0.
    """

    tp: int = 0
    fp: int = 0
    fn: int = 0
    tn: int = 0

    def __post_init__(self) -> None:
        for name in ("tp", "fp", "fn", "tn"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ParameterError(
                    f"ConfusionCounts.{name}: expected a non-negative integer, got {value!r}"
                )
            if value < 0:
                raise ParameterError(
                    f"ConfusionCounts.{name}: expected a non-negative integer, got {value}"
                )
            object.__setattr__(self, name, int(value))

    def __add__(self, other: ConfusionCounts) -> ConfusionCounts:
        if not isinstance(other, ConfusionCounts):
            return NotImplemented
        return ConfusionCounts(
            tp=self.tp + other.tp,
            fp=self.fp + other.fp,
            fn=self.fn + other.fn,
            tn=self.tn + other.tn,
        )

    def __radd__(self, other: object) -> ConfusionCounts:
        # lets the builtin ``sum(list_of_counts)`` start from 0
        if isinstance(other, int) and not isinstance(other, bool) and other == 0:
            return self
        return NotImplemented

    @property
    def total(self) -> int:
        """Number of counted pixels."""
        return self.tp + self.fp + self.fn + self.tn

    @property
    def precision(self) -> float:
        """``TP / (TP + FP)``; nan when nothing was detected."""
        return _ratio(self.tp, self.tp + self.fp)

    @property
    def recall(self) -> float:
        """``TP / (TP + FN)``; nan when the truth holds no change."""
        return _ratio(self.tp, self.tp + self.fn)

    @property
    def pwc(self) -> float:
        """Percentage of wrong classifications, ``100 (FN + FP) / total``; nan if empty."""
        return _ratio(100 * (self.fn + self.fp), self.total)

    @property
    def f_measure(self) -> float:
        """``2 Pr Re / (Pr + Re)``; nan when precision or recall is nan or both are 0."""
        p, r = self.precision, self.recall
        if math.isnan(p) or math.isnan(r):
            return math.nan
        return _ratio(2.0 * p * r, p + r)

    @property
    def iou(self) -> float:
        """Intersection over union of the change class, ``TP / (TP + FP + FN)``."""
        return _ratio(self.tp, self.tp + self.fp + self.fn)

    def as_dict(self) -> dict[str, float | int]:
        """Counts and every ratio, as a flat dict of Python numbers (JSON-ready,
        except that nan must be allowed by the writer)."""
        return {
            "tp": self.tp,
            "fp": self.fp,
            "fn": self.fn,
            "tn": self.tn,
            "total": self.total,
            "precision": self.precision,
            "recall": self.recall,
            "pwc": self.pwc,
            "f_measure": self.f_measure,
            "iou": self.iou,
        }


def _as_mask(name: str, array) -> np.ndarray:
    """Boolean view of a bool or 0/1 array; InputError for any other value."""
    a = np.asarray(array)
    if a.dtype == bool:
        return a
    if not (np.issubdtype(a.dtype, np.number)):
        raise InputError(f"{name}: expected a boolean or 0/1 array, got dtype {a.dtype}")
    bad = (a != 0) & (a != 1)
    if np.any(bad):
        raise InputError(
            f"{name}: expected a boolean or 0/1 array, got values such as "
            f"{a[bad].flat[0]!r}"
        )
    return a != 0


def confusion(predicted, truth, *, valid=None) -> ConfusionCounts:
    """Confusion counts of a predicted change mask against the true one.

    Parameters
    ----------
    predicted : ndarray of bool or {0, 1}, any shape, e.g. (H, W)
        Detected change pixels.
    truth : ndarray of bool or {0, 1}, same shape as ``predicted``
        True change pixels.
    valid : ndarray of bool or {0, 1}, same shape, optional
        Pixels to count; pixels where ``valid`` is False (nodata, borders) are left
        out of every count. Default: all pixels.

    Returns
    -------
    ConfusionCounts
        Counts as Python ints; pool tiles with ``+``.

    Raises
    ------
    ParameterError
        If the shapes differ.
    InputError
        If an array holds values other than 0/1 (or False/True).
    """
    predicted_arr = np.asarray(predicted)
    truth_arr = np.asarray(truth)
    if predicted_arr.shape != truth_arr.shape:
        raise ParameterError(
            f"predicted and truth: expected equal shapes, got predicted "
            f"{predicted_arr.shape} and truth {truth_arr.shape}"
        )
    p = _as_mask("predicted", predicted_arr)
    t = _as_mask("truth", truth_arr)
    if valid is not None:
        valid_arr = np.asarray(valid)
        if valid_arr.shape != p.shape:
            raise ParameterError(
                f"valid: expected the shape of predicted {p.shape}, got {valid_arr.shape}"
            )
        v = _as_mask("valid", valid_arr)
        p = p[v]
        t = t[v]
    tp = int(np.count_nonzero(p & t))
    fp = int(np.count_nonzero(p & ~t))
    fn = int(np.count_nonzero(~p & t))
    tn = int(p.size) - tp - fp - fn
    return ConfusionCounts(tp=tp, fp=fp, fn=fn, tn=tn)


def trajectory_rmse(
    estimated, truth, *, axes: Sequence[str], valid_rows=None
) -> dict[str, dict[str, float | int]]:
    """Per-axis error of an estimated camera trajectory (one pose per image row).

    Parameters
    ----------
    estimated : ndarray, shape (H, D)
        Estimated pose of each row (e.g. the row centroids ``c_i`` of METHOD.md
        section 3), in the units of each axis (pixels for ``tx``/``ty``, degrees for
        rotations).
    truth : ndarray, shape (H, D)
        True pose of each row, same units.
    axes : sequence of str, length D
        Axis names, in column order (e.g. ``("tx", "ty")``).
    valid_rows : ndarray of bool, shape (H,), optional
        Rows to evaluate. Rows holding a NaN in ``estimated`` or ``truth`` (on any
        axis, e.g. a skipped homogeneous row) are always left out.

    Returns
    -------
    dict
        ``{axis: {"rmse": float, "max_abs": float, "mean": float, "n_rows": int}}``
        where ``mean`` is the mean signed error ``estimated - truth`` (a bias). With
        no usable row every value is nan and ``n_rows`` is 0.

    Raises
    ------
    ParameterError
        If shapes disagree with each other, with ``axes`` or with ``valid_rows``.
    """
    est = np.asarray(estimated, dtype=np.float64)
    tru = np.asarray(truth, dtype=np.float64)
    axes = tuple(axes)
    if est.ndim != 2 or est.shape != tru.shape:
        raise ParameterError(
            f"estimated and truth: expected two arrays of equal shape (H, D), got "
            f"estimated {est.shape} and truth {tru.shape}"
        )
    if len(axes) != est.shape[1]:
        raise ParameterError(
            f"axes: expected {est.shape[1]} names (one per column of estimated), "
            f"got {len(axes)}: {axes!r}"
        )
    if len(set(axes)) != len(axes):
        raise ParameterError(f"axes: expected distinct names, got {axes!r}")
    use = np.all(np.isfinite(est), axis=1) & np.all(np.isfinite(tru), axis=1)
    if valid_rows is not None:
        vr = np.asarray(valid_rows)
        if vr.shape != (est.shape[0],):
            raise ParameterError(
                f"valid_rows: expected shape ({est.shape[0]},), got {vr.shape}"
            )
        use &= _as_mask("valid_rows", vr)
    err = est[use] - tru[use]
    n = int(err.shape[0])
    out: dict[str, dict[str, float | int]] = {}
    for j, name in enumerate(axes):
        if n == 0:
            out[name] = {"rmse": math.nan, "max_abs": math.nan, "mean": math.nan, "n_rows": 0}
            continue
        e = err[:, j]
        out[name] = {
            "rmse": float(np.sqrt(np.mean(e * e))),
            "max_abs": float(np.max(np.abs(e))),
            "mean": float(np.mean(e)),
            "n_rows": n,
        }
    return out
