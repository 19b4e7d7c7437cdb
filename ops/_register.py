"""Per-row registration of a distorted capture against a reference (METHOD.md section 3).

The trajectory starts at an informative block of rows near the middle of the
capture, found by a cheap correlation search over a wide pose range and refined
by a joint solve of eq. 13 for the block; it then propagates outwards, row by
row, each row searching ``N(c, b, s)`` around the centroid of its solved
neighbour and warm-started from the neighbour's weights.  Homogeneous rows are
not trusted for the trajectory: their centroid is interpolated and they are
solved afterwards around it.
"""

import dataclasses
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from ._camera import Camera, full_poses
from ._errors import ParameterError
from ._oracle import optimal_chi, solve_row_exact
from ._posespace import PoseSpace
from ._rowsolve import (
    _build_row,
    _gather_row,
    _propagate_rows,
    _row_step,
    _solve_huber_nn,
    _synthesize,
    _warp_into,
)

__all__ = ["RegistrationParams", "Registration", "register"]


@dataclass(frozen=True)
class RegistrationParams:
    """Tuning of :func:`register`; units are those of :data:`ops.AXIS_UNITS`.

    Attributes
    ----------
    axes : tuple of str
        Pose axes searched.
    half_width, step : tuple of float or None
        Row neighbourhood ``N(c, b, s)`` around the neighbour's centroid.  None
        means automatic: a step moves the farthest pixel by about one pixel
        (:func:`auto_step`) and the half-width is three steps, so tx, ty
        N(c, 3, 1) px as in the paper, and rz steps that shrink as images grow
        (the paper's rz N(c, 2, 0.5) deg suits its 256 x 384 images only).
    search : tuple of float
        Largest motion the wide initial search covers, per axis (+-).
    shutter : {"rolling", "global"}
        "global" solves one weight vector for every row.
    solver : {"fast", "exact"}
        The active-set row solver, or the exact cvxpy formulation of eq. 13
        (the oracle; seconds per row).
    lambda_w, lambda_chi : float
        Weights of ``||w||_1`` and ``||chi||_1`` in eq. 13, intensities in [0, 1].
        ``lambda_chi / 2`` is the residual above which a pixel counts as change.
    block_rows : int
        Rows solved jointly to start the trajectory (one row alone is ambiguous).
    homogeneous : float
        A row whose mean absolute horizontal gradient is below this fraction of
        the median row's is homogeneous (its centroid is interpolated).
    adapt : bool
        Widen the row neighbourhood to the blur extent found in the start block.
    tol : float
        Relative KKT tolerance of the row solver.
    max_outer, max_add : int
        Row solver limits: outer iterations, poses added to the working set per
        iteration.
    gain_slope : bool
        Also fit a linear illumination slope along the rows of the window
        (``1 + b (x - x_c)``, robustly, changes excluded): ``||w_i||_1`` gives each
        row its own gain, but a gain that varies across a row (vignetting, a
        slow illumination gradient over a wide-area mosaic) is otherwise left in
        the residual and read as change.  A local illumination term in the
        spirit of the authors' later work on local variations.
    """

    axes: tuple = ("tx", "ty", "rz")
    half_width: tuple = (3.0, 3.0, None)
    step: tuple = (1.0, 1.0, None)
    search: tuple = (20.0, 20.0, 3.0)
    shutter: str = "rolling"
    solver: str = "fast"
    lambda_w: float = 1e-3
    lambda_chi: float = 0.02
    block_rows: int = 7
    homogeneous: float = 0.2
    adapt: bool = True
    tol: float = 1e-6
    max_outer: int = 100
    max_add: int = 8
    gain_slope: bool = True

    def __post_init__(self):
        axes = tuple(self.axes)
        n = len(axes)
        hw = _per_axis(self.half_width, n, "half_width")
        st = _per_axis(self.step, n, "step")
        search = _per_axis(self.search, n, "search")
        if None in search:
            raise ParameterError(f"search: expected a number per axis, got {self.search}")
        object.__setattr__(self, "axes", axes)
        object.__setattr__(self, "half_width", hw)
        object.__setattr__(self, "step", st)
        object.__setattr__(self, "search", search)
        PoseSpace(axes, [1.0 if v is None else v for v in hw], [1.0 if v is None else v for v in st])  # validates
        if self.solver not in ("fast", "exact"):
            raise ParameterError(f"solver: expected 'fast' or 'exact', got {self.solver!r}")
        if self.shutter not in ("rolling", "global"):
            raise ParameterError(f"shutter: expected 'rolling' or 'global', got {self.shutter!r}")
        if not (self.lambda_w >= 0 and self.lambda_chi > 0):
            raise ParameterError(f"lambda_w >= 0 and lambda_chi > 0 expected, got {self.lambda_w}, {self.lambda_chi}")

    @property
    def is_resolved(self):
        return None not in self.half_width and None not in self.step

    def resolved(self, camera):
        """These parameters with every ``None`` step and half-width filled in for
        ``camera`` (see :func:`auto_step`); half-widths default to 3 steps."""
        step = tuple(auto_step(a, camera) if s is None else s for a, s in zip(self.axes, self.step))
        half = tuple(3.0 * s if b is None else b for b, s in zip(self.half_width, step))
        return dataclasses.replace(self, step=step, half_width=half)

    @property
    def space(self):
        if not self.is_resolved:
            raise ParameterError("RegistrationParams: steps are still 'auto'; call resolved(camera) first")
        return PoseSpace(self.axes, self.half_width, self.step)


