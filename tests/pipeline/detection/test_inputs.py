"""Inputs a survey has: any raster GDAL opens, recognised by opening it (VRT,
JPEG 2000, a GeoTIFF without its suffix), and a reference set for ``rsmb
detect`` (several files, or a folder of them)."""

import shutil

import numpy as np
import pytest

from rsmb import ops, tiles
from rsmb.pipeline.bench._archive import CaptureSpec, write_capture, write_reference
from rsmb.pipeline.cli import main

from ..conftest import read_store


def _copy(src, dst, driver, **options):
    import rasterio
    import rasterio.shutil

    rasterio.shutil.copy(str(src), str(dst), driver=driver, **options)
    with rasterio.open(src) as a, rasterio.open(dst) as b:
        assert b.driver == driver and (a.read() == b.read()).all()  # lossless: the same pixels
    return dst


def test_vrt_jpeg2000_and_a_suffixless_geotiff_are_inputs(geotiff_pair_files, tmp_path, capsys):
    """The same pair as GeoTIFFs, and as a VRT reference with a lossless
    JPEG 2000 capture, and as GeoTIFFs named ``.data``: the same masks."""
    _, ref, dist = geotiff_pair_files
    vrt = _copy(ref, tmp_path / "ref.vrt", "VRT")
    jp2 = _copy(dist, tmp_path / "dist.jp2", "JP2OpenJPEG", QUALITY="100", REVERSIBLE="YES")
    plain_ref, plain_dist = shutil.copy(ref, tmp_path / "ref.data"), shutil.copy(dist, tmp_path / "dist.data")
    assert tiles.probe_header(jp2)[0] == tiles.probe_header(dist)[0]
    stores = []
    for k, (r, d) in enumerate(((ref, dist), (vrt, jp2), (plain_ref, plain_dist))):
        stores.append(tmp_path / f"o{k}.zarr")
        assert main(["-q", "detect", str(r), str(d), "-o", str(stores[-1]), "--tile-size", "128"]) == 0, (r, d)
    masks = [read_store(s)[0]["change_mask"] for s in stores]
    assert masks[0].any()
    for mask in masks[1:]:
        np.testing.assert_array_equal(mask, masks[0])
    not_a_raster = tmp_path / "notes.data"
    not_a_raster.write_text("not an image")
    assert main(["-q", "detect", str(ref), str(not_a_raster), "-o", str(tmp_path / "x.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "notes.data: unsupported format '.data'" in err[0] and "GDAL" in err[0], err
    # at the default log level too: the GDAL error rasterio logs (at INFO) before raising it is not printed
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "rsmb", "detect", str(ref), str(not_a_raster), "-o",
                           str(tmp_path / "y.zarr")], capture_output=True, text=True, timeout=300)
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(err) == 1 and err[0].startswith("rsmb: error: "), proc.stderr


def test_detect_takes_the_reference_set_a_survey_takes(tmp_path):
    """A capture straddling a mosaic of two files: the two files, and their
    folder (with a stray note in it), give the same store; both files are read."""
    scene = (0.05 + 0.7 * ops.aerial_scene((320, 320), seed=4)).astype(np.float32)
    references = write_reference(tmp_path / "mosaic", scene, split=2)
    (tmp_path / "mosaic" / "README.txt").write_text("the reference mosaic")
    capture = tmp_path / "cap.tif"
    write_capture(capture, scene, CaptureSpec((60, 100), (160, 160), seed=9, changes=2))
    runs = {"files": [*map(str, references)], "folder": [str(tmp_path / "mosaic")]}
    stores = {}
    for name, refs in runs.items():
        stores[name] = tmp_path / f"{name}.zarr"
        assert main(["-q", "detect", *refs, str(capture), "-o", str(stores[name]), "--tile-size", "160"]) == 0
    (a, attrs_a), (b, attrs_b) = read_store(stores["files"]), read_store(stores["folder"])
    np.testing.assert_array_equal(a["change_mask"], b["change_mask"])
    assert (a["change_mask"] == 1).any()
    assert sorted(attrs_a["pairing"]["read"]) == sorted(attrs_b["pairing"]["read"]) == sorted(map(str, references))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ops.InputError, match="empty: a folder of reference files with no raster in it"):
        tiles.expand_references([tmp_path / "empty"])
