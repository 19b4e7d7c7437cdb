"""The compiled row loop of the propagation (METHOD.md section 3, step 2) and
the structs it reads and writes.

:func:`_propagate_rows` walks the rows in order, each on the grid
``N(c, b, s)`` around its solved neighbour's centroid: it gathers the row's
``F_i`` from pre-warped images, solves eq. 13 warm-started from the
neighbour's weights (:func:`_row_step`) and follows the path, returning to
Python (:mod:`ops.registration._propagate`) only when it needs a pre-warped image that is
not made yet, leaves the table of them, or sees the path jump.

Every kernel takes its many arrays as a few NamedTuples, grouped by who owns
them: the run (:class:`_Context`), the neighbour a row starts from
(:class:`_Neighbour`), one row (:class:`_Source`, :class:`_Row`) and work space
(:class:`_Work`).
"""

from typing import NamedTuple

import numba
import numpy as np

import math

from .._warp import _inside, _warp_into
from ._rowsolve import SOLVED, _column, _Columns, _solve

__all__ = []

_JIT = dict(nogil=True, cache=True)
_SUMS = dict(nogil=True, cache=True, fastmath={"reassoc", "contract"})

#: numba caches these kernels with the row solver and the row warp compiled
#: into them, keyed on this file alone: a change of
#: :mod:`ops.registration._rowsolve` or of :func:`ops._warp._warp_into` (and
#: what it calls) raises this number, or a checkout that ran the old code
#: keeps running it here.
ROWSOLVE_REVISION = 15

#: A row whose centroid, against where the path before it leads (its last pose
#: plus its velocity), moves the window's pixels by more than this (px)
#: re-anchors the path: some axis alone moves the window's farthest pixel that
#: much, and all axes together move some pixel of the window (a corner:
#: linearised, the poses move the window's pixels affinely) that much.  A trade
#: of rz against tx and ty that leaves the window's pixels in place is no jump;
#: the test of each axis alone stays a condition: a row whose axes add up to a
#: move no single one makes (a path the rows cannot follow, such as an
#: unestimated yaw) is not re-anchored, as block solves pulled such rows away
#: from their own fit.  A block of rows from it on is then solved jointly, as
#: the start block is, on a grid wide enough for both the row's pose and the
#: prediction, and the row is solved again around the block's centroid.  A
#: camera path moves a pixel by a small fraction of this from one row to the
#: next; a row that jumps is a real turn of the path or a fit that a change or
#: an ambiguity (rz against ty on a single row) has pulled into a wrong basin,
#: from which the rows after it could not climb out.  One row cannot tell the
#: two apart (its own eq. 13 cost can be lower in the wrong basin); a block
#: can.
DRIFT_PX = 0.75
#: ... plus this much (px) per row since the last row on the path: the
#: velocity the prediction extrapolates is itself uncertain.
DRIFT_PX_PER_ROW = 0.1


# ----------------------------------------------------------------- the run's structs


class _Settings(NamedTuple):
    """The row solver's settings: eq. 13's ``lambda_w``, the Huber knee
    ``lambda_chi / 2``, the KKT tolerance, iteration limits and the fewest
    valid pixels a row needs."""

    lam: float
    delta: float
    tol: float
    max_outer: int
    max_add: int
    min_valid: int


class _Prewarp(NamedTuple):
    """The pre-warped images (stack (S, rows, cols) float32) and the table of
    their slots by (other-axis lattice index - other_lo, band - band_lo), -1
    where not made yet; bands of ``band`` rows with ``pad`` rows above and
    below, columns offset by ``margin``.  Each slot holds the rows ``warped``
    (S, 2) [lo, hi) so far; the others are warped when a row first reads them
    (:func:`_warp_rows`): the reference window ``ref`` (Hr, Wr) float32 by the
    slot's pose of each row ``pose6`` (S, rows, 6), its first row at
    ``row0`` (S,) and its first column at ``col0`` of the reference window,
    with the camera's ``focal``, ``cx``, ``cy`` in that window's frame."""

    stack: np.ndarray
    table: np.ndarray
    other_lo: int
    band_lo: int
    band: int
    pad: int
    margin: int
    warped: np.ndarray
    ref: np.ndarray
    pose6: np.ndarray
    row0: np.ndarray
    col0: float
    focal: float
    cx: float
    cy: float


