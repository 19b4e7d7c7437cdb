"""The row problem: ``F_i`` for rows of a distorted window against a reference
window (built by warps, or gathered from a cache of pre-warped images), and the
solver that runs eq. 13 on lattice grids around a pose."""

import numpy as np

from .._camera import full_poses
from .._oracle import solve_row_exact
from .._timing import UNTIMED
from ._propagate_kernels import _Settings
from ._rowsolve import SOLVED, _solve_huber_nn
from .._warp import _build_row, _gather_valid, _warp_into

__all__ = []


class _RowProblem:
    """Builds ``F_i`` for rows of the distorted window against the reference
    window, in the reference window's pixel frame.

    When tx and ty are searched on whole-pixel steps, the reference is warped
    once per distinct value of the other axes and band of rows (lazily: a
    rotation is warped only over the rows that use it) and ``F_i`` is gathered
    from those images by integer shifts: exact, because translation comes last
    in the camera model, and far cheaper than resampling every pose of every row.
    """

    BAND = 64

    def __init__(self, reference, distorted, dist_valid, camera, ref_origin, dist_origin, axes, steps, margin,
                 row_pad=16, slow=None):
        self.ref = reference
        self.dist = distorted
        self.dist_valid = dist_valid
        self.dist_all_valid = bool(dist_valid.all())
        self.focal = float(camera.focal)
        self.cx = camera.center_xy[0] - ref_origin[1]
        self.cy = camera.center_xy[1] - ref_origin[0]
        self.dy = int(dist_origin[0] - ref_origin[0])
        self.dx = int(dist_origin[1] - ref_origin[1])
        self.axes = axes
        self.slow = slow  # SlowPath or None: rx, ry per row, baked into every warp
        self.width = distorted.shape[1]
        self.steps = np.asarray(steps, dtype=np.float64)
        shift_axes = [a for a in ("tx", "ty") if a in axes]
        self.gather = all(float(self.steps[axes.index(a)]).is_integer() for a in shift_axes)
        self.other = [d for d, a in enumerate(axes) if a not in ("tx", "ty")]
        self.ty = axes.index("ty") if "ty" in axes else None
        self.tx = axes.index("tx") if "tx" in axes else None
        self.slots = {}
        self.slot_cache = {}
        self.stack = None
        # per slot: the full pose (rows, 6) of each of its rows, the first
        # row's place in the reference window, the rows [lo, hi) warped so far
        self.slot_pose6, self.slot_row0, self.warped = None, None, None
        self.free = []
        self.generation = 0  # counts evictions: cached slot numbers are stale when it changes
        # columns: the distorted window plus the largest shift; rows: one band
        # plus room for the grid's ty offsets around its centre
        self.margin = int(margin)
        self.pad = int(row_pad)
        self.stack_shape = (self.BAND + 2 * self.pad, distorted.shape[1] + 2 * self.margin)

    def band_of(self, row, center_shift_y):
        """Band of pre-warped rows serving ``row`` on a grid centred at ty shift
        ``center_shift_y`` (px), and the row's index inside the band's images."""
        y = row + self.margin - center_shift_y
        band = y // self.BAND
        return band, row + self.margin - (band * self.BAND - self.pad)

    def _slot(self, key, index, band, lazy=False):
        """The slot of the pre-warped image of ``key`` (the other axes' lattice
        values, ``index`` a lattice point holding them) for ``band``, warped
        over all its rows; ``lazy``: none warped yet (the compiled propagation
        warps the rows it reads, :func:`ops.registration._propagate_kernels._warp_rows`).
        Each row is warped alone, so an image warped in parts equals one
        warped at once."""
        slot = self.slots.get((key, band))
        if slot is None:
            slot = self._free_slot(band)
            pose = np.zeros(len(self.axes))
            pose[self.other] = np.asarray(index, dtype=np.float64)[self.other] * self.steps[self.other]
            first_row = self.dy - self.margin + band * self.BAND - self.pad
            pose6 = full_poses(pose, self.axes)[None, :]
            if self.slow is not None:  # each pre-translation row with its own slow rotation
                pose6 = pose6 + self.slow.prewarp_pose6(first_row - self.dy + np.arange(self.stack_shape[0]))
            self.slot_pose6[slot] = pose6
            self.slot_row0[slot] = first_row
            self.warped[slot] = 0
            self.slots[(key, band)] = slot
        if not lazy:
            self._warp_rows(slot, 0, self.stack_shape[0])
        return slot

    def _warp_rows(self, slot, lo, hi):
        """Warp the rows [lo, hi) of ``slot`` not warped yet; the rows warped
        (``warped[slot]``) stay one range."""
        if hi <= lo:
            return
        have_lo, have_hi = self.warped[slot]
        if have_hi <= have_lo:
            have_lo = have_hi = lo
        lo, hi = min(lo, have_lo), max(hi, have_hi)
        for a, b in ((lo, have_lo), (have_hi, hi)):
            if b > a:
                _warp_into(self.ref, self.slot_pose6[slot, a:b], self.focal, self.cx, self.cy,
                           float(self.slot_row0[slot] + a), float(self.dx - self.margin), self.stack[slot, a:b])
        self.warped[slot] = (lo, hi)

    def _free_slot(self, band):
        """Room for one more pre-warped image of ``band``: an unused slot, else the
        slots of bands two or more away, else those of the neighbouring bands
        (rows are solved band after band, so other bands are rarely needed again,
        and warping again gives the same image), else a stack a quarter larger.
        This keeps a tile's memory to about two bands of rotations instead of
        every band it ever used, with no more warps."""
        if not self.free:
            for distance in (2, 1):
                stale = [kb for kb in self.slots if abs(kb[1] - band) >= distance]
                if stale:
                    self.free = [self.slots.pop(kb) for kb in stale]
                    self.slot_cache = {k: v for k, v in self.slot_cache.items() if abs(k[1] - band) < distance}
                    self.generation += 1
                    break
            else:
                used = 0 if self.stack is None else self.stack.shape[0]
                size = used + max(8, used // 4)
                grow = np.empty((size,) + self.stack_shape, dtype=np.float32)
                pose6 = np.zeros((size, self.stack_shape[0], 6))
                row0, warped = np.zeros(size, np.int64), np.zeros((size, 2), np.int64)
                if used:
                    grow[:used] = self.stack
                    pose6[:used], row0[:used], warped[:used] = self.slot_pose6, self.slot_row0, self.warped
                self.stack, self.slot_pose6, self.slot_row0, self.warped = grow, pose6, row0, warped
                self.free = list(range(grow.shape[0] - 1, used - 1, -1))
        return self.free.pop()

    def _slots_of(self, index, band, rows=None):
        """Pre-warped image of every pose of a grid (by its non-translation
        part), warped over the rows [lo, hi) ``rows`` at least (default all)."""
        lo, hi = (0, self.stack_shape[0]) if rows is None else rows
        if not self.other:
            slot = self._slot((), index[0], band, lazy=True)
            self._warp_rows(slot, lo, hi)
            return np.full(len(index), slot, dtype=np.int64)
        # grids are a centre plus fixed offsets: the slots depend on the centre only
        key = (len(index), band) + tuple(index[len(index) // 2, self.other])
        slots = self.slot_cache.get(key)
        if slots is None:
            keys, inverse = np.unique(index[:, self.other], axis=0, return_inverse=True)
            first = np.unique(inverse.ravel(), return_index=True)[1]
            distinct = np.array([self._slot(tuple(keys[u]), index[f], band, lazy=True) for u, f in enumerate(first)],
                                dtype=np.int64)
            slots = (distinct[inverse.ravel()], distinct)
            self.slot_cache[key] = slots
        for slot in slots[1]:
            self._warp_rows(slot, lo, hi)
        return slots[0]

    def with_slow(self, poses6, row):
        """Full poses (K, 6) of capture row ``row`` with the slow rotations added."""
        return poses6 if self.slow is None else poses6 + self.slow.pose6(row)

    def rotation_stride(self, coarsen=1):
        """Per axis, how many lattice steps a block solve may skip: rz steps are
        sized for the image's farthest pixel (1 px there), so near the principal
        point several of them move this window's pixels by about a pixel or
        less (the nearest whole number of steps, at most 4/3 px).  ``coarsen``
        multiplies the stride where one step moves those pixels by a pixel or
        less (not on coarser lattices such as the paper's 0.5 deg)."""
        stride = np.ones(len(self.axes))
        if "rz" in self.axes:
            h, w = self.dist.shape
            radius = np.hypot(np.array([self.dx, self.dx + w - 1]) - self.cx,
                              np.array([self.dy, self.dy + h - 1])[:, None] - self.cy).max()
            d = self.axes.index("rz")
            per_pixel = 1.0 / (np.radians(self.steps[d]) * max(radius, 1.0))  # steps per px of motion there
            stride[d] = max(1.0, np.round(per_pixel)) * (coarsen if per_pixel >= 0.99 else 1)
        return stride

    def shifts(self, poses):
        """Whole-pixel ty and tx shifts of grid poses: two int arrays (K,)."""
        shift = np.rint(poses).astype(np.int64)
        zeros = np.zeros(len(poses), np.int64)
        return (shift[:, self.ty] if self.ty is not None else zeros,
                shift[:, self.tx] if self.tx is not None else zeros)

    def gather_args(self, row, index, poses, only_row=False):
        """(slots, ty shifts, tx shifts, row inside the band) for one row; the
        pre-warped images are warped over every row of the band, or
        (``only_row``) over the rows this row reads at least."""
        shift_y, shift_x = self.shifts(poses)
        band, y = self.band_of(row, int(shift_y[len(shift_y) // 2]))
        rows = None
        if only_row:
            rows = (int(min(max(y - shift_y.max(), 0), self.stack_shape[0])),
                    int(min(max(y - shift_y.min() + 1, 0), self.stack_shape[0])))
        return self._slots_of(index, band, rows), shift_y, shift_x, y

    def build(self, rows, index, poses):
        """A (K, len(rows) * W) float32 and g (N,) with invalid pixels zeroed,
        plus valid (N,) bool, for poses on lattice ``index`` (K, D)."""
        k, n = poses.shape[0], self.width
        a = np.empty((k, len(rows) * n), dtype=np.float32)
        valid = np.empty(len(rows) * n, dtype=bool)
        if self.gather:  # in this problem's lattice units (a block solve may skip steps)
            index = np.rint(poses / self.steps).astype(np.int64)
        else:
            poses6 = full_poses(poses, self.axes)
        for q, i in enumerate(rows):
            # write straight into the block's columns of this row
            buf = a[:, q * n:(q + 1) * n] if len(rows) > 1 else a
            if self.gather:  # the capture's invalid pixels zeroed in the same pass
                slot, shift_y, shift_x, y = self.gather_args(i, index, poses, only_row=True)
                v = _gather_valid(self.stack, slot, shift_y, shift_x, y, self.margin, buf, self.dist_valid[i])
            else:
                v = _build_row(self.ref, float(i + self.dy), float(self.dx), self.with_slow(poses6, i), self.focal,
                               self.cx, self.cy, buf)
            valid[q * n:(q + 1) * n] = (v != 0) & self.dist_valid[i]
        if not (self.dist_all_valid or self.gather):
            a[:, ~valid] = 0.0
        g = np.where(valid, self.dist[rows].ravel(), 0.0)
        return a, g, valid


def _shift_margin(params, prior):
    """Largest translation (px) a row can reach: the search range (or the prior
    path) plus room for the row neighbourhood to follow the path and widen."""
    reach = 0.0
    for d, a in enumerate(params.axes):
        if a in ("tx", "ty"):
            extent = params.search[d] if prior is None else np.nanmax(np.abs(np.asarray(prior)[:, d]))
            reach = max(reach, extent + 3 * params.half_width[d] + 2 * params.step[d])
    return int(np.ceil(reach)) + 2


MIN_VALID_PIXELS = 16


MIN_VALID_FRACTION = 0.1


class _Solver:
    """Solves rows on lattice grids and keeps per-row weights."""

    def __init__(self, problem, params, clock=UNTIMED):
        self.problem = problem
        self.params = params
        self.clock = clock  # CPU-seconds per stage (ops._timing.StageClock)
        self.delta = 0.5 * params.lambda_chi
        self.last_cost = np.inf
        self.last_converged = True  # the last solve met its optimality conditions (ops.registration._rowsolve.SOLVED)

    @property
    def fast_rows(self):
        """Rows can take the single-call path (gathered F_i, fast solver)."""
        return self.problem.gather and self.params.solver == "fast"

    @staticmethod
    def min_valid(size):
        return int(np.ceil(max(MIN_VALID_PIXELS, MIN_VALID_FRACTION * size)))

    def settings(self, width):
        """The compiled kernels' settings for rows of ``width`` pixels."""
        p = self.params
        return _Settings(float(p.lambda_w), float(self.delta), float(p.tol), int(p.max_outer), int(p.max_add),
                         self.min_valid(width))

    def solve(self, rows, space, center, w0=None):
        index, poses = space.grid(center)
        a, g, valid = self.problem.build(rows, index, poses)
        self.last_cost = np.inf
        self.last_converged = True
        if valid.sum() < self.min_valid(valid.size):
            # too little of the row sees the reference: nothing to solve
            valid[:] = False
            return index, poses, np.zeros(len(poses)), a, valid
        if self.params.solver == "exact":
            solution = solve_row_exact(a.T, g, lambda_w=self.params.lambda_w, lambda_chi=self.params.lambda_chi,
                                       weights=valid.astype(np.float64))
            w, objective = np.maximum(solution.w, 0.0), solution.objective
        else:
            w = np.zeros(len(poses)) if w0 is None else w0.copy()
            objective, _, _, status = _solve_huber_nn(a, g, w, self.params.lambda_w, self.delta, self.params.tol,
                                                      self.params.max_outer, self.params.max_add)
            self.last_converged = status == SOLVED
        self.last_cost = objective / valid.sum()  # eq. 13 per valid pixel, comparable across grids
        return index, poses, w, a, valid


def _centroid(poses, w):
    total = w.sum()
    return (w @ poses) / total if total > 0 else None


def _spread(poses, w, centroid, mass=0.9):
    """Distance per axis from the centroid within which ``mass`` of the weight lies
    (the blur extent of the block, robust to a few stray small weights)."""
    out = np.zeros(poses.shape[1])
    for d in range(poses.shape[1]):
        dist = np.abs(poses[:, d] - centroid[d])
        order = np.argsort(dist)
        cum = np.cumsum(w[order])
        out[d] = dist[order][min(np.searchsorted(cum, mass * cum[-1]), len(cum) - 1)]
    return out
