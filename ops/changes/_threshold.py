"""Kapur's threshold of a change score (e.g. ``|chi|``, METHOD.md section 3 step 4).

- :func:`kapur_threshold`: Kapur, Sahoo & Wong (1985) maximum-entropy histogram threshold,
  the threshold the paper applies to ``|chi|``; :func:`kapur_threshold_histogram`
  does the same from a ready histogram (e.g. one summed over tiles).

The mask clean-up that follows the threshold (components, minimum area, holes)
is :mod:`._changes`.
"""

from __future__ import annotations

import math

import numpy as np

from rsmb.ops._errors import ParameterError

__all__ = ["kapur_threshold", "kapur_threshold_histogram"]


def _xlogx(p: np.ndarray) -> np.ndarray:
    """Elementwise ``p * ln(p)`` with ``0 ln 0 = 0``, float64."""
    out = np.zeros_like(p, dtype=np.float64)
    pos = p > 0
    out[pos] = p[pos] * np.log(p[pos])
    return out


def _kapur_entropy(hist: np.ndarray) -> np.ndarray:
    """Total entropy ``H_A(t) + H_B(t)`` for every split ``t`` of a histogram.

    Class A holds bins ``0..t``, class B bins ``t+1..B-1``. With ``P_t`` the cumulative
    probability and ``S_t = sum_{i<=t} p_i ln p_i``:
    ``H_A = ln P_t - S_t / P_t`` and ``H_B = ln(1 - P_t) - (S_tot - S_t) / (1 - P_t)``.
    Splits leaving one class empty get ``-inf``. Returns shape (B - 1,) (t = 0..B-2).
    """
    p = hist.astype(np.float64) / float(hist.sum())
    cum_p = np.cumsum(p)[:-1]
    plogp = _xlogx(p)
    cum_s = np.cumsum(plogp)[:-1]
    s_tot = float(plogp.sum())
    q = 1.0 - cum_p
    ok = (cum_p > 0) & (q > 1e-12)
    total = np.full(cum_p.shape, -np.inf)
    pa, qb, sa = cum_p[ok], q[ok], cum_s[ok]
    total[ok] = np.log(pa) - sa / pa + np.log(qb) - (s_tot - sa) / qb
    return total


def _plateau_centre(total: np.ndarray) -> tuple[int, int]:
    """First and last index of the run of maxima that contains the first maximum.

    Empty bins after a split leave the entropy unchanged, so the maximum is usually a
    plateau spanning a gap of the histogram; the threshold goes to its middle.
    """
    best = float(np.max(total))
    tol = 1e-12 * max(1.0, abs(best))
    at_max = total >= best - tol
    first = int(np.argmax(at_max))
    run = np.flatnonzero(~at_max[first:])
    last = first + (int(run[0]) - 1 if run.size else at_max.size - 1 - first)
    return first, last


def kapur_threshold(values, *, bins: int = 256, value_range=None) -> float:
    """Maximum-entropy threshold of Kapur, Sahoo & Wong (1985).

    The histogram of ``values`` is split into a low class (bins ``0..t``) and a high
    class (bins ``t+1..``); the split maximising the sum of the two class entropies
    ``H_A(t) + H_B(t)`` (each computed on the class-normalised histogram) is chosen.
    This is the threshold applied to ``|chi|`` in METHOD.md section 3, step 4.

    Parameters
    ----------
    values : array_like, any shape (flattened)
        Scores, e.g. ``|chi|`` in image intensity units. Non-finite values (NaN,
        +-inf, nodata already turned into NaN) are ignored.
    bins : int, optional
        Number of histogram bins, >= 2. Default 256.
    value_range : (float, float), optional
        ``(lo, hi)`` span of the histogram, in the units of ``values``. Values outside
        it are clipped into the end bins (so a long tail still counts as "high").
        Default: the finite minimum and maximum of ``values``.

    Returns
    -------
    float
        Threshold in the units of ``values``: pixels with ``values > threshold`` are the
        high class. It is a histogram bin edge; when the optimum is a plateau (empty
        bins between the classes) the middle of the plateau is returned. Degenerate
        inputs return ``+inf`` ("nothing above"): no finite value, all values equal
        (or within one bin), or a zero-width ``value_range``.

    Raises
    ------
    ParameterError
        If ``bins`` < 2 or ``value_range`` is not an increasing finite pair.

    References
    ----------
    J. N. Kapur, P. K. Sahoo, A. K. C. Wong, "A new method for gray-level picture
    thresholding using the entropy of the histogram", CVGIP 29(3), 1985.
    """
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 2:
        raise ParameterError(f"bins: expected an integer >= 2, got {bins!r}")
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if value_range is None:
        if v.size == 0:
            return math.inf
        lo, hi = float(v.min()), float(v.max())
    else:
        try:
            lo, hi = (float(x) for x in value_range)
        except (TypeError, ValueError) as exc:
            raise ParameterError(
                f"value_range: expected a pair (lo, hi) of numbers, got {value_range!r}"
            ) from exc
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ParameterError(
                f"value_range: expected finite lo <= hi, got {value_range!r}"
            )
    if v.size == 0 or not hi > lo:
        return math.inf
    hist, edges = np.histogram(np.clip(v, lo, hi), bins=int(bins), range=(lo, hi))
    return kapur_threshold_histogram(hist, edges)


def kapur_threshold_histogram(hist, edges) -> float:
    """:func:`kapur_threshold` of an already binned histogram.

    Same criterion as :func:`kapur_threshold`, for histograms built elsewhere, e.g.
    summed over tiles so that every tile gets the threshold of the whole image.

    Parameters
    ----------
    hist : array_like of non-negative numbers, shape (B,)
        Counts, B >= 2 (for example summed over the tiles of a mosaic).
    edges : array_like, shape (B + 1,)
        Strictly increasing bin edges, in value units.

    Returns
    -------
    float
        Threshold in the units of ``edges``: values above it are the high class. A bin
        edge, or the middle of a plateau of optimal edges (empty bins between the
        classes). ``+inf`` ("nothing above") for an empty histogram or when no split
        leaves two non-empty classes (all mass in one bin).

    Raises
    ------
    ParameterError
        If the shapes disagree, ``hist`` has negative or non-finite counts, or
        ``edges`` is not strictly increasing.
    """
    counts = np.asarray(hist, dtype=np.float64)
    e = np.asarray(edges, dtype=np.float64)
    if counts.ndim != 1 or counts.size < 2:
        raise ParameterError(
            f"hist: expected a 1-D histogram of >= 2 bins, got shape {counts.shape}"
        )
    if e.shape != (counts.size + 1,):
        raise ParameterError(
            f"edges: expected shape ({counts.size + 1},) for {counts.size} bins, got {e.shape}"
        )
    if not np.all(np.isfinite(counts)) or np.any(counts < 0):
        raise ParameterError("hist: expected finite, non-negative counts")
    if not (np.all(np.isfinite(e)) and np.all(np.diff(e) > 0)):
        raise ParameterError("edges: expected finite, strictly increasing bin edges")
    if counts.sum() <= 0:
        return math.inf
    total = _kapur_entropy(counts)
    if not np.any(np.isfinite(total)):
        # every value falls in one bin: no split has two non-empty classes
        return math.inf
    first, last = _plateau_centre(total)
    return float(0.5 * (e[first + 1] + e[last + 1]))
