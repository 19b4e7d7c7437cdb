"""Warps of the reference by camera poses, in compiled code: the sampling map of
a pose and the point it carries a capture pixel to, one row warped by many
poses (the columns of ``F_i``), rows gathered from pre-warped images by
whole-pixel shifts, whole windows warped by one pose, and the exposure average
of the forward model.

Shared by the forward model (:mod:`ops._forward`) and the row solvers, so that
both use one camera model; bilinear interpolation, NaN marks nodata.
"""

import math

import numba
import numpy as np

__all__ = []

_JIT = dict(nogil=True, cache=True)


@numba.njit(**_JIT)
def _inverse_map(pose6, focal, cx, cy):
    """Coefficients of the sampling map of one pose (observed -> reference).

    Returns (m, tx, ty, scale) with m the 3x3 matrix K R^T K^-1 (row-major, 9).
    """
    tx, ty, s = pose6[0], pose6[1], pose6[2]
    ax, ay, az = math.radians(pose6[3]), math.radians(pose6[4]), math.radians(pose6[5])
    cxr, sxr, cyr, syr, czr, szr = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    # R = Rz Ry Rx (see ops._camera._rotations)
    r = np.empty((3, 3))
    # Ry Rx
    a00, a01, a02 = cyr, -syr * sxr, syr * cxr
    a10, a11, a12 = 0.0, cxr, sxr
    a20, a21, a22 = -syr, -cyr * sxr, cyr * cxr
    r[0, 0] = czr * a00 - szr * a10
    r[0, 1] = czr * a01 - szr * a11
    r[0, 2] = czr * a02 - szr * a12
    r[1, 0] = szr * a00 + czr * a10
    r[1, 1] = szr * a01 + czr * a11
    r[1, 2] = szr * a02 + czr * a12
    r[2, 0], r[2, 1], r[2, 2] = a20, a21, a22
    m = np.empty(9)
    # K R^T K^-1
    m[0], m[1], m[2] = r[0, 0], r[1, 0], r[2, 0] * focal
    m[3], m[4], m[5] = r[0, 1], r[1, 1], r[2, 1] * focal
    m[6], m[7], m[8] = r[0, 2] / focal, r[1, 2] / focal, r[2, 2]
    return m, tx, ty, 1.0 + s


@numba.njit(**_JIT)
def _bilinear(ref, u, v):
    """``ref`` (Hr, Wr) at the point (u, v) (column, row), bilinear; NaN
    outside it or on no-data."""
    hr, wr = ref.shape
    if not (u >= 0.0 and v >= 0.0 and u <= wr - 1 and v <= hr - 1):
        return math.nan
    iu = min(int(u), wr - 2)
    iv = min(int(v), hr - 2)
    fu = u - iu
    fv = v - iv
    top = ref[iv, iu] * (1.0 - fu) + ref[iv, iu + 1] * fu
    bot = ref[iv + 1, iu] * (1.0 - fu) + ref[iv + 1, iu + 1] * fu
    return top * (1.0 - fv) + bot * fv


@numba.njit(**_JIT)
def _row_line(m, tx, ty, sc, y, x0, cx, cy):
    """A pose's inverse map (:func:`_inverse_map`) along output row ``y``
    from column ``x0``: ``h = m @ (ux, uy, 1)`` with ``ux = (x - cx - tx) /
    sc`` is linear in the column offset ``j``, ``h = (h0, h1, h2) + j * (d0,
    d1, d2)``, and the sample sits at ``(h0 / h2 + cx, h1 / h2 + cy)``."""
    uy = (y - cy - ty) / sc
    ux0 = (x0 - cx - tx) / sc
    du = 1.0 / sc
    h0 = m[0] * ux0 + m[1] * uy + m[2]
    h1 = m[3] * ux0 + m[4] * uy + m[5]
    h2 = m[6] * ux0 + m[7] * uy + m[8]
    return h0, h1, h2, m[0] * du, m[3] * du, m[6] * du


