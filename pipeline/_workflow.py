"""``rsmb run WORKFLOW.yaml``: a nightly run as a list of steps.

A workflow file is validated as data (types, ranges, required keys, and the
inputs that must exist) before any step runs::

    name: nightly-example
    scheduler: threads            # or processes, synchronous, tcp://..., a scheduler file
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

Relative paths are relative to the directory of the workflow file.  An input
must exist when the workflow starts unless an earlier step writes it.  Each
step calls the same library function as the command of the same name; a
detect step with ``resume: true`` whose output is finished is complete
already.  The summary of every step (status, seconds, result or reason) is
written to ``summary`` (default ``<name>.summary.json`` next to the first
detect output, else next to the workflow file), also when a step fails.
"""

import json
import logging
import time
from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from rsmb import ops
from rsmb.ops import InputError, RSMBError

__all__ = ["Workflow", "load_workflow", "check_inputs", "run_workflow"]

log = logging.getLogger("rsmb")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


_Axis = Literal[ops.POSE_AXES]
_Auto = Literal["auto"]


def _per_axis(value):
    """A number, 'auto', a list of them or a comma-separated string -> a list."""
    if isinstance(value, str):
        return [v.strip() for v in value.split(",")]
    return value if isinstance(value, list) else [value]


class DetectOptions(_Model):
    """The options of ``rsmb detect`` (same names, underscores for dashes)."""

    axes: list[_Axis] = ["tx", "ty", "rz"]
    half_width: list[Annotated[float, Field(ge=0)] | _Auto] = ["auto"]
    step: list[Annotated[float, Field(gt=0)] | _Auto] = ["auto"]
    search: list[Annotated[float, Field(ge=0)]] | None = None
    slow_axes: list[Literal["rx", "ry", "none"]] = ["rx", "ry"]
    shutter: Literal["rolling", "global"] = "rolling"
    solver: Literal["fast", "exact"] = "fast"
    lambda_w: Annotated[float, Field(ge=0)] = 1e-3
    lambda_chi: Annotated[float, Field(gt=0)] = 0.02
    threshold: Literal["noise", "kapur"] | Annotated[float, Field(gt=0)] = "noise"
    min_area: Annotated[int, Field(ge=0)] = 20
    focal: Annotated[float, Field(gt=0)] | None = None
    tile_size: Annotated[int, Field(ge=32)] | None = None
    overlap: Annotated[int, Field(ge=0)] | None = None
    workers: Annotated[int, Field(ge=1)] | None = None
    resume: bool = False

    @field_validator("axes", "half_width", "step", "search", "slow_axes", mode="before")
    @classmethod
    def _split(cls, value):
        return None if value is None else _per_axis(value)

    def config(self):
        """The :class:`DetectConfig` these options ask for."""
        from .cli import build_config

        text = lambda values: ",".join(map(str, values))  # noqa: E731
        return build_config(text(self.axes), text(self.half_width), text(self.step),
                            text(self.search) if self.search else None, self.shutter, self.solver, self.lambda_w,
                            self.lambda_chi, str(self.threshold), self.min_area, self.focal, self.tile_size,
                            self.overlap, slow_axes=text(self.slow_axes))


class DetectStep(DetectOptions):
    reference: Path
    distorted: Path
    output: Path
    geotiff: Path | None = None


class SynthStep(_Model):
    out_dir: Path
    size: Annotated[int, Field(ge=32)] | tuple[Annotated[int, Field(ge=32)], Annotated[int, Field(ge=32)]] = 512
    motion: Literal[tuple(sorted(ops.MOTIONS))] = "inplane"
    shutter: Literal["rolling", "global"] = "rolling"
    exposure: Annotated[float, Field(ge=0)] | None = None
    scale: float = 1.0
    gain: Annotated[float, Field(gt=0)] | tuple[Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]] = 1.0
    changes: Annotated[int, Field(ge=0)] = 8
    noise: Annotated[float, Field(ge=0)] = 0.002
    seed: int = 0
    format: Literal["png", "tif", "npy"] = "png"

    def writes(self):
        return [self.out_dir, self.out_dir / f"reference.{self.format}", self.out_dir / f"distorted.{self.format}",
                self.out_dir / "truth"]


class EvaluateStep(_Model):
    store: Path
    truth: Path


