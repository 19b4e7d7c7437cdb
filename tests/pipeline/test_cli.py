"""The command line through click's CliRunner; outputs re-opened from disk."""

import json
import logging

import numpy as np
import pytest
from click.testing import CliRunner

from rsmb import ops
from rsmb.pipeline.cli import cli, main

from .conftest import read_store


def _invoke(args):
    return CliRunner().invoke(cli, args, catch_exceptions=False)


def test_synth_detect_evaluate(tmp_path, capsys):
    pair_dir = tmp_path / "pair"
    result = _invoke(["synth", str(pair_dir), "--size", "256,256", "--changes", "6", "--seed", "3"])
    assert result.exit_code == 0, result.output
    store = tmp_path / "out.zarr"
    code = main(["-q", "detect", str(pair_dir / "reference.png"), str(pair_dir / "distorted.png"), "-o", str(store),
                 "--tile-size", "128"])
    assert code == 0
    arrays, attrs = read_store(store)
    assert arrays["change_mask"].shape == (256, 256) and arrays["change_mask"].dtype == np.uint8
    assert arrays["change_mask_reference"].shape == (256, 256)
    assert arrays["change_score"].dtype == np.float32 and arrays["registered"].dtype == np.float32
    assert arrays["trajectory"].shape == (256, 5)
    assert arrays["gain"].shape == (2, 2)
    assert attrs["pose_axes"] == ["tx", "ty", "rz", "rx", "ry"]
    assert attrs["inputs"]["reference"]["sha256"] and attrs["summary"]["timings"]["total_s"] > 0
    assert "ingest" not in attrs and not (tmp_path / "out.zarr.partial").exists()
    result = _invoke(["evaluate", str(store), str(pair_dir), "--json"])
    metrics = json.loads(result.output)
    assert metrics["changes"]["f_measure"] > 0.9
    assert metrics["gain"]["max_relative_error"] < 0.03
    _evaluate_refuses_what_it_cannot_read(tmp_path, store, pair_dir, capsys)


def _evaluate_refuses_what_it_cannot_read(tmp_path, store, pair_dir, capsys):
    """A zarr group that is not a detect store, and truth folders with one
    damaged file each: one line naming the path, exit 2."""
    import shutil

    import zarr

    other = tmp_path / "other.zarr"
    zarr.open_group(str(other), mode="w").create_array("x", shape=(4,), dtype="uint8")
    cases = [([str(other), str(pair_dir)], f"{other}: not an rsmb detect store")]
    for name, content in (("truth.json", b"{not json"), ("change_mask.png", b""), ("gain.npy", b"\x93NUMPY")):
        bad = tmp_path / f"bad_{name}"
        shutil.copytree(pair_dir / "truth", bad)
        (bad / name).write_bytes(content)
        cases.append(([str(store), str(bad)], f"{bad / name}: unreadable truth file"))
    capsys.readouterr()
    for args, named in cases:
        assert main(["evaluate", *args]) == 2, args
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and named in lines[0], (args, lines)


def test_dims_open_with_xarray(tmp_path, small_pair_files):
    import xarray as xr

    _, ref, dist = small_pair_files
    store = tmp_path / "x.zarr"
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(store)]) == 0
    ds = xr.open_zarr(store)
    assert ds["change_mask"].dims == ("row", "col")  # the sensor frame
    assert ds["change_mask_reference"].dims == ("y", "x")  # the ground frame
    assert ds["trajectory"].dims == ("row", "pose_axis")
    assert ds["gain"].dims == ("tile_y", "tile_x")


def test_existing_output_needs_overwrite(tmp_path, small_pair_files, capsys):
    _, ref, dist = small_pair_files
    store = tmp_path / "o.zarr"
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(store)]) == 0
    before = read_store(store)[0]["change_mask"]
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(store)]) == 2
    err = capsys.readouterr().err
    assert "output exists" in err and "--overwrite" in err and err.count("\n") == 1
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(store), "--overwrite"]) == 0
    assert np.array_equal(read_store(store)[0]["change_mask"], before)


