"""``rsmb demo``: the main job end to end on an embedded default.

Builds a wide-area aerial-like scene with known changes (procedural, nothing is
downloaded), sees it through a moving rolling-shutter camera with motion blur
and an illumination gain that varies across the scene, writes both as
GeoTIFFs, runs ``detect`` on the default runtime (a local zarr store, dask
threads), scores the result against the truth and writes the report.
"""

import json
import logging
from pathlib import Path

from rsmb import ops
from rsmb import tiles
from rsmb.ops import InputError

from .detection._detect import detect
from .detection._plan import DetectConfig
from ._evaluate import evaluate
from ._synth import write_pair

__all__ = ["run_demo"]

log = logging.getLogger("rsmb")


def run_demo(out_dir="rsmb-demo", *, size=2048, tile=None, changes=40, seed=0, scheduler="threads", workers=None,
             overwrite=False):
    """Run the demo into ``out_dir``; returns a dict with the paths and scores.

    Raises
    ------
    InputError
        If ``out_dir`` holds a previous demo and ``overwrite`` is False.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: output exists and is a file")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise InputError(f"{out}: output exists and is not empty; pass --overwrite to replace it")
    tiles.check_writable(out / "pair")
    log.info("demo: synthesising a %d x %d scene with %d changes", size, size, changes)
    pair = ops.synthesize_pair((size, size), motion="inplane", gain=(0.85, 1.15), changes=changes,
                               change_size=(16, 48), noise=0.002, seed=seed)
    ref, dist = write_pair(out / "pair", pair, fmt="tif", overwrite=True,
                           meta={"motion": "inplane", "gain": [0.85, 1.15], "changes": changes, "seed": seed})
    store = out / "changes.zarr"
    summary = detect(ref, dist, store, config=DetectConfig(tile=tile), scheduler=scheduler, workers=workers,
                     overwrite=True, geotiff=out / "geotiff")
    scores = evaluate(store, out / "pair")
    from .report._report import write_report

    report = write_report(store, out / "report", overwrite=True)
    (out / "scores.json").write_text(json.dumps(scores.as_dict(), indent=2))
    return {"report": str(report), "store": str(store), "summary": summary, "scores": scores}