class _Lattice(NamedTuple):
    """The row neighbourhood: lattice offsets (K, D) int64, counts per axis,
    steps per axis, the dimensions of ty, tx and the one other axis (-1 when
    absent), per axis the pixels a unit moves the window's farthest pixel
    (:func:`ops.registration._propagate._px_per_unit`), and how a unit of each
    axis moves each corner of the window
    (:func:`ops.registration._propagate._corner_shifts`)."""

    offsets: np.ndarray
    counts: np.ndarray
    step: np.ndarray
    ty_dim: int
    tx_dim: int
    other_dim: int
    px_per_unit: np.ndarray
    corner_shifts: np.ndarray


class _Capture(NamedTuple):
    """The distorted window (H, W) float32, its validity and the informative
    rows (H,) bool."""

    dist: np.ndarray
    dist_valid: np.ndarray
    informative: np.ndarray


class _RowOutputs(NamedTuple):
    """Per-row outputs the propagation writes: registered, chi, valid (H, W);
    trajectory (H, D); row_state, row_gain (H,); weights (H, K) and lattice
    centres (H, D) of every solved row."""

    registered: np.ndarray
    chi: np.ndarray
    valid: np.ndarray
    trajectory: np.ndarray
    row_state: np.ndarray
    row_gain: np.ndarray
    weights: np.ndarray
    centers: np.ndarray


class _Context(NamedTuple):
    """Everything the compiled propagation shares across rows: read
    (``prewarp``, ``lattice``, ``settings``, ``capture``) and written
    (``out``)."""

    prewarp: _Prewarp
    lattice: _Lattice
    settings: _Settings
    capture: _Capture
    out: _RowOutputs


# ------------------------------------------------------------ one row's structs


class _Gather(NamedTuple):
    """Where each pose k of a grid reads ``F_i``: pre-warped image ``slot[k]``
    shifted by whole pixels ``shift_y[k]``, ``shift_x[k]`` (int64 (K,) each)."""

    slot: np.ndarray
    shift_y: np.ndarray
    shift_x: np.ndarray


class _Source(NamedTuple):
    """Where one row reads ``F_i``: pose k reads row ``y - gather.shift_y[k]``
    of ``stack[gather.slot[k]]`` from column ``x0 - gather.shift_x[k]`` on
    (stack (S, rows, cols) float32)."""

    stack: np.ndarray
    gather: _Gather
    y: int
    x0: int


class _Row(NamedTuple):
    """One row of the capture, ``g`` (N,) float32 and its validity (N,) bool,
    and the rows of the outputs it writes: registered, chi (N,) float32, valid
    (N,) bool."""

    g: np.ndarray
    g_valid: np.ndarray
    registered: np.ndarray
    chi: np.ndarray
    valid: np.ndarray


class _Neighbour(NamedTuple):
    """The solved row a row starts from: its centroid pose (D,), the lattice
    centre of its grid (D,) int64 and its weights (K,) on that grid."""

    centroid: np.ndarray
    center: np.ndarray
    weights: np.ndarray


class _Work(NamedTuple):
    """Work space of one row, overwritten by each: ``F_i`` (K, N) float32, the
    weights (K,), the lattice centre of the grid (D,) int64 and where its poses
    read (:class:`_Gather`)."""

    a: np.ndarray
    w: np.ndarray
    center: np.ndarray
    gather: _Gather


# ------------------------------------------------------------------------ kernels


