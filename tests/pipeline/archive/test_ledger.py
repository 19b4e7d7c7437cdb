"""Tests of pipeline.archive._ledger: keys, skip / retry / redo decisions, a row left running,
SIGKILL mid-write, reopening, one writer."""

import datetime as dt
import sqlite3
import subprocess
import sys

import pytest

from rsmb.ops import InputError, ParameterError
from rsmb.pipeline.archive._ledger import (
    LEDGER_NAME,
    SCHEMA_VERSION,
    Ledger,
    RunKey,
    reference_set_digest,
)

REFS = ("refs/a.tif", "refs/b.tif")
REF_SHAS = ("a" * 64, "b" * 64)


def _key(sha="1" * 64, params=None, version="0.1.0", ref_shas=REF_SHAS):
    return RunKey.build(sha, ref_shas, REFS, params or {"threshold": 3.0, "tile": 512}, version)


@pytest.fixture
def path(tmp_path):
    return tmp_path / LEDGER_NAME


def _done(ledger, capture, key, **outputs):
    run = ledger.start(capture, key, night="n1")
    ledger.finish(run, "done", outputs=outputs or {"output": f"{capture}/changes.zarr"})
    return run


# ---------------------------------------------------------------------- keys


def test_key_depends_on_everything_but_paths():
    base = _key()
    assert _key().key == base.key
    assert _key(sha="2" * 64).key != base.key
    assert _key(params={"threshold": 3.5, "tile": 512}).key != base.key
    assert _key(version="0.2.0").key != base.key
    assert _key(ref_shas=REF_SHAS[::-1]).key != base.key  # mosaic order matters
    # parameter order does not
    assert _key(params={"tile": 512, "threshold": 3.0}).key == base.key
    assert base.reference_digest == reference_set_digest(list(REF_SHAS))
    with pytest.raises(ParameterError, match="reference_sha256s"):
        RunKey.build("1" * 64, REF_SHAS[:1], REFS, {}, "0.1.0")


# ----------------------------------------------------------------- decisions


def test_new_then_done_is_skipped_also_after_reopening(path):
    with Ledger(path) as ledger:
        decision = ledger.decide("north/c1.tif", _key())
        assert (decision.action, decision.reason) == ("run", "new capture")
        _done(ledger, "north/c1.tif", _key())
        assert ledger.decide("north/c1.tif", _key()).action == "skip"
    with Ledger(path) as ledger:
        decision = ledger.decide("north/c1.tif", _key())
        assert decision.action == "skip" and decision.reason.startswith("done with the same key")
        assert decision.previous.outputs == {"output": "north/c1.tif/changes.zarr"}
        assert ledger.decide("north/c2.tif", _key()).reason == "new capture"


def test_failed_is_retried_with_its_reason(path):
    with Ledger(path) as ledger:
        run = ledger.start("c.tif", _key())
        ledger.finish(run, "failed", "c.tif: is constant\n(every valid pixel equals 0)")
        decision = ledger.decide("c.tif", _key())
        assert decision.action == "run"
        assert decision.reason == "failed before (c.tif: is constant (every valid pixel equals 0)): retry"


def test_changed_content_parameters_version_references_are_redone(path):
    with Ledger(path) as ledger:
        _done(ledger, "c.tif", _key())
        cases = {
            "content changed (sha256 111111111111 -> 222222222222)": _key(sha="2" * 64),
            "parameters changed (threshold)": _key(params={"threshold": 4.0, "tile": 512}),
            "rsmb version changed (0.1.0 -> 0.2.0)": _key(version="0.2.0"),
            "reference set changed": _key(ref_shas=("c" * 64, "b" * 64)),
        }
        for reason, key in cases.items():
            decision = ledger.decide("c.tif", key)
            assert (decision.action, decision.reason) == ("run", f"{reason}: redo")


