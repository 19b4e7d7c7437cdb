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
    assert data["steps"]


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
