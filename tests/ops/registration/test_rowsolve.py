"""Tests of ops.registration._rowsolve: the fast row solver of eq. 13 against the cvxpy oracle,
and the gathered (pre-warped, integer-shifted) rows against direct warps.

Row problems are built from real structure: rows of a procedural aerial scene
warped by a grid of poses (``F_i``), a known sparse blur kernel ``w`` with a
known gain, optionally a pasted change and noise.
"""

import numpy as np
import pytest

from rsmb import ops
from rsmb.ops import Camera, PoseSpace, full_poses, row_objective, solve_row_exact, solve_row_fast
from rsmb.ops.registration._rowproblem import _RowProblem
from rsmb.ops.registration._rowsolve import LIMIT, SOLVED, STALLED, _huber_nn_iterate, _kkt, _solve_huber_nn
from rsmb.ops._warp import _build_row, _gather_row, _remap_rows

SCENE_SHAPE = (128, 384)
N_PROBLEMS = 24
REL = 1e-4

# pose grids giving K between 9 and 121
SPACES = [
    PoseSpace(("tx",), 4.0, 1.0),                               # 9
    PoseSpace(("tx", "ty"), 2.0, 1.0),                          # 25
    PoseSpace(("tx", "ty"), (3.0, 2.0), 1.0),                   # 35
    PoseSpace(("tx", "ty", "rz"), (2.0, 2.0, 1.0), (1.0, 1.0, 0.5)),  # 125 -> cut to 121 below
    PoseSpace(("tx", "rz"), (5.0, 2.5), (1.0, 0.5)),            # 121
    PoseSpace(("tx", "ty"), 5.0, 1.0),                          # 121
    PoseSpace(("tx", "ty", "rz"), (2.0, 1.0, 0.5), (1.0, 1.0, 0.5)),  # 45
]


@pytest.fixture(scope="module")
def scenes():
    scene = ops.aerial_scene(SCENE_SHAPE, seed=11)
    changed, mask = ops.paste_changes(scene, count=8, size_range=(8, 24), seed=12, margin=24)
    return scene, changed, mask


def _row_matrix(image, camera, y, x0, n, poses6):
    """F (N, K) float32: row y of ``image`` warped by each pose, columns x0 .. x0 + n."""
    out = np.empty((poses6.shape[0], n), dtype=np.float32)
    valid = _build_row(image, float(y), float(x0), poses6, camera.focal, camera.center_xy[0], camera.center_xy[1], out)
    assert valid.all(), "test problem must sample inside the scene"
    return np.ascontiguousarray(out.T)


def _problem(seed, scenes):
    """One seeded row problem: (F, g, lambda_w, lambda_chi, w_true, changed)."""
    scene, changed_scene, mask = scenes
    rng = np.random.default_rng(seed)
    camera = Camera.for_shape(SCENE_SHAPE)
    space = SPACES[seed % len(SPACES)]
    _, poses = space.grid(rng.uniform(-1.5, 1.5, len(space.axes)))
    if len(poses) > 121:
        poses = poses[:121]
    poses6 = full_poses(poses, space.axes)
    k = len(poses)
    n = int(rng.integers(64, 257))
    with_change = seed % 2 == 1
    margin = 12
    if with_change:
        rows = np.nonzero(mask[margin:-margin].any(axis=1))[0] + margin
        y = int(rng.choice(rows))
        cols = np.nonzero(mask[y])[0]
        lo = max(margin, int(cols.max()) - n + 4)
        hi = min(SCENE_SHAPE[1] - margin - n, int(cols.min()) - 4)
        x0 = int(rng.integers(min(lo, hi), max(lo, hi) + 1))
    else:
        y = int(rng.integers(margin, SCENE_SHAPE[0] - margin))
        x0 = int(rng.integers(margin, SCENE_SHAPE[1] - margin - n + 1))
    F = _row_matrix(scene, camera, y, x0, n, poses6)
    source = _row_matrix(changed_scene, camera, y, x0, n, poses6) if with_change else F
    # a blur kernel on a few poses, summing to the gain
    gain = rng.uniform(0.7, 1.3)
    support = rng.choice(k, size=int(rng.integers(1, 6)), replace=False)
    w_true = np.zeros(k)
    w_true[support] = rng.dirichlet(np.ones(support.size)) * gain
    g = source.astype(np.float64) @ w_true
    if seed % 4 >= 2:
        g = g + rng.normal(0.0, 0.01, n)
    lambda_w = float(rng.choice([1e-4, 1e-3, 1e-2]))
    lambda_chi = float(rng.choice([0.01, 0.02, 0.05]))
    return F, g, lambda_w, lambda_chi, w_true, with_change and not np.array_equal(source, F)


