import numpy as np
import pytest

from rsmb.ops._errors import InputError, ParameterError
from rsmb.ops._oracle import (
    ExactRowSolution,
    huber_objective,
    optimal_chi,
    row_objective,
    solve_row_exact,
)

K, N = 25, 200
LW, LC = 1e-3, 0.1  # chi takes residuals beyond 0.05


def _row_problem(seed, n=N, k=K):
    """F: a textured row shifted by -12..12 px (one column per pose); a sparse true w
    (3 poses, summing to 1, like a short blur); g = F w, float32 in [0, 1]."""
    rng = np.random.default_rng(seed)
    texture = np.convolve(rng.random(n + k + 8), np.ones(3) / 3, mode="same")
    F = np.stack([texture[4 + j: 4 + j + n] for j in range(k)], axis=1).astype(np.float32)
    w = np.zeros(k)
    support = rng.choice(k, 3, replace=False)
    w[support] = rng.uniform(0.2, 1.0, 3)
    w /= w.sum()
    g = (F.astype(np.float64) @ w).astype(np.float32)
    return F, g, w


@pytest.fixture(scope="module", params=[0, 1])
def no_change(request):
    F, g, w = _row_problem(request.param)
    return F, g, w, solve_row_exact(F, g, lambda_w=LW, lambda_chi=LC)


@pytest.fixture(scope="module")
def with_change():
    F, g, w = _row_problem(7)
    changed = g.copy()
    changed[80:110] += np.float32(0.4)  # an object that appeared
    return F, changed, w, solve_row_exact(F, changed, lambda_w=LW, lambda_chi=LC)


def test_solution_types_and_status(no_change):
    F, g, w, sol = no_change
    assert isinstance(sol, ExactRowSolution)
    assert sol.status == "optimal"
    assert sol.w.shape == (K,) and sol.w.dtype == np.float64
    assert sol.chi.shape == (N,) and sol.chi.dtype == np.float64
    assert np.all(sol.w >= 0)
    assert isinstance(sol.objective, float) and isinstance(sol.solve_seconds, float)
    assert sol.solve_seconds > 0
    assert 0 < sol.solver_seconds < sol.solve_seconds  # CLARABEL's own time; the rest is cvxpy compiling
    with pytest.raises(AttributeError):
        sol.status = "x"


def test_recovers_sparse_w_without_change(no_change):
    F, g, w, sol = no_change
    np.testing.assert_allclose(sol.w, w, atol=0.02)
    assert set(np.argsort(sol.w)[-3:]) == set(np.flatnonzero(w))
    assert np.max(np.abs(sol.chi)) < 1e-6


def test_optimum_not_worse_than_truth(no_change, with_change):
    for F, g, w, sol in (no_change, with_change):
        at_truth = row_objective(F, g, w, lambda_w=LW, lambda_chi=LC)
        assert sol.objective <= at_truth * (1 + 1e-9)


def test_row_objective_matches_solver(no_change, with_change):
    for F, g, w, sol in (no_change, with_change):
        implicit = row_objective(F, g, sol.w, lambda_w=LW, lambda_chi=LC)
        explicit = row_objective(F, g, sol.w, sol.chi, lambda_w=LW, lambda_chi=LC)
        assert implicit == pytest.approx(sol.objective, rel=1e-6)
        assert explicit == pytest.approx(sol.objective, rel=1e-6)
        # the soft-threshold chi is optimal for this w: never worse than the solver's
        assert implicit <= explicit * (1 + 1e-12)


def test_change_goes_to_chi(with_change):
    F, g, w, sol = with_change
    inside = np.zeros(N, bool)
    inside[80:110] = True
    # the step of 0.4 lands in chi, minus the knee lambda_chi / 2
    assert np.median(sol.chi[inside]) == pytest.approx(0.4 - LC / 2, abs=0.03)
    assert np.all(sol.chi[inside] > 0.2)
    assert np.max(np.abs(sol.chi[~inside])) < 0.05
    # and the motion is still recovered
    np.testing.assert_allclose(sol.w, w, atol=0.03)


