"""The survey's STAC catalog (``OUT_DIR/stac/``) on capture folders made by
construction: read back with pystac, every asset resolving, links relative, a
night's masks loaded with odc.stac onto one grid, earlier items kept."""

import datetime as dt
import json
import os

import numpy as np
import pystac
import pytest

from rsmb.pipeline.archive._stac import COLLECTION_ID, update_catalog
from rsmb.pipeline.bench._archive import PIXEL, scene_geo

from .products import done_rows, record_done, write_capture_folder

NIGHT1, NIGHT2 = "2026-11-01T21-00-00Z", "2026-11-02T21-00-00Z"
# (name, scene origin, shape, changes in scene rows/cols): a and b overlap by 32 columns
NIGHT1_CAPTURES = [("a", (0, 0), (96, 128), [(20, 20, 40, 40), (50, 100, 70, 120)]),
                   ("b", (16, 96), (96, 128), [(50, 100, 70, 120), (60, 180, 80, 200)])]


def _capture(root, night, name, origin, shape, changes, **kw):
    folder = root / "out" / "captures" / "flight" / name
    capture = root / "incoming" / "flight" / f"{name}.tif"
    mask = write_capture_folder(folder, capture, origin, shape, changes, **kw)
    record_done(root / "out", capture, folder, night, changes=len(changes))
    return mask


@pytest.fixture()
def night1(tmp_path):
    (tmp_path / "out").mkdir()
    masks = {}
    for k, (name, origin, shape, changes) in enumerate(NIGHT1_CAPTURES):
        tag = "2026:11:01 21:30:00" if k == 0 else None  # a: TIFF DateTime; b: file time
        masks[name] = _capture(tmp_path, NIGHT1, name, origin, shape, changes, datetime_tag=tag)
    catalog = update_catalog(tmp_path / "out", done_rows(tmp_path / "out"))
    return tmp_path, catalog, masks


def _items(catalog):
    return sorted(pystac.Catalog.from_file(str(catalog)).get_all_items(), key=lambda i: i.id)


def test_the_catalog_reads_back_and_every_asset_resolves(night1):
    root, catalog, _ = night1
    assert catalog == root / "out" / "stac" / "catalog.json"
    (collection,) = pystac.Catalog.from_file(str(catalog)).get_children()
    assert collection.id == COLLECTION_ID and isinstance(collection, pystac.Collection)
    items = _items(catalog)
    assert [i.id for i in items] == [f"flight__{n}__{NIGHT1}" for n in ("a", "b")]
    for item in items:
        assert set(item.assets) == {"change_mask_reference", "change_score_reference", "parallax_mask_reference",
                                    "changes", "store", "report", "thumbnail"}
        for asset in item.assets.values():
            assert not os.path.isabs(asset.href), asset.href
            assert os.path.exists(asset.get_absolute_href()), asset.href
        assert item.assets["thumbnail"].roles == ["thumbnail"]
        assert item.assets["change_mask_reference"].media_type == pystac.MediaType.COG
        assert item.assets["changes"].media_type == "application/geopackage+sqlite3"
        assert item.properties["proj:code"] == "EPSG:32618"
        assert item.properties["rsmb:night"] == NIGHT1
    # every link and asset href in the catalog's files is relative (rsmb:capture records where the capture was)
    def hrefs(node):
        if isinstance(node, dict):
            yield from ([node["href"]] if "href" in node else [])
            for value in node.values():
                yield from hrefs(value)
        elif isinstance(node, list):
            for value in node:
                yield from hrefs(value)

    files = list((root / "out" / "stac").rglob("*.json"))
    assert len(files) == 4  # the root catalog, the collection, two items
    for path in files:
        found = list(hrefs(json.loads(path.read_text())))
        assert found and not any(os.path.isabs(h) or "://" in h for h in found), (path, found)


def test_an_item_has_its_footprint_grid_and_datetime(night1):
    root, catalog, _ = night1
    a, b = _items(catalog)
    (h, w), origin = NIGHT1_CAPTURES[0][2], NIGHT1_CAPTURES[0][1]
    assert a.properties["proj:shape"] == [h, w]
    assert a.properties["proj:transform"] == list(scene_geo(origin).transform)
    # WGS 84 bbox holding the capture's corners (UTM 18N, north of the equator)
    from pyproj import Transformer

    x0, y0 = scene_geo(origin).transform[2], scene_geo(origin).transform[5]
    lon0, lat0 = Transformer.from_crs("EPSG:32618", "EPSG:4326", always_xy=True).transform(x0, y0)
    west, south, east, north = a.bbox
    assert west == pytest.approx(lon0, abs=1e-6) and north == pytest.approx(lat0, abs=1e-6)
    assert east > west and north > south and (east - west) < 0.01
    assert a.datetime == dt.datetime(2026, 11, 1, 21, 30, tzinfo=dt.timezone.utc)
    assert a.properties["rsmb:datetime_source"] == "tiff"
    mtime = os.stat(root / "incoming" / "flight" / "b.tif").st_mtime
    assert b.properties["rsmb:datetime_source"] == "mtime"
    assert b.datetime.timestamp() == pytest.approx(mtime, abs=1e-3)
    mask = a.assets["change_mask_reference"].extra_fields
    assert mask["raster:bands"] == [{"data_type": "uint8", "nodata": 255}]
    assert a.assets["change_score_reference"].extra_fields["raster:bands"] == [{"data_type": "float32", "nodata": "nan"}]
    assert mask["proj:code"] == "EPSG:32618" and mask["proj:shape"] == [h, w]


