"""Tests of tiles._georef: pairing rule, coverage, the reference resampled onto the
capture grid (larger reference, split reference, other pixel size, other CRS,
partial and no overlap)."""

import numpy as np
import pytest
import rasterio
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.transform import Affine
from rasterio.warp import calculate_default_transform, reproject

from rsmb import tiles
from rsmb.ops import InputError, ParameterError, aerial_scene
from rsmb.tiles import _georef
from rsmb.tiles._georef import RasterGrid, reference_coverage, reference_window, resampling_for
from rsmb.tiles._pairing import pair_images

UTM = "EPSG:32633"  # lat ~45 N at y = 5 000 000
X0, Y0 = 500000.0, 5000000.0
REF_SHAPE = (400, 400)
CAP_SHAPE = (120, 160)
CAP_OFFSET = (70, 90)  # capture pixel (0, 0) in the 1 m reference grid (row, col)


def _write(path, array, crs, transform, *, nodata=None):
    array = np.asarray(array)
    bands = array[None] if array.ndim == 2 else np.moveaxis(array, -1, 0)
    profile = dict(driver="GTiff", height=bands.shape[1], width=bands.shape[2], count=bands.shape[0],
                   dtype=bands.dtype.name, crs=None if crs is None else CRS.from_user_input(crs),
                   transform=transform, nodata=nodata)
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(bands)
    return str(path)


def _utm(col, row, pixel=1.0):
    """Transform of a grid whose pixel (0, 0) is at (row, col) of the 1 m reference grid."""
    return Affine(pixel, 0.0, X0 + col, 0.0, -pixel, Y0 - row)


@pytest.fixture(scope="module")
def scene():
    return aerial_scene(REF_SHAPE, seed=3)


@pytest.fixture(scope="module")
def files(tmp_path_factory, scene):
    """The 1 m reference, the same split in two files, and a capture inside it."""
    d = tmp_path_factory.mktemp("georef")
    ref = _write(d / "ref.tif", scene, UTM, _utm(0, 0))
    left = _write(d / "left.tif", scene[:, :200], UTM, _utm(0, 0))
    right = _write(d / "right.tif", scene[:, 200:], UTM, _utm(200, 0))
    r, c = CAP_OFFSET
    cap = _write(d / "cap.tif", scene[r:r + CAP_SHAPE[0], c:c + CAP_SHAPE[1]], UTM, _utm(c, r))
    return {"dir": d, "ref": ref, "left": left, "right": right, "cap": cap}


@pytest.fixture(scope="module")
def grid(files):
    return RasterGrid.from_info(tiles.probe_image(files["cap"]))


def _window(grid, margin=0):
    h, w = grid.shape
    return slice(-margin, h + margin), slice(-margin, w + margin)


def _crop(scene, margin=0):
    r, c = CAP_OFFSET
    return scene[r - margin:r + CAP_SHAPE[0] + margin, c - margin:c + CAP_SHAPE[1] + margin]


def _corr(a, b):
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


# ------------------------------------------------------------------ the grid


def test_grid_from_info_and_path(files, grid):
    assert grid.shape == CAP_SHAPE
    assert grid.transform == tuple(_utm(90, 70))[:6]
    assert RasterGrid.from_path(files["cap"]) == grid


def test_grid_refuses_ungeoreferenced(tmp_path):
    path = _write(tmp_path / "plain.tif", np.zeros((4, 4), np.float32), None, Affine.identity())
    with pytest.raises(InputError, match="plain.tif: is not georeferenced"):
        RasterGrid.from_path(path)


# ---------------------------------------------------------- reference window


def test_larger_reference_is_the_crop_at_the_offset(files, grid, scene):
    out = reference_window(files["ref"], grid, *_window(grid))
    assert out.dtype == np.float32 and out.shape == CAP_SHAPE
    np.testing.assert_array_equal(out, _crop(scene))


def test_window_beyond_the_capture_reads_the_reference_margin(files, grid, scene):
    out = reference_window([files["ref"]], grid, *_window(grid, margin=12))
    np.testing.assert_array_equal(out, _crop(scene, margin=12))
    # beyond the reference itself: NaN
    beyond = reference_window(files["ref"], grid, slice(-100, -71), slice(0, 10))
    assert np.isnan(beyond).all()


