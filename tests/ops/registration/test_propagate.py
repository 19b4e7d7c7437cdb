"""Row propagation: the compiled loop reads pre-warped images through a table
of slots that must follow the row problem's slots when they are reused."""

import numpy as np

from rsmb import ops
from rsmb.ops.registration import _propagate


def test_the_compiled_loop_never_reads_a_table_entry_of_a_reused_slot(monkeypatch):
    """Before each pre-warped image the loop asks for is made, a solve outside
    the loop (as a re-anchoring or a row off the table is) takes a slot by the
    problem's own rule, reusing the slots of bands two or more away.  Every
    time the loop is entered, each slot in its table must still hold the
    image of that entry's rotation and band (a stale entry made a tile read
    another band's image: rows a pixel off, false change), and the rows must
    be those of a run without the extra slots."""
    pair = ops.synthesize_pair((384, 256), motion="inplane", changes=4, noise=0.002, seed=3)
    kw = dict(camera=pair.camera, params=ops.RegistrationParams(slow_axes=()))
    calm = ops.register(pair.reference, pair.distorted, **kw)
    make, loop, problems, reused, checked = _propagate._Propagation._make_prewarp, _propagate._propagate_rows, [], [], []

    def under_pressure(self, other_index, band):
        problem = self.solver.problem
        problems[:] = [(problem, self._arrays)]
        if any(abs(b - band) >= 2 for _, b in problem.slots):
            spare, problem.free = problem.free, []
            generation = problem.generation
            problem._slot((10 ** 6 + len(reused),), np.zeros(len(self.step), np.int64), band, lazy=True)
            problem.free += spare
            reused.append(problem.generation != generation)
        return make(self, other_index, band)

    def entered(ctx, *args):
        if problems:
            problem, arr = problems[0]
            table = ctx.prewarp.table
            for o, b in zip(*np.nonzero(table >= 0)):
                key = ((int(o) + arr["other_lo"],) if arr["other"] >= 0 else (), int(b) + arr["band_lo"])
                assert problem.slots.get(key) == table[o, b], key
                checked.append(key)
        return loop(ctx, *args)

    monkeypatch.setattr(_propagate._Propagation, "_make_prewarp", under_pressure)
    monkeypatch.setattr(_propagate, "_propagate_rows", entered)
    pressed = ops.register(pair.reference, pair.distorted, **kw)
    assert any(reused) and checked
    np.testing.assert_array_equal(pressed.trajectory, calm.trajectory)
    np.testing.assert_array_equal(pressed.registered, calm.registered)


def test_a_row_jumps_by_how_far_its_pose_moves_the_windows_pixels():
    """A row is off the path when its pose moves the window's pixels more than
    DRIFT_PX from where the prediction puts them, all axes together: a
    rotation far from the principal point with the tx and ty that keep the
    window in place (a direction one row can hardly tell apart) moves its
    pixels by a fraction of what the rotation alone would, and is no jump
    (the rotation alone, measured at the farthest pixel, re-anchored many rows
    of a wide capture whose pixels the row's pose had hardly moved)."""
    from types import SimpleNamespace

    from rsmb.ops.registration._propagate_kernels import DRIFT_PX, _jumps, _trust_state

    problem = SimpleNamespace(dist=np.zeros((96, 512)), dx=1300, dy=900, focal=1800.0, cx=1024.0, cy=1024.0,
                              axes=("tx", "ty", "rz"))
    shifts = _propagate._corner_shifts(problem)
    per_unit = _propagate._px_per_unit(problem)
    corners = np.array([(x, y) for y in (900, 995) for x in (1300, 1811)], float) - (1024.0, 1024.0)
    # tx moves every corner by its own amount; rz by the corner's distance from the principal point per radian
    np.testing.assert_allclose(np.abs(shifts[:, :, 0]), [[1, 0]] * 4, atol=1e-6)
    np.testing.assert_allclose(np.hypot(*shifts[:, :, 2].T), np.radians(1.0) * np.hypot(*corners.T), rtol=1e-3)
    trust = _trust_state(np.zeros(3), 40)
    predicted = np.empty(3)
    theta = 1.5 * DRIFT_PX / (np.radians(1.0) * np.hypot(*corners.T).max())  # rz alone: 1.5 DRIFT_PX at the far corner
    assert _jumps(np.array([0.0, 0.0, theta]), 41, per_unit, shifts, trust, predicted)
    np.testing.assert_allclose(predicted, 0.0)
    # the same rz with the tx and ty that hold the window's centre: at most a few tenths of a pixel anywhere
    centre = shifts.mean(axis=0)
    txy = np.linalg.solve(centre[:, :2], -centre[:, 2] * theta)
    row = np.array([txy[0], txy[1], theta])
    assert np.hypot(*(shifts @ row).T).max() < 0.5 * DRIFT_PX
    assert np.max(np.abs(row) * per_unit) > DRIFT_PX  # rz alone: more than DRIFT_PX
    assert not _jumps(row, 41, per_unit, shifts, trust, predicted)
    # a real step of the path is still one: a pixel's worth of ty
    assert _jumps(np.array([0.0, 1.2 * DRIFT_PX, 0.0]), 41, per_unit, shifts, trust, predicted)
