"""Per-row registration of a distorted capture against a reference (METHOD.md section 3).

The trajectory starts at an informative block of rows near the middle of the
capture (:mod:`ops.registration._start`), then propagates outwards row by row
(:mod:`ops.registration._propagate`), each row searching ``N(c, b, s)`` around the centroid
of its solved neighbour and warm-started from the neighbour's weights.
Homogeneous rows are not trusted for the trajectory: their centroid is
interpolated and they are solved afterwards around it.  A gain slope along the
rows is divided out and the rows solved again when it matters (:mod:`ops.registration._gain`).
"""

from dataclasses import dataclass, field

import numpy as np

from .._camera import POSE_AXES, Camera
from .._errors import ParameterError
from ._gain import GAIN_SLOPE_RESOLVE, _column_gain_guess, _fold_gain, _gain_slope
from .._oracle import optimal_chi
from .._timing import UNTIMED, StageClock
from ._params import RegistrationParams
from ._propagate import _Propagation, _shift_weights
from ._rowproblem import _centroid, _RowProblem, _shift_margin, _Solver
from ._rowsolve import _synthesize
from ._slow import estimate_slow, slow_from_trajectory
from ._start import (StartPose, _adapted_half_width, _choose_start, _coarse_search, _found_start, _neighbourhood,
                     _row_energy, _search_band, _shared_start, _start, _start_row)

