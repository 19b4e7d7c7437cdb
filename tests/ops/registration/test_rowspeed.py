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