@numba.njit(**_JIT)
def _build_row(ref, y, x0, poses6, focal, cx, cy, out):
    """Fill ``out`` (K, N) with row ``y`` of the reference warped by each pose.

    ``ref`` (Hr, Wr) float32 may hold NaN for nodata.  ``y``, ``x0``, ``cx``,
    ``cy`` are in the reference window's pixel frame.  Returns uint8 (N,) with 1
    where every pose samples valid reference data; columns of invalid pixels are
    set to zero.
    """
    k_count, n = out.shape
    valid = np.ones(n, dtype=np.uint8)
    for k in range(k_count):
        m, tx, ty, sc = _inverse_map(poses6[k], focal, cx, cy)
        h0, h1, h2, d0, d1, d2 = _row_line(m, tx, ty, sc, y, x0, cx, cy)
        for j in range(n):
            inv = 1.0 / (h2 + j * d2)
            u = (h0 + j * d0) * inv + cx
            v = (h1 + j * d1) * inv + cy
            val = _bilinear(ref, u, v)
            if math.isnan(val):
                valid[j] = 0
                out[k, j] = 0.0
            else:
                out[k, j] = val
    for j in range(n):
        if valid[j] == 0:
            for k in range(k_count):
                out[k, j] = 0.0
    return valid


@numba.njit(**_JIT)
def _remap_rows(src, poses, focal, cx, cy, width, oy, ox):
    """Average over each row's pose samples of the warped source row.

    ``poses`` (H, S, 6); ``cx``, ``cy`` the principal point in the source frame;
    row ``i`` of the output is row ``i + oy`` of the source frame, column ``j``
    is ``j + ox``.  Returns (image float32 (H, W), valid uint8 (H, W)).
    """
    h, s = poses.shape[0], poses.shape[1]
    out = np.empty((h, width), dtype=np.float32)
    valid = np.empty((h, width), dtype=np.uint8)
    buf = np.empty((s, width), dtype=np.float32)
    for i in range(h):
        valid[i] = _build_row(src, i + oy, ox, poses[i], focal, cx, cy, buf)
        for j in range(width):
            acc = 0.0
            for q in range(s):
                acc += buf[q, j]
            out[i, j] = acc / s
    return out, valid


@numba.njit(**_JIT)
def _gather_row(stack, slot, shift_y, shift_x, y, x0, out):
    """Fill ``out`` (K, N) from pre-warped images: pose k reads
    ``stack[slot[k], y - shift_y[k], x0 + j - shift_x[k]]``.

    This is exact for poses whose translation is a whole number of pixels: the
    translation is applied last in the camera model, so a translated pose samples
    the image warped by the rest of the pose at a shifted pixel.  NaN marks
    invalid data.  Returns uint8 (N,) validity as :func:`_build_row`.
    """
    return _gather_valid(stack, slot, shift_y, shift_x, y, x0, out, np.ones(out.shape[1], np.bool_))


@numba.njit(**_JIT)
def _gather_valid(stack, slot, shift_y, shift_x, y, x0, out, keep):
    """:func:`_gather_row` with the pixels ``keep`` (N,) bool leaves out
    (the capture's invalid ones) invalid too: returns uint8 (N,), 1 where
    ``keep`` holds and every pose reads a finite value, and ``out``'s columns
    are zero wherever it is 0.

    Two passes over the poses: the first finds the valid pixels (each
    pose's pixels inside the image checked for NaN), the second writes each
    pose's row once, its value where valid and 0 elsewhere.  Every loop runs
    over slices of its own (the source, the row, the flags), which LLVM
    vectorises; the one pass that copied, checked the copy and zeroed the
    invalid columns after it did not (6x slower on a start search's rows)."""
    k_count, n = out.shape
    hr, wr = stack.shape[1], stack.shape[2]
    valid = np.empty(n, dtype=np.uint8)
    for j in range(n):
        valid[j] = 1 if keep[j] else 0
    for k in range(k_count):
        r = y - shift_y[k]
        if r < 0 or r >= hr:  # above or below the images: no pixel is valid
            valid[:] = 0
            break  # (so every pose of a row with a valid pixel reads inside them)
        c0 = x0 - shift_x[k]
        lo, hi = _inside(c0, n, wr)
        valid[:lo] = 0
        valid[hi:] = 0
        src, flags = stack[slot[k], r, c0 + lo:c0 + hi], valid[lo:hi]
        for j in range(hi - lo):
            flags[j] &= np.uint8(src[j] == src[j])  # 0 on NaN
    zero = np.float32(0.0)
    if not valid.any():
        out[:, :] = zero
        return valid
    for k in range(k_count):
        r, c0 = y - shift_y[k], x0 - shift_x[k]
        lo, hi = _inside(c0, n, wr)
        out[k, :lo] = zero
        out[k, hi:] = zero
        src, row, flags = stack[slot[k], r, c0 + lo:c0 + hi], out[k, lo:hi], valid[lo:hi]
        for j in range(hi - lo):
            row[j] = src[j] if flags[j] else zero
    return valid


