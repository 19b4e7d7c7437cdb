"""The steps of a workflow file as typed models (pydantic): what each step
takes, which of its fields name inputs that must exist, and the file's own
keys.  :mod:`pipeline.workflow._workflow` reads a file into them and runs it."""

from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, field_validator

from rsmb import ops

from .._options import METHOD_DEFAULTS as _D
from .._options import SYNTH_DEFAULTS as _S
from ..archive._ledger import SETTLE

__all__ = ["DetectOptions", "DetectStep", "EvaluateStep", "ReportStep", "STEPS", "SurveyStep", "SynthStep",
           "Workflow"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


_Axis = Literal[ops.POSE_AXES]
_Auto = Literal["auto"]


def _per_axis(value):
    """A number, 'auto', a list of them or a comma-separated string -> a list."""
    if isinstance(value, str):
        return [v.strip() for v in value.split(",")]
    return value if isinstance(value, list) else [value]


def _listed(text):
    """A default of :data:`METHOD_DEFAULTS` in the list form of these models."""
    return [v if v.isalpha() else float(v) for v in _per_axis(text)]


class _MethodOptions(_Model):
    """The options of the method shared by ``rsmb detect`` and ``rsmb survey``
    (same names, underscores for dashes; the same defaults, from
    :data:`pipeline._options.METHOD_DEFAULTS`)."""

    axes: list[_Axis] = _listed(_D["axes"])
    half_width: list[Annotated[float, Field(ge=0)] | _Auto] = _listed(_D["half_width"])
    step: list[Annotated[float, Field(gt=0)] | _Auto] = _listed(_D["step"])
    search: list[Annotated[float, Field(ge=0)]] | None = _D["search"]
    slow_axes: list[Literal["rx", "ry", "none"]] = _listed(_D["slow_axes"])
    shutter: Literal["rolling", "global"] = _D["shutter"]
    solver: Literal["fast", "exact"] = _D["solver"]
    lambda_w: Annotated[float, Field(ge=0)] = _D["lambda_w"]
    lambda_chi: Annotated[float, Field(gt=0)] = _D["lambda_chi"]
    threshold: Literal["noise", "kapur"] | Annotated[float, Field(gt=0)] = _D["threshold"]
    min_area: Annotated[int, Field(ge=0)] = _D["min_area"]
    no_layers: bool = _D["no_layers"]
    focal: Annotated[float, Field(gt=0)] | None = _D["focal"]
    tile_size: Annotated[int, Field(ge=32)] | None = _D["tile_size"]
    overlap: Annotated[int, Field(ge=0)] | None = _D["overlap"]

    @field_validator("axes", "half_width", "step", "search", "slow_axes", mode="before")
    @classmethod
    def _split(cls, value):
        return None if value is None else _per_axis(value)

    def config(self):
        """The :class:`DetectConfig` these options ask for."""
        from .._options import build_config

        text = lambda values: ",".join(map(str, values))  # noqa: E731
        return build_config(text(self.axes), text(self.half_width), text(self.step),
                            text(self.search) if self.search else None, self.shutter, self.solver, self.lambda_w,
                            self.lambda_chi, str(self.threshold), self.min_area, self.focal, self.tile_size,
                            self.overlap, slow_axes=text(self.slow_axes), layers=not self.no_layers)


class DetectOptions(_MethodOptions):
    """The options of ``rsmb detect`` (same names, underscores for dashes)."""

    workers: Annotated[int, Field(ge=1)] | None = None
    resume: bool = False


class DetectStep(DetectOptions):
    reference: Path
    distorted: Path
    output: Path
    geotiff: Path | None = None


class SynthStep(_Model):
    out_dir: Path
    size: Annotated[int, Field(ge=32)] | tuple[Annotated[int, Field(ge=32)], Annotated[int, Field(ge=32)]] = \
        _S["shape"]
    motion: Literal[tuple(sorted(ops.MOTIONS))] = _S["motion"]
    shutter: Literal["rolling", "global"] = _S["shutter"]
    exposure: Annotated[float, Field(ge=0)] | None = _S["exposure"]
    scale: float = _S["scale"]
    gain: Annotated[float, Field(gt=0)] | tuple[Annotated[float, Field(gt=0)], Annotated[float, Field(gt=0)]] = \
        _S["gain"]
    changes: Annotated[int, Field(ge=0)] = _S["changes"]
    noise: Annotated[float, Field(ge=0)] = _S["noise"]
    seed: int = _S["seed"]
    format: Literal["png", "tif", "npy"] = _S["fmt"]

    def writes(self):
        return [self.out_dir, self.out_dir / f"reference.{self.format}", self.out_dir / f"distorted.{self.format}",
                self.out_dir / "truth"]


class EvaluateStep(_Model):
    store: Path
    truth: Path


class ReportStep(_Model):
    store: Path
    out_dir: Path | None = None


class SurveyStep(_MethodOptions):
    """A night of captures (``rsmb survey``): the detect options, and where
    the night's captures, references and results are."""

    references: Annotated[list[Path], Field(min_length=1)]
    captures: str
    output: Path
    parallel: Annotated[int, Field(ge=1)] | None = None
    workers: Annotated[int, Field(ge=1)] | None = None
    worker_timeout: Annotated[float, Field(gt=0, allow_inf_nan=False)] = _D["worker_timeout"]
    report: bool = True
    settle: Annotated[float, Field(ge=0, allow_inf_nan=False)] = SETTLE

    @field_validator("references", mode="before")
    @classmethod
    def _one_or_many(cls, value):
        return [value] if isinstance(value, (str, Path)) else value

    @field_validator("captures")
    @classmethod
    def _glob(cls, value):
        if not value.strip():
            raise ValueError("expected a glob of the night's captures")
        return value


STEPS = {"synth": SynthStep, "detect": DetectStep, "evaluate": EvaluateStep, "report": ReportStep,
         "survey": SurveyStep}
#: per step kind, the fields that name inputs that must exist (or be written by an earlier step)
_INPUTS = {"synth": (), "detect": ("reference", "distorted"), "evaluate": ("store", "truth"), "report": ("store",),
           "survey": ("references",)}
#: scheduler names that are not files (anything else is a scheduler file, relative to the workflow)
_NAMED = ("threads", "processes", "synchronous", "slurm", "pbs")


class Workflow(_Model):
    """A validated workflow: its steps as typed models, paths absolute."""

    name: str
    path: Path
    scheduler: str = "threads"
    overwrite: bool = False
    keep_going: bool = False
    summary: Path
    steps: list[tuple[str, Union[SynthStep, DetectStep, EvaluateStep, ReportStep, SurveyStep]]]


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
        from .._scheduler import check_scheduler

        if value in ("threads", "processes", "synchronous") or value.startswith("tcp://"):
            check_scheduler(value)
        return value  # a scheduler file is resolved against the workflow's directory later
