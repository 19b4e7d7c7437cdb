"""Bench section ``ledger``: a "nothing new" night over a large archive.

An archive of ``count`` small capture files (32 bytes each, in folders of 100)
that earlier nights have done: the ledger holds, for each, a done attempt with
the key tonight's survey computes and the file's size, modification time and
inode with its sha256 (inserted directly, in one transaction: running 10,000
real detections would take hours).  Then ``survey`` runs the night on the real
files, which it finds by the glob and ``stat``s: every capture must be
skipped.  Measured: the night's wall and CPU seconds, the bytes the process
read (``rchar``: every ``read`` call, the ledger's own pages included, and
``read_bytes``: from the disk), and the decisions alone (glob, stats, ledger
query) on a read-only ledger.  The capture files are not images: a night that
opened one would fail it, so "every capture skipped" shows none was read.
"""

import dataclasses
import hashlib
import json
import os
import sqlite3
import time
from pathlib import Path

import numpy as np

from rsmb import ops
from rsmb import tiles

from ..archive import _survey
from ..archive._ledger import LEDGER_NAME, FileStat, Ledger, RunKey, utc_now
from ..detection._plan import VERSION, DetectConfig
from ._archive import write_reference

__all__ = ["bench_ledger"]

SHAPE = (1024, 1024)  # the shape the ledger records for each capture (its key's resolved steps)


def _io():
    """(rchar, read_bytes) of this process so far (Linux), else zeros."""
    try:
        import psutil

        io = psutil.Process().io_counters()
        return io.read_chars, io.read_bytes
    except (ImportError, AttributeError, OSError):
        return 0, 0


def _archive(root, count):
    """``count`` small files under ``root/incoming/dNNN/``: a list of paths."""
    paths = []
    for k in range(count):
        path = root / "incoming" / f"d{k // 100:03d}" / f"c{k:05d}.tif"
        if k % 100 == 0:
            path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(hashlib.sha256(str(k).encode()).digest())
        paths.append(path)
    return paths


def _fill_ledger(out, paths, references, config):
    """The ledger of earlier nights: each capture done with tonight's key, each
    file's stat and hash remembered (one transaction)."""
    out.mkdir(parents=True, exist_ok=True)
    with Ledger(out / LEDGER_NAME) as ledger:
        refs = [FileStat(str(r), *_stat(r), info.sha256, tuple(info.shape))
                for r, info in ((r, tiles.probe_image(r)) for r in references)]
        ledger.remember_files(refs)
    parameters = _survey._parameters(config, SHAPE)
    reference_shas = [r.sha256 for r in refs]
    stamp, files, runs = utc_now(), [], []
    for path in paths:
        sha = hashlib.sha256(path.read_bytes()).hexdigest()
        key = RunKey.build(sha, reference_shas, [str(r) for r in references], parameters, VERSION)
        files.append((str(path), *_stat(path), sha, json.dumps(list(SHAPE))))
        folder = out / _survey.CAPTURES / path.relative_to(out.parent / "incoming")
        outputs = {"output": str(folder), "vectors": str(folder / "changes.gpkg"), "changes": 0, "changed_m2": 0.0,
                   "reference": [str(r) for r in references]}
        runs.append((str(path), sha, key.key, json.dumps(list(key.reference_paths)), key.reference_digest,
                     key.parameters, key.version, "done", "", "earlier", stamp, stamp, json.dumps(outputs)))
    conn = sqlite3.connect(out / LEDGER_NAME)
    with conn:
        conn.executemany("INSERT INTO files (path, size, mtime_ns, inode, sha256, shape) VALUES (?, ?, ?, ?, ?, ?)",
                         files)
        conn.executemany("INSERT INTO runs (capture, sha256, key, reference_paths, reference_digest, parameters, "
                         "version, status, reason, night, started, finished, outputs) "
                         "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", runs)
    conn.close()


def _stat(path):
    st = os.stat(path)
    return st.st_size, st.st_mtime_ns, st.st_ino


def bench_ledger(tmp, *, count=10_000):
    """Time a night with nothing new over ``count`` done captures (module
    docstring).  Returns a dict of the figures."""
    root = Path(tmp) / "ledger"
    scene = (0.05 + 0.7 * ops.aerial_scene((256, 256), seed=3)).astype(np.float32)
    references = write_reference(root / "reference", scene)
    config = dataclasses.replace(DetectConfig(), tile=_survey.SURVEY_TILE)
    t0 = time.perf_counter()
    paths = _archive(root, count)
    out = root / "survey"
    _fill_ledger(out, paths, references, config)
    setup = time.perf_counter() - t0
    pattern = str(root / "incoming" / "**" / "*.tif")

    start, cpu, (rchar, disk) = time.perf_counter(), time.process_time(), _io()
    found = _survey.find_captures(pattern, out)
    with Ledger(out / LEDGER_NAME, readonly=True) as ledger:
        fates = _survey._decide_all(ledger, found, [str(r) for r in references], config, 0.0)
    decide = {"seconds": time.perf_counter() - start, "cpu_seconds": time.process_time() - cpu,
              "read_chars": _io()[0] - rchar}
    assert [f[2] for f in fates].count("skip") == count, "a capture was not known by its stat"

    start, cpu, (rchar, disk) = time.perf_counter(), time.process_time(), _io()
    result = _survey.survey([str(r) for r in references], pattern, out, report=False, settle=0)
    night = {"seconds": time.perf_counter() - start, "cpu_seconds": time.process_time() - cpu,
             "read_chars": _io()[0] - rchar, "read_bytes": _io()[1] - disk}
    if (result.skipped, result.done, result.failed) != (count, 0, 0):
        raise ops.RunError(f"ledger bench: expected {count} skipped, got {result.done} done, {result.skipped} "
                           f"skipped, {result.failed} failed")
    ledger_bytes = os.path.getsize(out / LEDGER_NAME)
    print(f"ledger: a night with nothing new over {count} done captures: {night['seconds']:.2f} s "
          f"({night['cpu_seconds']:.2f} CPU-s), read {night['read_chars'] / 1e6:.1f} MB by read calls "
          f"({night['read_bytes'] / 1e6:.1f} MB from disk; the ledger is {ledger_bytes / 1e6:.1f} MB, the "
          f"captures {count * 32 / 1e6:.2f} MB); decisions alone (glob, stat, ledger) {decide['seconds']:.2f} s "
          f"({decide['cpu_seconds']:.2f} CPU-s, {decide['read_chars'] / 1e6:.1f} MB read); "
          f"archive and ledger built in {setup:.1f} s", flush=True)
    return {"captures": count, "night": night, "decisions": decide, "ledger_bytes": ledger_bytes,
            "setup_seconds": setup}