def _bad_inputs(tmp_path, ref):
    constant = tmp_path / "constant.npy"
    np.save(constant, np.full((192, 256), 0.5, np.float32))
    nan = tmp_path / "nan.npy"  # NaN is no-data: a capture of NaN only has no valid pixel
    np.save(nan, np.full((192, 256), np.nan, np.float32))
    sparse = tmp_path / "sparse.npy"  # 0.2 % of the pixels valid
    arr = np.full((192, 256), np.nan, np.float32)
    arr[::16, ::16] = np.random.default_rng(0).random((12, 16))
    np.save(sparse, arr)
    small = tmp_path / "small.npy"
    np.save(small, np.random.default_rng(1).random((100, 100)).astype(np.float32))
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"not an image")
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros((0, 5), np.float32))
    return {
        "missing": (tmp_path / "missing.png", "no such file"),
        "unreadable": (garbage, "cannot read"),
        "constant": (constant, "constant"),
        "nan": (nan, "no valid pixel"),
        "sparse": (sparse, "too little valid data"),
        "size": (small, "differs from the reference"),
        "empty": (empty, "empty"),
    }


@pytest.mark.parametrize("case", ["missing", "unreadable", "constant", "nan", "sparse", "size", "empty"])
def test_bad_input_exits_2_with_one_line(tmp_path, small_pair_files, capsys, case):
    _, ref, _ = small_pair_files
    bad, words = _bad_inputs(tmp_path, ref)[case]
    store = tmp_path / "bad.zarr"
    code = main(["-q", "detect", str(ref), str(bad), "-o", str(store)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and bad.name in err and words in err, err
    assert not store.exists() and not (tmp_path / "bad.zarr.partial").exists()


def test_nan_in_a_float_capture_is_nodata(tmp_path, small_pair, small_pair_files):
    """A float capture without a nodata tag may hold NaN: those pixels are
    no-data (no evidence: NaN score, never change), the rest is detected."""
    _, ref, _ = small_pair_files
    capture = np.array(small_pair.distorted, np.float32)
    capture[20:40, 50:150] = np.nan
    holed = tmp_path / "holed.npy"
    np.save(holed, capture)
    store = tmp_path / "holed.zarr"
    assert main(["-q", "detect", str(ref), str(holed), "-o", str(store)]) == 0
    arrays, _ = read_store(store)
    assert np.isnan(arrays["change_score"][20:40, 50:150]).all()
    assert (arrays["change_mask"][20:40, 50:150] == 255).all()  # no evidence, not change
    assert np.isfinite(arrays["change_score"][80:, :]).mean() > 0.5


def test_bad_parameter_exits_2(tmp_path, small_pair_files, capsys):
    _, ref, dist = small_pair_files
    assert main(["detect", str(ref), str(dist), "-o", str(tmp_path / "p.zarr"), "--axes", "tx,warp"]) == 2
    assert "warp" in capsys.readouterr().err
    assert main(["detect", str(ref), str(dist), "-o", str(tmp_path / "p.zarr"), "--threshold", "otsu"]) == 2
    # rsmb's own checks name the option as click's do
    assert "Invalid value for '--threshold'" in capsys.readouterr().err
    assert main(["detect", str(ref), str(dist), "-o", str(tmp_path / "p.zarr"), "--search", "20,abc"]) == 2
    assert "Invalid value for '--search': expected comma-separated numbers" in capsys.readouterr().err


def test_global_shutter_and_kapur_options(tmp_path):
    pair = ops.synthesize_pair((128, 160), motion="inplane", shutter="global", changes=4, noise=0.002, seed=9)
    from rsmb.pipeline import write_pair

    ref, dist = write_pair(tmp_path / "gs", pair, fmt="npy")
    store = tmp_path / "gs.zarr"
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(store), "--shutter", "global",
                 "--threshold", "kapur"]) == 0
    arrays, attrs = read_store(store)
    assert attrs["parameters"]["registration"]["shutter"] == "global"
    assert attrs["parameters"]["changes"]["threshold"] == "kapur"
    traj = arrays["trajectory"]
    assert np.allclose(traj, traj[0])  # one pose for every row
    truth = pair.change_mask
    assert ops.confusion(arrays["change_mask"] == 1, truth).f_measure > 0.8


