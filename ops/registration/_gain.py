"""Illumination along the rows: eq. 13 gives each row one gain (``||w_i||_1``);
a gain that varies across a row (vignetting, a slow gradient over a wide-area
mosaic) is fitted as a slope, divided out of the capture before the rows are
solved again, and folded back into the registered image."""

import numba
import numpy as np


__all__ = []


GAIN_SLOPE_RESOLVE = 0.05  # relative gain change at the row ends that triggers another solve


def _column_gain_guess(ref, dist, dvalid, ref_origin, dist_origin, blocks=16):
    """A first guess of the gain slope along the rows from the median brightness
    of column blocks of the capture against the same columns of the reference
    (motion moves content far less than a block; a robust line through the
    block ratios): the factor ``1 + b u`` per
    column when it moves the row ends by more than GAIN_SLOPE_RESOLVE, else None."""
    height, width = dist.shape
    dy, dx = dist_origin[0] - ref_origin[0], dist_origin[1] - ref_origin[1]
    if width < 4 * blocks or dy < 0 or dx < 0:
        return None
    same = ref[dy:dy + height, dx:dx + width]
    if same.shape != dist.shape:
        return None
    edges = np.linspace(0, width, blocks + 1).astype(int)
    offsets = _column_offsets(width)
    u, ratio = [], []
    for c0, c1 in zip(edges[:-1], edges[1:]):
        d, r = dist[:, c0:c1][dvalid[:, c0:c1]], same[:, c0:c1]
        r = r[np.isfinite(r)]
        if d.size > 100 and r.size > 100 and np.median(r) > 0:
            u.append(offsets[c0:c1].mean())
            ratio.append(np.median(d) / np.median(r))
    if len(u) < 4:
        return None
    # Theil-Sen line: blocks holding changed objects are outvoted
    u, ratio = np.array(u), np.array(ratio)
    i, j = np.triu_indices(len(u), 1)
    slope = float(np.median((ratio[j] - ratio[i]) / (u[j] - u[i])))
    level = float(np.median(ratio - slope * u))
    factor = 1.0 + slope / level * offsets
    if level <= 0 or factor.min() <= 0.25 or np.abs(factor - 1.0).max() <= GAIN_SLOPE_RESOLVE:
        return None
    return factor


def _gain_slope(out, dist, delta, iterations=8):
    """Fit ``g = R (1 + b u)`` (u the column offset from the window centre) by
    iteratively reweighted Huber regression on every other row: the factor
    ``1 + b u`` per column, or None without enough pixels or for a slope that
    would flip the sign."""
    valid = out.valid & np.isfinite(out.registered)
    if valid.sum() < 100:
        return None
    u = _column_offsets(dist.shape[1])
    b = _huber_slope(out.registered, valid, dist, u, float(delta), iterations)
    if not np.isfinite(b):
        return None
    factor = 1.0 + b * u
    return factor if factor.min() > 0.25 else None


@numba.njit(nogil=True, cache=True)
def _huber_slope(registered, valid, dist, u, delta, iterations):
    """:func:`_gain_slope`'s ``b``, in float64, over the ``valid`` pixels of
    rows 0, 2, 4...: the residual ``y = dist - registered`` against
    ``z = registered * u``, each of ``iterations`` rounds weighting a pixel
    ``min(1, delta / |y - b z|)`` (Huber) and solving for ``b``; NaN when the
    weighted ``z`` vanish."""
    height, width = dist.shape
    n = 0
    for i in range(0, height, 2):
        for j in range(width):
            n += valid[i, j]
    y, z = np.empty(n), np.empty(n)
    k = 0
    for i in range(0, height, 2):
        for j in range(width):
            if valid[i, j]:
                reg = np.float64(registered[i, j])
                y[k] = dist[i, j] - reg
                z[k] = reg * u[j]
                k += 1
    b = 0.0
    for _ in range(iterations):
        num, den = 0.0, 0.0
        for k in range(n):
            w = min(1.0, delta / max(abs(y[k] - b * z[k]), 1e-12))
            den += w * z[k] * z[k]
            num += w * z[k] * y[k]
        if not den > 0:
            return np.nan
        b = num / den
    return b


def _column_offsets(width):
    """Column offsets from the window centre, the ``u`` of the gain slope."""
    return np.arange(width) - (width - 1) / 2.0


def _fold_gain(out, dist, factor, delta):
    """Multiply the registered image by the per-column gain ``factor`` and
    recompute the change term (``chi`` soft-thresholded at ``delta``, 0 where
    the registration has no value)."""
    registered, chi = out.registered.astype(np.float32), np.empty(dist.shape, np.float32)
    _fold(registered, out.valid, dist, np.asarray(factor, np.float64), float(delta), chi)
    out.registered, out.chi = registered, chi


@numba.njit(nogil=True, cache=True)
def _fold(registered, valid, dist, factor, delta, chi):
    """:func:`_fold_gain` in one pass, in place: where ``valid`` and finite,
    ``registered *= factor`` (per column, rounded to float32 once) and
    ``chi = sign(r) max(|r| - delta, 0)`` of ``r = dist - registered``;
    elsewhere ``chi = 0``."""
    height, width = dist.shape
    for i in range(height):
        for j in range(width):
            value = registered[i, j]
            if valid[i, j] and np.isfinite(value):
                value = np.float32(value * factor[j])
                registered[i, j] = value
                r = dist[i, j] - value
                chi[i, j] = np.sign(r) * max(abs(r) - delta, 0.0)
            else:
                chi[i, j] = 0.0
