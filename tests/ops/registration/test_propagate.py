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