def _per_axis(values, n, name):
    values = tuple(values) if isinstance(values, (tuple, list)) else (values,) * n
    if len(values) == 1:
        values = values * n
    if len(values) != n:
        raise ParameterError(f"{name}: expected one value per axis ({n}), got {values}")
    return tuple(None if v is None else float(v) for v in values)


def auto_step(axis, camera):
    """Grid step of ``axis`` that moves the farthest pixel of the image by about
    one pixel (METHOD.md: neighbouring warps one pixel apart).

    tx, ty: 1 px; rz: 1 / r rad with r the distance of the farthest corner from
    the principal point; rx, ry: 1 / f rad; s: 1 / r.
    """
    radius = float(np.hypot(camera.center_xy[0] + 0.5, camera.center_xy[1] + 0.5))
    if axis in ("tx", "ty"):
        return 1.0
    if axis == "rz":
        return float(np.degrees(1.0 / radius))
    if axis in ("rx", "ry"):
        return float(np.degrees(1.0 / camera.focal))
    return 1.0 / radius


@dataclass
class Registration:
    """Result of :func:`register` for a distorted window of shape (H, W).

    Attributes
    ----------
    registered : ndarray, shape (H, W), float32
        The reference warped and blurred to match the capture (``F_i w_i``);
        NaN where a pose sampled outside the reference.
    chi : ndarray, shape (H, W), float32
        Signed change term of eq. 13 (0 where invalid).
    valid : ndarray, shape (H, W), bool
        Pixels whose every pose sampled valid reference data.
    trajectory : ndarray, shape (H, D), float64
        Per-row centroid pose over ``axes`` in global pose coordinates.
    row_gain : ndarray, shape (H,)
        ``||w_i||_1`` per row (the illumination gain seen by that row).
    row_state : ndarray, shape (H,), uint8
        1 solved, 2 homogeneous (centroid interpolated), 3 failed (no fit).
    axes : tuple of str
    timings : dict
    """

    registered: np.ndarray
    chi: np.ndarray
    valid: np.ndarray
    trajectory: np.ndarray
    row_gain: np.ndarray
    row_state: np.ndarray
    axes: tuple
    timings: dict = field(default_factory=dict)

    @property
    def gain(self):
        """Illumination gain of the window: median ``||w_i||_1`` of solved rows."""
        good = self.row_state == 1
        return float(np.median(self.row_gain[good])) if good.any() else float("nan")


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
                 row_pad=16):
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

    def _slot(self, key, index, band):
        slot = self.slots.get((key, band))
        if slot is None:
            slot = self._free_slot(band)
            pose = np.zeros(len(self.axes))
            pose[self.other] = np.asarray(index, dtype=np.float64)[self.other] * self.steps[self.other]
            first_row = self.dy - self.margin + band * self.BAND - self.pad
            _warp_into(self.ref, full_poses(pose, self.axes), self.focal, self.cx, self.cy, float(first_row),
                       float(self.dx - self.margin), self.stack[slot])
            self.slots[(key, band)] = slot
        return slot

    def _free_slot(self, band):
        """Room for one more pre-warped image of ``band``: an unused slot, else the
        slots of bands two or more away, else those of the neighbouring bands
        (rows are solved band after band, so other bands are rarely needed again,
        and warping again gives the same image), else a stack a quarter larger.
        This keeps a tile's memory to about two bands of rotations: at an
        8192 x 8192 image's corner tile, 50 slots instead of 128 with no more
        warps."""
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
                grow = np.empty((used + max(8, used // 4),) + self.stack_shape, dtype=np.float32)
                if used:
                    grow[:used] = self.stack
                self.stack = grow
                self.free = list(range(grow.shape[0] - 1, used - 1, -1))
        return self.free.pop()

    def _slots_of(self, index, band):
        """Pre-warped image of every pose of a grid (by its non-translation part)."""
        if not self.other:
            return np.full(len(index), self._slot((), index[0], band), dtype=np.int64)
        # grids are a centre plus fixed offsets: the slots depend on the centre only
        key = (len(index), band) + tuple(index[len(index) // 2, self.other])
        slots = self.slot_cache.get(key)
        if slots is None:
            keys, inverse = np.unique(index[:, self.other], axis=0, return_inverse=True)
            first = np.unique(inverse.ravel(), return_index=True)[1]
            slots = np.array([self._slot(tuple(keys[u]), index[f], band) for u, f in enumerate(first)],
                             dtype=np.int64)[inverse.ravel()]
            self.slot_cache[key] = slots
        return slots

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

    def gather_args(self, row, index, poses):
        """(slots, ty shifts, tx shifts, row inside the band) for one row."""
        shift_y, shift_x = self.shifts(poses)
        band, y = self.band_of(row, int(shift_y[len(shift_y) // 2]))
        return self._slots_of(index, band), shift_y, shift_x, y

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
            if self.gather:
                slot, shift_y, shift_x, y = self.gather_args(i, index, poses)
                v = _gather_row(self.stack, slot, shift_y, shift_x, y, self.margin, buf)
            else:
                v = _build_row(self.ref, float(i + self.dy), float(self.dx), poses6, self.focal, self.cx, self.cy, buf)
            valid[q * n:(q + 1) * n] = (v != 0) & self.dist_valid[i]
        if not self.dist_all_valid:
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


def _row_energy(distorted, valid):
    grad = np.abs(np.diff(distorted, axis=1))
    ok = valid[:, 1:] & valid[:, :-1]
    count = ok.sum(axis=1)
    return np.where(count > 0, (grad * ok).sum(axis=1) / np.maximum(count, 1), 0.0)


def _gradients(image):
    """Smoothed x and y derivatives, float32: correlating these rather than
    intensities keeps large changed objects from dominating the score."""
    image = cv2.GaussianBlur(np.nan_to_num(image).astype(np.float32), (0, 0), 1.0)
    return cv2.Sobel(image, cv2.CV_32F, 1, 0), cv2.Sobel(image, cv2.CV_32F, 0, 1)


def _coarse_search(problem, params, rows, count=4):
    """Candidate start poses of a band of rows, best first: for each in-plane
    rotation on a coarse grid, the two best translations by normalised
    cross-correlation of image gradients (invariant to gain, robust to changed
    objects).  Returns the ``count`` best distinct ones and, per axis, how far
    the truth may lie from a candidate (half the coarse spacing)."""
    axes = params.axes
    search = dict(zip(axes, params.search))
    step = dict(zip(axes, params.step))
    margin_x = int(np.ceil(search.get("tx", 0.0))) + 1
    margin_y = int(np.ceil(search.get("ty", 0.0))) + 1
    r0, r1 = rows[0], rows[-1] + 1
    width = problem.width
    uncertainty = np.where(np.isin(axes, ("tx", "ty")), 1.0, 0.0)
    if width - 2 * margin_x < 16:
        return [np.zeros(len(axes))], uncertainty
    pad = 4
    lo, hi = max(r0 - pad, 0), min(r1 + pad, problem.dist.shape[0])
    templates = [t[r0 - lo:t.shape[0] - (hi - r1), margin_x:width - margin_x].copy()
                 for t in _gradients(problem.dist[lo:hi])]
    if min(t.std() for t in templates) == 0:
        return [np.zeros(len(axes))], uncertainty
    rz_values = [0.0]
    if "rz" in axes and search["rz"] > 0:
        # candidates close enough that the translation search bridges them at
        # the band's farthest pixel, and that the band tilts < 2 px between them
        corner = np.hypot(np.array([problem.dx, problem.dx + width]) - problem.cx,
                          np.array([r0, r1]) + problem.dy - problem.cy).max()
        bridge = min(2.0 / max(width / 2.0, 1.0), max(min(margin_x, margin_y) - 1, 1) / 2.0 / max(corner, 1.0))
        coarse = max(np.degrees(bridge), step["rz"])
        n = int(np.ceil(search["rz"] / coarse))
        rz_values = list(np.linspace(-search["rz"], search["rz"], 2 * n + 1))
        uncertainty[axes.index("rz")] = search["rz"] / (2 * n) if n else 0.0
    band = np.arange(r0 - margin_y, r1 + margin_y)
    peaks = []
    buf = np.empty((1, width), dtype=np.float32)
    for rz in rz_values:
        pose = full_poses(np.array([[rz]]), ("rz",))
        img = np.empty((band.size, width), dtype=np.float32)
        for q, i in enumerate(band):
            _build_row(problem.ref, float(i + problem.dy), float(problem.dx), pose, problem.focal,
                       problem.cx, problem.cy, buf)
            img[q] = buf[0]
        score = sum(cv2.matchTemplate(i, t, cv2.TM_CCOEFF_NORMED) for i, t in zip(_gradients(img), templates))
        for peak, (x, y) in _local_maxima(score, 2):
            peaks.append((peak, margin_x - x, margin_y - y, rz))
    peaks.sort(key=lambda p: -p[0])
    out = []
    for _, tx, ty, rz in peaks:
        values = {"tx": tx, "ty": ty, "rz": rz}
        pose = np.array([values.get(a, 0.0) for a in axes], dtype=np.float64)
        if all(np.abs(pose - q).max() > 1.5 for q in out):
            out.append(pose)
        if len(out) == count:
            break
    return out or [np.zeros(len(axes))], uncertainty


def _local_maxima(score, count, radius=3):
    """The ``count`` highest local maxima of a score map: (value, (x, y))."""
    out = []
    score = score.copy()
    for _ in range(count):
        _, peak, _, loc = cv2.minMaxLoc(score)
        if not np.isfinite(peak):
            break
        out.append((peak, loc))
        x, y = loc
        score[max(y - radius, 0):y + radius + 1, max(x - radius, 0):x + radius + 1] = -np.inf
    return out


MIN_VALID_PIXELS = 16
MIN_VALID_FRACTION = 0.1


class _Solver:
    """Solves rows on lattice grids and keeps per-row weights."""

    def __init__(self, problem, params):
        self.problem = problem
        self.params = params
        self.delta = 0.5 * params.lambda_chi

    @property
    def fast_rows(self):
        """Rows can take the single-call path (gathered F_i, fast solver)."""
        return self.problem.gather and self.params.solver == "fast"

    @staticmethod
    def min_valid(size):
        return int(np.ceil(max(MIN_VALID_PIXELS, MIN_VALID_FRACTION * size)))

    def solve(self, rows, space, center, w0=None):
        index, poses = space.grid(center)
        a, g, valid = self.problem.build(rows, index, poses)
        self.last_cost = np.inf
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
            objective, _, _ = _solve_huber_nn(a, g, w, self.params.lambda_w, self.delta, self.params.tol,
                                              self.params.max_outer, self.params.max_add)
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


def register(reference, distorted, *, camera=None, params=None, reference_origin_yx=(0, 0),
             distorted_origin_yx=(0, 0), reference_valid=None, distorted_valid=None, prior=None):
    """Register a distorted capture against a reference, row by row (eq. 13).

    Parameters
    ----------
    reference : ndarray, shape (Hr, Wr), float32 in [0, 1]
        Reference window (may be larger than the distorted one: a halo); NaN
        marks nodata, as ``reference_valid`` False does.
    distorted : ndarray, shape (H, W), float32 in [0, 1]
        Captured window.
    camera : Camera, optional
        Intrinsics of the *whole* image, default that of ``distorted``'s shape.
    params : RegistrationParams, optional
    reference_origin_yx, distorted_origin_yx : tuple of int
        Position of each window's pixel (0, 0) in the whole image.
    reference_valid, distorted_valid : ndarray of bool, optional
        False at nodata pixels.
    prior : ndarray, shape (H, D), optional
        A trajectory to search around instead of starting from the middle: every
        row searches ``N(prior_i, b, s)`` (used to re-solve a tile around its
        neighbours' path).

    Returns
    -------
    Registration
    """
    camera = camera or Camera.for_shape(distorted.shape)
    params = (params or RegistrationParams()).resolved(camera)
    ref = np.array(reference, dtype=np.float32)
    if reference_valid is not None:
        ref[~np.asarray(reference_valid, bool)] = np.nan
    dist = np.asarray(distorted, dtype=np.float32)
    dvalid = np.ones(dist.shape, bool) if distorted_valid is None else np.asarray(distorted_valid, bool)
    if prior is not None:
        prior = np.asarray(prior, dtype=np.float64)
        if prior.shape != (dist.shape[0], len(params.axes)):
            raise ParameterError(f"prior: expected shape {(dist.shape[0], len(params.axes))}, got {prior.shape}")
    args = (camera, params, reference_origin_yx, distorted_origin_yx, prior)
    # eq. 13 has one gain per row: a gain changing along the rows by more than a
    # few per cent biases the poses, so a slope fitted to the registration is
    # divided out of the capture and the rows are solved again (at most twice)
    factor, scaled = None, dist
    timings = {"coarse_search_s": 0.0, "rows_s": 0.0}
    for attempt in range(3):
        out, delta, spent = _solve_rows(ref, scaled, dvalid, *args)
        timings = {k: timings[k] + spent[k] for k in timings}
        more = _gain_slope(out, scaled, delta) if params.gain_slope else None
        if more is None:
            break
        resolve = np.abs(more - 1.0).max() > GAIN_SLOPE_RESOLVE
        if resolve and attempt == 0:
            # a fit after a biased solve falls short of the slope; column-block
            # brightness is the better first estimate when it agrees and is larger
            guess = _column_gain_guess(ref, dist, dvalid, reference_origin_yx, distorted_origin_yx)
            if guess is not None and (guess[-1] - guess[0]) / (more[-1] - more[0]) > 1.0:
                more = guess
        factor = more if factor is None else factor * more
        if not resolve:
            break
        scaled = dist / factor
    if factor is not None:
        _fold_gain(out, dist, factor, delta)
    return Registration(out.registered, out.chi, out.valid, out.trajectory, out.row_gain, out.row_state,
                        params.axes, timings)


GAIN_SLOPE_RESOLVE = 0.05  # relative gain change at the row ends that triggers another solve


def _solve_rows(ref, dist, dvalid, camera, params, reference_origin_yx, distorted_origin_yx, prior):
    """Every row of ``dist`` against ``ref`` (eq. 13): outputs, the Huber delta, timings."""
    row_pad = int(np.ceil(3 * max([params.half_width[d] for d, a in enumerate(params.axes) if a == "ty"] + [0])))
    problem = _RowProblem(ref, dist, dvalid, camera, reference_origin_yx, distorted_origin_yx, params.axes,
                          params.step, _shift_margin(params, prior), row_pad + 4)
    solver = _Solver(problem, params)
    t0 = time.perf_counter()
    height, width = dist.shape
    energy = _row_energy(dist, dvalid)
    informative = energy >= params.homogeneous * np.median(energy[energy > 0]) if (energy > 0).any() else energy > 0
    out = _Outputs(height, width, len(params.axes))
    mid = _start_row(informative, height)
    half_band = int(max(16, min(48, height // 6)))
    band = np.arange(max(0, mid - half_band), min(height, mid + half_band))
    candidates = _coarse_search(problem, params, band) if prior is None else None
    t1 = time.perf_counter()
    if prior is not None:
        _register_prior(solver, prior, informative, out)
    elif params.shutter == "global":
        _register_global(solver, candidates, informative, out)
    else:
        _register_rolling(solver, candidates, informative, mid, out)
    return out, solver.delta, {"coarse_search_s": t1 - t0, "rows_s": time.perf_counter() - t1}


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


class _Outputs:
    def __init__(self, height, width, dims):
        self.registered = np.full((height, width), np.nan, dtype=np.float32)
        self.chi = np.zeros((height, width), dtype=np.float32)
        self.valid = np.zeros((height, width), dtype=bool)
        self.trajectory = np.full((height, dims), np.nan)
        self.row_gain = np.zeros(height)
        self.row_state = np.zeros(height, dtype=np.uint8)

    def store(self, row, w, a, valid, g_row, delta):
        n = g_row.shape[0]
        reg = np.empty(n)
        _synthesize(a, w, reg)
        r = g_row - reg
        chi = optimal_chi(r, lambda_chi=2 * delta)
        self.registered[row] = np.where(valid, reg, np.nan)
        self.chi[row] = np.where(valid, chi, 0.0)
        self.valid[row] = valid
        self.row_gain[row] = w.sum()


def _start_row(informative, height):
    """The informative row nearest the middle."""
    rows = np.nonzero(informative)[0]
    if rows.size == 0:
        return height // 2
    return int(rows[np.argmin(np.abs(rows - height // 2))])


def _block_rows(informative, mid, count, height):
    rows = np.nonzero(informative)[0]
    if rows.size == 0:
        rows = np.arange(height)
    # the nearest rows: a rolling shutter moves between rows, so the block is
    # kept short in time
    return np.sort(rows[np.argsort(np.abs(rows - mid), kind="stable")][:count])


def _refine_start(solver, center, rows, uncertainty, iterations=2, stride=None):
    """Joint solve of a block of rows around a coarse pose (a grid wide enough
    for the coarse search's spacing, lattice steps ``stride`` times the
    parameters' steps, default :meth:`_RowProblem.rotation_stride`); returns the
    block's centroid, the blur extent per axis and the cost."""
    params = solver.params
    steps = np.asarray(params.step) * (solver.problem.rotation_stride() if stride is None else stride)
    coarse_hw = np.maximum(np.maximum(np.asarray(params.half_width) + steps, 4 * steps),
                           np.ceil(np.asarray(uncertainty) / steps) * steps + 2 * steps)
    space = PoseSpace(params.axes, tuple(coarse_hw), tuple(steps))
    for _ in range(iterations):
        _, poses, w, _, _ = solver.solve(rows, space, center)
        c = _centroid(poses, w)
        if c is None:
            return center, np.zeros_like(center), np.inf
        center = c
    return center, _spread(poses, w, center), solver.last_cost


def _choose_start(solver, start, rows):
    """The start pose among the correlation candidates whose block solve of
    eq. 13 costs least: correlation proposes, the model decides (periodic
    textures such as ploughed fields give several correlation peaks).
    ``start`` is (candidates, uncertainty per axis)."""
    candidates, uncertainty = start
    # where rz steps move the block's pixels by a pixel or less, candidates
    # compete on a lattice twice as coarse in rz (half the poses of the widest
    # block systems), and the winner is refined on the full lattice around a
    # pose then known to within one coarse step
    coarse = solver.problem.rotation_stride(2)
    coarsened = coarse != solver.problem.rotation_stride()  # per axis
    best = None
    for center in candidates:
        refined = _refine_start(solver, np.asarray(center, dtype=np.float64), rows, uncertainty, iterations=1,
                                stride=coarse)
        if best is None or refined[2] < best[2]:
            best = refined
    if (len(candidates) > 1 or coarsened.any()) and np.isfinite(best[2]):
        known = np.where(coarsened, np.asarray(solver.params.step) * coarse, uncertainty)
        best = _refine_start(solver, best[0], rows, known, iterations=1)
    return best[0], best[1]


def _adapted_half_width(space, spread):
    """Half-widths that cover a blur of extent ``spread`` (per axis) plus one step,
    never narrower than ``space``'s."""
    steps = np.asarray(space.step)
    need = np.ceil(spread / steps - 1e-9) * steps + steps
    return tuple(np.maximum(space.half_width, need))


def _register_rolling(solver, candidates, informative, mid, out):
    """Start near the middle, propagate outwards row by row."""
    space, center = _start(solver, candidates, informative, mid)
    run = _Propagation(solver, space, out)
    run.from_row(mid, center, informative)
    run.finish()


def _start(solver, candidates, informative, mid):
    """Start pose of the middle block and the row neighbourhood, widened to the
    blur extent of the middle row."""
    params = solver.params
    block = _block_rows(informative, mid, params.block_rows, len(informative))
    center, _ = _choose_start(solver, candidates, block)
    space = params.space
    if params.adapt:
        wide = space.widened(tuple(np.asarray(space.half_width) + np.asarray(space.step)))
        _, poses, w, _, _ = solver.solve([mid], wide, center)
        c = _centroid(poses, w)
        if c is not None:
            space = space.widened(_adapted_half_width(space, _spread(poses, w, c)))
    return space, center


class _Propagation:
    """Row-by-row propagation of the trajectory on one row neighbourhood."""

    def __init__(self, solver, space, out):
        self.solver, self.space, self.out = solver, space, out
        self.weights = {}
        self._grid_key, self._grid, self._a = None, None, None
        self.counts, self.size = space.counts, space.size
        self.step = np.asarray(space.step)
        self.offsets_step = space.offsets() * self.step
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
        p = solver.params
        objective, count = _row_step(problem.stack, slot, shift_y, shift_x, int(y), problem.margin,
                                     problem.dist[i], problem.dist_valid[i], w, p.lambda_w, solver.delta, p.tol,
                                     p.max_outer, p.max_add, solver.min_valid(problem.width), self._a,
                                     out.registered[i], out.chi[i], out.valid[i])
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
                self._compiled(rows, start, informative)
            return
        for direction in (-1, 1):
            c_prev, prev = out.trajectory[start], start
            for i in range(start + direction, height if direction > 0 else -1, direction):
                if not informative[i]:
                    out.row_state[i] = 2
                    continue
                c = self.solve_row(i, c_prev, prev)
                if c is None or not out.valid[i].any():
                    out.row_state[i] = 3
                    continue
                out.trajectory[i] = c
                out.row_state[i] = 1
                c_prev, prev = c, i

    def _compiled(self, rows, start, informative):
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
        p = solver.params
        prev = start
        pos = 0
        while pos < len(rows):
            center_prev, w_prev = self.weights[prev]
            reached, other_index, band, status = _propagate_rows(
                problem.stack if problem.stack is not None else np.empty((1, 1, 1), np.float32), arr["table"],
                arr["other_lo"], arr["band_lo"], problem.BAND, problem.pad, problem.margin, rows[pos:],
                out.trajectory[prev].astype(np.float64), prev, center_prev, w_prev, informative, problem.dist,
                problem.dist_valid, arr["offsets"], arr["counts"], self.step,
                problem.ty if problem.ty is not None else -1, problem.tx if problem.tx is not None else -1,
                arr["other"], p.lambda_w, solver.delta, p.tol, p.max_outer, p.max_add, solver.min_valid(problem.width),
                self._a, out.registered, out.chi, out.valid, out.trajectory, out.row_state, out.row_gain,
                arr["weights"], arr["centers"])
            for i in rows[pos:pos + reached]:
                if out.row_state[i] != 2:
                    self.weights[i] = (arr["centers"][i].copy(), arr["weights"][i].copy())
                if out.row_state[i] == 1:
                    prev = i
            pos += reached
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
                if c is None or not out.valid[i].any():
                    out.row_state[i] = 3
                else:
                    out.trajectory[i], out.row_state[i], prev = c, 1, i
                pos += 1

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


def _register_global(solver, candidates, informative, out):
    """One weight vector for every row (global shutter)."""
    params = solver.params
    height = out.row_gain.shape[0]
    rows = np.nonzero(informative)[0]
    if rows.size == 0:
        rows = np.arange(height)
    rows = rows[np.linspace(0, rows.size - 1, min(32, rows.size)).round().astype(int)]
    rows = np.unique(rows)
    center, spread = _choose_start(solver, candidates, rows)
    space = params.space.widened(_adapted_half_width(params.space, spread))
    index, poses, w, _, _ = solver.solve(rows, space, center)
    c = _centroid(poses, w)
    keep = w > 0
    index, poses, w = index[keep], poses[keep], w[keep]
    for i in range(height):
        a, g, valid = solver.problem.build([i], index, poses)
        out.store(i, w, a, valid, solver.problem.dist[i].astype(np.float64), solver.delta)
        out.trajectory[i] = c if c is not None else center
        out.row_state[i] = 1 if informative[i] else 2


def _register_prior(solver, prior, informative, out):
    """Every row around a given trajectory, warm-started from the row above."""
    space = solver.params.space
    counts = space.counts
    previous = None
    for i in range(prior.shape[0]):
        w0 = None
        if previous is not None:
            w0 = _shift_weights(previous[1], counts, space.snap(prior[i]) - previous[0])
        index, poses, w, a, valid = solver.solve([i], space, prior[i], w0)
        out.store(i, w, a, valid, solver.problem.dist[i].astype(np.float64), solver.delta)
        c = _centroid(poses, w)
        good = informative[i] and c is not None and valid.any()
        out.trajectory[i] = c if good else prior[i]
        out.row_state[i] = 1 if good else (2 if not informative[i] else 3)
        previous = (space.snap(prior[i]), w)
