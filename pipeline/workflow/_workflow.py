"""``rsmb run WORKFLOW.yaml``: a nightly run as a list of steps.

A workflow file is validated as data (types, ranges, required keys, and the
inputs that must exist) before any step runs::

    name: nightly-example
    scheduler: threads            # or processes, synchronous, tcp://..., a scheduler file, slurm, pbs
    overwrite: true               # replace outputs of a previous night
    keep_going: false             # after a failed step, run the remaining ones
    detect:                       # defaults for every detect step (the detect options)
      tile_size: 512
      threshold: noise
    steps:
      - synth: {out_dir: runs/pair, size: 1024, motion: inplane, changes: 12, seed: 1, format: tif}
      - detect: {reference: runs/pair/reference.tif, distorted: runs/pair/distorted.tif,
                 output: runs/changes.zarr, geotiff: runs/geotiff}
      - evaluate: {store: runs/changes.zarr, truth: runs/pair}
      - report: {store: runs/changes.zarr}
      - survey: {references: [mosaic/a.tif, mosaic/b.tif], captures: "incoming/**/*.tif",
                 output: runs/survey, parallel: 3}

Relative paths, and the captures glob, are relative to the directory of the
workflow file.  An input must exist when the workflow starts unless an earlier
step writes it (a path inside an earlier step's output counts as written).
Each step calls the same library function as the command of the same name; a
detect step with ``resume: true`` whose output is finished is complete
already.  The summary of every step (status, seconds, result or reason) is
written to ``summary`` (default ``<name>.summary.json`` next to the first
detect output, else next to the workflow file), also when a step fails.

A survey step takes the options of ``rsmb survey`` (``references``,
``captures``, ``output``, ``parallel``, ``workers``, ``worker_timeout``,
``report``) and the detect options by the same names; the workflow's
``detect`` defaults are for detect steps and do not apply to it.  A survey is
resumable by nature: its ledger skips the captures done with the same inputs
and parameters, so running the workflow again redoes only what is new, failed
or changed; it takes neither ``resume`` nor the workflow's ``overwrite`` (a
capture's folder is replaced only when the capture is redone).  Its output
folder must be new, empty or an earlier survey's.  A night with failed
captures is a failed step (the others finished): its reason counts them, its
result names them, and the workflow exits 3.
"""

import json
import logging
import os
import time
from pathlib import Path

from pydantic import ValidationError

from rsmb import ops
from rsmb import tiles
from rsmb.ops import InputError, RSMBError

from ._workflow_steps import _INPUTS, _NAMED, STEPS, DetectOptions, SurveyStep, Workflow, _File, _MethodOptions

__all__ = ["Workflow", "load_workflow", "check_inputs", "run_workflow"]

log = logging.getLogger("rsmb")


def _error(path, where, exc):
    """One line for a pydantic error: the file, the step and the key."""
    errors = exc.errors()
    name = lambda e: ".".join(str(p) for p in e["loc"])  # noqa: E731
    for kind, words in (("extra_forbidden", "unknown keys"), ("missing", "missing keys")):
        keys = sorted(name(e) for e in errors if e["type"] == kind)
        if keys:
            return InputError(f"{path}: {where}{words} {keys}")
    first = errors[0]
    return InputError(f"{path}: {where}{name(first)}: {first['msg']} (got {first.get('input')!r})")


def _absolute(model, base):
    """``model`` with every relative Path field (alone or in a list) and a
    survey's captures glob made absolute against ``base``."""
    absolute = lambda v: v if v.is_absolute() else base / v  # noqa: E731
    changes = {k: absolute(v) for k, v in model if isinstance(v, Path)}
    changes.update({k: [absolute(p) for p in v] for k, v in model
                     if isinstance(v, list) and v and all(isinstance(p, Path) for p in v)})
    if isinstance(model, SurveyStep) and not os.path.isabs(model.captures):
        changes["captures"] = os.path.join(base, model.captures)
    return model.model_copy(update=changes)


def _check_options(model):
    """What pydantic cannot see of the method options (a value per axis, say):
    the config is built once here, so a bad one is refused before any step runs.
    Returns None or the problem as ``key: message``."""
    import click

    try:
        model.config()
    except click.BadParameter as exc:
        key = (exc.param_hint or "").strip("'").lstrip("-").replace("-", "_")  # as _options.bad_option quotes it
        return f"{key}: {exc.message}"
    except ops.ParameterError as exc:
        return str(exc)
    return None


