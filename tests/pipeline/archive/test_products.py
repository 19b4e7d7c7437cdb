"""The products a survey writes beside a capture's store, by a process of
their own in a night with reports (pipeline.archive._products)."""

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rsmb.ops import InputError
from rsmb.pipeline.archive import _products
from rsmb.pipeline.archive import _survey as survey_module

from .test_survey import _night, _scene

FILES = ("change_mask_reference.tif", "change_score_reference.tif", "parallax_mask_reference.tif", "changes.gpkg",
         "thumbnail.png", "report/overlay.png", "report/before_after.jpg", "report/trajectory.png",
         "report/change_score.png")


def test_a_night_with_reports_writes_its_products_in_a_process_of_its_own(tmp_path, monkeypatch):
    """With reports and more than one capture, the night's own process
    writes none of the products (the child does), and they are those the
    night's process writes from the same store, byte for byte."""
    references, night = _night(tmp_path, _scene(), bad=False)

    def not_here(*args, **kwargs):
        raise AssertionError("written by the night's process")

    monkeypatch.setattr(_products, "write_capture_products", not_here)
    result = survey_module.survey(references, str(night / "**" / "*.tif"), tmp_path / "out", settle=0)
    assert result.done == 3, [c.reason for c in result.captures]
    monkeypatch.undo()
    for capture in result.captures:
        folder, here = Path(capture.output), tmp_path / "here" / Path(capture.output).name
        here.mkdir(parents=True)
        changes, area = _products.write_capture_products(folder / "changes.zarr", here,
                                                         os.stat(capture.capture).st_mtime)
        assert (changes, area) == (capture.changes, capture.changed_m2)
        for name in FILES:
            assert (here / name).read_bytes() == (folder / name).read_bytes(), name
    # the child's answer: what the night's process would make of the same store
    capture = result.captures[0]
    store, stamp = Path(capture.output) / "changes.zarr", os.stat(capture.capture).st_mtime
    products = _products.ProductProcess()
    try:
        child = products.write(store, tmp_path / "child", stamp)
    finally:
        products.close()
    here = _products.Here().write(store, tmp_path / "here2", stamp)
    assert child[:2] == here[:2] == (capture.changes, capture.changed_m2)
    (cover, changes, crs), (cover_here, changes_here, crs_here) = child[2], here[2]
    assert cover.equals_exact(cover_here, 0) and crs == crs_here and len(changes) == len(changes_here) > 0
    assert all(a.equals_exact(b, 0) for a, b in zip(changes, changes_here))


def test_products_that_fail_in_the_process_fail_with_the_reason_the_night_would_give(tmp_path):
    store = tmp_path / "missing.zarr"
    with pytest.raises(InputError) as here:
        _products.Here().write(store, tmp_path, 0.0)
    products = _products.ProductProcess()
    try:
        with pytest.raises(InputError) as child:
            products.write(store, tmp_path, 0.0)
    finally:
        products.close()
    assert str(child.value) == str(here.value)


def test_a_products_process_that_dies_fails_its_capture_and_the_night_writes_the_next(tmp_path, caplog):
    """The capture whose products the child was writing when it died fails
    (what it wrote is unknown); the next ones are written by the night's
    process, with a warning once."""
    caplog.set_level(logging.WARNING, logger="rsmb")  # an earlier test's -q may have left it quieter
    store = tmp_path / "missing.zarr"
    products = _products.ProductProcess()
    try:
        with pytest.raises(InputError, match="missing.zarr") as first:
            products.write(store, tmp_path, 0.0)  # the child started, and answered
        os.kill(products._child.pid, signal.SIGKILL)
        products._child.wait()
        with pytest.raises(InputError, match="the products' process ended .* it runs again next night"):
            products.write(store, tmp_path, 0.0)
        with pytest.raises(InputError) as here:
            products.write(store, tmp_path, 0.0)
        assert str(here.value) == str(first.value)
        assert products._child is None
    finally:
        products.close()
    assert sum("products' process ended" in r.getMessage() for r in caplog.records) == 1


def _products_processes(night_pid):
    """Pids of the products' processes of the night ``night_pid`` still running."""
    out = []
    for pid in os.listdir("/proc"):
        try:
            cmdline = Path("/proc", pid, "cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        if pid.isdigit() and "_products import serve" in cmdline and cmdline.rstrip("\0").endswith(f", {night_pid})"):
            out.append(int(pid))
    return out


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="reads /proc")
def test_ctrl_c_ends_the_products_process_with_the_night(tmp_path):
    """SIGINT to a night with reports once a capture is done: exit 130, and its
    products' process ends with it."""
    references, night = _night(tmp_path, _scene(), bad=False)
    out = tmp_path / "out"
    args = ["-q", "survey", *map(str, references), "--captures", str(night / "**" / "*.tif"), "-o", str(out),
            "--settle", "0", "--parallel", "1"]
    proc = subprocess.Popen([sys.executable, "-m", "rsmb.pipeline.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    while not (out / "captures" / "flight1").is_dir() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _products_processes(proc.pid) or proc.poll() is not None
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode in (0, 130), stderr.decode()
    deadline = time.monotonic() + 30
    while _products_processes(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _products_processes(proc.pid)