@numba.njit(**_SUMS)
def _lattice_columns(source, g_valid, a):
    """The columns of ``F_i`` of one row (:class:`ops.registration._rowsolve._Columns`)
    without gathering them: the distinct pre-warped rows the poses shift
    (a few per row of the lattice's other axes), copied once with their no-data
    (NaN, outside the image) at 0, and the pixels every pose reads valid and
    the capture has (``g_valid``); ``a`` (K, N) is the work space the solve
    copies its working set into.  Pose k reads row ``source.y -
    gather.shift_y[k]`` of ``stack[gather.slot[k]]`` from column ``source.x0
    - gather.shift_x[k]`` on, as :func:`ops._warp._gather_row` does."""
    stack, gather = source.stack, source.gather
    slot, sy, sx = gather.slot, gather.shift_y, gather.shift_x
    k_count, n = a.shape
    hr, wr = stack.shape[1], stack.shape[2]
    lo, hi = sx[0], sx[0]
    for k in range(k_count):
        lo, hi = min(lo, sx[k]), max(hi, sx[k])
    width = n + hi - lo
    row_of, col_of = np.zeros(k_count, np.int64), np.empty(k_count, np.int64)
    pick = np.empty(k_count, np.int64)
    valid = g_valid.copy()
    # (slot, row) -> distinct row, in a table over the slots and the rows
    # this row's poses read only (a few of each), numbered in pose order
    used = np.full(stack.shape[0], -1, np.int64)  # slot -> its place among the slots read
    slots, r_lo, r_hi = 0, hr, -1
    for k in range(k_count):
        r = source.y - sy[k]
        if 0 <= r < hr:
            if used[slot[k]] < 0:
                used[slot[k]] = slots
                slots += 1
            r_lo, r_hi = min(r_lo, r), max(r_hi, r)
    span = max(r_hi - r_lo + 1, 0)
    first = np.full(slots * span, -1, np.int64)
    distinct = 0
    for k in range(k_count):
        r = source.y - sy[k]
        col_of[k] = hi - sx[k]
        if r < 0 or r >= hr:  # a pose above or below the band: no pixel is valid
            valid[:] = False
            continue
        key = used[slot[k]] * span + r - r_lo
        if first[key] < 0:
            first[key] = distinct
            pick[distinct] = slot[k] * hr + r
            distinct += 1
        row_of[k] = first[key]
    src = np.empty((max(distinct, 1), width), np.float32)
    x0 = source.x0 - hi
    good = np.empty((max(distinct, 1), width), np.bool_)  # False on no-data and beyond the image
    spoilt = np.zeros(max(distinct, 1), np.bool_)
    inside_lo, inside_hi = _inside(x0, width, wr)  # columns [inside_lo, inside_hi) lie inside the image
    if distinct == 0:
        src[:] = 0.0
        good[:] = True
    for q in range(distinct):
        img = stack[pick[q] // hr, pick[q] % hr]
        if inside_lo > 0 or inside_hi < width:
            spoilt[q] = True
            src[q, :inside_lo] = 0.0
            src[q, inside_hi:] = 0.0
            good[q, :inside_lo] = False
            good[q, inside_hi:] = False
        if _copy_finite(img[x0 + inside_lo:x0 + inside_hi], src[q, inside_lo:inside_hi],
                        good[q, inside_lo:inside_hi]):
            spoilt[q] = True
    if spoilt.any():
        _mark_no_data(good, spoilt, _shifts_of(row_of, col_of, sy, source.y, hr, distinct, hi - lo), valid)
    return _Columns(src, row_of, col_of, valid, a, np.zeros(k_count, np.bool_))


@numba.njit(**_JIT)
def _copy_finite(img, out, good):
    """``out`` = ``img`` where it is finite, 0 at NaN (no-data), ``good`` =
    where it is finite; returns whether any was NaN.  One branch-free loop
    over the row (vectorised), where a test of bounds and NaN per pixel was
    not."""
    nan = 0
    for c in range(img.shape[0]):
        v = img[c]
        ok = not math.isnan(v)
        out[c] = v if ok else np.float32(0.0)
        good[c] = ok
        nan += 0 if ok else 1
    return nan > 0


@numba.njit(**_JIT)
def _shifts_of(row_of, col_of, sy, y, hr, distinct, span):
    """(distinct, span + 1) bool: at which columns ``col_of`` (in [0, span])
    the poses read each distinct row."""
    shifts = np.zeros((distinct, span + 1), np.bool_)
    for k in range(row_of.shape[0]):
        if 0 <= y - sy[k] < hr:
            shifts[row_of[k], col_of[k]] = True
    return shifts


@numba.njit(**_JIT)
def _mark_no_data(good, spoilt, shifts, valid):
    """``valid`` (N,) False at every pixel some pose reads from a no-data
    pixel: pixel j of a pose reading distinct row q at column s is
    ``good[q, j + s]``.  The ``spoilt`` rows read at every shift any row is
    read at (the usual case: the lattice's tx offsets) are ANDed together
    first, so the shifts are applied once for all of them; each other
    spoilt row applies its own."""
    n = valid.shape[0]
    distinct, span = shifts.shape
    every = np.zeros(span, np.bool_)
    for q in range(distinct):
        for s in range(span):
            every[s] |= shifts[q, s]
    common = np.ones(good.shape[1], np.bool_)
    for q in range(distinct):
        if not spoilt[q]:
            continue
        usual = True
        for s in range(span):
            usual &= shifts[q, s] == every[s]
        for s in range(span):
            if usual:
                break
            if shifts[q, s]:
                for j in range(n):
                    valid[j] &= good[q, j + s]
        if usual:
            for c in range(good.shape[1]):
                common[c] &= good[q, c]
    for s in range(span):
        if every[s]:
            for j in range(n):
                valid[j] &= common[j + s]


@numba.njit(**_SUMS)
def _row_step(source, row, settings, w, a):
    """One row of the propagation in a single call (no Python in between):
    the row's columns of ``F_i`` from ``source`` (:func:`_lattice_columns`,
    ``a`` (K, N) their work space), eq. 13 solved warm-started from ``w`` (in
    place), and the registered row, the change term and the validity written
    into ``row`` (NaN / 0 / False where invalid).  Returns (objective, valid
    pixel count, whether the solve met its optimality conditions,
    :data:`ops.registration._rowsolve.SOLVED`); the objective is inf when too
    few pixels are valid to solve.
    """
    k_count, n = a.shape
    delta = settings.delta
    g_row = row.g
    reg_out, chi_out, valid_out = row.registered, row.chi, row.valid
    cols = _lattice_columns(source, row.g_valid, a)
    g = np.empty(n)
    count = 0
    for j in range(n):
        ok = cols.valid[j]
        valid_out[j] = ok
        if ok:
            g[j] = g_row[j]
            count += 1
        else:
            g[j] = 0.0
    if count < settings.min_valid:
        for k in range(k_count):
            w[k] = 0.0
        for j in range(n):
            valid_out[j] = False
            reg_out[j] = np.nan
            chi_out[j] = 0.0
        return np.inf, count, True
    obj, _, _, status = _solve(cols, g, w, settings.lam, delta, settings.tol, settings.max_outer, settings.max_add)
    reg = np.zeros(n)
    for k in range(k_count):
        if w[k] > 0.0:
            ak = _column(cols, k)
            for j in range(n):
                reg[j] += w[k] * ak[j]
    for j in range(n):
        if valid_out[j]:
            reg_out[j] = reg[j]
            r = g_row[j] - reg[j]
            if r > delta:
                chi_out[j] = r - delta
            elif r < -delta:
                chi_out[j] = r + delta
            else:
                chi_out[j] = 0.0
        else:
            reg_out[j] = np.nan
            chi_out[j] = 0.0
    return obj, count, status == SOLVED


@numba.njit(**_JIT)
def _warp_rows(prewarp, slot, r):
    """Make row ``r`` of pre-warped image ``slot`` readable: warp the rows
    between it and those warped so far (they stay one range)."""
    lo, hi = prewarp.warped[slot, 0], prewarp.warped[slot, 1]
    if lo >= hi:
        lo, hi = r, r
    a, b = (r, lo) if r < lo else (hi, r + 1)
    _warp_into(prewarp.ref, prewarp.pose6[slot, a:b], prewarp.focal, prewarp.cx, prewarp.cy,
               float(prewarp.row0[slot] + a), prewarp.col0, prewarp.stack[slot, a:b])
    prewarp.warped[slot, 0], prewarp.warped[slot, 1] = min(lo, a), max(hi, b)


@numba.njit(**_SUMS)
def _solve_at(ctx, i, neighbour, work):
    """Solve row ``i`` on the grid ``N(neighbour.centroid, b, s)``,
    warm-started from the neighbour's weights shifted onto it.  Writes the
    row's outputs and ``work.w``, ``work.center``, ``work.gather``.  Returns
    (status, other lattice index, band, cost per valid pixel, valid count,
    negative when the solve stopped at its iteration limit): status 0 solved,
    1 a pre-warped image is missing, 2 the grid left the table."""
    prewarp, lattice, capture, out = ctx.prewarp, ctx.lattice, ctx.capture, ctx.out
    table, other_lo, band_lo = prewarp.table, prewarp.other_lo, prewarp.band_lo
    offsets, counts, step = lattice.offsets, lattice.counts, lattice.step
    ty_dim, tx_dim, other_dim = lattice.ty_dim, lattice.tx_dim, lattice.other_dim
    k_count, dims = offsets.shape
    pose, prev_center, w_prev = neighbour.centroid, neighbour.center, neighbour.weights
    w, center = work.w, work.center
    slot, sy, sx = work.gather.slot, work.gather.shift_y, work.gather.shift_x
    for d in range(dims):
        center[d] = np.int64(np.round(pose[d] / step[d]))
    cy = np.int64(np.round(center[ty_dim] * step[ty_dim])) if ty_dim >= 0 else 0
    bnd = (i + prewarp.margin - cy) // prewarp.band
    y = i + prewarp.margin - (bnd * prewarp.band - prewarp.pad)
    b = bnd - band_lo
    for k in range(k_count):
        if ty_dim >= 0:
            sy[k] = np.int64(np.round((center[ty_dim] + offsets[k, ty_dim]) * step[ty_dim]))
        if tx_dim >= 0:
            sx[k] = np.int64(np.round((center[tx_dim] + offsets[k, tx_dim]) * step[tx_dim]))
        o = center[other_dim] + offsets[k, other_dim] - other_lo if other_dim >= 0 else 0
        if o < 0 or o >= table.shape[0] or b < 0 or b >= table.shape[1]:
            return 2, o + other_lo, bnd, 0.0, 0
        if table[o, b] < 0:
            return 1, o + other_lo, bnd, 0.0, 0
        slot[k] = table[o, b]
    warped, rows = prewarp.warped, prewarp.stack.shape[1]
    for k in range(k_count):  # the rows this row reads, warped if not yet
        r = y - sy[k]
        if 0 <= r < rows and not (warped[slot[k], 0] <= r < warped[slot[k], 1]):
            _warp_rows(prewarp, slot[k], r)
    # warm start: new[o] = old[o + (center - prev_center)]
    for k in range(k_count):
        w[k] = 0.0
        src = 0
        inside = True
        for d in range(dims):
            m = offsets[k, d] + counts[d] // 2 + center[d] - prev_center[d]
            if m < 0 or m >= counts[d]:
                inside = False
                break
            src = src * counts[d] + m
        if inside:
            w[k] = w_prev[src]
    source = _Source(prewarp.stack, work.gather, y, prewarp.margin)
    row = _Row(capture.dist[i], capture.dist_valid[i], out.registered[i], out.chi[i], out.valid[i])
    objective, count, converged = _row_step(source, row, ctx.settings, w, work.a)
    return 0, 0, 0, objective / max(count, 1), count if converged else -count


@numba.njit(**_SUMS)
def _centroid_of(w, center, offsets, step, out):
    """``out`` (D,) = the centroid pose of weights ``w`` on the grid at
    lattice ``center``; returns their sum."""
    k_count, dims = offsets.shape
    total = 0.0
    for k in range(k_count):
        total += w[k]
    for d in range(dims):
        acc = 0.0
        for k in range(k_count):
            acc += w[k] * offsets[k, d]
        out[d] = (center[d] + acc / total) * step[d] if total > 0.0 else np.nan
    return total


@numba.njit(**_SUMS)
def _propagate_rows(ctx, rows, neighbour, a, trust, anchor):
    """Propagate the trajectory along ``rows`` (in order) from the solved row
    ``neighbour`` (not changed), all in compiled code: per row, the grid
    ``N(c, b, s)`` around the last solved row's centroid ``c``, its pre-warped
    images (``ctx.prewarp.table[other index - other_lo, band - band_lo]``, -1
    if missing), a warm start shifted from the last solved row,
    :func:`_row_step`, the centroid.  ``a`` (K, N) is work space; ``trust``
    (2 D + 2,) carries the path (last pose, velocity per row, its row, 1 when
    the caller has just re-anchored it) across calls.

    Returns (position reached in ``rows``, other-axis lattice index, band,
    status): status 0 done, 1 a pre-warped image is missing (make it and call
    again from that position), 2 the grid left the table (solve that row
    another way), 3 the row's centroid jumped off the path (:func:`_jumps`;
    ``anchor`` (2, D) holds it and the path's prediction): re-anchor the path
    on a block of rows and call again from that position.
    """
    lattice, out = ctx.lattice, ctx.out
    offsets, step = lattice.offsets, lattice.step
    k_count, dims = offsets.shape
    work = _Work(a, np.empty(k_count), np.empty(dims, np.int64),
                 _Gather(np.empty(k_count, np.int64), np.zeros(k_count, np.int64), np.zeros(k_count, np.int64)))
    w, center = work.w, work.center
    c_own, predicted = np.empty(dims), np.empty(dims)
    prev = _Neighbour(neighbour.centroid.copy(), neighbour.center.copy(), neighbour.weights.copy())
    for pos in range(rows.shape[0]):
        i = rows[pos]
        if not ctx.capture.informative[i]:
            out.row_state[i] = 2
            continue
        status, o, bnd, cost, count = _solve_at(ctx, i, prev, work)
        if status != 0:
            return pos, o, bnd, status
        total = _centroid_of(w, center, offsets, step, c_own)
        for k in range(k_count):
            out.weights[i, k] = w[k]
        for d in range(dims):
            out.centers[i, d] = center[d]
        out.row_gain[i] = total
        if total <= 0.0 or count <= 0:  # nothing fitted, or unconverged: failed
            out.row_state[i] = 3
            if total > 0.0 and count < 0:
                # its fit, though not certified, still centres the next row's
                # grid better than a row further back (that row is checked
                # on its own); the path and its trust are not moved
                for d in range(dims):
                    prev.centroid[d] = c_own[d]
                prev.center[:] = center
                prev.weights[:] = w
            continue
        if trust[2 * dims + 1] == 0.0 and _jumps(c_own, i, lattice.px_per_unit, lattice.corner_shifts, trust,
                                                 predicted):
            anchor[0] = c_own
            anchor[1] = predicted
            return pos, 0, 0, 3  # off the path: the caller re-anchors on a block of rows
        _follow(c_own, i, trust)
        for d in range(dims):
            prev.centroid[d] = c_own[d]
            out.trajectory[i, d] = c_own[d]
        out.row_state[i] = 1
        prev.center[:] = center
        prev.weights[:] = w
    return rows.shape[0], 0, 0, 0


# ----------------------------------------------------------------------- the path


@numba.njit(**_SUMS)
def _jumps(centroid, row, px_per_unit, corner_shifts, trust, predicted):
    """Whether ``centroid`` of ``row`` is off the path's prediction, written
    to ``predicted``: by more than :data:`DRIFT_PX` (plus
    :data:`DRIFT_PX_PER_ROW` per row since) both on some axis alone (its
    difference times ``px_per_unit``, what a unit moves the window's farthest
    pixel) and all axes together (the largest move of a window corner,
    ``corner_shifts``: :func:`ops.registration._propagate._corner_shifts`).
    ``trust`` (2 D + 2,) = (last pose (D), its velocity per row (D), its row,
    a re-anchor flag)."""
    dims = centroid.shape[0]
    gap = row - trust[2 * dims]
    limit = DRIFT_PX + DRIFT_PX_PER_ROW * (abs(gap) - 1)
    alone = 0.0
    for d in range(dims):
        predicted[d] = trust[d] + trust[dims + d] * gap
        alone = max(alone, abs(centroid[d] - predicted[d]) * px_per_unit[d])
    if not alone > limit:
        return False
    together = 0.0
    for c in range(corner_shifts.shape[0]):
        du, dv = 0.0, 0.0
        for d in range(dims):
            du += corner_shifts[c, 0, d] * (centroid[d] - predicted[d])
            dv += corner_shifts[c, 1, d] * (centroid[d] - predicted[d])
        together = max(together, math.hypot(du, dv))
    return together > limit


@numba.njit(**_SUMS)
def _follow(centroid, row, trust):
    """The trusted path moves on to ``centroid`` at ``row``; its velocity is a
    slow average of its steps."""
    dims = centroid.shape[0]
    gap = row - trust[2 * dims]
    if gap != 0:
        for d in range(dims):
            trust[dims + d] = 0.8 * trust[dims + d] + 0.2 * (centroid[d] - trust[d]) / gap
    for d in range(dims):
        trust[d] = centroid[d]
    trust[2 * dims] = row
    trust[2 * dims + 1] = 0.0


def _trust_state(centroid, row):
    """The initial ``trust`` of :func:`_jumps`: the path at ``row``, at rest."""
    dims = len(centroid)
    return np.concatenate([np.asarray(centroid, np.float64), np.zeros(dims), [float(row), 0.0]])
