"""``import rsmb``: the public API is the functions the commands call."""

import importlib
from pathlib import Path

import numpy as np
import pytest

import rsmb
from rsmb.pipeline.cli import main

from .conftest import read_store


def test_api_and_command_write_the_same_store(tmp_path, small_pair_files):
    _, ref, dist = small_pair_files
    result = rsmb.detect(ref, dist, tmp_path / "api.zarr", config=rsmb.DetectConfig(tile=128))
    assert isinstance(result, rsmb.DetectResult) and result.output == str(tmp_path / "api.zarr")
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(tmp_path / "cli.zarr"), "--tile-size", "128"]) == 0
    api, api_attrs = read_store(tmp_path / "api.zarr")
    cli, cli_attrs = read_store(tmp_path / "cli.zarr")
    assert api.keys() == cli.keys()
    for name in api:
        np.testing.assert_array_equal(api[name], cli[name], err_msg=name)
    assert api_attrs["run_key"] == cli_attrs["run_key"] and api_attrs["parameters"] == cli_attrs["parameters"]


def test_api_names(tmp_path):
    for name in rsmb.__all__:
        value = getattr(rsmb, name)  # each public name resolves to an object ...
        assert isinstance(value, str) if name == "__version__" else callable(value), name
    paths = rsmb.synth(tmp_path / "pair", shape=(96, 96), changes=1, seed=2, fmt="tif")
    assert isinstance(paths, rsmb.PairPaths) and paths.reference.is_file() and paths.distorted.is_file()
    result = rsmb.detect(paths.reference, paths.distorted, tmp_path / "o.zarr")
    assert isinstance(result, rsmb.DetectResult) and result.shape == [96, 96]
    scores = rsmb.evaluate(tmp_path / "o.zarr", tmp_path / "pair")
    assert isinstance(scores, rsmb.Evaluation) and 0 <= scores.changes.f_measure <= 1
    assert rsmb.report(tmp_path / "o.zarr").name == "index.html"
    # ... and a survey of a night with no captures (an existing, empty folder) finishes with nothing to do
    (tmp_path / "no-flight").mkdir()
    night = rsmb.survey([paths.reference], str(tmp_path / "no-flight" / "*.tif"), tmp_path / "survey")
    assert isinstance(night, rsmb.SurveyResult)
    assert (night.captures, night.done, night.skipped, night.failed) == ([], 0, 0, 0)
    assert Path(night.summary).is_file() and Path(night.index).is_file()


def test_api_and_command_run_the_same_night(tmp_path):
    """``rsmb.survey`` with its defaults keys a capture as ``rsmb survey`` with
    its own: the second of the two skips what the first did."""
    from rsmb import ops
    from rsmb.pipeline.bench._archive import CaptureSpec, write_capture, write_reference

    scene = (0.05 + 0.7 * ops.aerial_scene((192, 192), seed=3)).astype(np.float32)
    references = write_reference(tmp_path / "reference", scene)
    write_capture(tmp_path / "incoming" / "cap.tif", scene, CaptureSpec((32, 32), (96, 96), seed=1, changes=1))
    captures, out = str(tmp_path / "incoming" / "*.tif"), tmp_path / "night"
    assert main(["-q", "survey", *map(str, references), "--captures", captures, "-o", str(out), "--no-report",
                 "--settle", "0"]) == 0
    result = rsmb.survey(references, captures, out, report=False, settle=0)
    assert isinstance(result, rsmb.SurveyResult) and (result.done, result.skipped, result.failed) == (0, 1, 0)
    assert result.captures[0].reason.startswith("done with the same key")


class _Called(Exception):
    pass


# rsmb name -> (a command line, the module and function its command calls)
_COMMANDS = {
    "detect": (["detect", "ref.tif", "dist.tif", "-o", "o.zarr"], "rsmb.pipeline.detection._detect", "detect"),
    "survey": (["survey", "ref.tif", "--captures", "*.tif", "-o", "night"], "rsmb.pipeline.archive._survey", "survey"),
    "synth": (["synth", "pair"], "rsmb.pipeline._synth", "synth"),
    "evaluate": (["evaluate", "o.zarr", "pair"], "rsmb.pipeline._evaluate", "evaluate"),
    "report": (["report", "o.zarr"], "rsmb.pipeline.report._report", "write_report"),
}


@pytest.mark.parametrize("name", sorted(_COMMANDS))
def test_each_command_calls_its_api_function(name, tmp_path, monkeypatch, capsys):
    argv, module, attribute = _COMMANDS[name]
    monkeypatch.chdir(tmp_path)
    api = getattr(rsmb, name)
    assert getattr(importlib.import_module(module), attribute) is api
    calls = []

    def spy(*args, **kwargs):
        calls.append(name)
        raise _Called

    monkeypatch.setattr(importlib.import_module(module), attribute, spy)
    assert main(["-q", *argv]) == 1  # the spy's exception, reported as unexpected
    assert calls == [name] and "_Called" in capsys.readouterr().err


def test_errors_are_public_and_defined_once(tmp_path):
    """``rsmb.errors`` names the classes ``rsmb.ops`` defines (one definition),
    and what the public API raises on bad input is caught from there."""
    import rsmb.errors
    from rsmb import ops

    for name in rsmb.errors.__all__:
        assert getattr(rsmb.errors, name) is getattr(ops, name), name
        assert issubclass(getattr(rsmb.errors, name), rsmb.errors.RSMBError), name
    assert issubclass(rsmb.errors.InputError, ValueError) and issubclass(rsmb.errors.RunError, RuntimeError)
    missing = tmp_path / "missing.tif"
    with pytest.raises(rsmb.errors.InputError, match="missing.tif"):
        rsmb.detect(missing, missing, tmp_path / "o.zarr")
    with pytest.raises(rsmb.errors.ParameterError, match="threshold"):
        ops.ChangeParams(threshold="median")


@pytest.mark.parametrize("agreement", [0, -1.0, float("nan"), float("inf"), "2", True])
def test_a_bad_agreement_tolerance_is_refused_when_configured(agreement):
    """The tolerance tiles are re-solved at (and warned about at five times)
    must be a positive number of pixels: refused before any work."""
    import rsmb.errors

    with pytest.raises(rsmb.errors.ParameterError, match="agreement: expected a positive number of pixels"):
        rsmb.DetectConfig(agreement=agreement)
    assert rsmb.DetectConfig(agreement=np.float32(3)).agreement == 3
