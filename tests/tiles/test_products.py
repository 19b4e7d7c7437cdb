"""Tests of tiles._products: COGs (overviews, nodata, description, no clobber) and
change polygons in a GeoPackage (CRS, one feature per component, pixel sums,
areas, inside the footprint)."""

import logging
import struct

import numpy as np
import pyogrio
import pytest
import rasterio
import zarr
from pyogrio.raw import read
from rasterio.crs import CRS

from rsmb.ops import InputError, label_components
from rsmb.tiles import GeoInfo
from rsmb.tiles._products import (
    _geometry,
    change_polygons,
    write_changes_gpkg,
    write_cog,
)

UTM = CRS.from_epsg(32633).to_wkt()
GEO = GeoInfo(crs=UTM, transform=(0.5, 0.0, 500000.0, 0.0, -0.5, 5000000.0))
H, W = 60, 80


@pytest.fixture
def mask():
    """Components: a square with a hole, two blocks joined only through a diagonal,
    a single pixel, one touching the image edge."""
    m = np.zeros((H, W), np.uint8)
    m[5:15, 5:15] = 1
    m[9:11, 9:11] = 0  # hole
    m[20:25, 20:25] = 1
    m[25:30, 25:30] = 1  # diagonal neighbour of the block above: same component
    m[40, 40] = 1
    m[50:60, 70:80] = 1
    return m


@pytest.fixture
def score(mask):
    rng = np.random.default_rng(1)
    s = rng.random((H, W)).astype(np.float32)
    s[52, 72] = np.nan  # nodata inside a component
    return s


# -------------------------------------------------------------------------- COG


def test_cog_has_overviews_nodata_and_description(tmp_path):
    rng = np.random.default_rng(0)
    score = rng.random((600, 600)).astype(np.float32)
    score[:10] = np.nan
    out = write_cog(tmp_path / "score.tif", score, GEO, nodata=float("nan"), description="change_score")
    with rasterio.open(out) as ds:
        assert ds.driver == "GTiff" and ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert ds.overviews(1)
        assert np.isnan(ds.nodata)
        assert ds.descriptions == ("change_score",)
        assert ds.crs == CRS.from_wkt(UTM) and tuple(ds.transform)[:6] == GEO.transform
        assert ds.block_shapes == [(512, 512)]
        np.testing.assert_array_equal(ds.read(1), score)
    assert [p.name for p in tmp_path.iterdir()] == ["score.tif"]  # nothing left aside


def test_cog_from_a_zarr_mask(tmp_path):
    mask = zarr.create_array(store=str(tmp_path / "m.zarr"), shape=(600, 600), chunks=(256, 256), dtype="uint8")
    mask[100:200, 300:400] = 1
    out = write_cog(tmp_path / "mask.tif", mask, GEO, nodata=255, description="change_mask")
    with rasterio.open(out) as ds:
        assert ds.dtypes == ("uint8",) and ds.nodata == 255 and ds.overviews(1)
        assert int(ds.read(1).sum()) == 100 * 100


def test_cog_refuses_to_clobber(tmp_path):
    target = tmp_path / "mask.tif"
    target.write_bytes(b"keep")
    with pytest.raises(InputError, match=r"mask\.tif: output exists"):
        write_cog(target, np.zeros((8, 8), np.uint8), GEO)
    assert target.read_bytes() == b"keep"
    assert [p.name for p in tmp_path.iterdir()] == ["mask.tif"]
    write_cog(target, np.zeros((8, 8), np.uint8), GEO, overwrite=True)
    with rasterio.open(target) as ds:
        assert ds.shape == (8, 8)


# --------------------------------------------------------------------- polygons


def test_one_multipolygon_per_component(mask, score):
    labels, area, _ = label_components(mask.astype(bool), score)
    features = change_polygons(mask, score, GEO)
    assert len(features) == len(area) - 1 == 4
    assert [f.pixels for f in features] == area[1:].tolist()
    assert sum(f.pixels for f in features) == int(mask.sum())
    diagonal = features[1]
    assert len(diagonal.polygons) == 2  # two 4-connected parts, one feature
    square = features[0]
    assert len(square.polygons) == 1 and len(square.polygons[0]) == 2  # exterior and hole
    for f in features:
        assert f.area_m2 == pytest.approx(f.pixels * 0.25)
        values = score[labels == f.label]
        assert f.mean_score == pytest.approx(float(np.nanmean(values)), rel=1e-6)
        assert f.peak_score == pytest.approx(float(np.nanmax(values)))