@pytest.fixture(scope="module")
def solved(scenes):
    """Every problem solved by both solvers (the oracle is the slow part: solve once)."""
    out = []
    for seed in range(N_PROBLEMS):
        F, g, lw, lc, w_true, changed = _problem(seed, scenes)
        fast = solve_row_fast(F, g, lambda_w=lw, lambda_chi=lc)
        exact = solve_row_exact(F, g, lambda_w=lw, lambda_chi=lc)
        out.append((seed, F, g, lw, lc, w_true, changed, fast, exact))
    return out


def test_problems_cover_the_requested_range(solved):
    ks = [p[1].shape[1] for p in solved]
    ns = [p[1].shape[0] for p in solved]
    assert min(ks) == 9 and max(ks) == 121
    assert min(ns) >= 64 and max(ns) <= 256
    assert sum(p[6] for p in solved) >= N_PROBLEMS // 3  # rows crossing a pasted change


@pytest.mark.parametrize("seed", range(N_PROBLEMS))
def test_fast_matches_exact_objective(solved, seed):
    _, F, g, lw, lc, _, _, (w, chi, obj), exact = solved[seed]
    assert exact.status == "optimal"
    # the fast objective is never (meaningfully) above the oracle's
    assert obj <= exact.objective * (1 + REL)
    # the objective it reports is eq. 13 at its own w
    at_fast = row_objective(F, g, w, lambda_w=lw, lambda_chi=lc)
    at_exact = row_objective(F, g, exact.w, lambda_w=lw, lambda_chi=lc)
    assert at_fast == pytest.approx(obj, rel=1e-9)
    assert at_fast <= at_exact * (1 + REL)
    assert at_fast <= exact.objective * (1 + REL)
    # and with its own chi it is the same number
    assert row_objective(F, g, w, chi, lambda_w=lw, lambda_chi=lc) == pytest.approx(obj, rel=1e-9)


@pytest.mark.parametrize("seed", range(N_PROBLEMS))
def test_fast_w_nonnegative_and_chi_soft_threshold(solved, seed):
    _, F, g, lw, lc, _, _, (w, chi, _), _ = solved[seed]
    assert w.shape == (F.shape[1],) and chi.shape == (F.shape[0],)
    assert np.all(w >= 0)
    r = g - F.astype(np.float64) @ w
    np.testing.assert_allclose(chi, np.sign(r) * np.maximum(np.abs(r) - lc / 2, 0.0), atol=1e-12)
    np.testing.assert_allclose(chi, ops.optimal_chi(r, lambda_chi=lc), atol=1e-12)


def test_noise_free_rows_without_change_recover_gain_and_centroid(solved):
    """Sanity of the problems themselves: with no noise and no change, ||w||_1 is the gain
    (up to the l1 shrinkage) and chi vanishes."""
    checked = 0
    for seed, F, g, lw, lc, w_true, changed, (w, chi, _), _ in solved:
        if seed % 4 != 0 or lw > 1e-3:
            continue
        checked += 1
        assert w.sum() == pytest.approx(w_true.sum(), rel=0.05)
        assert np.abs(chi).max() < 1e-6
    assert checked >= 2


def test_change_lands_in_chi(solved):
    """Rows crossing a pasted change put it in chi, rows without change do not."""
    with_change = [p for p in solved if p[6] and p[0] % 4 == 1]
    assert with_change
    for seed, F, g, lw, lc, w_true, changed, (w, chi, _), _ in with_change:
        assert np.count_nonzero(chi) >= 3


