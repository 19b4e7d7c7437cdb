"""Propagation of the trajectory row by row (METHOD.md section 3, step 2): each
row searches ``N(c, b, s)`` around the centroid of its solved neighbour,
warm-started from the neighbour's weights shifted onto its own grid.

:class:`_Propagation` drives it: from the start row outwards in both
directions, rows run in the compiled loop of :mod:`ops.registration._propagate_kernels`
when the problem allows it (one axis besides tx, ty), and one Python call per
row otherwise.  Python makes the pre-warped images the loop asks for, solves
the rows that leave its table, re-anchors the path when a row jumps off it
(:data:`ops.registration._propagate_kernels.DRIFT_PX`), and finally solves the rows not
solved on their own around the interpolated path.
"""

import numpy as np

from .._camera import full_poses
from .._warp import _inverse_map, _point

from ._propagate_kernels import (_Capture, _Context, _follow, _Gather, _jumps, _Lattice, _Neighbour, _Prewarp,
                                 _propagate_rows, _Row, _row_step, _RowOutputs, _Source, _trust_state)
from ._rowproblem import _centroid
from ._start import _refine_start

__all__ = []


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


def _corner_shifts(problem):
    """Per corner of ``problem``'s window (4) the displacement (px; column,
    row) of that pixel per unit of each axis of ``problem`` (D): the sampling
    map linearised at the identity pose, (4, 2, D).  A pose difference
    ``delta`` moves the corner by ``shifts[c] @ delta``; the axes add up, so a
    difference along a direction a single row cannot tell apart (rz against
    tx and ty far from the principal point) moves the window's pixels by
    what it moves them, not by each axis's share alone."""
    h, w = problem.dist.shape
    corners = [(x, y) for y in (problem.dy, problem.dy + h - 1) for x in (problem.dx, problem.dx + w - 1)]
    eps = 1e-3
    out = np.zeros((4, 2, len(problem.axes)))
    for d in range(len(problem.axes)):
        ends = []
        for sign in (-1.0, 1.0):
            unit = np.zeros(len(problem.axes))
            unit[d] = sign * eps
            m, tx, ty, sc = _inverse_map(full_poses(unit, problem.axes), problem.focal, problem.cx, problem.cy)
            ends.append([_point(m, tx, ty, sc, float(x), float(y), problem.cx, problem.cy) for x, y in corners])
        out[:, :, d] = (np.asarray(ends[1]) - np.asarray(ends[0])) / (2 * eps)
    return out


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
        self.corner_shifts = _corner_shifts(solver.problem)
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
        source = _Source(problem.stack, _Gather(slot, shift_y, shift_x), int(y), problem.margin)
        row = _Row(problem.dist[i], problem.dist_valid[i], out.registered[i], out.chi[i], out.valid[i])
        objective, count, solver.last_converged = _row_step(source, row, solver.settings(problem.width), w, self._a)
        solver.last_cost = objective / max(count, 1)
        out.row_gain[i] = w.sum()
        return w

    def from_row(self, start, center, informative):
        out, height = self.out, len(informative)
        c_start = self.solve_row(start, center, None)
        out.trajectory[start] = center if c_start is None else c_start
        fitted = c_start is not None and out.valid[start].any() and self.solver.last_converged
        out.row_state[start] = 1 if fitted else 3  # the rows still start from it; finish() solves it again
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
                if _jumps(c, i, self.px_per_unit, self.corner_shifts, trust, predicted):
                    rows = np.arange(i, height if direction > 0 else -1, direction)
                    again = self.solve_row(i, self._reanchor(rows, informative, c, predicted, trust), prev)
                    c = c if again is None else np.asarray(again, np.float64)
                _follow(c, i, trust)
                out.trajectory[i] = c
                out.row_state[i] = 1
                c_prev, prev = c, i

    def _compiled(self, rows, start, informative, trust):
        """:func:`from_row`'s loop in compiled code (:func:`_propagate_rows`),
        returning to Python only for what it cannot do: make a pre-warped image
        it needs, solve a row whose grid leaves the table of them, re-anchor the
        path where a row jumps off it."""
        problem, out = self.solver.problem, self.out
        arr = self._compiled_arrays(len(informative))
        lattice = _Lattice(arr["offsets"], arr["counts"], self.step, -1 if problem.ty is None else problem.ty,
                           -1 if problem.tx is None else problem.tx, arr["other"], self.px_per_unit,
                           self.corner_shifts)
        capture = _Capture(problem.dist, problem.dist_valid, informative)
        outputs = _RowOutputs(out.registered, out.chi, out.valid, out.trajectory, out.row_state, out.row_gain,
                              arr["weights"], arr["centers"])
        settings = self.solver.settings(problem.width)
        prev, pos, c_prev = start, 0, out.trajectory[start].astype(np.float64)
        anchor = np.empty((2, len(self.step)))
        self._refill_table()  # slots may have been reused since the table was filled
        generation = problem.generation
        while pos < len(rows):
            if problem.generation != generation:
                # a solve outside the loop (a re-anchoring, a row off the table)
                # reused slots of far bands: the table must not point at them
                self._refill_table()
                generation = problem.generation
            center_prev, w_prev = self.weights[prev]
            # the stack grows as pre-warped images are made: read it afresh
            if problem.stack is not None:
                stack, warped, pose6, row0 = problem.stack, problem.warped, problem.slot_pose6, problem.slot_row0
            else:
                stack, warped = np.empty((1, 1, 1), np.float32), np.zeros((1, 2), np.int64)
                pose6, row0 = np.zeros((1, 1, 6)), np.zeros(1, np.int64)
            prewarp = _Prewarp(stack, arr["table"], arr["other_lo"], arr["band_lo"], problem.BAND, problem.pad,
                               problem.margin, warped, problem.ref, pose6, row0, float(problem.dx - problem.margin),
                               problem.focal, float(problem.cx), float(problem.cy))
            reached, other_index, band, status = _propagate_rows(
                _Context(prewarp, lattice, settings, capture, outputs), rows[pos:],
                _Neighbour(c_prev, center_prev, w_prev), self._a, trust, anchor)
            prev = self._keep_weights(rows[pos:pos + reached], prev)
            pos += reached
            c_prev = out.trajectory[prev].astype(np.float64)
            if status == 1:
                self._make_prewarp(other_index, band)
            elif status == 2:  # outside the table: this row the Python way, then carry on
                prev = self._solve_outside(rows[pos], prev)
                pos += 1
            elif status == 3:
                c_prev = self._reanchor(rows[pos:], informative, anchor[0], anchor[1], trust)

    def _compiled_arrays(self, height):
        """The compiled loop's arrays, made on first use: the table of
        pre-warped image slots by (other-axis lattice index - ``other_lo``,
        band - ``band_lo``), wide enough for the search range and every band
        of the window; the weights and lattice centres of every row; the
        lattice offsets and counts; F_i's work space."""
        if self._arrays is None:
            solver, problem, k = self.solver, self.solver.problem, self.size
            reach = problem.margin + problem.pad
            other = problem.other[0] if problem.other else -1
            span = int(np.ceil(solver.params.search[other] / self.step[other])) + 4 * max(self.counts) if other >= 0 else 0
            band_lo = (problem.margin - reach) // problem.BAND - 1
            band_hi = (height + problem.margin + reach) // problem.BAND + 1
            self._arrays = dict(table=np.full((2 * span + 1, band_hi - band_lo + 1), -1, np.int64), other_lo=-span,
                                band_lo=band_lo, weights=np.zeros((height, k)),
                                centers=np.zeros((height, len(self.step)), np.int64), other=other,
                                offsets=np.ascontiguousarray(self.space.offsets()),
                                counts=np.asarray(self.counts, np.int64))
            if self._a is None:
                self._a = np.empty((k, problem.width), dtype=np.float32)
        return self._arrays

    def _keep_weights(self, rows, prev):
        """Keep the grid and weights of every row the compiled loop fitted;
        returns the last solved row (``prev`` if none)."""
        arr, state = self._arrays, self.out.row_state
        for i in rows:
            if state[i] != 2:
                self.weights[i] = (arr["centers"][i].copy(), arr["weights"][i].copy())
            if state[i] == 1:
                prev = i
        return prev

    def _make_prewarp(self, other_index, band):
        """A slot for the pre-warped image of ``other_index`` (lattice index of
        the other axis) and ``band``, entered in the table; the compiled loop
        warps its rows as rows read them."""
        problem, arr = self.solver.problem, self._arrays
        index = np.zeros(len(self.step), np.int64)
        if arr["other"] >= 0:
            index[arr["other"]] = other_index
        key = (other_index,) if arr["other"] >= 0 else ()
        generation = problem.generation
        slot = problem._slot(key, index, band, lazy=True)  # the compiled loop warps the rows it reads
        if problem.generation != generation:  # slots of far bands were reused
            self._refill_table()
        arr["table"][other_index - arr["other_lo"], band - arr["band_lo"]] = slot

    def _solve_outside(self, i, prev):
        """Row ``i``, whose grid leaves the table, solved the Python way around
        the last solved row ``prev``; returns the new last solved row."""
        out = self.out
        c = self.solve_row(i, out.trajectory[prev], prev)
        if c is None or not out.valid[i].any() or not self.solver.last_converged:
            out.row_state[i] = 3
            return prev
        out.trajectory[i], out.row_state[i] = c, 1
        return i

    def _reanchor(self, rows, informative, own, predicted, trust):
        """The path re-anchored at ``rows[0]`` (see
        :data:`ops.registration._propagate_kernels.DRIFT_PX`): a block of
        the informative rows from it on solved jointly on a grid that holds the
        row's own pose and the prediction; ``trust`` is set to the block's
        centroid there (flagged: that row is not checked again).  Returns the
        centroid, the centre of the row's next grid."""
        block = [r for r in rows[:4 * self.solver.params.block_rows] if informative[r]][:self.solver.params.block_rows]
        # a grid holding both poses, at most twice the row neighbourhood wide:
        # a row that jumped farther than that is not a pose worth holding
        uncertainty = np.minimum(np.abs(own - predicted), 2 * np.asarray(self.space.half_width)) + self.step
        with self.solver.clock.stage("reanchor"):
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
        them around the interpolated path: a failed row whose solve there
        meets the optimality conditions is solved (its own centroid), any row
        whose does not is failed (state 3)."""
        out = self.out
        good = out.row_state == 1
        if not good.any():
            out.row_state[out.row_state != 2] = 3
            return
        rows = np.arange(len(good))
        for d in range(out.trajectory.shape[1]):
            out.trajectory[~good, d] = np.interp(rows[~good], rows[good], out.trajectory[good, d])
        solved = np.nonzero(good)[0]
        for i in np.nonzero(~good)[0]:
            nearest = int(solved[np.argmin(np.abs(solved - i))])
            c = self.solve_row(i, out.trajectory[i], nearest)
            if c is None or not out.valid[i].any() or not self.solver.last_converged:
                out.row_state[i] = 3
            elif out.row_state[i] == 3:
                out.trajectory[i], out.row_state[i] = c, 1
