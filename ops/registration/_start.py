"""Where the trajectory starts: an informative block of rows near the middle of
the capture, candidate poses from a cheap correlation search over a wide pose
range, and the candidate whose joint block solve of eq. 13 costs least.

Camera poses are global: windows holding the same rows of one capture (the
tiles of one band) share their start.  One window searches
(:class:`StartPose`); the others refine their own start block around its pose
(:func:`_shared_start`) and search alone only where that is unsound."""

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft

from .._camera import full_poses
from .._errors import ParameterError
from .._posespace import PoseSpace
from ._rowproblem import _centroid, _spread
from .._warp import _warp_into

__all__ = ["StartPose"]

#: A shared start is used by a window whose informative row nearest the start's
#: row lies at most this many rows from it (the half-height of the band the
#: correlation search covers); farther away the window searches alone.
SHARED_ROWS = 48

#: A window's start block solved around a shared start keeps it when its
#: centroid lies within this many lattice steps of the start's pose per axis.
SHARED_STEPS = 2


@dataclass(frozen=True)
class StartPose:
    """The start of a trajectory found on one window (:func:`find_start`),
    for the windows holding the same rows of the capture.

    Attributes
    ----------
    row : int
        Row of the whole image whose start block was solved.
    pose : tuple of float
        The block's centroid over ``axes``, global pose coordinates (units of
        :data:`ops.AXIS_UNITS`).
    axes : tuple of str
    """

    row: int
    pose: tuple
    axes: tuple