def test_reference_split_over_two_files_equals_the_unsplit(files, grid):
    whole = reference_window(files["ref"], grid, *_window(grid, margin=5))
    split = reference_window([files["left"], files["right"]], grid, *_window(grid, margin=5))
    np.testing.assert_array_equal(split, whole)


def test_first_file_with_valid_data_wins(files, grid, scene):
    holed = scene.copy()
    holed[:, 150:] = -1.0  # nodata in the right part of the first file
    first = _write(files["dir"] / "holed.tif", holed, UTM, _utm(0, 0), nodata=-1.0)
    other = _write(files["dir"] / "other.tif", 1.0 - scene, UTM, _utm(0, 0))
    out = reference_window([first, other], grid, *_window(grid))
    cut = 150 - CAP_OFFSET[1]
    np.testing.assert_array_equal(out[:, :cut], _crop(scene)[:, :cut])
    np.testing.assert_array_equal(out[:, cut:], 1.0 - _crop(scene)[:, cut:])


def test_luminance_policy_is_the_one_of_read_window(files, grid, scene):
    rng = np.random.default_rng(0)
    rgba = rng.integers(1, 256, size=REF_SHAPE + (4,), dtype=np.uint8)
    rgba[:40, :, 3] = 0  # transparent rows
    path = _write(files["dir"] / "rgba.tif", rgba, UTM, _utm(0, 0))
    out = reference_window(path, grid, slice(-100, 20), slice(0, 50))
    # window rows -100..20 of the capture are rows -30..90 of the file
    data, valid = tiles.read_window(path, slice(0, 90), slice(CAP_OFFSET[1], CAP_OFFSET[1] + 50))
    assert not valid[:40].any() and valid[40:].all()
    assert np.isnan(out[:70]).all()  # 30 rows beyond the file, 40 transparent rows
    np.testing.assert_array_equal(out[70:], data[40:])


def test_only_the_window_is_read(files, grid, monkeypatch):
    seen = []
    real = _georef.read_window

    def spy(path, rows, cols):
        seen.append((rows.stop - rows.start) * (cols.stop - cols.start))
        return real(path, rows, cols)

    monkeypatch.setattr(_georef, "read_window", spy)
    reference_window(files["ref"], grid, slice(10, 42), slice(20, 52))
    pad = 2 * (1 + _georef._KERNEL_PAD) + 1
    assert seen and max(seen) <= (32 + 2 * pad) ** 2


def test_coarser_reference_matches_a_whole_reproject(files, grid, scene):
    coarse = scene.reshape(200, 2, 200, 2).mean(axis=(1, 3)).astype(np.float32)
    path = _write(files["dir"] / "coarse.tif", coarse, UTM, _utm(0, 0, pixel=2.0))
    assert resampling_for(RasterGrid.from_path(path), grid) == "lanczos"
    out = reference_window(path, grid, *_window(grid, margin=8))
    expected = np.full(out.shape, np.nan, np.float32)
    reproject(coarse, expected, src_transform=_utm(0, 0, 2.0), src_crs=UTM, src_nodata=np.nan,
              dst_transform=grid.window_affine(*_window(grid, margin=8)), dst_crs=UTM,
              dst_nodata=np.nan, resampling=Resampling.lanczos)
    np.testing.assert_allclose(out, expected, atol=1e-5)
    assert _corr(out, _crop(scene, margin=8)) > 0.95


def _other_grid(path, pixel_yx, shape, crs=UTM, origin=(X0, Y0)):
    """A header-only grid (no pixels needed to choose the resampling)."""
    return RasterGrid(str(path), CRS.from_user_input(crs).to_wkt(), (pixel_yx[1], 0.0, origin[0], 0.0,
                                                                       -pixel_yx[0], origin[1]), shape)


@pytest.mark.parametrize("pixel_yx, expected", [
    ((1.0, 1.0), "copy"),      # the capture's own grid
    ((2.0, 2.0), "lanczos"),   # coarser: interpolated
    ((0.8, 0.8), "lanczos"),   # slightly finer: under 2 reference pixels per capture pixel
    ((0.5, 0.5), "average"),   # 2 x 2 reference pixels under each capture pixel
    ((0.25, 0.25), "average"),
    ((0.5, 1.0), "lanczos"),   # finer along one axis only
    ((0.5, 0.4), "average"),
])
def test_resampling_is_chosen_by_the_pixel_size_ratio(grid, pixel_yx, expected):
    reference = _other_grid("other.tif", pixel_yx, (900, 900))
    assert resampling_for(reference, grid) == expected


