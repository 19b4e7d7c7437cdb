"""``rsmb run WORKFLOW.yaml``: a nightly run as a list of steps.

A workflow file is read once and validated before anything runs::

    name: nightly-example
    scheduler: threads            # or processes, synchronous, tcp://..., a scheduler file
    overwrite: true               # replace outputs of a previous night
    detect:                       # defaults for every detect step (the detect options)
      tile_size: 512
      threshold: noise
    steps:
      - synth: {out_dir: runs/pair, size: 1024, motion: inplane, changes: 12, seed: 1, format: tif}
      - detect: {reference: runs/pair/reference.tif, distorted: runs/pair/distorted.tif,
                 output: runs/changes.zarr, geotiff: runs/geotiff}
      - evaluate: {store: runs/changes.zarr, truth: runs/pair}
      - report: {store: runs/changes.zarr}

Relative paths are relative to the directory the command runs in.  Each step
calls the same library function as the command of the same name.  A summary of
every step is written to ``<name>.summary.json`` next to the first detect
output (or in the current directory).
"""

import json
import logging
import time
from pathlib import Path


from rsmb.ops import InputError

__all__ = ["run_workflow", "load_workflow"]

log = logging.getLogger("rsmb")

_DETECT_KEYS = {"axes", "half_width", "step", "search", "shutter", "solver", "lambda_w", "lambda_chi", "threshold",
                "min_area", "focal", "tile_size", "overlap", "workers", "resume"}
_STEP_KEYS = {
    "synth": {"out_dir", "size", "motion", "shutter", "exposure", "scale", "gain", "changes", "noise", "seed",
              "format"},
    "detect": {"reference", "distorted", "output", "geotiff"} | _DETECT_KEYS,
    "evaluate": {"store", "truth"},
    "report": {"store", "out_dir"},
}
_REQUIRED = {"synth": {"out_dir"}, "detect": {"reference", "distorted", "output"}, "evaluate": {"store", "truth"},
             "report": {"store"}}


def load_workflow(path):
    """Read and validate a workflow file; returns the parsed dict.

    Raises
    ------
    InputError
        Unreadable file or invalid content (the message names the file and the
        offending key or step).
    """
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise InputError(f"{path}: cannot read workflow ({' '.join(str(exc).split())})") from exc
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping with 'steps', got {type(data).__name__}")
    unknown = set(data) - {"name", "scheduler", "overwrite", "detect", "steps"}
    if unknown:
        raise InputError(f"{path}: unknown keys {sorted(unknown)}")
    defaults = data.get("detect") or {}
    bad = set(defaults) - _DETECT_KEYS
    if bad:
        raise InputError(f"{path}: detect defaults: unknown keys {sorted(bad)}")
    steps = data.get("steps")
    if not isinstance(steps, list) or not steps:
        raise InputError(f"{path}: expected a non-empty list of steps")
    for number, step in enumerate(steps, 1):
        if not isinstance(step, dict) or len(step) != 1:
            raise InputError(f"{path}: step {number}: expected one of {sorted(_STEP_KEYS)} with its options")
        (kind, options), = step.items()
        if kind not in _STEP_KEYS:
            raise InputError(f"{path}: step {number}: unknown step {kind!r}; expected one of {sorted(_STEP_KEYS)}")
        options = options or {}
        bad = set(options) - _STEP_KEYS[kind]
        missing = _REQUIRED[kind] - set(options)
        if bad or missing:
            raise InputError(f"{path}: step {number} ({kind}): unknown keys {sorted(bad)}, missing {sorted(missing)}")
    return data


def _run_detect(options, defaults, scheduler, overwrite):
    from .cli import build_config
    from ._detect import detect

    o = {**defaults, **options}
    text = lambda key, default: ",".join(map(str, o[key])) if isinstance(o.get(key), list) else o.get(key, default)  # noqa: E731
    config = build_config(text("axes", "tx,ty,rz"), text("half_width", "auto"), text("step", "auto"),
                          text("search", None), o.get("shutter", "rolling"), o.get("solver", "fast"),
                          float(o.get("lambda_w", 1e-3)), float(o.get("lambda_chi", 0.02)),
                          str(o.get("threshold", "noise")), int(o.get("min_area", 20)), o.get("focal"),
                          int(o["tile_size"]) if o.get("tile_size") else None, o.get("overlap"))
    return detect(o["reference"], o["distorted"], o["output"], config=config, scheduler=scheduler,
                  workers=o.get("workers"), overwrite=overwrite, resume=bool(o.get("resume", False)),
                  geotiff=o.get("geotiff")).as_dict()


def _run_synth(o, overwrite):
    from ._synth import synth

    size = o.get("size", 512)
    ref, dist = synth(o["out_dir"], shape=(size, size) if isinstance(size, int) else tuple(size),
                      motion=o.get("motion", "inplane"), shutter=o.get("shutter", "rolling"),
                      exposure=o.get("exposure"), scale=o.get("scale", 1.0), gain=o.get("gain", 1.0),
                      changes=o.get("changes", 8), noise=o.get("noise", 0.002), seed=o.get("seed", 0),
                      fmt=o.get("format", "png"), overwrite=overwrite)
    return {"reference": str(ref), "distorted": str(dist)}


def run_workflow(path, *, scheduler=None):
    """Run every step of a workflow file in order; returns the list of step
    summaries (also written as JSON)."""
    from ._evaluate import evaluate
    from ._report import write_report

    data = load_workflow(path)
    scheduler = scheduler or data.get("scheduler", "threads")
    overwrite = bool(data.get("overwrite", False))
    defaults = data.get("detect") or {}
    name = data.get("name", Path(path).stem)
    results = []
    for number, step in enumerate(data["steps"], 1):
        (kind, options), = step.items()
        options = options or {}
        log.info("%s: step %d/%d: %s", name, number, len(data["steps"]), kind)
        start = time.perf_counter()
        if kind == "synth":
            result = _run_synth(options, overwrite)
        elif kind == "detect":
            result = _run_detect(options, defaults, scheduler, overwrite)
        elif kind == "evaluate":
            result = evaluate(options["store"], options["truth"]).as_dict()
        else:
            result = {"report": str(write_report(options["store"], options.get("out_dir"), overwrite=True))}
        results.append({"step": number, "kind": kind, "seconds": time.perf_counter() - start, "result": result})
    outputs = [s["result"]["output"] for s in results if s["kind"] == "detect"]
    where = Path(outputs[0]).parent if outputs else Path(".")
    summary_path = where / f"{name}.summary.json"
    summary_path.write_text(json.dumps(results, indent=2, default=str))
    log.info("%s: %d steps done; summary in %s", name, len(results), summary_path)
    return results
