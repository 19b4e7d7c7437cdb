"""detect on georeferenced pairs: the reference set is read under the capture's
footprint and resampled onto its grid, whatever its extent, files, pixel size
or CRS (DESIGN.md, "Georeferenced pairs")."""

import numpy as np
import pytest

from rsmb import ops
from rsmb.pipeline import DetectConfig, detect, evaluate
from rsmb.pipeline.bench._archive import CaptureSpec, write_capture, write_reference
from rsmb.pipeline.cli import main

from ..conftest import read_store


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    """A 768 x 768 scene, a capture of a 256 x 256 window of it (crossing the
    scene's middle column), and the hand-cut same-grid pair of that capture."""
    d = tmp_path_factory.mktemp("archive")
    scene = (0.05 + 0.7 * ops.aerial_scene((768, 768), seed=5)).astype(np.float32)
    spec = CaptureSpec((200, 260), (256, 256), seed=7, changes=4)
    cut = write_capture(d / "capture.tif", scene, spec, hand_cut=d / "cut")
    detect(cut.reference, cut.distorted, d / "cut.zarr")
    return d, scene, evaluate(d / "cut.zarr", d / "capture.truth").changes.f_measure


CASES = {
    "larger": {},
    "two files": {"split": 2},
    "finer pixels": {"pixel": 0.4},
    "coarser pixels": {"pixel": 0.7},
    "EPSG:3857": {"crs": "EPSG:3857"},
    "EPSG:4326": {"crs": "EPSG:4326"},
}


@pytest.mark.parametrize("case", CASES)
def test_reference_sets_match_the_hand_cut_pair(tmp_path, archive, case):
    d, scene, hand_cut_f = archive
    references = write_reference(tmp_path / "mosaic", scene, **CASES[case])
    result = detect(references, d / "capture.tif", tmp_path / "o.zarr")
    assert result.pairing == "georeferenced" and result.reference_coverage == 1.0
    f = evaluate(tmp_path / "o.zarr", d / "capture.truth").changes.f_measure
    assert hand_cut_f >= 0.95 and abs(f - hand_cut_f) <= 0.02, (f, hand_cut_f)
    attrs = read_store(tmp_path / "o.zarr")[1]
    assert attrs["pairing"]["mode"] == "georeferenced" and attrs["proj:code"] == "EPSG:32618"


def test_a_capture_straddling_two_files_equals_one_file(tmp_path, archive):
    d, scene, _ = archive
    one = detect(write_reference(tmp_path / "one", scene), d / "capture.tif", tmp_path / "one.zarr")
    two = detect(write_reference(tmp_path / "two", scene, split=2), d / "capture.tif", tmp_path / "two.zarr")
    assert one.changed_pixels == two.changed_pixels
    a, b = read_store(tmp_path / "one.zarr")[0], read_store(tmp_path / "two.zarr")[0]
    for name in ("change_mask", "registered", "trajectory"):
        np.testing.assert_array_equal(a[name], b[name])
    attrs = read_store(tmp_path / "two.zarr")[1]
    assert len(attrs["pairing"]["read"]) == 2 and "reference_2" in attrs["inputs"]


def test_partial_overlap_runs_on_the_covered_part(tmp_path):
    scene = (0.05 + 0.7 * ops.aerial_scene((768, 768), seed=5)).astype(np.float32)
    spec = CaptureSpec((200, 100), (256, 512), seed=7, changes=6)
    write_capture(tmp_path / "capture.tif", scene, spec)
    references = write_reference(tmp_path / "part", scene[:, :450])  # the capture's columns 350.. are outside
    result = detect(references, tmp_path / "capture.tif", tmp_path / "o.zarr", config=DetectConfig(tile=256))
    assert result.reference_coverage == pytest.approx(350 / 512, abs=0.01)
    arrays = read_store(tmp_path / "o.zarr")[0]
    # a capture pixel has a model where its row's poses carry it onto covered
    # reference: up to the motion's largest shift (tx up to 10 px here) past the edge
    motion = np.genfromtxt(tmp_path / "capture.truth" / "trajectory.csv", delimiter=",", names=True)
    uncovered = np.s_[:, 350 + int(np.ceil(np.abs(motion["tx"]).max())) + 2:]
    assert (arrays["change_mask"][uncovered] == 255).all() and np.isnan(arrays["registered"][uncovered]).all()
    truth = ops.changes._metrics._as_mask("truth", __import__("cv2").imread(str(tmp_path / "capture.truth" /
                                                                       "change_mask.png"), 0) > 0)
    covered = np.isfinite(arrays["registered"])
    counts = ops.confusion(arrays["change_mask"] == 1, truth, valid=covered)
    assert counts.precision >= 0.95 and counts.recall >= 0.9, counts.as_dict()


def test_no_overlap_and_a_pair_5_km_apart_are_refused(tmp_path, archive, capsys):
    d, scene, _ = archive
    far = write_reference(tmp_path / "far", scene[:200, :200])  # north-west corner: the capture is elsewhere
    assert main(["detect", str(far[0]), str(d / "capture.tif"), "-o", str(tmp_path / "a.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not overlap" in err[0] and str(far[0]) in err[0] and "capture.tif" in err[0]
    spec = CaptureSpec((200, 260), (256, 256), seed=7, changes=4)
    write_capture(tmp_path / "moved.tif", scene, spec, offset_m=(5000.0, 0.0))
    assert main(["detect", str(d / "cut" / "reference.tif"), str(tmp_path / "moved.tif"), "-o",
                 str(tmp_path / "b.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not overlap" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["far", "moved.tif", "moved.truth"]


def test_the_bench_user_cut_is_the_reference_on_the_capture_grid(tmp_path):
    # the bench's second baseline: a user's own rasterio cut of a case's reference
    import rasterio

    from rsmb.pipeline.bench._bench_survey import _metric_pixel, _user_cut

    scene = (0.05 + 0.7 * ops.aerial_scene((160, 160), seed=2)).astype(np.float32)
    cut = write_capture(tmp_path / "capture.tif", scene, CaptureSpec((40, 50), (96, 96), seed=1, changes=1),
                        hand_cut=tmp_path / "cut")
    two = write_reference(tmp_path / "two", scene, split=2)  # the capture straddles both files
    user = _user_cut(two, tmp_path / "capture.tif", tmp_path / "user.tif")
    with rasterio.open(user) as a, rasterio.open(cut.reference) as b:
        assert a.transform == b.transform and a.crs == b.crs
        np.testing.assert_array_equal(a.read(1), b.read(1))
    coarse = write_reference(tmp_path / "coarse", scene, pixel=0.7)
    assert _metric_pixel(coarse[0], tmp_path / "capture.tif") == pytest.approx((0.7, 0.7), abs=1e-6)
    user = _user_cut(coarse, tmp_path / "capture.tif", tmp_path / "user_coarse.tif")
    with rasterio.open(user) as a, rasterio.open(cut.reference) as b:
        got, full = a.read(1).astype(np.float64), b.read(1).astype(np.float64)
    assert (got > 0).all() and np.corrcoef(got.ravel(), full.ravel())[0, 1] > 0.9
