"""Tests of tiles._io and the modules behind it (_sources, _luminance, _geo): every
input format, the error cases, windows, GeoTIFF output."""

import logging
import warnings

import numpy as np
import pytest
import rasterio
import zarr
from PIL import Image
from rasterio.crs import CRS
from rasterio.transform import Affine

from rsmb.ops._errors import InputError, RSMBError
from rsmb.tiles import (
    GeoInfo,
    as_float01,
    check_same_shape,
    probe_header,
    probe_image,
    read_image,
    read_window,
    write_geotiff,
)

H, W = 40, 50
BORDER = 3
TRANSFORM = Affine(10.0, 0.0, 500000.0, 0.0, -10.0, 4500000.0)


def _luma(rgb_uint8):
    rgb = rgb_uint8.astype(np.float64) / 255.0
    return 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]


# ---------------------------------------------------------------- fixtures


@pytest.fixture
def rgb():
    """(H, W, 3) uint8 RGB with a zero border (the nodata) and no zero pixel inside."""
    rng = np.random.default_rng(0)
    image = rng.integers(1, 256, size=(H, W, 3), dtype=np.uint8)
    image[:BORDER] = 0
    image[-BORDER:] = 0
    image[:, :BORDER] = 0
    image[:, -BORDER:] = 0
    return image


@pytest.fixture
def border_mask():
    valid = np.zeros((H, W), dtype=bool)
    valid[BORDER:-BORDER, BORDER:-BORDER] = True
    return valid


@pytest.fixture
def geotiff(tmp_path, rgb):
    """3-band uint8 GeoTIFF in EPSG:32618, nodata 0 on the border."""
    path = tmp_path / "ref.tif"
    with rasterio.open(
        path, "w", driver="GTiff", height=H, width=W, count=3, dtype="uint8",
        crs=CRS.from_epsg(32618), transform=TRANSFORM, nodata=0,
        tiled=True, blockxsize=16, blockysize=16,
    ) as ds:
        ds.write(np.moveaxis(rgb, -1, 0))
    return path


@pytest.fixture
def gray_u8():
    rng = np.random.default_rng(1)
    return rng.integers(0, 256, size=(H, W), dtype=np.uint8)


# ---------------------------------------------------------------- GeoTIFF


def test_geotiff_luminance_mask_and_georef(geotiff, rgb, border_mask):
    raster = read_image(geotiff)
    assert raster.data.dtype == np.float32 and raster.data.shape == (H, W)
    np.testing.assert_array_equal(raster.valid, border_mask)
    expected = _luma(rgb)[border_mask]
    np.testing.assert_allclose(raster.data[border_mask], expected, atol=1e-6)
    assert np.all(raster.data[~border_mask] == 0)
    assert CRS.from_wkt(raster.geo.crs) == CRS.from_epsg(32618)
    assert raster.geo.transform == tuple(TRANSFORM)[:6]
    assert raster.geo.nodata == 0
    assert len(raster.sha256) == 64


def test_write_geotiff_keeps_crs_and_transform(tmp_path, geotiff, border_mask):
    geo = read_image(geotiff).geo
    out = write_geotiff(tmp_path / "mask.tif", border_mask, geo, nodata=255)
    with rasterio.open(out) as ds:
        assert ds.crs == CRS.from_epsg(32618)
        assert tuple(ds.transform)[:6] == geo.transform
        assert ds.dtypes == ("uint8",) and ds.nodata == 255
        assert ds.compression.name.lower() == "deflate"
        np.testing.assert_array_equal(ds.read(1), border_mask.astype(np.uint8))


def test_write_geotiff_float_without_georef(tmp_path):
    data = np.random.default_rng(2).random((H, W), dtype=np.float32)
    out = write_geotiff(tmp_path / "score.tif", data, GeoInfo())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(out) as ds:
            assert ds.crs is None
            np.testing.assert_array_equal(ds.read(1), data)
    assert read_image(out).geo.is_empty


def test_write_geotiff_uncompressed_on_request(tmp_path, geotiff, border_mask):
    geo = read_image(geotiff).geo
    out = write_geotiff(tmp_path / "mask.tif", border_mask, geo, nodata=255, compress=None)
    with rasterio.open(out) as ds:
        assert ds.compression is None and ds.crs == CRS.from_user_input(geo.crs) and ds.nodata == 255
        np.testing.assert_array_equal(ds.read(1), border_mask.astype(np.uint8))