def load_workflow(path):
    """Read and validate a workflow file (types, ranges, keys; see
    :func:`check_inputs` for the inputs); returns a :class:`Workflow`.

    Raises
    ------
    InputError
        Unreadable file or invalid content: one line naming the file, the step
        and the key.
    """
    import yaml

    path = Path(path).absolute()
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise InputError(f"{path}: cannot read workflow ({' '.join(str(exc).split())})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping with 'steps', got {type(data).__name__}")
    try:
        top = _File.model_validate(data)
    except ValidationError as exc:
        if exc.errors()[0]["loc"][:1] == ("steps",) and exc.errors()[0]["type"] == "too_short":
            raise InputError(f"{path}: expected a non-empty list of steps") from None
        raise _error(path, "", exc) from None
    except ops.ParameterError as exc:
        raise InputError(f"{path}: {exc}") from None
    defaults = top.detect or {}
    try:
        DetectOptions.model_validate(defaults)
    except ValidationError as exc:
        raise _error(path, "detect defaults: ", exc) from None
    base = path.parent
    steps = []
    for number, step in enumerate(top.steps, 1):
        if len(step) != 1:
            raise InputError(f"{path}: step {number}: expected one of {sorted(STEPS)} with its options")
        (kind, options), = step.items()
        if kind not in STEPS:
            raise InputError(f"{path}: step {number}: unknown step {kind!r}; expected one of {sorted(STEPS)}")
        options = {**(defaults if kind == "detect" else {}), **(options or {})}
        try:
            model = STEPS[kind].model_validate(options)
        except ValidationError as exc:
            raise _error(path, f"step {number} ({kind}): ", exc) from None
        problem = _check_options(model) if isinstance(model, _MethodOptions) else None
        if problem:
            raise InputError(f"{path}: step {number} ({kind}): {problem}")
        steps.append((kind, _absolute(model, base)))
    scheduler = top.scheduler
    if not (scheduler in _NAMED or scheduler.startswith("tcp://")):
        scheduler = str(base / scheduler)
    outputs = [m.output for k, m in steps if k == "detect"]
    name = top.name or path.stem
    summary = top.summary if top.summary is not None else (outputs[0].parent if outputs else base) / \
        f"{name}.summary.json"
    return Workflow(name=name, path=path, scheduler=scheduler, overwrite=top.overwrite, keep_going=top.keep_going,
                    summary=summary if summary.is_absolute() else base / summary, steps=steps)


def _writes(kind, model):
    if kind == "synth":
        return model.writes()
    if kind == "detect":
        return [model.output] + ([model.geotiff] if model.geotiff else [])
    if kind == "report":
        return [model.out_dir] if model.out_dir else []
    if kind == "survey":
        return [model.output]
    return []


def _check_survey(model, written):
    """A survey step's references (those on disk: georeferenced) and output
    folder (new, empty or a survey's), as ``rsmb survey`` checks them."""
    from ..archive._survey import check_output

    # a folder of reference files stands for its files, as survey reads it
    for path in tiles.expand_references([p for p in model.references if p not in written]):
        if not tiles.is_georeferenced(tiles.probe_header(path)[1]):
            raise InputError(f"references: {path}: not georeferenced (a survey pairs captures by footprint)")
    check_output(model.output, option="output")


def check_inputs(workflow):
    """Raise :class:`InputError` for the first input that does not exist and
    that no earlier step writes, or that its step cannot use (one line naming
    the file, the step and the key)."""
    written = set()
    made = lambda path: path in written or any(p in written for p in path.parents)  # noqa: E731
    for number, (kind, model) in enumerate(workflow.steps, 1):
        where = f"{workflow.path}: step {number} ({kind})"
        for key in _INPUTS[kind]:
            value = getattr(model, key)
            for path in value if isinstance(value, list) else [value]:
                if not made(path) and not path.exists():
                    raise InputError(f"{where}: {key}: {path} does not exist")
        try:
            if kind == "survey":
                _check_survey(model, {p for p in model.references if made(p)})
            if kind == "detect":
                _check_detect(model, made, workflow.overwrite)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
        written.update(_writes(kind, model))
    try:
        tiles.check_writable(workflow.summary)
    except InputError as exc:
        raise InputError(f"{workflow.path}: summary: {exc}") from None
    if not (workflow.scheduler in ("threads", "processes", "synchronous") or workflow.scheduler.startswith("tcp://")):
        from .._scheduler import check_scheduler

        try:
            check_scheduler(workflow.scheduler)
        except ops.ParameterError as exc:
            raise InputError(f"{workflow.path}: {exc}") from None


def _check_detect(model, made, overwrite):
    """A detect step's inputs on disk open as images (their headers read; a
    reference folder's files), and its outputs pass ``rsmb detect``'s own
    rules (:func:`check_outputs`), but for a finished store it resumes."""
    from ..detection._outputs import check_outputs

    for path in tiles.expand_references([] if made(model.reference) else [model.reference]):
        tiles.probe_header(path)
    if not made(model.distorted):
        tiles.probe_header(model.distorted)
    if made(model.output) or (model.resume and tiles.is_complete_store(model.output)):
        return
    check_outputs(model.output, None if model.geotiff is None or made(model.geotiff) else model.geotiff, overwrite)


class StepInterrupted(Exception):
    """A survey step whose night was stopped (SIGINT or SIGTERM): it recorded
    what finished; ``result`` is the step's result all the same."""

    def __init__(self, message, result):
        super().__init__(message)
        self.result = result


