"""The exit-code contract of the command line: a bad option or an output that
cannot be written exits 2 with exactly one line on stderr naming the flag or
the path, before any work starts, and leaves nothing behind."""

import hashlib
import os
import signal
import subprocess
import sys

import pytest

from rsmb.pipeline import _detect
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
    (masks / "change_mask.tif").write_bytes(b"an earlier night's mask")
    cases = [
        (["-o", str(afile / "o.zarr")], str(afile / "o.zarr")),
        (["-o", str(existing)], str(existing)),
        (["-o", str(tmp_path / "o.zarr"), "--geotiff", str(afile)], str(afile)),
        (["-o", str(tmp_path / "o.zarr"), "--geotiff", str(afile / "sub")], str(afile / "sub")),
        (["-o", str(tmp_path / "o.zarr"), "--geotiff", str(masks)], str(masks / "change_mask.tif")),
    ]
    if os.geteuid() != 0:  # root writes anywhere: a read-only directory only stops other users
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        cases.append((["-o", str(locked / "o.zarr")], str(locked / "o.zarr")))
    return cases, masks / "change_mask.tif"


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
