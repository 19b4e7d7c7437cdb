"""GIS products of a run: Cloud-Optimised GeoTIFFs and change polygons.

DESIGN.md, "Survey archives": per capture, the masks and the score as
Cloud-Optimised GeoTIFFs (overviews, nodata, band description) and
``changes.gpkg``, layer ``changes``: one MultiPolygon per change in the capture's
CRS with the fields ``pixels``, ``area_m2``, ``mean_score`` and ``peak_score``.
Both are written aside (a hidden temporary directory next to the target) and
renamed into place, so a reader never sees a half-written file.

Area rule (``area_m2``): for a projected CRS, the polygon's planar area
(shapely) in square metres (the CRS's linear unit converted to metres): pixel
count times the pixel's area, the area on the map projection, which differs
from the ground area by the projection's scale (for UTM, at most about 0.1 %).
For a geographic CRS, the polygon's geodesic area on the CRS's ellipsoid
(``pyproj.Geod.geometry_area_perimeter``, vertices joined by geodesics).
Without a CRS, ``area_m2`` is NaN.

The polygons are shapely geometries; their WKB is shapely's.
"""

from __future__ import annotations

import datetime
import os
import tempfile
import threading
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from rsmb.ops import label_components
from rsmb.ops._errors import InputError, ParameterError

from ._gdal import quiet_gdal
from ._io import GeoInfo, write_geotiff
from ._store_atomic import swap_into_place

__all__ = ["ChangePolygon", "change_polygons", "write_changes_gpkg", "write_cog"]

#: Internal tile size of the COGs; overviews are made down to one block.
COG_BLOCK = 512
#: Layer name and fields of ``changes.gpkg`` (DESIGN.md contract).
CHANGES_LAYER = "changes"
CHANGES_FIELDS = ("pixels", "area_m2", "mean_score", "peak_score")


# ---------------------------------------------------------------------- writing aside


