"""Georeferencing of a raster: CRS, affine transform and nodata, and their JSON form.

:class:`GeoInfo` is what every input format reports and what the output store
records as GeoZarr-style attributes (:meth:`GeoInfo.to_attrs`).  Strict JSON has no
NaN or infinity, so a non-finite nodata value is written as zarr v3 spells it
(``"NaN"``, ``"Infinity"``, ``"-Infinity"``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from rsmb.ops._errors import ParameterError

_NONFINITE_TO_JSON = {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}
_JSON_TO_NONFINITE = {v: float(k) for k, v in _NONFINITE_TO_JSON.items()}


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
        attrs["nodata"] = _float_to_json(self.nodata)
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
        nodata = attrs.get("nodata")
        if isinstance(nodata, str):
            nodata = _JSON_TO_NONFINITE[nodata]
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


def _float_to_json(value: float | None) -> float | str | None:
    if value is None or math.isfinite(value):
        return value
    return _NONFINITE_TO_JSON[str(float(value))]
