"""Tests of pipeline.report: the HTML report of one detect run, its
matplotlib figures and the input previews the store keeps."""

import re
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import zarr
from PIL import Image

from rsmb import pipeline
from rsmb.ops import InputError, ParameterError, synthesize_pair
from rsmb.pipeline.report._report import (
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


def _image_size(path):
    with Image.open(path) as im:
        im.verify()  # a valid image
    with Image.open(path) as im:
        assert im.format == ("JPEG" if path.suffix == ".jpg" else "PNG")
        return im.size


# --------------------------------------------------------------------------- the report


def test_report_has_every_figure(store, tmp_path):
    index = write_report(store, tmp_path / "rep")
    assert index == tmp_path / "rep" / "index.html"
    page = index.read_text(encoding="utf-8")
    attrs = zarr.open_group(str(store), mode="r").attrs.asdict()
    for name in FIGURES:
        w, h = _image_size(tmp_path / "rep" / name)
        assert 100 <= w <= 2000 and 100 <= h <= 2000
        assert re.search(f'<img src="{name}"[^>]* width="{w}" height="{h}"', page)
    assert _image_size(tmp_path / "rep" / "overlay.png") == (SHAPE[1], SHAPE[0])  # small: full resolution
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
    w, h = _image_size(tmp_path / "rep" / "overlay.png")
    assert w * h <= max_pixels
    f = downsample_factor(SHAPE, max_pixels)
    assert (h, w) == (-(-SHAPE[0] // f), -(-SHAPE[1] // f))


def test_small_changes_survive_downsampling(store, tmp_path):
    """Block maximum: every changed block shows red or yellow in a 32 x 32 overlay."""
    write_report(store, tmp_path / "rep", max_pixels=32 * 32)
    mask = zarr.open_group(str(store), mode="r")["change_mask"][:] == 1
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
    (out / "trajectory.svg").write_bytes(b"an earlier version's figure")
    assert write_report(store, out, overwrite=True).is_file()
    assert (out / "notes.txt").read_text() == "kept"
    assert not (out / "trajectory.svg").exists()  # replaced by trajectory.png, not left to look current


def test_a_report_that_fails_leaves_the_folder_as_it_was(store, tmp_path):
    """A store with a damaged chunk: the report fails, and the folder keeps
    the earlier report byte for byte (a new folder is not made), with nothing
    half-written beside it."""
    import shutil

    damaged = tmp_path / "damaged.zarr"
    shutil.copytree(store, damaged)
    chunk = next(p for p in sorted((damaged / "change_score").rglob("*")) if p.is_file() and p.name != "zarr.json")
    chunk.write_bytes(b"\x00" * 64)
    out = tmp_path / "rep"
    write_report(store, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(Exception):
        write_report(damaged, out, overwrite=True)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    with pytest.raises(Exception):
        write_report(damaged, tmp_path / "new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["damaged.zarr", "rep"]


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
    """Two reports at once in threads: no global state (matplotlib figures without pyplot)."""
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


@pytest.mark.parametrize("factor", [2, 3, 5])
def test_block_max_and_preview_sums_equal_the_reductions_over_block_axes(factor):
    """The strided-view block maximum and the previews' integer block sums give
    the values of the plain reductions over each block's axes, NaN ignored
    (an all-NaN block stays NaN), partial edge blocks included."""
    from rsmb.pipeline.report._previews import reduce_preview

    rng = np.random.default_rng(factor)
    band = rng.random((40 * factor + 1, 30 * factor + 2), dtype=np.float32)
    band[rng.random(band.shape) < 0.4] = np.nan
    band[:factor, :factor] = np.nan  # a block with no value
    padded = np.pad(band, ((0, -band.shape[0] % factor), (0, -band.shape[1] % factor)), constant_values=np.nan)
    cells = padded.reshape(padded.shape[0] // factor, factor, padded.shape[1] // factor, factor)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        expected = np.nanmax(cells, axis=(1, 3))
    got = block_reduce(band, factor, "max")
    np.testing.assert_array_equal(got, expected)
    assert np.isnan(got[0, 0])
    rgba = rng.integers(0, 256, (24 * factor, 16 * factor, 4), dtype=np.uint8)
    rgba[..., 3] = 255
    h, w = rgba.shape[:2]
    mean = rgba[..., :3].astype(np.float32).reshape(h // factor, factor, w // factor, factor, 3).mean(axis=(1, 3))
    np.testing.assert_array_equal(reduce_preview(rgba, factor)[..., :3], (mean + np.float32(0.5)).astype(np.uint8))


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
    from rsmb.pipeline.report._report_figures import flat_axes_split

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
    from rsmb.pipeline.report._report_figures import _outlines

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



# --------------------------------------------------------------------------- figures drawn with matplotlib


def test_report_names_flat_axes_instead_of_drawing_them(store, tmp_path):
    """A store whose rx and ry are zero on every row: the caption says so and
    the trajectory figure is shorter than with rx drawn."""
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
    _, flat_height = _image_size(tmp_path / "flat" / "trajectory.png")

    per_tile[5, 0, 3] = 0.01  # rx moves in one tile on one row: drawn again
    group["tile_trajectory"][:] = per_tile
    page = write_report(copy, tmp_path / "rx").read_text(encoding="utf-8")
    assert "No panel for ry (deg): zero on every row" in page
    _, rx_height = _image_size(tmp_path / "rx" / "trajectory.png")
    assert rx_height > flat_height


@pytest.fixture
def trajectory_data():
    """300 rows, 2 tile columns, tile rows split at row 128; tx a ramp, rz a
    sine; tile column 1 unsolved on rows 100-119 and on row 200 alone."""
    rows = np.arange(300, dtype=np.float64)
    traj = np.zeros((300, 2))
    traj[:, 0] = -3.0 + 0.02 * rows
    traj[:, 1] = 0.5 * np.sin(rows / 40.0)
    per_tile = np.repeat(traj[:, None, :], 2, axis=1)
    per_tile[:, 1, 1] += 0.05
    per_tile[100:120, 1] = np.nan
    per_tile[200, 1] = np.nan
    return rows, traj, per_tile


def test_trajectory_figure_panels_lines_and_note(trajectory_data):
    """One panel per axis drawn, in order; in each the fused path (black)
    and each tile column's own with its values (NaN where unsolved, where
    matplotlib breaks the line); one dashed tile-row boundary; a legend; the
    note names the flat axis."""
    from rsmb.pipeline.report._report_plots import trajectory_figure

    rows, traj, per_tile = trajectory_data
    fig = trajectory_figure(rows, traj, per_tile, ["tx (px)", "rz (deg)"], boundaries=[128], flat=["ty (px)"])
    axes = fig.axes
    assert [ax.get_ylabel() for ax in axes] == ["tx (px)", "rz (deg)"]
    assert axes[-1].get_xlabel().startswith("row (px)")
    for d, ax in enumerate(axes):
        solid = [line for line in ax.lines if line.get_linestyle() == "-"]
        fused = [line for line in solid if line.get_color() == "black"]
        assert len(fused) == 1
        np.testing.assert_array_equal(fused[0].get_ydata(), traj[:, d])
        tiles = [line for line in solid if line.get_color() != "black"]
        assert len(tiles) == 2
        np.testing.assert_array_equal(tiles[1].get_ydata(), per_tile[:, 1, d])  # NaN kept: the line breaks
        assert np.isnan(tiles[1].get_ydata()[[100, 119, 200]]).all()
        dashed = [line for line in ax.lines if line.get_linestyle() == "--"]
        assert len(dashed) == 1 and list(dashed[0].get_xdata()) == [128, 128]
        assert ax.get_xlim() == (0.0, 299.0)
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == ["fused", "tile column 0", "tile column 1"]
    assert "Not drawn, zero on every row: ty (px)" in [t.get_text() for t in fig.texts]


def _cell_texts(ax):
    return {(round(t.get_position()[1]), round(t.get_position()[0])): t.get_text() for t in ax.texts}


def test_tile_map_figure_values_colours_marks_and_tolerance():
    """A cell per tile with its value written in it (n/a and grey where
    unknown) and coloured by the colormap at its value; re-solved tiles
    outlined dashed red with a legend; the tolerance as a black line on the
    colorbar."""
    from matplotlib import colormaps
    from matplotlib.colors import to_rgba
    from matplotlib.patches import Rectangle

    from rsmb.pipeline.report._report_plots import tile_map_figure

    agree = np.array([[0.1, np.nan], [0.4, 2.5]])
    fig = tile_map_figure(agree, cmap="magma_r", lo=0.0, hi=3.0, title="t", label="disagreement (px)", fmt=".2f",
                          marked=[(1, 1)], marked_label="re-solved", line=(0.5, "tolerance 0.5 px"))
    ax, cax = fig.axes
    assert _cell_texts(ax) == {(0, 0): "0.10", (0, 1): "n/a", (1, 0): "0.40", (1, 1): "2.50"}
    image = ax.images[0]
    np.testing.assert_array_equal(np.ma.getdata(image.get_array()), agree)
    assert image.to_rgba(np.array([2.5]))[0] == pytest.approx(colormaps["magma_r"](2.5 / 3.0))
    assert image.to_rgba(np.ma.masked_invalid([np.nan]))[0] == pytest.approx(to_rgba("#d9d9d9"))
    red = [p for p in ax.patches if isinstance(p, Rectangle) and p.get_edgecolor() == to_rgba("red")]
    assert len(red) == 1 and red[0].get_xy() == pytest.approx((1 - 0.45, 1 - 0.45)) and red[0].get_linestyle() == "--"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["re-solved"]
    marks = [line for line in cax.lines if line.get_color() == "black"]
    assert len(marks) == 1 and list(marks[0].get_ydata()) == [0.5, 0.5]
    assert cax.get_ylabel() == "disagreement (px); line: tolerance 0.5 px"


def test_tile_map_of_equal_values():
    """Every tile the same gain: a range is made around it, every cell gets the
    colormap's middle colour and the colorbar brackets the value."""
    from matplotlib import colormaps

    from rsmb.pipeline.report._report_plots import tile_map_figure

    fig = tile_map_figure(np.ones((3, 2)), cmap="cividis", title="t", label="gain", fmt=".4f")
    ax, cax = fig.axes
    assert set(_cell_texts(ax).values()) == {"1.0000"} and len(ax.texts) == 6
    assert ax.images[0].to_rgba(np.array([1.0]))[0] == pytest.approx(colormaps["cividis"](0.5), abs=1 / 255)
    lo, hi = cax.get_ylim()
    assert lo < 1.0 < hi


def test_report_tile_maps_show_the_store(store, tmp_path):
    """gain.png and agreement.png of a 2 x 2 store: the values drawn are the store's."""
    from rsmb.pipeline.report import _report_figures, _report_plots

    drawn = {}
    real = _report_plots.tile_map_figure

    def spy(values, **kwargs):
        drawn[kwargs["title"]] = (np.array(values), kwargs)
        return real(values, **kwargs)

    group = zarr.open_group(str(store), mode="r")
    attrs = group.attrs.asdict()
    try:
        _report_plots.tile_map_figure = spy
        _report_figures._write_gain(group, attrs, tmp_path / "g.png")
        _report_figures._write_agreement(group, attrs, tmp_path / "a.png")
    finally:
        _report_plots.tile_map_figure = real
    np.testing.assert_array_equal(drawn["Illumination gain per tile"][0], group["gain"][:])
    values, kwargs = drawn["Tile path vs fused path"]
    np.testing.assert_array_equal(values, group["tile_agreement"][:])
    assert kwargs["line"][0] == attrs["parameters"]["agreement"]
    assert _image_size(tmp_path / "g.png")[0] > 100 and _image_size(tmp_path / "a.png")[0] > 100


def test_score_figure_draws_each_value_as_a_square_and_marks_the_threshold(tmp_path):
    """The score is drawn unresampled: each value a ``zoom`` x ``zoom`` square
    of its colormap colour; the colorbar runs from 0 to vmax with a cyan line at
    the threshold; NaN is white."""
    from matplotlib import colormaps

    from rsmb.pipeline.report._report_figures import _write_score
    from rsmb.pipeline.report._report_plots import DPI, score_figure

    score = np.zeros((40, 60), np.float32)
    score[10:20, 30:50] = 0.37
    score[0, 0] = np.nan
    entry = _write_score({"change_score": score}, {"summary": {"threshold": 0.25}}, 1, tmp_path / "s.png")
    assert entry["vmax"] == pytest.approx(0.5)  # twice the threshold, above every score
    assert entry["zoom"] == 512 // 40
    assert _image_size(tmp_path / "s.png") == entry["size"] == (60 * 12 + 230, 40 * 12 + 100)

    fig = score_figure(score, vmax=0.5, threshold=0.25, zoom=4)
    ax, cax = fig.axes
    np.testing.assert_array_equal(ax.artists[0].get_array(),
                                  colormaps["inferno"].with_extremes(bad="white")(score / 0.5, bytes=True))
    assert cax.get_ylim() == (0.0, 0.5)
    cyan = [line for line in cax.lines if line.get_color() == "cyan"]
    assert len(cyan) == 1 and list(cyan[0].get_ydata()) == [0.25, 0.25]
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    pixels = np.asarray(canvas.buffer_rgba())[..., :3]
    x0, y1 = ax.get_position().x0 * fig.get_figwidth() * DPI, ax.get_position().y1 * fig.get_figheight() * DPI
    top = pixels.shape[0] - int(round(y1))
    left = int(round(x0))
    changed = colormaps["inferno"](0.37 / 0.5, bytes=True)[:3]
    block = pixels[top + 12 * 4 + 1:top + 12 * 4 + 3, left + 35 * 4 + 1:left + 35 * 4 + 3]  # value (12, 35)
    assert (block == changed).all()
    zero = colormaps["inferno"](0.0, bytes=True)[:3]
    assert (pixels[top + 5 * 4 + 1, left + 5 * 4 + 1] == zero).all()
    assert (pixels[top + 2, left + 2] == 255).all()  # NaN: white (inside the spines)


def test_score_figure_without_threshold_has_no_mark():
    from rsmb.pipeline.report._report_plots import score_figure

    fig = score_figure(np.linspace(0, 1, 64 * 64, dtype=np.float32).reshape(64, 64), vmax=1.0)
    assert not [line for line in fig.axes[1].lines if line.get_color() == "cyan"]
    assert "threshold" not in fig.axes[1].get_ylabel()


def test_report_score_colorbar_has_the_store_threshold(store, tmp_path):
    page = write_report(store, tmp_path / "rep").read_text(encoding="utf-8")
    threshold = zarr.open_group(str(store), mode="r").attrs["summary"]["threshold"]
    assert f"Threshold {threshold:.4g} (cyan line on the colorbar)" in page
    w, h = _image_size(tmp_path / "rep" / "change_score.png")
    assert (w, h) == (SHAPE[1] * 2 + 230, SHAPE[0] * 2 + 100)  # each value a 2 x 2 square


# --------------------------------------------------------------------------- before and after


def _rgb_png(path, rgb):
    Image.fromarray(rgb).save(path)
    return str(path)


def _block_mean(a, f):
    h, w = a.shape[:2]
    pad = np.pad(a.astype(np.float64), ((0, -h % f), (0, -w % f)) + ((0, 0),) * (a.ndim - 2),
                 constant_values=np.nan)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN blocks: NaN
        return np.nanmean(pad.reshape(pad.shape[0] // f, f, pad.shape[1] // f, f, *a.shape[2:]), axis=(1, 3))


def test_previews_keep_colour_and_mark_missing_data(tmp_path):
    """An 8-bit RGB capture and an RGBA reference: block means of the colour
    bands, values kept as they are; alpha 0 where the reference's alpha is."""
    from rsmb import tiles
    from rsmb.pipeline.report._previews import read_preview, write_previews

    rng = np.random.default_rng(4)
    cap = rng.integers(0, 256, (70, 101, 3), dtype=np.uint8)
    ref = np.concatenate([rng.integers(0, 256, (70, 101, 3), dtype=np.uint8), np.full((70, 101, 1), 255, np.uint8)],
                         axis=-1)
    ref[:30, :40, 3] = 0  # no data: three whole preview blocks of 10 x 10 (rows 0-29, cols 0-39)
    pairing = tiles.pair_images(_rgb_png(tmp_path / "ref.png", ref), _rgb_png(tmp_path / "cap.png", cap))
    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    write_previews(group, pairing, side=11)  # 101 px -> factor 10, 8 x 11 preview pixels
    after, factor = read_preview(group, "preview_capture")
    assert factor == 10 and after.shape == (7, 11, 4) and after.dtype == np.uint8
    np.testing.assert_array_equal(after[..., :3], np.floor(_block_mean(cap, 10) + 0.5).astype(np.uint8))
    assert (after[..., 3] == 255).all()
    before, _ = read_preview(group, "preview_reference")
    masked = ref[..., :3].astype(np.float64)
    masked[ref[..., 3] == 0] = np.nan
    expected = _block_mean(masked, 10)
    assert (before[:3, :4, 3] == 0).all() and (before[3:, :, 3] == 255).all() and (before[:, 4:, 3] == 255).all()
    np.testing.assert_array_equal(before[3:, :, :3], np.floor(expected[3:] + 0.5).astype(np.uint8))
    assert group["preview_capture"].metadata.dimension_names == ("preview_row", "preview_col", "rgba")


def test_previews_of_16_bit_gray_are_stretched_gray(tmp_path):
    """One band of 16 bits: gray (R = G = B), its 0.5th and 99.5th percentiles
    at 0 and 255, the order of values kept."""
    from rsmb import tiles
    from rsmb.pipeline.report._previews import read_preview, write_previews

    image = np.tile(np.linspace(1000, 5000, 200).astype(np.uint16), (50, 1))
    path = tmp_path / "g.png"
    Image.fromarray(image).save(path)
    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    write_previews(group, tiles.pair_images(str(path), str(path)))
    rgba, factor = read_preview(group, "preview_capture")
    assert factor == 1
    assert (rgba[..., 0] == rgba[..., 1]).all() and (rgba[..., 1] == rgba[..., 2]).all()
    row = rgba[0, :, 0].astype(int)
    assert row[0] == 0 and row[-1] == 255 and (np.diff(row) >= 0).all()


def test_georeferenced_reference_preview_is_on_the_capture_grid(tmp_path):
    """A larger RGB GeoTIFF reference and a gray capture that is a window of
    it: the reference preview is the reference's window under the capture,
    block-averaged onto the capture's grid (ground frame)."""
    import rasterio
    from rasterio.transform import from_origin

    from rsmb import tiles
    from rsmb.pipeline.report._previews import read_preview, write_previews

    rng = np.random.default_rng(6)
    ref = rng.integers(0, 256, (3, 120, 160), dtype=np.uint8)
    kw = dict(driver="GTiff", crs="EPSG:32633", dtype="uint8")
    with rasterio.open(tmp_path / "ref.tif", "w", height=120, width=160, count=3,
                       transform=from_origin(500000, 4000000, 0.5, 0.5), **kw) as ds:
        ds.write(ref)
    r0, c0 = 20, 40  # the capture's origin in reference pixels
    with rasterio.open(tmp_path / "cap.tif", "w", height=64, width=80, count=1,
                       transform=from_origin(500000 + 0.5 * c0, 4000000 - 0.5 * r0, 0.5, 0.5), **kw) as ds:
        ds.write(ref[:1, r0:r0 + 64, c0:c0 + 80])
    pairing = tiles.pair_images(str(tmp_path / "ref.tif"), str(tmp_path / "cap.tif"))
    assert pairing.mode == "georeferenced"
    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    write_previews(group, pairing, side=40)  # factor 2
    before, factor = read_preview(group, "preview_reference")
    assert factor == 2 and before.shape == (32, 40, 4)
    window = np.moveaxis(ref[:, r0:r0 + 64, c0:c0 + 80], 0, -1)
    assert np.abs(before[..., :3].astype(int) - _block_mean(window, 2)).max() <= 1
    assert (before[..., 3] == 255).all()
    assert group["preview_reference"].attrs["frame"].startswith("ground")


@pytest.mark.parametrize("copies", [1, 2, 3])
@pytest.mark.parametrize("n", [1, 2, 5, 200, 4097])
def test_percentiles_of_copies_are_numpys_of_the_copies(n, copies):
    """The stretch's percentiles of ``copies`` copies of some values, computed
    from the values alone, are numpy's percentiles of the copies to the byte
    (ties, integers, negative values, the ends and the middle)."""
    from rsmb.pipeline.report._previews import _percentiles_of_copies

    rng = np.random.default_rng(n * 10 + copies)
    for values in (rng.random(n).astype(np.float32), np.floor(rng.random(n) * 5).astype(np.float32),
                   np.floor(rng.random(n) * 65535).astype(np.float32), (rng.random(n) - 0.5) * 1e6):
        for q in ((0.5, 99.5), (0.0, 100.0), (25.0, 50.0, 75.0)):
            expected = np.percentile(np.tile(values, copies), q)
            found = _percentiles_of_copies(values, q, copies)
            assert found.dtype == expected.dtype and found.tobytes() == expected.tobytes(), (values, q)


def test_gray_reference_set_preview_is_its_three_band_stretch(tmp_path):
    """A 16-bit gray reference set of two files (no data where the first one
    ends, filled by the second) and then a colour file: the preview is the
    three-band computation (the gray drawn as three equal bands, stretched by
    the percentiles of all three) to the byte."""
    import rasterio
    from rasterio.transform import from_origin

    from rsmb import tiles
    from rsmb.pipeline.report import _previews
    from rsmb.pipeline.report._previews import read_preview, write_previews

    rng = np.random.default_rng(8)
    kw = dict(driver="GTiff", crs="EPSG:32633", transform=from_origin(500000, 4000000, 0.5, 0.5))
    gray = rng.integers(500, 60000, (90, 120), dtype=np.uint16)
    files = []
    for k, cols in enumerate((slice(0, 70), slice(50, 120))):
        data = np.zeros_like(gray)
        data[:, cols] = gray[:, cols] + k
        with rasterio.open(tmp_path / f"g{k}.tif", "w", height=90, width=120, count=1, dtype="uint16", nodata=0,
                           **kw) as ds:
            ds.write(data, 1)
        files.append(str(tmp_path / f"g{k}.tif"))
    with rasterio.open(tmp_path / "cap.tif", "w", height=90, width=100, count=1, dtype="uint16", **kw) as ds:
        ds.write(gray[:, :100], 1)

    def three_bands(grids, capture, factor, shape):  # the computation before gray stayed one band
        from rasterio.transform import Affine
        from rasterio.warp import Resampling, reproject

        out = None
        for grid in grids:
            with rasterio.open(grid.path) as ds:
                dest = np.full((1,) + shape, np.nan, np.float32)
                reproject(rasterio.band(ds, [1]), dest, src_transform=ds.transform, src_crs=ds.crs,
                          src_nodata=ds.nodata, dst_transform=capture.affine @ Affine.scale(factor),
                          dst_crs=capture.crs, dst_nodata=np.nan, resampling=Resampling.average)
            dest = np.repeat(dest, 3, axis=0)
            if out is None:
                out = dest
            else:
                fill = ~np.isfinite(out).all(axis=0) & np.isfinite(dest).all(axis=0)
                out[:, fill] = dest[:, fill]
        valid = np.isfinite(out).all(axis=0)
        lo, hi = np.percentile(out[:, valid], (0.5, 99.5))
        scaled = np.clip(np.nan_to_num((out - lo) * (255.0 / max(float(hi - lo), 1e-12)) + 0.5, nan=0.0), 0, 255)
        return np.concatenate([np.moveaxis(scaled.astype(np.uint8), 0, -1),
                               (valid * 255).astype(np.uint8)[..., None]], axis=-1)

    pairing = tiles.pair_images(files, str(tmp_path / "cap.tif"))
    group = zarr.open_group(str(tmp_path / "s.zarr"), mode="w")
    write_previews(group, pairing, side=50)  # factor 2
    before, factor = read_preview(group, "preview_reference")
    expected = three_bands(pairing.reference_grids, pairing.grid, factor, before.shape[:2])
    assert (before[..., 3] == 255).mean() > 0.9 and np.unique(before[..., 0]).size > 100
    assert np.array_equal(before, expected)
    # a colour file after the gray ones: three bands from there on, the same preview as all three-band
    rgb = np.stack([gray, gray // 2, gray // 3])
    with rasterio.open(tmp_path / "c.tif", "w", height=90, width=120, count=3, dtype="uint16", **kw) as ds:
        ds.write(rgb)
    mixed = _previews._warp_preview(tiles.pair_images(files + [str(tmp_path / "c.tif")],
                                                      str(tmp_path / "cap.tif")).reference_grids,
                                    pairing.grid, factor, before.shape[:2])
    assert np.array_equal(mixed, before)  # the gray files cover everything: the colour file fills nothing


def test_detect_store_keeps_previews_and_the_report_shows_them(store, tmp_path):
    """``rsmb detect`` stores both previews (the synthetic pair is 16-bit gray:
    stretched gray, same size); the report draws before_after.jpg from them,
    and a store without them (an earlier version's) still gets its report."""
    import shutil

    group = zarr.open_group(str(store), mode="r")
    for name in ("preview_reference", "preview_capture"):
        rgba = group[name][:]
        assert rgba.shape == SHAPE + (4,) and (rgba[..., 3] == 255).all()
        assert (rgba[..., 0] == rgba[..., 2]).all()
    page = write_report(store, tmp_path / "rep").read_text(encoding="utf-8")
    assert '<img src="before_after.jpg"' in page and "Reference (before)" not in page  # titles are in the figure
    assert "outlined in magenta on both" in page
    old = tmp_path / "old.zarr"
    shutil.copytree(store, old)
    for name in ("preview_reference", "preview_capture"):
        shutil.rmtree(old / name)
    zarr.consolidate_metadata(str(old))
    page = write_report(old, tmp_path / "old").read_text(encoding="utf-8")
    assert "before_after.jpg: not available (the store has no input previews" in page
    assert not (tmp_path / "old" / "before_after.jpg").exists()


def test_detect_store_previews_are_those_of_its_inputs(store):
    """The previews ``rsmb detect`` makes beside its stages are the ones
    made from its inputs alone, byte for byte, with their factor."""
    from rsmb import tiles
    from rsmb.pipeline.report._previews import preview_arrays, read_preview

    group = zarr.open_group(str(store), mode="r")
    inputs = group.attrs["inputs"]
    factor, arrays = preview_arrays(tiles.pair_images(inputs["reference"]["path"], inputs["distorted"]["path"]))
    for name, (rgba, _) in arrays.items():
        stored, stored_factor = read_preview(group, name)
        assert stored_factor == factor and stored.tobytes() == rgba.tobytes() and stored.shape == rgba.shape


def test_before_after_figure_outlines_the_changes_on_both():
    """Each panel shows its preview with a contour around each change of its
    own mask (in input pixels: preview pixels times the factor) and a circle
    around a change of one pixel."""
    from rsmb.pipeline.report._report_plots import before_after_figure

    rng = np.random.default_rng(8)
    before = rng.integers(0, 256, (50, 80, 4), dtype=np.uint8)
    after = rng.integers(0, 256, (50, 80, 4), dtype=np.uint8)
    before[..., 3] = after[..., 3] = 255
    ref_mask, cap_mask = np.zeros((50, 80)), np.zeros((50, 80))
    ref_mask[10:20, 30:50] = 1
    cap_mask[12:22, 33:53] = 1
    cap_mask[40, 5] = 1  # one pixel
    fig = before_after_figure(before, after, ref_mask, cap_mask, titles=("before", "after"), factor=4)
    for ax, mask, title, image in zip(fig.axes, (ref_mask, cap_mask), ("before", "after"), (before, after)):
        assert ax.get_title() == title
        np.testing.assert_array_equal(ax.artists[0].get_array(), image)
        assert ax.get_xlim() == (0, 80 * 4) and ax.get_ylim() == (50 * 4, 0)
        contour = [c for c in ax.collections if hasattr(c, "levels")][0]
        vertices = np.concatenate([p.vertices for p in contour.get_paths() if len(p.vertices)])
        rows, cols = np.nonzero(mask)
        big = vertices[vertices[:, 0] > 60]  # the rectangle's outline: half a pixel outside its pixel centres
        assert big[:, 0].min() == pytest.approx(cols[cols > 15].min() * 4, abs=2.01)
        assert big[:, 0].max() == pytest.approx((cols.max() + 1) * 4, abs=2.01)
        assert big[:, 1].min() == pytest.approx(rows[cols > 15].min() * 4, abs=2.01)
    circles = [c for c in fig.axes[1].collections if not hasattr(c, "levels")]
    assert len(circles) == 1 and circles[0].get_offsets().tolist() == [[5.5 * 4, 40.5 * 4]]
    assert not [c for c in fig.axes[0].collections if not hasattr(c, "levels")]  # no small change there


def test_overlay_of_a_preview_keeps_its_colours():
    """An RGBA preview: its colours where nothing changed, red over a change,
    dark blue where alpha is 0."""
    rgba = np.zeros((20, 30, 4), np.uint8)
    rgba[..., 2], rgba[..., 3] = 180, 255
    rgba[:2, :2, 3] = 0
    mask = np.zeros((20, 30), np.uint8)
    mask[8:14, 8:14] = 1
    rgb = overlay_rgb(rgba, mask).astype(int)
    assert tuple(rgb[18, 25]) == (0, 0, 180)
    assert rgb[10, 10, 0] > 100 and rgb[10, 10, 0] > rgb[10, 10, 1]
    assert tuple(rgb[0, 0]) == tuple((np.array([0.16, 0.18, 0.32]) * 255 + 0.5).astype(int))


def test_reduce_preview_averages_pixels_with_data():
    from rsmb.pipeline.report._previews import reduce_preview

    rgba = np.zeros((4, 6, 4), np.uint8)
    rgba[..., 0] = np.arange(6, dtype=np.uint8) * 10
    rgba[..., 3] = 255
    rgba[0, 0, 3] = 0  # left out of its block's mean
    rgba[2:, 4:, 3] = 0  # a block without data
    small = reduce_preview(rgba, 2)
    assert small.shape == (2, 3, 4)
    assert small[0, 0, 0] == 7  # (10 + 0 + 10) / 3 rounded
    assert small[1, 0, 0] == 5 and small[0, 2, 0] == 45
    assert small[1, 2, 3] == 0 and (small[..., 3].sum() == 5 * 255)
    assert reduce_preview(rgba, 1) is rgba
    rng = np.random.default_rng(2)
    full = rng.integers(0, 256, (12, 18, 4), dtype=np.uint8)
    full[..., 3] = 255
    for k in (2, 3):  # whole blocks all with data (a shortcut) equal the general rule
        general = full.copy()
        general[-1, -1, 3] = 254  # not the shortcut, the same means
        np.testing.assert_array_equal(reduce_preview(full, k)[..., :3], reduce_preview(general, k)[..., :3])
        np.testing.assert_array_equal(reduce_preview(full, k)[..., :3],
                                      np.floor(_block_mean(full[..., :3], k) + 0.5).astype(np.uint8))


# --------------------------------------------------------------------------- pixels and PNG files


@pytest.mark.parametrize("zoom", [1, 3])
def test_pixels_draw_what_imshow_draws(zoom):
    """An image drawn pixel for pixel into its axes' box gives the canvas
    imshow gives at whole screen pixels per value, spines and no-data pixels
    (alpha 0) included."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from rsmb.pipeline.report._report_plots import _axes_px, _draw_pixels, _px_figure

    rng = np.random.default_rng(11)
    rgba = rng.integers(0, 256, (37, 53, 4), dtype=np.uint8)
    rgba[..., 3] = 255
    rgba[:5, :7, 3] = 0  # no data: the axes' face shows through (the previews' alpha is 0 or 255)
    canvases = []
    for draw in ("imshow", "pixels"):
        fig = _px_figure(53 * zoom + 90, 37 * zoom + 70)
        ax = _axes_px(fig, 50, 30, 53 * zoom, 37 * zoom)
        ax.set_facecolor("#808080")
        extent = (0, 53 * 2, 37 * 2, 0)
        if draw == "imshow":
            ax.imshow(rgba, extent=extent, interpolation="nearest", resample=False)
        else:
            _draw_pixels(ax, rgba, extent, zoom)
        ax.set_title("t")
        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        canvases.append(np.asarray(canvas.buffer_rgba()).copy())
    np.testing.assert_array_equal(canvases[0], canvases[1])


@pytest.mark.parametrize("channels", [3, 4])
def test_write_png_reads_back(tmp_path, channels):
    from rsmb.pipeline.report._png import write_png

    rng = np.random.default_rng(12)
    pixels = rng.integers(0, 256, (29, 41, channels), dtype=np.uint8)
    assert write_png(pixels, tmp_path / "a.png") == {"size": (41, 29)}
    with Image.open(tmp_path / "a.png") as im:
        assert im.mode == ("RGB" if channels == 3 else "RGBA")
        np.testing.assert_array_equal(np.asarray(im), pixels)
