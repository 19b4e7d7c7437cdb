"""detect with raised structures: parallax goes to parallax_mask and its
table of depths, not to change_mask; --no-layers turns the step off."""

import numpy as np

from rsmb import ops
from rsmb.pipeline import evaluate, write_pair
from rsmb.pipeline.cli import main

from ..conftest import read_store


def test_parallax_mask_and_its_depths(tmp_path):
    duration = 256 + 16.0 + 1.0
    t = np.linspace(0, duration, 16)
    poses = np.zeros((16, 6))
    poses[:, 0], poses[:, 1] = np.linspace(16, 18, 16), np.linspace(3, 5, 16)
    pair = ops.synthesize_pair((256, 256), path=ops.CameraPath(t, poses), exposure=16.0, changes=3, noise=0.002,
                               seed=51, interpolation="cubic", structures=3, depths=(0.4, 0.8))
    write_pair(tmp_path / "pair", pair, fmt="npy")
    args = [str(tmp_path / "pair" / "reference.npy"), str(tmp_path / "pair" / "distorted.npy"), "--tile-size", "256"]
    assert main(["-q", "detect", *args, "-o", str(tmp_path / "on.zarr")]) == 0
    assert main(["-q", "detect", *args, "-o", str(tmp_path / "off.zarr"), "--no-layers"]) == 0
    on, attrs = read_store(tmp_path / "on.zarr")
    off, attrs_off = read_store(tmp_path / "off.zarr")
    assert on["parallax_mask"].dtype == np.uint8 and not (off["parallax_mask"] == 1).any()
    assert not ((on["change_mask"] == 1) & (on["parallax_mask"] == 1)).any()
    depths = [c["depth"] for c in attrs["parallax"]["components"] if c["pixels"] > 150]
    assert len(depths) >= 3 and all(0.4 <= d <= 0.85 for d in depths), attrs["parallax"]["components"]
    assert attrs["summary"]["parallax_components"] == len(attrs["parallax"]["components"])
    assert attrs_off["parallax"]["components"] == [] and "--no-layers" in attrs_off["parallax"]["rule"]
    with_layers = evaluate(tmp_path / "on.zarr", tmp_path / "pair").changes
    without = evaluate(tmp_path / "off.zarr", tmp_path / "pair").changes
    assert with_layers.precision >= 0.9 and without.precision < with_layers.precision - 0.2, (with_layers, without)
