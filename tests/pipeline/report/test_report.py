"""Tests of pipeline.report._report: the HTML report of one detect run."""

import re
import xml.etree.ElementTree as ET
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
SVG = "{http://www.w3.org/2000/svg}"


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


def _svg_size(path):
    """Width and height of an SVG file (which must parse as XML, with a
    viewBox of the same size)."""
    root = ET.parse(path).getroot()
    assert root.tag == f"{SVG}svg"
    size = (int(root.get("width")), int(root.get("height")))
    assert root.get("viewBox") == f"0 0 {size[0]} {size[1]}"
    return size


def _size(path):
    return _svg_size(path) if path.suffix == ".svg" else _png_size(path)


def _score_frame(page):
    """The inline ``<svg>`` of the change score in a report page, parsed."""
    match = re.search(r'<svg class="figure".*?</svg>', page, re.S)
    assert match, "no score frame in the page"
    return ET.fromstring(match.group(0))


# --------------------------------------------------------------------------- the report


def test_report_has_every_figure(store, tmp_path):
    index = write_report(store, tmp_path / "rep")
    assert index == tmp_path / "rep" / "index.html"
    page = index.read_text(encoding="utf-8")
    attrs = zarr.open_group(str(store), mode="r").attrs.asdict()
    for name in FIGURES:
        assert f'src="{name}"' in page or f'<image href="{name}"' in page
        w, h = _size(tmp_path / "rep" / name)
        assert 100 <= w <= 2000 and 100 <= h <= 2000
        if name != "change_score.png":  # drawn inside its frame, sized there
            assert re.search(f'<img src="{name}"[^>]* width="{w}" height="{h}"', page)
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
    (out / "trajectory.png").write_bytes(b"an earlier version's figure")
    assert write_report(store, out, overwrite=True).is_file()
    assert (out / "notes.txt").read_text() == "kept"
    assert not (out / "trajectory.png").exists()  # replaced by trajectory.svg, not left to look current


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
    """Two reports at once in threads: no global state (matplotlib lends only its colormaps)."""
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
    _, flat_height = _svg_size(tmp_path / "flat" / "trajectory.svg")
    assert _panel_labels(tmp_path / "flat" / "trajectory.svg") == ["tx (px)", "ty (px)", "rz (deg)"]
    assert "Not drawn, zero on every row: rx (deg), ry (deg)" in _svg_texts(tmp_path / "flat" / "trajectory.svg")

    per_tile[5, 0, 3] = 0.01  # rx moves in one tile on one row: drawn again
    group["tile_trajectory"][:] = per_tile
    page = write_report(copy, tmp_path / "rx").read_text(encoding="utf-8")
    assert "No panel for ry (deg): zero on every row" in page
    _, rx_height = _svg_size(tmp_path / "rx" / "trajectory.svg")
    assert rx_height > flat_height
    assert _panel_labels(tmp_path / "rx" / "trajectory.svg") == ["tx (px)", "ty (px)", "rz (deg)", "rx (deg)"]


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


def test_score_values_are_pixels_of_the_png(tmp_path):
    """A small score map is written one value per PNG pixel, each exactly its
    colormap colour, and shown ``zoom`` times larger without smoothing."""
    from matplotlib import colormaps

    from rsmb.pipeline.report._report_figures import _write_score

    score = np.zeros((40, 60), np.float32)
    score[10:20, 30:50] = 0.37
    score[0, 0] = np.nan
    entry = _write_score({"change_score": score}, {"summary": {"threshold": 0.25}}, 1, tmp_path / "s.png")
    assert entry["vmax"] == pytest.approx(0.5)  # twice the threshold, above every score
    rgb = np.asarray(Image.open(tmp_path / "s.png").convert("RGB"))
    assert rgb.shape == (40, 60, 3) and entry["size"] == (60, 40)
    with np.errstate(invalid="ignore"):
        expected = colormaps["inferno"].with_extremes(bad="white")(score / np.float32(0.5), bytes=True)[..., :3]
    np.testing.assert_array_equal(rgb, expected)
    assert tuple(rgb[0, 0]) == (255, 255, 255)  # unknown: white
    assert entry["zoom"] == 512 // 40
    image = ET.fromstring(entry["frame"]).find(f"{SVG}image")
    assert image.get("href") == "s.png"
    assert (int(image.get("width")), int(image.get("height"))) == (60 * 12, 40 * 12)
    assert "pixelated" in image.get("style")


