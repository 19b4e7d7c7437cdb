"""The change history across nights (``OUT_DIR/changes.gpkg``) on capture
folders made by construction: one change appears, persists and goes; another
is seen by two overlapping captures of one night (one feature)."""

import json

import numpy as np
import pyogrio
import pytest
import shapely

from rsmb.pipeline.archive._history import (COVERED, MIN_OVERLAP, HISTORY_NAME, night_time, read_history,
                                            update_history)
from rsmb.pipeline.bench._archive import PIXEL, scene_geo

from .products import done_rows, record_done, write_capture_folder

NIGHTS = ("2026-11-01T21-00-00Z", "2026-11-02T21-00-00Z", "2026-11-03T21-00-00Z")
X = (40, 20, 60, 40)  # appears night 1, persists night 2, gone night 3 (scene rows/cols, end exclusive)
Y = (60, 100, 80, 120)  # night 1, seen by two overlapping captures; never covered again
Z = (90, 50, 110, 70)  # new on night 3
CRS = "EPSG:32618"


def _shift(rect, d):
    return tuple(v + d for v in rect)


def _scene_box(rect):
    """A scene rectangle (rows/cols) as a polygon in the archive's CRS."""
    r0, c0, r1, c1 = rect
    _, _, x0, _, _, y0 = scene_geo().transform
    return shapely.box(x0 + c0 * PIXEL, y0 - r1 * PIXEL, x0 + c1 * PIXEL, y0 - r0 * PIXEL)


# the nights: (capture name, scene origin, shape, changes it sees)
PLAN = {
    NIGHTS[0]: [("a", (0, 0), (128, 128), [X, Y]), ("b", (0, 96), (128, 128), [_shift(Y, 1)])],
    NIGHTS[1]: [("c", (0, 0), (128, 90), [_shift(X, 2)])],
    NIGHTS[2]: [("d", (0, 0), (128, 90), [Z])],
}


def _night(root, night):
    for name, origin, shape, changes in PLAN[night]:
        folder = root / "out" / "captures" / name
        capture = root / "incoming" / f"{name}.tif"
        write_capture_folder(folder, capture, origin, shape, changes)
        record_done(root / "out", capture, folder, night)


def _by_box(history, rect):
    """The one feature of ``history`` overlapping ``rect``."""
    box = _scene_box(rect)
    found = [c for c in history.changes if c.geometry.intersects(box)]
    assert len(found) == 1, found
    return found[0]


@pytest.fixture(scope="module")
def three_nights(tmp_path_factory):
    root = tmp_path_factory.mktemp("history")
    (root / "out").mkdir()
    histories = []
    for night in NIGHTS:
        _night(root, night)
        histories.append(update_history(root / "out", done_rows(root / "out"), night, CRS))
    return root, histories


def test_the_matching_rule_is_a_share_of_the_smaller_polygon():
    """Two 20 x 20 boxes offset along x share (20 - dx) / 20 of either: one change when that share is
    at least MIN_OVERLAP, two otherwise; a box inside a larger one is the same change."""
    from rsmb.pipeline.archive._history import _join, _same

    box = shapely.box(0, 0, 20, 20)
    just_in = 20 * (1 - MIN_OVERLAP) - 0.5
    just_out = 20 * (1 - MIN_OVERLAP) + 0.5
    assert _same(box, shapely.box(just_in, 0, just_in + 20, 20))
    assert not _same(box, shapely.box(just_out, 0, just_out + 20, 20))
    assert _same(box, shapely.box(5, 5, 8, 8)) and not _same(box, shapely.box(30, 0, 40, 10))
    joined = _join([(box, "p"), (shapely.box(just_in, 0, just_in + 20, 20), "q"),
                    (shapely.box(just_out + 40, 0, just_out + 60, 20), "q")])
    assert [c for _, c in joined] == [["p", "q"], ["q"]]


def test_a_change_half_covered_and_not_seen_is_unobserved_not_gone(tmp_path):
    """COVERED of a feature's area must be covered for "not seen" to mean "gone"."""
    (tmp_path / "out").mkdir()
    _night(tmp_path, NIGHTS[0])
    update_history(tmp_path / "out", done_rows(tmp_path / "out"), NIGHTS[0], CRS)
    folder, capture = tmp_path / "out" / "captures" / "f", tmp_path / "incoming" / "f.tif"
    # columns 0..31 with a 2-px no-evidence frame: X (columns 20..39) is covered on columns 20..29 only
    write_capture_folder(folder, capture, (0, 0), (128, 32), [])
    record_done(tmp_path / "out", capture, folder, NIGHTS[1])
    history = update_history(tmp_path / "out", done_rows(tmp_path / "out"), NIGHTS[1], CRS)
    assert 0.4 < 10 / 20 < COVERED and _by_box(history, X).status == "unobserved"


