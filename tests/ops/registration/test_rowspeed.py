"""The row solver's fast paths against the solver before them and against cvxpy.

The rows are a propagation in miniature: consecutive rows of a synthetic
in-plane pair (an aerial scene, pasted changes, noise), each gathered on the
default neighbourhood ``N(c, 3 steps, auto)`` around the true path and warm
started from the row before it, as :mod:`ops.registration._propagate` does.
The previous solver (``_previous_rowsolve``, the code at e25acef kept
verbatim) must reach the same objective with the same status; cvxpy's eq. 13
bounds both.
"""

import numpy as np
import pytest

from rsmb import ops
from rsmb.ops import solve_row_exact
from rsmb.ops.registration._rowproblem import _RowProblem
from rsmb.ops.registration._rowsolve import SOLVED, _admit_worst, _huber_nn_iterate, _solve_huber_nn

from . import _previous_rowsolve as previous

SHAPE = (96, 320)
ROWS = range(30, 66)


def _row_problems(seed):
    """(a (K, N) float32, g (N,), valid) of consecutive rows, the pose lattice
    centred on the true path of each row."""
    pair = ops.synthesize_pair(SHAPE, motion="inplane", changes=4, noise=0.002, seed=seed)
    params = ops.RegistrationParams().resolved(pair.camera)
    space = params.space
    problem = _RowProblem(pair.reference, pair.distorted, np.ones(SHAPE, bool), pair.camera, (0, 0), (0, 0),
                          params.axes, params.step, 40)
    axes = [ops.POSE_AXES.index(a) for a in params.axes]
    out = []
    for i in ROWS:
        index, poses = space.grid(pair.trajectory[i, axes])
        a, g, valid = problem.build([i], index, poses)
        out.append((a, g.astype(np.float64), valid))
    return out, params


@pytest.fixture(scope="module")
def rows():
    return [_row_problems(seed) for seed in (3, 4)]


def _propagate(solve, problems, params):
    """Solve the rows in order, each warm-started from the row before it."""
    delta = 0.5 * params.lambda_chi
    w = np.zeros(problems[0][0].shape[0])
    found = []
    for a, g, _ in problems:
        w = w.copy()
        obj, it, viol, status = solve(a, g, w, params.lambda_w, delta, params.tol, params.max_outer, params.max_add)
        found.append((obj, it, status, w.copy()))
    return found


def test_same_rows_same_answers_as_the_previous_solver(rows):
    """Every row: the same status (solved), the same objective within 1e-9
    relative, the same support and weights up to rounding."""
    checked = 0
    for problems, params in rows:
        new = _propagate(_solve_huber_nn, problems, params)
        old = _propagate(previous._solve_huber_nn, problems, params)
        assert problems[0][0].shape[0] >= 300  # the default neighbourhood of in-plane rows
        for (obj, _, status, w), (obj0, _, status0, w0) in zip(new, old):
            assert status == status0 == SOLVED
            assert obj == pytest.approx(obj0, rel=1e-9)
            np.testing.assert_allclose(w, w0, atol=1e-6 * max(w0.sum(), 1.0))
            checked += 1
    assert checked == 2 * len(ROWS)


def test_propagated_rows_match_cvxpy(rows):
    """Rows solved in the propagation's order reach eq. 13's optimum (cvxpy
    CLARABEL) within 1e-6 relative."""
    problems, params = rows[0]
    found = _propagate(_solve_huber_nn, problems, params)
    for q in (0, 35):
        a, g, valid = problems[q]
        exact = solve_row_exact(a.T, g, lambda_w=params.lambda_w, lambda_chi=params.lambda_chi,
                                weights=valid.astype(np.float64))
        assert exact.status == "optimal"
        assert found[q][0] <= exact.objective * (1 + 1e-6) + 1e-12
        assert found[q][0] >= exact.objective * (1 - 1e-6) - 1e-12