def test_a_nights_masks_load_with_odc_stac_onto_one_grid(night1):
    import odc.stac

    root, catalog, masks = night1
    data = odc.stac.load(_items(catalog), bands=["change_mask_reference"], crs="EPSG:32618", resolution=PIXEL,
                         groupby="rsmb:night")
    mosaic = data["change_mask_reference"]
    assert mosaic.sizes["time"] == 1 and mosaic.odc.crs == "EPSG:32618"
    # the expected mosaic by construction: the scene's rows 0..112, columns 0..224, first capture with data wins
    expected = np.full((112, 224), 255, np.uint8)
    for name, (r0, c0), (h, w), _ in NIGHT1_CAPTURES:
        window = expected[r0:r0 + h, c0:c0 + w]
        np.copyto(window, masks[name], where=window == 255)
    x0, y0 = scene_geo().transform[2], scene_geo().transform[5]
    assert float(mosaic.x[0]) == pytest.approx(x0 + PIXEL / 2) and float(mosaic.y[0]) == pytest.approx(y0 - PIXEL / 2)
    assert mosaic.shape[1:] == expected.shape
    got = mosaic.isel(time=0).values
    # where both have evidence they agree (the overlap's changes are the same by construction)
    assert np.array_equal(got, expected)


def test_the_next_night_keeps_earlier_items_and_a_redone_capture_replaces_its_own(night1):
    root, catalog, _ = night1
    before = {i.id: json.dumps(i.to_dict(), sort_keys=True) for i in _items(catalog)}
    _capture(root, NIGHT2, "c", (0, 300), (96, 96), [])
    _capture(root, NIGHT2, "a", (0, 0), (96, 128), [])  # a redone: its folder replaced, a new attempt
    catalog = update_catalog(root / "out", done_rows(root / "out"))
    items = {i.id: i for i in _items(catalog)}
    assert sorted(items) == sorted([f"flight__a__{NIGHT2}", f"flight__b__{NIGHT1}",
                                    f"flight__c__{NIGHT2}"])
    b = f"flight__b__{NIGHT1}"
    assert json.dumps(items[b].to_dict(), sort_keys=True) == before[b]
    for item in items.values():
        for asset in item.assets.values():
            assert os.path.exists(asset.get_absolute_href())
    (collection,) = pystac.Catalog.from_file(str(catalog)).get_children()
    west, south, east, north = collection.extent.spatial.bboxes[0]
    assert all(west <= i.bbox[0] and east >= i.bbox[2] for i in items.values())


def test_an_item_whose_products_moved_is_made_again(night1):
    """The ledger records a capture's folder elsewhere (a survey folder migrated to a new layout): its
    item is rebuilt there, with every asset resolving, the other item kept as it was."""
    import shutil
    import sqlite3

    root, catalog, _ = night1
    old = root / "out" / "captures" / "flight" / "a"
    new = root / "out" / "captures" / "flight" / "a.tif"
    shutil.move(old, new)
    with sqlite3.connect(root / "out" / "ledger.sqlite") as db:
        (outputs,) = db.execute("SELECT outputs FROM runs WHERE capture LIKE '%a.tif'").fetchone()
        db.execute("UPDATE runs SET outputs = ? WHERE capture LIKE '%a.tif'",
                   (json.dumps({**json.loads(outputs), "output": str(new)}),))
    before = {i.id: i.to_dict() for i in _items(catalog)}
    items = {i.properties["rsmb:capture"]: i for i in _items(update_catalog(root / "out", done_rows(root / "out")))}
    a, b = items[str(root / "incoming" / "flight" / "a.tif")], items[str(root / "incoming" / "flight" / "b.tif")]
    assert a.assets["change_mask_reference"].get_absolute_href() == str(new / "change_mask_reference.tif")
    assert all(os.path.exists(x.get_absolute_href()) for x in a.assets.values())
    assert b.to_dict() == before[b.id]
