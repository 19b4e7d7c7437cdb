"""The tiled pipeline: tiled equals whole, seams, georeferencing, resume, schedulers."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rsmb import ops
from rsmb import pipeline
from rsmb.pipeline import DetectConfig, detect, write_pair

from ..conftest import inplane_pair_files, read_store


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


@pytest.fixture(scope="module")
def wide_pair(tmp_path_factory):
    """1024 x 1000: 256-px tiles leave a ragged last column (232 px)."""
    pair, _, ref, dist = inplane_pair_files(tmp_path_factory, "wide", (1024, 1000), changes=20, seed=7, fmt="npy")
    return pair, ref, dist


@pytest.fixture(scope="module")
def whole_result(tmp_path_factory, wide_pair):
    _, ref, dist = wide_pair
    store = tmp_path_factory.mktemp("whole") / "whole.zarr"
    detect(ref, dist, store, config=DetectConfig(tile=1024))
    return read_store(store)


@pytest.mark.parametrize("tile", [256, 240])
def test_tiled_equals_whole(tmp_path, wide_pair, whole_result, tile):
    pair, ref, dist = wide_pair
    store = tmp_path / "tiled.zarr"
    summary = detect(ref, dist, store, config=DetectConfig(tile=tile))
    tiled, attrs = read_store(store)
    whole, whole_attrs = whole_result
    assert whole_attrs["tile_grid"]["tiles"] == [1, 1]
    assert attrs["tile_grid"]["tiles"] == [4, 4]
    widths = np.diff(attrs["tile_grid"]["col_edges"])
    assert len(set(widths)) > 1  # a ragged (or merged) edge tile
    a, b = whole["change_mask"] == 1, tiled["change_mask"] == 1
    assert _iou(a, b) >= 0.98
    assert _iou(whole["change_mask_reference"] == 1, tiled["change_mask_reference"] == 1) >= 0.98
    rows = np.isfinite(whole["registered"]).mean(axis=1) > 0.5  # rows whose content is in the reference
    diff = tiled["trajectory"][rows] - whole["trajectory"][rows]
    assert np.sqrt(np.mean(diff[:, :2] ** 2, axis=0)).max() <= 0.1  # px, tx and ty
    assert ops.confusion(b, pair.change_mask).f_measure >= 0.95
    assert summary.tasks_per_tile <= 8
    # every tile started from its band's start (one search per row of tiles)
    assert summary.timings["tiles_shared_start"] == 16


def test_summary_has_cpu_seconds_per_stage(whole_result):
    """The store's summary splits the run's CPU time by stage (summed over
    tasks): every stage named, none negative, the registration stages spent."""
    from rsmb.pipeline.detection._detect import CPU_STAGES

    _, attrs = whole_result
    cpu = attrs["summary"]["timings"]["cpu_s"]
    assert set(cpu) == set(CPU_STAGES) | {"total"}
    assert all(v >= 0.0 for v in cpu.values())
    assert cpu["rows"] > 0 and cpu["start"] > 0 and cpu["ingest"] > 0 and cpu["change_masks"] > 0
    assert abs(cpu["total"] - sum(v for k, v in cpu.items() if k != "total")) < 1e-9


def test_failed_rows_produce_no_change(tmp_path):
    """Rows whose solve cannot meet the optimality conditions (a tolerance
    rounding cannot reach on some rows) are failed in ``tile_row_state`` and
    their pixels carry no evidence in the store: score NaN, never change."""
    pair = ops.synthesize_pair((192, 256), motion="inplane", changes=6, noise=0.002, seed=11)
    ref, dist = write_pair(tmp_path / "pair", pair, fmt="npy")
    store = tmp_path / "strict.zarr"
    config = DetectConfig(registration=ops.RegistrationParams(tol=1e-13), tile=256)
    detect(ref, dist, store, config=config)
    arrays, _ = read_store(store)
    failed = arrays["tile_row_state"][:, 0] == 3
    assert 5 <= failed.sum() <= 150
    assert np.isnan(arrays["change_score"][failed]).all()
    assert (arrays["change_mask"][failed] == 255).all()  # no evidence, not change
    assert np.isnan(arrays["registered"][failed]).all()
    assert np.isfinite(arrays["change_score"][~failed]).mean() > 0.5


def test_object_across_a_four_tile_corner_is_one_component(tmp_path):
    pair = ops.synthesize_pair((512, 512), motion="wobble", changes=0, noise=0.002, seed=8, scale=0.5)
    distorted = pair.distorted.copy()
    distorted[249:263, 249:263] = 0.97  # 14 x 14 = 196 px, 49 px in each of four tiles
    ref_path, dist_path = tmp_path / "ref.npy", tmp_path / "dist.npy"
    np.save(ref_path, pair.reference)
    np.save(dist_path, distorted)
    changes = ops.ChangeParams(min_area=100)  # more than any quarter, less than the whole
    results = {}
    for tile in (256, 512):
        store = tmp_path / f"t{tile}.zarr"
        detect(ref_path, dist_path, store, config=DetectConfig(tile=tile, changes=changes))
        results[tile] = read_store(store)[0]["change_mask"] == 1
    from scipy import ndimage

    labels, n = ndimage.label(results[256], structure=np.ones((3, 3)))
    assert n == 1
    assert results[256][256, 256] and results[256][250, 250] and results[256][261, 261]
    assert 150 <= results[256].sum() <= 260
    assert np.array_equal(results[256], results[512])


def test_geotiff_in_geotiff_out(tmp_path, geotiff_pair_files):
    import rasterio
    import xarray as xr

    _, ref, dist = geotiff_pair_files
    store, gtiff = tmp_path / "geo.zarr", tmp_path / "masks"
    detect(ref, dist, store, config=DetectConfig(tile=128), geotiff=gtiff)
    _, attrs = read_store(store)
    with rasterio.open(dist) as src:
        crs, transform = src.crs, src.transform
    assert attrs["proj:code"] == "EPSG:32618"
    assert tuple(attrs["spatial:transform"]) == pytest.approx(tuple(transform)[:6])
    for name in ("change_mask_reference.tif", "change_score_reference.tif", "parallax_mask_reference.tif"):
        with rasterio.open(gtiff / name) as out:
            assert out.crs == crs
            assert out.transform.almost_equals(transform)
            assert out.shape == (256, 256)
    arrays = read_store(store)[0]
    for name, nodata in (("change_mask_reference", 255), ("change_score_reference", None),
                         ("parallax_mask_reference", 255)):
        with rasterio.open(gtiff / f"{name}.tif") as out:  # the store's ground-frame array, no-data and all
            assert out.descriptions == (name,) and (out.nodata == nodata if nodata else np.isnan(out.nodata))
            assert np.array_equal(out.read(1), arrays[name], equal_nan=True)
    ground = arrays["change_mask_reference"]
    assert set(np.unique(ground)) == {0, 1, 255} and np.array_equal(ground == 255, np.isnan(
        arrays["change_score_reference"]))
    ds = xr.open_zarr(store)
    assert ds.attrs["proj:code"] == "EPSG:32618" and ds["change_mask"].dims == ("row", "col")


def test_smooth_gain_per_tile(tmp_path):
    """A gain ramp of 0.7 to 1.3 across 4 x 4 tiles: each tile's own gain."""
    pair = ops.synthesize_pair((512, 512), motion="inplane", gain=(0.7, 1.3), changes=4, noise=0.002, seed=13)
    ref, dist = write_pair(tmp_path / "pair", pair, fmt="npy")
    store = tmp_path / "gain.zarr"
    summary = detect(ref, dist, store, config=DetectConfig(tile=128))
    assert summary.tiles == [4, 4]
    scores = pipeline.evaluate(store, tmp_path / "pair")
    assert scores.gain["max_relative_error"] <= 0.03, scores.gain
    assert scores.changes.f_measure >= 0.9, scores.changes


