"""Geometry and storage: ingest of GeoTIFF/PNG/NPY/zarr, tile grids, result stores."""

from ._io import GeoInfo, Raster, as_float01, check_same_shape, read_image, read_window, write_geotiff
from ._store import (
    ArraySpec,
    abort_result_store,
    create_result_store,
    finalize_result_store,
    jsonable,
    open_result_store,
    write_array,
)

__all__ = [
    "GeoInfo",
    "Raster",
    "as_float01",
    "read_image",
    "read_window",
    "check_same_shape",
    "write_geotiff",
    "ArraySpec",
    "create_result_store",
    "write_array",
    "finalize_result_store",
    "abort_result_store",
    "open_result_store",
    "jsonable",
]