class StepFailed(RSMBError):
    """A step that ran to its end with a failure to report (a survey whose
    night had failed captures): the message is the reason, ``result`` the
    step's result all the same."""

    def __init__(self, message, result):
        super().__init__(message)
        self.result = result


def _survey_step(model, scheduler, stop=None):
    """Run a survey step (``stop``: as :func:`~rsmb.pipeline.archive._survey.survey`'s);
    its result holds the night's counts, where its summary and index are,
    and the reason of every failed capture."""
    from ..archive._survey import survey

    night = survey(model.references, model.captures, model.output, config=model.config(), scheduler=scheduler,
                   workers=model.workers, parallel=model.parallel, worker_timeout=model.worker_timeout,
                   report=model.report, settle=model.settle, stop=stop)
    result = {"output": str(model.output), "done": night.done, "skipped": night.skipped, "failed": night.failed,
              "summary": night.summary, "index": night.index,
              "failed_captures": {c.capture: c.reason for c in night.captures if c.status == "failed"}}
    if night.interrupted:
        raise StepInterrupted(f"the night was stopped ({stop.why}): finished captures recorded, the others run "
                              f"next night; see {night.summary}", result)
    if night.failed:
        raise StepFailed(f"{night.failed} of {len(night.captures)} captures failed (the others finished); "
                         f"see {night.summary}", result)
    return result


def _run_step(kind, model, workflow, scheduler, stop):
    from ..detection._detect import detect
    from .._evaluate import evaluate
    from ..report._report import write_report
    from .._synth import synth

    if kind == "synth":
        options = model.model_dump(exclude={"out_dir", "size", "format"})
        size = model.size
        paths = synth(model.out_dir, shape=(size, size) if isinstance(size, int) else size, fmt=model.format,
                      overwrite=workflow.overwrite, **options)
        return {"reference": str(paths.reference), "distorted": str(paths.distorted)}
    if kind == "detect":
        return detect(model.reference, model.distorted, model.output, config=model.config(), scheduler=scheduler,
                      workers=model.workers, overwrite=workflow.overwrite, resume=model.resume,
                      geotiff=model.geotiff).as_dict()
    if kind == "evaluate":
        return evaluate(model.store, model.truth).as_dict()
    if kind == "survey":
        return _survey_step(model, scheduler, stop)
    return {"report": str(write_report(model.store, model.out_dir, overwrite=True))}


def run_workflow(path, *, scheduler=None, stop=None):
    """Validate a workflow file, then run its steps in order.

    A failed step is recorded with its reason; the remaining steps run only
    with ``keep_going: true``.  A survey step stopped by ``stop`` (as
    :func:`~rsmb.pipeline.archive._survey.survey`'s: the command sets it on
    SIGINT and SIGTERM), or any step interrupted (KeyboardInterrupt, raised
    again), is recorded ``interrupted`` and no step runs after it.  The
    summary is written whatever happens.

    Returns
    -------
    list of dict
        Per step: ``step``, ``kind``, ``status`` ("done", "failed",
        "interrupted" or "not run"), ``seconds``, and ``result`` or
        ``reason`` (both for a survey step with failed captures or stopped).
    """
    workflow = load_workflow(path)
    check_inputs(workflow)
    scheduler = scheduler or workflow.scheduler
    results = []
    failed = stopped = False
    try:
        for number, (kind, model) in enumerate(workflow.steps, 1):
            record = {"step": number, "kind": kind}
            results.append(record)
            if stopped or (failed and not workflow.keep_going):
                record.update(status="not run", seconds=0.0)
                continue
            log.info("%s: step %d/%d: %s", workflow.name, number, len(workflow.steps), kind)
            start = time.perf_counter()
            try:
                record["result"] = _run_step(kind, model, workflow, scheduler, stop)
                record["status"] = "done"
            except StepInterrupted as exc:
                stopped = True
                record.update(status="interrupted", reason=str(exc), result=exc.result)
            except KeyboardInterrupt:
                record.update(status="interrupted", reason="interrupted before it finished (a signal)",
                              seconds=time.perf_counter() - start)
                for later, (other, _) in enumerate(workflow.steps[number:], number + 1):
                    results.append({"step": later, "kind": other, "status": "not run", "seconds": 0.0})
                raise
            except (RSMBError, OSError) as exc:
                failed = True
                record.update(status="failed", reason=" ".join(str(exc).split()))
                if isinstance(exc, StepFailed):
                    record["result"] = exc.result
                log.error("%s: step %d (%s) failed: %s", workflow.name, number, kind, record["reason"])
            record["seconds"] = time.perf_counter() - start
    finally:
        workflow.summary.parent.mkdir(parents=True, exist_ok=True)
        workflow.summary.write_text(json.dumps(results, indent=2, default=str))
        log.info("%s: %d steps; summary in %s", workflow.name, len(results), workflow.summary)
    return results