def test_resampling_of_a_geographic_reference_uses_its_metric_pixel_size(grid):
    # at ~45 N a degree of longitude is ~78.8 km, a degree of latitude ~111.1 km
    lon, lat = rasterio.warp.transform(UTM, "EPSG:4326", [X0], [Y0])
    fine = _other_grid("fine.tif", (0.45 / 111_100, 0.45 / 78_800), (900, 900), "EPSG:4326",
                       (lon[0] - 0.01, lat[0] + 0.01))
    square = _other_grid("square.tif", (0.6 / 111_100, 0.6 / 111_100), (900, 900), "EPSG:4326",
                        (lon[0] - 0.01, lat[0] + 0.01))
    assert resampling_for(fine, grid) == "average"
    # square degrees: 0.43 m east-west (2.3 per capture pixel) but 0.6 m north-south (1.7)
    assert resampling_for(square, grid) == "lanczos"


def test_coarser_reference_keeps_the_contrast_of_fine_detail(files, grid):
    # a pattern of period 3 reference pixels (2 m) resampled onto the 1 m capture grid: the
    # Lanczos kernel keeps most of its amplitude; bilinear interpolation halves it
    period = 3 * 2.0  # metres

    def pattern(y, x):
        return (np.sin(2 * np.pi * x / period + 0.3) * np.cos(2 * np.pi * y / (1.1 * period) + 0.2)).astype(np.float32)

    rows, cols = np.mgrid[0:200, 0:200] * 2.0 + 1.0  # 2 m pixel centres, metres from the origin
    path = _write(files["dir"] / "pattern.tif", pattern(rows, cols), UTM, _utm(0, 0, pixel=2.0))
    r, c = CAP_OFFSET
    cy, cx = np.mgrid[0:CAP_SHAPE[0], 0:CAP_SHAPE[1]] + 0.5
    truth = pattern(cy + r, cx + c).astype(np.float64)

    def kept(out):  # least-squares amplitude of the true pattern in ``out``
        return float((out * truth).sum() / (truth * truth).sum())

    out = reference_window(path, grid, *_window(grid))
    bilinear = np.full(out.shape, np.nan, np.float32)
    reproject(pattern(rows, cols), bilinear, src_transform=_utm(0, 0, 2.0), src_crs=UTM,
              dst_transform=grid.affine, dst_crs=UTM, resampling=Resampling.bilinear)
    assert kept(out) > 0.9 and kept(bilinear) < 0.5
    assert float(np.sqrt(np.mean((out - truth) ** 2))) < 0.06


@pytest.mark.parametrize("pixel", [0.7, 0.4, 1.6])
def test_a_nodata_edge_keeps_a_constant_reference_constant(files, grid, pixel):
    # the kernel's weights are renormalised over the valid pixels (Lanczos has negative lobes: without it
    # the last pixels before the edge would be off); the capture is valid up to the data's edge
    shape = (int(REF_SHAPE[0] / pixel), int(REF_SHAPE[1] / pixel))
    edge = int((CAP_OFFSET[1] + 80) / pixel)  # reference column of the edge: the capture's column ~80
    constant = np.full(shape, 0.5, np.float32)
    constant[:, edge:] = -1.0
    path = _write(files["dir"] / f"edge{pixel}.tif", constant, UTM, _utm(0, 0, pixel), nodata=-1.0)
    out = reference_window(path, grid, *_window(grid))
    x = np.arange(CAP_SHAPE[1]) + 0.5 + CAP_OFFSET[1]  # capture pixel centres, metres from the origin
    np.testing.assert_array_equal(np.isfinite(out), np.broadcast_to(x < edge * pixel, out.shape))
    np.testing.assert_allclose(out[np.isfinite(out)], 0.5, atol=1e-6)