def test_latest_done_key_decides(path):
    with Ledger(path) as ledger:
        _done(ledger, "c.tif", _key())
        # a failed attempt with other parameters leaves the first outputs in place
        run = ledger.start("c.tif", _key(version="0.2.0"))
        ledger.finish(run, "failed", "solver failed")
        assert ledger.decide("c.tif", _key()).action == "skip"
        assert ledger.decide("c.tif", _key(version="0.2.0")).reason == "failed before (solver failed): retry"
        # a done attempt with other parameters replaced them
        _done(ledger, "c.tif", _key(version="0.2.0"))
        decision = ledger.decide("c.tif", _key())
        assert decision.action == "run" and "version changed (0.2.0 -> 0.1.0)" in decision.reason


def test_row_left_running_counts_as_not_done(path):
    ledger = Ledger(path)
    ledger.start("c.tif", _key(), night="n1")
    assert ledger.decide("c.tif", _key()).reason.startswith("interrupted")
    ledger.close()  # the night stops without finishing
    with Ledger(path) as ledger:
        (row,) = ledger.runs(capture="c.tif")
        assert row.status == "failed" and row.reason.startswith("interrupted") and row.finished
        decision = ledger.decide("c.tif", _key())
        assert decision.action == "run" and decision.reason.startswith("failed before (interrupted")


# ------------------------------------------------------------ crash safety


def _child(path, body):
    code = (
        "import os, signal\n"
        "from rsmb.pipeline.archive._ledger import Ledger, RunKey\n"
        f"ledger = Ledger({str(path)!r})\n"
        "key = RunKey.build('1' * 64, ['a' * 64], ['a.tif'], {}, '0.1.0')\n"
        f"{body}\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -9, proc.stderr


def test_sigkill_mid_night_and_mid_transaction(path):
    _child(path, "ledger.finish(ledger.start('done.tif', key), 'done')\n"
                 "ledger.start('running.tif', key)\n"
                 "ledger._conn.execute('BEGIN IMMEDIATE')\n"
                 "ledger._conn.execute(\"UPDATE runs SET status = 'done' WHERE capture = 'running.tif'\")\n"
                 "ledger._conn.execute(\"DELETE FROM runs WHERE capture = 'done.tif'\")")
    conn = sqlite3.connect(path)
    assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    conn.close()
    key = RunKey.build("1" * 64, ["a" * 64], ["a.tif"], {}, "0.1.0")
    with Ledger(path) as ledger:  # the uncommitted transaction left no trace
        assert {r.capture: r.status for r in ledger.captures()} == {"done.tif": "done", "running.tif": "failed"}
        assert ledger.decide("done.tif", key).action == "skip"
        assert ledger.decide("running.tif", key).action == "run"


# ------------------------------------------------------------- the file


def test_one_writer_many_readers(path):
    with Ledger(path) as ledger:
        _done(ledger, "c.tif", _key())
        with pytest.raises(InputError, match="in use by another rsmb survey"):
            Ledger(path)
        with Ledger(path, readonly=True) as reader:
            assert [r.capture for r in reader.captures()] == ["c.tif"]
    Ledger(path).close()  # the lock is released on close


def test_bad_files_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="no such ledger"):
        Ledger(tmp_path / "missing.sqlite", readonly=True)
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"not a database at all" * 100)
    with pytest.raises(InputError, match=r"junk\.sqlite: not a readable ledger"):
        Ledger(junk)
    other = tmp_path / "other.sqlite"
    conn = sqlite3.connect(other)
    conn.execute("PRAGMA user_version=99")
    conn.execute("CREATE TABLE t (x)")
    conn.close()
    with pytest.raises(InputError, match=f"schema version 99; this rsmb reads version {SCHEMA_VERSION}"):
        Ledger(other)
    Ledger(other.with_name("fresh.sqlite")).close()  # the lock of a refused open was released
    Ledger(other.with_name("fresh.sqlite")).close()


def test_finish_checks_its_arguments(path):
    with Ledger(path) as ledger:
        run = ledger.start("c.tif", _key())
        with pytest.raises(ParameterError, match="status"):
            ledger.finish(run, "skipped")
        ledger.finish(run, "done")
        with pytest.raises(ParameterError, match="run_id"):
            ledger.finish(run, "failed", "again")
        assert ledger.runs(capture="c.tif")[0].status == "done"