def test_huber_equals_explicit_form_at_soft_threshold():
    rng = np.random.default_rng(3)
    F, g, _ = _row_problem(3)
    for _ in range(5):
        w = rng.uniform(0, 0.2, K)
        lc = float(rng.uniform(0.0, 0.3))
        r = g.astype(np.float64) - F.astype(np.float64) @ w
        chi = optimal_chi(r, lambda_chi=lc)
        np.testing.assert_allclose(chi, np.sign(r) * np.maximum(np.abs(r) - lc / 2, 0))
        explicit = row_objective(F, g, w, chi, lambda_w=LW, lambda_chi=lc)
        assert huber_objective(F, g, w, lambda_w=LW, lambda_chi=lc) == pytest.approx(explicit, rel=1e-12)
        assert row_objective(F, g, w, lambda_w=LW, lambda_chi=lc) == pytest.approx(explicit, rel=1e-12)
        # any other chi is worse
        other = chi + rng.normal(0, 0.01, N)
        assert row_objective(F, g, w, other, lambda_w=LW, lambda_chi=lc) > explicit


def test_weights_exclude_pixels():
    F, g, w = _row_problem(11)
    changed = g.copy()
    changed[40:90] = np.float32(1.0)  # a saturated area ...
    weights = np.ones(N)
    weights[40:90] = 0  # ... masked out as nodata
    sol = solve_row_exact(F, changed, lambda_w=LW, lambda_chi=LC, weights=weights)
    assert np.all(sol.chi[40:90] == 0)
    np.testing.assert_allclose(sol.w, w, atol=0.02)
    ref = row_objective(F, changed, sol.w, lambda_w=LW, lambda_chi=LC, weights=weights)
    assert ref == pytest.approx(sol.objective, rel=1e-6)
    assert huber_objective(F, changed, sol.w, lambda_w=LW, lambda_chi=LC, weights=weights) == pytest.approx(ref)
    # equal to solving the kept pixels only
    keep = weights > 0
    sub = solve_row_exact(F[keep], changed[keep], lambda_w=LW, lambda_chi=LC)
    assert sub.objective == pytest.approx(sol.objective, rel=1e-7)
    none = solve_row_exact(F, g, lambda_w=LW, lambda_chi=LC, weights=np.zeros(N))
    assert none.objective == 0.0 and not none.w.any()


def test_stacked_rows_share_one_w():
    """Global shutter: a block of 3 rows stacked into N = 3 * width, one w."""
    blocks = [_row_problem(s, n=60) for s in (20, 21, 22)]
    w = blocks[0][2]
    F = np.concatenate([b[0] for b in blocks])
    g = (F.astype(np.float64) @ w).astype(np.float32)
    sol = solve_row_exact(F, g, lambda_w=LW, lambda_chi=LC)
    assert sol.chi.shape == (180,)
    np.testing.assert_allclose(sol.w, w, atol=0.02)


def test_parameter_errors():
    F, g, _ = _row_problem(0)
    with pytest.raises(ParameterError, match="g"):
        solve_row_exact(F, g[:-1], lambda_w=LW, lambda_chi=LC)
    with pytest.raises(ParameterError, match="F"):
        solve_row_exact(F[:, 0], g, lambda_w=LW, lambda_chi=LC)
    with pytest.raises(ParameterError, match="lambda_w"):
        solve_row_exact(F, g, lambda_w=-1.0, lambda_chi=LC)
    with pytest.raises(ParameterError, match="lambda_chi"):
        row_objective(F, g, np.zeros(K), lambda_w=LW, lambda_chi=float("nan"))
    with pytest.raises(ParameterError, match="weights"):
        solve_row_exact(F, g, lambda_w=LW, lambda_chi=LC, weights=np.full(N, 0.5))
    with pytest.raises(ParameterError, match="w"):
        row_objective(F, g, np.zeros(K + 1), lambda_w=LW, lambda_chi=LC)
    bad = g.copy()
    bad[3] = np.nan
    with pytest.raises(InputError, match="g"):
        solve_row_exact(F, bad, lambda_w=LW, lambda_chi=LC)