@pytest.mark.parametrize("factor", [2, 4])
def test_finer_reference_is_the_mean_of_the_pixels_under_each_capture_pixel(files, grid, factor):
    fine = np.random.default_rng(factor).random((REF_SHAPE[0] * factor, REF_SHAPE[1] * factor), np.float32)
    path = _write(files["dir"] / f"fine{factor}.tif", fine, UTM, _utm(0, 0, pixel=1.0 / factor))
    out = reference_window(path, grid, *_window(grid))
    (r, c), (h, w) = CAP_OFFSET, CAP_SHAPE
    under = fine[r * factor:(r + h) * factor, c * factor:(c + w) * factor]
    np.testing.assert_allclose(out, under.reshape(h, factor, w, factor).mean(axis=(1, 3)), atol=1e-6)


@pytest.mark.parametrize("pixel", [2.0, 0.7, 0.4])
def test_windows_of_a_resampled_reference_stitch_into_the_whole(files, grid, scene, pixel):
    # tiles that do not divide the window, and one window for the whole: the same pixels
    shape = (int(REF_SHAPE[0] / pixel), int(REF_SHAPE[1] / pixel))
    resampled = np.full(shape, np.nan, np.float32)
    reproject(scene, resampled, src_transform=_utm(0, 0), src_crs=UTM, dst_transform=_utm(0, 0, pixel),
              dst_crs=UTM, resampling=Resampling.average if pixel > 1 else Resampling.lanczos)
    path = _write(files["dir"] / f"grid{pixel}.tif", resampled, UTM, _utm(0, 0, pixel))
    rows, cols = _window(grid, margin=9)
    whole = reference_window(path, grid, rows, cols)
    assert np.isfinite(whole).all()
    tiled = np.vstack([np.hstack([reference_window(path, grid, slice(r0, min(r0 + 37, rows.stop)),
                                                   slice(c0, min(c0 + 53, cols.stop)))
                                  for c0 in range(cols.start, cols.stop, 53)])
                       for r0 in range(rows.start, rows.stop, 37)])
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-6)  # float32 rounding; a seam would be ~1e-2


@pytest.mark.parametrize("crs, res", [("EPSG:3857", 0.7), ("EPSG:4326", 6e-6)])
def test_reference_in_another_crs(files, grid, scene, crs, res):
    transform, width, height = calculate_default_transform(
        UTM, crs, REF_SHAPE[1], REF_SHAPE[0], *rasterio.transform.array_bounds(*REF_SHAPE, _utm(0, 0)),
        resolution=res)
    warped = np.full((height, width), np.nan, np.float32)
    reproject(scene, warped, src_transform=_utm(0, 0), src_crs=UTM, dst_transform=transform,
              dst_crs=crs, dst_nodata=np.nan, resampling=Resampling.bilinear)
    warped = np.where(np.isnan(warped), -1.0, warped).astype(np.float32)
    path = _write(files["dir"] / f"ref_{crs.replace(':', '')}.tif", warped, crs, transform, nodata=-1.0)
    out = reference_window(path, grid, *_window(grid))
    assert np.isfinite(out).all()
    assert _corr(out, _crop(scene)) > 0.98
    assert float(np.abs(out - _crop(scene)).mean()) < 0.03


def test_bad_windows_are_refused(files, grid):
    with pytest.raises(ParameterError, match="rows"):
        reference_window(files["ref"], grid, slice(0, 10, 2), slice(0, 10))
    with pytest.raises(ParameterError, match="cols"):
        reference_window(files["ref"], grid, slice(0, 10), slice(None, 10))


# ---------------------------------------------------------------- coverage


def test_partial_overlap_nan_outside_and_fraction(files, scene):
    # capture whose columns 0..99 lie over reference columns 300..399, the rest beyond
    d = files["dir"]
    cap = _write(d / "edge.tif", np.zeros(CAP_SHAPE, np.float32), UTM, _utm(300, 70))
    pairing = pair_images([files["left"], files["right"]], cap)
    assert pairing.mode == "georeferenced"
    assert pairing.coverage.fraction == pytest.approx(100 / 160)
    assert pairing.coverage.files == (files["right"],)
    assert pairing.coverage.file_fractions == (0.0, pytest.approx(100 / 160))
    out = pairing.reference_window(slice(0, 120), slice(0, 160))
    np.testing.assert_array_equal(out[:, :100], scene[70:190, 300:400])
    assert np.isnan(out[:, 100:]).all()