def test_one_change_seen_by_two_overlapping_captures_is_one_feature(three_nights):
    root, (first, _, _) = three_nights
    assert len(first.changes) == 2
    y = _by_box(first, Y)
    assert y.status == "new" and y.nights_seen == 1
    assert y.captures == sorted(str(root / "incoming" / f"{n}.tif") for n in ("a", "b"))
    assert y.first_seen == y.last_seen == night_time(NIGHTS[0]) == "2026-11-01T21:00:00Z"
    # the feature's ground position: the union of both captures' polygons
    assert y.geometry.equals(_scene_box(Y).union(_scene_box(_shift(Y, 1))))
    assert (first.tonight.new, first.tonight.persisting, first.tonight.gone, first.tonight.captures) == (2, 0, 0, 2)


def test_a_change_appears_persists_and_goes(three_nights):
    _, (first, second, third) = three_nights
    x1, x2, x3 = (_by_box(h, X) for h in (first, second, third))
    assert x1.change_id == x2.change_id == x3.change_id
    assert (x1.status, x2.status, x3.status) == ("new", "persisting", "gone")
    assert x2.nights_seen == 2 and x2.last_seen == night_time(NIGHTS[1])
    assert x3.nights_seen == 2 and x3.last_seen == night_time(NIGHTS[1]) and x3.gone_since == night_time(NIGHTS[2])
    assert x2.geometry.equals(_scene_box(_shift(X, 2)))  # the latest observation
    assert (second.tonight.new, second.tonight.persisting, second.tonight.gone) == (0, 1, 0)
    assert (third.tonight.new, third.tonight.persisting, third.tonight.gone) == (1, 0, 1)


def test_a_change_not_covered_since_is_unobserved(three_nights):
    _, (_, second, third) = three_nights
    assert _by_box(second, Y).status == "unobserved" and _by_box(third, Y).status == "unobserved"
    assert _by_box(third, Z).status == "new"
    assert third.tonight.unobserved == 1 and third.tonight.total == 3


def test_the_file_holds_the_history_its_footprints_and_a_layer_per_night(three_nights):
    root, (*_, third) = three_nights
    path = root / "out" / HISTORY_NAME
    layers = sorted(pyogrio.list_layers(path)[:, 0])
    assert layers == sorted(["changes", "footprints", *(f"night_{n}" for n in NIGHTS)])
    info = pyogrio.read_info(path, layer="changes")
    assert info["crs"] == CRS and info["geometry_type"] == "MultiPolygon" and info["features"] == 3
    assert set(info["fields"]) >= {"first_seen", "last_seen", "nights_seen", "captures", "status"}
    again = read_history(path)
    assert [(c.change_id, c.status, c.nights_seen, c.captures) for c in again.changes] == \
           [(c.change_id, c.status, c.nights_seen, c.captures) for c in third.changes]
    assert len(again.footprints) == 4
    _, _, _, fields = pyogrio.raw.read(path, layer=f"night_{NIGHTS[2]}", columns=["status"])
    assert sorted(fields[0]) == ["gone", "new"]
    _, _, _, fields = pyogrio.raw.read(path, layer="changes", columns=["captures"])
    assert all(isinstance(json.loads(v), list) for v in fields[0])


def test_a_night_without_observations_changes_nothing(three_nights):
    root, (*_, third) = three_nights
    path = root / "out" / HISTORY_NAME
    before = path.read_bytes()
    history = update_history(root / "out", done_rows(root / "out"), "2026-11-04T21-00-00Z", CRS)
    assert path.read_bytes() == before
    assert (history.tonight.new, history.tonight.persisting, history.tonight.gone) == (0, 0, 0)


def test_nights_not_taken_in_are_caught_up_in_order(three_nights, tmp_path):
    """All three nights recorded, the history written once: the same history as night by night."""
    _, (*_, third) = three_nights
    (tmp_path / "out").mkdir()
    for night in NIGHTS:
        _night(tmp_path, night)
    history = update_history(tmp_path / "out", done_rows(tmp_path / "out"), NIGHTS[2], CRS)
    assert [(c.change_id, c.status, c.nights_seen, c.first_seen, c.last_seen, c.gone_since)
            for c in history.changes] == \
           [(c.change_id, c.status, c.nights_seen, c.first_seen, c.last_seen, c.gone_since) for c in third.changes]
    assert (history.tonight.new, history.tonight.gone) == (1, 1)


def test_a_night_that_finds_no_change_marks_what_it_covered_gone(tmp_path):
    (tmp_path / "out").mkdir()
    _night(tmp_path, NIGHTS[0])
    update_history(tmp_path / "out", done_rows(tmp_path / "out"), NIGHTS[0], CRS)
    folder, capture = tmp_path / "out" / "captures" / "e", tmp_path / "incoming" / "e.tif"
    write_capture_folder(folder, capture, (0, 0), (128, 90), [])  # covers X, not Y; no change
    record_done(tmp_path / "out", capture, folder, NIGHTS[1])
    history = update_history(tmp_path / "out", done_rows(tmp_path / "out"), NIGHTS[1], CRS)
    assert (_by_box(history, X).status, _by_box(history, Y).status) == ("gone", "unobserved")
    assert (history.tonight.new, history.tonight.gone, history.tonight.captures) == (0, 1, 1)


