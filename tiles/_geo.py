"""Georeferencing of a raster: CRS, affine transform and nodata, and their JSON form.

:class:`GeoInfo` is what every input format reports and what the output store
records as GeoZarr-style attributes (:meth:`GeoInfo.to_attrs`).  Strict JSON has no
NaN or infinity, so a non-finite nodata value is written as zarr v3 spells it
(``"NaN"``, ``"Infinity"``, ``"-Infinity"``).

The output store also speaks CF, as rioxarray and odc-geo write it: 1-D ``x`` /
``y`` coordinates of the pixel centres (:func:`pixel_centres`, rotation-free
transforms only) and a ``spatial_ref`` grid-mapping variable
(:func:`cf_grid_mapping`), for the ground-frame arrays (dimensions y, x) only.
Sensor-frame arrays (dimensions row, col: the capture's pixels as the rolling
shutter recorded them) name a ``sensor_frame`` variable as their grid mapping,
which holds no CRS and no transform: rioxarray and GDAL find none for them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from rsmb.ops._errors import ParameterError

from ._json import float_from_json, jsonable

__all__ = ["GeoInfo", "write_spatial_coords"]



@dataclass(frozen=True)
class GeoInfo:
    """Georeferencing of a raster, as far as the input had one.

    Attributes
    ----------
    crs : str or None
        Coordinate reference system as WKT2 (2019), None when the input had none.
    transform : tuple of 6 float or None
        Affine coefficients ``(a, b, c, d, e, f)`` in rasterio's ``Affine`` order:
        ``x = a * col + b * row + c`` and ``y = d * col + e * row + f``, with (col, row)
        pixel-corner coordinates and (x, y) in CRS units.  None when not georeferenced.
    nodata : float or None
        The nodata value of the first band of the input, None when it had none.
    """

    crs: str | None = None
    transform: tuple[float, ...] | None = None
    nodata: float | None = None

    def __post_init__(self) -> None:
        if self.transform is not None:
            coeffs = tuple(float(v) for v in self.transform)
            if len(coeffs) != 6:
                raise ParameterError(
                    f"transform: expected 6 affine coefficients (a, b, c, d, e, f), "
                    f"got {len(coeffs)}"
                )
            object.__setattr__(self, "transform", coeffs)
        if self.nodata is not None:
            object.__setattr__(self, "nodata", float(self.nodata))

    @property
    def is_empty(self) -> bool:
        """True when neither a CRS nor a transform is known."""
        return self.crs is None and self.transform is None

    def to_attrs(self) -> dict[str, Any]:
        """GeoZarr-style attributes, JSON-serialisable.

        Returns
        -------
        dict
            ``"proj:wkt2"`` (WKT2 string) and ``"proj:code"`` (e.g. ``"EPSG:32618"``,
            only when an authority code is found) when a CRS is known;
            ``"spatial:transform"`` (list of 6 floats) and ``"spatial:dimensions"``
            (``["y", "x"]``) when a transform is known; ``"nodata"`` always (None,
            a float, or ``"NaN"`` / ``"Infinity"`` / ``"-Infinity"`` for non-finite
            values, which strict JSON cannot hold).
        """
        attrs: dict[str, Any] = {}
        if self.crs is not None:
            attrs["proj:wkt2"] = self.crs
            code = _crs_code(self.crs)
            if code is not None:
                attrs["proj:code"] = code
        if self.transform is not None:
            attrs["spatial:transform"] = [float(v) for v in self.transform]
            attrs["spatial:dimensions"] = ["y", "x"]
        attrs["nodata"] = jsonable(self.nodata)
        return attrs

    @classmethod
    def from_attrs(cls, attrs: dict[str, Any]) -> GeoInfo:
        """Inverse of :meth:`to_attrs`; missing keys give None.

        ``"proj:wkt2"`` wins over ``"proj:code"``; a code alone is resolved to WKT2
        with rasterio.
        """
        crs = attrs.get("proj:wkt2")
        if crs is None and attrs.get("proj:code") is not None:
            from rasterio.crs import CRS

            crs = CRS.from_user_input(attrs["proj:code"]).to_wkt(version="WKT2_2019")
        transform = attrs.get("spatial:transform")
        nodata = float_from_json(attrs.get("nodata"))
        return cls(
            crs=crs,
            transform=None if transform is None else tuple(transform),
            nodata=nodata,
        )


def _crs_code(wkt: str) -> str | None:
    """``"AUTH:CODE"`` for a WKT CRS, or None when rasterio finds no authority."""
    from rasterio.crs import CRS

    try:
        authority = CRS.from_wkt(wkt).to_authority()
    except Exception:  # noqa: BLE001 - a CRS without a code is fine
        return None
    if authority is None:
        return None
    return f"{authority[0]}:{authority[1]}"


# ------------------------------------------------------- CF coordinates (xarray, rioxarray)


def is_rotation_free(transform: tuple[float, ...]) -> bool:
    """True when the affine transform has no rotation or shear (``b == d == 0``),
    so that x depends on the column alone and y on the row alone."""
    return transform[1] == 0.0 and transform[3] == 0.0


def pixel_centres(transform: tuple[float, ...], shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates of the pixel centres of a rotation-free grid.

    Parameters
    ----------
    transform : tuple of 6 float
        ``(a, b, c, d, e, f)`` as in :class:`GeoInfo`, with ``b == d == 0``.
    shape : tuple of int
        (H, W) in pixels.

    Returns
    -------
    x : ndarray, shape (W,), float64
        ``c + a * (col + 0.5)``, CRS units.
    y : ndarray, shape (H,), float64
        ``f + e * (row + 0.5)``, CRS units.

    Raises
    ------
    ParameterError
        If the transform rotates or shears (1-D coordinates cannot describe it).
    """
    if not is_rotation_free(transform):
        raise ParameterError(
            f"transform: expected no rotation (b = d = 0) for 1-D x/y coordinates, "
            f"got b = {transform[1]:g}, d = {transform[3]:g}"
        )
    a, _, c, _, e, f = (float(v) for v in transform)
    h, w = shape
    return c + a * (np.arange(w) + 0.5), f + e * (np.arange(h) + 0.5)


