"""Tests of pipeline._report: the HTML report of one detect run."""

import re
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import zarr
from PIL import Image

from rsmb import pipeline
from rsmb.ops import InputError, ParameterError, synthesize_pair
from rsmb.pipeline._report import (
    DEFAULT_MAX_PIXELS,
    FIGURES,
    block_reduce,
    downsample_factor,
    overlay_rgb,
    write_report,
)
from rsmb.pipeline._synth import write_pair

SHAPE = (256, 256)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A finished detect store of a 256 x 256 pair on a 2 x 2 tile grid."""
    base = tmp_path_factory.mktemp("report")
    pair = synthesize_pair(SHAPE, changes=4, noise=0.002, seed=3)
    ref, dist = write_pair(base / "pair", pair, fmt="png")
    out = base / "run.zarr"
    pipeline.detect(ref, dist, out, config=pipeline.DetectConfig(tile=128), scheduler="synchronous")
    return out


def _png_size(path):
    with Image.open(path) as im:
        im.verify()  # a valid PNG
    with Image.open(path) as im:
        assert im.format == "PNG"
        return im.size


# --------------------------------------------------------------------------- the report


def test_report_has_every_figure(store, tmp_path):
    index = write_report(store, tmp_path / "rep")
    assert index == tmp_path / "rep" / "index.html"
    page = index.read_text(encoding="utf-8")
    attrs = zarr.open_group(str(store), mode="r").attrs.asdict()
    for name in FIGURES:
        assert f'src="{name}"' in page
        w, h = _png_size(tmp_path / "rep" / name)
        assert 100 <= w <= 2000 and 100 <= h <= 2000
    assert _png_size(tmp_path / "rep" / "overlay.png") == (SHAPE[1], SHAPE[0])  # small: full resolution
    for role in ("reference", "distorted"):
        assert attrs["inputs"][role]["sha256"] in page
        assert attrs["inputs"][role]["path"] in page
    assert "register (s)" in page and "lambda_chi" in page and "changed pixels" in page
    assert page.count("<figcaption>") == len(FIGURES)


def test_report_is_self_contained(store, tmp_path):
    page = write_report(store, tmp_path / "rep").read_text(encoding="utf-8")
    assert "<script" not in page.lower()
    assert not re.search(r"(src|href)=\"(https?:)?//", page)
    local = set(re.findall(r"(?:src|href)=\"([^\"]+)\"", page))
    assert local == set(FIGURES)


def test_default_directory_next_to_store(store):
    index = write_report(store, overwrite=True)
    assert index.parent == store.with_name(store.name + ".report")
    assert all((index.parent / name).is_file() for name in FIGURES)


@pytest.mark.parametrize("max_pixels", [64 * 64, 100 * 37, 1])
def test_overlay_honours_max_pixels(store, tmp_path, max_pixels):
    write_report(store, tmp_path / "rep", max_pixels=max_pixels)
    w, h = _png_size(tmp_path / "rep" / "overlay.png")
    assert w * h <= max_pixels
    f = downsample_factor(SHAPE, max_pixels)
    assert (h, w) == (-(-SHAPE[0] // f), -(-SHAPE[1] // f))


def test_small_changes_survive_downsampling(store, tmp_path):
    """Block maximum: every changed block shows red or yellow in a 32 x 32 overlay."""
    write_report(store, tmp_path / "rep", max_pixels=32 * 32)
    mask = zarr.open_group(str(store), mode="r")["change_mask"][:]
    assert mask.any()
    rgb = np.asarray(Image.open(tmp_path / "rep" / "overlay.png").convert("RGB")).astype(int)
    f = SHAPE[0] // 32
    blocks = mask.reshape(32, f, 32, f).max(axis=(1, 3)) > 0
    reddish = (rgb[..., 0] > rgb[..., 2] + 60)
    assert reddish[blocks].all()


def test_existing_directory_refused(store, tmp_path):
    out = tmp_path / "rep"
    write_report(store, out)
    with pytest.raises(InputError, match="not empty"):
        write_report(store, out)
    (out / "notes.txt").write_text("kept")
    assert write_report(store, out, overwrite=True).is_file()
    assert (out / "notes.txt").read_text() == "kept"


def test_empty_existing_directory_is_used(store, tmp_path):
    (tmp_path / "rep").mkdir()
    assert write_report(store, tmp_path / "rep").is_file()


def test_missing_store(tmp_path):
    with pytest.raises(InputError, match="no such output store"):
        write_report(tmp_path / "nothing.zarr", tmp_path / "rep")


def test_not_a_detect_store(tmp_path):
    zarr.open_group(str(tmp_path / "other.zarr"), mode="w").create_array("x", shape=(4,), dtype="uint8")
    with pytest.raises(InputError, match="change_mask"):
        write_report(tmp_path / "other.zarr", tmp_path / "rep")


@pytest.mark.parametrize("bad", [0, -5, 2.5, "big", True])
def test_bad_max_pixels(store, tmp_path, bad):
    with pytest.raises(ParameterError, match="max_pixels"):
        write_report(store, tmp_path / "rep", max_pixels=bad)


def test_reports_in_threads(store, tmp_path):
    """Matplotlib without pyplot: two reports at once in threads."""
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda i: write_report(store, tmp_path / f"rep{i}", max_pixels=96 * 96), range(2)))
    for index in results:
        assert all((index.parent / name).is_file() for name in FIGURES)


# --------------------------------------------------------------------------- downsampling helpers


@pytest.mark.parametrize("shape", [(256, 256), (8192, 8192), (1000, 37), (5, 3000), (1, 1)])
@pytest.mark.parametrize("max_pixels", [1, 7, 64 * 64, 1000, DEFAULT_MAX_PIXELS])
def test_downsample_factor_is_smallest(shape, max_pixels):
    f = downsample_factor(shape, max_pixels)
    size = lambda k: -(-shape[0] // k) * -(-shape[1] // k)  # noqa: E731
    assert size(f) <= max_pixels
    assert f == 1 or size(f - 1) > max_pixels


def _blocks_numpy(a, f, how):
    h, w = a.shape
    out = np.full((-(-h // f), -(-w // f)), np.nan, np.float32)
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            cell = a[i * f:(i + 1) * f, j * f:(j + 1) * f]
            cell = cell[np.isfinite(cell)]
            if cell.size:
                out[i, j] = cell.mean() if how == "mean" else cell.max()
    return out


@pytest.mark.parametrize("factor", [1, 3, 7, 64])
@pytest.mark.parametrize("how", ["mean", "max"])
def test_block_reduce_tiled_equals_whole(tmp_path, factor, how):
    """Band-wise reads from a zarr array (chunks that do not divide the image
    nor the factor) equal the block reduction of the whole array."""
    rng = np.random.default_rng(7)
    a = rng.random((61, 45)).astype(np.float32)
    a[5:20, 3:30] = np.nan  # some all-NaN blocks for the larger factors
    z = zarr.open_array(str(tmp_path / "a.zarr"), mode="w", shape=a.shape, dtype="float32", chunks=(10, 16),
                        fill_value=np.nan)
    z[:] = a
    got = block_reduce(z, factor, how)
    np.testing.assert_allclose(got, _blocks_numpy(a, factor, how), rtol=1e-5, equal_nan=True)
    np.testing.assert_allclose(block_reduce(a, factor, how), got, rtol=1e-6, equal_nan=True)


def test_block_max_keeps_single_pixel():
    mask = np.zeros((100, 100), np.uint8)
    mask[37, 81] = 1
    small = block_reduce(mask, 16, "max")
    assert small.shape == (7, 7)
    assert small.sum() == 1 and small[37 // 16, 81 // 16] == 1


def test_overlay_colours():
    gray = np.tile(np.linspace(0, 1, 40, dtype=np.float32), (30, 1))
    gray[0:3, 0:3] = np.nan
    mask = np.zeros((30, 40), np.uint8)
    mask[10:20, 10:20] = 1
    mask[25, 35] = 1  # a one-pixel change gets a ring
    out = overlay_rgb(gray, mask, row_lines=[15], col_lines=[5])
    assert out.shape == (30, 40, 3) and out.dtype == np.uint8
    rgb = out.astype(int)
    assert (rgb[12:18, 12:18, 0] > rgb[12:18, 12:18, 2] + 60).all()  # red fill inside
    assert tuple(rgb[10, 14]) == tuple(rgb[25, 35])  # outline colour on edge and tiny change
    ring = np.argwhere((rgb[..., 0] > 200) & (rgb[..., 1] > 200) & (rgb[..., 2] < 100))
    assert any(abs(r - 25) == 3 for r, _ in ring)  # ring drawn around the dot
    assert rgb[1, 1, 2] > rgb[1, 1, 0]  # NaN drawn bluish
    assert rgb[5, 5, 2] > rgb[5, 5, 0] or rgb[5, 5, 1] > rgb[5, 5, 0]  # faint cyan grid (col 5)


def test_failed_rows_are_counted_in_the_summary_and_the_report(tmp_path, small_pair_files):
    """Rows stopped at the iteration limit are failed: the run summary counts
    them and the report says so."""
    from rsmb.ops import RegistrationParams

    _, ref, dist = small_pair_files
    config = pipeline.DetectConfig(registration=RegistrationParams(max_outer=1), tile=128)
    result = pipeline.detect(ref, dist, tmp_path / "o.zarr", config=config)
    states = zarr.open_group(str(tmp_path / "o.zarr"), mode="r")["tile_row_state"][:]
    assert result.failed_rows == int((states == 3).sum()) > 0
    page = write_report(tmp_path / "o.zarr").read_text()
    assert f"failed tile rows (no fit, or unconverged)</td><td class=\"num\">{result.failed_rows}<" in page


# --------------------------------------------------------------------------- axes that are zero on every row


def test_flat_axes_split_by_construction():
    """An axis is flat when every finite value, fused and per tile, is zero."""
    from rsmb.pipeline._report_figures import flat_axes_split

    rows = np.arange(50, dtype=np.float64)
    traj = np.zeros((50, 5))
    traj[:, 0] = 0.1 * rows
    traj[:, 2] = np.sin(rows)
    per_tile = np.repeat(traj[:, None, :], 3, axis=1)
    per_tile[7, 1, 3] = np.nan  # an unsolved row is not a value
    assert flat_axes_split(traj, per_tile) == ([0, 2], [1, 3, 4])
    per_tile[9, 2, 4] = 1e-9  # one tile column away from zero on one row
    assert flat_axes_split(traj, per_tile) == ([0, 2, 4], [1, 3])
    assert flat_axes_split(traj) == ([0, 2], [1, 3, 4])
    assert flat_axes_split(np.zeros((50, 3))) == ([0], [1, 2])  # never no panel at all
    unsolved = traj.copy()
    unsolved[:, 1] = np.nan  # no value at all is not zero: drawn (empty)
    assert flat_axes_split(unsolved) == ([0, 1, 2], [3, 4])


def test_report_names_flat_axes_instead_of_drawing_them(store, tmp_path):
    """A store whose rx and ry are zero on every row: the trajectory figure has
    no panel for them, the caption says so and the figure is shorter than with
    rx drawn."""
    import shutil

    copy = tmp_path / "flat.zarr"
    shutil.copytree(store, copy)
    group = zarr.open_group(str(copy), mode="r+")
    assert list(group["trajectory"].attrs["pose_axes"])[3:] == ["rx", "ry"]
    traj, per_tile = group["trajectory"][:], group["tile_trajectory"][:]
    traj[:, 3:], per_tile[..., 3:] = 0.0, 0.0
    traj[:, 0] = np.linspace(-2.0, 2.0, traj.shape[0])
    group["trajectory"][:], group["tile_trajectory"][:] = traj, per_tile
    page = write_report(copy, tmp_path / "flat").read_text(encoding="utf-8")
    assert "No panel for rx (deg), ry (deg): zero on every row" in page
    _, flat_height = _png_size(tmp_path / "flat" / "trajectory.png")

    per_tile[5, 0, 3] = 0.01  # rx moves in one tile on one row: drawn again
    group["tile_trajectory"][:] = per_tile
    page = write_report(copy, tmp_path / "rx").read_text(encoding="utf-8")
    assert "No panel for ry (deg): zero on every row" in page
    _, rx_height = _png_size(tmp_path / "rx" / "trajectory.png")
    assert rx_height > flat_height


def _outlines_whole_image(changed, small=4):
    """The overlay's outline pixels by their definition, on the whole image:
    the complement of a binary erosion, and rings from whole-image dilations."""
    from scipy import ndimage

    edge = changed & ~ndimage.binary_erosion(changed, border_value=0)
    labels, count = ndimage.label(changed)
    area = np.bincount(labels.ravel(), minlength=count + 1)
    inner = ndimage.binary_dilation((area <= small)[labels] & changed, iterations=2)
    return edge | (ndimage.binary_dilation(inner) & ~inner & ~changed)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("dots", [0, 3, 200])
def test_outlines_in_windows_equal_whole_image(seed, dots):
    """Edges by shifted slices and rings dilated in windows around the tiny
    changes equal the whole-image morphology: changes on the border, tiny ones
    close to each other and to large ones, none, and more than the per-window
    limit."""
    from rsmb.pipeline._report_figures import _outlines

    rng = np.random.default_rng(seed)
    changed = np.zeros((90, 70), bool)
    for _ in range(6):
        r, c, h, w = rng.integers(0, 90), rng.integers(0, 70), rng.integers(1, 12), rng.integers(1, 12)
        changed[r:r + h, c:c + w] = True
    changed[rng.integers(0, 90), 69] = True  # a tiny change on the border
    for r, c in zip(rng.integers(0, 90, dots), rng.integers(0, 70, dots)):
        changed[r, c] = True
    np.testing.assert_array_equal(_outlines(changed), _outlines_whole_image(changed))
    pair = np.zeros_like(changed)
    pair[40, 30] = pair[40, 34] = True  # two dots whose rings overlap
    np.testing.assert_array_equal(_outlines(pair), _outlines_whole_image(pair))
    assert not _outlines(np.zeros_like(changed)).any()


def test_score_values_are_pasted_pixel_for_pixel(tmp_path):
    """A small score map is drawn without resampling: each value is a square
    of ``zoom`` PNG pixels of exactly its colormap colour."""
    from matplotlib import colormaps
    from scipy import ndimage

    from rsmb.pipeline._report_figures import _write_score

    score = np.zeros((40, 60), np.float32)
    score[10:20, 30:50] = 0.37
    entry = _write_score({"change_score": score}, {"summary": {"threshold": 0.25}}, 1, tmp_path / "s.png")
    assert entry["vmax"] == pytest.approx(0.5)  # twice the threshold, above every score
    rgb = np.asarray(Image.open(tmp_path / "s.png").convert("RGB"))
    assert (rgb.shape[1], rgb.shape[0]) == entry["size"]
    zoom = 512 // 40
    colour = np.array(colormaps["inferno"](np.float32(0.37) / np.float32(0.5), bytes=True)[:3])
    labels, _ = ndimage.label((rgb == colour).all(axis=-1))
    sizes = [(s[0].stop - s[0].start, s[1].stop - s[1].start) for s in ndimage.find_objects(labels)]
    assert (10 * zoom, 20 * zoom) in sizes
    block = labels == 1 + sizes.index((10 * zoom, 20 * zoom))
    assert block.sum() == 10 * zoom * 20 * zoom  # a full rectangle
