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
    products = _products.ProductProcess().start()
    try:
        child = products.write(store, tmp_path / "child", stamp, capture.capture)
    finally:
        products.close()
    here = _products.Here().write(store, tmp_path / "here2", stamp, capture.capture)
    assert child[:2] == here[:2] == (capture.changes, capture.changed_m2)
    (cover, changes, crs), (cover_here, changes_here, crs_here) = child[2], here[2]
    assert cover.equals_exact(cover_here, 0) and crs == crs_here and len(changes) == len(changes_here) > 0
    assert all(a.equals_exact(b, 0) for a, b in zip(changes, changes_here))


def test_no_products_process_without_reports_or_for_one_capture(tmp_path, monkeypatch):
    """Without reports (nothing of their Python to take out) and for a night
    of one capture (nothing runs beside it), the driver threads write the
    products."""
    references, night = _night(tmp_path, _scene(), bad=False)

    def no_child():
        raise AssertionError("a products' process was started")

    monkeypatch.setattr(survey_module, "ProductProcess", no_child)
    result = survey_module.survey(references, str(night / "**" / "*.tif"), tmp_path / "a", settle=0, report=False)
    assert result.done == 3
    result = survey_module.survey(references, str(night / "**" / "cap0.tif"), tmp_path / "b", settle=0)
    assert result.done == 1 and (Path(result.captures[0].output) / "report" / "index.html").is_file()


def _missing_store_reason(tmp_path):
    with pytest.raises(InputError) as here:
        _products.Here().write(tmp_path / "missing.zarr", tmp_path, 0.0, "c.tif")
    return str(here.value)


def test_products_that_fail_in_the_process_fail_with_the_reason_the_night_would_give(tmp_path):
    products = _products.ProductProcess().start()
    try:
        with pytest.raises(InputError) as child:
            products.write(tmp_path / "missing.zarr", tmp_path, 0.0, "c.tif")
    finally:
        products.close()
    assert str(child.value) == _missing_store_reason(tmp_path)
    assert _products.failure_reason(TypeError("bad\nvalue")) == "TypeError: bad value"


def _warnings(caplog):
    return [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "products' process" in r.getMessage()]


def test_a_products_process_that_dies_fails_its_capture_and_the_night_writes_the_next(tmp_path, caplog):
    """The capture whose products the child was writing when it died fails
    (what it wrote is unknown); the next ones are written by the night's
    process, with a warning once."""
    caplog.set_level(logging.WARNING, logger="rsmb")  # an earlier test's -q may have left it quieter
    store = tmp_path / "missing.zarr"
    products = _products.ProductProcess().start()
    try:
        with pytest.raises(InputError, match="missing.zarr"):
            products.write(store, tmp_path, 0.0, "c.tif")  # the child is ready, and answered
        child = products._child
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        with pytest.raises(InputError, match="^c.tif: the products' process ended .* it runs again next night$"):
            products.write(store, tmp_path, 0.0, "c.tif")
        assert products._child is None and child.stdin.closed
        with pytest.raises(InputError) as here:
            products.write(store, tmp_path, 0.0, "c.tif")
        assert str(here.value) == _missing_store_reason(tmp_path)
    finally:
        products.close()
    assert len(_warnings(caplog)) == 1


def test_a_products_process_that_cannot_start_or_ends_before_it_is_ready_costs_no_capture(tmp_path, caplog,
                                                                                          monkeypatch):
    caplog.set_level(logging.WARNING, logger="rsmb")
    reason = _missing_store_reason(tmp_path)

    def no_process(*args, **kwargs):
        raise OSError("no such program")

    for broken in ((_products.subprocess, "Popen", no_process), (_products.sys, "executable", "/bin/false")):
        monkeypatch.setattr(*broken)
        products = _products.ProductProcess().start()
        monkeypatch.undo()
        try:
            with pytest.raises(InputError) as here:  # written here: the reason the night's process gives
                products.write(tmp_path / "missing.zarr", tmp_path, 0.0, "c.tif")
            assert str(here.value) == reason and products._child is None
        finally:
            products.close()
    warnings = _warnings(caplog)
    assert len(warnings) == 2 and "cannot start it (no such program)" in warnings[0], warnings
    assert "ended before it was ready" in warnings[1], warnings


def test_a_killed_products_process_writes_nothing_more(tmp_path):
    """A stopped night kills the child: it is reaped, and a driver still
    asking is told the night stopped."""
    products = _products.ProductProcess().start()
    child = products._child
    products.kill()
    assert child.poll() is not None
    with pytest.raises(InputError, match="^c.tif: the night stopped before its products were written$"):
        products.write(tmp_path / "missing.zarr", tmp_path, 0.0, "c.tif")
    products.close()


def _products_processes(night_pid):
    """Pids of the products' processes of the night ``night_pid`` still running."""
    out = []
    for pid in os.listdir("/proc"):
        try:
            cmdline = Path("/proc", pid, "cmdline").read_bytes().decode(errors="replace")
            state = Path("/proc", pid, "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z" and "_products import serve" in cmdline and cmdline.rstrip("\0").endswith(f", {night_pid})"):
            out.append(int(pid))
    return out


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="reads /proc")
def test_ctrl_c_ends_the_products_process_with_the_night(tmp_path):
    """SIGINT to a night with reports while its child writes a capture's
    products: exit 130, and no products' process outlives the night."""
    references, night = _night(tmp_path, _scene(), bad=False)
    out = tmp_path / "out"
    args = ["-q", "survey", *map(str, references), "--captures", str(night / "**" / "*.tif"), "-o", str(out),
            "--settle", "0", "--parallel", "1"]
    proc = subprocess.Popen([sys.executable, "-m", "rsmb.pipeline.cli", *args], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    building = out / ".partial" / "building"
    deadline = time.monotonic() + 300

    def writing():
        """The first COG of a capture's products in its folder aside: the
        child is writing them (the night removes scratch folders meanwhile:
        one gone while it is searched is not there yet)."""
        try:
            return bool(list(building.rglob("change_mask_reference.tif")))
        except FileNotFoundError:
            return False

    while not writing() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert _products_processes(proc.pid)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr.decode()
    time.sleep(1.0)
    assert not _products_processes(proc.pid)


def test_a_report_drawn_in_the_nights_process_waits_for_the_nights_matplotlib_imports(tmp_path, monkeypatch):
    """The night imports matplotlib in a thread as its captures start; a
    report written by the night's own process (one capture, or a products
    process that gave up) waits for that thread first, so that two threads
    never import matplotlib at once.  Products without a report do not
    wait."""
    order = []

    class Imports:
        def join(self):
            order.append("joined")

    def written(store, folder, last_change, report=True):
        order.append(f"written, report {report}")
        return 0, 0.0

    monkeypatch.setattr(_products, "write_capture_products", written)
    monkeypatch.setattr(_products, "observe", lambda folder: None)
    assert _products.Here(True, Imports()).write(tmp_path, tmp_path, 0.0, "c.tif") == (0, 0.0, None)
    assert order == ["joined", "written, report True"]
    order.clear()
    _products.Here(False, Imports()).write(tmp_path, tmp_path, 0.0, "c.tif")
    assert order == ["written, report False"]
    order.clear()
    child = _products.ProductProcess(Imports())  # never started: it writes here, as after giving up
    child.write(tmp_path, tmp_path, 0.0, "c.tif")
    assert order == ["joined", "written, report True"]