def _check_absent(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise InputError(f"{path}: output exists; pass --overwrite to replace it")


def _aside(final: Path) -> tempfile.TemporaryDirectory:
    return tempfile.TemporaryDirectory(prefix=f".{final.name}.", suffix=".partial", dir=final.parent)


# -------------------------------------------------------------------------- COG


def write_cog(
    path: str | os.PathLike,
    array,
    geo: GeoInfo,
    *,
    nodata: float | None = None,
    description: str | None = None,
    overwrite: bool = False,
    overview_resampling: str | None = None,
) -> Path:
    """Write a single-band Cloud-Optimised GeoTIFF (GDAL's COG driver).

    Parameters
    ----------
    path : str or path-like
        The file to write.
    array : ndarray or zarr array, shape (H, W)
        bool or uint8 (written as uint8) or floating (written as float32); read in
        strips of 256 rows, never whole.
    geo : GeoInfo
        CRS and transform to record (may be empty).  ``geo.nodata`` is not used.
    nodata : float, optional
        Nodata value to record (``float("nan")`` for a score whose NaN means no data).
    description : str, optional
        Band description (e.g. ``"change_score"``).
    overwrite : bool
        Replace an existing file.
    overview_resampling : str, optional
        GDAL resampling of the overviews; default ``"nearest"`` for uint8/bool
        (masks stay 0/1) and ``"average"`` for floating arrays.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    InputError
        ``path`` exists and ``overwrite`` is False (checked before writing anything).
    ParameterError
        ``array`` not 2-D or of another dtype.

    Notes
    -----
    512 x 512 internal tiles, deflate with a predictor, overviews halving down to
    one tile (so an image larger than 512 px on a side has at least one).  The COG
    driver only copies an existing dataset: a tiled GTiff is written first in a
    temporary directory next to ``path``, copied to a COG there and renamed.
    """
    from rasterio.shutil import copy

    final = Path(path)
    _check_absent(final, overwrite)
    if not hasattr(array, "dtype"):
        array = np.asarray(array)
    dtype = np.dtype(array.dtype)
    if overview_resampling is None:
        overview_resampling = "average" if dtype.kind == "f" else "nearest"
    with _aside(final) as tmp:
        # uncompressed: the COG driver reads it once and compresses what it writes
        plain = write_geotiff(Path(tmp) / "plain.tif", array, geo, nodata=nodata,
                              description=description, compress=None)
        cog = Path(tmp) / final.name
        copy(plain, cog, driver="COG", blocksize=COG_BLOCK, compress="DEFLATE",
             predictor="YES", overviews="AUTO", overview_resampling=overview_resampling.upper(),
             bigtiff="IF_SAFER")
        swap_into_place(cog, final, overwrite=overwrite)
    return final


# --------------------------------------------------------------------- polygons


class ChangePolygon(NamedTuple):
    """One connected change component as a (multi)polygon with its measures.

    Attributes
    ----------
    label : int
        Component number, 1..n in raster order of first pixel.
    polygons : tuple
        MultiPolygon coordinates: polygons, each a tuple of rings (exterior first,
        then holes), each ring a tuple of (x, y) in CRS units (pixel-corner
        coordinates when the raster has no transform).
    pixels : int
        Pixel count of the component.
    area_m2 : float
        Area in square metres (module docstring: area rule); NaN without a CRS.
    mean_score, peak_score : float
        Mean and maximum of the score over the component's pixels with a finite
        score; NaN when there is none.
    """

    label: int
    polygons: tuple
    pixels: int
    area_m2: float
    mean_score: float
    peak_score: float


def change_polygons(mask, score, geo: GeoInfo) -> list[ChangePolygon]:
    """One MultiPolygon per connected component of a change mask.

    Parameters
    ----------
    mask : ndarray or zarr array, shape (H, W), bool or uint8
        The cleaned change mask: 1 (True) change, 0 none, 255 no evidence
        (not a change); every component is kept.
    score : ndarray or zarr array, shape (H, W), float
        The change score; NaN = no data.
    geo : GeoInfo
        Georeferencing of the grid (the polygons are in its CRS units).

    Returns
    -------
    list of ChangePolygon
        One per 8-connected component (the connectivity of
        :func:`rsmb.ops.label_components`), in label order.  A component joined
        only through a diagonal is one MultiPolygon of 4-connected parts, so
        ``len(result)`` equals the component count.

    Notes
    -----
    Loads the mask and the score whole: memory about 9 bytes per pixel.
    """
    mask = np.asarray(mask[...]) if not isinstance(mask, np.ndarray) else mask
    score = np.asarray(score[...], dtype=np.float32)
    if mask.ndim != 2 or mask.shape != score.shape:
        raise ParameterError(f"mask, score: expected two arrays of one shape (H, W), "
                             f"got {mask.shape} and {score.shape}")
    labels, pixels, _ = label_components(mask == 1, score)
    n = len(pixels) - 1
    if n == 0:
        return []
    mean, peak = _score_stats(labels, score, n)
    parts = _component_parts(labels, geo)
    areas = _areas(parts, pixels, geo)
    return [ChangePolygon(k, parts[k], int(pixels[k]), float(areas[k]), float(mean[k]), float(peak[k]))
            for k in range(1, n + 1)]


def _score_stats(labels: np.ndarray, score: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and max of the finite scores per label (index 0 = background)."""
    ok = (labels > 0) & np.isfinite(score)
    lab, val = labels[ok], score[ok].astype(np.float64)
    count = np.bincount(lab, minlength=n + 1)
    total = np.bincount(lab, weights=val, minlength=n + 1)
    peak = np.full(n + 1, -np.inf)
    np.maximum.at(peak, lab, val)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count
    mean[count == 0] = np.nan
    peak[count == 0] = np.nan
    return mean, peak


def _component_parts(labels: np.ndarray, geo: GeoInfo) -> dict[int, tuple]:
    """Polygons of each label, grouped per label (4-connected parts)."""
    from rasterio.features import shapes
    from rasterio.transform import Affine

    affine = Affine(*geo.transform) if geo.transform is not None else Affine.identity()
    parts: dict[int, list] = {}
    for geom, value in shapes(labels, mask=labels > 0, connectivity=4, transform=affine):
        rings = tuple(tuple((float(x), float(y)) for x, y in ring) for ring in geom["coordinates"])
        parts.setdefault(int(value), []).append(rings)
    return {k: tuple(v) for k, v in parts.items()}


def _areas(parts: dict[int, tuple], pixels: np.ndarray, geo: GeoInfo) -> np.ndarray:
    """Area in m^2 per label (index 0 unused), by the module's area rule."""
    import pyproj

    areas = np.full(len(pixels), np.nan)
    if geo.crs is None or geo.transform is None:
        return areas
    crs = pyproj.CRS.from_user_input(geo.crs)
    if crs.is_geographic:
        geod = crs.get_geod()
        for k, polys in parts.items():
            areas[k] = abs(geod.geometry_area_perimeter(_geometry(polys))[0])
        return areas
    unit = float(crs.axis_info[0].unit_conversion_factor) if crs.axis_info else 1.0
    for k, polys in parts.items():
        areas[k] = _geometry(polys).area * unit * unit
    return areas


def _geometry(polygons: tuple):
    """The shapely MultiPolygon of :attr:`ChangePolygon.polygons`."""
    from shapely.geometry import MultiPolygon

    return MultiPolygon([(rings[0], rings[1:]) for rings in polygons])


# --------------------------------------------------------------------- GeoPackage


def write_changes_gpkg(
    path: str | os.PathLike,
    features: Sequence[ChangePolygon],
    crs: str | None,
    *,
    last_change: float | None = None,
    overwrite: bool = False,
) -> Path:
    """Write change polygons as a GeoPackage, layer ``changes``.

    Parameters
    ----------
    path : str or path-like
        The ``.gpkg`` file to write.
    features : sequence of ChangePolygon
        From :func:`change_polygons`; may be empty (an empty layer with the fields
        is written).
    crs : str or None
        The capture's CRS (WKT or ``"EPSG:..."``); None leaves it undefined.
    last_change : float, optional
        POSIX time recorded as ``gpkg_contents.last_change``; None records the
        time of writing.  A fixed time makes the file a function of its
        features only: the same features give the same bytes.
    overwrite : bool
        Replace an existing file.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    InputError
        ``path`` exists and ``overwrite`` is False (checked before writing anything).

    Notes
    -----
    Geometry type MultiPolygon, one feature per component; fields ``pixels``
    (int64), ``area_m2``, ``mean_score``, ``peak_score`` (float64, NaN written as
    NULL).  Written with pyogrio from shapely's ISO WKB, so geopandas is not
    needed; pyogrio's INFO line about it ("Created N records") is demoted to
    DEBUG (:func:`quiet_gdal`).
    """
    import shapely
    from pyogrio.raw import write

    final = Path(path)
    _check_absent(final, overwrite)
    geometry = np.array([shapely.to_wkb(_geometry(f.polygons), flavor="iso", byte_order=1) for f in features] or [],
                        dtype=object)
    field_data = [
        np.array([f.pixels for f in features], dtype=np.int64),
        np.array([f.area_m2 for f in features], dtype=np.float64),
        np.array([f.mean_score for f in features], dtype=np.float64),
        np.array([f.peak_score for f in features], dtype=np.float64),
    ]
    with _aside(final) as tmp:
        out = Path(tmp) / final.name
        with quiet_gdal(), _gpkg_date(last_change):
            write(str(out), geometry, field_data, list(CHANGES_FIELDS), layer=CHANGES_LAYER,
                  driver="GPKG", geometry_type="MultiPolygon", crs=crs)
        swap_into_place(out, final, overwrite=overwrite)
    return final


#: pyogrio's GDAL configuration is process-wide: one GeoPackage date at a time.
_GPKG_DATE_LOCK = threading.Lock()


class _gpkg_date:
    """Scope in which GDAL's GeoPackage driver stamps ``stamp`` (POSIX time)
    as every date it writes (GDAL's ``OGR_CURRENT_DATE``); None changes nothing."""

    def __init__(self, stamp):
        self.value = None if stamp is None else datetime.datetime.fromtimestamp(
            stamp, datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"

    def __enter__(self):
        if self.value is not None:
            from pyogrio import set_gdal_config_options

            _GPKG_DATE_LOCK.acquire()
            set_gdal_config_options({"OGR_CURRENT_DATE": self.value})

    def __exit__(self, *exc):
        if self.value is not None:
            from pyogrio import set_gdal_config_options

            set_gdal_config_options({"OGR_CURRENT_DATE": None})
            _GPKG_DATE_LOCK.release()