__all__ = ["Registration", "find_start", "register"]


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
        Per-row centroid pose over ``axes`` in global pose coordinates (the
        row axes, then the slow ones: zero where no slow part was found).
    row_gain : ndarray, shape (H,)
        ``||w_i||_1`` per row (the illumination gain seen by that row).
    row_weights : dict
        Row -> (poses (n, D) over ``axes`` without the slow ones, weights (n,)):
        the nonzero weights of every row's final solve, on the capture
        divided by ``column_gain`` (what the depth-layer step re-renders).
    column_gain : ndarray, shape (W,), or None
        The gain along the rows folded into ``registered`` (None: none).
    row_state : ndarray, shape (H,), uint8
        1 solved, 2 homogeneous (centroid interpolated), 3 failed: no solve
        of the row met the optimality conditions (KKT to ``params.tol``,
        re-solved once with more iterations) or too few of its pixels were
        valid; its centroid is interpolated and its pixels carry no evidence
        (not valid, ``registered`` NaN, ``chi`` 0).
    axes : tuple of str
    timings : dict
        CPU-seconds of the calling thread per stage (``<stage>_s``: ``slow``
        the slow part, ``start`` the start search, ``rows`` the row solves,
        ``reanchor`` rows solved again in a block where the path jumped,
        ``gain_slope`` the gain-slope fits and the rounds of rows solved again
        after them; :func:`reground` adds ``reground``), and counts
        (``shared_start``: 1 when the rows started from the given ``start``).
    """

    registered: np.ndarray
    chi: np.ndarray
    valid: np.ndarray
    trajectory: np.ndarray
    row_gain: np.ndarray
    row_state: np.ndarray
    axes: tuple
    timings: dict = field(default_factory=dict)
    row_weights: dict = field(default_factory=dict)
    column_gain: np.ndarray | None = None
    slow: object = None

    @property
    def gain(self):
        """Illumination gain of the window: median ``||w_i||_1`` of solved rows."""
        good = self.row_state == 1
        return float(np.median(self.row_gain[good])) if good.any() else float("nan")


def register(reference, distorted, *, camera=None, params=None, reference_origin_yx=(0, 0),
             distorted_origin_yx=(0, 0), reference_valid=None, distorted_valid=None, prior=None, slow="auto",
             start=None):
    """Register a distorted capture against a reference, row by row (eq. 13).

    Parameters
    ----------
    reference : ndarray, shape (Hr, Wr), float32 in [0, 1]
        Reference window (may be larger than the distorted one: a halo); NaN
        marks nodata, as ``reference_valid`` False does.
    distorted : ndarray, shape (H, W), float32 in [0, 1]
        Captured window; NaN marks nodata, as ``distorted_valid`` False does.
    camera : Camera, optional
        Intrinsics of the *whole* image, default that of ``distorted``'s shape.
    params : RegistrationParams, optional
    reference_origin_yx, distorted_origin_yx : tuple of int
        Position of each window's pixel (0, 0) in the whole image.
    reference_valid, distorted_valid : ndarray of bool, optional
        False at nodata pixels.
    prior : ndarray, shape (H, D), optional
        A trajectory over ``params.trajectory_axes`` to search around instead of
        starting from the middle: every row searches ``N(prior_i, b, s)`` with
        the prior's slow part (used to re-solve a tile around its neighbours'
        path).
    slow : "auto", SlowPath or None
        The slow out-of-plane part of the path (``params.slow_axes``): "auto"
        estimates it from these windows (:func:`estimate_slow`); a
        :class:`SlowPath` (rows of ``distorted``) found on a wider view, such
        as the whole image at a coarser scale, is used as it is; None: no slow
        part.  Ignored with a ``prior``, which carries its own.
    start : StartPose, optional
        A start found on a window holding the same rows of the capture
        (:func:`find_start` on another tile of the band): the start block is
        solved around its pose instead of searched for, and searched for
        where that is unsound (no informative row near the start's row, or a
        pose more than two lattice steps from it).  Rolling shutter only; ignored
        with a ``prior``.

    Returns
    -------
    Registration
    """
    if start is not None and not isinstance(start, StartPose):
        raise ParameterError(f"start: expected a StartPose or None, got {type(start).__name__}")
    camera = camera or Camera.for_shape(distorted.shape)
    params = (params or RegistrationParams()).resolved(camera)
    ref, dist, dvalid = _windows(reference, distorted, reference_valid, distorted_valid)
    timings = {"slow_s": 0.0, "start_s": 0.0, "rows_s": 0.0, "reanchor_s": 0.0, "gain_slope_s": 0.0}
    clock = StageClock(timings)
    if prior is not None:
        prior = np.asarray(prior, dtype=np.float64)
        expected = (dist.shape[0], len(params.trajectory_axes))
        if prior.shape != expected:
            raise ParameterError(f"prior: expected shape {expected}, got {prior.shape}")
        slow = slow_from_trajectory(prior, params.trajectory_axes)
        prior = prior[:, :len(params.axes)]
    else:
        slow = _slow_part(slow, params, ref, dist, dvalid, camera, reference_origin_yx, distorted_origin_yx, clock)
    args = (camera, params, reference_origin_yx, distorted_origin_yx, prior)
    # eq. 13 has one gain per row: a gain changing along the rows by more than a
    # few per cent biases the poses, so a slope fitted to the registration is
    # divided out of the capture and the rows are solved again (at most twice)
    # the rounds after the first count as the gain slope's
    factor, scaled = None, dist
    for attempt in range(3):
        rounds = clock if attempt == 0 else StageClock()
        out, delta = _solve_rows(ref, scaled, dvalid, *args, slow, rounds, start)
        if attempt:
            timings["gain_slope_s"] += sum(rounds.seconds.values())
        else:
            timings["shared_start"] = int(start is not None and out.shared_start)
        with clock.stage("gain_slope"):
            more = _gain_slope(out, scaled, delta) if params.gain_slope else None
        if more is None:
            break
        resolve = np.abs(more - 1.0).max() > GAIN_SLOPE_RESOLVE
        if resolve and attempt == 0:
            # a fit after a biased solve falls short of the slope; column-block
            # brightness is the better first estimate when it agrees and is larger
            with clock.stage("gain_slope"):
                guess = _column_gain_guess(ref, dist, dvalid, reference_origin_yx, distorted_origin_yx)
            if guess is not None and (guess[-1] - guess[0]) / (more[-1] - more[0]) > 1.0:
                more = guess
        factor = more if factor is None else factor * more
        if not resolve:
            break
        scaled = dist / factor
    if factor is not None:
        with clock.stage("gain_slope"):
            _fold_gain(out, dist, factor, delta)
    out.no_evidence_where_failed()
    trajectory = np.concatenate([out.trajectory, _slow_columns(slow, params.slow_axes, dist.shape[0])], axis=1)
    return Registration(out.registered, out.chi, out.valid, trajectory, out.row_gain, out.row_state,
                        params.trajectory_axes, timings, out.weights, factor, slow)


def find_start(reference, distorted, *, camera=None, params=None, reference_origin_yx=(0, 0),
               distorted_origin_yx=(0, 0), reference_valid=None, distorted_valid=None, slow="auto"):
    """The start of :func:`register`'s trajectory on these windows, alone: the
    correlation search and the block solve that picks among its candidates,
    for the windows that hold the same rows (``register(..., start=)``).

    Parameters are those of :func:`register`.

    Returns
    -------
    StartPose or None
        None when the window has no informative row or the block solve found
        no weight: every window then searches alone.
    """
    camera = camera or Camera.for_shape(distorted.shape)
    params = (params or RegistrationParams()).resolved(camera)
    ref, dist, dvalid = _windows(reference, distorted, reference_valid, distorted_valid)
    slow = _slow_part(slow, params, ref, dist, dvalid, camera, reference_origin_yx, distorted_origin_yx, None)
    solver = _solver(ref, dist, dvalid, camera, params, reference_origin_yx, distorted_origin_yx, None, slow, UNTIMED)
    informative = _informative(dist, dvalid, params)
    if not informative.any():
        return None
    mid = _start_row(informative, dist.shape[0])
    candidates = _coarse_search(solver.problem, params, _search_band(mid, dist.shape[0]))
    center, cost = _found_start(solver, candidates, informative, mid)
    if not np.isfinite(cost):
        return None
    return StartPose(int(mid + distorted_origin_yx[0]), tuple(float(v) for v in center), tuple(params.axes))


def _windows(reference, distorted, reference_valid, distorted_valid):
    """The windows as the solves take them: float32, the reference NaN where
    not valid, the capture 0 there, and the capture's valid mask."""
    ref = np.array(reference, dtype=np.float32)
    if reference_valid is not None:
        ref[~np.asarray(reference_valid, bool)] = np.nan
    dist = np.asarray(distorted, dtype=np.float32)
    dvalid = np.isfinite(dist)  # NaN: no-data, as False in distorted_valid
    if distorted_valid is not None:
        dvalid &= np.asarray(distorted_valid, bool)
    return ref, np.where(dvalid, dist, np.float32(0.0)), dvalid


