"""Workflow files: validation, and a small nightly run end to end."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from rsmb import ops
from rsmb.pipeline.bench._archive import CaptureSpec, write_capture, write_reference
from rsmb.pipeline.workflow._workflow import load_workflow
from rsmb.pipeline.cli import main

WORKFLOWS = Path(__file__).resolve().parents[3] / "workflows"


@pytest.mark.parametrize("name", ["nightly-example.yaml", "cluster-template.yaml"])
def test_shipped_workflows_are_valid(name):
    data = load_workflow(WORKFLOWS / name)
    assert data.steps


@pytest.mark.slow
def test_the_nightly_example_runs(tmp_path):
    """The shipped example, copied out of the source tree (its outputs land
    beside the file): every step done, its survey step included."""
    path = tmp_path / "nightly-example.yaml"
    path.write_text((WORKFLOWS / "nightly-example.yaml").read_text())
    assert main(["-q", "run", str(path)]) == 0
    steps = json.loads((tmp_path / "nightly-example" / "nightly-example.summary.json").read_text())
    assert [s["status"] for s in steps] == ["done"] * len(steps) and steps[-1]["kind"] == "survey"
    assert steps[-1]["result"]["done"] == 1 and (tmp_path / "nightly-example" / "survey" / "captures" / "distorted.tif").is_dir()


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
    assert (tmp_path / "out" / "masks" / "change_mask_reference.tif").exists()


@pytest.mark.parametrize("flow, words", [
    ({"steps": []}, "non-empty list"),
    ({"steps": [{"detect": {"reference": "a.tif"}}]}, "missing"),
    ({"steps": [{"explode": {}}]}, "unknown step"),
    ({"detect": {"tile": 5}, "steps": [{"report": {"store": "x"}}]}, "unknown keys"),
    ({"schedular": "threads", "steps": [{"report": {"store": "x"}}]}, "unknown keys"),
    ({"steps": [{"survey": {"references": [], "captures": "in/*.tif", "output": "n"}}]}, "references"),
    ({"steps": [{"survey": {"references": "r.tif", "captures": " ", "output": "n"}}]}, "captures"),
    ({"steps": [{"survey": {"references": "r.tif", "captures": "in/*.tif", "output": "n", "parallel": 0}}]},
     "parallel"),
    ({"steps": [{"survey": {"references": "r.tif", "captures": "in/*.tif", "output": "n", "resume": True}}]},
     "unknown keys"),  # a survey resumes by its ledger
    ({"steps": [{"survey": {"references": "r.tif", "captures": "in/*.tif", "output": "n", "step": [1, 1]}}]},
     r"step 1 \(survey\): step: expected 1 or 3 values"),
    ({"steps": [{"detect": {"reference": "a", "distorted": "b", "output": "o", "half_width": [1, 2]}}]},
     r"step 1 \(detect\): half_width: expected 1 or 3 values"),
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


def _survey_archive(root):
    """A reference mosaic of two files and a night: two good captures and a
    truncated one (it fails)."""
    scene = (0.05 + 0.7 * ops.aerial_scene((384, 384), seed=7)).astype(np.float32)
    write_reference(root / "reference", scene, split=2)
    for k, origin in enumerate([(40, 40), (150, 150)]):
        write_capture(root / "incoming" / f"cap{k}.tif", scene, CaptureSpec(origin, (192, 192), seed=10 + k,
                                                                           changes=2))
    data = (root / "incoming" / "cap0.tif").read_bytes()
    (root / "incoming" / "truncated.tif").write_bytes(data[:len(data) // 2])


def test_a_survey_step_fails_with_its_night_and_resumes_by_its_ledger(tmp_path, monkeypatch):
    _survey_archive(tmp_path)
    path = _write(tmp_path, {"name": "nightly", "keep_going": True, "steps": [
        {"survey": {"references": ["reference/mosaic_0.tif", "reference/mosaic_1.tif"], "captures": "incoming/*.tif",
                    "output": "night", "slow_axes": "none", "report": False, "settle": 0}},
        # inside the survey's output, so written by it; the archive wrote each capture's truth beside it
        {"evaluate": {"store": "night/captures/cap0.tif/changes.zarr", "truth": "incoming/cap0.truth"}},
    ]})
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # paths and the glob are relative to the workflow file
    assert main(["-q", "run", str(path)]) == 3
    survey, evaluate = json.loads((tmp_path / "nightly.summary.json").read_text())
    assert survey["status"] == "failed" and survey["reason"].startswith("1 of 3 captures failed")
    result = survey["result"]
    assert (result["done"], result["skipped"], result["failed"]) == (2, 0, 1)
    assert list(result["failed_captures"]) == [str(tmp_path / "incoming" / "truncated.tif")]
    assert evaluate["status"] == "done" and evaluate["result"]["changes"]["f_measure"] > 0.8  # keep_going
    assert os.listdir(elsewhere) == []
    # the night again: done captures skipped, nothing rewritten; the truncated capture retried, fails again
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "night").glob("captures/cap*.tif/*.tif")}
    assert len(stamps) == 6
    assert main(["-q", "run", str(path)]) == 3
    (tmp_path / "incoming" / "truncated.tif").unlink()
    assert main(["-q", "run", str(path)]) == 0
    survey, evaluate = json.loads((tmp_path / "nightly.summary.json").read_text())
    assert survey["status"] == "done" and (survey["result"]["done"], survey["result"]["skipped"]) == (0, 2)
    assert stamps == {p: p.stat().st_mtime_ns for p in (tmp_path / "night").glob("captures/cap*.tif/*.tif")}


def test_a_survey_step_is_checked_before_any_step_runs(tmp_path, capsys):
    _survey_archive(tmp_path)
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "todo.txt").write_text("someone else's")
    survey = {"references": ["reference/mosaic_0.tif"], "captures": "incoming/*.tif", "output": "night"}
    cases = [({**survey, "references": ["reference/missing.tif"]}, "references: "),
             ({**survey, "references": ["incoming/cap0.truth/change_mask.png"]}, "not georeferenced"),
             ({**survey, "output": "notes"}, "output is a folder of other files")]
    for options, words in cases:
        path = _write(tmp_path, {"steps": [{"synth": {"out_dir": "pair", "size": 64, "changes": 0}},
                                           {"survey": options}]})
        assert main(["-q", "run", str(path)]) == 2, options
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "step 2 (survey)" in err[0] and words in err[0], err
        assert not (tmp_path / "pair").exists() and not (tmp_path / "night").exists()
    path = _write(tmp_path, {"steps": [{"survey": survey}]})
    assert main(["run", str(path), "--check"]) == 0
    assert "step 1 survey" in capsys.readouterr().out and not (tmp_path / "night").exists()
    path = _write(tmp_path, {"steps": [{"survey": {**survey, "references": ["reference"]}}]})
    assert main(["run", str(path), "--check"]) == 0  # a folder of reference files: a mosaic, as survey reads it


def test_a_detect_step_and_the_summary_are_checked_before_any_step_runs(tmp_path, capsys):
    """A detect step's input that is no image, its output already there
    (without overwrite, or with resume of what is no finished store), its
    GeoTIFFs already there, and a summary that cannot be written (its folder
    is a file) are bad input: one line, exit 2, before the first step runs.
    A reference folder (a mosaic's files) is an input as detect takes it."""
    (tmp_path / "text.tif").write_text("not an image")
    (tmp_path / "taken.zarr").mkdir()
    (tmp_path / "tifs").mkdir()
    (tmp_path / "tifs" / "change_mask_reference.tif").write_bytes(b"an earlier run's")
    first = {"synth": {"out_dir": "pair", "size": 64, "changes": 0}}
    detect = {"reference": "pair/reference.png", "distorted": "pair/distorted.png", "output": "o.zarr"}
    cases = [({"steps": [first, {"detect": {**detect, "reference": "text.tif"}}]}, "step 2 (detect): " +
              str(tmp_path / "text.tif")),
             ({"steps": [first, {"detect": {**detect, "output": "taken.zarr"}}]}, "output exists"),
             ({"steps": [first, {"detect": {**detect, "output": "taken.zarr", "resume": True}}]}, "output exists"),
             ({"steps": [first, {"detect": {**detect, "geotiff": "tifs"}}]}, "change_mask_reference.tif: exists"),
             ({"summary": "text.tif/s.json", "steps": [first]}, "summary: ")]
    for flow, words in cases:
        path = _write(tmp_path, flow)
        assert main(["-q", "run", str(path)]) == 2, flow
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
        assert not (tmp_path / "pair").exists()
    path = _write(tmp_path, {"overwrite": True, "steps": [first, {"detect": {**detect, "output": "taken.zarr"}}]})
    assert main(["run", str(path), "--check"]) == 0  # overwrite: the output is the step's to replace
    _survey_archive(tmp_path / "archive")
    path = _write(tmp_path, {"steps": [{"detect": {"reference": "archive/reference", "distorted":
                                                   "archive/incoming/cap0.tif", "output": "m.zarr"}}]})
    assert main(["run", str(path), "--check"]) == 0  # a folder of reference files: a mosaic


def test_a_jobqueue_scheduler_is_a_name_not_a_file(tmp_path, capsys):
    pytest.importorskip("dask_jobqueue")
    import dask

    path = _write(tmp_path, {"scheduler": "slurm", "steps": [{"synth": {"out_dir": "pair", "size": 64}}]})
    with dask.config.set({"jobqueue.slurm.cores": None, "jobqueue.slurm.memory": None}):
        assert main(["run", str(path), "--check"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scheduler: slurm: dask's jobqueue configuration has no jobqueue.slurm.cores" in err[0]
    with dask.config.set({"jobqueue.slurm.cores": 4, "jobqueue.slurm.memory": "8GB"}):
        assert main(["run", str(path), "--check"]) == 0
    assert load_workflow(path).scheduler == "slurm"
