"""The outputs of a detect run: checked before any work starts (writable, not
there already without ``--overwrite``), a finished store recognised for
``--resume``, and the rasters as Cloud-Optimised GeoTIFFs, written aside and
renamed into place."""

import logging
import os
from pathlib import Path

import numpy as np

from rsmb import tiles
from rsmb import ops
from rsmb.ops import InputError

__all__ = []

log = logging.getLogger("rsmb")


#: The GIS rasters, all in the ground frame: each the store's array of its name.
GEOTIFFS = ("change_mask_reference.tif", "change_score_reference.tif", "parallax_mask_reference.tif")
MASK_NODATA = ops.NO_EVIDENCE


def _check_outputs(output, geotiff, overwrite):
    """Refuse outputs that cannot be written or that exist without
    ``overwrite``, before any work starts (an overwrite a killed run left
    half-done repaired first)."""
    tiles.repair_interrupted_overwrite(output)
    check_outputs(output, geotiff, overwrite)


def check_outputs(output, geotiff, overwrite):
    """:func:`_check_outputs`' rules, touching nothing (``rsmb run --check``)."""
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


def ground_geo(pairing_mode, reference_geo, capture_geo):
    """The georeferencing of the ground frame (the reference grid): the
    capture's nominal grid when the pair was paired by georeferencing; the
    reference's own when compared pixel for pixel (the capture's when the
    reference has none: the two grids are the same by assumption)."""
    if pairing_mode == "pixel" and not reference_geo.is_empty:
        return reference_geo
    return capture_geo


def write_products(store, directory, geo, *, overwrite=False):
    """The ground-frame masks and score as Cloud-Optimised GeoTIFFs in
    ``directory`` (:data:`GEOTIFFS`, each the store's array of that name with
    ``geo``: overviews, band descriptions, no-data 255 for the masks and NaN
    for the score, as in the store), each written aside and renamed into place.
    Returns the paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    group = tiles.open_result_store(store)
    paths = []
    for name in GEOTIFFS:
        array = group[name[:-4]]
        nodata = float("nan") if array.dtype.kind == "f" else MASK_NODATA
        paths.append(tiles.write_cog(directory / name, array, geo, nodata=nodata, description=name[:-4],
                                     overwrite=overwrite))
    return paths