def cf_xy_attrs(crs: str | None) -> tuple[dict[str, str], dict[str, str]]:
    """CF attributes of the x and y coordinate arrays, as rioxarray writes them.

    Projected CRS: ``standard_name`` ``projection_x_coordinate`` /
    ``projection_y_coordinate`` and ``units`` the CRS's linear unit (``"metre"``,
    or ``"<factor> metre"``); geographic CRS: ``longitude`` / ``latitude`` in
    ``degrees_east`` / ``degrees_north``; no CRS: the axes alone.
    """
    x = {"axis": "X"}
    y = {"axis": "Y"}
    if crs is None:
        return x, y
    from rasterio.crs import CRS

    parsed = CRS.from_user_input(crs)
    if parsed.is_geographic:
        x.update(long_name="longitude", standard_name="longitude", units="degrees_east")
        y.update(long_name="latitude", standard_name="latitude", units="degrees_north")
        return x, y
    x.update(long_name="x coordinate of projection", standard_name="projection_x_coordinate")
    y.update(long_name="y coordinate of projection", standard_name="projection_y_coordinate")
    _, factor = parsed.linear_units_factor
    units = "metre" if factor == 1 else f"{factor:g} metre"
    x["units"] = y["units"] = units
    return x, y


def cf_grid_mapping(geo: GeoInfo) -> dict[str, Any]:
    """Attributes of the CF grid-mapping variable ``spatial_ref``.

    The CF parameters of the CRS from pyproj's ``CRS.to_cf`` (with
    ``grid_mapping_name`` where CF has one), then, as rioxarray and GDAL write
    them, ``crs_wkt`` and ``spatial_ref`` (the WKT of rasterio's ``CRS.to_wkt``)
    and ``GeoTransform`` (the six GDAL coefficients ``c a b f d e``, space
    separated) when a transform is known.

    Raises
    ------
    ParameterError
        If ``geo`` has no CRS.
    """
    if geo.crs is None:
        raise ParameterError("geo: expected a CRS for a CF grid mapping, got none")
    import pyproj
    from rasterio.crs import CRS

    attrs: dict[str, Any] = dict(pyproj.CRS.from_user_input(geo.crs).to_cf())
    wkt = CRS.from_user_input(geo.crs).to_wkt()
    attrs["crs_wkt"] = wkt
    attrs["spatial_ref"] = wkt
    if geo.transform is not None:
        a, b, c, d, e, f = geo.transform
        attrs["GeoTransform"] = " ".join(repr(float(v)) for v in (c, a, b, f, d, e))
    return attrs