@numba.njit(**_JIT)
def _inside(c0, n, width):
    """The columns ``[lo, hi)`` of a row of ``n`` pixels from column ``c0``
    that lie inside an image ``width`` wide."""
    lo, hi = min(max(-c0, 0), n), max(min(width - c0, n), 0)
    return min(lo, hi), hi


@numba.njit(**_JIT)
def _warp_into(src, poses6, focal, cx, cy, oy, ox, out):
    """``out`` (R, W) = rows ``oy ..`` (columns ``ox ..``) of ``src`` warped by
    ``poses6`` (1, 6): one pose for every row, or (R, 6): row ``q`` by its own
    pose; NaN where a pose samples outside ``src`` or nodata.

    The arithmetic of :func:`_build_row` with one pose, written straight
    into ``out``; where the pose keeps the image plane (no rx, ry: the
    homography's last row is (0, 0, 1)) its division by 1 is left out, which
    changes no bit.  A row's sample points are computed first, in a loop of
    their own (no memory reads: it vectorises, the division included), then
    sampled: the same operations on the same values as one loop doing both."""
    rows, width = out.shape
    m, tx, ty, sc = _inverse_map(poses6[0], focal, cx, cy)
    us, vs = np.empty(width), np.empty(width)
    for q in range(rows):
        if poses6.shape[0] > 1:
            m, tx, ty, sc = _inverse_map(poses6[q], focal, cx, cy)
        row = out[q]
        h0, h1, h2, d0, d1, d2 = _row_line(m, tx, ty, sc, oy + q, ox, cx, cy)
        if d2 == 0.0 and h2 == 1.0:
            for j in range(width):
                us[j] = (h0 + j * d0) + cx
                vs[j] = (h1 + j * d1) + cy
        else:
            for j in range(width):
                inv = 1.0 / (h2 + j * d2)
                us[j] = (h0 + j * d0) * inv + cx
                vs[j] = (h1 + j * d1) * inv + cy
        for j in range(width):
            row[j] = _bilinear(src, us[j], vs[j])


@numba.njit(**_JIT)
def _point(m, tx, ty, sc, x, y, cx, cy):
    """The point (u, v) (column, row) of the reference window that a pose
    (rotation map ``m``, translations ``tx``, ``ty`` px, scale ``sc``)
    carries capture pixel (x, y) to."""
    return _point_on_row(_row_map(m, tx, ty, sc, y, cx, cy), x)


@numba.njit(**_JIT)
def _row_map(m, tx, ty, sc, y, cx, cy):
    """:func:`_point`'s map reduced to capture row ``y``: what
    :func:`_point_on_row` needs for any column of it."""
    uy = (y - cy - ty) / sc
    ch = m[7] * uy + m[8]
    return (m[0], m[3], m[6], m[1] * uy + m[2], m[4] * uy + m[5], ch, cx + tx, 1.0 / sc, cx, cy, 1.0 / ch)


@numba.njit(**_JIT)
def _point_on_row(row, x):
    """:func:`_point` at column ``x`` of the row :func:`_row_map` reduced to
    (the division along the row done once where the pose has no tilt)."""
    m0, m3, m6, cu, cv, ch, x0, inverse_scale, cx, cy, flat_h = row
    ux = (x - x0) * inverse_scale
    h = flat_h if m6 == 0.0 else 1.0 / (m6 * ux + ch)
    return (m0 * ux + cu) * h + cx, (m3 * ux + cv) * h + cy
