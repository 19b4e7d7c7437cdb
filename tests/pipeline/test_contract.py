"""The exit-code contract of the command line: a bad option or an output that
cannot be written exits 2 with exactly one line on stderr naming the flag or
the path, before any work starts, and leaves nothing behind."""

import contextlib
import hashlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from rsmb.pipeline.detection import _detect
from rsmb.pipeline.archive import _survey
from rsmb.pipeline.cli import main

from .conftest import read_store


@pytest.fixture
def no_work(monkeypatch):
    """Any ingest fails the test: errors must come before work starts."""

    def ingest(*args, **kwargs):
        raise AssertionError("ingest ran")

    monkeypatch.setattr(_detect, "_ingest", ingest)


BAD_OPTIONS = [
    (["--tile-size", "0"], "--tile-size"),
    (["--tile-size", "-5"], "--tile-size"),
    (["--workers", "0"], "--workers"),
    (["--overlap", "-1"], "--overlap"),
    (["--axes", "foo"], "--axes"),
    (["--axes", "tx,tx"], "--axes"),
    (["--slow-axes", "rz"], "--slow-axes"),
    (["--slow-axes", "rx,rx"], "--slow-axes"),
    (["--step", "0"], "--step"),
    (["--step", "1,1,nan"], "--step"),
    (["--half-width", "-1"], "--half-width"),
    (["--search", "a,b,c"], "--search"),
    (["--search", "1,2"], "--search"),
    (["--lambda-chi", "0"], "--lambda-chi"),
    (["--lambda-w", "-1"], "--lambda-w"),
    (["--threshold", "-0.1"], "--threshold"),
    (["--threshold", "otsu"], "--threshold"),
    (["--min-area", "-1"], "--min-area"),
    (["--focal", "0"], "--focal"),
    (["--scheduler", "bogus"], "--scheduler"),
    (["--scheduler", "tcp://no-port"], "--scheduler"),
    (["--shutter", "sideways"], "--shutter"),
    (["--solver", "magic"], "--solver"),
    (["--bogus-flag"], "--bogus-flag"),
]