def test_help_texts():
    for command in ([], ["detect"], ["synth"], ["evaluate"]):
        result = _invoke(command + ["--help"])
        assert result.exit_code == 0 and "Usage" in result.output


def test_a_capture_with_nothing_to_register_says_so(tmp_path, capsys, caplog):
    """An 8 x 8 pair: no tile has data to fit a gain, so the summary's gain is
    null in strict JSON (never NaN) and "n/a" in the text line, and the log
    warns that there is no evidence almost anywhere."""
    rng = np.random.default_rng(1)
    image = rng.random((8, 8)).astype(np.float32)
    np.save(tmp_path / "r.npy", image)
    np.save(tmp_path / "d.npy", image)
    assert main(["detect", str(tmp_path / "r.npy"), str(tmp_path / "d.npy"), "-o", str(tmp_path / "o.zarr"),
                 "--json"]) == 0

    def no_nan(constant):
        raise ValueError(f"not JSON: {constant}")

    summary = json.loads(capsys.readouterr().out, parse_constant=no_nan)
    assert summary["gain_min"] is None and summary["gain_max"] is None and summary["no_evidence"] == 1.0
    assert "no evidence on 100 % of the capture's pixels" in caplog.text
    assert main(["-q", "detect", str(tmp_path / "r.npy"), str(tmp_path / "d.npy"), "-o", str(tmp_path / "p.zarr")]) == 0
    assert "gain n/a" in capsys.readouterr().out


def test_tiles_that_are_no_one_camera_path_are_warned_about(tmp_path, caplog):
    """A capture of three strips, each displaced from the reference by its own
    tx (-14, 0, +14 px): each tile registers on its own, the fused path is the
    middle strip's, and the outer two stray by 14 px, which the band's median
    strayness (14 px) keeps from being re-solved.  detect warns; strips of
    one tx do not."""
    scene = ops.aerial_scene((400, 900), seed=3).astype(np.float32)
    np.save(tmp_path / "r.npy", scene[72:328, 66:834])
    for name, shifts in (("one", (0, 0, 0)), ("three", (-14, 0, 14))):
        strips = [scene[72:328, 66 + s + 256 * k:66 + s + 256 * (k + 1)] for k, s in enumerate(shifts)]
        np.save(tmp_path / f"{name}.npy", np.concatenate(strips, axis=1))
    args = ["--tile-size", "256", "--slow-axes", "none"]
    with caplog.at_level(logging.WARNING, logger="rsmb"):
        assert main(["detect", str(tmp_path / "r.npy"), str(tmp_path / "one.npy"), "-o", str(tmp_path / "a.zarr"),
                     *args]) == 0
        assert "tiles' paths differ from the fused one" not in caplog.text
        assert main(["detect", str(tmp_path / "r.npy"), str(tmp_path / "three.npy"), "-o",
                     str(tmp_path / "b.zarr"), *args]) == 0
    assert "tiles' paths differ from the fused one by up to 14.0 px" in caplog.text


def test_a_capture_of_another_scene_is_warned_about(tmp_path, caplog):
    """A capture of another scene than its reference's (the trial's wrong
    reference) is no clean 'done' in silence: its change threshold follows
    residuals of the whole scene's contrast, and detect warns; a capture of
    the reference's scene does not."""
    from rsmb import ops

    one, other = (ops.synthesize_pair((256, 256), seed=s, changes=0) for s in (1, 2))
    for name, image in (("r", one.reference), ("d", one.distorted), ("x", other.distorted)):
        np.save(tmp_path / f"{name}.npy", image)
    with caplog.at_level(logging.WARNING, logger="rsmb"):
        assert main(["detect", str(tmp_path / "r.npy"), str(tmp_path / "d.npy"), "-o", str(tmp_path / "a.zarr")]) == 0
        assert "is the reference of this capture's scene?" not in caplog.text
        assert main(["detect", str(tmp_path / "r.npy"), str(tmp_path / "x.npy"), "-o", str(tmp_path / "b.zarr")]) == 0
    assert "is the reference of this capture's scene?" in caplog.text