def _slow_part(slow, params, ref, dist, dvalid, camera, reference_origin_yx, distorted_origin_yx, clock):
    """The slow part :func:`register` uses (its ``slow`` argument checked,
    "auto" estimated on the windows, timed as ``slow`` on ``clock``)."""
    if not params.slow_axes:
        return None
    if isinstance(slow, str):
        if slow != "auto":
            raise ParameterError(f"slow: expected 'auto', a SlowPath or None, got {slow!r}")
        with (clock or StageClock()).stage("slow"):
            return estimate_slow(ref, dist, dvalid, camera=camera, reference_origin_yx=reference_origin_yx,
                                 distorted_origin_yx=distorted_origin_yx, axes=params.slow_axes,
                                 limit=2.0 * params.slow_search)
    if slow is not None and slow.rotation.shape[0] != dist.shape[0]:
        raise ParameterError(f"slow: expected a path of {dist.shape[0]} rows, got {slow.rotation.shape[0]}")
    return slow


def _solver(ref, dist, dvalid, camera, params, reference_origin_yx, distorted_origin_yx, prior, slow, clock):
    """The row problem of the windows and its solver."""
    row_pad = int(np.ceil(3 * max([params.half_width[d] for d, a in enumerate(params.axes) if a == "ty"] + [0])))
    problem = _RowProblem(ref, dist, dvalid, camera, reference_origin_yx, distorted_origin_yx, params.axes,
                          params.step, _shift_margin(params, prior), row_pad + 4, slow)
    return _Solver(problem, params, clock)


def _informative(dist, dvalid, params):
    """Rows whose texture (mean absolute horizontal gradient) reaches
    ``params.homogeneous`` times the median row's: the rows trusted for the path."""
    energy = _row_energy(dist, dvalid)
    if not (energy > 0).any():
        return energy > 0
    return energy >= params.homogeneous * np.median(energy[energy > 0])


def _slow_columns(slow, axes, height):
    """The slow axes' columns (H, len(axes)) of the trajectory (zero without a slow part)."""
    out = np.zeros((height, len(axes)))
    if slow is not None:
        pose6 = slow.pose6(np.arange(height))
        for q, a in enumerate(axes):
            out[:, q] = pose6[:, POSE_AXES.index(a)]
    return out