def test_write_geotiff_from_a_zarr_array_in_strips(tmp_path):
    data = np.random.default_rng(3).random((600, 70), dtype=np.float32)  # three 256-row strips
    source = zarr.create_array(str(tmp_path / "score.zarr"), shape=data.shape, chunks=(100, 70), dtype="float32")
    source[...] = data
    out = write_geotiff(tmp_path / "score.tif", source, GeoInfo(crs="EPSG:32618", transform=tuple(TRANSFORM)[:6]))
    with rasterio.open(out) as ds:
        np.testing.assert_array_equal(ds.read(1), data)
        assert ds.crs == CRS.from_epsg(32618) and ds.transform == TRANSFORM


def test_geoinfo_attrs_round_trip(geotiff):
    geo = read_image(geotiff).geo
    attrs = geo.to_attrs()
    assert attrs["proj:code"] == "EPSG:32618"
    assert attrs["spatial:transform"] == list(tuple(TRANSFORM)[:6])
    assert attrs["spatial:dimensions"] == ["y", "x"]
    assert GeoInfo.from_attrs(attrs) == geo
    nan_geo = GeoInfo(nodata=float("nan"))
    assert nan_geo.to_attrs() == {"nodata": "NaN"}
    assert np.isnan(GeoInfo.from_attrs(nan_geo.to_attrs()).nodata)
    assert GeoInfo().is_empty and not geo.is_empty


@pytest.mark.parametrize("rows, cols", [
    (slice(5, 23), slice(7, 44)),   # crosses 16-pixel blocks, includes the border
    (slice(0, 2), slice(None)),     # all nodata
    (slice(30, None), slice(-9, None)),
])
def test_read_window_equals_slice_of_full_read(geotiff, rows, cols):
    full = read_image(geotiff)
    data, valid = read_window(geotiff, rows, cols)
    np.testing.assert_array_equal(data, full.data[rows, cols])
    np.testing.assert_array_equal(valid, full.valid[rows, cols])


def test_read_window_npy_and_zarr(tmp_path, rgb):
    npy = tmp_path / "img.npy"
    np.save(npy, rgb)
    za = zarr.create_array(str(tmp_path / "s.zarr"), shape=rgb.shape,
                           chunks=(16, 16, 3), dtype="uint8")
    za[...] = rgb
    for path in (npy, tmp_path / "s.zarr"):
        full = read_image(path)
        data, valid = read_window(path, slice(4, 30), slice(10, 41))
        np.testing.assert_array_equal(data, full.data[4:30, 10:41])
        np.testing.assert_array_equal(valid, full.valid[4:30, 10:41])


# ---------------------------------------------------------------- other formats


def test_png_gray_8bit(tmp_path, gray_u8):
    path = tmp_path / "gray.png"
    Image.fromarray(gray_u8).save(path)
    raster = read_image(path)
    np.testing.assert_allclose(raster.data, gray_u8 / 255.0, atol=1e-7)
    assert raster.valid.all() and raster.geo.is_empty


def test_png_rgb_8bit(tmp_path, rgb):
    path = tmp_path / "rgb.png"
    Image.fromarray(rgb).save(path)
    raster = read_image(path)
    np.testing.assert_allclose(raster.data, _luma(rgb), atol=1e-6)
    assert raster.valid.all()  # no nodata in a PNG: black pixels stay valid


def test_png_rgba_alpha_zero_is_invalid(tmp_path, rgb, border_mask):
    rgba = np.dstack([rgb, np.where(border_mask, 255, 0).astype(np.uint8)])
    path = tmp_path / "rgba.png"
    Image.fromarray(rgba).save(path)
    raster = read_image(path)
    np.testing.assert_array_equal(raster.valid, border_mask)


def test_png_16bit_scaled_to_unit_range(tmp_path):
    image = np.random.default_rng(3).integers(0, 65536, size=(H, W), dtype=np.uint16)
    image[0, 0], image[0, 1] = 0, 65535
    path = tmp_path / "gray16.png"
    Image.fromarray(image).save(path)
    raster = read_image(path)
    np.testing.assert_allclose(raster.data, image / 65535.0, atol=1e-7)
    assert raster.data.min() == 0.0 and raster.data.max() == 1.0