def test_the_history_is_in_the_reference_crs(tmp_path):
    (tmp_path / "out").mkdir()
    _night(tmp_path, NIGHTS[0])
    history = update_history(tmp_path / "out", done_rows(tmp_path / "out"), NIGHTS[0], "EPSG:3857")
    assert pyogrio.read_info(history.path, layer="changes")["crs"] == "EPSG:3857"
    from pyproj import Transformer

    centre = _scene_box(X).centroid
    expected = Transformer.from_crs(CRS, "EPSG:3857", always_xy=True).transform(centre.x, centre.y)
    # X: the one change capture a saw alone
    x = [c for c in history.changes if c.captures == [str(tmp_path / "incoming" / "a.tif")]]
    assert len(x) == 1
    assert np.allclose([x[0].geometry.centroid.x, x[0].geometry.centroid.y], expected, atol=0.05)


def test_the_map_draws_footprints_and_changes_by_status(three_nights, tmp_path):
    """After night 3 the map holds a new change (red fill) and no persisting one (orange in the legend
    only); the latest night's footprint is outlined in blue."""
    from PIL import Image

    from rsmb.pipeline.archive._survey_map import STATUS_COLOURS, write_map

    _, (*_, third) = three_nights
    rgb = np.asarray(Image.open(write_map(tmp_path / "map.png", third)).convert("RGB")).reshape(-1, 3)

    def present(colour):
        want = np.array([int(colour[i:i + 2], 16) for i in (1, 3, 5)])
        return int((np.abs(rgb.astype(int) - want).max(axis=1) <= 8).sum())

    legend_marker = 200  # the legend's marker of each status is smaller than this many pixels
    assert present(STATUS_COLOURS["new"]) > legend_marker
    assert present(STATUS_COLOURS["persisting"]) < legend_marker
    # the blue outline (antialiased: blue-dominant pixels) is far longer than the legend patch's
    blue = (rgb[:, 2].astype(int) - rgb[:, 0].astype(int) > 80).sum()
    assert blue > 500


def test_an_observation_is_the_union_of_its_mask_polygons(tmp_path):
    """The coverage and the changes read from a ground-frame mask are the union of its polygons: pixels
    that touch only at a corner, holes of no evidence, a change that touches no evidence and one joined
    to another by a diagonal (one 8-connected component, two 4-connected parts)."""
    import rasterio
    from rasterio.features import shapes
    from rasterio.transform import from_origin
    from scipy import ndimage

    from rsmb.pipeline.archive._history import MASK_NODATA, read_observation

    rng = np.random.default_rng(3)
    mask = np.where(rng.random((64, 80)) < 0.03, MASK_NODATA, 0).astype(np.uint8)  # scattered no evidence
    mask[:5, :] = MASK_NODATA  # a collar
    mask[4, 30], mask[5, 30] = 0, MASK_NODATA  # a pixel of evidence that touches the rest at its corners only
    mask[2, 40] = 0  # and one alone
    mask[20:30, 10:20] = MASK_NODATA  # a hole
    mask[40, 40] = mask[41, 41] = 1  # one change of two diagonal parts
    mask[10:16, 50:60] = 1
    mask[12, 55] = MASK_NODATA  # a change with a hole
    mask[50:52, 5:7] = 1
    transform = from_origin(500000.0, 4200000.0, 0.5, 0.5)
    path = tmp_path / "mask.tif"
    with rasterio.open(path, "w", driver="GTiff", width=80, height=64, count=1, dtype="uint8", crs=CRS,
                       transform=transform, nodata=MASK_NODATA) as ds:
        ds.write(mask, 1)

    coverage, changes, _ = read_observation(path)

    valid = mask != MASK_NODATA
    pieces = [shapely.geometry.shape(g) for g, _ in shapes(valid.astype(np.uint8), mask=valid, transform=transform)]
    assert len(pieces) > 1  # corners split the coverage into polygons the union joins
    assert coverage.is_valid and shapely.normalize(coverage).equals_exact(
        shapely.normalize(shapely.union_all(pieces)), 0)
    assert coverage.area == pytest.approx(valid.sum() * 0.25)
    labels, n = ndimage.label(mask == 1, structure=np.ones((3, 3), bool))
    assert len(changes) == n == 3
    parts = {}
    for geom, value in shapes(labels.astype(np.int32), mask=labels > 0, connectivity=4, transform=transform):
        parts.setdefault(int(value), []).append(shapely.geometry.shape(geom))
    for k, change in enumerate(changes, start=1):
        assert change.is_valid and change.area == pytest.approx((labels == k).sum() * 0.25)
        assert shapely.normalize(change).equals_exact(shapely.normalize(shapely.union_all(parts[k])), 0)
    assert changes[1].geom_type == "MultiPolygon"  # the diagonal pair (the second in raster order)


def test_the_maps_imports_ahead_of_the_night_never_raise(monkeypatch):
    """A night imports the map's modules in a thread as its captures start: a broken matplotlib is left
    for the map itself to report."""
    import sys

    from rsmb.pipeline.archive._survey_map import preload

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    preload()
