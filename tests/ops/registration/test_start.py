"""The start search's block solves: started warm (from a lattice twice as
coarse, from the solve before, from the winning candidate) they reach the
optimum a cold start reaches, with fewer full solves."""

import dataclasses

import cv2
import numpy as np
import pytest

from rsmb import ops
from rsmb.ops.registration._rowproblem import _centroid, _RowProblem, _shift_margin, _Solver
from rsmb.ops.registration._start import (SHARED_ROWS, _block_space, _carried, _choose_start, _Correlation, _median,
                                          _refine, _refine_start, _shared_start)


def _solver(seed=3, size=192):
    """A block-solve setting on a synthetic in-plane pair (automatic steps),
    its middle rows and the true pose of the middle row."""
    pair = ops.synthesize_pair((size, size), motion="inplane", changes=3, noise=0.002, seed=seed)
    params = ops.RegistrationParams().resolved(pair.camera)
    valid = np.ones(pair.distorted.shape, bool)
    problem = _RowProblem(pair.reference.astype(np.float32), pair.distorted.astype(np.float32), valid, pair.camera,
                          (0, 0), (0, 0), params.axes, params.step, _shift_margin(params, None), 16)
    rows = np.arange(size // 2 - 3, size // 2 + 4)
    truth = pair.trajectory[size // 2, [ops.POSE_AXES.index(a) for a in params.axes]]
    return _Solver(problem, params), rows, truth


class _Counting:
    """A solver whose solves are counted (cold: started from zero)."""

    def __init__(self, solver):
        self.inner, self.cold, self.warm = solver, 0, 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def solve(self, rows, space, center, w0=None):
        if w0 is None:
            self.cold += 1
        else:
            self.warm += 1
        return self.inner.solve(rows, space, center, w0)


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (1.4, -1.2, 0.1)])
def test_a_warm_block_solve_reaches_the_cold_optimum(offset):
    solver, rows, truth = _solver()
    start = truth + np.asarray(offset)
    uncertainty = np.array([2.0, 2.0, 0.15])
    space = _block_space(solver, uncertainty)
    _, poses, w, _, _ = solver.solve(rows, space, start)  # cold, on the same grid
    cold_cost, cold_center = solver.last_cost, _centroid(poses, w)
    counting = _Counting(solver)
    center, spread, cost, warm = _refine(counting, start, rows, uncertainty, 1, None)
    assert counting.cold == 1 and counting.warm == 1  # the coarse lattice cold, the full one from it
    assert abs(cost - cold_cost) <= 1e-9 * cold_cost
    np.testing.assert_allclose(center, cold_center, atol=1e-4)
    assert np.abs(center - truth).max() < 1.0  # and it is the pose
    assert (warm[1] > 0).all() and len(warm[0]) == len(warm[1])


def test_a_second_iteration_on_the_same_grid_is_not_solved_again():
    solver, rows, truth = _solver()
    uncertainty = np.array([1.0, 1.0, 0.1])
    space = _block_space(solver, uncertainty, np.ones(3))
    first = _refine(solver, truth, rows, uncertainty, 1, np.ones(3))[0]
    counting = _Counting(solver)
    center = space.lattice_poses(space.snap(first))  # a start on the lattice point the first centroid snaps to
    again = _refine(counting, center, rows, uncertainty, 3, np.ones(3))
    # the first solve's centroid snaps back to its own grid: one full-lattice solve (and its coarse start)
    assert counting.warm == 1 and counting.cold == 1
    assert np.isfinite(again[2])
    np.testing.assert_allclose(again[0], _refine_start(solver, center, rows, uncertainty, 1, np.ones(3))[0])