def test_warm_starts_on_a_wrong_support_reach_the_optimum(rows):
    """A warm start is first solved on its own support: a support that
    lacks the optimum's heaviest pose and holds a far one instead still ends
    at the cold start's objective (1e-9) and eq. 13's optimum (cvxpy, 1e-6)."""
    problems, params = rows[0]
    delta = 0.5 * params.lambda_chi
    for q in (3, 20):
        a, g, valid = problems[q]
        w = np.zeros(a.shape[0])
        obj, _, _, status = _solve_huber_nn(a, g, w, params.lambda_w, delta, params.tol, params.max_outer,
                                            params.max_add)
        assert status == SOLVED
        far = np.abs(np.arange(len(w)) - np.argmax(w))  # in lattice order: another corner of the grid
        far[w > 0] = -1
        w0 = w.copy()
        w0[np.argmax(w)] = 0.0
        w0[np.argmax(far)] = 0.5 * w.max()
        assert (w0 > 0).sum() >= 1 and not np.array_equal(w0 > 0, w > 0)
        obj2, _, _, status2 = _solve_huber_nn(a, g, w0, params.lambda_w, delta, params.tol, params.max_outer,
                                              params.max_add)
        assert status2 == SOLVED
        assert obj2 == pytest.approx(obj, rel=1e-9)
        exact = solve_row_exact(a.T, g, lambda_w=params.lambda_w, lambda_chi=params.lambda_chi,
                                weights=valid.astype(np.float64))
        assert obj2 <= exact.objective * (1 + 1e-6) + 1e-12
        assert obj2 >= exact.objective * (1 - 1e-6) - 1e-12


def test_working_sets_larger_than_the_product_cache(rows):
    """Admitting every violator at once (the re-solve's setting) makes working
    sets larger than the cache of column products holds: they are computed
    afresh, with the previous solver's answer."""
    problems, params = rows[1]
    delta = 0.5 * params.lambda_chi
    large = 0
    for a, g, _ in problems[::6]:
        w, w0 = np.zeros(a.shape[0]), np.zeros(a.shape[0])
        obj, _, how, _ = _huber_nn_iterate(a, g, w, params.lambda_w, delta, params.tol, 400, a.shape[0])
        obj0, _, how0, _ = previous._huber_nn_iterate(a, g, w0, params.lambda_w, delta, params.tol, 400, a.shape[0])
        assert how == how0 == SOLVED
        assert obj == pytest.approx(obj0, rel=1e-9)
        large += 1
    assert large == 6


@pytest.mark.parametrize("full", [True, False])
def test_admit_worst_picks_the_most_negative_gradients(full):
    """The poses admitted are the ``max_add`` most negative gradients outside
    the working set among those current (all, or those seen), lower index
    first on ties: what a full sort of the gradient picked."""
    rng = np.random.default_rng(21)
    for trial in range(200):
        k = int(rng.integers(1, 60))
        grad = np.round(rng.normal(0.0, 1.0, k), 1)  # ties happen
        work = rng.random(k) < 0.3
        seen = rng.random(k) < 0.6
        max_add = int(rng.integers(0, 10))
        eligible = ~work & (seen | full) & (grad < 0)
        order = np.lexsort((np.arange(k), grad))
        expected = work.copy()
        expected[[o for o in order if eligible[o]][:max_add]] = True
        got = work.copy()
        _admit_worst(grad, got, seen, full, max_add, np.empty(max(max_add, 1), np.int64))
        np.testing.assert_array_equal(got, expected, err_msg=str(trial))


# ------------------------------------------------ columns read from pre-warped rows


