"""The survey's STAC catalog: ``OUT_DIR/stac/``.

DESIGN.md, "Survey archives".  A root Catalog (``stac/catalog.json``, so that
``pystac.Catalog.from_file`` reads it) holding one Collection (id
:data:`COLLECTION_ID`, ``stac/rsmb-survey/collection.json``) with one Item per
capture and night: the capture's latest
done attempt in the ledger (a capture redone replaces its earlier Item, whose
products no longer exist, and an Item whose products moved, as when a survey
folder of an earlier layout is migrated, is made again; the Items of every
other capture and night are kept).
Written with pystac as a self-contained catalog: every link and asset href is
relative, so the folder can be moved or served as it is.

An Item (id: the capture's folder below ``captures/``, ``/`` as ``__``, then
``__`` and the night):

- geometry and bbox: the capture's nominal footprint (the bounds of its
  ground-frame mask's grid) in WGS 84;
- ``datetime``: the capture's own time, the TIFF ``DateTime`` tag when the file
  has one (read as UTC), else the file's modification time;
  ``rsmb:datetime_source`` says which (``tiff`` or ``mtime``);
- ``proj`` extension (v2): ``proj:code`` (``proj:wkt2`` when the CRS has no
  code), ``proj:shape`` and ``proj:transform`` of that grid, on the Item and on
  each COG asset (each from its own file);
- ``rsmb:capture``, ``rsmb:night``, ``rsmb:run_id``, ``rsmb:changes``,
  ``rsmb:changed_m2``;
- assets: ``change_mask_reference``, ``change_score_reference``,
  ``parallax_mask_reference`` (COGs, all in the ground frame, role ``data``, raster extension ``data_type`` and ``nodata``), ``changes``
  (GeoPackage), ``store`` (the zarr store), ``report`` (its ``index.html``,
  role ``overview``) and ``thumbnail`` (role ``thumbnail``); a product that is
  absent (``--no-report``) has no asset.

So ``odc.stac.load(items, bands=["change_mask_reference"], crs=..., resolution=...,
groupby="rsmb:night")`` mosaics a night's masks onto one grid.  The catalog is
built aside and renamed into place.
"""

from __future__ import annotations

import datetime as _dt
import os
import shutil
from pathlib import Path

from rsmb import tiles

__all__ = ["COLLECTION_ID", "STAC_DIR", "update_catalog", "capture_datetime"]

STAC_DIR = "stac"
COLLECTION_ID = "rsmb-survey"
#: (asset key, file in the capture's folder, media type, roles)
_COGS = ("change_mask_reference", "change_score_reference", "parallax_mask_reference")
_OTHER = (("changes", "changes.gpkg", "application/geopackage+sqlite3", ["data"]),
          ("store", "changes.zarr", "application/vnd+zarr", ["data"]),
          ("report", "report/index.html", "text/html", ["overview"]),
          ("thumbnail", "thumbnail.png", "image/png", ["thumbnail"]))


def capture_datetime(path, fallback):
    """(UTC datetime, source) of a capture: the TIFF ``DateTime`` tag (as UTC), else the file's
    modification time, else ``fallback`` (an ISO 8601 string: the ledger's time) when the file is gone."""
    import rasterio

    try:
        with rasterio.open(path) as ds:
            tag = ds.tags().get("TIFFTAG_DATETIME")
        if tag:
            return _dt.datetime.strptime(tag.strip(), "%Y:%m:%d %H:%M:%S").replace(tzinfo=_dt.timezone.utc), "tiff"
    except (rasterio.errors.RasterioError, ValueError):
        pass
    try:
        return _dt.datetime.fromtimestamp(os.stat(path).st_mtime, _dt.timezone.utc), "mtime"
    except OSError:
        return _dt.datetime.fromisoformat(fallback.replace("Z", "+00:00")), "processed"


def _proj(ds):
    """proj extension fields of an open rasterio dataset."""
    fields = {"proj:shape": [ds.height, ds.width], "proj:transform": list(ds.transform)[:6]}
    epsg = ds.crs.to_epsg() if ds.crs else None
    if epsg:
        fields["proj:code"] = f"EPSG:{epsg}"
    elif ds.crs:
        fields["proj:wkt2"] = ds.crs.to_wkt()
    return fields


def _footprint(ds):
    """(GeoJSON geometry, bbox) of a dataset's bounds in WGS 84 (edges densified)."""
    import shapely
    from rasterio.warp import transform_geom

    box = shapely.segmentize(shapely.box(*ds.bounds), max(ds.res) * 64)
    geometry = transform_geom(ds.crs, "EPSG:4326", shapely.geometry.mapping(box))
    return geometry, list(shapely.bounds(shapely.geometry.shape(geometry)))


def _cog_asset(path, key):
    import pystac
    import rasterio

    with rasterio.open(path) as ds:
        nodata = ds.nodata
        band = {"data_type": ds.dtypes[0]}
        if nodata is not None:
            band["nodata"] = "nan" if nodata != nodata else (int(nodata) if float(nodata).is_integer() else nodata)
        fields = {**_proj(ds), "raster:bands": [band]}
    return pystac.Asset(str(path), title=key, media_type=pystac.MediaType.COG, roles=["data"], extra_fields=fields)


