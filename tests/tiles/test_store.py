"""Tests of tiles._store and tiles._store_atomic: partial store, finalize/abort, overwrite, dims, JSON."""

import datetime
import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from rasterio.crs import CRS
from rasterio.transform import Affine

from rsmb.ops._errors import InputError, ParameterError
from rsmb.tiles import (
    ArraySpec,
    abort_result_store,
    create_result_store,
    finalize_result_store,
    jsonable,
    open_result_store,
    update_attrs,
    write_array,
    write_spatial_coords,
)

H, W, D = 30, 44, 6
TILE = 16


def _specs():
    tiles_y, tiles_x = -(-H // TILE), -(-W // TILE)
    return {
        "change_mask": ArraySpec((H, W), "uint8", (TILE, TILE), ("y", "x")),
        "trajectory": ArraySpec((H, D), "float32", (H, D), ("row", "axis")),
        "gain": ArraySpec((tiles_y, tiles_x), "float32", (tiles_y, tiles_x),
                          ("tile_y", "tile_x"), fill_value=1.0),
    }


@pytest.fixture
def arrays():
    rng = np.random.default_rng(0)
    return {
        "change_mask": (rng.random((H, W)) > 0.9).astype(np.uint8),
        "trajectory": rng.normal(size=(H, D)).astype(np.float32),
    }


@pytest.fixture
def out(tmp_path):
    return tmp_path / "out.zarr"


def _partials(path):
    return sorted(p.name for p in path.parent.iterdir() if ".partial" in p.name)


def _write_store(out, arrays, *, overwrite=False, attrs=None):
    group = create_result_store(out, _specs(), attrs or {"run": 1}, overwrite=overwrite)
    assert not out.exists()  # nothing at the final path before finalisation
    mask = arrays["change_mask"]
    for r0 in range(0, H, TILE):  # tile by tile: regions do not divide the image
        for c0 in range(0, W, TILE):
            region = (slice(r0, r0 + TILE), slice(c0, c0 + TILE))
            write_array(group, "change_mask", mask[region], region)
    write_array(group, "trajectory", arrays["trajectory"])
    return finalize_result_store(group, out, overwrite=overwrite)


def test_create_write_finalize(out, arrays):
    attrs = {"params": {"tile": (TILE, TILE)}, "input": Path("ref.tif"),
             "n": np.int64(3)}
    assert _write_store(out, arrays, attrs=attrs) == out
    assert _partials(out) == []
    store = open_result_store(out)
    np.testing.assert_array_equal(store["change_mask"][...], arrays["change_mask"])
    np.testing.assert_array_equal(store["trajectory"][...], arrays["trajectory"])
    np.testing.assert_array_equal(store["gain"][...], np.ones((2, 3), np.float32))
    assert dict(store.attrs) == {
        "params": {"tile": [TILE, TILE]}, "input": "ref.tif", "n": 3, "complete": True,
    }
    with pytest.raises(ValueError, match="read-only"):
        store["gain"][0, 0] = 2.0


def test_xarray_opens_with_dim_names(out, arrays):
    _write_store(out, arrays)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no consolidation warning either
        ds = xr.open_zarr(out)
    assert ds["change_mask"].dims == ("y", "x")
    assert ds["trajectory"].dims == ("row", "axis")
    assert ds["gain"].dims == ("tile_y", "tile_x")
    assert ds.sizes["y"] == H and ds.sizes["axis"] == D
    np.testing.assert_array_equal(ds["change_mask"].values, arrays["change_mask"])
    assert ds.attrs["run"] == 1


def test_update_attrs_keeps_the_consolidated_metadata(out, arrays):
    """A finished store's root attributes change in one write; its
    consolidated metadata (the children's) stays as it was and xarray opens
    the store with the new attributes; a store without consolidated metadata
    gets it."""
    _write_store(out, arrays)
    root = json.loads((out / "zarr.json").read_text())
    update_attrs(out, {"summary": {"output": Path("moved.zarr")}, "run": 2})
    after = json.loads((out / "zarr.json").read_text())
    assert after["consolidated_metadata"] == root["consolidated_metadata"]
    assert after["attributes"] == {**root["attributes"], "summary": {"output": "moved.zarr"}, "run": 2}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert xr.open_zarr(out).attrs["run"] == 2
    plain = out.with_name("plain.zarr")
    group = create_result_store(plain, _specs(), {"run": 1}, overwrite=False)
    update_attrs(group.store.root, {"run": 3})
    consolidated = json.loads((Path(group.store.root) / "zarr.json").read_text())["consolidated_metadata"]
    assert consolidated is not None and set(consolidated["metadata"]) == set(_specs())


def test_existing_output_without_overwrite_raises(out, arrays):
    _write_store(out, arrays)
    with pytest.raises(InputError, match="output exists; pass --overwrite") as exc_info:
        create_result_store(out, _specs(), {}, overwrite=False)
    assert str(exc_info.value).startswith(str(out))
    assert _partials(out) == []


def test_overwrite_replaces_only_at_finalize(out, arrays):
    _write_store(out, arrays, attrs={"run": 1})
    group = create_result_store(out, _specs(), {"run": 2}, overwrite=True)
    assert open_result_store(out).attrs["run"] == 1  # old store intact while writing
    write_array(group, "change_mask", np.ones((H, W), np.uint8))
    finalize_result_store(group, out, overwrite=True)
    store = open_result_store(out)
    assert store.attrs["run"] == 2
    assert store["change_mask"][...].all()
    assert sorted(p.name for p in out.parent.iterdir()) == ["out.zarr"]


def test_overwrite_refuses_non_zarr_path(tmp_path):
    victim = tmp_path / "notes"
    victim.mkdir()
    (victim / "keep.txt").write_text("precious")
    with pytest.raises(InputError, match="not a zarr store"):
        create_result_store(victim, _specs(), {}, overwrite=True)
    assert (victim / "keep.txt").read_text() == "precious"


def test_abort_leaves_nothing(out):
    group = create_result_store(out, _specs(), {}, overwrite=False)
    write_array(group, "gain", np.full((2, 3), 0.5, np.float32))
    assert len(_partials(out)) == 1
    abort_result_store(group)
    assert _partials(out) == [] and not out.exists()
    abort_result_store(group)  # idempotent
    with pytest.raises(ParameterError):
        abort_result_store(out)  # never deletes a final store


def test_write_array_checks(out):
    group = create_result_store(out, _specs(), {}, overwrite=False)
    with pytest.raises(ParameterError, match="expected shape \\(4, 4\\)"):
        write_array(group, "change_mask", np.zeros((5, 4), np.uint8),
                    (slice(0, 4), slice(0, 4)))
    with pytest.raises(ParameterError, match="'nope'"):
        write_array(group, "nope", np.zeros(3))
    abort_result_store(group)


def test_open_missing_store(tmp_path):
    with pytest.raises(InputError, match="no such output store"):
        open_result_store(tmp_path / "missing.zarr")


def test_array_spec_validation():
    with pytest.raises(ParameterError, match="same length"):
        ArraySpec((3, 4), "uint8", (3,), ("y", "x"))
    assert ArraySpec([3, 4], np.float32, [2, 2], ["y", "x"]).dtype == "float32"


def test_jsonable():
    @dataclass
    class Params:
        tile: tuple

    value = {
        "a": np.float32(1.5), "b": np.arange(3), "c": (1, (2, Path("p"))),
        "d": Params((512, 512)), "e": float("nan"), "f": np.dtype("uint8"),
        "g": datetime.date(2024, 1, 2), 3: {np.bool_(True)},
    }
    out = jsonable(value)
    assert out == {
        "a": 1.5, "b": [0, 1, 2], "c": [1, [2, "p"]], "d": {"tile": [512, 512]},
        "e": "NaN", "f": "uint8", "g": "2024-01-02", "3": [True],
    }
    json.dumps(out, allow_nan=False)
    with pytest.raises(ParameterError, match="attrs.x"):
        jsonable({"x": object()})


def test_repair_of_an_interrupted_overwrite(out, arrays):
    import os

    import zarr

    from rsmb.tiles import is_complete_store, partial_path, repair_interrupted_overwrite

    replaced = out.with_name(out.name + ".replaced")
    assert repair_interrupted_overwrite(out) is None
    # killed after the old store moved aside, the new one unfinished: the old one comes back
    _write_store(out, arrays, attrs={"run": 1})
    os.replace(out, replaced)
    zarr.create_group(store=str(partial_path(out)), zarr_format=3)
    assert not is_complete_store(partial_path(out))
    assert repair_interrupted_overwrite(out) == "restored"
    assert open_result_store(out).attrs["run"] == 1 and not replaced.exists()
    abort_result_store(partial_path(out))
    # killed after the old store moved aside, the new one finished: the new one goes in place
    os.replace(out, replaced)
    _write_store(out.with_name("new.zarr"), arrays, attrs={"run": 2})
    os.replace(out.with_name("new.zarr"), partial_path(out))
    assert repair_interrupted_overwrite(out) == "completed"
    assert open_result_store(out).attrs["run"] == 2 and not replaced.exists()
    # killed before the old store was deleted
    replaced.mkdir()
    assert repair_interrupted_overwrite(out) == "cleaned" and not replaced.exists()
    with pytest.raises(InputError, match="interrupted"):
        os.replace(out, replaced)
        open_result_store(out)


def test_swap_into_place_files_and_directories(tmp_path, monkeypatch):
    """The one swap: a file or a folder written aside becomes the output; an
    existing one is replaced only with ``overwrite``; a failed second rename
    puts the old folder back."""
    import os

    from rsmb.tiles import swap_into_place

    final, tmp = tmp_path / "mask.tif", tmp_path / "aside.tif"
    tmp.write_text("one")
    assert swap_into_place(tmp, final, overwrite=False) == final
    assert final.read_text() == "one" and not tmp.exists()
    tmp.write_text("two")
    with pytest.raises(InputError, match="mask.tif: output exists"):
        swap_into_place(tmp, final, overwrite=False)
    assert final.read_text() == "one" and tmp.read_text() == "two"
    swap_into_place(tmp, final, overwrite=True)
    assert final.read_text() == "two" and not tmp.exists()

    folder, aside = tmp_path / "capture", tmp_path / "capture.partial"
    for text in ("first", "second"):
        aside.mkdir()
        (aside / "changes.txt").write_text(text)
        if text == "second":
            with pytest.raises(InputError, match="capture: output exists"):
                swap_into_place(aside, folder, overwrite=False)
        swap_into_place(aside, folder, overwrite=True)
        assert (folder / "changes.txt").read_text() == text and not aside.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture", "mask.tif"]

    aside.mkdir()
    (aside / "changes.txt").write_text("third")
    real_replace = os.replace

    def fail_second(src, dst):
        if str(src) == str(aside):
            raise OSError("disk gone")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", fail_second)
    with pytest.raises(OSError, match="disk gone"):
        swap_into_place(aside, folder, overwrite=True)
    assert (folder / "changes.txt").read_text() == "second"
    assert not (tmp_path / "capture.replaced").exists()


# ---------------------------------------------------------------- CF coordinates

# a north-up UTM grid whose origin is not on a round number
UTM = Affine(0.5, 0.0, 583000.25, 0.0, -0.5, 4507000.75)


def _geo(epsg, transform):
    from rsmb.tiles import GeoInfo

    return GeoInfo(crs=CRS.from_epsg(epsg).to_wkt(version="WKT2_2019"), transform=tuple(transform)[:6])


def _georeferenced_store(out, arrays, geo):
    group = create_result_store(out, _specs(), {"run": 1}, overwrite=False)
    write_array(group, "change_mask", arrays["change_mask"])
    written = write_spatial_coords(group, geo, (H, W))
    finalize_result_store(group, out, overwrite=False)
    return written


def test_spatial_coords_read_by_xarray_and_rioxarray(out, arrays):
    pytest.importorskip("rioxarray")
    assert _georeferenced_store(out, arrays, _geo(32618, UTM)) == ["x", "y", "spatial_ref"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = xr.open_zarr(out, consolidated=True)  # the coordinates are in the consolidated metadata
    cols, rows = np.arange(W) + 0.5, np.arange(H) + 0.5
    np.testing.assert_allclose(ds.x.values, [(UTM @ (c, 0.5))[0] for c in cols], rtol=0, atol=1e-9)
    np.testing.assert_allclose(ds.y.values, [(UTM @ (0.5, r))[1] for r in rows], rtol=0, atol=1e-9)
    assert ds.x.dtype == np.float64 and ds.x.dims == ("x",) and ds.y.dims == ("y",)
    assert ds.x.attrs["standard_name"] == "projection_x_coordinate" and ds.y.attrs["units"] == "metre"
    mask = ds.change_mask
    assert mask.rio.crs.to_epsg() == 32618
    assert mask.rio.transform().almost_equals(UTM)
    assert ds.rio.crs.to_epsg() == 32618
    ref = ds.spatial_ref
    assert ref.shape == () and int(ref) == 0
    assert ref.attrs["grid_mapping_name"] == "transverse_mercator"
    assert CRS.from_wkt(ref.attrs["crs_wkt"]).to_epsg() == 32618
    assert [float(v) for v in ref.attrs["GeoTransform"].split()] == list(UTM.to_gdal())
    assert "spatial_ref" not in ds.trajectory.dims and "grid_mapping" not in ds.trajectory.attrs
    np.testing.assert_array_equal(mask.values, arrays["change_mask"])


def test_spatial_coords_geographic_rotated_and_none(tmp_path, arrays):
    pytest.importorskip("rioxarray")
    lonlat = Affine(1e-4, 0.0, -75.5, 0.0, -1e-4, 40.25)
    _georeferenced_store(tmp_path / "ll.zarr", arrays, _geo(4326, lonlat))
    ds = xr.open_zarr(tmp_path / "ll.zarr")
    assert ds.x.attrs["units"] == "degrees_east" and ds.y.attrs["standard_name"] == "latitude"
    assert ds.change_mask.rio.crs.to_epsg() == 4326

    rotated = Affine.rotation(10.0) @ Affine.scale(0.5, -0.5)
    rotated = Affine.translation(583000.0, 4507000.0) @ rotated
    assert _georeferenced_store(tmp_path / "rot.zarr", arrays, _geo(32618, rotated)) == ["spatial_ref"]
    ds = xr.open_zarr(tmp_path / "rot.zarr")
    assert "x" not in ds.coords and ds.change_mask.rio.crs.to_epsg() == 32618
    assert ds.spatial_ref.attrs["GeoTransform"].split() == [repr(v) for v in rotated.to_gdal()]
    assert ds.change_mask.rio.transform().almost_equals(rotated)

    from rsmb.tiles import GeoInfo

    assert _georeferenced_store(tmp_path / "none.zarr", arrays, GeoInfo()) == []
    assert set(xr.open_zarr(tmp_path / "none.zarr").coords) == set()
