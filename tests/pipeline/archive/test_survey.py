"""``rsmb survey``: a night of georeferenced captures against a reference mosaic
(DESIGN.md, "Survey archives"), on archives these tests build."""

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from rsmb import ops
from rsmb.pipeline.archive import _survey as survey_module
from rsmb.tiles import _sources
from rsmb.pipeline.bench._archive import CaptureSpec, _write, scene_geo, write_capture, write_reference
from rsmb.pipeline.cli import main

from ..conftest import read_store

GOOD = [(100, 100), (300, 420), (420, 150)]
LARGE_REFERENCE_W = 704


def _scene():
    return (0.05 + 0.7 * ops.aerial_scene((768, 768), seed=5)).astype(np.float32)


def _night(root, scene, *, bad=True, large=False):
    """A reference mosaic of two files and a night folder: three good captures
    in flight1/, and with ``bad`` four bad ones in flight2/.  With ``large``,
    the reference stops 64 px short of the scene's right edge and flight1/ has
    a fourth capture, cap3, of 544 x 544 px (more than one 512-px COG block:
    its COGs have overviews) that overhangs the reference by about 40 px (no
    data there)."""
    references = write_reference(root / "reference", scene[:, :LARGE_REFERENCE_W] if large else scene, split=2)
    night = root / "incoming"
    for k, origin in enumerate(GOOD):
        write_capture(night / "flight1" / f"cap{k}.tif", scene, CaptureSpec(origin, (256, 256), seed=10 + k,
                                                                            changes=3))
    if large:
        write_capture(night / "flight1" / "cap3.tif", scene, CaptureSpec((112, 200), (544, 544), seed=13, changes=5))
    if bad:
        write_capture(night / "flight2" / "elsewhere.tif", scene, CaptureSpec((100, 100), (256, 256), seed=20),
                      offset_m=(9000.0, 0.0))
        write_capture(night / "flight2" / "nogeo.tif", scene, CaptureSpec((100, 100), (256, 256), seed=21),
                      georeferenced=False)
        _write(night / "flight2" / "flat.tif", np.full((256, 256), 0.4, np.float32), scene_geo((100, 100)))
        truncated = night / "flight2" / "truncated.tif"
        data = (night / "flight1" / "cap0.tif").read_bytes()
        truncated.write_bytes(data[:len(data) // 2])
    return references, night


def _survey(references, night, out, *extra):
    return main(["-q", "survey", *map(str, references), "--captures", str(night / "**" / "*.tif"), "-o", str(out),
                 "--no-report", "--settle", "0", *extra])


class FirstNight(NamedTuple):
    root: Path
    references: list
    night: Path
    out: Path
    args: list  # the command
    code: int  # its exit code
    seconds: float  # from the command's start to its return (summary and index written)


@pytest.fixture(scope="module")
def first_night(tmp_path_factory):
    root = tmp_path_factory.mktemp("survey")
    references, night = _night(root, _scene(), large=True)
    out = root / "out"
    args = ["-q", "survey", *map(str, references), "--captures", str(night / "**" / "*.tif"), "-o", str(out),
            "--json", "--settle", "0"]
    start = time.perf_counter()
    code = main(args)
    return FirstNight(root, references, night, out, args, code, time.perf_counter() - start)


def _summary(out):
    nights = sorted((out / "nights").glob("*.json"))
    return json.loads(nights[-1].read_text())


def test_bad_captures_fail_and_the_rest_finish(first_night, capsys):
    out = first_night.out
    assert first_night.code == 3
    summary = _summary(out)
    status = {os.path.basename(c["capture"]): c for c in summary["captures"]}
    assert summary["done"] == 4 and summary["failed"] == 4 and summary["skipped"] == 0
    for name in ("cap0.tif", "cap1.tif", "cap2.tif", "cap3.tif"):
        c = status[name]
        assert c["status"] == "done" and c["changes"] >= 1 and c["changed_m2"] > 0
        assert set(c) == {"capture", "status", "reason", "reference", "output", "vectors", "changes", "changed_m2",
                          "seconds"}
    assert "does not overlap" in status["elsewhere.tif"]["reason"]
    assert "not georeferenced" in status["nogeo.tif"]["reason"]
    assert "constant" in status["flat.tif"]["reason"]
    assert "cut short" in status["truncated.tif"]["reason"]
    assert not (out / "captures" / "flight2").exists() and not (out / ".partial").exists()


def test_each_capture_folder_holds_its_products(first_night):
    import pyogrio
    import rasterio

    night, out = first_night.night, first_night.out
    folder = out / "captures" / "flight1" / "cap1.tif"
    assert sorted(p.name for p in folder.iterdir()) == ["change_mask_reference.tif", "change_score_reference.tif",
                                                       "changes.gpkg", "changes.zarr", "parallax_mask_reference.tif",
                                                       "report", "thumbnail.png"]
    with rasterio.open(night / "flight1" / "cap1.tif") as src:
        crs, bounds = src.crs, src.bounds
    info = pyogrio.read_info(folder / "changes.gpkg", layer="changes", force_total_bounds=True)
    arrays, attrs = read_store(folder / "changes.zarr")
    assert info["crs"] in (crs.to_string(), f"EPSG:{crs.to_epsg()}")
    assert info["features"] >= 1
    _, _, geometry, fields = pyogrio.raw.read(folder / "changes.gpkg", layer="changes")
    assert fields[0].sum() == (arrays["change_mask_reference"] == 1).sum()  # pixels, in the ground frame
    xmin, ymin, xmax, ymax = info["total_bounds"]
    assert bounds.left <= xmin and xmax <= bounds.right and bounds.bottom <= ymin and ymax <= bounds.top
    for name, nodata in (("change_mask_reference.tif", 255), ("change_score_reference.tif", None)):
        with rasterio.open(folder / name) as ds:
            assert ds.crs == crs and ds.descriptions[0] == name[:-4]
            assert (ds.nodata == nodata) if nodata is not None else np.isnan(ds.nodata)
            assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
    assert attrs["summary"]["output"] == str(folder / "changes.zarr")
    page = (folder / "report" / "index.html").read_text()  # built aside, it names where the store ended up
    assert f"Store <code>{folder / 'changes.zarr'}</code>" in page and ".partial" not in page


def test_the_products_are_the_stores_kept_components(first_night):
    """Every done capture's GIS products against its own store's ground
    frame: each COG holds the store's array of its name, no-data (255, NaN)
    included, and has overviews (nearest for the masks, so still 0, 1 or
    no-data) when larger than one 512-px block; changes.gpkg has one polygon
    per 8-connected component of change_mask_reference, with its pixel count
    and area_m2 = pixels x the pixel's area."""
    import pyogrio
    import rasterio
    from scipy import ndimage

    out, night = first_night.out, first_night.night
    for name in ("cap0", "cap1", "cap2", "cap3"):
        folder = out / "captures" / "flight1" / f"{name}.tif"
        arrays, _ = read_store(folder / "changes.zarr")
        unknown = ~np.isfinite(arrays["registered"])
        assert unknown.any() == (name == "cap3")  # cap3 overhangs the reference
        ground = arrays["change_mask_reference"]  # 255: no evidence, or a ground pixel the capture did not see
        assert np.array_equal(ground == 255, np.isnan(arrays["change_score_reference"])), name
        assert (ground == 255).mean() > 0.05 if name == "cap3" else (ground == 255).mean() < 0.05, name
        for product, nodata in (("change_mask_reference", 255), ("change_score_reference", np.nan),
                                ("parallax_mask_reference", 255)):
            with rasterio.open(folder / f"{product}.tif") as ds:
                assert ds.nodata == nodata or (np.isnan(nodata) and np.isnan(ds.nodata)), (name, product)
                np.testing.assert_array_equal(ds.read(1), arrays[product], err_msg=f"{name} {product}")
                assert ds.overviews(1) == ([2] if max(ds.shape) > 512 else []), (name, product)
                if ds.overviews(1) and product == "change_mask_reference":
                    overview = ds.read(1, out_shape=(ds.height // 2, ds.width // 2))
                    assert set(np.unique(overview)) == {0, 1, 255}, (name, product)
        with rasterio.open(night / "flight1" / f"{name}.tif") as src:
            a, b, _, d, e, _ = tuple(src.transform)[:6]
        labels, count = ndimage.label(arrays["change_mask_reference"] == 1, structure=np.ones((3, 3)))
        _, _, geometry, fields = pyogrio.raw.read(folder / "changes.gpkg", layer="changes")
        pixels, area_m2 = fields[0], fields[1]
        assert len(geometry) == count >= 1, name
        assert sorted(pixels) == sorted(np.bincount(labels.ravel())[1:]), name
        np.testing.assert_allclose(area_m2, pixels * abs(a * e - b * d), rtol=1e-12, err_msg=name)


def test_the_index_lists_every_capture_with_its_thumbnail(first_night):
    """Every capture once, named relative to the glob's prefix (its full path
    only in the tooltip, never repeated in its reason), in a table that fits
    the window (fixed columns, long words wrap)."""
    page = (first_night.out / "index.html").read_text()
    for capture in sorted(first_night.night.rglob("*.tif")):
        name = capture.relative_to(first_night.night).as_posix()
        assert f"<code>{name}</code>" in page and page.count(str(capture)) == 1, name
    assert page.count("<img src='captures/flight1/cap") == 4 and "http" not in page
    assert "table-layout:fixed" in page and "overflow-wrap:anywhere" in page


def test_a_night_writes_its_history_catalog_and_map(first_night):
    """After a night: ``changes.gpkg`` in the reference CRS holds every change
    of the done captures (all new), ``stac/`` an item per done capture with
    every asset resolving, and the index shows the counts and the map."""
    import pyogrio
    import pystac
    import rasterio

    out = first_night.out
    done = [c for c in _summary(out)["captures"] if c["status"] == "done"]
    with rasterio.open(first_night.references[0]) as ds:
        reference_crs = ds.crs
    info = pyogrio.read_info(out / "changes.gpkg", layer="changes")
    assert info["crs"] == f"EPSG:{reference_crs.to_epsg()}"
    _, _, _, fields = pyogrio.raw.read(out / "changes.gpkg", layer="changes", columns=["status", "captures"])
    assert set(fields[0]) == {"new"} and 1 <= len(fields[0]) <= sum(c["changes"] for c in done)
    assert set().union(*(json.loads(v) for v in fields[1])) <= {c["capture"] for c in done}
    items = list(pystac.Catalog.from_file(str(out / "stac" / "catalog.json")).get_items(recursive=True))
    assert sorted(i.properties["rsmb:capture"] for i in items) == sorted(c["capture"] for c in done)
    assert all(os.path.exists(a.get_absolute_href()) for i in items for a in i.assets.values())
    import odc.stac

    night = odc.stac.load(items, bands=["change_mask_reference"], crs=reference_crs.to_string(), resolution=0.5,
                          groupby="rsmb:night")["change_mask_reference"]
    assert night.sizes["time"] == 1 and set(np.unique(night.values)) <= {0, 1, 255}
    assert (night.values == 1).any() and (night.values == 0).any()
    page = (out / "index.html").read_text()
    assert f"{len(fields[0])} new</b>" in page and "<img class='map' src='map.png'" in page
    assert (out / "map.png").stat().st_size > 0


def test_a_rerun_redoes_nothing(first_night):
    """The same command again: the good captures are skipped, the bad ones
    retried (and failed again), no product is touched, and it takes at most 20 %
    of the first night's time.  Both are timed alike, from the command's start
    (``main``) to its return, after the night's summary and index are written,
    in this process: the interpreter's start and its imports, the same for
    every command whatever the night holds, are outside both.  The rerun starts
    with no file checksum remembered, as a new command would."""
    out = first_night.out
    stamps = {p: p.stat().st_mtime_ns for p in (out / "captures" / "flight1").rglob("*") if p.is_file()}
    _sources._sha256_file.cache_clear()
    start = time.perf_counter()
    assert main(first_night.args) == 3  # the bad ones are retried and fail again
    seconds = time.perf_counter() - start
    summary = _summary(out)
    assert summary["skipped"] == 4 and summary["done"] == 0 and summary["failed"] == 4
    assert all(c["output"] and c["changes"] is not None for c in summary["captures"] if c["status"] == "skipped")
    assert stamps == {p: p.stat().st_mtime_ns for p in (out / "captures" / "flight1").rglob("*") if p.is_file()}
    assert seconds <= 0.2 * first_night.seconds, (seconds, first_night.seconds)


def test_new_and_changed_captures_run_alone(tmp_path, monkeypatch):
    scene = _scene()
    references, night = _night(tmp_path, scene, bad=False)
    out = tmp_path / "out"
    assert _survey(references, night, out) == 0

    def no_scheduler(*args, **kwargs):
        raise AssertionError("a night with nothing to run opened a scheduler")

    with monkeypatch.context() as patch:  # nothing to run: no cluster jobs submitted, no connection made
        patch.setattr(survey_module, "open_runner", no_scheduler)
        assert _survey(references, night, out) == 0
    write_capture(night / "flight3" / "new.tif", scene, CaptureSpec((200, 300), (256, 256), seed=31, changes=2))
    write_capture(night / "flight1" / "cap1.tif", scene, CaptureSpec(GOOD[1], (256, 256), seed=32, changes=2))
    assert _survey(references, night, out, "--json") == 0
    by = {os.path.basename(c["capture"]): c for c in _summary(out)["captures"]}
    assert by["new.tif"]["status"] == "done" and by["cap1.tif"]["status"] == "done"
    assert by["cap0.tif"]["status"] == "skipped" and by["cap2.tif"]["status"] == "skipped"
    rows = sqlite3.connect(out / "ledger.sqlite").execute(
        "SELECT capture, status, reason FROM runs ORDER BY id").fetchall()
    assert [r for r in rows if r[0].endswith("cap1.tif")][-1][2].startswith("content changed")


def test_the_next_capture_is_detected_while_one_writes_its_report(tmp_path, monkeypatch):
    """--parallel 1 counts captures being detected, not captures writing their
    products and report: with products that take a second, the next capture's
    detection runs meanwhile, and no two detections ever overlap."""
    import threading

    from rsmb.pipeline.archive._products import ProductProcess

    references, night = _night(tmp_path, _scene(), bad=False)
    spans, lock = {"detect": [], "report": []}, threading.Lock()

    def timed(kind, func, pause=0.0):
        def run(*args, **kwargs):
            start = time.perf_counter()
            try:
                time.sleep(pause)
                return func(*args, **kwargs)
            finally:
                with lock:
                    spans[kind].append((start, time.perf_counter()))
        return run

    monkeypatch.setattr(survey_module, "detect", timed("detect", survey_module.detect))
    monkeypatch.setattr(ProductProcess, "write", timed("report", ProductProcess.write, pause=1.0))
    result = survey_module.survey(references, str(night / "**" / "*.tif"), tmp_path / "out", parallel=1,
                                  settle=0)
    assert result.done == 3 and len(spans["detect"]) == 3 and len(spans["report"]) == 3
    detections = sorted(spans["detect"])
    assert all(a[1] <= b[0] for a, b in zip(detections, detections[1:]))  # one at a time
    # a detection and a report run at the same time (serially, each report would
    # end before the next detection starts; which of the two starts first is a race)
    assert any(d0 < r1 and r0 < d1 for d0, d1 in detections for r0, r1 in spans["report"])


def test_the_history_reads_each_mask_as_its_capture_ends(tmp_path, monkeypatch):
    """Each done capture's ground-frame mask is read for the history once, in
    the capture's own driver thread as it ends (beside the other captures'
    detection), not in the night's serial end; the history is the one read
    from the placed files afresh."""
    import threading

    from rsmb import tiles
    from rsmb.pipeline.archive import _history
    from rsmb.pipeline.archive._night_end import latest_done
    from rsmb.pipeline.archive._ledger import Ledger

    references, night = _night(tmp_path, _scene(), bad=False)
    reads, read = [], _history.read_observation

    def spy(path):
        reads.append((Path(path).name, threading.current_thread() is threading.main_thread()))
        return read(path)

    monkeypatch.setattr(_history, "read_observation", spy)
    out = tmp_path / "out"
    assert _survey(references, night, out) == 0
    assert reads == [("change_mask_reference.tif", False)] * len(GOOD)
    monkeypatch.setattr(_history, "read_observation", read)
    again = tmp_path / "again"
    again.mkdir()
    with Ledger(out / "ledger.sqlite") as ledger:
        rows = latest_done(ledger)
    night_name = rows[0].night
    _history.update_history(again, rows, night_name, tiles.probe_header(references[0])[1].crs)
    kept, fresh = _history.read_history(out / "changes.gpkg"), _history.read_history(again / "changes.gpkg")
    assert len(kept.changes) == len(fresh.changes) > 0
    assert [(c.geometry.wkb, c.status, c.captures) for c in kept.changes] == \
           [(c.geometry.wkb, c.status, c.captures) for c in fresh.changes]
    assert [f.geometry.wkb for f in kept.footprints] == [f.geometry.wkb for f in fresh.footprints]


def _capture_files(out):
    """The bytes of every file in the night's capture folders (not the ledger,
    nights/, stac/ or index.html: they record when each night ran), by path."""
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and len(p.relative_to(out).parts) > 1
            and p.relative_to(out).parts[0] not in ("nights", "stac")}


def _without_timings(zarr_json):
    """A store's root metadata without what measures its own run: the summary's
    ``timings`` and ``megapixels_per_s``."""
    doc = json.loads(zarr_json)
    summary = doc["attributes"]["summary"]
    assert summary.pop("timings") and summary.pop("megapixels_per_s") > 0
    return doc


# The interrupted night: the survey's own process, SIGKILLed by itself the
# moment its ledger records the first capture done (a fixed point mid-night: the
# other captures are being detected, written or waiting, whatever the machine's
# speed; watching the folders from outside raced with the products' writers).
_KILLED_AFTER_FIRST_DONE = """
import os, signal, sys
from rsmb.pipeline.archive._ledger import Ledger
from rsmb.pipeline.cli import main

finish = Ledger.finish

def finish_then_die(self, run_id, status, *args, **kwargs):
    finish(self, run_id, status, *args, **kwargs)
    if status == "done":
        os.kill(os.getpid(), signal.SIGKILL)

Ledger.finish = finish_then_die
sys.exit(main(sys.argv[1:]))
"""


def test_a_night_killed_midway_finishes_as_if_never_interrupted(tmp_path):
    """SIGKILL mid-night, then the same command: nothing done twice, and every
    file of every capture folder (store chunks and metadata, changes.gpkg, the
    COGs, thumbnail.png; reports are off) is the same as an uninterrupted
    night's, bit for bit, but for the fields that record how fast a run went:
    the store's root ``zarr.json`` (its summary's ``timings`` and
    ``megapixels_per_s``; the rest of the document compared as JSON).
    changes.gpkg is dated by its capture, so it is compared whole.  Both nights
    run in the same folder (the uninterrupted one moved aside after), so the
    paths recorded inside the files are the same too."""
    scene = _scene()
    references, night = _night(tmp_path, scene, bad=False)
    out, whole = tmp_path / "out", tmp_path / "whole"
    assert _survey(references, night, out) == 0
    os.replace(out, whole)
    cmd = [sys.executable, "-c", _KILLED_AFTER_FIRST_DONE, "-q", "survey", *map(str, references), "--captures",
           str(night / "**" / "*.tif"), "-o", str(out), "--no-report", "--parallel", "1", "--settle", "0"]
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300)
    assert proc.returncode == -signal.SIGKILL
    rows = sqlite3.connect(out / "ledger.sqlite").execute("SELECT status FROM runs").fetchall()
    assert sorted(s for s, in rows) == ["done", "running", "running"]  # killed mid-night
    assert not (out / "nights").exists()
    assert _survey(references, night, out) == 0
    rows = sqlite3.connect(out / "ledger.sqlite").execute("SELECT capture, status FROM runs").fetchall()
    done = [c for c, s in rows if s == "done"]
    assert sorted(done) == sorted(set(done)) and len(done) == 3  # nothing done twice
    a, b = _capture_files(whole), _capture_files(out)
    assert a.keys() == b.keys() and len(a) > 3 * 10
    differ = sorted(name for name in a if a[name] != b[name])
    for name in differ:
        if name.endswith("changes.zarr/zarr.json"):
            assert _without_timings(a[name]) == _without_timings(b[name]), name
        else:
            pytest.fail(f"{name} differs between the interrupted night and the uninterrupted one")


def test_dry_run_writes_nothing_and_says_why(tmp_path, capsys):
    references, night = _night(tmp_path, _scene(), bad=False)
    out = tmp_path / "out"
    assert _survey(references, night, out, "--dry-run") == 0
    assert not out.exists()
    text = capsys.readouterr().out
    assert text.count("would run") == 3 and "new capture" in text


def test_bad_invocations_and_an_empty_night(tmp_path, capsys):
    references, night = _night(tmp_path, _scene(), bad=False)
    nogeo = tmp_path / "nogeo.png"
    shutil.copy(night / "flight1" / "cap0.tif", tmp_path / "x.tif")
    import cv2

    cv2.imwrite(str(nogeo), np.zeros((64, 64), np.uint8) + 7)
    afile = tmp_path / "afile"
    afile.write_text("x")
    for args, named in ((["survey", str(nogeo), "--captures", "*.tif", "-o", str(tmp_path / "o")], str(nogeo)),
                        (["survey", str(references[0]), "--captures", "*.tif", "-o", str(afile)], str(afile)),
                        (["survey", str(tmp_path / "missing.tif"), "--captures", "*.tif", "-o", str(tmp_path / "o")],
                         "missing.tif"),
                        (["survey", str(references[0]), "-o", str(tmp_path / "o")], "--captures")):
        assert main(args) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and named in err[0], (args, err)
    assert not (tmp_path / "o").exists()
    # a captures folder that does not exist is bad input; an existing empty one is a night of 0 captures
    assert main(["-q", "survey", str(references[0]), "--captures", str(tmp_path / "none" / "*.tif"), "-o",
                 str(tmp_path / "empty"), "--json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--captures" in err[0] and str(tmp_path / "none") in err[0], err
    assert not (tmp_path / "empty").exists()
    (tmp_path / "none").mkdir()
    assert main(["-q", "survey", str(references[0]), "--captures", str(tmp_path / "none" / "*.tif"), "-o",
                 str(tmp_path / "empty"), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out) == {"captures": [], "done": 0, "skipped": 0, "failed": 0}
    assert "a night of 0 captures" in captured.err


def test_a_capture_that_fails_before_it_runs_is_logged(tmp_path, caplog):
    """A capture the night cannot open (text named .tif) fails before any
    detection, and the log says so with an ERROR line naming it, as it does
    for a capture that fails while it runs."""
    references = write_reference(tmp_path / "reference", _scene())
    (tmp_path / "incoming").mkdir()
    (tmp_path / "incoming" / "notes.tif").write_text("not an image")
    assert main(["survey", *map(str, references), "--captures", str(tmp_path / "incoming" / "*.tif"), "-o",
                 str(tmp_path / "out"), "--no-report", "--settle", "0"]) == 3
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert any("notes.tif: failed before it ran" in m for m in errors), errors


def test_the_surveys_default_tile_raises_no_note_on_a_small_capture(tmp_path, caplog):
    """The survey's default tile (:data:`SURVEY_TILE`) is not one the user
    asked for: a capture smaller than it runs as one tile without the note
    ``detect --tile-size`` gives when a tile asked for exceeds the image; the
    ledger keys the capture as before (by the survey's configuration).  The
    same size asked for gives the note."""
    references = write_reference(tmp_path / "reference", _scene())
    write_capture(tmp_path / "incoming" / "cap.tif", _scene(), CaptureSpec((40, 60), (256, 256), seed=3, changes=2))
    assert main(["survey", *map(str, references), "--captures", str(tmp_path / "incoming" / "*.tif"), "-o",
                 str(tmp_path / "out"), "--no-report", "--settle", "0"]) == 0
    notes = [r.getMessage() for r in caplog.records if "larger than the image" in r.getMessage()]
    assert notes == []
    store = read_store(tmp_path / "out" / "captures" / "cap.tif" / "changes.zarr")[1]
    assert store["parameters"]["tile"] == 256 and store["tile_grid"]["tiles"] == [1, 1]
    key = survey_module._parameters(survey_module.DetectConfig(tile=survey_module.SURVEY_TILE), (256, 256))
    assert key["config"]["tile"] == survey_module.SURVEY_TILE
    caplog.clear()  # the same size asked for: the note says it does not fit
    assert main(["survey", *map(str, references), "--captures", str(tmp_path / "incoming" / "*.tif"), "-o",
                 str(tmp_path / "asked"), "--no-report", "--settle", "0", "--tile-size", "1024"]) == 0
    notes = [r.getMessage() for r in caplog.records if "larger than the image" in r.getMessage()]
    assert len(notes) == 1 and "tile size 1024 px" in notes[0], notes
