"""Report writers for the tests of the survey's report process
(:mod:`rsmb.pipeline.archive._report_process`): each is put in place of its
``_write_report`` and sent to the child by reference, so it lives in a module
the child can import.  They take their settings from the environment, which
the child inherits."""

import json
import os
import signal
import time
from pathlib import Path

from rsmb.pipeline.report._report import write_report

#: A file each writer appends one JSON line to: its process, the store, start and end (time.monotonic).
LOG = "RSMB_TEST_REPORT_LOG"
#: Seconds the slow writer waits before it writes.
PAUSE = "RSMB_TEST_REPORT_PAUSE"
#: A file whose absence makes :func:`dies_once` die (it creates it first).
MARKER = "RSMB_TEST_REPORT_MARKER"


def _log(store, start, what):
    with open(os.environ[LOG], "a") as f:
        f.write(json.dumps({"pid": os.getpid(), "store": str(store), "start": start, "end": time.monotonic(),
                            "what": what}) + "\n")


def read_log(path):
    path = Path(path)
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def _half_written(out_dir):
    """What a writer killed midway leaves: a figure and no page."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    (Path(out_dir) / "overlay.png").write_bytes(b"half")


def slow(store, out_dir):
    """The real report, after a pause."""
    start = time.monotonic()
    time.sleep(float(os.environ.get(PAUSE, "0")))
    write_report(store, out_dir)
    _log(store, start, "written")


def dies_once(store, out_dir):
    """Killed (SIGKILL, by itself) halfway through the first report it is
    asked for; the real report after."""
    start = time.monotonic()
    marker = Path(os.environ[MARKER])
    if not marker.exists():
        marker.write_text("died")
        _half_written(out_dir)
        _log(store, start, "killed")
        os.kill(os.getpid(), signal.SIGKILL)
    write_report(store, out_dir)
    _log(store, start, "written")


def always_dies(store, out_dir):
    """Killed (SIGKILL, by itself) halfway through every report."""
    _half_written(out_dir)
    _log(store, time.monotonic(), "killed")
    os.kill(os.getpid(), signal.SIGKILL)


def hangs(store, out_dir):
    """Starts a report and never ends it (until killed)."""
    _half_written(out_dir)
    _log(store, time.monotonic(), "started")
    time.sleep(600)