def _colorbar_threshold(frame):
    """The threshold as drawn: the cyan line's height up the colour gradient,
    in units of the bar (0 at the bottom, 1 at vmax)."""
    bar = next(r for r in frame.iter(f"{SVG}rect") if r.get("fill", "").startswith("url(#"))
    y0, height = float(bar.get("y")), float(bar.get("height"))
    cyan = [p for p in frame.iter(f"{SVG}path") if p.get("stroke") == "cyan"]
    assert len(cyan) == 1
    y = float(re.match(r"M[-\d.]+ ([-\d.]+)h", cyan[0].get("d")).group(1))
    return (y0 + height - y) / height, height


def test_score_colorbar_marks_the_threshold(store, tmp_path):
    """The page draws the score PNG in a frame whose colorbar goes from 0 to
    vmax and carries a cyan line at the store's threshold, with tick labels."""
    page = write_report(store, tmp_path / "rep").read_text(encoding="utf-8")
    attrs = zarr.open_group(str(store), mode="r").attrs.asdict()
    threshold = attrs["summary"]["threshold"]
    frame = _score_frame(page)
    w, h = _png_size(tmp_path / "rep" / "change_score.png")
    assert (w, h) == (SHAPE[1], SHAPE[0])  # small: one full-resolution value per PNG pixel
    image = frame.find(f"{SVG}image")
    assert image.get("href") == "change_score.png"
    zoom = int(image.get("width")) // w
    assert zoom == 2 and int(image.get("height")) == h * zoom
    score = zarr.open_group(str(store), mode="r")["change_score"][:]
    from rsmb.pipeline.report._report_figures import _score_vmax

    vmax = _score_vmax(score, threshold)
    level, height = _colorbar_threshold(frame)
    assert level == pytest.approx(threshold / vmax, abs=0.15 / height)
    texts = [t.text for t in frame.iter(f"{SVG}text")]
    assert "Change score" in texts and "column (px)" in texts and "row (px)" in texts
    assert any("cyan line: threshold" in t for t in texts)
    bar_ticks = [float(t.replace("\u2212", "-")) for t in texts if re.fullmatch(r"[\d.]+", t) and "." in t]
    assert bar_ticks[0] == 0.0 and max(bar_ticks) <= vmax
    assert "Threshold" in page and "cyan line on the colorbar" in page


def test_score_frame_without_threshold_has_no_mark(tmp_path):
    from rsmb.pipeline.report._report_figures import _write_score

    score = np.linspace(0, 1, 64 * 64, dtype=np.float32).reshape(64, 64)
    entry = _write_score({"change_score": score}, {"summary": {}}, 1, tmp_path / "s.png")
    frame = ET.fromstring(entry["frame"])
    assert not [p for p in frame.iter(f"{SVG}path") if p.get("stroke") == "cyan"]
    assert not any("threshold" in (t.text or "") for t in frame.iter(f"{SVG}text"))


# --------------------------------------------------------------------------- the trajectory as SVG


def _svg_texts(path):
    return [t.text for t in ET.parse(path).getroot().iter(f"{SVG}text")]


def _panels(path):
    return [g for g in ET.parse(path).getroot().iter(f"{SVG}g") if g.get("class") == "panel"]


def _panel_labels(path):
    """Each panel's axis label: its one rotated text."""
    return [next(t.text for t in g.iter(f"{SVG}text") if t.get("transform")) for g in _panels(path)]


def _polylines(panel):
    """(stroke colour, [(x, y), ...]) of every polyline of a panel."""
    out = []
    for g in panel.iter(f"{SVG}g"):
        for line in g.findall(f"{SVG}polyline"):
            pts = [tuple(map(float, p.split(","))) for p in line.get("points").split()]
            out.append((g.get("stroke"), pts))
    return out


