"""The survey ledger, ``OUT_DIR/ledger.sqlite``: what was run, on what, and how it went.

DESIGN.md, "Survey archives": every capture ever seen, its sha256, the reference
set, the parameters, the rsmb version, the status, the reason, the times and the
outputs.  A capture done with the same key is skipped, a failed one retried, a
changed one redone.

One row per attempt (table ``runs``; the view ``captures`` shows the latest attempt
of each capture).  The key of an attempt is
``sha256(capture sha256, reference set digest, parameters JSON, rsmb version)``
(:class:`RunKey`); the reference set digest is the sha256 of the references'
sha256s in mosaic order (order matters: the first file with data wins).

Decision rule (:meth:`Ledger.decide`): skip when the capture's latest *done*
attempt has the same key (its outputs are the ones in place: a later failed
attempt never replaced them, capture folders being atomic); otherwise run, and say
why: new, failed before (retry), interrupted, or what changed since the last done
(content, reference set, parameters, version).

Writers: only the driver process writes the ledger, through one connection; the
tasks on workers never touch it (they return results to the driver).  A second
driver on the same ledger is refused (an exclusive ``flock`` on
``ledger.sqlite.lock``, released by the kernel when the process dies).  The
database is in WAL mode with ``synchronous=FULL`` and every change is one
transaction, so a SIGKILL at any moment leaves either the state before or the
state after that change.  Where WAL does not work (network file systems: NFS,
Lustre, SMB have no shared memory between hosts), the ledger says so in the
log and uses the rollback journal (``DELETE``), with the same guarantees for
its one writer: the probe sets WAL and writes one transaction with it; any
refusal or error falls back.

Files (table ``files``, schema version 2): the sha256 and image shape of every
capture and reference file hashed, with the size, modification time (ns) and
inode it had.  A file whose three are unchanged is not read again: a night with
nothing new costs one ``stat`` per file (:meth:`Ledger.file_stats`).  A ledger
of version 1 gains the table when opened for writing.  An attempt left ``running`` by a night that was killed
is closed as ``failed`` (reason ``interrupted``) when the ledger is next opened
for writing, so it counts as not done and is rerun.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import logging
import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from rsmb.ops._errors import InputError, ParameterError

__all__ = ["LEDGER_NAME", "SCHEMA_VERSION", "Decision", "FileStat", "Ledger", "LedgerRow", "RunKey",
           "reference_set_digest"]

log = logging.getLogger("rsmb")

#: File name of the ledger inside a survey's output directory.
LEDGER_NAME = "ledger.sqlite"
#: Default settle time of a survey, seconds: a capture modified less long ago
#: is still being copied in and waits for the next night (the one default of
#: ``rsmb survey --settle``, ``survey(settle=)`` and a workflow's ``settle``).
SETTLE = 60.0
#: Version of the tables below, stored as SQLite's ``user_version``.
SCHEMA_VERSION = 2
STATUSES = ("running", "done", "failed")

_FILES = """
CREATE TABLE files (
    path TEXT PRIMARY KEY,
    size INTEGER NOT NULL,
    mtime_ns INTEGER NOT NULL,
    inode INTEGER NOT NULL,
    sha256 TEXT NOT NULL,
    shape TEXT NOT NULL
)"""
_SCHEMA = """
CREATE TABLE runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    capture TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    key TEXT NOT NULL,
    reference_paths TEXT NOT NULL,
    reference_digest TEXT NOT NULL,
    parameters TEXT NOT NULL,
    version TEXT NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('running', 'done', 'failed')),
    reason TEXT NOT NULL DEFAULT '',
    night TEXT,
    started TEXT NOT NULL,
    finished TEXT,
    outputs TEXT NOT NULL DEFAULT '{}'
);
CREATE INDEX runs_by_capture ON runs (capture, id);
CREATE VIEW captures AS
    SELECT runs.* FROM runs
    JOIN (SELECT capture, MAX(id) AS id FROM runs GROUP BY capture) AS latest
    ON runs.id = latest.id;
