"""Fixtures: synthetic pairs on disk (array -> file -> store)."""

import os
import shutil
import subprocess
import sys
import time

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


@pytest.fixture
def dask_cluster(tmp_path_factory):
    """A real dask scheduler and one worker process (no nanny: killing it kills
    the worker) on 127.0.0.1, ports :0, the worker in a working directory of its
    own.  Yields (scheduler file, worker process)."""
    dask_cli = shutil.which("dask", path=os.path.dirname(sys.executable)) or shutil.which("dask")
    if dask_cli is None:
        pytest.skip("the dask command line is not installed")
    home = tmp_path_factory.mktemp("cluster")
    file = home / "scheduler.json"
    procs = [subprocess.Popen([dask_cli, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(file)], cwd=home, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)]
    deadline = time.time() + 60
    while not file.exists() and time.time() < deadline:
        time.sleep(0.1)
    elsewhere = home / "worker-cwd"
    elsewhere.mkdir()
    procs.append(subprocess.Popen([dask_cli, "worker", "--scheduler-file", str(file), "--nworkers", "1",
                                   "--nthreads", "2", "--no-dashboard", "--no-nanny", "--host", "127.0.0.1"],
                                  cwd=elsewhere, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    try:
        yield file, procs[1]
    finally:
        for proc in procs[::-1]:
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