def _item(row, folder, item_id):
    """The Item of a done attempt ``row`` whose products are in ``folder`` (absolute asset hrefs)."""
    import pystac
    import rasterio
    from pystac.extensions.projection import ProjectionExtension
    from pystac.extensions.raster import RasterExtension

    with rasterio.open(folder / "change_mask_reference.tif") as ds:
        geometry, bbox = _footprint(ds)
        proj = _proj(ds)
    when, source = capture_datetime(row.capture, row.finished or row.started)
    outputs = row.outputs
    item = pystac.Item(item_id, geometry, bbox, when, {
        **proj, "rsmb:capture": row.capture, "rsmb:night": row.night, "rsmb:run_id": row.id,
        "rsmb:changes": outputs.get("changes"), "rsmb:changed_m2": outputs.get("changed_m2"),
        "rsmb:datetime_source": source})
    for key in _COGS:
        if (folder / f"{key}.tif").is_file():
            item.add_asset(key, _cog_asset(folder / f"{key}.tif", key))
    for key, name, media, roles in _OTHER:
        if (folder / name).exists():
            item.add_asset(key, pystac.Asset(str(folder / name), title=key, media_type=media, roles=roles))
    ProjectionExtension.add_to(item)
    RasterExtension.add_to(item)
    return item


def _item_id(out, folder, night):
    """The capture's folder below ``out/captures/`` (else below ``out``), ``/`` as ``__``, and the night."""
    base = out / "captures" if Path(folder).is_relative_to(out / "captures") else out
    name = os.path.relpath(folder, base).replace(os.sep, "/")
    return f"{name.replace('/', '__')}__{night}"


def _read(stac):
    """The existing Collection's Items (loaded), or []."""
    import pystac

    path = stac / "catalog.json"
    if not path.is_file():
        return []
    return [item.clone() for item in pystac.Catalog.from_file(str(path)).get_items(recursive=True)]


def update_catalog(out, rows, *, history=None):
    """Write ``OUT_DIR/stac/`` for the done attempts ``rows`` (module docstring: the layout).

    Parameters
    ----------
    out : path-like
        The survey folder.
    rows : sequence of LedgerRow
        The latest done attempt of each capture (an Item is kept or made for each whose folder
        exists; Items of earlier attempts of these captures are dropped).
    history : path-like, optional
        The survey's change history, added as the Collection's asset ``history``.

    Returns
    -------
    pathlib.Path
        ``stac/catalog.json``.
    """
    import pystac

    out = Path(out)
    stac = out / STAC_DIR
    current = {}
    for row in rows:
        folder = Path(row.outputs.get("output") or "")
        folder = folder if folder.is_absolute() else out / folder
        if row.status == "done" and (folder / "change_mask_reference.tif").is_file():
            current[row.capture] = (row, folder)
    items, stored = {}, _read(stac)
    for item in stored:  # kept while its attempt is still the capture's latest done one, where it was
        capture, run_id = item.properties.get("rsmb:capture"), item.properties.get("rsmb:run_id")
        mask = item.assets.get("change_mask_reference")
        if capture in current and current[capture][0].id == run_id and mask is not None and \
                Path(mask.get_absolute_href()) == current[capture][1] / "change_mask_reference.tif":
            for asset in item.assets.values():
                asset.href = asset.get_absolute_href()
            items[capture] = item
    if len(items) == len(stored) == len(current) and (stac / "catalog.json").is_file() and \
            _has_history(stac) == (history is not None and Path(history).is_file()):
        return stac / "catalog.json"  # nothing new: the catalog is as it should be
    for capture, (row, folder) in current.items():
        if capture not in items:
            items[capture] = _item(row, folder, _item_id(out, folder, row.night))
    catalog = pystac.Catalog("rsmb-survey-catalog", "The products of an rsmb survey", title="rsmb survey")
    catalog.add_child(_collection(list(items.values()), history))
    return _save(out, stac, catalog)


def _has_history(stac):
    """Whether the stored Collection has its ``history`` asset."""
    import json

    path = stac / COLLECTION_ID / "collection.json"
    return path.is_file() and "history" in json.loads(path.read_text()).get("assets", {})


def _collection(items, history):
    import pystac

    if items:
        west, south = min(i.bbox[0] for i in items), min(i.bbox[1] for i in items)
        east, north = max(i.bbox[2] for i in items), max(i.bbox[3] for i in items)
        times = sorted(i.datetime for i in items)
        extent = pystac.Extent(pystac.SpatialExtent([[west, south, east, north]]),
                               pystac.TemporalExtent([[times[0], times[-1]]]))
    else:
        extent = pystac.Extent(pystac.SpatialExtent([[-180.0, -90.0, 180.0, 90.0]]),
                               pystac.TemporalExtent([[None, None]]))
    collection = pystac.Collection(COLLECTION_ID, "Captures of an rsmb survey and their change products, "
                                   "one item per capture and night", extent, license="other",
                                   title="rsmb survey")
    for item in sorted(items, key=lambda i: i.id):
        collection.add_item(item)
    if history is not None and Path(history).is_file():
        collection.add_asset("history", pystac.Asset(str(Path(history).absolute()), title="change history",
                                                     media_type="application/geopackage+sqlite3", roles=["data"]))
    return collection


def _save(out, stac, catalog):
    """The catalog built in ``.stac.partial`` (same depth as ``stac/``: relative hrefs hold) and renamed."""
    import pystac

    aside = out / f".{STAC_DIR}.partial"
    shutil.rmtree(aside, ignore_errors=True)
    catalog.normalize_hrefs(str(aside / "catalog.json"))  # a folder name with a dot reads as a file
    catalog.make_all_asset_hrefs_relative()
    for child in catalog.get_children():
        for asset in child.assets.values():  # the collection's own assets (the history)
            asset.href = os.path.relpath(asset.href, os.path.dirname(child.get_self_href()))
    catalog.save(catalog_type=pystac.CatalogType.SELF_CONTAINED)
    tiles.swap_into_place(aside, stac, overwrite=True)  # the catalog of every night so far replaces the last one
    return stac / "catalog.json"