def _warm_restart(F, g, lw, lc, w):
    """Iterations and objective of the solver restarted at ``w`` (KKT tol 1e-7)."""
    w_warm = w.copy()
    obj, iterations, _, _ = _solve_huber_nn(np.ascontiguousarray(F.T), g, w_warm, lw, 0.5 * lc, 1e-7, 100, 32)
    return obj, iterations, w_warm


@pytest.mark.parametrize("seed", [2, 3, 10, 13])
def test_warm_start_from_optimum_returns_immediately(solved, seed):
    _, F, g, lw, lc, _, _, (w, chi, obj), _ = solved[seed]
    obj2, iterations, w_warm = _warm_restart(F, g, lw, lc, w)
    assert iterations == 0
    np.testing.assert_array_equal(w_warm, w)
    assert obj2 == pytest.approx(obj, rel=1e-12)
    w3, chi3, obj3 = solve_row_fast(F, g, lambda_w=lw, lambda_chi=lc, w0=w)
    np.testing.assert_array_equal(w3, w)
    np.testing.assert_array_equal(chi3, chi)
    assert obj3 == pytest.approx(obj, rel=1e-12)


@pytest.mark.parametrize("seed", [0, 4, 12])
def test_solver_stops_at_its_own_optimum(solved, seed):
    """Regression: well-fitting rows (small objective) once spun to max_outer, the
    Cholesky ridge leaving a KKT residual above tol * objective with x == w."""
    _, F, g, lw, lc, _, _, (w, _, obj), exact = solved[seed]
    assert obj <= exact.objective * (1 + REL)
    _, cold_iterations, _, _ = _solve_huber_nn(np.ascontiguousarray(F.T), g, np.zeros_like(w), lw, 0.5 * lc,
                                            1e-7, 100, 32)
    _, warm_iterations, _ = _warm_restart(F, g, lw, lc, w)
    assert cold_iterations < 20
    assert warm_iterations == 0


@pytest.mark.parametrize("seed", [1, 6, 9])
def test_warm_start_from_anywhere_reaches_the_optimum(solved, seed):
    """Non-negativity holds for any warm start, negative entries included."""
    _, F, g, lw, lc, _, _, (w, _, obj), exact = solved[seed]
    rng = np.random.default_rng(100 + seed)
    w0 = rng.normal(0.0, 0.3, w.shape)
    w2, _, obj2 = solve_row_fast(F, g, lambda_w=lw, lambda_chi=lc, w0=w0)
    assert np.all(w2 >= 0)
    assert obj2 <= exact.objective * (1 + REL)
    assert obj2 == pytest.approx(obj, rel=REL)


@pytest.mark.parametrize("seed", [0, 5, 12, 17])
@pytest.mark.parametrize("variant", ["no_l1_on_w", "duplicate_poses"])
def test_fast_matches_exact_on_degenerate_problems(scenes, seed, variant):
    """lambda_w = 0 (w not sparse-regularised) and F with repeated columns (two poses
    giving the same row, e.g. rx and ty on one row): the optimum is not unique in w
    but its objective is."""
    F, g, lw, lc, _, _ = _problem(seed, scenes)
    if variant == "no_l1_on_w":
        lw = 0.0
    else:
        F = np.ascontiguousarray(np.concatenate([F, F[:, ::3]], axis=1))
    w, chi, obj = solve_row_fast(F, g, lambda_w=lw, lambda_chi=lc)
    exact = solve_row_exact(F, g, lambda_w=lw, lambda_chi=lc)
    assert np.all(w >= 0)
    assert obj <= exact.objective * (1 + REL) + 1e-12
    assert row_objective(F, g, w, lambda_w=lw, lambda_chi=lc) == pytest.approx(obj, rel=1e-9, abs=1e-15)