def write_spatial_coords(group, geo, shape: tuple[int, int]) -> list[str]:
    """Write the CF coordinates of a georeferenced store, as rioxarray reads them.

    For a rotation-free transform, 1-D float64 arrays ``x`` (W,) and ``y`` (H,)
    of the pixel centres (:func:`pixel_centres`) with ``dimension_names`` ("x",)
    and ("y",) and CF attributes (:func:`cf_xy_attrs`); a rotated or sheared
    transform gets no x/y arrays (1-D coordinates cannot describe it) but keeps
    its ``GeoTransform``.  With a CRS, a scalar int64 array ``spatial_ref`` (value
    0) holding the CF grid mapping (:func:`cf_grid_mapping`), named in the
    ``grid_mapping`` and ``coordinates`` attributes of every array whose
    dimensions are ("y", "x") (``coordinates`` is how xarray keeps a scalar
    coordinate), and, when the store has (row, col) arrays, a scalar
    ``sensor_frame`` named as their grid mapping (:func:`_mark_sensor_frame`).  Then ``xr.open_zarr(store)`` has x/y coordinates and
    ``.rio.crs`` / ``.rio.transform()`` of rioxarray give the input's CRS and
    transform.  Call it before :func:`finalize_result_store` consolidates the
    metadata; existing ``x``, ``y``, ``spatial_ref`` arrays are replaced.

    Parameters
    ----------
    group : zarr.Group
        A writable store, e.g. from :func:`create_result_store`.
    geo : GeoInfo
        The georeferencing of the (y, x) arrays; nothing is written without a
        transform.
    shape : tuple of int
        (H, W) of the (y, x) arrays, pixels.

    Returns
    -------
    list of str
        Names of the arrays written.
    """
    if geo.transform is None:
        return []
    written = []
    if is_rotation_free(geo.transform):
        x, y = pixel_centres(geo.transform, shape)
        for name, values, attrs in zip(("x", "y"), (x, y), cf_xy_attrs(geo.crs)):
            array = group.create_array(name, shape=values.shape, dtype="float64", chunks=values.shape,
                                       dimension_names=(name,), fill_value=float("nan"), overwrite=True)
            array[:] = values
            array.update_attributes(attrs)
            written.append(name)
    if geo.crs is not None:
        ref = group.create_array("spatial_ref", shape=(), dtype="int64", dimension_names=(),
                                 fill_value=0, overwrite=True)
        ref[...] = 0
        ref.update_attributes(jsonable(cf_grid_mapping(geo)))
        written.append("spatial_ref")
        arrays = [array for _, array in group.arrays()]  # each array's metadata read once
        for array in arrays:
            if tuple(array.metadata.dimension_names or ()) == ("y", "x"):
                array.update_attributes({"grid_mapping": "spatial_ref", "coordinates": "spatial_ref"})
        sensor = [array for array in arrays if tuple(array.metadata.dimension_names or ()) == ("row", "col")]
        if sensor:
            written.append(_mark_sensor_frame(group, sensor))
    return written


def _mark_sensor_frame(group, arrays) -> str:
    """A scalar ``sensor_frame`` variable without CRS or transform, named as
    the grid mapping of every (row, col) array: xarray attaches the scalar
    ``spatial_ref`` coordinate to every array of the store, and rioxarray would
    read the ground frame's CRS and GeoTransform from it for a sensor-frame
    array too."""
    frame = group.create_array("sensor_frame", shape=(), dtype="int64", dimension_names=(), fill_value=0,
                               overwrite=True)
    frame[...] = 0
    frame.update_attributes({"long_name": "sensor frame: the capture's pixels as the rolling shutter recorded them, "
                                     "warped against the ground by the camera's motion; no map coordinates",
                        "comment": "the ground frame (dims y, x) has them: see spatial_ref"})
    for array in arrays:
        array.update_attributes({"grid_mapping": "sensor_frame"})
    return "sensor_frame"
