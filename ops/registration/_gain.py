"""Illumination along the rows: eq. 13 gives each row one gain (``||w_i||_1``);
a gain that varies across a row (vignetting, a slow gradient over a wide-area
mosaic) is fitted as a slope, divided out of the capture before the rows are
solved again, and folded back into the registered image."""

import numpy as np

from .._oracle import optimal_chi

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
    iteratively reweighted Huber regression: the factor ``1 + b u`` per column,
    or None without enough pixels or for a slope that would flip the sign."""
    valid = out.valid & np.isfinite(out.registered)
    if valid.sum() < 100:
        return None
    u = _column_offsets(dist.shape[1])
    sample = valid.copy()
    sample[1::2] = False  # every other row is plenty for one parameter
    reg = out.registered[sample].astype(np.float64)
    y = dist[sample] - reg
    z = reg * np.broadcast_to(u, dist.shape)[sample]
    b = 0.0
    for _ in range(iterations):
        r = y - b * z
        wts = np.minimum(1.0, delta / np.maximum(np.abs(r), 1e-12))
        den = float(np.sum(wts * z * z))
        if den <= 0:
            return None
        b = float(np.sum(wts * z * y)) / den
    factor = 1.0 + b * u
    return factor if factor.min() > 0.25 else None


def _column_offsets(width):
    """Column offsets from the window centre, the ``u`` of the gain slope."""
    return np.arange(width) - (width - 1) / 2.0


def _fold_gain(out, dist, factor, delta):
    """Multiply the registered image by the per-column gain ``factor`` and
    recompute the change term."""
    valid = out.valid & np.isfinite(out.registered)
    out.registered = np.where(valid, out.registered * factor, out.registered).astype(np.float32)
    r = dist - out.registered
    out.chi = optimal_chi(np.where(valid, r, 0.0), lambda_chi=2 * delta).astype(np.float32)
