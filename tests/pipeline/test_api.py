"""``import rsmb``: the public API is the functions the commands call."""

import numpy as np

import rsmb
from rsmb.pipeline.cli import main

from .conftest import read_store


def test_api_and_command_write_the_same_store(tmp_path, small_pair_files):
    _, ref, dist = small_pair_files
    result = rsmb.detect(ref, dist, tmp_path / "api.zarr", config=rsmb.DetectConfig(tile=128))
    assert isinstance(result, rsmb.DetectResult) and result.output == str(tmp_path / "api.zarr")
    assert main(["-q", "detect", str(ref), str(dist), "-o", str(tmp_path / "cli.zarr"), "--tile-size", "128"]) == 0
    api, api_attrs = read_store(tmp_path / "api.zarr")
    cli, cli_attrs = read_store(tmp_path / "cli.zarr")
    assert api.keys() == cli.keys()
    for name in api:
        np.testing.assert_array_equal(api[name], cli[name], err_msg=name)
    assert api_attrs["run_key"] == cli_attrs["run_key"] and api_attrs["parameters"] == cli_attrs["parameters"]


def test_api_names(tmp_path):
    paths = rsmb.synth(tmp_path / "pair", shape=(96, 96), changes=1, seed=2)
    assert isinstance(paths, rsmb.PairPaths) and paths.reference.is_file() and paths.distorted.is_file()
    result = rsmb.detect(paths.reference, paths.distorted, tmp_path / "o.zarr")
    scores = rsmb.evaluate(tmp_path / "o.zarr", tmp_path / "pair")
    assert isinstance(scores, rsmb.Evaluation) and 0 <= scores.changes.f_measure <= 1
    assert rsmb.report(tmp_path / "o.zarr").name == "index.html"
    assert result.shape == [96, 96] and rsmb.__version__
    assert set(rsmb.__all__) <= set(dir(rsmb))
