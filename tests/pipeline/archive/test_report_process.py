"""The survey's reports written by a process of their own
(:mod:`rsmb.pipeline.archive._report_process`): a report process that dies is
replaced and the report written again once, a second death fails the capture
(never a hang), and a night stopped by Ctrl-C leaves no process and no
half-written report behind."""

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

from rsmb.pipeline.archive import _report_process, _survey as survey_module

from . import report_workers
from .test_survey import _night, _scene

ROOT = Path(__file__).resolve().parents[3]  # the repository: the child imports report_workers from it


def _one_capture_night(tmp_path):
    references, night = _night(tmp_path, _scene(), bad=False)
    return references, str(night / "flight1" / "cap0.tif")


def _gone(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_a_report_process_killed_midway_is_replaced_and_the_report_written_again(tmp_path, monkeypatch):
    references, capture = _one_capture_night(tmp_path)
    monkeypatch.setattr(_report_process, "_write_report", report_workers.dies_once)
    monkeypatch.setenv(report_workers.LOG, str(tmp_path / "reports.jsonl"))
    monkeypatch.setenv(report_workers.MARKER, str(tmp_path / "died"))
    result = survey_module.survey(references, capture, tmp_path / "out", settle=0)
    assert result.done == 1 and result.failed == 0
    log = report_workers.read_log(tmp_path / "reports.jsonl")
    assert [r["what"] for r in log] == ["killed", "written"] and log[0]["pid"] != log[1]["pid"]
    assert _gone(log[0]["pid"]) and _gone(log[1]["pid"])  # both waited for
    report = Path(result.captures[0].output) / "report"
    assert (report / "index.html").is_file()
    assert (report / "overlay.png").read_bytes()[:4] == b"\x89PNG"  # the dead one's half-written file is gone
    assert not (tmp_path / "out" / ".partial").exists()


def test_a_report_process_that_dies_twice_fails_its_capture(tmp_path, monkeypatch):
    references, capture = _one_capture_night(tmp_path)
    monkeypatch.setattr(_report_process, "_write_report", report_workers.always_dies)
    monkeypatch.setenv(report_workers.LOG, str(tmp_path / "reports.jsonl"))
    start = time.monotonic()
    result = survey_module.survey(references, capture, tmp_path / "out", settle=0)
    assert time.monotonic() - start < 120  # no hang
    assert result.done == 0 and result.failed == 1
    assert "ended abruptly twice" in result.captures[0].reason
    log = report_workers.read_log(tmp_path / "reports.jsonl")
    assert [r["what"] for r in log] == ["killed", "killed"] and all(_gone(r["pid"]) for r in log)
    out = tmp_path / "out"
    assert not (out / "captures" / "cap0.tif").exists() and not (out / ".partial").exists()
    rows = sqlite3.connect(out / "ledger.sqlite").execute("SELECT status, reason FROM runs").fetchall()
    assert [s for s, _ in rows] == ["failed"] and "ended abruptly twice" in rows[0][1]


# The night in a process of its own, its report writer one that never ends.
_HANGING_REPORT = """
import sys
from rsmb.pipeline.archive import _report_process
from tests.pipeline.archive import report_workers
from rsmb.pipeline.cli import main

_report_process._write_report = report_workers.hangs
sys.exit(main(sys.argv[1:]))
"""


def test_ctrl_c_while_a_report_is_written_leaves_no_process_and_no_report(tmp_path):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it)
    while the night's report process writes a report that would never end:
    the night stops with exit 130 within seconds, the report process is gone
    (killed and waited for, not orphaned), the capture is not placed (no
    half-written report anywhere) and is recorded interrupted; the next night
    writes it whole."""
    references, capture = _one_capture_night(tmp_path)
    out = tmp_path / "out"
    args = ["-q", "survey", *map(str, references), "--captures", capture, "-o", str(out), "--settle", "0"]
    env = {**os.environ, report_workers.LOG: str(tmp_path / "reports.jsonl")}
    proc = subprocess.Popen([sys.executable, "-c", _HANGING_REPORT, *args], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not report_workers.read_log(tmp_path / "reports.jsonl") and proc.poll() is None:
            assert time.monotonic() < deadline, "the report never started"
            time.sleep(0.05)
        start = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr.decode()
    assert time.monotonic() - start < 15
    (started,) = report_workers.read_log(tmp_path / "reports.jsonl")
    assert _gone(started["pid"])
    assert not (out / "captures" / "cap0.tif").exists() and not (out / ".partial").exists()
    assert not list(out.rglob("overlay.png"))
    rows = sqlite3.connect(out / "ledger.sqlite").execute("SELECT status, reason FROM runs").fetchall()
    assert [s for s, _ in rows] == ["failed"] and "interrupted" in rows[0][1]
    result = survey_module.survey(references, capture, out, settle=0)
    assert result.done == 1 and (Path(result.captures[0].output) / "report" / "index.html").is_file()