def _l1_regime_problem(scene, seed, noise, lambda_chi):
    """A real row, 9 tx poses, a 3-pose blur, noise far above the Huber knee
    lambda_chi / 2: almost every pixel is an outlier (the l1 part of the loss)."""
    camera = Camera.for_shape(SCENE_SHAPE)
    poses6 = full_poses(PoseSpace(("tx",), 4.0, 1.0).grid([0.0])[1], ("tx",))
    F = _row_matrix(scene, camera, 40 + seed, 60, 128, poses6)
    w_true = np.zeros(9)
    w_true[[3, 4, 5]] = [0.3, 0.4, 0.3]
    rng = np.random.default_rng(seed)
    g = F.astype(np.float64) @ w_true + rng.normal(0.0, noise, 128)
    return F, g, 1e-3, lambda_chi


@pytest.mark.parametrize("seed, noise, lambda_chi", [(0, 0.01, 1e-4), (3, 0.01, 1e-4), (16, 0.05, 0.002)])
def test_fast_solver_in_the_l1_regime(scenes, seed, noise, lambda_chi):
    """Regression: with (almost) no inlier pixels the Newton model of a stable
    partition was unbounded (zero Gram matrix) and the solver returned weights
    ~1e12 and an objective ~1e12 as converged."""
    F, g, lw, lc = _l1_regime_problem(scenes[0], seed, noise, lambda_chi)
    w, _, obj = solve_row_fast(F, g, lambda_w=lw, lambda_chi=lc)
    exact = solve_row_exact(F, g, lambda_w=lw, lambda_chi=lc)
    assert obj <= exact.objective * (1 + REL)
    assert w.sum() < 10.0


def test_zero_row_gives_zero_weights():
    rng = np.random.default_rng(5)
    F = rng.uniform(0, 1, (64, 9)).astype(np.float32)
    w, chi, obj = solve_row_fast(F, np.zeros(64), lambda_w=1e-3, lambda_chi=0.02)
    np.testing.assert_array_equal(w, 0.0)
    np.testing.assert_array_equal(chi, 0.0)
    assert obj == 0.0


# ---------------------------------------------------------------- gathered rows


def _problems_both_ways(reference, distorted, camera, ref_origin, dist_origin, axes, steps, margin):
    valid = np.ones(distorted.shape, bool)
    gathered = _RowProblem(reference, distorted, valid, camera, ref_origin, dist_origin, axes, steps, margin)
    direct = _RowProblem(reference, distorted, valid, camera, ref_origin, dist_origin, axes, steps, margin)
    assert gathered.gather
    direct.gather = False
    return gathered, direct


@pytest.mark.parametrize("ref_origin, dist_origin, space", [
    ((0, 0), (0, 0), PoseSpace(("tx", "ty", "rz"), (3.0, 3.0, 1.0), (1.0, 1.0, 0.5))),
    ((40, 60), (52, 75), PoseSpace(("tx", "ty", "rz"), (3.0, 3.0, 1.0), (1.0, 1.0, 0.5))),
    ((40, 60), (52, 75), PoseSpace(("ty", "s", "tx", "ry"), (2.0, 0.02, 2.0, 0.4), (1.0, 0.01, 1.0, 0.2))),
])
def test_gathered_rows_equal_warped_rows(scenes, ref_origin, dist_origin, space):
    """Whole-pixel tx, ty combined with other axes (and a tile origin): the
    pre-warped, shifted images give the same F as warping every pose."""
    scene = scenes[0]
    camera = Camera.for_shape((200, 480))  # the whole image the windows belong to
    ry, rx = ref_origin
    reference = scene[:, :]
    dy, dx = dist_origin[0] - ry, dist_origin[1] - rx
    distorted = scene[dy + 20:dy + 20 + 80, dx + 30:dx + 30 + 200]
    dist_origin = (dist_origin[0] + 20, dist_origin[1] + 30)
    gathered, direct = _problems_both_ways(reference, distorted, camera, ref_origin, dist_origin,
                                           space.axes, space.step, margin=12)
    rng = np.random.default_rng(7)
    for lattice in ([0, 0, 0, 0], [2, -3, 3, 2], [-4, 1, -1, -1]):
        center = np.array(lattice[:len(space.axes)]) * np.array(space.step)
        index, poses = space.grid(center)
        rows = sorted(rng.choice(distorted.shape[0], size=3, replace=False).tolist())
        a1, g1, v1 = gathered.build(rows, index, poses)
        a2, g2, v2 = direct.build(rows, index, poses)
        np.testing.assert_array_equal(v1, v2)
        assert v1.mean() > 0.5
        np.testing.assert_array_equal(g1, g2)
        np.testing.assert_allclose(a1, a2, atol=1e-5)
        # rows really differ from pose to pose (rotation and shifts act)
        assert np.abs(a1[0] - a1[-1])[v1].mean() > 0.01


