"""Propagation of the trajectory row by row (METHOD.md section 3, step 2): each
row searches ``N(c, b, s)`` around the centroid of its solved neighbour,
warm-started from the neighbour's weights shifted onto its own grid.

The loop over rows runs in compiled code (:func:`_propagate_rows`) and returns
to Python only to pre-warp a rotation band it needs; the kernels take their
many arrays as small structs (NamedTuples).
"""

from typing import NamedTuple

import numba
import numpy as np

from ._rowproblem import _centroid
from ._rowsolve import _solve_huber_nn, _synthesize
from ._start import _refine_start
from ._warp import _gather_row

__all__ = []

_SUMS = dict(nogil=True, cache=True, fastmath={"reassoc", "contract"})

#: A row whose centroid moves the window's farthest pixel more than this (px)
#: away from where the path before it leads (its last pose plus its velocity)
#: re-anchors the path: a block of rows from it on is solved jointly, as the
#: start block is, on a grid wide enough for both the row's pose and the
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


class _Gather(NamedTuple):
    """Where each pose k of a grid reads ``F_i``: pre-warped image ``slot[k]``
    shifted by whole pixels ``shift_y[k]``, ``shift_x[k]`` (int64 (K,) each)."""

    slot: np.ndarray
    shift_y: np.ndarray
    shift_x: np.ndarray


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
    below, columns offset by ``margin``."""

    stack: np.ndarray
    table: np.ndarray
    other_lo: int
    band_lo: int
    band: int
    pad: int
    margin: int


class _Lattice(NamedTuple):
    """The row neighbourhood: lattice offsets (K, D) int64, counts per axis,
    steps per axis, the dimensions of ty, tx and the one other axis (-1 when
    absent), and per axis the pixels a unit moves the window's farthest pixel
    (:func:`px_per_unit`)."""

    offsets: np.ndarray
    counts: np.ndarray
    step: np.ndarray
    ty_dim: int
    tx_dim: int
    other_dim: int
    px_per_unit: np.ndarray


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


@numba.njit(**_SUMS)
def _row_step(stack, gather, y, x0, g_row, g_valid, w, settings, a, reg_out, chi_out, valid_out):
    """One row of the propagation in a single call (no Python in between):
    gather ``F_i`` (pose k reads pre-warped image ``gather.slot[k]`` shifted by
    ``gather.shift_y[k]``, ``gather.shift_x[k]``) into the work array ``a``
    (K, N), solve eq. 13 warm-started from ``w`` (in place), and write the
    registered row, the change term and the validity into the outputs (NaN / 0
    / False where invalid).  Returns (objective, valid pixel count, whether
    the solve converged); the objective is inf when too few pixels are valid
    to solve.
    """
    k_count, n = a.shape
    delta = settings.delta
    v = _gather_row(stack, gather.slot, gather.shift_y, gather.shift_x, y, x0, a)
    g = np.empty(n)
    count = 0
    for j in range(n):
        ok = v[j] != 0 and g_valid[j]
        valid_out[j] = ok
        if ok:
            g[j] = g_row[j]
            count += 1
        else:
            g[j] = 0.0
            for k in range(k_count):
                a[k, j] = 0.0
    if count < settings.min_valid:
        for k in range(k_count):
            w[k] = 0.0
        for j in range(n):
            valid_out[j] = False
            reg_out[j] = np.nan
            chi_out[j] = 0.0
        return np.inf, count, True
    obj, iterations, _ = _solve_huber_nn(a, g, w, settings.lam, delta, settings.tol, settings.max_outer,
                                         settings.max_add)
    reg = np.empty(n)
    _synthesize(a, w, reg)
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
    return obj, count, iterations < settings.max_outer


@numba.njit(**_SUMS)
def _solve_at(pose, i, prewarp, lattice, settings, capture, out, prev_center, w_prev, a, w, center, gather):
    """Solve row ``i`` on the grid ``N(pose, b, s)``, warm-started from the
    weights ``w_prev`` of a grid centred at ``prev_center`` (None-like: a
    negative first entry of ``prev_center`` is never used, see the caller).
    Writes the row's outputs, ``w`` and ``center``.  Returns (status, other
    lattice index, band, cost per valid pixel, valid count, negative when the
    solve stopped at its iteration limit): status 0 solved, 1 a pre-warped
    image is missing, 2 the grid left the table."""
    table, other_lo, band_lo = prewarp.table, prewarp.other_lo, prewarp.band_lo
    offsets, counts, step = lattice.offsets, lattice.counts, lattice.step
    ty_dim, tx_dim, other_dim = lattice.ty_dim, lattice.tx_dim, lattice.other_dim
    k_count, dims = offsets.shape
    slot, sy, sx = gather.slot, gather.shift_y, gather.shift_x
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
    objective, count, converged = _row_step(prewarp.stack, gather, y, prewarp.margin, capture.dist[i],
                                            capture.dist_valid[i], w, settings, a, out.registered[i], out.chi[i],
                                            out.valid[i])
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
def _propagate_rows(prewarp, lattice, settings, capture, out, rows, prev, c_prev, prev_center, w_prev, a, trust,
                    anchor):
    """Propagate the trajectory along ``rows`` (in order) from the solved row
    ``prev`` (centroid ``c_prev``, lattice centre ``prev_center``, weights
    ``w_prev``), all in compiled code: per row, the grid ``N(c_prev, b, s)``,
    its pre-warped images (``prewarp.table[other index - other_lo, band -
    band_lo]``, -1 if missing), a warm start shifted from the previous row,
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
    offsets, step = lattice.offsets, lattice.step
    k_count, dims = offsets.shape
    w = np.empty(k_count)
    gather = _Gather(np.empty(k_count, np.int64), np.zeros(k_count, np.int64), np.zeros(k_count, np.int64))
    center = np.empty(dims, np.int64)
    c_own, predicted = np.empty(dims), np.empty(dims)
    c_prev = c_prev.copy()
    prev_center = prev_center.copy()
    w_prev = w_prev.copy()
    for pos in range(rows.shape[0]):
        i = rows[pos]
        if not capture.informative[i]:
            out.row_state[i] = 2
            continue
        status, o, bnd, cost, count = _solve_at(c_prev, i, prewarp, lattice, settings, capture, out, prev_center,
                                                w_prev, a, w, center, gather)
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
            continue
        if trust[2 * dims + 1] == 0.0 and _jumps(c_own, i, lattice.px_per_unit, trust, predicted):
            anchor[0] = c_own
            anchor[1] = predicted
            return pos, 0, 0, 3  # off the path: the caller re-anchors on a block of rows
        _follow(c_own, i, trust)
        for d in range(dims):
            c_prev[d] = c_own[d]
            out.trajectory[i, d] = c_own[d]
        out.row_state[i] = 1
        prev_center[:] = center
        w_prev[:] = w
    return rows.shape[0], 0, 0, 0