def test_empty_mask_has_no_polygon(score):
    assert change_polygons(np.zeros((H, W), bool), score, GEO) == []


def test_geographic_area_is_geodesic(mask, score):
    # 1e-5 degree pixels at 45 N: about 1.11 m x 0.79 m
    geo = GeoInfo(crs=CRS.from_epsg(4326).to_wkt(), transform=(1e-5, 0.0, 15.0, 0.0, -1e-5, 45.0))
    features = change_polygons(mask, score, geo)
    lat = np.deg2rad(45.0)
    # WGS 84 metres per degree of latitude and of longitude at 45 N
    m_lat = 111132.954 - 559.822 * np.cos(2 * lat) + 1.175 * np.cos(4 * lat)
    m_lon = 111412.84 * np.cos(lat) - 93.5 * np.cos(3 * lat)
    pixel_m2 = 1e-5 * m_lat * 1e-5 * m_lon
    for f in features:
        assert f.area_m2 == pytest.approx(f.pixels * pixel_m2, rel=1e-3)


def _previous_wkb(polygons):
    """The hand-written ISO WKB (little endian) the products used before shapely."""
    out = [struct.pack("<BII", 1, 6, len(polygons))]
    for rings in polygons:
        out.append(struct.pack("<BII", 1, 3, len(rings)))
        for ring in rings:
            out.append(struct.pack("<I", len(ring)))
            out.append(np.asarray(ring, dtype="<f8").tobytes())
    return b"".join(out)


def _previous_geographic_area(rings, crs):
    """The area the products gave before pyproj.Geod: shoelace in a Lambert
    azimuthal equal-area CRS (WGS 84) centred on the polygon."""
    from rasterio.warp import transform

    xs, ys = np.asarray(rings[0]).T
    (lon,), (lat,) = transform(crs, CRS.from_epsg(4326), [(xs.min() + xs.max()) / 2], [(ys.min() + ys.max()) / 2])
    laea = f"+proj=laea +lat_0={lat} +lon_0={lon} +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
    area = 0.0
    for i, ring in enumerate(rings):
        x, y = (np.asarray(v) for v in transform(crs, laea, [p[0] for p in ring], [p[1] for p in ring]))
        a = 0.5 * abs(float(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1])))
        area += a if i == 0 else -a
    return area


def test_wkb_is_the_previous_hand_written_one(mask, score):
    import shapely

    for f in change_polygons(mask, score, GEO):
        assert shapely.to_wkb(_geometry(f.polygons), flavor="iso", byte_order=1) == _previous_wkb(f.polygons)


def test_geodesic_areas_equal_the_previous_equal_area_ones(mask, score):
    """Pixels of 1e-5 degree: the geodesic area (pyproj.Geod) and the
    equal-area projection's agree to float tolerance, part by part."""
    geo = GeoInfo(crs=CRS.from_epsg(4326).to_wkt(), transform=(1e-5, 0.0, 15.0, 0.0, -1e-5, 45.0))
    crs = CRS.from_epsg(4326)
    for f in change_polygons(mask, score, geo):
        previous = sum(_previous_geographic_area(rings, crs) for rings in f.polygons)
        assert f.area_m2 == pytest.approx(previous, rel=1e-6)


def test_no_evidence_is_not_change(mask, score):
    """255 (no evidence) in a mask is neither a change nor part of one."""
    marked = np.where(mask == 1, 1, 0).astype(np.uint8)
    marked[:, :3] = 255
    marked[30:35, 0:60] = 255
    expected = change_polygons(mask, score, GEO)
    assert change_polygons(marked, score, GEO) == expected


# -------------------------------------------------------------------- GeoPackage


def test_gpkg_reopened_with_pyogrio(tmp_path, mask, score):
    features = change_polygons(mask, score, GEO)
    out = write_changes_gpkg(tmp_path / "changes.gpkg", features, GEO.crs)
    info = pyogrio.read_info(out, layer="changes")
    assert info["geometry_type"] == "MultiPolygon" and info["features"] == 4
    assert list(info["fields"]) == ["pixels", "area_m2", "mean_score", "peak_score"]
    assert CRS.from_user_input(info["crs"]) == CRS.from_wkt(UTM)
    meta, _, geometry, fields = read(out, layer="changes")
    assert fields[0].sum() == mask.sum()
    assert list(geometry) == [_previous_wkb(f.polygons) for f in features]
    np.testing.assert_allclose(fields[1], fields[0] * 0.25)
    # inside the footprint of the capture
    left, top = GEO.transform[2], GEO.transform[5]
    xmin, ymin, xmax, ymax = pyogrio.read_bounds(out, layer="changes")[1]
    assert xmin.min() >= left and xmax.max() <= left + W * 0.5
    assert ymin.min() >= top - H * 0.5 and ymax.max() <= top
    assert [p.name for p in tmp_path.iterdir()] == ["changes.gpkg"]