def test_gather_row_kernel_against_build_row(scenes):
    """The kernel itself: a stack warped by rz only, read at integer shifts, equals
    _build_row with the translation in the pose."""
    scene = scenes[0]
    camera = Camera.for_shape(SCENE_SHAPE)
    cx, cy = camera.center_xy
    rz_values = [-1.0, 0.0, 1.5]
    stack = np.empty((len(rz_values),) + SCENE_SHAPE, np.float32)
    for s, rz in enumerate(rz_values):
        poses = np.broadcast_to(full_poses([rz], ("rz",)), (SCENE_SHAPE[0], 1, 6)).copy()
        image, valid = _remap_rows(scene, poses, camera.focal, cx, cy, SCENE_SHAPE[1], 0.0, 0.0)
        image[valid == 0] = np.nan
        stack[s] = image
    rng = np.random.default_rng(8)
    k = 30
    slot = rng.integers(0, len(rz_values), k).astype(np.int64)
    shift_x = rng.integers(-4, 5, k).astype(np.int64)
    shift_y = rng.integers(-4, 5, k).astype(np.int64)
    poses6 = full_poses(np.stack([shift_x, shift_y, np.asarray(rz_values)[slot]], -1), ("tx", "ty", "rz"))
    n, x0 = 200, 90
    for y in (20, 64, 101):
        out_g = np.empty((k, n), np.float32)
        out_b = np.empty((k, n), np.float32)
        v_g = _gather_row(stack, slot, shift_y, shift_x, y, x0, out_g)
        v_b = _build_row(scene, float(y), float(x0), poses6, camera.focal, cx, cy, out_b)
        np.testing.assert_array_equal(v_g, v_b)
        assert v_g.all()
        np.testing.assert_allclose(out_g, out_b, atol=1e-5)


def test_solved_means_the_optimality_conditions_hold(solved):
    """Every problem solved with the defaults reports SOLVED, and that status
    is checked at the point returned: the KKT violation, or the certified
    bound on the objective's excess, within the tolerance of the objective;
    the objective then lies within 1e-6 (relative) of cvxpy's."""
    for seed, F, g, lw, lc, _, _, _, exact in solved:
        a = np.ascontiguousarray(F.T)
        w = np.zeros(F.shape[1])
        obj, _, viol, status = _solve_huber_nn(a, g, w, lw, 0.5 * lc, 1e-6, 100, 8)
        assert status == SOLVED, seed
        value, viol_again, gap = _kkt(a, g, w, lw, 0.5 * lc)
        assert viol == pytest.approx(viol_again, rel=1e-6, abs=1e-12) and value == pytest.approx(obj, rel=1e-12)
        assert min(viol, gap) <= 1e-6 * obj
        assert obj <= exact.objective * (1 + 1e-6) + 1e-12, seed


