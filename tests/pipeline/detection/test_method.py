"""The method lives in the library: ``rsmb.ops.run_method`` on a small pair
gives the masks ``rsmb detect`` writes for it (one tile: the tile task only
reads, calls the same function and writes)."""

import numpy as np

from rsmb import ops, tiles
from rsmb.pipeline import default_overlap
from rsmb.pipeline.cli import main

from ..conftest import read_store


def test_ops_on_a_small_pair_gives_the_masks_of_rsmb_detect(tmp_path, small_pair_files):
    _, ref_path, dist_path = small_pair_files
    out = tmp_path / "o.zarr"
    assert main(["-q", "detect", str(ref_path), str(dist_path), "-o", str(out), "--tile-size", "256",
                 "--slow-axes", "none"]) == 0
    stored, attrs = read_store(out)
    assert stored["change_mask"].any()  # the pair has changes to find

    reference, capture = (tiles.read_image(p).data for p in (ref_path, dist_path))
    camera = ops.Camera.for_shape(capture.shape)
    params = ops.RegistrationParams(slow_axes=()).resolved(camera)
    intensity = ops.IntensityScale.from_dict(attrs["intensity"])
    halo = default_overlap(params, camera, capture.shape)  # the reference beyond the image: NaN, as detect reads it
    found = ops.run_method(np.pad(reference, halo, constant_values=np.nan), capture, camera=camera, params=params,
                           intensity=intensity, reference_origin_yx=(-halo, -halo))
    changes = ops.method_changes(found, camera=camera)

    np.testing.assert_array_equal(found.score, stored["change_score"])
    np.testing.assert_array_equal(found.parallax, stored["parallax_mask"] > 0)
    np.testing.assert_array_equal(changes.mask, stored["change_mask"] > 0)
    np.testing.assert_array_equal(changes.mask_reference, stored["change_mask_reference"] > 0)
    assert changes.threshold == attrs["summary"]["threshold"]