def _solve_rows(ref, dist, dvalid, camera, params, reference_origin_yx, distorted_origin_yx, prior, slow, clock,
                start=None):
    """Every row of ``dist`` against ``ref`` (eq. 13; rolling shutter: from
    ``start``, a :class:`StartPose`, where it is sound): outputs and the
    Huber delta; CPU-seconds per stage into ``clock`` (a :class:`StageClock`)."""
    solver = _solver(ref, dist, dvalid, camera, params, reference_origin_yx, distorted_origin_yx, prior, slow, clock)
    height, width = dist.shape
    out = _Outputs(height, width, len(params.axes))
    with clock.stage("start"):
        informative = _informative(dist, dvalid, params)
        mid = _start_row(informative, height)
    if prior is not None:
        with clock.stage("rows"):
            _register_prior(solver, prior, informative, out)
    elif params.shutter == "global":
        with clock.stage("start"):
            candidates = _coarse_search(solver.problem, params, _search_band(mid, height))
        with clock.stage("rows"):
            _register_global(solver, candidates, informative, out)
    else:
        _register_rolling(solver, informative, mid, out, start, distorted_origin_yx[0])
    return out, solver.delta


class _Outputs:
    def __init__(self, height, width, dims):
        self.registered = np.full((height, width), np.nan, dtype=np.float32)
        self.chi = np.zeros((height, width), dtype=np.float32)
        self.valid = np.zeros((height, width), dtype=bool)
        self.trajectory = np.full((height, dims), np.nan)
        self.row_gain = np.zeros(height)
        self.row_state = np.zeros(height, dtype=np.uint8)
        self.weights = {}  # row -> (poses, weights) of its final solve, nonzero weights only
        self.shared_start = False  # the rows started from a given StartPose

    def no_evidence_where_failed(self):
        """Rows in state 3 (no solution that meets the optimality conditions)
        carry no evidence: not valid, registered NaN, no change term, no
        weights to render."""
        failed = self.row_state == 3
        self.valid[failed] = False
        self.registered[failed] = np.nan
        self.chi[failed] = 0.0
        for i in np.nonzero(failed)[0]:
            self.weights.pop(int(i), None)

    def keep_weights(self, row, poses, w):
        keep = w > 0
        self.weights[row] = (poses[keep], w[keep])

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


def _register_rolling(solver, informative, mid, out, start, row0):
    """Start near the middle (around ``start``, a :class:`StartPose`, when it
    is sound: :func:`_shared_start`; ``row0``: the window's first row in the
    image), propagate outwards row by row."""
    with solver.clock.stage("start"):
        shared = None if start is None else _shared_start(solver, start, informative, row0)
        if shared is None:
            candidates = _coarse_search(solver.problem, solver.params, _search_band(mid, len(informative)))
            space, center = _start(solver, candidates, informative, mid)
        else:
            mid, center = shared
            space = _neighbourhood(solver, mid, center)
    with solver.clock.stage("rows"):
        run = _Propagation(solver, space, out)
        run.from_row(mid, center, informative)
        run.finish()
    offsets = run.space.offsets()
    for i, (lattice, w) in run.weights.items():
        out.keep_weights(i, run.space.lattice_poses(np.asarray(lattice)[None, :] + offsets), w)
    out.shared_start = shared is not None


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
    converged = solver.last_converged
    c = _centroid(poses, w)
    keep = w > 0
    index, poses, w = index[keep], poses[keep], w[keep]
    for i in range(height):
        a, g, valid = solver.problem.build([i], index, poses)
        out.store(i, w, a, valid, solver.problem.dist[i].astype(np.float64), solver.delta)
        out.keep_weights(i, poses, w)
        out.trajectory[i] = c if c is not None else center
        out.row_state[i] = 3 if not (converged and valid.any()) else (1 if informative[i] else 2)


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
        out.keep_weights(i, poses, w)
        c = _centroid(poses, w)
        fitted = c is not None and valid.any() and solver.last_converged
        good = informative[i] and fitted
        out.trajectory[i] = c if good else prior[i]
        out.row_state[i] = 1 if good else (2 if fitted else 3)
        previous = (space.snap(prior[i]), w)