def test_early_exits_no_longer_claim_convergence(solved):
    """With a tolerance rounding cannot meet, the iterations stop early (no
    step decreases the objective): the old contract read any stop before
    ``max_outer`` as converged.  The solver now solves such a row again and
    reports STALLED with a violation above the tolerance, never SOLVED; the
    iteration limit reports LIMIT."""
    stalled = 0
    for seed, F, g, lw, lc, _, _, _, _ in solved[:12]:
        a = np.ascontiguousarray(F.T)
        w = np.zeros(F.shape[1])
        obj, iterations, how, _ = _huber_nn_iterate(a, g, w, lw, 0.5 * lc, 1e-15, 100, 8)
        _, viol, gap = _kkt(a, g, w, lw, 0.5 * lc)
        if how != STALLED or min(viol, gap) <= 1e-15 * obj:
            continue
        stalled += 1
        assert iterations < 100  # what used to be read as "converged"
        w2 = np.zeros(F.shape[1])
        obj2, iterations2, viol2, status = _solve_huber_nn(a, g, w2, lw, 0.5 * lc, 1e-15, 100, 8)
        assert status == STALLED and viol2 > 1e-15 * obj2
        assert iterations2 >= iterations
    assert stalled >= 3
    # one iteration from zero cannot meet the conditions: the iterations end at
    # their limit, and the solve (with its re-solve) reports LIMIT or holds them
    for seed, F, g, lw, lc, _, _, (w_fast, _, _), _ in solved[:8]:
        a = np.ascontiguousarray(F.T)
        *_, how, _ = _huber_nn_iterate(a, g, np.zeros(F.shape[1]), lw, 0.5 * lc, 1e-6, 1, 8)
        assert how == LIMIT, seed
        w = np.zeros(F.shape[1])
        obj, _, viol, status = _solve_huber_nn(a, g, w, lw, 0.5 * lc, 1e-6, 1, 8)
        _, viol_again, gap = _kkt(a, g, w, lw, 0.5 * lc)
        assert status in (LIMIT, SOLVED)
        assert (status == SOLVED) == (min(viol_again, gap) <= 1e-6 * obj * (1 + 1e-9)), seed


def test_working_set_passes_agree_with_passes_over_every_pose(solved):
    """The solver's gradient passes over the working set only (every pose
    checked once the working set is optimal) reach the same objective as the
    previous solver's pass over every pose at every iteration, both within
    1e-6 of cvxpy's, cold and warm-started from a neighbouring problem's
    weights."""
    for (seed, F, g, lw, lc, _, _, _, exact), before in zip(solved, [None] + solved[:-1]):
        a = np.ascontiguousarray(F.T)
        starts = [np.zeros(F.shape[1])]
        if before is not None and before[1].shape == F.shape:
            starts.append(before[7][0])
        for w0 in starts:
            objectives = []
            for restricted in (True, False):
                w = w0.copy()
                obj, _, how, _ = _huber_nn_iterate(a, g, w, lw, 0.5 * lc, 1e-7, 100, 32, restricted)
                assert how == SOLVED and np.all(w >= 0)
                objectives.append(obj)
            assert objectives[0] == pytest.approx(objectives[1], rel=1e-6), seed
            assert objectives[0] <= exact.objective * (1 + 1e-6) + 1e-12, seed


@pytest.mark.parametrize("seed", range(6))
def test_line_search_is_the_exact_minimiser_along_the_step(seed):
    """The one-pass line search (pixels that cross a Huber kink searched
    apart from those that keep their side) finds the minimiser over [0, 1]
    of sum rho(r - t e) + t * slope: checked against a dense grid of t,
    refined, with pixels on both sides, crossing one and both kinks, and
    with e = 0."""
    from rsmb.ops.registration._rowsolve import _huber_value, _line_search

    rng = np.random.default_rng(seed)
    n, delta = 300, 0.05
    r = rng.normal(0.0, 0.08, n)
    e = rng.normal(0.0, 0.1, n)
    e[::17] = 0.0
    slope = float(rng.normal(0.0, 0.5))

    def phi(t):
        return sum(_huber_value(x, delta) for x in r - t * e) + t * slope

    t = _line_search(r, e, slope, delta, np.empty(n, np.int64))
    assert 0.0 <= t <= 1.0
    grid = np.linspace(0.0, 1.0, 2001)
    best = grid[np.argmin([phi(x) for x in grid])]
    fine = np.linspace(max(best - 1e-3, 0.0), min(best + 1e-3, 1.0), 2001)
    reference = min(phi(x) for x in fine)
    assert phi(t) <= reference + 1e-12 * max(abs(reference), 1.0)
    crossing = np.sum((np.abs(r) <= delta) != (np.abs(r - e) <= delta))
    assert crossing > 10  # the case exercises the kink walk