def test_jpeg_gray(tmp_path, gray_u8):
    path = tmp_path / "gray.jpg"
    Image.fromarray(gray_u8).save(path, quality=95)
    raster = read_image(path)
    assert raster.data.shape == (H, W)
    assert 0.0 <= raster.data.min() <= raster.data.max() <= 1.0


def test_npy_float_kept_as_is(tmp_path):
    image = np.random.default_rng(4).normal(size=(H, W))  # float64, outside [0, 1]
    path = tmp_path / "float.npy"
    np.save(path, image)
    raster = read_image(path)
    assert raster.data.dtype == np.float32
    np.testing.assert_array_equal(raster.data, image.astype(np.float32))


def test_npy_uint16(tmp_path):
    image = np.random.default_rng(5).integers(0, 65536, size=(H, W), dtype=np.uint16)
    path = tmp_path / "u16.npy"
    np.save(path, image)
    np.testing.assert_allclose(read_image(path).data, image / 65535.0, atol=1e-7)


def test_zarr_arrays_v3_in_group_and_v2(tmp_path, gray_u8):
    group = zarr.open_group(str(tmp_path / "in.zarr"), mode="w", zarr_format=3)
    img = group.create_array("img", shape=(H, W), chunks=(16, 16), dtype="uint8")
    img[...] = gray_u8
    v2 = zarr.create_array(str(tmp_path / "v2.zarr"), shape=(H, W), chunks=(16, 16),
                           dtype="uint8", zarr_format=2)
    v2[...] = gray_u8
    a = read_image(tmp_path / "in.zarr" / "img")
    b = read_image(tmp_path / "v2.zarr")
    np.testing.assert_allclose(a.data, gray_u8 / 255.0, atol=1e-7)
    np.testing.assert_array_equal(a.data, b.data)
    assert a.sha256 == b.sha256  # hash of the array bytes, not of the store layout
    # probing hashes chunk-row strips without loading the array: the same digest
    assert probe_image(tmp_path / "in.zarr" / "img").sha256 == a.sha256 == probe_image(tmp_path / "v2.zarr").sha256
    with pytest.raises(InputError, match="zarr group, not an array.*img"):
        read_image(tmp_path / "in.zarr")


def test_zarr_array_geo_attrs_and_nodata(tmp_path, gray_u8, border_mask):
    geo = GeoInfo(crs=CRS.from_epsg(32618).to_wkt(version="WKT2_2019"),
                  transform=tuple(TRANSFORM)[:6], nodata=0)
    image = np.where(border_mask, np.maximum(gray_u8, 1), 0).astype(np.uint8)
    za = zarr.create_array(str(tmp_path / "geo.zarr"), shape=(H, W), chunks=(16, 16),
                           dtype="uint8", attributes=geo.to_attrs())
    za[...] = image
    raster = read_image(tmp_path / "geo.zarr")
    assert raster.geo == geo
    np.testing.assert_array_equal(raster.valid, border_mask)


def test_as_float01_policy():
    assert as_float01(np.array([0, 255], np.uint8), name="a").tolist() == [0.0, 1.0]
    assert as_float01(np.array([65535], np.uint16), name="a").tolist() == [1.0]
    assert as_float01(np.array([127], np.int8), name="a").tolist() == [1.0]
    assert as_float01(np.array([2.5]), name="a").dtype == np.float32
    with pytest.raises(InputError, match="a: contains inf"):
        as_float01(np.array([np.inf]), name="a")


# ---------------------------------------------------------------- errors


def _assert_one_line(exc_info, path):
    message = str(exc_info.value)
    assert "\n" not in message
    assert message.startswith(str(path))
    assert isinstance(exc_info.value, (RSMBError, ValueError))


def _save(path, array):
    np.save(path, array)
    return path


def _write(path, content):
    path.write_bytes(content)
    return path