""" + _FILES + ";\n"
_COLUMNS = ("id", "capture", "sha256", "key", "reference_paths", "reference_digest", "parameters",
            "version", "status", "reason", "night", "started", "finished", "outputs")


def utc_now() -> str:
    """The current UTC time, ISO 8601 to the millisecond with a ``Z``."""
    now = _dt.datetime.now(_dt.timezone.utc)
    return now.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def reference_set_digest(sha256s: Sequence[str]) -> str:
    """Digest of a reference set: sha256 of its files' sha256s, one a line, in
    mosaic order."""
    return _sha256("\n".join(sha256s))


# --------------------------------------------------------------------------- values


@dataclass(frozen=True)
class FileStat:
    """A file as hashed: its path, ``os.stat`` size, modification time (ns)
    and inode then, its sha256 and its image shape (rows, cols)."""

    path: str
    size: int
    mtime_ns: int
    inode: int
    sha256: str
    shape: tuple[int, int]

    def same_file(self, st: os.stat_result) -> bool:
        """True when ``st`` (a new ``os.stat``) has the size, time and inode recorded."""
        return (self.size, self.mtime_ns, self.inode) == (st.st_size, st.st_mtime_ns, st.st_ino)


@dataclass(frozen=True)
class RunKey:
    """Everything a capture's result depends on; :attr:`key` is its digest.

    Attributes
    ----------
    sha256 : str
        The capture file's sha256 (hex).
    reference_paths : tuple of str
        The reference files, in mosaic order (recorded, not part of the key).
    reference_digest : str
        :func:`reference_set_digest` of their sha256s.
    parameters : str
        The parameters as canonical JSON (sorted keys, no spaces).
    version : str
        The rsmb version.
    """

    sha256: str
    reference_paths: tuple[str, ...]
    reference_digest: str
    parameters: str
    version: str

    @classmethod
    def build(cls, sha256: str, reference_sha256s: Sequence[str], reference_paths: Sequence[str],
              parameters: Mapping[str, Any], version: str) -> RunKey:
        """A key from the capture's sha256, the references' sha256s and paths (same
        order), the parameters (a JSON-serialisable mapping) and the version."""
        if len(reference_sha256s) != len(reference_paths):
            raise ParameterError(f"reference_sha256s: expected one per reference path "
                                 f"({len(reference_paths)}), got {len(reference_sha256s)}")
        params = json.dumps(parameters, sort_keys=True, separators=(",", ":"), allow_nan=False)
        return cls(sha256, tuple(str(p) for p in reference_paths),
                   reference_set_digest(list(reference_sha256s)), params, str(version))

    @property
    def key(self) -> str:
        """sha256 of capture sha256, reference digest, parameters and version."""
        return _sha256("\n".join([self.sha256, self.reference_digest, self.parameters, self.version]))


@dataclass(frozen=True)
class LedgerRow:
    """One attempt at a capture, as stored (JSON columns decoded)."""

    id: int
    capture: str
    sha256: str
    key: str
    reference_paths: tuple[str, ...]
    reference_digest: str
    parameters: dict
    version: str
    status: str
    reason: str
    night: str | None
    started: str
    finished: str | None
    outputs: dict

    @classmethod
    def _from_sql(cls, row: tuple) -> LedgerRow:
        values = dict(zip(_COLUMNS, row))
        values["reference_paths"] = tuple(json.loads(values["reference_paths"]))
        values["parameters"] = json.loads(values["parameters"])
        values["outputs"] = json.loads(values["outputs"])
        return cls(**values)


@dataclass(frozen=True)
class Decision:
    """What to do with a capture tonight.

    Attributes
    ----------
    action : {"run", "skip"}
    reason : str
        One line: ``new capture``, ``done with the same key ...``, ``failed before
        (...): retry``, ``interrupted ...: rerun``, ``content changed ...: redo`` ...
    previous : LedgerRow or None
        The attempt the decision compared with.
    """

    action: str
    reason: str
    previous: LedgerRow | None = None


# --------------------------------------------------------------------------- ledger


class Ledger:
    """The SQLite ledger of a survey (module docstring: rules and guarantees).

    Parameters
    ----------
    path : str or path-like
        The ledger file (``OUT_DIR / LEDGER_NAME``); created with its schema when
        absent (not in read-only mode).
    readonly : bool
        Open for reading only (a ``--dry-run``, a report): no lock, no recovery,
        the file must exist.

    Raises
    ------
    InputError
        Not a readable ledger (not SQLite, another schema version), missing in
        read-only mode, or held by another driver.
    """

    def __init__(self, path: str | os.PathLike, *, readonly: bool = False) -> None:
        self.path = Path(path)
        self.readonly = readonly
        self.journal = None
        self._lock = None if readonly else _lock(self.path)
        try:
            self._conn = self._connect()
            self._check_schema()
            if not readonly:
                self._recover_interrupted()
        except BaseException:
            self._release_lock()
            raise

    # -- lifecycle

    def _connect(self) -> sqlite3.Connection:
        try:
            if self.readonly:
                if not self.path.exists():
                    raise InputError(f"{self.path}: no such ledger")
                conn = sqlite3.connect(f"{self.path.resolve().as_uri()}?mode=ro", uri=True,
                                       isolation_level=None)
            else:
                conn = sqlite3.connect(self.path, isolation_level=None)
                problem = _wal_problem(conn)
                if problem is None:
                    self.journal = "wal"
                else:  # a network file system: the rollback journal works where WAL does not
                    conn.close()
                    conn = sqlite3.connect(self.path, isolation_level=None)
                    mode = conn.execute("PRAGMA journal_mode=DELETE").fetchone()[0]
                    if mode.lower() != "delete":
                        raise InputError(f"{self.path}: neither WAL ({problem}) nor the rollback journal "
                                         f"(got {mode}) works here")
                    self.journal = "delete"
                    log.warning("ledger %s: WAL unavailable on this file system (%s); using the rollback "
                                "journal (DELETE)", self.path, problem)
                conn.execute("PRAGMA synchronous=FULL")
            conn.execute("PRAGMA busy_timeout=10000")
            return conn
        except sqlite3.DatabaseError as exc:
            raise InputError(f"{self.path}: not a readable ledger ({_one_line(exc)})") from exc

    def _check_schema(self) -> None:
        try:
            version = self._conn.execute("PRAGMA user_version").fetchone()[0]
            tables = self._conn.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]
        except sqlite3.DatabaseError as exc:
            raise InputError(f"{self.path}: not a readable ledger ({_one_line(exc)})") from exc
        if version == 1 and not self.readonly:  # version 2 adds the files' stat and hash
            with self._transaction():
                self._conn.execute(_FILES)
                self._conn.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            return
        if version == 1 and self.readonly:
            return  # read as it is: no files remembered yet
        if version == 0 and tables == 0 and not self.readonly:
            with self._transaction():  # one statement at a time: executescript would commit
                for statement in _SCHEMA.split(";"):
                    if statement.strip():
                        self._conn.execute(statement)
                self._conn.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            return
        if version != SCHEMA_VERSION:
            raise InputError(f"{self.path}: ledger schema version {version}; this rsmb reads "
                             f"version {SCHEMA_VERSION}")

    def _recover_interrupted(self) -> None:
        with self._transaction():
            self._conn.execute(
                "UPDATE runs SET status = 'failed', finished = ?, "
                "reason = 'interrupted: left running by a night that did not finish' "
                "WHERE status = 'running'", (utc_now(),))

    def close(self) -> None:
        """Close the connection and release the writer's lock."""
        conn, self._conn = getattr(self, "_conn", None), None
        if conn is not None:
            conn.close()
        self._release_lock()

    def _release_lock(self) -> None:
        lock, self._lock = getattr(self, "_lock", None), None
        if lock is not None:
            lock.close()  # closing the descriptor releases the flock

    def __enter__(self) -> Ledger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[None]:
        if self._conn is None:
            raise ParameterError(f"ledger: {self.path} is closed")
        self._conn.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            self._conn.execute("ROLLBACK")
            raise
        self._conn.execute("COMMIT")

    def _rows(self, sql: str, args: tuple = ()) -> list[LedgerRow]:
        if self._conn is None:
            raise ParameterError(f"ledger: {self.path} is closed")
        return [LedgerRow._from_sql(r) for r in self._conn.execute(sql, args).fetchall()]

    # -- decisions and writes

    def decide(self, capture: str, run_key: RunKey) -> Decision:
        """Run or skip ``capture`` with ``run_key`` (module docstring: the rule).

        Parameters
        ----------
        capture : str
            The capture's identity in the archive (its path as the survey names it).
        run_key : RunKey

        Returns
        -------
        Decision
        """
        return self.decide_from(self.runs(capture=capture), run_key)

    def history_by_capture(self) -> dict[str, list[LedgerRow]]:
        """Every attempt, by capture, in the order they started (one query:
        a night decides thousands of captures from it with :meth:`decide_from`)."""
        history: dict[str, list[LedgerRow]] = {}
        for row in self.runs():
            history.setdefault(row.capture, []).append(row)
        return history

    @staticmethod
    def decide_from(history: Sequence[LedgerRow], run_key: RunKey) -> Decision:
        """:meth:`decide` on a capture's attempts ``history`` (oldest first)."""
        if not history:
            return Decision("run", "new capture")
        last = history[-1]
        done = [r for r in history if r.status == "done"]
        if done and done[-1].key == run_key.key:
            return Decision("skip", f"done with the same key on {done[-1].finished}", done[-1])
        if last.key == run_key.key and last.status == "running":
            return Decision("run", f"interrupted (started {last.started}): rerun", last)
        if last.key == run_key.key and last.status == "failed":
            return Decision("run", f"failed before ({last.reason}): retry", last)
        previous = done[-1] if done else last
        return Decision("run", f"{_changes(previous, run_key)}: redo", previous)

    def start(self, capture: str, run_key: RunKey, *, night: str | None = None) -> int:
        """Record that ``capture`` starts now; returns the attempt's id.

        Parameters
        ----------
        capture : str
        run_key : RunKey
        night : str, optional
            The night's identity (its UTC start time), for :meth:`runs`.
        """
        row = (capture, run_key.sha256, run_key.key, json.dumps(list(run_key.reference_paths)),
               run_key.reference_digest, run_key.parameters, run_key.version, "running", "",
               night, utc_now())
        with self._transaction():
            cursor = self._conn.execute(
                "INSERT INTO runs (capture, sha256, key, reference_paths, reference_digest, "
                "parameters, version, status, reason, night, started) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", row)
        return int(cursor.lastrowid)

    def finish(self, run_id: int, status: str, reason: str = "",
               outputs: Mapping[str, Any] | None = None) -> None:
        """Close attempt ``run_id`` as ``"done"`` or ``"failed"``.

        Parameters
        ----------
        run_id : int
            From :meth:`start`.
        status : {"done", "failed"}
        reason : str
            Why it failed (one line; whitespace is collapsed), or a note.
        outputs : mapping, optional
            JSON-serialisable description of the outputs (paths, counts).

        Raises
        ------
        ParameterError
            Unknown status, or ``run_id`` is not a running attempt.
        """
        if status not in ("done", "failed"):
            raise ParameterError(f"status: expected 'done' or 'failed', got {status!r}")
        values = (status, _one_line(reason), utc_now(), json.dumps(dict(outputs or {}), sort_keys=True),
                  int(run_id))
        with self._transaction():
            cursor = self._conn.execute(
                "UPDATE runs SET status = ?, reason = ?, finished = ?, outputs = ? "
                "WHERE id = ? AND status = 'running'", values)
            if cursor.rowcount != 1:
                raise ParameterError(f"run_id: expected a running attempt of {self.path}, got {run_id}")

    def amend(self, run_id: int, *, outputs: Mapping[str, Any]) -> None:
        """Replace the outputs recorded for attempt ``run_id`` (its folder moved)."""
        with self._transaction():
            self._conn.execute("UPDATE runs SET outputs = ? WHERE id = ?",
                               (json.dumps(dict(outputs), sort_keys=True), int(run_id)))

    def undo_done(self, capture: str, reason: str) -> None:
        """Mark every done attempt of ``capture`` failed with ``reason``: its
        outputs are gone, so it runs again (a retry) however its key compares."""
        with self._transaction():
            self._conn.execute("UPDATE runs SET status = 'failed', reason = ? WHERE capture = ? AND status = 'done'",
                               (_one_line(reason), capture))

    # -- files

    def file_stats(self) -> dict[str, FileStat]:
        """Every file remembered (path -> :class:`FileStat`), in one query."""
        if self._conn is None:
            raise ParameterError(f"ledger: {self.path} is closed")
        if not self._conn.execute("SELECT count(*) FROM sqlite_master WHERE name = 'files'").fetchone()[0]:
            return {}  # a version-1 ledger read as it is
        rows = self._conn.execute("SELECT path, size, mtime_ns, inode, sha256, shape FROM files").fetchall()
        return {r[0]: FileStat(r[0], r[1], r[2], r[3], r[4], tuple(json.loads(r[5]))) for r in rows}

    def remember_files(self, stats: Sequence[FileStat]) -> None:
        """Record (or replace) files' stat and hash, in one transaction."""
        if not stats:
            return
        with self._transaction():
            self._conn.executemany(
                "INSERT OR REPLACE INTO files (path, size, mtime_ns, inode, sha256, shape) VALUES (?, ?, ?, ?, ?, ?)",
                [(f.path, int(f.size), int(f.mtime_ns), int(f.inode), f.sha256, json.dumps(list(f.shape)))
                 for f in stats])

    # -- listings

    def runs(self, *, capture: str | None = None, night: str | None = None,
             status: str | None = None, outside: str | None = None) -> list[LedgerRow]:
        """Attempts in the order they started, optionally of one capture, one
        night or one status, or (``outside``, a folder) with an output folder
        recorded that is not under it (the filter runs in SQLite)."""
        where, args = [], []
        if outside is not None:
            where.append("json_extract(outputs, '$.output') IS NOT NULL "
                         "AND substr(json_extract(outputs, '$.output'), 1, ?) != ?")
            prefix = outside.rstrip(os.sep) + os.sep
            args.extend([len(prefix), prefix])
        if status is not None:
            where.append("status = ?")
            args.append(status)
        if capture is not None:
            where.append("capture = ?")
            args.append(capture)
        if night is not None:
            where.append("night = ?")
            args.append(night)
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        return self._rows(f"SELECT {', '.join(_COLUMNS)} FROM runs{clause} ORDER BY id", tuple(args))

    def captures(self) -> list[LedgerRow]:
        """The latest attempt of every capture ever seen, by capture name."""
        return self._rows(f"SELECT {', '.join(_COLUMNS)} FROM captures ORDER BY capture")


