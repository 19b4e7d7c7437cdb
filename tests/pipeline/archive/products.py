"""Capture folders as a survey leaves them, made by construction for the history
and catalog tests: the ground-frame mask COG with known changes, the other COGs,
an empty GeoPackage, a zarr group, a thumbnail and a report page, and the
capture file itself; recorded as done in a real ledger."""

from pathlib import Path

import numpy as np

from rsmb import tiles
from rsmb.pipeline.archive._ledger import LEDGER_NAME, Ledger, RunKey
from rsmb.pipeline.bench._archive import _write, scene_geo

NODATA = 255


def mask_of(shape, origin_yx, changes, *, border=2):
    """uint8 mask of a capture at scene pixel ``origin_yx``: 1 on the scene
    rectangles ``changes`` ((r0, c0, r1, c1), scene pixels, end exclusive) it
    covers, 255 on a ``border``-pixel frame (no evidence), else 0."""
    mask = np.full(shape, NODATA, np.uint8)
    mask[border:shape[0] - border, border:shape[1] - border] = 0
    for r0, c0, r1, c1 in changes:
        r0, r1 = r0 - origin_yx[0], r1 - origin_yx[0]
        c0, c1 = c0 - origin_yx[1], c1 - origin_yx[1]
        r0, c0, r1, c1 = max(r0, border), max(c0, border), min(r1, shape[0] - border), min(c1, shape[1] - border)
        if r0 < r1 and c0 < c1:
            mask[r0:r1, c0:c1] = 1
    return mask


def write_capture_folder(folder, capture, origin_yx, shape, changes, *, datetime_tag=None, report=True):
    """The capture file ``capture`` (a GeoTIFF of the window) and its products
    in ``folder``; returns the mask written."""
    import zarr
    from PIL import Image

    import shutil

    folder, capture = Path(folder), Path(capture)
    shutil.rmtree(folder, ignore_errors=True)  # a capture redone: its folder replaced whole, as the survey does
    folder.mkdir(parents=True)
    capture.parent.mkdir(parents=True, exist_ok=True)
    geo = scene_geo(origin_yx)
    _write(capture, np.full(shape, 0.5, np.float32), geo)
    if datetime_tag:
        import rasterio

        with rasterio.open(capture, "r+") as ds:
            ds.update_tags(TIFFTAG_DATETIME=datetime_tag)
    mask = mask_of(shape, origin_yx, changes)
    score = np.where(mask == NODATA, np.nan, mask.astype(np.float32))
    tiles.write_cog(folder / "change_mask_reference.tif", mask, geo, nodata=NODATA)
    tiles.write_cog(folder / "change_score_reference.tif", score, geo, nodata=float("nan"))
    tiles.write_cog(folder / "parallax_mask_reference.tif", np.where(mask == NODATA, NODATA, 0).astype(np.uint8),
                    geo, nodata=NODATA)
    tiles.write_changes_gpkg(folder / "changes.gpkg", [], geo.crs)
    zarr.open_group(str(folder / "changes.zarr"), mode="w")
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(folder / "thumbnail.png")
    if report:
        (folder / "report").mkdir(exist_ok=True)
        (folder / "report" / "index.html").write_text("<html></html>")
    return mask


def record_done(out, capture, folder, night, *, sha="0" * 64, changes=0):
    """``capture`` done on ``night`` with its products in ``folder``, in ``out``'s ledger; returns the run id."""
    key = RunKey.build(sha, [], [], {}, "test")
    with Ledger(Path(out) / LEDGER_NAME) as ledger:
        run = ledger.start(str(capture), key, night=night)
        ledger.finish(run, "done", "new capture", {"output": str(folder), "changes": changes, "changed_m2": 0.0})
    return run


def done_rows(out):
    from rsmb.pipeline.archive._night_end import latest_done

    with Ledger(Path(out) / LEDGER_NAME, readonly=True) as ledger:
        return latest_done(ledger)
