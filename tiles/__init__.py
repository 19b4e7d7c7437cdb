"""Geometry and storage: ingest of GeoTIFF/PNG/NPY/zarr, georeferenced pairing of a
capture with a reference set, tile grids, result stores, the seam merge of
per-tile labels and the GIS products (COGs, change polygons in a GeoPackage)."""

from ._georef import (
    Coverage,
    RasterGrid,
    is_georeferenced,
    reference_coverage,
    reference_window,
    resampling_for,
)
from ._grid import Tile, TileGrid
from ._pairing import Pairing, pair_images
from ._ingest import (CellSums, WindowStats, cell_sums, check_stats, ingest_core, overview_from_sums, read_clipped,
                      read_padded)
from ._chunkfiles import ChunkFiles, chunk_files
from ._geo import GeoInfo, write_spatial_coords
from ._sources import expand_references
from ._io import (
    ImageInfo,
    Raster,
    check_same_shape,
    probe_header,
    probe_image,
    read_image,
    read_window,
    write_geotiff,
)
from ._json import jsonable
from ._lock import FileLock, LockBusy, LockError, acquire_lock, lock_holder
from ._luminance import as_float01
from ._products import ChangePolygon, change_polygons, write_changes_gpkg, write_cog
from ._stitch import TileLabels, merge_tile_labels
from ._store import (IMAGE_COMPRESSORS, ArraySpec, create_result_store, open_result_store, update_attrs,
                     write_array)
from ._store_atomic import (
    abort_result_store,
    check_writable,
    finalize_result_store,
    is_complete_store,
    partial_path,
    repair_interrupted_overwrite,
    swap_into_place,
)

__all__ = [
    "IMAGE_COMPRESSORS",
    "RasterGrid",
    "Coverage",
    "Pairing",
    "is_georeferenced",
    "pair_images",
    "reference_coverage",
    "reference_window",
    "resampling_for",
    "Tile",
    "TileGrid",
    "WindowStats",
    "check_stats",
    "ingest_core",
    "CellSums",
    "cell_sums",
    "overview_from_sums",
    "read_clipped",
    "read_padded",
    "ChunkFiles",
    "chunk_files",
    "GeoInfo",
    "ImageInfo",
    "Raster",
    "as_float01",
    "probe_header",
    "probe_image",
    "read_image",
    "read_window",
    "check_same_shape",
    "write_geotiff",
    "write_cog",
    "ChangePolygon",
    "change_polygons",
    "write_changes_gpkg",
    "TileLabels",
    "merge_tile_labels",
    "ArraySpec",
    "check_writable",
    "create_result_store",
    "write_array",
    "write_spatial_coords",
    "finalize_result_store",
    "is_complete_store",
    "abort_result_store",
    "open_result_store",
    "partial_path",
    "repair_interrupted_overwrite",
    "swap_into_place",
    "update_attrs",
    "jsonable",
    "FileLock",
    "LockBusy",
    "LockError",
    "acquire_lock",
    "lock_holder",
    "expand_references",
]
