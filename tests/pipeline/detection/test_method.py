"""The method lives in the library: ``rsmb.ops.run_method`` on a small pair
gives the masks ``rsmb detect`` writes for it (one tile: the tile task only
reads, calls the same function and writes)."""

import numpy as np
import pytest

from rsmb import ops, tiles
from rsmb.pipeline import default_overlap, write_pair
from rsmb.pipeline.cli import main

from ..conftest import read_store


@pytest.mark.parametrize("gain", [1.0, 1.5])  # 1.5: the capture's highlights saturate (clipped pixels scored)
def test_ops_on_a_small_pair_gives_the_masks_of_rsmb_detect(tmp_path, gain):
    pair = ops.synthesize_pair((160, 200), motion="inplane", changes=4, noise=0.002, gain=gain, seed=5)
    ref_path, dist_path = write_pair(tmp_path, pair, fmt="png")
    out = tmp_path / "o.zarr"
    assert main(["-q", "detect", str(ref_path), str(dist_path), "-o", str(out), "--tile-size", "256",
                 "--slow-axes", "none"]) == 0
    stored, attrs = read_store(out)
    assert (stored["change_mask"] == 1).any()  # the pair has changes to find
    intensity = ops.IntensityScale.from_dict(attrs["intensity"])
    assert (intensity.capture_clipped > 0.01) == (gain > 1)

    reference, capture = (tiles.read_image(p).data for p in (ref_path, dist_path))
    camera = ops.Camera.for_shape(capture.shape)
    params = ops.RegistrationParams(slow_axes=()).resolved(camera)
    halo = default_overlap(params, camera, capture.shape)  # the reference beyond the image: NaN, as detect reads it
    found = ops.run_method(np.pad(reference, halo, constant_values=np.nan), capture, camera=camera, params=params,
                           intensity=intensity, reference_origin_yx=(-halo, -halo))
    changes = ops.method_changes(found, camera=camera)

    np.testing.assert_array_equal(found.score, stored["change_score"])
    np.testing.assert_array_equal(found.parallax, stored["parallax_mask"] == 1)
    np.testing.assert_array_equal(changes.mask, stored["change_mask"] == 1)
    np.testing.assert_array_equal(changes.mask_reference, stored["change_mask_reference"] == 1)
    assert changes.threshold == attrs["summary"]["threshold"]


def test_what_the_depth_explained_reaches_rsmb_detects_masks(tmp_path):
    """With raised structures, the masks of ``rsmb detect`` measure the
    parallax's neighbours against what the depth explained, as
    :func:`ops.method_changes` does (``work/explained``, read by the label
    tasks); on this pair that leaves out rims of structures, no true change."""
    from rsmb.ops.synthetic._synth import readout_path

    path = readout_path(256, 24.0, tx=(15, 19), ty=(3, 6), rz=(-0.5, 0.5))
    pair = ops.synthesize_pair((256, 256), path=path, exposure=24.0, changes=3, structures=5, noise=0.002, seed=1,
                               interpolation="cubic")
    ref_path, dist_path = write_pair(tmp_path, pair, fmt="npy")
    out = tmp_path / "o.zarr"
    assert main(["-q", "detect", str(ref_path), str(dist_path), "-o", str(out), "--tile-size", "256",
                 "--slow-axes", "none"]) == 0
    stored, attrs = read_store(out)
    reference, capture = (tiles.read_image(p).data for p in (ref_path, dist_path))
    camera = ops.Camera.for_shape(capture.shape)
    params = ops.RegistrationParams(slow_axes=()).resolved(camera)
    halo = default_overlap(params, camera, capture.shape)
    found = ops.run_method(np.pad(reference, halo, constant_values=np.nan), capture, camera=camera, params=params,
                           intensity=ops.IntensityScale.from_dict(attrs["intensity"]), reference_origin_yx=(-halo, -halo))
    assert found.parallax.any() and found.explained is not None
    assert (found.explained[found.parallax] > 0).any() and not found.explained[~found.parallax].any()
    changes = ops.method_changes(found, camera=camera)
    np.testing.assert_array_equal(found.parallax, stored["parallax_mask"] == 1)
    np.testing.assert_array_equal(changes.mask, stored["change_mask"] == 1)
    rims = ops.change_mask(np.nan_to_num(found.score), changes.threshold) & ~changes.mask
    assert rims.any() and not rims[pair.change_mask > 0].any()  # what it leaves out here is no change