@pytest.fixture
def trajectory_store(tmp_path):
    """A store with only what the trajectory figure reads: 300 rows, 2 tile
    columns, tile rows split at row 128; tx a ramp, ty zero everywhere, rz a
    sine; tile column 1 unsolved on rows 100-119 and on row 200 alone."""
    rows = np.arange(300, dtype=np.float64)
    traj = np.zeros((300, 3))
    traj[:, 0] = -3.0 + 0.02 * rows
    traj[:, 2] = 0.5 * np.sin(rows / 40.0)
    per_tile = np.repeat(traj[:, None, :], 2, axis=1)
    per_tile[:, 1, 2] += 0.05
    per_tile[100:120, 1] = np.nan
    per_tile[200, 1] = np.nan
    group = zarr.open_group(str(tmp_path / "t.zarr"), mode="w")
    group.create_array("trajectory", data=traj).attrs.update({"pose_axes": ["tx", "ty", "rz"],
                                                              "units": ["px", "px", "deg"]})
    group.create_array("tile_trajectory", data=per_tile)
    attrs = {"tile_grid": {"row_edges": [0, 128, 300], "col_edges": [0, 100, 200], "tiles": [2, 2]}}
    return group, attrs, traj


def test_trajectory_svg_panels_lines_and_note(trajectory_store, tmp_path):
    """One panel per axis not zero on every row, in order; in each the fused
    path (black, one line) and each tile column's path, broken where it is
    NaN; one dashed tile-row boundary; the note names the flat axis."""
    from rsmb.pipeline.report._report_figures import _write_trajectory

    group, attrs, traj = trajectory_store
    entry = _write_trajectory(group, attrs, tmp_path / "t.svg")
    assert entry["flat_axes"] == ["ty (px)"]
    assert _svg_size(tmp_path / "t.svg") == entry["size"]
    assert _panel_labels(tmp_path / "t.svg") == ["tx (px)", "rz (deg)"]
    texts = _svg_texts(tmp_path / "t.svg")
    assert "Not drawn, zero on every row: ty (px)" in texts
    assert "row (px); dashed: tile-row boundaries" in texts
    assert {"fused", "tile column 0", "tile column 1"} <= set(texts)  # the legend
    for panel in _panels(tmp_path / "t.svg"):
        lines = _polylines(panel)
        by_colour = {}
        for colour, pts in lines:
            by_colour.setdefault(colour, []).append(pts)
        assert len(by_colour["#000"]) == 1  # fused: one unbroken line
        assert len(by_colour["#1f77b4"]) == 1  # tile column 0
        assert len(by_colour["#ff7f0e"]) == 3  # tile column 1: rows 0-99, 120-199, 201-299
        xs = [pts[0][0] for pts in by_colour["#ff7f0e"]] + [pts[-1][0] for pts in by_colour["#ff7f0e"]]
        assert len(set(xs)) == 6 and min(xs) == 0.0  # the breaks are at different rows
        for _, pts in lines:
            assert all(b[0] > a[0] for a, b in zip(pts, pts[1:]))  # rows increase along a line
            assert all(round(v, 1) == v for p in pts for v in p)  # 0.1 px
        dashed = [p for p in panel.iter(f"{SVG}path") if p.get("stroke-dasharray")]
        assert len(dashed) == 1 and dashed[0].get("d").count("M") == 1  # one tile-row boundary
    ramp = next(pts for colour, pts in _polylines(_panels(tmp_path / "t.svg")[0]) if colour == "#000")
    assert len(ramp) <= 3  # a straight line needs no inner points (chunks of 256 rows)


def test_trajectory_y_ticks_label_the_drawn_values(trajectory_store, tmp_path):
    """The y tick labels are evenly spaced round values whose positions map
    linearly to the values, and the fused path drawn lies where the ticks say
    its values are (within 0.15 px)."""
    from rsmb.pipeline.report._report_figures import _write_trajectory

    group, attrs, traj = trajectory_store
    _write_trajectory(group, attrs, tmp_path / "t.svg")
    panel = _panels(tmp_path / "t.svg")[0]  # tx, a ramp from -3 to 2.98
    ticks = [(float(t.get("y")), float(t.text.replace("\u2212", "-"))) for t in panel.iter(f"{SVG}text")
             if t.get("text-anchor") == "end"]
    assert 3 <= len(ticks) <= 6  # a step of 1, 2, 2.5 or 5 times a power of ten, at most 5 of them
    values = np.array([v for _, v in ticks])
    assert np.allclose(np.diff(values), values[1] - values[0]) and values[1] - values[0] in (1.0, 2.0, 2.5)
    ys = np.array([y for y, _ in ticks])
    slope, offset = np.polyfit(values, ys, 1)
    assert np.allclose(slope * values + offset, ys, atol=0.06)
    fused = next(pts for colour, pts in _polylines(panel) if colour == "#000")
    for x, y in fused:
        row = x * 299 / 889  # the panel is 889 px wide for rows 0..299
        assert y == pytest.approx(slope * traj[int(round(row)), 0] + offset, abs=0.15)