def _stack_and_gather(seed, nan_share, dxs=range(-3, 4), keep=1.0):
    """A stack of pre-warped images with no-data, and a lattice of poses
    reading it (slots by the other axis, whole-pixel shifts ``dxs``), some of
    them beyond the stack's columns; ``keep`` < 1: a random share of the
    poses only, so that rows are read at different sets of shifts."""
    rng = np.random.default_rng(seed)
    stack = rng.uniform(0.1, 0.9, (5, 40, 90)).astype(np.float32)
    stack[rng.random(stack.shape) < nan_share] = np.nan
    slot, shift_y, shift_x = [], [], []
    for rot in range(3):
        for dy in range(-2, 3):
            for dx in dxs:
                if dx == dxs[0] or rng.random() < keep:  # every row read at one shift at least
                    slot.append(1 + rot)
                    shift_y.append(dy)
                    shift_x.append(dx + (8 if seed % 2 else 0))
    return stack, np.array(slot), np.array(shift_y), np.array(shift_x)


@pytest.mark.parametrize("seed, nan_share, dxs, keep", [(0, 0.0, range(-3, 4), 1.0), (1, 0.0, range(-3, 4), 1.0),
                                                 (2, 0.002, range(-3, 4), 1.0), (3, 0.01, range(-3, 4), 1.0),
                                                 (4, 0.01, (-5, -2, 0, 4), 1.0), (5, 0.02, (-9, -1, 3), 1.0),
                                                 (7, 0.004, (-12, 0, 12), 1.0), (8, 0.01, range(-3, 4), 0.5),
                                                 (9, 0.02, (-6, -1, 0, 5), 0.6)])
def test_lattice_columns_equal_gathered_rows(seed, nan_share, dxs, keep):
    """Each pose's column read from the distinct pre-warped rows equals the
    gathered row (:func:`_gather_row`), the valid pixels are the same (no-data,
    columns beyond the stack, the capture's own no-data), and the gradient
    over every pose read from those rows equals the one over the gathered
    matrix; with shifts a pixel apart or far apart."""
    from rsmb.ops._warp import _gather_row
    from rsmb.ops.registration._propagate_kernels import _Gather, _lattice_columns, _Source
    from rsmb.ops.registration._rowsolve import _column, _dense, _gradient

    stack, slot, shift_y, shift_x = _stack_and_gather(seed, nan_share, dxs, keep)
    read_at = {}
    for k in range(len(slot)):
        read_at.setdefault((slot[k], shift_y[k]), set()).add(shift_x[k])
    assert (len({frozenset(v) for v in read_at.values()}) > 1) == (keep < 1)  # rows read at different shifts
    n, x0, y = 80, 6, 20
    rng = np.random.default_rng(50 + seed)
    g_valid = rng.random(n) > 0.05
    gathered = np.empty((len(slot), n), np.float32)
    v = _gather_row(stack, slot, shift_y, shift_x, y, x0, gathered)
    valid = (v != 0) & g_valid
    gathered[:, ~valid] = 0.0
    cols = _lattice_columns(_Source(stack, _Gather(slot, shift_y, shift_x), y, x0), g_valid,
                            np.full((len(slot), n), np.nan, np.float32))
    np.testing.assert_array_equal(cols.valid, valid)
    assert 0 < valid.sum() < n if (nan_share or seed % 2) else valid.sum() == g_valid.sum()
    assert cols.src.shape[0] == 15  # 3 slots x 5 rows: what the poses shift
    for k in range(len(slot)):
        np.testing.assert_array_equal(_column(cols, k), gathered[k])
    r = np.where(valid, rng.normal(0.0, 0.02, n), 0.0)
    grad, grad_dense = np.empty(len(slot)), np.empty(len(slot))
    _gradient(cols, r, 1e-3, 0.01, grad)
    _gradient(_dense(gathered), r, 1e-3, 0.01, grad_dense)
    np.testing.assert_allclose(grad, grad_dense, rtol=1e-12, atol=1e-15)