class ReportStep(_Model):
    store: Path
    out_dir: Path | None = None


STEPS = {"synth": SynthStep, "detect": DetectStep, "evaluate": EvaluateStep, "report": ReportStep}
#: per step kind, the fields that name inputs that must exist (or be written by an earlier step)
_INPUTS = {"synth": (), "detect": ("reference", "distorted"), "evaluate": ("store", "truth"), "report": ("store",)}


class Workflow(_Model):
    """A validated workflow: its steps as typed models, paths absolute."""

    name: str
    path: Path
    scheduler: str = "threads"
    overwrite: bool = False
    keep_going: bool = False
    summary: Path
    steps: list[tuple[str, Union[SynthStep, DetectStep, EvaluateStep, ReportStep]]]


class _File(_Model):
    name: str | None = None
    scheduler: str = "threads"
    overwrite: bool = False
    keep_going: bool = False
    summary: Path | None = None
    detect: dict | None = None
    steps: Annotated[list[dict], Field(min_length=1)]

    @field_validator("scheduler")
    @classmethod
    def _scheduler(cls, value):
        from ._scheduler import check_scheduler

        if value in ("threads", "processes", "synchronous") or value.startswith("tcp://"):
            check_scheduler(value)
        return value  # a scheduler file is resolved against the workflow's directory later


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
    """``model`` with every relative Path field made absolute against ``base``."""
    changes = {k: base / v for k, v in model if isinstance(v, Path) and not v.is_absolute()}
    return model.model_copy(update=changes)


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
        steps.append((kind, _absolute(model, base)))
    scheduler = top.scheduler
    if not (scheduler in ("threads", "processes", "synchronous") or scheduler.startswith("tcp://")):
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
    return []


def check_inputs(workflow):
    """Raise :class:`InputError` for the first input that does not exist and
    that no earlier step writes (one line naming the file, the step and the key)."""
    written = set()
    for number, (kind, model) in enumerate(workflow.steps, 1):
        for key in _INPUTS[kind]:
            value = getattr(model, key)
            if value not in written and not value.exists():
                raise InputError(f"{workflow.path}: step {number} ({kind}): {key}: {value} does not exist")
        written.update(_writes(kind, model))
    if not (workflow.scheduler in ("threads", "processes", "synchronous") or workflow.scheduler.startswith("tcp://")):
        from ._scheduler import check_scheduler

        try:
            check_scheduler(workflow.scheduler)
        except ops.ParameterError as exc:
            raise InputError(f"{workflow.path}: {exc}") from None


def _run_step(kind, model, workflow, scheduler):
    from ._detect import detect
    from ._evaluate import evaluate
    from ._report import write_report
    from ._synth import synth

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
    return {"report": str(write_report(model.store, model.out_dir, overwrite=True))}


def run_workflow(path, *, scheduler=None):
    """Validate a workflow file, then run its steps in order.

    A failed step is recorded with its reason; the remaining steps run only
    with ``keep_going: true``.  The summary is written whatever happens.

    Returns
    -------
    list of dict
        Per step: ``step``, ``kind``, ``status`` ("done", "failed" or "not
        run"), ``seconds``, and ``result`` or ``reason``.
    """
    workflow = load_workflow(path)
    check_inputs(workflow)
    scheduler = scheduler or workflow.scheduler
    results = []
    failed = False
    try:
        for number, (kind, model) in enumerate(workflow.steps, 1):
            record = {"step": number, "kind": kind}
            results.append(record)
            if failed and not workflow.keep_going:
                record.update(status="not run", seconds=0.0)
                continue
            log.info("%s: step %d/%d: %s", workflow.name, number, len(workflow.steps), kind)
            start = time.perf_counter()
            try:
                record["result"] = _run_step(kind, model, workflow, scheduler)
                record["status"] = "done"
            except (RSMBError, OSError) as exc:
                failed = True
                record.update(status="failed", reason=" ".join(str(exc).split()))
                log.error("%s: step %d (%s) failed: %s", workflow.name, number, kind, record["reason"])
            record["seconds"] = time.perf_counter() - start
    finally:
        workflow.summary.parent.mkdir(parents=True, exist_ok=True)
        workflow.summary.write_text(json.dumps(results, indent=2, default=str))
        log.info("%s: %d steps; summary in %s", workflow.name, len(results), workflow.summary)
    return results
