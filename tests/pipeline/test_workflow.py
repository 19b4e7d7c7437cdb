"""Workflow files: validation, and a small nightly run end to end."""

import json
from pathlib import Path

import pytest
import yaml

from rsmb import ops
from rsmb.pipeline._workflow import load_workflow
from rsmb.pipeline.cli import main

WORKFLOWS = Path(__file__).resolve().parents[2] / "workflows"


@pytest.mark.parametrize("name", ["nightly-example.yaml", "cluster-template.yaml"])
def test_shipped_workflows_are_valid(name):
    data = load_workflow(WORKFLOWS / name)
    assert data.steps


def test_small_workflow_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    flow = {
        "name": "tiny",
        "overwrite": True,
        "detect": {"tile_size": 128},
        "steps": [
            {"synth": {"out_dir": "pair", "size": 256, "changes": 5, "seed": 2, "format": "tif"}},
            {"detect": {"reference": "pair/reference.tif", "distorted": "pair/distorted.tif",
                        "output": "out/changes.zarr", "geotiff": "out/masks"}},
            {"evaluate": {"store": "out/changes.zarr", "truth": "pair"}},
        ],
    }
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(flow))
    assert main(["-q", "run", str(path)]) == 0
    summary = json.loads((tmp_path / "out" / "tiny.summary.json").read_text())
    assert [s["kind"] for s in summary] == ["synth", "detect", "evaluate"]
    assert summary[2]["result"]["changes"]["f_measure"] > 0.9
    assert (tmp_path / "out" / "masks" / "change_mask.tif").exists()


@pytest.mark.parametrize("flow, words", [
    ({"steps": []}, "non-empty list"),
    ({"steps": [{"detect": {"reference": "a.tif"}}]}, "missing"),
    ({"steps": [{"explode": {}}]}, "unknown step"),
    ({"detect": {"tile": 5}, "steps": [{"report": {"store": "x"}}]}, "unknown keys"),
    ({"schedular": "threads", "steps": [{"report": {"store": "x"}}]}, "unknown keys"),
])
def test_invalid_workflows_are_refused_before_running(tmp_path, flow, words):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(flow))
    with pytest.raises(ops.InputError, match=words):
        load_workflow(path)
    assert main(["run", str(path)]) == 2


def _write(tmp_path, flow, name="flow.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(flow))
    return path


@pytest.mark.parametrize("detect, words", [
    ({"tile_size": "big"}, "tile_size"),
    ({"tile_size": 8}, "tile_size"),
    ({"min_area": -3}, "min_area"),
    ({"threshold": -1}, "threshold"),
    ({"axes": "tx,foo"}, "axes"),
    ({"step": [1, 0, 1]}, "step"),
    ({"resume": "sometimes"}, "resume"),
])
def test_wrong_types_are_refused_naming_the_key(tmp_path, detect, words):
    path = _write(tmp_path, {"detect": detect, "steps": [{"report": {"store": "x"}}]})
    with pytest.raises(ops.InputError, match=words):
        load_workflow(path)


def test_paths_are_relative_to_the_workflow_file(tmp_path, monkeypatch):
    flows = tmp_path / "flows"
    flows.mkdir()
    path = _write(flows, {"name": "rel", "detect": {"tile_size": 128}, "steps": [
        {"synth": {"out_dir": "pair", "size": 192, "changes": 3, "seed": 4, "format": "npy"}},
        {"detect": {"reference": "pair/reference.npy", "distorted": "pair/distorted.npy", "output": "o.zarr"}}]})
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["-q", "run", str(path)]) == 0
    assert (flows / "o.zarr").is_dir() and (flows / "rel.summary.json").is_file()
    assert list(elsewhere.iterdir()) == []


def test_missing_input_is_refused_before_any_step(tmp_path, capsys):
    path = _write(tmp_path, {"steps": [
        {"synth": {"out_dir": "pair", "size": 64, "changes": 0}},
        {"detect": {"reference": "pair/reference.png", "distorted": "nowhere.png", "output": "o.zarr"}}]})
    assert main(["-q", "run", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "step 2 (detect): distorted" in err[0] and "nowhere.png" in err[0]
    assert not (tmp_path / "pair").exists()  # nothing ran


def _failing_night(tmp_path, keep_going):
    return _write(tmp_path, {"name": "night", "keep_going": keep_going, "detect": {"tile_size": 128}, "steps": [
        {"synth": {"out_dir": "pair", "size": 192, "changes": 3, "seed": 4, "format": "npy"}},
        {"synth": {"out_dir": "flat", "size": 192, "changes": 0, "scale": 0.0, "format": "npy"}},
        {"detect": {"reference": "pair/reference.npy", "distorted": "pair/distorted.npy", "output": "a.zarr",
                    "min_area": 10}},
        # the truth directory is not a detect store: this step fails
        {"evaluate": {"store": "pair", "truth": "pair"}},
        {"detect": {"reference": "pair/reference.npy", "distorted": "pair/distorted.npy", "output": "b.zarr",
                    "resume": True}},
    ]})


def test_a_failed_step_stops_the_rest_and_the_summary_says_so(tmp_path):
    path = _failing_night(tmp_path, keep_going=False)
    assert main(["-q", "run", str(path)]) == 3
    summary = json.loads((tmp_path / "night.summary.json").read_text())
    assert [s["status"] for s in summary] == ["done", "done", "done", "failed", "not run"]
    assert "pair" in summary[3]["reason"] and not (tmp_path / "b.zarr").exists()


def test_keep_going_runs_the_rest_and_resume_skips_finished_outputs(tmp_path, caplog):
    path = _failing_night(tmp_path, keep_going=True)
    assert main(["-q", "run", str(path)]) == 3
    summary = json.loads((tmp_path / "night.summary.json").read_text())
    assert [s["status"] for s in summary] == ["done", "done", "done", "failed", "done"]
    # the night again, fixed: finished outputs with resume are complete, not errors
    flow = yaml.safe_load(path.read_text())
    del flow["steps"][3]
    flow["overwrite"] = True
    flow["steps"][2]["detect"]["resume"] = True
    path.write_text(yaml.safe_dump(flow))
    stamp = (tmp_path / "b.zarr" / "zarr.json").stat().st_mtime_ns
    assert main(["run", str(path)]) == 0
    assert (tmp_path / "b.zarr" / "zarr.json").stat().st_mtime_ns == stamp
    assert "already complete" in caplog.text
    assert [s["status"] for s in json.loads((tmp_path / "night.summary.json").read_text())] == ["done"] * 4


def test_check_validates_without_running(tmp_path, capsys):
    path = _failing_night(tmp_path, keep_going=False)
    assert main(["run", str(path), "--check"]) == 0
    assert "valid, 5 steps" in capsys.readouterr().out and not (tmp_path / "pair").exists()