def test_polylines_break_at_nan_and_keep_the_drawn_line():
    """Dropped points lie within the tolerance of the line drawn through the
    kept ones (plus rounding); NaN breaks the line; a lone point is a dot."""
    from rsmb.pipeline.report._report_svg import _TOLERANCE, polylines

    rng = np.random.default_rng(5)
    x = np.arange(700, dtype=np.float64) * 0.87
    y = 50 + 30 * np.sin(x / 90.0) + rng.normal(0, 0.02, x.size)
    y[300:310] = np.nan
    y[500] = y[502] = np.nan  # row 501 alone
    lines = polylines(x, y)
    assert len(lines) == 3 + 1
    pts = [np.array([p.split(",") for p in line.split()], float) for line in lines]
    assert pts[2].shape == (2, 2) and (pts[2][0] == pts[2][1]).all()  # the dot at row 501
    assert pts[2][0][0] == pytest.approx(round(501 * 0.87, 1))
    kept = sum(len(p) for p in pts)
    assert kept < 0.8 * (700 - 12)  # a smooth line loses points
    for p, (lo, hi) in zip([pts[0], pts[1], pts[3]], [(0, 300), (310, 500), (503, 700)]):
        assert p[0][0] == pytest.approx(round(x[lo], 1)) and p[-1][0] == pytest.approx(round(x[hi - 1], 1))
        drawn = np.interp(x[lo:hi], p[:, 0], p[:, 1])
        assert np.abs(drawn - y[lo:hi]).max() <= _TOLERANCE + 0.1 + 1e-9
    straight = polylines(np.arange(1000.0), np.full(1000, 7.25))
    assert len(straight) == 1 and len(straight[0].split()) <= 1000 // 256 + 2


@pytest.mark.parametrize("lo, hi, nbins, expected", [
    (0, 1023, 9, [0, 200, 400, 600, 800, 1000]),
    (0, 2047, 9, [0, 250, 500, 750, 1000, 1250, 1500, 1750, 2000]),
    (-10.9, 10.9, 5, [-10, -5, 0, 5, 10]),
    (0.0, 0.105, 6, [0.0, 0.02, 0.04, 0.06, 0.08, 0.1]),
])
def test_nice_ticks(lo, hi, nbins, expected):
    from rsmb.pipeline.report._report_svg import nice_ticks, tick_labels

    ticks, step = nice_ticks(lo, hi, nbins)
    np.testing.assert_allclose(ticks, expected, atol=1e-12)
    labels = [float(s.replace("\u2212", "-")) for s in tick_labels(ticks, step)]
    np.testing.assert_allclose(labels, expected, atol=1e-12)
    assert len(set(tick_labels(ticks, step))) == len(ticks)


def test_tick_labels_format():
    from rsmb.pipeline.report._report_svg import tick_labels

    assert tick_labels([-2.5, 0.0, 2.5], 2.5) == ["\u22122.5", "0.0", "2.5"]
    assert tick_labels([0.0, 200.0], 200.0) == ["0", "200"]
    assert tick_labels([-1e-17, 0.25], 0.25) == ["0.00", "0.25"]  # no "-0.00"
    assert tick_labels([0.0, 2e-8, 4e-8], 2e-8) == ["0", "2e\u221208", "4e\u221208"]


# --------------------------------------------------------------------------- per-tile maps as SVG


def _cells(path):
    """{(tile_y, tile_x): (fill, text)} of a tile map, from the cell rects and
    the texts centred in them."""
    root = ET.parse(path).getroot()
    rects = [r for g in root.iter(f"{SVG}g") if g.get("shape-rendering") for r in g.findall(f"{SVG}rect")]
    xs = sorted({float(r.get("x")) for r in rects})
    ys = sorted({float(r.get("y")) for r in rects})
    cells = {}
    for r in rects:
        x, y, w, h = (float(r.get(k)) for k in ("x", "y", "width", "height"))
        inside = [t.text for t in root.iter(f"{SVG}text") if t.get("text-anchor") == "middle"
                  and t.get("dominant-baseline") and x < float(t.get("x")) < x + w and y < float(t.get("y")) < y + h]
        cells[ys.index(y), xs.index(x)] = (r.get("fill"), inside[0] if inside else None)
    return cells


