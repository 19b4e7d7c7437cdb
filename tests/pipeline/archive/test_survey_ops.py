"""Survey operations: two runs on one folder, a layout whose names cannot
collide, the output folder kept out of the glob, the earlier layout moved."""

import contextlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rsmb import ops
from rsmb.pipeline.bench._archive import CaptureSpec, write_capture, write_reference
from rsmb.pipeline.cli import main

SCENE_SHAPE = (512, 512)


def _scene():
    return (0.05 + 0.7 * ops.aerial_scene(SCENE_SHAPE, seed=7)).astype(np.float32)


def _capture(path, scene, origin, seed):
    write_capture(path, scene, CaptureSpec(origin, (160, 160), seed=seed, changes=2))


def _args(references, pattern, out, *extra):
    return ["-q", "survey", *map(str, references), "--captures", str(pattern), "-o", str(out), "--no-report",
            "--tile-size", "160", "--settle", "0", *extra]


def _tree(root):
    """Every path under ``root`` (``root`` included) with its size and modification time."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in [root, *sorted(root.rglob("*"))]}


def _wait_for(predicate, seconds=120.0):
    deadline = time.time() + seconds
    while not predicate():
        if time.time() > deadline:
            raise AssertionError("timed out")
        time.sleep(0.05)


def _freeze(proc):
    """Send SIGSTOP and wait until every thread of ``proc`` is stopped: the
    signal is delivered asynchronously, so a thread may write for a moment after
    ``send_signal`` returns."""
    proc.send_signal(signal.SIGSTOP)

    def stopped():
        states = []
        for stat in Path(f"/proc/{proc.pid}/task").glob("*/stat"):
            try:
                states.append(stat.read_text().rsplit(")", 1)[1].split()[0])
            except (OSError, IndexError):
                continue
        return bool(states) and all(s in "Tt" for s in states)

    _wait_for(stopped, 30.0)


@contextlib.contextmanager
def _frozen(args, ready):
    """``rsmb args`` run in a process of its own and frozen (:func:`_freeze`)
    once ``ready()`` holds (or it ended); on leaving, resumed and waited for:
    it must then finish with exit 0."""
    first = subprocess.Popen([sys.executable, "-m", "rsmb.pipeline.cli", *args], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE)
    try:
        _wait_for(lambda: ready() or first.poll() is not None)
        _freeze(first)
        yield first
    finally:
        first.send_signal(signal.SIGCONT)
    assert first.wait(timeout=300) == 0, first.stderr.read()


def _summary(out):
    return json.loads(sorted((out / "nights").glob("*.json"))[-1].read_text())


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    root = tmp_path_factory.mktemp("ops")
    scene = _scene()
    references = write_reference(root / "reference", scene, split=1)
    return root, scene, references


def test_a_second_survey_on_the_folder_changes_nothing(archive, tmp_path, capsys):
    """The first night is frozen (SIGSTOP) while it builds a capture; a second
    night on the same folder exits 2 with one line naming the lock, and the
    folder is the same file for file (sizes and times); the first then
    finishes every capture intact."""
    _, scene, references = archive
    night = tmp_path / "night"
    for k, origin in enumerate(((60, 60), (200, 250), (300, 100))):
        _capture(night / f"c{k}.tif", scene, origin, seed=40 + k)
    out = tmp_path / "out"
    args = _args(references, night / "*.tif", out, "--parallel", "1")
    with _frozen(args, lambda: (out / ".partial" / "building").exists()):
        before = _tree(out)
        assert main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "ledger.sqlite.lock: in use by another rsmb survey" in err[0], err
        assert _tree(out) == before
        # a dry run meanwhile tells the capture being built from one a night left running
        assert main([*args, "--dry-run", "--json"]) == 0
        reasons = [c["reason"] for c in json.loads(capsys.readouterr().out)["captures"]]
        assert any(r.startswith("running now in the night on this folder (pid ") for r in reasons), reasons
    summary = _summary(out)
    assert summary["done"] == 3 and summary["failed"] == 0
    for k in range(3):
        assert (out / "captures" / f"c{k}.tif" / "changes.gpkg").is_file()
    assert not (out / ".partial").exists()


def test_two_detect_runs_on_one_store(geotiff_pair_files, tmp_path, capsys):
    """A second ``rsmb detect`` on a store being written exits 2 naming its
    lock, leaves the running one's files as they are, and the first finishes;
    the lock file leaves with the run."""
    _, ref, dist = geotiff_pair_files
    store = tmp_path / "out.zarr"
    args = ["-q", "detect", str(ref), str(dist), "-o", str(store)]
    with _frozen(args, lambda: Path(f"{store}.partial").exists()):
        before = _tree(tmp_path)
        for extra in ([], ["--overwrite"]):
            assert main(args + extra) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and "out.zarr.lock: in use by another rsmb detect" in err[0], err
        assert _tree(tmp_path) == before
    assert (store / "zarr.json").is_file() and not Path(f"{store}.partial").exists()
    assert not Path(f"{store}.lock").exists()


def test_names_that_nest_or_shadow_the_survey_cannot_collide(archive, tmp_path):
    """a.tif and a/b.tif, nights.tif and index.tif each get their own folder
    under captures/; changing a.tif redoes a.tif alone and the night history
    stays."""
    _, scene, references = archive
    night = tmp_path / "night"
    names = {"a.tif": (60, 60), "a/b.tif": (200, 250), "nights.tif": (300, 100), "index.tif": (100, 300)}
    for k, (name, origin) in enumerate(names.items()):
        _capture(night / name, scene, origin, seed=50 + k)
    out = tmp_path / "out"
    args = _args(references, night / "**" / "*.tif", out, "--json")
    assert main(args) == 0
    summary = _summary(out)
    assert summary["done"] == 4
    for name in names:
        folder = out / "captures" / name
        assert (folder / "changes.gpkg").is_file() and (folder / "change_mask_reference.tif").is_file(), name
    assert (out / "index.html").is_file() and len(list((out / "nights").glob("*.json"))) == 1
    _capture(night / "a.tif", scene, (70, 60), seed=60)
    time.sleep(0.01)
    assert main(args) == 0
    by = {Path(c["capture"]).relative_to(night).as_posix(): c["status"] for c in _summary(out)["captures"]}
    assert by == {"a.tif": "done", "a/b.tif": "skipped", "nights.tif": "skipped", "index.tif": "skipped"}
    assert (out / "captures" / "a" / "b.tif" / "changes.gpkg").is_file()
    assert len(list((out / "nights").glob("*.json"))) == 2


def test_the_output_folder_inside_the_captures_folder_is_never_a_capture(archive, tmp_path):
    """The survey folder lies inside the captures' folder and the glob reaches
    it through a symlink and through ``..``: its own COGs are not captures on
    the next night."""
    _, scene, references = archive
    night = tmp_path / "night"
    _capture(night / "c0.tif", scene, (60, 60), seed=70)
    out = night / "survey"
    (night / "link").symlink_to(out, target_is_directory=True)
    assert main(_args(references, night / "**" / "*.tif", out)) == 0
    for pattern in (night / "**" / "*.tif", night / "link" / ".." / "**" / "*.tif"):
        assert main(_args(references, pattern, night / "link" / ".." / "survey", "--json")) == 0
        summary = _summary(out)
        assert [Path(c["capture"]).name for c in summary["captures"]] == ["c0.tif"], summary
        assert summary["failed"] == 0


def test_a_folder_of_the_earlier_layout_is_moved_on_first_use(archive, tmp_path):
    """A survey folder whose capture folders sit beside the ledger, without
    suffix (the layout before captures/), is moved on the next night: folders
    under captures/ with the suffix, the ledger's outputs and the store's
    summary follow, nothing is redone."""
    _, scene, references = archive
    night = tmp_path / "night"
    _capture(night / "f" / "c0.tif", scene, (60, 60), seed=80)
    _capture(night / "f" / "c0" / "c1.tif", scene, (200, 200), seed=81)
    out = tmp_path / "out"
    args = _args(references, night / "**" / "*.tif", out, "--json")
    assert main(args) == 0
    # make it the earlier layout: folders moved up, without suffix, nested; the ledger says so
    db = sqlite3.connect(out / "ledger.sqlite")
    (out / "f").mkdir()
    os.replace(out / "captures" / "f" / "c0.tif", out / "f" / "c0")
    os.replace(out / "captures" / "f" / "c0" / "c1.tif", out / "f" / "c0" / "c1")
    shutil.rmtree(out / "captures")
    for run_id, outputs in db.execute("SELECT id, outputs FROM runs").fetchall():
        old = outputs.replace("/captures/f/c0.tif", "/f/c0").replace("/captures/f/c0/c1.tif", "/f/c0/c1")
        db.execute("UPDATE runs SET outputs = ? WHERE id = ?", (old, run_id))
    db.commit()
    db.close()
    assert main(args) == 0
    summary = _summary(out)
    assert summary["skipped"] == 2 and summary["done"] == 0
    for name in ("f/c0.tif", "f/c0/c1.tif"):
        folder = out / "captures" / name
        assert (folder / "changes.gpkg").is_file(), name
        attrs = json.loads((folder / "changes.zarr" / "zarr.json").read_text())["attributes"]
        assert attrs["summary"]["output"] == str(folder / "changes.zarr")
        assert [c["output"] for c in summary["captures"] if c["capture"].endswith(name)] == [str(folder)]
    assert not (out / "f").exists()


def test_a_lock_failure_that_is_not_contention_says_so(archive, tmp_path, capsys, monkeypatch):
    """A file system without locks (NFS without lockd: ENOLCK) is exit 2 with
    what happened, not "in use"."""
    import errno
    import fcntl

    _, scene, references = archive
    _capture(tmp_path / "night" / "c0.tif", scene, (60, 60), seed=90)

    def flock(fd, op):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(fcntl, "flock", flock)
    assert main(_args(references, tmp_path / "night" / "*.tif", tmp_path / "out")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ledger.sqlite.lock: cannot lock (No locks available" in err[0], err
    assert "in use" not in err[0]


def test_a_night_with_nothing_new_reads_no_file(archive, tmp_path, monkeypatch):
    """The second night hashes nothing (captures and reference known by
    their stat); a capture rewritten with the same size and a new time is
    read again, and only it."""
    from rsmb.pipeline.archive import _survey as survey_module
    from rsmb import tiles

    _, scene, references = archive
    night = tmp_path / "night"
    for k, origin in enumerate(((60, 60), (200, 250))):
        _capture(night / f"c{k}.tif", scene, origin, seed=100 + k)
    out = tmp_path / "out"
    args = _args(references, night / "*.tif", out, "--json")
    assert main(args) == 0
    read = []
    probe = tiles.probe_image

    def counted(path):
        read.append(Path(path).name)
        return probe(path)

    monkeypatch.setattr(survey_module.tiles, "probe_image", counted)
    assert main(args) == 0
    assert read == [] and _summary(out)["skipped"] == 2
    st = os.stat(night / "c1.tif")
    os.utime(night / "c1.tif", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert main(args) == 0
    assert read == ["c1.tif"]
    assert _summary(out)["skipped"] == 2  # same content: same key


def test_a_capture_still_being_written_waits(archive, tmp_path, capsys):
    """Modified within --settle: skipped with its reason, not in the ledger,
    no folder; --dry-run says so; once older it runs."""
    _, scene, references = archive
    night = tmp_path / "night"
    _capture(night / "c0.tif", scene, (60, 60), seed=110)
    _capture(night / "c1.tif", scene, (200, 250), seed=111)
    old = time.time() - 3600
    os.utime(night / "c0.tif", (old, old))
    out = tmp_path / "out"
    args = [*_args(references, night / "*.tif", out), "--settle", "600"]
    assert main([*args, "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "would run" in text and "would wait" in text and "dry run: 1 to run, 0 to skip, 1 still being written; nothing written" in text
    assert main([*args, "--json"]) == 0
    by = {Path(c["capture"]).name: c for c in json.loads(capsys.readouterr().out)["captures"]}
    assert by["c0.tif"]["status"] == "done"
    assert by["c1.tif"]["status"] == "skipped" and by["c1.tif"]["reason"].startswith("still being written")
    assert by["c1.tif"]["output"] is None and not (out / "captures" / "c1.tif").exists()
    rows = sqlite3.connect(out / "ledger.sqlite").execute("SELECT capture FROM runs").fetchall()
    assert [Path(c).name for c, in rows] == ["c0.tif"]
    os.utime(night / "c1.tif", (old, old))
    assert main([*args, "--json"]) == 0
    by = {Path(c["capture"]).name: c["status"] for c in json.loads(capsys.readouterr().out)["captures"]}
    assert by == {"c0.tif": "skipped", "c1.tif": "done"}


def test_a_capture_modified_during_its_detection_is_not_recorded_done(archive, tmp_path, monkeypatch, capsys):
    from rsmb.pipeline.archive import _survey as survey_module

    _, scene, references = archive
    night = tmp_path / "night"
    _capture(night / "c0.tif", scene, (60, 60), seed=120)
    detect = survey_module.detect

    def touched(references, capture, *args, **kwargs):
        result = detect(references, capture, *args, **kwargs)
        with open(capture, "ab") as fh:  # more bytes arrive meanwhile
            fh.write(b"\0" * 16)
        return result

    monkeypatch.setattr(survey_module, "detect", touched)
    out = tmp_path / "out"
    args = _args(references, night / "*.tif", out, "--json")
    assert main(args) == 3
    (capture,) = json.loads(capsys.readouterr().out)["captures"]
    assert capture["status"] == "failed" and "modified during its detection" in capture["reason"]
    assert not (out / "captures" / "c0.tif").exists()
    monkeypatch.setattr(survey_module, "detect", detect)
    assert main(args) == 0
    (capture,) = json.loads(capsys.readouterr().out)["captures"]
    assert capture["status"] == "done" and capture["reason"].startswith("content changed")


def _ledger_rows(out):
    try:
        with sqlite3.connect(out / "ledger.sqlite", timeout=10) as db:
            return db.execute("SELECT capture, status, reason FROM runs ORDER BY id").fetchall()
    except sqlite3.Error:
        return []


def _six_captures(night, scene, seed):
    """Six small captures ``c00.tif`` .. ``c05.tif`` of ``scene`` in ``night``, placed by ``seed``."""
    rng = np.random.default_rng(seed)
    for k in range(6):
        origin = tuple(int(v) for v in rng.integers(40, 300, size=2))
        _capture(night / f"c{k:02d}.tif", scene, origin, seed=100 * (seed - 3) + k)
    return night


def test_ctrl_c_stops_within_seconds_and_nothing_finished_is_redone(archive, tmp_path):
    """SIGINT to a night of many small captures once one is done: the night
    stops within seconds with exit 130, writes its summary and index, records
    every finished capture done (its folder in place) and leaves no attempt
    running; the next night skips them and runs the rest."""
    _, scene, references = archive
    night = _six_captures(tmp_path / "night", scene, 5)
    out = tmp_path / "out"
    args = _args(references, night / "*.tif", out, "--parallel", "1", "--json")
    proc = subprocess.Popen([sys.executable, "-m", "rsmb.pipeline.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    _wait_for(lambda: any(s == "done" for _, s, _ in _ledger_rows(out)) or proc.poll() is not None, 300)
    start = time.monotonic()
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    seconds = time.monotonic() - start
    assert proc.returncode == 130, stderr.decode()
    assert seconds < 15, seconds
    assert "stopped by SIGINT" in stderr.decode()
    rows = _ledger_rows(out)
    assert "running" not in {s for _, s, _ in rows}
    done = {Path(c).name for c, s, _ in rows if s == "done"}
    assert 1 <= len(done) < 6
    summary = json.loads(stdout)
    assert summary == _summary(out) and summary["done"] == len(done) and (out / "index.html").is_file()
    # one detection at a time (--parallel 1): at most one was under way, the others waited and were not run
    status = {Path(c["capture"]).name: (c["status"], c["reason"]) for c in summary["captures"]}
    assert sum(s == "failed" for s, _ in status.values()) <= 1, status
    assert all(r.startswith("not run: the night was stopped") for s, r in status.values() if s == "skipped"), status
    assert sum(s == "skipped" for s, _ in status.values()) >= 6 - len(done) - 1, status
    for name in done:
        assert (out / "captures" / name / "changes.gpkg").is_file(), name
    assert main(_args(references, night / "*.tif", out, "--json")) == 0
    by = {Path(c["capture"]).name: c["status"] for c in _summary(out)["captures"]}
    assert {n for n, s in by.items() if s == "skipped"} == done
    assert {n for n, s in by.items() if s == "done"} == {f"c{k:02d}.tif" for k in range(6)} - done


def test_a_workflow_stopped_records_its_night_and_its_steps(archive, tmp_path):
    """SIGINT to ``rsmb run`` during its survey step once a capture is done:
    the night stops in order as ``rsmb survey``'s does (its summary written),
    the workflow's summary says the step was interrupted and the next did not
    run, and the command exits 130 with one line; then SIGTERM during a
    detect step (no night to stop in order) interrupts it at once: 143, the
    step recorded interrupted."""
    import yaml

    _, scene, references = archive
    night = _six_captures(tmp_path / "night", scene, 6)
    survey = {"references": [str(r) for r in references], "captures": str(night / "*.tif"),
              "output": str(tmp_path / "out"), "parallel": 1, "report": False, "settle": 0, "tile_size": 160}
    flow = tmp_path / "night.yaml"
    later = {"synth": {"out_dir": str(tmp_path / "later"), "size": 64}}

    def stopped(steps, ready, signum):
        """``rsmb run`` of ``steps`` sent ``signum`` once ``ready()``: (exit code, stderr, the summary's steps)."""
        flow.write_text(yaml.safe_dump({"name": "w", "steps": steps}))
        proc = subprocess.Popen([sys.executable, "-m", "rsmb.pipeline.cli", "-q", "run", str(flow)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        _wait_for(lambda: ready() or proc.poll() is not None, 300)
        proc.send_signal(signum)
        _, stderr = proc.communicate(timeout=60)
        return proc.returncode, stderr.decode(), json.loads((tmp_path / "w.summary.json").read_text())

    code, stderr, steps = stopped([{"survey": survey}, later],
                                  lambda: any(s == "done" for _, s, _ in _ledger_rows(tmp_path / "out")), signal.SIGINT)
    assert code == 130 and "workflow stopped by SIGINT" in stderr, stderr
    assert [s["status"] for s in steps] == ["interrupted", "not run"]
    assert steps[0]["result"]["summary"] == str(sorted((tmp_path / "out" / "nights").glob("*.json"))[-1])
    assert _summary(tmp_path / "out")["done"] >= 1

    pair = ops.synthesize_pair((512, 512), seed=2)
    np.save(tmp_path / "ref.npy", pair.reference)
    np.save(tmp_path / "dist.npy", pair.distorted)
    detect = {"reference": str(tmp_path / "ref.npy"), "distorted": str(tmp_path / "dist.npy"),
              "output": str(tmp_path / "d.zarr"), "tile_size": 64}
    code, stderr, steps = stopped([{"detect": detect}, later], (tmp_path / "d.zarr.partial" / "work").is_dir,
                                  signal.SIGTERM)
    assert code == 143 and "interrupted by SIGTERM" in stderr, stderr
    assert [s["status"] for s in steps] == ["interrupted", "not run"]
    assert not (tmp_path / "d.zarr.lock").exists()


def test_an_unquoted_captures_glob_is_refused(archive, tmp_path, capsys):
    """The shell expanded ``--captures dir/*.tif``: its first match became the
    glob, the others references.  Exit 2 with one line, nothing written."""
    _, scene, references = archive
    night = tmp_path / "night"
    for k in range(3):
        _capture(night / f"c{k}.tif", scene, (60 + 40 * k, 80), seed=400 + k)
    out = tmp_path / "out"
    code = main(["-q", "survey", *map(str, references), *map(str, sorted(night.glob("*.tif"))[1:]),
                 "--captures", str(night / "c0.tif"), "-o", str(out)])
    assert code == 2 and not out.exists()
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "unquoted glob" in err and f"--captures '{night}/*.tif'" in err


def test_every_worker_lost_ends_the_night_within_the_timeout(archive, tmp_path, dask_cluster):
    """The only worker of a tcp:// cluster killed mid-night: exit 1 with one
    line within --worker-timeout plus a few seconds, once for the night (not
    once per capture); the log names the cluster it ran on."""
    scheduler_file, worker = dask_cluster
    _, scene, references = archive
    night = tmp_path / "night"
    for k in range(6):
        _capture(night / f"c{k}.tif", scene, (40 + 50 * k, 60), seed=300 + k)
    out = tmp_path / "out"
    address = json.loads(Path(scheduler_file).read_text())["address"]
    args = [a for a in _args(references, night / "*.tif", out) if a != "-q"]
    proc = subprocess.Popen([sys.executable, "-m", "rsmb.pipeline.cli", *args, "--scheduler", address,
                             "--worker-timeout", "5", "--parallel", "2"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    _wait_for(lambda: (out / ".partial" / "building").exists() or proc.poll() is not None, 120)
    worker.kill()
    start = time.monotonic()
    _, stderr = proc.communicate(timeout=120)
    seconds = time.monotonic() - start
    err = stderr.decode()
    assert proc.returncode == 1, err
    assert seconds < 5 + 10, seconds
    assert f"on dask.distributed at {address}" in err
    last = [line for line in err.strip().splitlines() if line.startswith("rsmb:")]
    assert len(last) == 1 and "no dask worker left for 5 s" in last[0], err


def test_a_capture_waiting_for_a_detection_slot_is_not_started_once_the_night_stops():
    """A capture waiting for one of the night's detection slots when the night
    is stopped raises _NotStarted (it is recorded ``skipped``, as a queued
    one), within a fraction of a second and without taking the slot; one that
    gets a slot before the stop runs."""
    import threading

    from rsmb.pipeline.archive import _survey

    stop, slots = _survey._Stop(), threading.Semaphore(1)
    with _survey._slot(slots, stop):  # a free slot: taken
        assert not slots.acquire(blocking=False)
    assert slots.acquire(blocking=False)  # and given back
    threading.Timer(0.3, stop.event.set).start()
    start = time.monotonic()
    with pytest.raises(_survey._NotStarted):
        with _survey._slot(slots, stop):  # the only slot is held (above): it waits, then the night stops
            pass
    assert time.monotonic() - start < 1.0
    slots.release()
    with pytest.raises(_survey._NotStarted):  # a slot free after the stop is not taken either
        with _survey._slot(slots, stop):
            pass
    assert slots.acquire(blocking=False)
