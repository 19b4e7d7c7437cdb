"""The outputs of a detect run: checked before any work starts (writable, not
there already without ``--overwrite``), a finished store recognised for
``--resume``, and the GeoTIFFs written aside and renamed into place."""

import logging
import os
import tempfile
from pathlib import Path

from rsmb import tiles
from rsmb.ops import InputError

__all__ = []

log = logging.getLogger("rsmb")


GEOTIFFS = ("change_mask.tif", "change_mask_reference.tif", "change_score.tif")


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


def _write_geotiffs(store, directory, reference_geo, capture_geo):
    """The masks and the score as GeoTIFFs, each written aside and renamed
    into place."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    group = tiles.open_result_store(store)
    sources = {"change_mask.tif": ("change_mask", capture_geo),
               "change_mask_reference.tif": ("change_mask_reference", reference_geo),
               "change_score.tif": ("change_score", capture_geo)}
    for name in GEOTIFFS:
        array, geo = sources[name]
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tif", dir=directory)
        os.close(fd)
        try:
            tiles.write_geotiff(tmp, group[array], geo)
            os.replace(tmp, directory / name)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
