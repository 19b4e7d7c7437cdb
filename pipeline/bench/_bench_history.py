"""The ``history`` section of ``rsmb bench``: three nights of ``rsmb survey``
into one folder, on a scene where the truth is known by construction.

- Night 1: captures a and b overlap by half; object X is in a only, object Y in
  both (one change seen by two captures: one feature, two captures).
- Night 2: capture c sees X again (persisting) and covers Y's place, where Y was
  removed (gone).
- Night 3: capture d covers X's place, where X was removed (gone).

Every capture is rendered through the forward model (rolling shutter, blur,
noise) and detected by the survey; statuses are read back from
``changes.gpkg`` after each night.  Features that touch neither object are
counted as false.  Then the end-of-night step (history, STAC catalog, map) is
replayed on a copy of the folder without them and timed in CPU-seconds: the
cost of taking in every capture of the three nights at once.
"""

import json
import shutil
import time
from pathlib import Path

import numpy as np

from rsmb import ops

from ._archive import PIXEL, CaptureSpec, scene_geo, write_capture, write_reference

__all__ = ["bench_history"]

X = (150, 110, 176, 136)  # scene rows/cols, end exclusive
Y = (210, 250, 236, 276)
SIZE = (256, 256)
# night -> [(capture name, scene origin, objects in the scene that night)]
NIGHTS = (
    [("a", (64, 64), (X, Y)), ("b", (64, 192), (X, Y))],
    [("c", (80, 48), (X,))],
    [("d", (80, 48), ())],
)
EXPECTED = {"X": ("new", "persisting", "gone"), "Y": ("new", "gone", "gone")}


def _echo(text):
    print(text, flush=True)


def _with(scene, objects):
    out = scene.copy()
    for k, (r0, c0, r1, c1) in enumerate(objects):
        out[r0:r1, c0:c1] = 0.92 if k % 2 == 0 else 0.12  # a bright roof, a dark one
    return out


def _box(rect, pad=0):
    import shapely

    r0, c0, r1, c1 = rect
    _, _, x0, _, _, y0 = scene_geo().transform
    return shapely.box(x0 + (c0 - pad) * PIXEL, y0 - (r1 + pad) * PIXEL, x0 + (c1 + pad) * PIXEL,
                       y0 - (r0 - pad) * PIXEL)


def _status(history, rect):
    """The features of ``history`` on the object ``rect``."""
    return [c for c in history.changes if c.geometry.intersects(_box(rect))]


def bench_history(workdir, *, seed=7):
    """Run the three nights; returns the statuses, counts and timings (also printed)."""
    from ..archive._history import read_history
    from ..archive._ledger import LEDGER_NAME, Ledger
    from ..archive._night_end import close_night
    from ..archive._survey import survey

    root = Path(workdir, "history")
    scene = (0.05 + 0.7 * ops.aerial_scene((384, 512), seed=seed)).astype(np.float32)
    references = write_reference(root / "reference", scene)
    out = root / "survey"
    rows, statuses, wall = [], {"X": [], "Y": []}, 0.0
    for k, captures in enumerate(NIGHTS, 1):
        for j, (name, origin, objects) in enumerate(captures):
            write_capture(root / f"night{k}" / f"{name}.tif", _with(scene, objects),
                          CaptureSpec(origin, SIZE, seed=seed + 10 * k + j, changes=0))
        start = time.perf_counter()
        result = survey(references, str(root / f"night{k}" / "*.tif"), out, report=False, settle=0)
        wall += time.perf_counter() - start
        history = read_history(out / "changes.gpkg")
        night = _night_counts(out, result.night)
        x, y = _status(history, X), _status(history, Y)
        statuses["X"].append(x[0].status if len(x) == 1 else f"{len(x)} features")
        statuses["Y"].append(y[0].status if len(y) == 1 else f"{len(y)} features")
        false = [c for c in history.changes if not c.geometry.intersects(_box(X, 4)) and not c.geometry.intersects(_box(Y, 4))]
        rows.append({"night": k, "captures": result.done, "failed": result.failed, **night,
                     "features": len(history.changes), "false_features": len(false),
                     "y_captures": len(y[0].captures) if len(y) == 1 else None})
        _echo(f"history night {k}: {result.done} capture(s) done, {result.failed} failed; tonight "
              f"{night['new']} new, {night['persisting']} persisting, {night['gone']} gone; "
              f"X {statuses['X'][-1]}, Y {statuses['Y'][-1]}"
              f"{' (seen by %d captures)' % rows[-1]['y_captures'] if k == 1 and rows[-1]['y_captures'] else ''}; "
              f"{len(history.changes)} feature(s), {len(false)} touching neither object")
    replay = root / "replay"
    shutil.copytree(out, replay, ignore=shutil.ignore_patterns("changes.gpkg", "stac", "map.png", "*.lock"))
    with Ledger(replay / LEDGER_NAME) as ledger:
        start, cpu = time.perf_counter(), time.process_time()
        record = close_night(replay, ledger, result.night, references)
        cpu, seconds = time.process_time() - cpu, time.perf_counter() - start
    ok = {name: tuple(statuses[name]) == EXPECTED[name] for name in EXPECTED}
    ok["Y one feature of two captures"] = rows[0]["y_captures"] == 2
    _echo(f"history: X {' -> '.join(statuses['X'])}, Y {' -> '.join(statuses['Y'])} (expected "
          f"{' -> '.join(EXPECTED['X'])} and {' -> '.join(EXPECTED['Y'])}): "
          f"{'as expected' if all(ok.values()) else 'NOT as expected: ' + json.dumps(ok)}; "
          f"three nights {wall:.1f} s wall; history, catalog and map of {len(record.history.footprints)} "
          f"captures at once {cpu:.2f} CPU-s ({seconds:.2f} s)")
    return {"nights": rows, "statuses": statuses, "as_expected": ok, "nights_wall_s": wall,
            "close_night_cpu_s": cpu, "close_night_s": seconds, "captures": len(record.history.footprints)}


def _night_counts(out, night):
    """new, persisting and gone of the night's layer (zeros when it has none)."""
    import pyogrio

    layer = f"night_{night}"
    if layer not in pyogrio.list_layers(out / "changes.gpkg")[:, 0]:
        return {"new": 0, "persisting": 0, "gone": 0}
    _, _, _, fields = pyogrio.raw.read(out / "changes.gpkg", layer=layer, columns=["status"])
    return {s: int(sum(v == s for v in fields[0])) for s in ("new", "persisting", "gone")}