def test_listings_and_times(path):
    with Ledger(path) as ledger:
        _done(ledger, "b.tif", _key())
        run = ledger.start("a.tif", _key(), night="n2")
        ledger.finish(run, "failed", "no overlap")
        _done(ledger, "b.tif", _key(version="0.2.0"))
        assert [r.capture for r in ledger.runs(night="n1")] == ["b.tif", "b.tif"]
        assert [(r.capture, r.status, r.version) for r in ledger.captures()] == [
            ("a.tif", "failed", "0.1.0"), ("b.tif", "done", "0.2.0")]
        row = ledger.runs(capture="a.tif")[0]
        assert row.reference_paths == REFS and row.parameters == {"threshold": 3.0, "tile": 512}
        started = dt.datetime.fromisoformat(row.started.replace("Z", "+00:00"))
        assert started.utcoffset() == dt.timedelta(0)
        assert row.finished >= row.started


# ------------------------------------------------------- journal and files


class _NoWal(sqlite3.Connection):
    """A connection on a file system where WAL fails, as on NFS: setting it
    raises what SQLite says there."""

    def execute(self, sql, *args):
        if sql.replace(" ", "").upper() == "PRAGMAJOURNAL_MODE=WAL":
            raise sqlite3.OperationalError("locking protocol")
        return super().execute(sql, *args)


def test_without_wal_the_rollback_journal_serves(path, monkeypatch, caplog):
    """WAL made unavailable (the pragma fails, as on NFS): the ledger says so
    in the log, uses the rollback journal, and keeps its decisions across
    reopening; a probe that reports WAL refused (another mode returned)
    falls back the same way."""
    from rsmb.pipeline.archive import _ledger

    connect = sqlite3.connect
    monkeypatch.setattr(_ledger.sqlite3, "connect", lambda *a, **k: connect(*a, factory=_NoWal, **k))
    with caplog.at_level("WARNING", logger="rsmb"), Ledger(path) as ledger:
        assert ledger.journal == "delete"
        assert ledger._conn.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
        _done(ledger, "c.tif", _key())
    assert "WAL unavailable on this file system (locking protocol); using the rollback journal" in caplog.text
    assert not path.with_name(path.name + "-wal").exists()
    monkeypatch.setattr(_ledger.sqlite3, "connect", connect)
    monkeypatch.setattr(_ledger, "_wal_problem", lambda conn: "journal_mode=WAL gave delete")
    with Ledger(path) as ledger:
        assert ledger.journal == "delete" and ledger.decide("c.tif", _key()).action == "skip"
        with pytest.raises(InputError, match="in use by another rsmb survey"):
            Ledger(path)
    with Ledger(path, readonly=True) as reader:
        assert [r.status for r in reader.runs()] == ["done"]


def test_files_are_remembered_and_a_version_1_ledger_gains_them(path):
    from rsmb.pipeline.archive._ledger import FileStat

    with Ledger(path) as ledger:
        _done(ledger, "c.tif", _key())
        ledger.remember_files([FileStat("c.tif", 10, 123, 7, "1" * 64, (4, 5))])
        ledger.remember_files([FileStat("c.tif", 11, 124, 7, "2" * 64, (4, 5))])  # replaced
        assert ledger.file_stats() == {"c.tif": FileStat("c.tif", 11, 124, 7, "2" * 64, (4, 5))}
    conn = sqlite3.connect(path)
    conn.execute("DROP TABLE files")
    conn.execute("PRAGMA user_version=1")
    conn.commit()
    conn.close()
    with Ledger(path, readonly=True) as reader:  # read as it is
        assert reader.file_stats() == {} and len(reader.runs()) == 1
    with Ledger(path) as ledger:
        assert ledger.file_stats() == {} and ledger.decide("c.tif", _key()).action == "skip"
    assert sqlite3.connect(path).execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION == 2