def test_gpkg_areas_match_the_polygons(tmp_path, mask, score):
    # the polygons themselves (holes included) have the pixel area
    features = change_polygons(mask, score, GEO)
    for f in features:
        total = 0.0
        for rings in f.polygons:
            for i, ring in enumerate(rings):
                x, y = np.asarray(ring).T
                a = 0.5 * abs(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1]))
                total += a if i == 0 else -a
        assert total == pytest.approx(f.area_m2)


def test_empty_gpkg_is_a_valid_layer(tmp_path):
    out = write_changes_gpkg(tmp_path / "changes.gpkg", [], GEO.crs)
    info = pyogrio.read_info(out, layer="changes")
    assert info["features"] == 0 and info["geometry_type"] == "MultiPolygon"
    assert list(info["fields"]) == ["pixels", "area_m2", "mean_score", "peak_score"]
    assert CRS.from_user_input(info["crs"]) == CRS.from_wkt(UTM)


def test_gpkg_refuses_to_clobber(tmp_path, mask, score):
    target = tmp_path / "changes.gpkg"
    target.write_bytes(b"keep")
    with pytest.raises(InputError, match=r"changes\.gpkg: output exists"):
        write_changes_gpkg(target, change_polygons(mask, score, GEO), GEO.crs)
    assert target.read_bytes() == b"keep"
    write_changes_gpkg(target, [], GEO.crs, overwrite=True)
    assert pyogrio.read_info(target, layer="changes")["features"] == 0


def test_gpkg_write_keeps_pyogrio_info_off_the_terminal(tmp_path, mask, score, caplog):
    # pyogrio logs "Created N records" at INFO for every layer: a survey at INFO printed it per capture
    def pyogrio_records():
        return [r for r in caplog.records if r.name.startswith("pyogrio")]

    features = change_polygons(mask, score, GEO)
    caplog.set_level(logging.INFO)
    write_changes_gpkg(tmp_path / "a.gpkg", features, GEO.crs)
    assert pyogrio_records() == []
    pyogrio.raw.write(str(tmp_path / "direct.gpkg"), np.array([_previous_wkb(features[0].polygons)],
                      dtype=object), [], [], layer="changes", driver="GPKG", geometry_type="MultiPolygon", crs=GEO.crs)
    assert [r.levelno for r in pyogrio_records()] == [logging.INFO]  # pyogrio used directly: untouched

    caplog.clear()
    caplog.set_level(logging.DEBUG)
    write_changes_gpkg(tmp_path / "b.gpkg", features, GEO.crs)
    assert [(r.levelno, r.getMessage()) for r in pyogrio_records()] == [(logging.DEBUG, "Created 4 records")]


def test_gpkg_dated_by_last_change_is_the_same_file_every_time(tmp_path, mask, score):
    # a survey dates changes.gpkg by its capture: a redone capture (or a night
    # resumed after a kill) must give the same bytes, in threads at once too
    import sqlite3
    from concurrent.futures import ThreadPoolExecutor

    features = change_polygons(mask, score, GEO)
    stamps = [1.7e9, 1.7e9, 1.7e9 + 86400.25, 1.7e9]
    with ThreadPoolExecutor(4) as pool:
        paths = list(pool.map(lambda i: write_changes_gpkg(tmp_path / f"{i}.gpkg", features, GEO.crs,
                                                           last_change=stamps[i]), range(4)))
    data = [p.read_bytes() for p in paths]
    assert data[0] == data[1] == data[3] != data[2]
    with sqlite3.connect(paths[2]) as db:
        assert db.execute("SELECT last_change FROM gpkg_contents").fetchall() == [("2023-11-15T22:13:20.250Z",)]
    undated = write_changes_gpkg(tmp_path / "now.gpkg", features, GEO.crs)  # no date: GDAL's clock again
    with sqlite3.connect(undated) as db:
        assert db.execute("SELECT last_change FROM gpkg_contents").fetchone()[0].startswith("20")
    assert undated.read_bytes() != data[0]