def _changes(previous: LedgerRow, run_key: RunKey) -> str:
    """What differs between an earlier attempt and ``run_key``, in words."""
    changes = []
    if previous.sha256 != run_key.sha256:
        changes.append(f"content changed (sha256 {previous.sha256[:12]} -> {run_key.sha256[:12]})")
    if previous.reference_digest != run_key.reference_digest:
        changes.append("reference set changed")
    params = json.loads(run_key.parameters)
    if previous.parameters != params:
        keys = sorted(k for k in set(previous.parameters) | set(params)
                      if previous.parameters.get(k) != params.get(k))
        changes.append(f"parameters changed ({', '.join(keys)})")
    if previous.version != run_key.version:
        changes.append(f"rsmb version changed ({previous.version} -> {run_key.version})")
    if not changes:  # same key, an earlier attempt that was neither done nor retried
        changes.append(f"previous attempt {previous.status}")
    return "; ".join(changes)


def _wal_problem(conn: sqlite3.Connection) -> str | None:
    """None when WAL works on ``conn``'s file (set, then one write transaction
    committed with it), else what went wrong."""
    try:
        mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
        if mode.lower() != "wal":
            return f"journal_mode=WAL gave {mode}"
        conn.execute("BEGIN IMMEDIATE")
        conn.execute("COMMIT")
    except sqlite3.Error as exc:
        return _one_line(exc)
    return None


def _lock(path: Path):
    """An exclusive, non-blocking lock on ``<path>.lock``: one driver per
    ledger (:func:`rsmb.tiles.acquire_lock`: contention says "in use", any
    other failure says what it is)."""
    from rsmb.tiles._lock import acquire_lock

    if not path.parent.is_dir():
        raise InputError(f"{path.parent}: no such directory for the ledger")
    return acquire_lock(f"{path}.lock", what="rsmb survey")
