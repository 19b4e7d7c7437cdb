"""Fixtures: synthetic pairs on disk (array -> file -> store)."""

import numpy as np
import pytest

import ops
from pipeline import write_pair


@pytest.fixture(scope="session")
def small_pair():
    return ops.synthesize_pair((192, 256), motion="inplane", changes=5, noise=0.002, seed=11)


@pytest.fixture(scope="session")
def small_pair_files(tmp_path_factory, small_pair):
    out = tmp_path_factory.mktemp("pair")
    ref, dist = write_pair(out, small_pair, fmt="png")
    return out, ref, dist


@pytest.fixture(scope="session")
def geotiff_pair_files(tmp_path_factory):
    pair = ops.synthesize_pair((256, 256), motion="inplane", changes=5, noise=0.002, seed=12)
    out = tmp_path_factory.mktemp("geopair")
    ref, dist = write_pair(out, pair, fmt="tif")
    return out, ref, dist


def read_store(path):
    import zarr

    group = zarr.open_group(str(path), mode="r")
    return {name: np.asarray(array[...]) for name, array in group.arrays()}, group.attrs.asdict()
