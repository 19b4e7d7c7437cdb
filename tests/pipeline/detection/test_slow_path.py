"""detect on captures whose camera yaws and pitches: the slow out-of-plane part
of the path is found once on the whole capture at a coarser scale and every
tile registers on it (pipeline.detection._overview).  The capture is rendered with the
independent cubic renderer from a georeferenced reference larger than it."""

import numpy as np
import pytest

from rsmb import ops
from rsmb.ops.synthetic._synth import readout_path
from rsmb.pipeline import DetectConfig, detect, evaluate
from rsmb.pipeline.bench._archive import CaptureSpec, write_capture, write_reference
from rsmb.pipeline.detection._overview import overview_factor

from ..conftest import read_store

SIDE, MARGIN, EXPOSURE = 512, 128, 24.0


@pytest.fixture(scope="module")
def yaw_capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("yaw")
    scene = (0.05 + 0.7 * ops.aerial_scene((SIDE + 2 * MARGIN,) * 2, seed=21)).astype(np.float32)
    path = readout_path(SIDE, EXPOSURE, rx=(2.0, -2.0), ry=(-2.5, 2.0), tx=(-4.0, 4.0), ty=(1.0, 4.0),
                        rz=(-0.8, 0.8))
    spec = CaptureSpec((MARGIN, MARGIN), (SIDE, SIDE), seed=22, changes=8, exposure=EXPOSURE, path=path,
                       interpolation="cubic")
    write_capture(d / "capture.tif", scene, spec)
    return d, write_reference(d / "mosaic", scene)


def test_tiles_register_on_the_slow_path_found_on_the_overview(tmp_path, yaw_capture):
    d, references = yaw_capture
    # depth layers off in both runs: they would explain some of the bends left without the slow part
    plain = ops.ChangeParams(layers=False)
    out = detect(references, d / "capture.tif", tmp_path / "o.zarr", config=DetectConfig(tile=256, changes=plain))
    assert out.tiles == [2, 2] and "slow_s" in out.timings
    arrays, attrs = read_store(tmp_path / "o.zarr")
    assert attrs["pose_axes"] == ["tx", "ty", "rz", "rx", "ry"]
    truth = np.loadtxt(d / "capture.truth" / "trajectory.csv", delimiter=",", skiprows=1)
    error = np.abs(arrays["trajectory"][:, 3:] - truth[:, [3, 4]]).mean(axis=0)
    assert error.max() < 0.3, error
    f = evaluate(tmp_path / "o.zarr", d / "capture.truth").changes.f_measure
    detect(references, d / "capture.tif", tmp_path / "none.zarr",
           config=DetectConfig(tile=256, changes=plain, registration=ops.RegistrationParams(slow_axes=())))
    f_without = evaluate(tmp_path / "none.zarr", d / "capture.truth").changes.f_measure
    assert f >= 0.9 and f > f_without + 0.1, (f, f_without)


def test_a_resumed_run_makes_the_overview_the_ingest_made(tmp_path, yaw_capture, monkeypatch):
    """The ingest tasks make the overviews' cells from what they write; a run
    resumed after the ingest makes them again from the store, with the same
    bits: the same slow part, the same store."""
    from rsmb.pipeline.detection import _detect

    d, references = yaw_capture
    config = DetectConfig(tile=256, changes=ops.ChangeParams(layers=False))
    detect(references, d / "capture.tif", tmp_path / "ingested.zarr", config=config)
    ingest = _detect._ingest
    monkeypatch.setattr(_detect, "_ingest", lambda *args: (ingest(*args)[0], None))  # as after a resume
    detect(references, d / "capture.tif", tmp_path / "read.zarr", config=config)
    a, b = read_store(tmp_path / "ingested.zarr")[0], read_store(tmp_path / "read.zarr")[0]
    assert np.abs(a["trajectory"][:, 3:]).max() > 0.5  # a slow part was found
    for name in ("trajectory", "registered", "change_mask"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_an_in_plane_capture_has_no_slow_path(tmp_path, geotiff_pair_files):
    d, ref, dist = geotiff_pair_files
    detect(ref, dist, tmp_path / "o.zarr", config=DetectConfig(tile=128))
    arrays, _ = read_store(tmp_path / "o.zarr")
    assert not arrays["trajectory"][:, 3:].any()


@pytest.mark.parametrize("shape,factor", [((256, 300), 1), ((1024, 1100), 2), ((2048, 2048), 4), ((4096, 4096), 8), ((8192, 9000), 8)])
def test_overview_factor(shape, factor):
    assert overview_factor(shape) == factor


def test_the_tiles_halo_follows_the_slow_part_found(small_pair_files, tmp_path):
    """The store's reference margin covers the whole search (slow axes
    included: it is ingested before the slow part is known); the tiles then
    read only the halo the rows need: the in-plane reach without a slow part,
    more with one, the reach of the whole search at most, and a halo the user
    chose as it is."""
    from rsmb.pipeline.detection._plan import _plan

    _, ref, dist = small_pair_files
    plan = _plan([str(ref)], str(dist), str(tmp_path / "o.zarr"), DetectConfig())
    height = plan.shape[0]
    none = plan.for_rows(np.full((height, 3), np.nan))
    some = plan.for_rows(np.column_stack([np.zeros(height), np.linspace(-1.0, 1.0, height), np.zeros(height)]))
    assert none.grid.halo < some.grid.halo < plan.grid.halo == plan.reach
    assert none.grid.tile == plan.grid.tile and none.key == plan.key and none.margin == plan.margin
    given = _plan([str(ref)], str(dist), str(tmp_path / "o.zarr"), DetectConfig(overlap=40))
    assert given.for_rows(np.full((height, 3), np.nan)).grid.halo == 40