@pytest.mark.parametrize("args, flag", BAD_OPTIONS, ids=[" ".join(a) for a, _ in BAD_OPTIONS])
def test_bad_option_exits_2_with_one_line(tmp_path, small_pair_files, capsys, no_work, args, flag):
    _, ref, dist = small_pair_files
    out = tmp_path / "o.zarr"
    assert main(["detect", str(ref), str(dist), "-o", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and flag in err[0], err
    assert os.listdir(tmp_path) == []


def test_missing_output_option(small_pair_files, capsys):
    _, ref, dist = small_pair_files
    assert main(["detect", str(ref), str(dist)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--output" in err[0], err


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _bad_outputs(tmp_path):
    """(extra arguments, path the message must name) of outputs that cannot be
    written; made on disk here."""
    afile = tmp_path / "afile"
    afile.write_text("not a directory")
    existing = tmp_path / "exists.zarr"
    existing.mkdir()
    (existing / "zarr.json").write_text("{}")
    masks = tmp_path / "masks"
    masks.mkdir()
    (masks / "change_mask_reference.tif").write_bytes(b"an earlier night's mask")
    cases = [
        (["-o", str(afile / "o.zarr")], str(afile / "o.zarr")),
        (["-o", str(existing)], str(existing)),
        (["-o", str(tmp_path / "o.zarr"), "--geotiff", str(afile)], str(afile)),
        (["-o", str(tmp_path / "o.zarr"), "--geotiff", str(afile / "sub")], str(afile / "sub")),
        (["-o", str(tmp_path / "o.zarr"), "--geotiff", str(masks)], str(masks / "change_mask_reference.tif")),
    ]
    if os.geteuid() != 0:  # root writes anywhere: a read-only directory only stops other users
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        cases.append((["-o", str(locked / "o.zarr")], str(locked / "o.zarr")))
    return cases, masks / "change_mask_reference.tif"


def test_unwritable_outputs_exit_2_before_work(tmp_path, small_pair_files, capsys, no_work):
    _, ref, dist = small_pair_files
    cases, kept = _bad_outputs(tmp_path)
    before = _digest(kept)
    listing = sorted(os.listdir(tmp_path))
    for args, path in cases:
        assert main(["detect", str(ref), str(dist), *args]) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and path in err[0], (args, err)
        assert sorted(os.listdir(tmp_path)) == listing, args  # nothing left behind
    assert _digest(kept) == before  # an existing GeoTIFF is kept


def test_missing_input_exits_2(tmp_path, small_pair_files, capsys):
    _, ref, _ = small_pair_files
    assert main(["detect", str(ref), str(tmp_path / "nope.png"), "-o", str(tmp_path / "o.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.png" in err[0]
    assert os.listdir(tmp_path) == []


def test_sizes_beyond_the_image_are_clamped_with_a_note(tmp_path, small_pair_files, caplog):
    _, ref, dist = small_pair_files
    out = tmp_path / "o.zarr"
    assert main(["detect", str(ref), str(dist), "-o", str(out), "--tile-size", "100000",
                 "--overlap", "5000"]) == 0
    attrs = read_store(out)[1]
    side = max(attrs["tile_grid"]["shape"])
    assert attrs["tile_grid"]["tile"] == side and attrs["tile_grid"]["halo"] == side
    assert attrs["tile_grid"]["tiles"] == [1, 1]
    assert "larger than the image" in caplog.text and "reaches beyond the image" in caplog.text


def test_resume_on_a_finished_output_is_complete(tmp_path, small_pair_files, caplog):
    _, ref, dist = small_pair_files
    out = tmp_path / "o.zarr"
    args = ["detect", str(ref), str(dist), "-o", str(out), "--tile-size", "128"]
    assert main(["-q", *args]) == 0
    stamp = os.stat(out / "zarr.json").st_mtime_ns
    assert main([*args, "--resume"]) == 0
    assert "already complete" in caplog.text
    assert os.stat(out / "zarr.json").st_mtime_ns == stamp
    # a finished store of another run is not mistaken for this one
    assert main(["-q", *args, "--resume", "--min-area", "7"]) == 2


_KILL_BETWEEN_RENAMES = """
import os, signal, sys
from rsmb.pipeline.cli import main
real = os.replace
def replace(src, dst):
    real(src, dst)
    if str(dst).endswith(".replaced"):  # the old store moved aside: die before the new one moves in
        os.kill(os.getpid(), signal.SIGKILL)
os.replace = replace
sys.exit(main(sys.argv[1:]))
"""


def test_kill_between_the_renames_of_an_overwrite_is_repaired(tmp_path, small_pair_files):
    _, ref, dist = small_pair_files
    out = tmp_path / "o.zarr"
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(out), "--tile-size", "128"]) == 0
    args = ["-q", "detect", str(ref), str(dist), "-o", str(out), "--tile-size", "128", "--min-area", "30",
            "--overwrite"]
    proc = subprocess.run([sys.executable, "-c", _KILL_BETWEEN_RENAMES, *args], capture_output=True)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists() and (tmp_path / "o.zarr.replaced").is_dir() and (tmp_path / "o.zarr.partial").is_dir()
    # the next run finds the interrupted overwrite, puts the finished new store in place, then refuses to clobber it
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(out), "--tile-size", "128"]) == 2
    assert sorted(os.listdir(tmp_path)) == ["o.zarr"]
    assert read_store(out)[1]["parameters"]["changes"]["min_area"] == 30


def _other_commands(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("not a directory")
    return [
        (["synth", str(afile / "pair")], str(afile / "pair")),
        (["synth", str(afile)], str(afile)),
        (["synth", str(tmp_path / "s"), "--size", "10,10"], "--size"),
        (["synth", str(tmp_path / "s"), "--size", "64"], "--size"),
        (["synth", str(tmp_path / "s"), "--gain", "-1"], "--gain"),
        (["synth", str(tmp_path / "s"), "--noise", "-1"], "--noise"),
        (["synth", str(tmp_path / "s"), "--scale", "nan"], "--scale"),
        (["synth", str(tmp_path / "s"), "--changes", "-1"], "--changes"),
        (["synth", str(tmp_path / "s"), "--exposure", "-3"], "--exposure"),
        (["synth", str(tmp_path / "s"), "--format", "gif"], "--format"),
        (["evaluate", str(tmp_path / "nope.zarr"), str(tmp_path)], str(tmp_path / "nope.zarr")),
        (["report", str(tmp_path / "nope.zarr")], str(tmp_path / "nope.zarr")),
        (["report", str(afile)], str(afile)),
        (["demo", "-o", str(afile / "d")], str(afile / "d")),
        (["demo", "--size", "10"], "--size"),
        (["demo", "--tile-size", "3"], "--tile-size"),
        (["demo", "--scheduler", "nope"], "--scheduler"),
        (["bench", "--sections", "foo"], "--sections"),
        (["bench", "--workers", "0"], "--workers"),
        (["bench", "--sizes", "0"], "--sizes"),
        (["run", str(tmp_path / "nope.yaml")], str(tmp_path / "nope.yaml")),
        (["run", str(afile), "--scheduler", "bogus"], "--scheduler"),
    ]


def test_other_commands_keep_the_contract(tmp_path, capsys):
    cases = _other_commands(tmp_path)
    for args, named in cases:
        assert main(args) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and named in err[0], (args, err)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"], args


# ------------------------------------------------------------------------- survey


@pytest.fixture(scope="module")
def survey_inputs(tmp_path_factory):
    """A georeferenced reference and one capture of it, in a folder of their own."""
    import numpy as np

    from rsmb import ops
    from rsmb.pipeline.bench._archive import CaptureSpec, write_capture, write_reference

    root = tmp_path_factory.mktemp("survey-inputs")
    scene = (0.05 + 0.7 * ops.aerial_scene((192, 192), seed=3)).astype(np.float32)
    references = write_reference(root / "reference", scene)
    write_capture(root / "incoming" / "cap.tif", scene, CaptureSpec((32, 32), (96, 96), seed=1, changes=1))
    return references[0], str(root / "incoming" / "*.tif")


@pytest.fixture
def no_survey_work(monkeypatch):
    """Looking for captures fails the test: errors must come before work starts."""

    def find_captures(*args, **kwargs):
        raise AssertionError("the survey looked for captures")

    monkeypatch.setattr(_survey, "find_captures", find_captures)


BAD_SURVEY_OPTIONS = [
    (["--parallel", "0"], "--parallel"),
    (["--workers", "0"], "--workers"),
    (["--tile-size", "0"], "--tile-size"),
    (["--axes", "foo"], "--axes"),
    (["--step", "0"], "--step"),
    (["--worker-timeout", "-1"], "--worker-timeout"),
    (["--worker-timeout", "nan"], "--worker-timeout"),
    (["--threshold", "otsu"], "--threshold"),
    (["--scheduler", "bogus"], "--scheduler"),
    (["--captures", ""], "--captures"),
    (["--captures", "  "], "--captures"),
    (["--bogus-flag"], "--bogus-flag"),
]


@pytest.mark.parametrize("args, flag", BAD_SURVEY_OPTIONS, ids=[" ".join(a) or "empty" for a, _ in BAD_SURVEY_OPTIONS])
def test_survey_bad_option_exits_2_with_one_line(tmp_path, survey_inputs, capsys, no_survey_work, args, flag):
    reference, captures = survey_inputs
    assert main(["survey", str(reference), "--captures", captures, "-o", str(tmp_path / "night"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and flag in err[0], err
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("content", ["", "{}", '{"address": 7}', "not json", "[1, 2]"],
                         ids=["empty", "no address", "address not text", "text", "a list"])
def test_a_file_that_is_no_scheduler_file_exits_2_before_work(tmp_path, small_pair_files, survey_inputs, capsys,
                                                               no_work, no_survey_work, content):
    """A ``--scheduler`` path to a file that is not a dask scheduler file (JSON
    with an ``address``) is bad input for detect and survey alike: one line
    naming the option, exit 2, no output folder."""
    _, ref, dist = small_pair_files
    reference, captures = survey_inputs
    (tmp_path / "in").mkdir()
    bad = tmp_path / "in" / "scheduler.json"
    bad.write_text(content)
    for args in (["detect", str(ref), str(dist), "-o", str(tmp_path / "o.zarr")],
                 ["survey", str(reference), "--captures", captures, "-o", str(tmp_path / "night")]):
        assert main([*args, "--scheduler", str(bad)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--scheduler" in err[0] and "scheduler file" in err[0], err
        assert os.listdir(tmp_path) == ["in"]


def test_a_reference_still_being_copied_stops_the_survey_before_work(tmp_path, survey_inputs, capsys,
                                                                     no_survey_work):
    """A reference GeoTIFF cut short (its header opens, its data ends early: a
    copy still running) is bad input of the night, not a failure of each
    capture: exit 2, one line naming it, no output folder."""
    reference, captures = survey_inputs
    (tmp_path / "in").mkdir()
    cut = tmp_path / "in" / "mosaic.tif"
    data = Path(reference).read_bytes()
    cut.write_bytes(data[:len(data) // 2])
    assert main(["survey", str(cut), "--captures", captures, "-o", str(tmp_path / "night")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cut) in err[0] and "cut short" in err[0], err
    assert os.listdir(tmp_path) == ["in"]


def _bad_survey_invocations(tmp_path, monkeypatch):
    """(name, extra arguments, what the message must name, the context it runs
    in) of survey invocations that are bad input; files are made here."""
    import dask

    afile = tmp_path / "afile"
    afile.write_text("not a directory")
    other = tmp_path / "other"  # a folder of someone else's files, no ledger
    other.mkdir()
    (other / "notes.txt").write_text("keep")

    def unconfigured():
        pytest.importorskip("dask_jobqueue")  # its defaults in dask's configuration: no cores, no memory
        return dask.config.set({"jobqueue.slurm.cores": None, "jobqueue.slurm.memory": None,
                                "jobqueue.pbs.cores": None, "jobqueue.pbs.memory": None})

    @contextlib.contextmanager
    def no_extra():
        with monkeypatch.context() as patch:
            patch.setitem(sys.modules, "dask_jobqueue", None)  # the import fails as without the cluster extra
            yield

    night = str(tmp_path / "night")
    return [
        ("a file", ["-o", str(afile)], str(afile), contextlib.nullcontext),
        ("under a file", ["-o", str(afile / "night")], str(afile / "night"), contextlib.nullcontext),
        ("a folder of other files", ["-o", str(other)], str(other), contextlib.nullcontext),
        ("slurm unconfigured", ["-o", night, "--scheduler", "slurm"], "--scheduler", unconfigured),
        ("pbs unconfigured", ["-o", night, "--scheduler", "pbs"], "--scheduler", unconfigured),
        ("slurm without the extra", ["-o", night, "--scheduler", "slurm"], "--scheduler", no_extra),
        ("a missing reference", ["-o", night, str(tmp_path / "missing.tif")], "missing.tif", contextlib.nullcontext),
        ("a reference that is no image", ["-o", night, str(afile)], str(afile), contextlib.nullcontext),
    ]


def test_survey_bad_invocations_exit_2_before_work(tmp_path, survey_inputs, capsys, no_survey_work, monkeypatch):
    reference, captures = survey_inputs
    cases = _bad_survey_invocations(tmp_path, monkeypatch)
    listing = sorted(os.walk(tmp_path))
    for name, args, named, context in cases:
        with context():
            assert main(["survey", str(reference), "--captures", captures, *args]) == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and named in err[0], (name, err)
        assert sorted(os.walk(tmp_path)) == listing, name  # nothing left behind
    assert (tmp_path / "other" / "notes.txt").read_text() == "keep"


def test_survey_output_may_be_new_empty_or_a_survey(tmp_path, survey_inputs, capsys):
    reference, captures = survey_inputs
    empty = tmp_path / "empty"
    empty.mkdir()
    survey = ["-q", "survey", str(reference), "--captures", captures, "--no-report", "--settle", "0", "-o"]
    assert main([*survey, str(tmp_path / "new"), "--dry-run"]) == 0 and not (tmp_path / "new").exists()
    assert main([*survey, str(empty)]) == 0
    assert main([*survey, str(empty), "--dry-run"]) == 0  # a survey's folder: its ledger decides
    assert "would skip" in capsys.readouterr().out