def test_rows_of_the_propagation_as_solved_before(rows):
    """A propagation row solved on its columns read from pre-warped rows
    (:func:`_row_step`) gives the weights, registered row and change term of
    the gathered matrix solved by the previous solver."""
    from rsmb.ops.registration._propagate_kernels import _Gather, _Row, _row_step, _Source, _Settings

    pair = ops.synthesize_pair(SHAPE, motion="inplane", changes=4, noise=0.002, seed=3)
    params = ops.RegistrationParams().resolved(pair.camera)
    space = params.space
    problem = _RowProblem(pair.reference, pair.distorted, np.ones(SHAPE, bool), pair.camera, (0, 0), (0, 0),
                          params.axes, params.step, 40)
    axes = [ops.POSE_AXES.index(a) for a in params.axes]
    settings = _Settings(params.lambda_w, 0.5 * params.lambda_chi, params.tol, params.max_outer, params.max_add, 16)
    w = np.zeros(space.size)
    for i in ROWS[::5]:
        index, poses = space.grid(pair.trajectory[i, axes])
        slots, shift_y, shift_x, y = problem.gather_args(i, index, poses)
        a, g, valid = problem.build([i], index, poses)
        w0 = w.copy()
        out = _Row(pair.distorted[i], np.ones(SHAPE[1], bool), np.empty(SHAPE[1], np.float32),
                   np.empty(SHAPE[1], np.float32), np.empty(SHAPE[1], bool))
        work = np.empty((space.size, SHAPE[1]), np.float32)
        obj, count, converged = _row_step(_Source(problem.stack, _Gather(slots, shift_y, shift_x), y, problem.margin),
                                          out, settings, w, work)
        obj0, _, _, status0 = previous._solve_huber_nn(a, g.astype(np.float64), w0, params.lambda_w,
                                                        0.5 * params.lambda_chi, params.tol, params.max_outer,
                                                        params.max_add)
        assert converged and status0 == SOLVED and count == valid.sum()
        assert obj == pytest.approx(obj0, rel=1e-9)
        np.testing.assert_allclose(w, w0, atol=1e-6 * w0.sum())
        np.testing.assert_array_equal(out.valid, valid)
        np.testing.assert_allclose(out.registered[valid], a.T.astype(np.float64)[valid] @ w0, atol=1e-5)


# ------------------------------------------------ the Lawson-Hanson factor updates


def test_factor_updates_equal_a_fresh_factorisation():
    """After poses enter (a row appended) and leave (a row removed, Givens
    rotations) in a random order, the factor still factors the free set's
    ridged Gram matrix in its order, and solves its system as a fresh
    Cholesky factorisation does."""
    from rsmb.ops.registration._rowsolve import _factor_add, _factor_remove, _factor_solve

    rng = np.random.default_rng(7)
    m = 24
    cols = rng.normal(0.5, 0.2, (m, 200)) + 0.3 * rng.normal(0.0, 1.0, (1, 200))  # correlated columns
    h = cols @ cols.T
    b = cols @ rng.normal(0.0, 1.0, 200)
    ridge = 1e-10 * h.diagonal().max()
    lmat, order, where = np.empty((m, m)), np.empty(m, np.int64), np.full(m, -1, np.int64)
    free, nf, removals = np.zeros(m, bool), 0, 0
    for step in range(300):
        p = int(rng.integers(m))
        if free[p]:
            nf = _factor_remove(lmat, order, where, nf, where[p])
            removals += 1
        else:
            where[p] = nf
            nf = _factor_add(h, lmat, order, nf, p, ridge)
        free[p] = not free[p]
        sel = order[:nf]
        assert sorted(sel) == list(np.nonzero(free)[0])
        np.testing.assert_array_equal(where[sel], np.arange(nf))
        low = lmat[:nf, :nf]
        np.testing.assert_allclose(np.tril(low) @ np.tril(low).T, h[np.ix_(sel, sel)] + ridge * np.eye(nf),
                                   rtol=0, atol=1e-10 * h.diagonal().max())
        if nf:
            z, rhs, dz = np.empty(m), np.empty(m), np.empty(m)
            _factor_solve(h, b, lmat, order, nf, z, rhs, dz)
            np.testing.assert_allclose(z[:nf], np.linalg.solve(h[np.ix_(sel, sel)], b[sel]), rtol=1e-6)
    assert removals > 100