def _rsmb(*args):
    return [sys.executable, "-m", "rsmb", *map(str, args)]


def _done_tiles(partial):
    import zarr

    try:
        return int((zarr.open_group(str(partial), mode="r")["work/tile_summary"][..., -1] == 1).sum())
    except Exception:  # noqa: BLE001 - not created yet
        return 0


def test_resume_after_kill_runs_only_missing_tiles(tmp_path):
    pair = ops.synthesize_pair((384, 384), motion="inplane", changes=3, noise=0.002, seed=14)
    ref, dist = write_pair(tmp_path / "pair", pair, fmt="npy")
    store = tmp_path / "r.zarr"
    args = [ref, dist, "-o", store, "--tile-size", 96, "--workers", 1]  # 4 x 4 tiles, one at a time
    proc = subprocess.Popen(_rsmb("-q", "detect", *args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    partial = Path(str(store) + ".partial")
    deadline = time.time() + 240
    while _done_tiles(partial) < 6 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done = _done_tiles(partial)
    assert 6 <= done < 16 and not store.exists()
    resumed = subprocess.run(_rsmb("detect", *args, "--resume"), capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resume: {done} of 16 tiles already registered" in resumed.stderr
    assert "register: 16/16" not in resumed.stderr
    fresh = tmp_path / "fresh.zarr"
    detect(ref, dist, fresh, config=DetectConfig(tile=96))
    a, b = read_store(store)[0], read_store(fresh)[0]
    for name in ("change_mask", "change_mask_reference", "change_score", "registered", "trajectory", "gain"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_resume_refuses_other_parameters(tmp_path, small_pair_files):
    _, ref, dist = small_pair_files
    store = tmp_path / "x.zarr"
    partial = Path(str(store) + ".partial")
    group = pipeline.detection._detect.tiles.create_result_store(store, {}, {"run_key": "something else"}, overwrite=False)
    assert partial.exists() and group is not None
    with pytest.raises(ops.InputError, match="without --resume"):
        detect(ref, dist, store, resume=True)


@pytest.fixture(scope="module")
def threads_store(tmp_path_factory, small_pair_files):
    """The small pair in 128-px tiles on the default (threads) scheduler."""
    _, ref, dist = small_pair_files
    store = tmp_path_factory.mktemp("threads") / "a.zarr"
    detect(ref, dist, store, config=DetectConfig(tile=128))
    return read_store(store)[0]


@pytest.mark.parametrize("scheduler", ["processes", "synchronous"])
def test_local_schedulers_agree(tmp_path, small_pair_files, threads_store, scheduler):
    _, ref, dist = small_pair_files
    b = tmp_path / "b.zarr"
    detect(ref, dist, b, config=DetectConfig(tile=128), scheduler=scheduler, workers=2)
    for name in ("change_mask", "registered", "trajectory"):
        np.testing.assert_array_equal(threads_store[name], read_store(b)[0][name])


def test_store_opens_with_coordinates_and_crs(tmp_path, geotiff_pair_files):
    """Opened with xarray and rioxarray, the ground-frame arrays have x, y,
    the capture's CRS and transform; the sensor-frame arrays have pixel
    dimensions, no map coordinates, no CRS, and rioxarray refuses to write
    them as a raster: the two frames cannot be mistaken."""
    import rasterio
    import rioxarray  # noqa: F401 - registers .rio
    import xarray as xr
    from rioxarray.exceptions import MissingSpatialDimensionError

    _, ref, dist = geotiff_pair_files
    store = tmp_path / "geo.zarr"
    detect(ref, dist, store, config=DetectConfig(tile=128))
    ds = xr.open_zarr(store)
    with rasterio.open(dist) as src:
        transform, epsg, (h, w) = src.transform, src.crs.to_epsg(), src.shape
    np.testing.assert_allclose(ds.x.values, transform.c + transform.a * (np.arange(w) + 0.5))
    np.testing.assert_allclose(ds.y.values, transform.f + transform.e * (np.arange(h) + 0.5))
    for name in ("change_mask_reference", "change_score_reference", "parallax_mask_reference"):
        a = ds[name]
        assert a.dims == ("y", "x") and {"x", "y"} <= set(a.coords), name
        assert a.rio.crs.to_epsg() == epsg == 32618 and a.rio.transform() == transform, name
    for name in ("change_mask", "change_score", "parallax_mask", "registered"):
        a = ds[name]
        assert a.dims == ("row", "col") and not {"x", "y"} & set(a.coords), name
        assert a.rio.crs is None and a.rio.transform().is_identity, name
        with pytest.raises(MissingSpatialDimensionError):
            a.rio.to_raster(tmp_path / f"{name}.tif")
    assert set(np.unique(ds["change_mask"].values)) <= {0, 1, 255}


def test_work_beside_the_stages_gives_its_result_or_its_error():
    """:class:`_Beside` (the previews' thread): its function's result, or
    the error it raised, raised again in the caller's thread."""
    from rsmb.pipeline.detection._detect import _Beside

    assert _Beside(divmod, 7, 2).start().result() == (3, 1)
    assert _Beside(divmod, 9, 2).result() == (4, 1)  # never started: result() runs it
    with pytest.raises(ZeroDivisionError):
        _Beside(divmod, 7, 0).start().result()


def test_task_arrays_write_empty_chunks_only_when_compressed(tmp_path):
    """A task writes every chunk of a compressed array, one equal to the fill
    value too (zarr's comparison of each chunk with it is skipped: an empty
    compressed chunk is a few bytes), and skips the empty chunks of an
    uncompressed scratch array (a whole chunk's bytes); both read back what
    was written."""
    from rsmb import tiles
    from rsmb.pipeline.detection import _tasks

    specs = {"packed": tiles.ArraySpec((8, 8), "uint8", (4, 4), ("row", "col")),
             "scratch": tiles.ArraySpec((8, 8), "float32", (4, 4), ("y", "x"), float("nan"), compressed=False)}
    tiles.create_result_store(tmp_path / "s.zarr", specs, {}, overwrite=False)
    run = _tasks.RunStore(str(tiles.partial_path(tmp_path / "s.zarr")), "key-empty-chunks")
    _tasks._array(run, "packed")[:4, :4] = np.zeros((4, 4), np.uint8)
    _tasks._array(run, "packed")[4:, 4:] = np.ones((4, 4), np.uint8)
    _tasks._array(run, "scratch")[:4, :4] = np.full((4, 4), np.nan, np.float32)
    _tasks._array(run, "scratch")[4:, 4:] = np.ones((4, 4), np.float32)
    folders = {name: Path(run.path) / name / "c" for name in specs}
    chunks = {name: sorted(str(p.relative_to(c)) for p in c.rglob("*") if p.is_file()) for name, c in folders.items()}
    assert chunks == {"packed": ["0/0", "1/1"], "scratch": ["1/1"]}
    assert (_tasks._array(run, "packed")[:] == np.kron([[0, 0], [0, 1]], np.ones((4, 4)))).all()
    assert np.isnan(_tasks._array(run, "scratch")[:4, :]).all() and (_tasks._array(run, "scratch")[4:, 4:] == 1).all()


def test_task_arrays_open_once_per_run_and_scratch_as_chunk_files(tmp_path):
    """Threads asking for an array of a run at once share one open array,
    also once the run's store has its offsets and scale; another run on the
    same path opens its own; uncompressed scratch is read as chunk files."""
    import dataclasses
    from concurrent.futures import ThreadPoolExecutor

    from rsmb import tiles
    from rsmb.pipeline.detection import _tasks

    specs = {"scratch": tiles.ArraySpec((8, 8), "float32", (4, 4), ("y", "x"), float("nan"), compressed=False)}
    tiles.create_result_store(tmp_path / "s.zarr", specs, {}, overwrite=False)
    run = _tasks.RunStore(str(tiles.partial_path(tmp_path / "s.zarr")), "key-open-once")
    with ThreadPoolExecutor(4) as pool:
        arrays = list(pool.map(lambda _: _tasks._array(run, "scratch"), range(8)))
    assert all(a is arrays[0] for a in arrays) and isinstance(arrays[0], tiles.ChunkFiles)
    assert _tasks._array(dataclasses.replace(run, reference_offset=3), "scratch") is arrays[0]
    assert _tasks._array(dataclasses.replace(run, key="another run"), "scratch") is not arrays[0]


def test_label_and_mask_tasks_by_groups_of_blocks(tmp_path, monkeypatch):
    """The label and mask tasks take the blocks of a block row in groups
    (:func:`_tasks.block_groups`: every block once, neighbours of one row
    spanning at most ``width`` px, a wider block alone, narrower groups
    where there would be fewer than the workers) and read each group's
    window once; the store is the same whatever the groups, a
    change across the seam between two groups included."""
    import functools

    from rsmb import tiles
    from rsmb.pipeline.detection import _tasks

    blocks = tiles.TileGrid((512, 1300), 128, 16).coarsened(2)  # 2 x 5 blocks of 256 px, the last one 276
    groups = _tasks.block_groups(blocks, width=512)
    assert [[b.index for b in g] for g in groups] == [[(0, 0), (0, 1)], [(0, 2), (0, 3)], [(0, 4)],
                                                      [(1, 0), (1, 1)], [(1, 2), (1, 3)], [(1, 4)]]
    assert [[b.index for b in g] for g in _tasks.block_groups(blocks, width=1024)] == [
        [(0, 0), (0, 1), (0, 2), (0, 3)], [(0, 4)], [(1, 0), (1, 1), (1, 2), (1, 3)], [(1, 4)]]
    assert [len(g) for g in _tasks.block_groups(blocks, width=100)] == [1] * 10  # a wide block alone
    assert [len(g) for g in _tasks.block_groups(tiles.TileGrid((8192, 8192), 4096, 64))] == [1, 1, 1, 1]
    # never fewer groups than workers where the blocks allow: one block row of four, two workers, three
    row = tiles.TileGrid((1024, 4096), 1024, 64)
    assert [len(g) for g in _tasks.block_groups(row, least=1)] == [4]
    assert [len(g) for g in _tasks.block_groups(row, least=2)] == [2, 2]
    assert [len(g) for g in _tasks.block_groups(row, least=3)] == [1, 1, 1, 1]
    assert [len(g) for g in _tasks.block_groups(tiles.TileGrid((4096, 4096), 1024, 64), least=2)] == [4] * 4

    pair = ops.synthesize_pair((512, 768), motion="inplane", changes=10, noise=0.002, seed=5)
    distorted = pair.distorted.copy()
    distorted[200:216, 248:264] = 0.95  # across the seam of the first two blocks of a row (256 px)
    ref, dist = tmp_path / "ref.npy", tmp_path / "dist.npy"
    np.save(ref, pair.reference)
    np.save(dist, distorted)
    stores = {}
    for width in (256, 512):
        monkeypatch.setattr(_tasks, "block_groups", functools.partial(_tasks.block_groups, width=width))
        detect(ref, dist, tmp_path / f"g{width}.zarr", config=DetectConfig(tile=128))
        stores[width], attrs = read_store(tmp_path / f"g{width}.zarr")
    assert attrs["tile_grid"]["block"] == 256 and attrs["tile_grid"]["tiles"] == [4, 6]
    assert (stores[512]["change_mask"][200:216, 248:264] == 1).all()
    for name, values in stores[256].items():
        assert np.array_equal(values, stores[512][name], equal_nan=values.dtype.kind == "f"), name


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_detect_stopped_by_a_signal_keeps_what_resume_continues(tmp_path, signum, code):
    """SIGINT or SIGTERM during a detect: one line naming the signal, exit
    128 + its number, the store's lock released, the partial store kept, and
    ``--resume`` finishes it."""
    from rsmb.pipeline.cli import main

    pair = ops.synthesize_pair((512, 512), seed=2)
    np.save(tmp_path / "ref.npy", pair.reference)
    np.save(tmp_path / "dist.npy", pair.distorted)
    args = ["-q", "detect", str(tmp_path / "ref.npy"), str(tmp_path / "dist.npy"), "-o", str(tmp_path / "o.zarr"),
            "--tile-size", "64"]
    proc = subprocess.Popen([sys.executable, "-m", "rsmb.pipeline.cli", *args], stderr=subprocess.PIPE)
    done = tmp_path / "o.zarr.partial" / "work" / "tile_summary"  # a tile registered: a run --resume continues
    deadline = time.time() + 120
    while not any(p.is_file() for p in done.rglob("c/*/*/*")) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == code, stderr.decode()
    assert stderr.decode().strip() == f"rsmb: interrupted by {signal.Signals(signum).name}"
    assert not (tmp_path / "o.zarr.lock").exists() and (tmp_path / "o.zarr.partial").is_dir()
    assert main([*args, "--resume"]) == 0