@numba.njit(**_SUMS)
def _jumps(centroid, row, px_per_unit, trust, predicted):
    """Whether ``centroid`` of ``row`` lands more than :data:`DRIFT_PX` (plus
    :data:`DRIFT_PX_PER_ROW` per row since) from the path's prediction,
    written to ``predicted``.  ``trust`` (2 D + 2,) = (last pose (D), its
    velocity per row (D), its row, a re-anchor flag)."""
    dims = centroid.shape[0]
    gap = row - trust[2 * dims]
    jump = 0.0
    for d in range(dims):
        predicted[d] = trust[d] + trust[dims + d] * gap
        jump = max(jump, abs(centroid[d] - predicted[d]) * px_per_unit[d])
    return jump > DRIFT_PX + DRIFT_PX_PER_ROW * (abs(gap) - 1)


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


def _px_per_unit(problem):
    """Per axis of ``problem`` (a :class:`_RowProblem`), the pixels a unit of
    the axis moves the window's farthest pixel: 1 for tx, ty; its distance from
    the principal point for s, and per radian for rz; the focal length per
    radian for rx, ry (axes in degrees)."""
    h, w = problem.dist.shape
    radius = float(np.hypot(np.abs(np.array([problem.dx, problem.dx + w - 1]) - problem.cx).max(),
                            np.abs(np.array([problem.dy, problem.dy + h - 1]) - problem.cy).max()))
    scale = {"tx": 1.0, "ty": 1.0, "s": radius, "rz": np.radians(radius), "rx": np.radians(problem.focal),
             "ry": np.radians(problem.focal)}
    return np.array([scale[a] for a in problem.axes])


def _shift_weights(w, counts, delta):
    """Weights on a grid moved by ``delta`` lattice steps: new[o] = old[o + delta]."""
    old = w.reshape(counts)
    new = np.zeros_like(old)
    src, dst = [], []
    for n, d in zip(counts, delta):
        d = int(d)
        if abs(d) >= n:
            return new.ravel()
        src.append(slice(max(d, 0), n + min(d, 0)))
        dst.append(slice(max(-d, 0), n - max(d, 0)))
    new[tuple(dst)] = old[tuple(src)]
    return new.ravel()