# ------------------------------------------------ pre-warped rows made as rows read them


@pytest.mark.parametrize("slow", [False, True])
def test_rows_warped_as_read_equal_the_whole_image(slow):
    """A pre-warped image whose rows the compiled loop warps one by one as
    rows read them, in any order (:func:`_warp_rows`), holds the image warped
    at once, bit for bit, also with a slow path giving each row its own pose;
    the rows warped stay one range, and the Python side completes it."""
    from rsmb.ops.registration._propagate_kernels import _Prewarp, _warp_rows

    pair = ops.synthesize_pair(SHAPE, motion="inplane", changes=2, noise=0.002, seed=5)
    params = ops.RegistrationParams().resolved(pair.camera)
    path = None
    if slow:
        rng = np.random.default_rng(6)
        path = ops.SlowPath(np.cumsum(rng.normal(0.0, 0.02, (SHAPE[0], 2)), 0), np.linspace(-1.0, 1.0, SHAPE[0]))

    def problem():
        return _RowProblem(pair.reference, pair.distorted, np.ones(SHAPE, bool), pair.camera, (0, 0), (0, 0),
                           params.axes, params.step, 40, 13, path)

    index = np.array([0, 0, 3])
    whole, lazy = problem(), problem()
    whole_slot = whole._slot((3,), index, 1)
    full = whole.stack[whole_slot]
    slot = lazy._slot((3,), index, 1, lazy=True)
    assert tuple(lazy.warped[slot]) == (0, 0)
    prewarp = _Prewarp(lazy.stack, np.zeros((1, 1), np.int64), 0, 0, lazy.BAND, lazy.pad, lazy.margin, lazy.warped,
                       lazy.ref, lazy.slot_pose6, lazy.slot_row0, float(lazy.dx - lazy.margin), lazy.focal,
                       float(lazy.cx), float(lazy.cy))
    rows = lazy.stack_shape[0]
    for r in (40, 41, 39, 44, 30, 60):
        _warp_rows(prewarp, slot, r)
        lo, hi = lazy.warped[slot]
        assert lo <= r < hi
        np.testing.assert_array_equal(lazy.stack[slot, lo:hi], full[lo:hi])
    assert tuple(lazy.warped[slot]) == (30, 61)
    assert lazy._slot((3,), index, 1) == slot  # a full request completes it
    assert tuple(lazy.warped[slot]) == (0, rows)
    np.testing.assert_array_equal(lazy.stack[slot], full)
    assert np.isfinite(full).any()


def test_block_columns_from_rows_warped_as_needed():
    """``build`` warps only the rows of each pre-warped image its rows read:
    the same ``F_i`` as from whole images, with fewer rows warped."""
    pair = ops.synthesize_pair(SHAPE, motion="inplane", changes=2, noise=0.002, seed=8)
    params = ops.RegistrationParams().resolved(pair.camera)
    space = params.space
    axes = [ops.POSE_AXES.index(a) for a in params.axes]

    def problem():
        return _RowProblem(pair.reference, pair.distorted, np.ones(SHAPE, bool), pair.camera, (0, 0), (0, 0),
                           params.axes, params.step, 40)

    needed, whole = problem(), problem()
    for rows in ([40, 41, 42], [47]):
        index, poses = space.grid(pair.trajectory[rows[0], axes])
        a, g, valid = needed.build(rows, index, poses)
        slots = np.unique(whole.gather_args(rows[0], index, poses)[0])  # every row of these images
        a0, g0, valid0 = whole.build(rows, index, poses)
        np.testing.assert_array_equal(a, a0)
        np.testing.assert_array_equal(valid, valid0)
        np.testing.assert_array_equal(g, g0)
        assert all(tuple(whole.warped[s]) == (0, whole.stack_shape[0]) for s in slots)
    spans = needed.warped[:, 1] - needed.warped[:, 0]
    assert 0 < spans.max() < needed.stack_shape[0]