def test_coverage_in_another_crs(files, grid):
    # a geographic reference whose east edge runs through the capture's middle
    from rasterio.warp import transform_bounds

    west, south, east, north = transform_bounds(UTM, "EPSG:4326", *grid_bounds(grid))
    middle = (west + east) / 2
    step = 1e-5
    shape = (int((north - south) / step) + 20, int((middle - west) / step) + 10)
    transform = Affine(step, 0.0, west - 10 * step, 0.0, -step, north + 10 * step)
    path = _write(files["dir"] / "half4326.tif", np.ones(shape, np.float32), "EPSG:4326", transform)
    coverage = reference_coverage([files["ref"], path], grid)
    assert coverage.fraction == 1.0 and coverage.files == (files["ref"], path)
    assert coverage.file_fractions[1] == pytest.approx(0.5, abs=0.02)


def grid_bounds(grid):
    left, top = grid.transform[2], grid.transform[5]
    return left, top + grid.transform[4] * grid.shape[0], left + grid.transform[0] * grid.shape[1], top


def test_no_overlap_names_both_files(files):
    cap = _write(files["dir"] / "far.tif", np.zeros(CAP_SHAPE, np.float32), UTM, _utm(5000, 0))
    with pytest.raises(InputError, match=r"far\.tif: footprint does not overlap the reference .*ref\.tif"):
        pair_images(files["ref"], cap)


def test_same_size_pair_5_km_apart_is_refused(files, scene):
    d = files["dir"]
    a = _write(d / "a.tif", scene[:120, :160], UTM, _utm(0, 0))
    b = _write(d / "b.tif", scene[:120, :160], UTM, _utm(0, -5000))
    with pytest.raises(InputError, match=r"b\.tif: footprint does not overlap the reference .*a\.tif"):
        pair_images(a, b)


# ---------------------------------------------------------------- pairing


def test_georeferenced_pairing(files, grid):
    pairing = pair_images([files["left"], files["right"]], files["cap"])
    assert pairing.mode == "georeferenced" and pairing.grid == grid
    assert pairing.shape == CAP_SHAPE and pairing.coverage.fraction == 1.0
    assert [g.path for g in pairing.reference_grids] == [files["left"], files["right"]]
    np.testing.assert_array_equal(pairing.reference_window(slice(0, 120), slice(0, 160)),
                                  reference_window(files["ref"], grid, slice(0, 120), slice(0, 160)))


def test_pixel_pairing_without_georeferencing(tmp_path, scene):
    a = str(tmp_path / "a.npy")
    b = str(tmp_path / "b.npy")
    np.save(a, scene[:50, :60])
    np.save(b, scene[:50, :60])
    pairing = pair_images(a, b)
    assert pairing.mode == "pixel" and "neither" in pairing.reason
    np.testing.assert_array_equal(pairing.reference_window(slice(-2, 52), slice(0, 60))[2:52],
                                  scene[:50, :60])
    np.save(b, scene[:50, :61])
    with pytest.raises(InputError, match=r"b\.npy: size \(50, 61\) differs from the reference .*a\.npy"):
        pair_images(a, b)
    with pytest.raises(InputError, match="2 reference files given"):
        pair_images([a, a], b)


def test_mixed_pairing_is_pixel_for_pixel(files, tmp_path, scene):
    plain = str(tmp_path / "plain.npy")
    np.save(plain, _crop(scene))
    pairing = pair_images(plain, files["cap"])
    assert pairing.mode == "pixel" and "plain.npy is not georeferenced" in pairing.reason
    with pytest.raises(InputError, match="give images of the same size"):
        pair_images(files["ref"], plain)


def test_no_reference_is_a_parameter_error(files):
    with pytest.raises(ParameterError, match="references"):
        pair_images([], files["cap"])


def test_pairing_reason_names_the_resampling(files, scene):
    coarse = _write(files["dir"] / "coarse_reason.tif", scene[::2, ::2], UTM, _utm(0, 0, pixel=2.0))
    fine = _write(files["dir"] / "fine_reason.tif", np.repeat(np.repeat(scene, 2, 0), 2, 1), UTM,
                  _utm(0, 0, pixel=0.5))
    assert "(copy; 100.0% of the capture covered)" in pair_images(files["ref"], files["cap"]).reason
    assert "(lanczos; " in pair_images(coarse, files["cap"]).reason
    assert "(average, lanczos; " in pair_images([fine, coarse], files["cap"]).reason