def test_tile_maps_write_values_colours_marks_and_tolerance(store, tmp_path):
    """gain.svg and agreement.svg: a cell per tile with its value written in
    it (n/a and grey where unknown), the colormap's colour at the value, the
    re-solved tiles outlined dashed red with a legend, the tolerance as a black
    line on the agreement colorbar."""
    import shutil

    from matplotlib import colormaps

    copy = tmp_path / "maps.zarr"
    shutil.copytree(store, copy)
    group = zarr.open_group(str(copy), mode="r+")
    agree = np.array([[0.1, np.nan], [0.4, 2.5]])
    gain = np.array([[1.0, 1.02], [0.98, 1.01]])
    group["tile_agreement"][:], group["gain"][:] = agree, gain
    summary = dict(group.attrs["summary"])
    summary["resolved_tiles"] = [[1, 1]]
    group.attrs["summary"] = summary
    tolerance = group.attrs["parameters"]["agreement"]
    write_report(copy, tmp_path / "rep")

    cells = _cells(tmp_path / "rep" / "gain.svg")
    assert {k: v[1] for k, v in cells.items()} == {(0, 0): "1.0000", (0, 1): "1.0200", (1, 0): "0.9800",
                                                  (1, 1): "1.0100"}
    top = colormaps["cividis"](1.0, bytes=True)[:3]
    assert cells[0, 1][0] == "#{:02x}{:02x}{:02x}".format(*top)  # the largest gain: the top colour

    cells = _cells(tmp_path / "rep" / "agreement.svg")
    assert cells[0, 1] == ("#d9d9d9", "n/a")
    assert cells[1, 1][1] == "2.50" and cells[0, 0][1] == "0.10"
    root = ET.parse(tmp_path / "rep" / "agreement.svg").getroot()
    dashed_red = [r for r in root.iter(f"{SVG}rect") if r.get("stroke") == "red"]
    assert len(dashed_red) == 1 + 1  # the re-solved tile and the legend's swatch
    texts = [t.text for t in root.iter(f"{SVG}text")]
    assert "re-solved around the other tiles' path" in texts
    assert f"disagreement (px); line: tolerance {tolerance:g} px" in texts
    bar = next(r for r in root.iter(f"{SVG}rect") if r.get("fill", "").startswith("url(#"))
    y0, height = float(bar.get("y")), float(bar.get("height"))
    mark = [p for p in root.iter(f"{SVG}path") if p.get("stroke-width") == "2"]
    assert len(mark) == 1
    y = float(re.match(r"M[-\d.]+ ([-\d.]+)h", mark[0].get("d")).group(1))
    vmax = max(2.5, 1.2 * tolerance)
    assert (y0 + height - y) / height == pytest.approx(tolerance / vmax, abs=0.1 / height)


def test_tile_map_of_equal_values(tmp_path):
    """Every tile the same gain: a range is made around it, every cell gets
    the colormap's middle colour and the colorbar ticks bracket the value."""
    from matplotlib import colormaps

    from rsmb.pipeline.report._report_figures import _write_tile_map

    entry = _write_tile_map(np.ones((3, 2)), tmp_path / "g.svg", cmap="cividis", title="t", label="gain", fmt=".4f")
    assert _svg_size(tmp_path / "g.svg") == entry["size"]
    cells = _cells(tmp_path / "g.svg")
    middle = "#{:02x}{:02x}{:02x}".format(*colormaps["cividis"](0.5, bytes=True)[:3])
    assert len(cells) == 6 and all(v == (middle, "1.0000") for v in cells.values())
    ticks = [float(t.text.replace("\u2212", "-")) for t in ET.parse(tmp_path / "g.svg").getroot().iter(f"{SVG}text")
             if t.get("dominant-baseline") and not t.get("text-anchor") and t.text[0].isdigit()]
    assert len(ticks) >= 2 and min(ticks) <= 1.0 <= max(ticks)