@pytest.mark.parametrize("make, problem", [
    (lambda p: p / "missing.tif", "no such file"),
    (lambda p: _write(p / "image.bmp", b"BM"), "unsupported format"),
    (lambda p: _write(p / "broken.tif", b"not a tiff"), "cannot read"),
    (lambda p: _save(p / "empty.npy", np.zeros((0, 5), np.float32)), "is empty"),
    (lambda p: _save(p / "flat.npy", np.full((4, 5), 7, np.uint8)), "is constant"),
    (lambda p: _save(p / "nan.npy", np.full((2, 3), np.nan)), "no valid pixel"),  # NaN: no-data
    (lambda p: _save(p / "cube.npy", np.zeros((2, 3, 4, 5))), "expected \\(H, W\\)"),
])
def test_input_errors_name_file_and_problem(tmp_path, make, problem):
    path = make(tmp_path)
    with pytest.raises(InputError, match=problem) as exc_info:
        read_image(path)
    _assert_one_line(exc_info, path)


def test_an_input_that_cannot_be_reached_is_not_called_missing(tmp_path, monkeypatch):
    """A file in a folder the user may not enter exists: the error says
    permission, not "no such file" (the test runs as any user: the refusal
    is made by ``os.stat``)."""
    import os

    path = _save(tmp_path / "image.npy", np.ones((4, 5), np.float32))
    real_stat = os.stat

    def refuse(p, *args, **kwargs):
        if os.fspath(p) == str(path):
            raise PermissionError(13, "Permission denied", str(path))
        return real_stat(p, *args, **kwargs)

    monkeypatch.setattr(os, "stat", refuse)
    with pytest.raises(InputError, match="permission denied") as exc_info:
        read_image(path)
    _assert_one_line(exc_info, path)
    with pytest.raises(InputError, match="Not a directory") as exc_info:
        read_image(path / "inside.npy")  # a file used as a folder
    _assert_one_line(exc_info, path / "inside.npy")


def test_nan_in_a_float_image_is_nodata(tmp_path):
    """NaN in a float raster without a nodata tag is no-data (not an error)."""
    image = np.array([[0.0, np.nan, 0.25], [1.0, 0.5, np.nan]], np.float32)
    raster = read_image(_save(tmp_path / "holes.npy", image))
    np.testing.assert_array_equal(raster.valid, np.isfinite(image))
    np.testing.assert_array_equal(raster.data[raster.valid], image[np.isfinite(image)])


def _truncated(path, keep):
    """A tiled 3-band GeoTIFF cut to ``keep`` of its bytes (header kept or not)."""
    rng = np.random.default_rng(5)
    with rasterio.open(path, "w", driver="GTiff", height=600, width=700, count=3, dtype="uint8",
                       crs="EPSG:32618", transform=TRANSFORM, tiled=True, compress="deflate") as ds:
        ds.write(rng.integers(0, 256, size=(3, 600, 700), dtype=np.uint8))
    with open(path, "r+b") as fh:
        fh.truncate(keep(path.stat().st_size))
    return path