def test_carried_weights_land_on_equal_poses_of_the_finer_grid():
    from rsmb.ops._posespace import PoseSpace

    fine = PoseSpace(("tx", "ty", "rz"), (2.0, 2.0, 0.2), (1.0, 1.0, 0.1))
    poses = np.array([[2.0, 0.0, 0.2], [0.0, -2.0, -0.2], [4.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    w0 = _carried((poses, np.array([0.25, 0.5, 0.75, 1.0])), fine, fine.snap([0.0, 0.0, 0.0]))
    _, grid = fine.grid([0.0, 0.0, 0.0])
    # the first two are grid poses; the third lies outside the grid and the fourth off the lattice
    np.testing.assert_allclose(w0[np.all(np.isclose(grid, poses[0]), axis=1)], [0.25])
    np.testing.assert_allclose(w0[np.all(np.isclose(grid, poses[1]), axis=1)], [0.5])
    assert w0.sum() == pytest.approx(0.75)


def test_the_chosen_start_is_the_cold_refinement_of_the_best_candidate():
    """Candidates compete on the coarse rz lattice; the winner's refinement on
    the full lattice starts from its weights and ends where a cold start does."""
    solver, rows, truth = _solver()
    wrong = truth + np.array([6.0, -5.0, 0.0])
    uncertainty = np.array([1.0, 1.0, 0.1])
    center, _ = _choose_start(solver, ([wrong, truth], uncertainty), rows)
    coarse = solver.problem.rotation_stride(2)
    coarsened = coarse != solver.problem.rotation_stride()
    known = np.where(coarsened, np.asarray(solver.params.step) * coarse, uncertainty)
    best = _refine(solver, truth, rows, uncertainty, 1, coarse)[0]
    _, poses, w, _, _ = solver.solve(rows, _block_space(solver, known), best)
    np.testing.assert_allclose(center, _centroid(poses, w), atol=1e-4)
    assert np.abs(center - truth).max() < 1.0


# --- a start shared by windows holding the same rows (the tiles of a band) ---

def _band(seed=5, shape=(224, 448), motion="inplane"):
    """A synthetic pair cut into two side-by-side windows that hold the same
    rows, each with its own reference window (a halo of ``halo`` px, NaN
    beyond the image as ``rsmb detect`` reads it)."""
    pair = ops.synthesize_pair(shape, motion=motion, changes=4, noise=0.002, seed=seed)
    halo, half = 40, shape[1] // 2
    padded = np.pad(pair.reference.astype(np.float32), halo, constant_values=np.nan)
    windows = []
    for c0 in (0, half):
        ref = padded[:, c0:c0 + half + 2 * halo]
        windows.append(dict(reference=ref, distorted=pair.distorted[:, c0:c0 + half],
                            reference_origin_yx=(-halo, c0 - halo), distorted_origin_yx=(0, c0)))
    return pair, ops.RegistrationParams(), windows


def _count_searches(monkeypatch):
    from rsmb.ops.registration import _register

    calls = []

    def counted(*args, **kw):
        calls.append(1)
        return _coarse_search(*args, **kw)

    from rsmb.ops.registration._start import _coarse_search
    monkeypatch.setattr(_register, "_coarse_search", counted)
    return calls


@pytest.mark.parametrize("seed", [5, 6, 7, 8])
@pytest.mark.parametrize("motion", ["inplane", "translation"])
def test_a_start_block_around_the_bands_start_ends_where_its_own_search_ends(motion, seed):
    """The right window's start block solved around the left window's start
    (:func:`_shared_start`) lands where the right window's own search does,
    to a small fraction of a lattice step, though the two windows' own
    starts differ by up to a step or more (rz against ty on narrow windows)."""
    from rsmb.ops.registration import _register

    pair, params, (left, right) = _band(motion=motion, seed=seed)
    start = ops.find_start(camera=pair.camera, params=params, **left)
    own = ops.find_start(camera=pair.camera, params=params, **right)
    params = params.resolved(pair.camera)
    ref, dist, valid = _register._windows(right["reference"], right["distorted"], None, None)
    solver = _register._solver(ref, dist, valid, pair.camera, params, right["reference_origin_yx"],
                               right["distorted_origin_yx"], None, None, _register.UNTIMED)
    row, center = _shared_start(solver, start, _register._informative(dist, valid, params), 0)
    assert row == own.row
    assert (np.abs(center - np.asarray(own.pose)) <= 0.15 * np.asarray(params.step)).all()


@pytest.mark.parametrize("seed", [5, 6])
@pytest.mark.parametrize("motion", ["inplane", "translation"])
def test_a_window_from_its_bands_start_tracks_the_truth(monkeypatch, motion, seed):
    """Started from the left window's start, the right window runs no search
    of its own, follows the true path as closely as the test_register cases
    ask, and most of its rows are the rows it finds alone (a start a
    hundredth of a pixel apart may tip an edge row or a re-anchoring)."""
    pair, params, (left, right) = _band(motion=motion, seed=seed)
    start = ops.find_start(camera=pair.camera, params=params, **left)
    assert start is not None and start.axes == params.axes
    truth = pair.trajectory[start.row, [ops.POSE_AXES.index(a) for a in params.axes]]
    assert np.abs(np.asarray(start.pose)[:2] - truth[:2]).max() < 0.5  # px
    alone = ops.register(camera=pair.camera, params=params, **right)
    calls = _count_searches(monkeypatch)
    shared = ops.register(camera=pair.camera, params=params, start=start, **right)
    assert not calls and shared.timings["shared_start"] == 1
    rows = (shared.row_state == 1) & (alone.row_state == 1)
    assert rows.mean() > 0.9
    idx = [ops.POSE_AXES.index(a) for a in shared.axes]
    err = shared.trajectory[rows] - pair.trajectory[rows][:, idx]
    assert np.sqrt(np.mean(err[:, :2] ** 2, axis=0)).max() < 0.25  # px
    same = np.abs(shared.trajectory[rows] - alone.trajectory[rows]).max(axis=1) <= 0.02
    assert same.mean() >= 0.8


def test_a_start_elsewhere_is_not_shared(monkeypatch):
    """A start whose pose lies several pixels off this window's (another
    motion, parallax) or whose row is far from any of this window's
    informative rows: the window searches alone, with the answer it finds alone."""
    pair, params, (left, right) = _band()
    start = ops.find_start(camera=pair.camera, params=params, **left)
    alone = ops.register(camera=pair.camera, params=params, **right)
    off = dataclasses.replace(start, pose=tuple(np.asarray(start.pose) + np.array([5.0, -4.0, 0.0])))
    far = dataclasses.replace(start, row=start.row + 10 * SHARED_ROWS)
    for other in (off, far):
        calls = _count_searches(monkeypatch)
        reg = ops.register(camera=pair.camera, params=params, start=other, **right)
        assert calls and reg.timings["shared_start"] == 0
        np.testing.assert_array_equal(reg.trajectory, alone.trajectory)


def test_a_window_without_data_has_no_start_to_share():
    pair, params, (left, _) = _band()
    empty = dict(left, distorted=np.full(left["distorted"].shape, np.nan, np.float32))
    assert ops.find_start(camera=pair.camera, params=params, **empty) is None


def test_a_start_over_other_axes_is_refused():
    pair, params, (left, right) = _band()
    start = ops.StartPose(100, (0.0, 0.0), ("tx", "ty"))
    with pytest.raises(ops.ParameterError, match="start"):
        ops.register(camera=pair.camera, params=params, start=start, **right)


def test_a_start_that_is_no_start_pose_is_refused_before_any_work():
    pair, params, (_, right) = _band()
    with pytest.raises(ops.ParameterError, match="start: expected a StartPose"):
        ops.register(camera=pair.camera, params=params, start=(100, (0.0, 0.0, 0.0)), **right)


@pytest.mark.parametrize("size", [7, 9000, 20001, 20000])
@pytest.mark.parametrize("kind", ["normal", "ties", "skewed", "constant", "huge"])
def test_median_equals_numpys(size, kind):
    """The bracketing selection gives np.median's value bit for bit, odd and
    even sizes, with ties, with a sample that misses the middle, and with
    values whose double overflows float32 (np.median takes the middle value
    alone when the size is odd)."""
    rng = np.random.default_rng(size)
    values = {"normal": rng.standard_normal(size), "ties": rng.integers(0, 5, size) * 0.25,
              "skewed": np.where(rng.random(size) < 0.5, rng.exponential(size=size), 1e6 + rng.random(size)),
              "constant": np.full(size, 0.3), "huge": rng.uniform(2e38, 3e38, size)}[kind].astype(np.float32)
    with np.errstate(over="ignore"):  # the mean of an even size's middle pair may overflow, as np.median's does
        want = float(np.median(values))
        assert _median(values) == want
    if size % 2:
        assert np.isfinite(want)
    assert _median(values.astype(np.float64)) == float(np.median(values.astype(np.float64)))


def _ccoeff_normed(image, template):
    """TM_CCOEFF_NORMED in float64, directly from its definition."""
    image, template = image.astype(np.float64), template.astype(np.float64)
    th, tw = template.shape
    t = template - template.mean()
    out = np.zeros((image.shape[0] - th + 1, image.shape[1] - tw + 1))
    for y, x in np.ndindex(out.shape):
        w = image[y:y + th, x:x + tw]
        w = w - w.mean()
        norm = np.sqrt((w * w).sum() * (t * t).sum())
        out[y, x] = (w * t).sum() / norm if norm > 1e-9 else 0.0
    return out


def test_correlation_equals_opencvs_normalised_scores():
    """The FFT correlation against a template prepared once gives the
    TM_CCOEFF_NORMED scores (float64 by definition) to float32 rounding, and
    cv2.matchTemplate's to its own float32 rounding (which grows with the
    images' mean: it correlates uncentred values), on several images of one
    shape: texture with a mean offset, a copy of the template's own window
    (score 1 there), and flat windows (no variance: score 0)."""
    rng = np.random.default_rng(7)
    shape, (th, tw) = (50, 160), (30, 140)
    template = cv2.GaussianBlur(rng.standard_normal((th, tw)).astype(np.float32), (0, 0), 1.5) + 3.0
    correlation = _Correlation(template, shape)
    images = [cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), 1.5) - 2.0 for _ in range(3)]
    images[1][9:9 + th, 17:17 + tw] = 0.5 * template + 1.0
    images[2][:, :] = 0.0
    images[2][:, 150:] = rng.standard_normal((shape[0], shape[1] - 150)).astype(np.float32)
    for image in images:
        got = correlation.scores(image)
        assert got.shape == (shape[0] - th + 1, shape[1] - tw + 1) and got.dtype == np.float32
        np.testing.assert_allclose(got, _ccoeff_normed(image, template), atol=1e-6, rtol=0)
        np.testing.assert_allclose(got, cv2.matchTemplate(image, template, cv2.TM_CCOEFF_NORMED), atol=1e-5, rtol=0)
    assert correlation.scores(images[1])[9, 17] == pytest.approx(1.0, abs=1e-6)
    assert (correlation.scores(images[2])[:, :10] == 0.0).all()
