"""One source of defaults: the parameter dataclasses.  Every option of the
commands that run the method, and every field of the workflow models, has the
default of the dataclass field it sets (read here from click's parameters and
pydantic's fields, not from the helper that derives them)."""

import dataclasses
import inspect

import pytest

from rsmb import ops
from rsmb.pipeline import DetectConfig
from rsmb.pipeline._scheduler import WORKER_TIMEOUT, open_runner
from rsmb.pipeline.cli import cli
from rsmb.pipeline.detection._detect import detect
from rsmb.pipeline.workflow._workflow_steps import DetectStep, SurveyStep

REG, CHANGES, CONFIG = ops.RegistrationParams(), ops.ChangeParams(), DetectConfig()


def _per_axis(value):
    """A per-axis default in the form the dataclass holds (None for 'auto')."""
    words = value.split(",") if isinstance(value, str) else list(value)
    values = tuple(None if w == "auto" else float(w) for w in words)
    return values * len(REG.axes) if len(values) == 1 else values


def _names(value):
    words = value.split(",") if isinstance(value, str) else list(value)
    return () if words == ["none"] else tuple(words)


# option name -> (the dataclass value it must equal, how to read the option's default)
EXPECTED = {
    "axes": (REG.axes, _names),
    "half_width": (REG.half_width, _per_axis),
    "step": (REG.step, _per_axis),
    "slow_axes": (REG.slow_axes, _names),
    "shutter": (REG.shutter, str),
    "solver": (REG.solver, str),
    "lambda_w": (REG.lambda_w, float),
    "lambda_chi": (REG.lambda_chi, float),
    "threshold": (CHANGES.threshold, lambda v: v),
    "min_area": (CHANGES.min_area, int),
    "no_layers": (not CHANGES.layers, bool),
    "focal": (CONFIG.focal, lambda v: v),
    "tile_size": (CONFIG.tile, lambda v: v),
    "overlap": (CONFIG.overlap, lambda v: v),
    "worker_timeout": (WORKER_TIMEOUT, float),
}


@pytest.mark.parametrize("command", ["detect", "survey"])
def test_click_defaults_are_the_dataclass_defaults(command):
    params = {p.name: p for p in cli.commands[command].params}
    for name, (expected, read) in EXPECTED.items():
        assert read(params[name].default) == expected, f"{command} --{name.replace('_', '-')}"
    # --search: none given means each axis's default search, the dataclass's
    assert params["search"].default is None
    assert REG.search == tuple(ops.RegistrationParams(axes=REG.axes, search=None).search) == (20.0, 20.0, 3.0)


@pytest.mark.parametrize("model", [DetectStep, SurveyStep])
def test_workflow_defaults_are_the_dataclass_defaults(model):
    fields = model.model_fields
    for name, (expected, read) in EXPECTED.items():
        if name == "worker_timeout" and name not in fields:
            continue  # detect steps run on the workflow's scheduler
        assert read(fields[name].get_default(call_default_factory=True)) == expected, f"{model.__name__}.{name}"
    assert fields["search"].default is None


def test_options_left_at_their_defaults_build_the_default_config(tmp_path):
    from rsmb.pipeline._options import build_config

    params = {p.name: p.default for p in cli.commands["detect"].params}
    config = build_config(params["axes"], params["half_width"], params["step"], params["search"], params["shutter"],
                          params["solver"], params["lambda_w"], params["lambda_chi"], params["threshold"],
                          params["min_area"], params["focal"], params["tile_size"], params["overlap"],
                          slow_axes=params["slow_axes"], layers=not params["no_layers"])
    assert config == DetectConfig()
    step = DetectStep(reference=tmp_path / "r.tif", distorted=tmp_path / "d.tif", output=tmp_path / "o.zarr")
    assert step.config() == DetectConfig()


def test_runtime_defaults_are_one_value():
    from rsmb.pipeline.archive._survey import survey

    for function in (open_runner, detect, survey):
        assert inspect.signature(function).parameters["worker_timeout"].default == WORKER_TIMEOUT


def test_the_row_solver_has_one_set_of_settings():
    """The registration's rows, the depth re-solve and solve_row_fast use the
    same tolerance and iteration limits."""
    from rsmb.ops.registration._rowsolve import MAX_ADD, MAX_OUTER, TOL

    defaults = inspect.signature(ops.solve_row_fast).parameters
    depth = {f.name: f.default for f in dataclasses.fields(ops.AlternateParams)}
    for name, value in (("tol", TOL), ("max_outer", MAX_OUTER), ("max_add", MAX_ADD)):
        assert getattr(REG, name) == depth[name] == defaults[name].default == value, name


def test_synth_defaults_are_the_functions():
    """``rsmb synth`` and a workflow's synth step default to rsmb.synth's keywords."""
    from rsmb.pipeline import synth
    from rsmb.pipeline.workflow._workflow_steps import SynthStep

    function = {n: p.default for n, p in inspect.signature(synth).parameters.items() if n != "out_dir"}
    options = {p.name: p.default for p in cli.commands["synth"].params}
    fields = SynthStep.model_fields
    assert tuple(int(v) for v in options["size"].split(",")) == function["shape"] == fields["size"].default
    assert float(options["gain"]) == function["gain"] == fields["gain"].default
    assert options["fmt"] == function["fmt"] == fields["format"].default
    for name in ("motion", "shutter", "exposure", "scale", "changes", "noise", "seed"):
        assert options[name] == function[name] == fields[name].default, name
