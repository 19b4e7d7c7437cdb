"""The outputs of a detect run: checked before any work starts (writable, not
there already without ``--overwrite``), a finished store recognised for
``--resume``, and the rasters as Cloud-Optimised GeoTIFFs, written aside and
renamed into place."""

import logging
import os
from pathlib import Path

import numpy as np

from rsmb import tiles
from rsmb.ops import InputError

__all__ = []

log = logging.getLogger("rsmb")


GEOTIFFS = ("change_mask.tif", "change_mask_reference.tif", "change_score.tif")
MASK_NODATA = 255


def _check_outputs(output, geotiff, overwrite):
    """Refuse outputs that cannot be written or that exist without
    ``overwrite``, before any work starts."""
    tiles.repair_interrupted_overwrite(output)
    if os.path.lexists(output) and not overwrite:
        raise InputError(f"{output}: output exists; pass --overwrite to replace it")
    tiles.check_writable(output)
    if geotiff is None:
        return
    directory = Path(geotiff)
    if os.path.lexists(directory) and not directory.is_dir():
        raise InputError(f"{directory}: --geotiff must be a directory, this is a file")
    for name in GEOTIFFS:
        if os.path.lexists(directory / name) and not overwrite:
            raise InputError(f"{directory / name}: exists; pass --overwrite to replace it")
    tiles.check_writable(directory / GEOTIFFS[0])


def _finished(output, key):
    """The summary of a finished store at ``output`` made by the run ``key`` (a
    ``--resume`` of it is complete already), else None; a finished store of
    another run is refused."""
    if not tiles.is_complete_store(output):
        return None
    attrs = tiles.open_result_store(output).attrs.asdict()
    if attrs.get("run_key") != key:
        raise InputError(f"{output}: finished by a run with other inputs or parameters; pass --overwrite "
                         f"instead of --resume to replace it")
    log.info("%s: already complete", output)
    return attrs["summary"]


class _Known:
    """``array[rows]`` (strips of a zarr array) with ``fill`` where the
    registration is unknown (``registered`` is NaN): the no-data of a raster
    product."""

    def __init__(self, array, registered, fill):
        self.array, self.registered, self.fill = array, registered, fill
        self.shape, self.dtype = array.shape, array.dtype

    def __getitem__(self, key):
        values = np.asarray(self.array[key])
        return np.where(np.isfinite(self.registered[key]), values, self.fill).astype(self.dtype)


def write_products(store, directory, reference_geo, capture_geo, *, overwrite=False):
    """The masks and the score as Cloud-Optimised GeoTIFFs in ``directory``
    (:data:`GEOTIFFS`: overviews, band descriptions, no-data 255 for the masks
    and NaN for the score where the registration is unknown), each written
    aside and renamed into place.  Returns the paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    group = tiles.open_result_store(store)
    registered = group["registered"]
    products = {"change_mask.tif": ("change_mask", capture_geo, MASK_NODATA),
                "change_mask_reference.tif": ("change_mask_reference", reference_geo, MASK_NODATA),
                "change_score.tif": ("change_score", capture_geo, float("nan"))}
    paths = []
    for name in GEOTIFFS:
        array, geo, nodata = products[name]
        paths.append(tiles.write_cog(directory / name, _Known(group[array], registered, nodata), geo, nodata=nodata,
                                     description=array, overwrite=overwrite))
    return paths