def _search_band(mid, height):
    """Rows the correlation search covers around the start row ``mid``."""
    half = int(max(16, min(SHARED_ROWS, height // 6)))
    return np.arange(max(0, mid - half), min(height, mid + half))


def _row_energy(distorted, valid):
    grad = np.abs(np.diff(distorted, axis=1))
    ok = valid[:, 1:] & valid[:, :-1]
    count = ok.sum(axis=1)
    return np.where(count > 0, (grad * ok).sum(axis=1) / np.maximum(count, 1), 0.0)


def _gradients(image, valid=None):
    """Smoothed x and y derivatives, float32: correlating these rather than
    intensities keeps large changed objects from dominating the score.  No-data
    (NaN, or False in ``valid``: clipped highlights, the edge of the
    reference) has no gradient, and neither has its border: filling it with
    any value would draw edges that the correlation follows."""
    ok = np.isfinite(image) if valid is None else valid & np.isfinite(image)
    if not ok.all():
        image = np.where(ok, image, _median(image[ok]) if ok.any() else 0.0)
    image = image.astype(np.float32)
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    gx, gy = cv2.Sobel(image, cv2.CV_32F, 1, 0), cv2.Sobel(image, cv2.CV_32F, 0, 1)
    if not ok.all():
        near = cv2.dilate((~ok).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        gx[near], gy[near] = 0.0, 0.0
    return gx, gy


def _median(values, samples=1024, margin=48):
    """``float(np.median(values))`` of a non-empty 1-D array without NaN, by
    selecting only the values between two order statistics of an evenly
    strided sample that bracket the middle (the whole array when they do
    not).  The warped bands of the correlation search all hold no-data, filled
    with this median before their gradients are taken."""
    n = values.size
    k = (n - 1) // 2, n // 2  # the middle order statistics (equal when n is odd)
    if n > 8 * samples:
        sample = np.sort(values[::n // samples])
        q = k[0] * sample.size // n
        lo, hi = sample[max(q - margin, 0)], sample[min(q + margin, sample.size - 1)]
        below = int(np.count_nonzero(values < lo))
        inside = values[(values >= lo) & (values <= hi)]
        if below <= k[0] and k[1] < below + inside.size:
            part = np.partition(inside, (k[0] - below, k[1] - below))
            # np.median's own arithmetic: the mean of the middle value or pair, in the
            # values' dtype (one value when n is odd: a value's double may overflow)
            return float(np.mean(part[k[0] - below:k[1] - below + 1]))
    return float(np.median(values))


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
                 for t in _gradients(problem.dist[lo:hi], problem.dist_valid[lo:hi])]
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
    correlations = [_Correlation(t, (band.size, width)) for t in templates]
    peaks = []
    img = np.empty((band.size, width), dtype=np.float32)
    for rz in rz_values:
        # the band warped in one compiled call, each row by its own pose (the
        # slow part varies along the rows); NaN where it samples no data
        pose = full_poses(np.array([[rz]]), ("rz",))
        poses = pose if problem.slow is None else pose + problem.slow.pose6(band)
        _warp_into(problem.ref, poses, problem.focal, problem.cx, problem.cy, float(band[0] + problem.dy),
                   float(problem.dx), img)
        score = sum(c.scores(i) for i, c in zip(_gradients(img), correlations))
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


class _Correlation:
    """``cv2.matchTemplate(image, template, cv2.TM_CCOEFF_NORMED)`` for many
    images of one shape against one template, with the template's spectrum
    and norm computed once (OpenCV transforms the template again on every
    call, one of its three transforms): the cross-correlation by a float32
    FFT, the windows' sums and sums of squares from float64 integral images,
    and OpenCV's rule where the normalised score leaves [-1, 1] by rounding.
    A flat template (zero norm) scores 0 everywhere, where OpenCV gives 1:
    the search rejects flat templates before it correlates."""

    def __init__(self, template, shape):
        self.th, self.tw = template.shape
        self.out = (shape[0] - self.th + 1, shape[1] - self.tw + 1)
        # rows padded to a fast length no shorter than the image's: the
        # circular correlation then equals the linear one at every output
        self.rows = cv2.getOptimalDFTSize(shape[0])
        centred = template.astype(np.float64) - float(np.mean(template, dtype=np.float64))
        self.norm = float(np.sqrt(np.sum(centred * centred)))
        padded = np.zeros((self.rows, shape[1]), np.float32)
        padded[:self.th, :self.tw] = centred
        self.spectrum = np.conj(scipy.fft.fft(scipy.fft.rfft(padded, axis=1), axis=0))

    def scores(self, image):
        """The normalised score map, float32, shape (H - h + 1, W - w + 1)."""
        (oh, ow), th, tw = self.out, self.th, self.tw
        spectrum = scipy.fft.fft(scipy.fft.rfft(image, axis=1), n=self.rows, axis=0)
        # only the output's rows are transformed back
        num = scipy.fft.irfft(scipy.fft.ifft(spectrum * self.spectrum, axis=0)[:oh], n=image.shape[1], axis=1)
        num = num[:, :ow].astype(np.float64)
        sums = cv2.integral2(image, sdepth=cv2.CV_64F, sqdepth=cv2.CV_64F)
        s, sq = (i[th:th + oh, tw:tw + ow] - i[:oh, tw:tw + ow] - i[th:th + oh, :ow] + i[:oh, :ow] for i in sums)
        t = np.sqrt(np.maximum(sq - s * s / (th * tw), 0.0)) * self.norm
        a = np.abs(num)
        out = np.where(a < t, num / np.where(t > 0, t, 1.0), np.where(a < t * 1.125, np.sign(num), 0.0))
        return out.astype(np.float32)


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
    return _refine(solver, center, rows, uncertainty, iterations, stride)[:3]


def _refine(solver, center, rows, uncertainty, iterations, stride, warm=None):
    """:func:`_refine_start`, also returning the last solve's poses with
    weight and their weights (None when nothing had weight).

    Each solve after the first starts from the weights of the one before; the
    first from ``warm`` (such a (poses, weights) pair) or else from the
    block's solve on a lattice twice as coarse.  Eq. 13 is convex: the start
    changes the work, not the optimum the solver converges to."""
    space = _block_space(solver, uncertainty, stride)
    grid = None
    for _ in range(iterations):
        # the grid is centred on the lattice point nearest the centre: when the
        # last centroid snaps to the same point, the next solve would be the
        # same problem, whose answer is in hand
        if grid is not None and np.array_equal(space.snap(center), grid):
            break
        grid = space.snap(center)
        if warm is None:
            warm = _coarse_weights(solver, rows, space, center)
        w0 = None if warm is None else _carried(warm, space, grid)
        _, poses, w, _, _ = solver.solve(rows, space, center, w0)
        cost = solver.last_cost
        c = _centroid(poses, w)
        if c is None:
            return center, np.zeros_like(center), np.inf, None
        center = c
        keep = w > 0
        warm = (poses[keep], w[keep])
    return center, _spread(poses, w, center), cost, warm


def _block_space(solver, uncertainty, stride=None):
    """The pose space of a block solve around a pose known to within
    ``uncertainty`` per axis: lattice steps ``stride`` times the parameters'
    (default :meth:`_RowProblem.rotation_stride`), half-widths wide enough for
    the row neighbourhood and the uncertainty, at least four steps."""
    params = solver.params
    steps = np.asarray(params.step) * (solver.problem.rotation_stride() if stride is None else stride)
    half = np.maximum(np.maximum(np.asarray(params.half_width) + steps, 4 * steps),
                      np.ceil(np.asarray(uncertainty) / steps) * steps + 2 * steps)
    return PoseSpace(params.axes, tuple(half), tuple(steps))


def _coarse_weights(solver, rows, space, center):
    """The block's weights on the lattice twice as coarse as ``space``'s on
    every axis (an eighth of the poses with three axes), as a start for the
    solve on ``space``: from it the active-set solver reaches the full
    lattice's support in fewer passes over all its poses than from zero.
    (poses, weights) with weight, or None."""
    coarse = PoseSpace(space.axes, space.half_width, tuple(2 * np.asarray(space.step)))
    _, poses, w, _, _ = solver.solve(rows, coarse, center)
    keep = w > 0
    return (poses[keep], w[keep]) if keep.any() else None


def _carried(warm, space, grid):
    """Weights ``warm`` = (poses (n, D), weights (n,)) on the grid of ``space``
    centred at lattice index ``grid``: each pose's weight at the grid point
    equal to it, poses off the grid's lattice or outside it dropped (a start
    for the solver, which needs none of them)."""
    poses, weights = warm
    index = poses / np.asarray(space.step)
    on = np.abs(index - np.rint(index)).max(axis=1) < 1e-6
    counts = np.asarray(space.counts)
    local = np.rint(index[on]).astype(np.int64) - grid + counts // 2
    inside = ((local >= 0) & (local < counts)).all(axis=1)
    w0 = np.zeros(space.size)
    w0[np.ravel_multi_index(local[inside].T, tuple(counts))] = weights[on][inside]
    return w0


def _choose_start(solver, start, rows):
    """The start pose among the correlation candidates whose block solve of
    eq. 13 costs least: correlation proposes, the model decides (periodic
    textures such as ploughed fields give several correlation peaks).
    ``start`` is (candidates, uncertainty per axis).  Returns the pose and
    the blur extent per axis."""
    return _choose(solver, start, rows)[:2]


def _choose(solver, start, rows):
    """:func:`_choose_start`, returning what :func:`_refine` does."""
    candidates, uncertainty = start
    # where rz steps move the block's pixels by a pixel or less, candidates
    # compete on a lattice twice as coarse in rz (half the poses of the widest
    # block systems), and the winner is refined on the full lattice around a
    # pose then known to within one coarse step
    coarse = solver.problem.rotation_stride(2)
    coarsened = coarse != solver.problem.rotation_stride()  # per axis
    best = None
    for center in candidates:
        refined = _refine(solver, np.asarray(center, dtype=np.float64), rows, uncertainty, 1, coarse)
        if best is None or refined[2] < best[2]:
            best = refined
    if (len(candidates) > 1 or coarsened.any()) and np.isfinite(best[2]):
        known = np.where(coarsened, np.asarray(solver.params.step) * coarse, uncertainty)
        # from the winner's weights: its coarse lattice lies on the full one
        best = _refine(solver, best[0], rows, known, 1, None, warm=best[3])
    return best


def _adapted_half_width(space, spread):
    """Half-widths that cover a blur of extent ``spread`` (per axis) plus one step,
    never narrower than ``space``'s."""
    steps = np.asarray(space.step)
    need = np.ceil(spread / steps - 1e-9) * steps + steps
    return tuple(np.maximum(space.half_width, need))


def _start(solver, candidates, informative, mid):
    """Start pose of the middle block and the row neighbourhood, widened to the
    blur extent of the middle row."""
    center, _ = _found_start(solver, candidates, informative, mid)
    return _neighbourhood(solver, mid, center), center


def _found_start(solver, candidates, informative, mid):
    """The start block's pose at ``mid`` and its cost (:func:`_choose`)."""
    block = _block_rows(informative, mid, solver.params.block_rows, len(informative))
    center, _, cost, _ = _choose(solver, candidates, block)
    return center, cost


def _shared_start(solver, start, informative, row0):
    """This window's start from a :class:`StartPose` found on another window
    holding the same rows (``row0``: this window's first row in the whole
    image): its start block at the informative row nearest the start's row,
    solved around the start's pose (known to a lattice step per axis: one
    pixel of motion at the image's farthest pixel with automatic steps; the
    block grid is wider still).  Returns (start row, pose), or None where
    sharing is unsound and the window must search alone: no informative row
    within :data:`SHARED_ROWS` rows of the start's, a block solve without
    weight, or a centroid more than :data:`SHARED_STEPS` steps from the
    start's pose on some axis (the window's pose is elsewhere: parallax, or
    another motion; a narrow window trades rz for ty along a flat valley of
    eq. 13 by a step or so)."""
    params = solver.params
    if tuple(start.axes) != tuple(params.axes):
        raise ParameterError(f"start: expected a pose over axes {tuple(params.axes)}, got {tuple(start.axes)}")
    rows = np.nonzero(informative)[0]
    if rows.size == 0:
        return None
    local = int(start.row) - int(row0)
    mid = int(rows[np.argmin(np.abs(rows - local))])
    if abs(mid - local) > SHARED_ROWS:
        return None
    pose = np.asarray(start.pose, dtype=np.float64)
    step = np.asarray(params.step, dtype=np.float64)
    block = _block_rows(informative, mid, params.block_rows, len(informative))
    center, _, cost, _ = _refine(solver, pose, block, step, 2, None)
    if not np.isfinite(cost) or (np.abs(center - pose) > SHARED_STEPS * step).any():
        return None
    return mid, center


def _neighbourhood(solver, mid, center):
    """The row neighbourhood: the parameters' space, widened to the blur
    extent of the start row ``mid`` solved around ``center`` (``adapt``)."""
    params = solver.params
    space = params.space
    if params.adapt:
        wide = space.widened(tuple(np.asarray(space.half_width) + np.asarray(space.step)))
        _, poses, w, _, _ = solver.solve([mid], wide, center)
        c = _centroid(poses, w)
        if c is not None:
            space = space.widened(_adapted_half_width(space, _spread(poses, w, c)))
    return space
