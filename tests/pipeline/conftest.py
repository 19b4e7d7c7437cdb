"""Fixtures: synthetic pairs on disk (array -> file -> store)."""

import numpy as np
import pytest

from rsmb import ops
from rsmb.pipeline import write_pair


@pytest.fixture(scope="session")
def small_pair():
    return ops.synthesize_pair((192, 256), motion="inplane", changes=5, noise=0.002, seed=11)


@pytest.fixture(scope="session")
def small_pair_files(tmp_path_factory, small_pair):
    out = tmp_path_factory.mktemp("pair")
    ref, dist = write_pair(out, small_pair, fmt="png")
    return out, ref, dist


def inplane_pair_files(tmp_path_factory, name, shape, *, changes, seed, fmt):
    """A synthetic in-plane pair written to a fresh directory: (pair, directory,
    reference path, distorted path)."""
    pair = ops.synthesize_pair(shape, motion="inplane", changes=changes, noise=0.002, seed=seed)
    out = tmp_path_factory.mktemp(name)
    return (pair, out, *write_pair(out, pair, fmt=fmt))


@pytest.fixture(scope="session")
def geotiff_pair_files(tmp_path_factory):
    return inplane_pair_files(tmp_path_factory, "geopair", (256, 256), changes=5, seed=12, fmt="tif")[1:]


def read_store(path):
    import zarr

    group = zarr.open_group(str(path), mode="r")
    return {name: np.asarray(array[...]) for name, array in group.arrays()}, group.attrs.asdict()