class _Propagation:
    """Row-by-row propagation of the trajectory on one row neighbourhood."""

    def __init__(self, solver, space, out):
        self.solver, self.space, self.out = solver, space, out
        self.weights = {}
        self._grid_key, self._grid, self._a = None, None, None
        self.counts, self.size = space.counts, space.size
        self.step = np.asarray(space.step)
        self.offsets_step = space.offsets() * self.step
        self.px_per_unit = _px_per_unit(solver.problem)
        self._arrays = None

    def solve_row(self, i, c, neighbour):
        space = self.space
        center = np.round(np.asarray(c, dtype=np.float64) / self.step).astype(np.int64)
        w0 = None
        if neighbour is not None and neighbour in self.weights:
            idx_n, w_n = self.weights[neighbour]
            w0 = _shift_weights(w_n, self.counts, center - idx_n)
        if self.solver.fast_rows:
            w = self._fast_row(i, center, w0)
            total = w.sum()
            self.weights[i] = (center, w)
            return center * self.step + (w @ self.offsets_step) / total if total > 0 else None
        index, poses, w, a, valid = self.solver.solve([i], space, c, w0)
        self.weights[i] = (center, w)
        self.out.store(i, w, a, valid, self.solver.problem.dist[i].astype(np.float64), self.solver.delta)
        return _centroid(poses, w)

    def _fast_row(self, i, center, w0):
        """The whole row in one compiled call (gathered F_i, fast solver)."""
        solver, space, problem, out = self.solver, self.space, self.solver.problem, self.out
        band_key = (tuple(center), problem.band_of(i, int(center[problem.ty] * self.step[problem.ty])
                                                   if problem.ty is not None else 0)[0])
        if self._grid_key != (band_key, problem.generation):
            index = center[None, :] + space.offsets()
            self._grid = problem.gather_args(i, index, space.lattice_poses(index))[:3]
            self._grid_key = (band_key, problem.generation)
        slot, shift_y, shift_x = self._grid
        y = problem.band_of(i, int(shift_y[len(shift_y) // 2]))[1]
        w = np.zeros(self.size) if w0 is None else w0
        if self._a is None:
            self._a = np.empty((self.size, problem.width), dtype=np.float32)
        objective, count, solver.last_converged = _row_step(problem.stack, _Gather(slot, shift_y, shift_x), int(y),
                                                            problem.margin,
                                     problem.dist[i], problem.dist_valid[i], w, solver.settings(problem.width),
                                     self._a, out.registered[i], out.chi[i], out.valid[i])
        solver.last_cost = objective / max(count, 1)
        out.row_gain[i] = w.sum()
        return w

    def from_row(self, start, center, informative):
        out, height = self.out, len(informative)
        c_start = self.solve_row(start, center, None)
        out.trajectory[start] = center if c_start is None else c_start
        out.row_state[start] = 1
        if self.solver.fast_rows and len(self.solver.problem.other) <= 1:
            for direction in (-1, 1):
                rows = np.arange(start + direction, height if direction > 0 else -1, direction)
                self._compiled(rows, start, informative, _trust_state(out.trajectory[start], start))
            return
        dims = len(self.step)
        for direction in (-1, 1):
            c_prev, prev = out.trajectory[start], start
            trust = _trust_state(out.trajectory[start], start)
            for i in range(start + direction, height if direction > 0 else -1, direction):
                if not informative[i]:
                    out.row_state[i] = 2
                    continue
                c = self.solve_row(i, c_prev, prev)
                if c is None or not out.valid[i].any() or not self.solver.last_converged:
                    out.row_state[i] = 3
                    continue
                c = np.asarray(c, np.float64)
                predicted = np.empty(dims)
                if _jumps(c, i, self.px_per_unit, trust, predicted):
                    rows = np.arange(i, height if direction > 0 else -1, direction)
                    again = self.solve_row(i, self._reanchor(rows, informative, c, predicted, trust), prev)
                    c = c if again is None else np.asarray(again, np.float64)
                _follow(c, i, trust)
                out.trajectory[i] = c
                out.row_state[i] = 1
                c_prev, prev = c, i

    def _compiled(self, rows, start, informative, trust):
        """:func:`from_row`'s loop in compiled code (:func:`_propagate_rows`),
        returning to Python only to pre-warp a rotation band it needs."""
        solver, problem, out, space = self.solver, self.solver.problem, self.out, self.space
        height, k = len(informative), self.size
        if self._arrays is None:
            reach = problem.margin + problem.pad
            other = problem.other[0] if problem.other else -1
            span = int(np.ceil(solver.params.search[other] / self.step[other])) + 4 * max(self.counts) if other >= 0 else 0
            band_lo = (problem.margin - reach) // problem.BAND - 1
            band_hi = (height + problem.margin + reach) // problem.BAND + 1
            self._arrays = dict(table=np.full((2 * span + 1, band_hi - band_lo + 1), -1, np.int64), other_lo=-span,
                                band_lo=band_lo, weights=np.zeros((height, k)), centers=np.zeros((height, len(self.step)),
                                                                                                  np.int64),
                                other=other, offsets=np.ascontiguousarray(space.offsets()),
                                counts=np.asarray(self.counts, np.int64))
            if self._a is None:
                self._a = np.empty((k, problem.width), dtype=np.float32)
        arr = self._arrays
        lattice = _Lattice(arr["offsets"], arr["counts"], self.step, -1 if problem.ty is None else problem.ty,
                           -1 if problem.tx is None else problem.tx, arr["other"], self.px_per_unit)
        capture = _Capture(problem.dist, problem.dist_valid, informative)
        outputs = _RowOutputs(out.registered, out.chi, out.valid, out.trajectory, out.row_state, out.row_gain,
                              arr["weights"], arr["centers"])
        settings = solver.settings(problem.width)
        prev, pos, c_prev = start, 0, out.trajectory[start].astype(np.float64)
        anchor = np.empty((2, len(self.step)))
        while pos < len(rows):
            center_prev, w_prev = self.weights[prev]
            stack = problem.stack if problem.stack is not None else np.empty((1, 1, 1), np.float32)
            prewarp = _Prewarp(stack, arr["table"], arr["other_lo"], arr["band_lo"], problem.BAND, problem.pad,
                               problem.margin)
            reached, other_index, band, status = _propagate_rows(
                prewarp, lattice, settings, capture, outputs, rows[pos:], prev, c_prev, center_prev, w_prev, self._a,
                trust, anchor)
            for i in rows[pos:pos + reached]:
                if out.row_state[i] != 2:
                    self.weights[i] = (arr["centers"][i].copy(), arr["weights"][i].copy())
                if out.row_state[i] == 1:
                    prev = i
            pos += reached
            c_prev = out.trajectory[prev].astype(np.float64)
            if status == 1:
                index = np.zeros(len(self.step), np.int64)
                if arr["other"] >= 0:
                    index[arr["other"]] = other_index
                key = (other_index,) if arr["other"] >= 0 else ()
                generation = problem.generation
                slot = problem._slot(key, index, band)
                if problem.generation != generation:  # slots of far bands were reused
                    self._refill_table()
                arr["table"][other_index - arr["other_lo"], band - arr["band_lo"]] = slot
            elif status == 2:
                # outside the table: this row the Python way, then carry on
                i = rows[pos]
                c = self.solve_row(i, out.trajectory[prev], prev)
                if c is None or not out.valid[i].any() or not self.solver.last_converged:
                    out.row_state[i] = 3
                else:
                    out.trajectory[i], out.row_state[i], prev = c, 1, i
                pos += 1
            elif status == 3:
                c_prev = self._reanchor(rows[pos:], informative, anchor[0], anchor[1], trust)

    def _reanchor(self, rows, informative, own, predicted, trust):
        """The path re-anchored at ``rows[0]`` (see :data:`DRIFT_PX`): a block of
        the informative rows from it on solved jointly on a grid that holds the
        row's own pose and the prediction; ``trust`` is set to the block's
        centroid there (flagged: that row is not checked again).  Returns the
        centroid, the centre of the row's next grid."""
        block = [r for r in rows[:4 * self.solver.params.block_rows] if informative[r]][:self.solver.params.block_rows]
        # a grid holding both poses, at most twice the row neighbourhood wide:
        # a row that jumped farther than that is not a pose worth holding
        uncertainty = np.minimum(np.abs(own - predicted), 2 * np.asarray(self.space.half_width)) + self.step
        center, _, _ = _refine_start(self.solver, predicted, np.sort(block), uncertainty, iterations=2,
                                     stride=np.ones(len(self.step)))
        dims = len(self.step)
        trust[:dims] = center
        trust[2 * dims] = rows[0]
        trust[2 * dims + 1] = 1.0
        return np.asarray(center, np.float64)

    def _refill_table(self):
        """The compiled loop's (rotation, band) -> slot table from the problem's slots."""
        arr, table = self._arrays, self._arrays["table"]
        table[:] = -1
        for (key, band), slot in self.solver.problem.slots.items():
            r, b = (key[0] if key else 0) - arr["other_lo"], band - arr["band_lo"]
            if 0 <= r < table.shape[0] and 0 <= b < table.shape[1]:
                table[r, b] = slot

    def finish(self):
        """Interpolate the centroids of rows not solved on their own, then solve
        them around the interpolated path."""
        out = self.out
        good = out.row_state == 1
        if not good.any():
            return
        rows = np.arange(len(good))
        for d in range(out.trajectory.shape[1]):
            out.trajectory[~good, d] = np.interp(rows[~good], rows[good], out.trajectory[good, d])
        solved = np.nonzero(good)[0]
        for i in np.nonzero(~good)[0]:
            nearest = int(solved[np.argmin(np.abs(solved - i))])
            self.solve_row(i, out.trajectory[i], nearest)