def _damaged(path):
    """A tiled 3-band GeoTIFF whose second half is overwritten with zeros: its
    header and length intact, its later blocks undecodable."""
    path = _truncated(path, lambda size: size)
    size = path.stat().st_size
    with open(path, "r+b") as fh:
        fh.seek(size // 2)
        fh.write(bytes(size - size // 2))
    return path


@pytest.mark.parametrize("call", [probe_header, probe_image, read_image])
def test_a_geotiff_cut_short_is_refused_from_its_header(tmp_path, call):
    """A GeoTIFF whose header opens but whose data the file no longer holds
    (still being copied): refused by its block offsets, before any pixel is
    read, one line saying so."""
    path = _truncated(tmp_path / "cut.tif", lambda size: size // 2)
    with pytest.raises(InputError, match="cut short") as exc_info:
        call(path)
    _assert_one_line(exc_info, path)


@pytest.mark.parametrize("read", [read_image, lambda p: read_window(p, slice(400, 600), slice(None))])
def test_damaged_geotiff_error_names_gdal_cause(tmp_path, read):
    path = _damaged(tmp_path / "bad.tif")
    assert probe_image(path).shape == (600, 700)  # the header is intact
    with pytest.raises(InputError, match="cannot read image") as exc_info:
        read(path)
    _assert_one_line(exc_info, path)
    message = str(exc_info.value)
    assert "See previous exception" not in message
    assert "ZIPDecode" in message  # GDAL's (libtiff's) own description of the failure


def test_truncated_header_error_names_gdal_cause(tmp_path):
    path = _truncated(tmp_path / "head.tif", lambda size: 100)
    for call in (probe_image, read_image):
        with pytest.raises(InputError, match="cannot read image") as exc_info:
            call(path)
        _assert_one_line(exc_info, path)
        assert "TIFF" in str(exc_info.value)


def test_gdal_info_lines_do_not_leak_but_stay_at_debug(tmp_path, caplog):
    path = _damaged(tmp_path / "bad.tif")

    def gdal_records():
        return [r for r in caplog.records if r.name.startswith("rasterio._e")]

    caplog.set_level(logging.INFO)
    with pytest.raises(InputError):
        read_image(path)
    assert gdal_records() == []
    with rasterio.open(path) as ds, pytest.raises(rasterio.errors.RasterioIOError):
        ds.read()  # rasterio used directly, outside rsmb: its records untouched
    assert gdal_records() and {r.levelno for r in gdal_records()} == {logging.INFO}

    caplog.clear()
    caplog.set_level(logging.DEBUG)
    with pytest.raises(InputError):
        read_image(path)
    assert any("GDAL signalled an error" in r.getMessage() for r in gdal_records())
    assert {r.levelno for r in gdal_records()} == {logging.DEBUG}


def test_no_valid_pixel(tmp_path):
    path = tmp_path / "allnodata.tif"
    with rasterio.open(path, "w", driver="GTiff", height=4, width=5, count=1,
                       dtype="uint8", crs=CRS.from_epsg(32618), transform=TRANSFORM,
                       nodata=0) as ds:
        ds.write(np.zeros((1, 4, 5), np.uint8))
    with pytest.raises(InputError, match="no valid pixel") as exc_info:
        read_image(path)
    _assert_one_line(exc_info, path)


def test_nan_nodata_is_mask_not_error(tmp_path):
    data = np.random.default_rng(6).random((1, 8, 9)).astype(np.float32)
    data[0, :2] = np.nan
    path = tmp_path / "float.tif"
    with rasterio.open(path, "w", driver="GTiff", height=8, width=9, count=1,
                       dtype="float32", crs=CRS.from_epsg(32618), transform=TRANSFORM,
                       nodata=np.nan) as ds:
        ds.write(data)
    raster = read_image(path)
    assert not raster.valid[:2].any() and raster.valid[2:].all()
    assert np.isfinite(raster.data).all()


def test_check_same_shape(tmp_path, gray_u8):
    a = read_image(_save(tmp_path / "a.npy", gray_u8))
    b = read_image(_save(tmp_path / "b.npy", gray_u8[:-1]))
    check_same_shape(a, a)
    with pytest.raises(InputError) as exc_info:
        check_same_shape(a, b)
    message = str(exc_info.value)
    assert "a.npy" in message and "b.npy" in message
    assert str((H, W)) in message and str((H - 1, W)) in message and "\n" not in message


# ---------------------------------------------------------------- dispatch


def test_each_format_is_one_reader(tmp_path, geotiff, gray_u8):
    from rsmb.tiles import _sources

    np.save(tmp_path / "a.npy", gray_u8)
    zarr.create_array(str(tmp_path / "s.zarr"), data=gray_u8)
    kinds = {p: type(_sources.open_source(str(p))).__name__
             for p in (geotiff, tmp_path / "a.npy", tmp_path / "s.zarr")}
    assert list(kinds.values()) == ["RasterioSource", "NumpySource", "ZarrSource"]


def test_a_new_format_is_one_class(tmp_path, gray_u8, monkeypatch):
    from rsmb.tiles import _sources

    class CsvSource(_sources._ArraySource):
        extensions = (".csv",)

        def _load(self):
            return np.loadtxt(self.path, delimiter=",", dtype=np.uint8)

    path = tmp_path / "gray.csv"
    np.savetxt(path, gray_u8, delimiter=",", fmt="%d")
    with pytest.raises(InputError, match="unsupported format '.csv'"):
        probe_image(path)
    monkeypatch.setattr(_sources, "_FORMATS", _sources._FORMATS + (CsvSource,))
    assert probe_image(path).shape == gray_u8.shape
    np.testing.assert_allclose(read_image(path).data, gray_u8 / 255.0, atol=1e-6)
    data, _ = read_window(path, slice(2, 5), slice(None))
    np.testing.assert_allclose(data, gray_u8[2:5] / 255.0, atol=1e-6)
