"""detect on a real dask.distributed cluster: a scheduler and a worker process
on 127.0.0.1, the worker in another working directory."""

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from rsmb.pipeline import DetectConfig, detect
from rsmb.pipeline.cli import main

from .conftest import read_store


def test_relative_paths_on_a_cluster_give_the_threads_result(tmp_path, small_pair_files, dask_cluster,
                                                              monkeypatch):
    import shutil

    file, _ = dask_cluster
    _, ref, dist = small_pair_files
    shutil.copy(ref, tmp_path / "ref.png")
    shutil.copy(dist, tmp_path / "dist.png")
    detect(ref, dist, tmp_path / "local.zarr", config=DetectConfig(tile=128))
    monkeypatch.chdir(tmp_path)
    address = json.loads(file.read_text())["address"]
    assert address.startswith("tcp://127.0.0.1:")
    for scheduler, store in ((address, "remote.zarr"), (str(file), "file.zarr")):
        assert main(["-q", "detect", "ref.png", "dist.png", "-o", store, "--tile-size", "128",
                     "--scheduler", scheduler]) == 0
        for name in ("change_mask", "registered", "trajectory"):
            np.testing.assert_array_equal(read_store(tmp_path / "local.zarr")[0][name],
                                          read_store(tmp_path / store)[0][name])


def test_losing_every_worker_ends_the_run_within_the_timeout(tmp_path, dask_cluster):
    from rsmb.ops import synthesize_pair
    from rsmb.pipeline import write_pair

    file, worker = dask_cluster
    pair = synthesize_pair((768, 768), motion="inplane", changes=6, noise=0.002, seed=21)
    ref, dist = write_pair(tmp_path / "pair", pair, fmt="npy")
    store = tmp_path / "o.zarr"
    proc = subprocess.Popen([sys.executable, "-m", "rsmb", "-q", "detect", str(ref), str(dist), "-o", str(store),
                             "--tile-size", "96", "--scheduler", str(file), "--worker-timeout", "5"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (tmp_path / "o.zarr.partial" / "work").exists() and time.time() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None, proc.stderr.read()
    worker.kill()
    killed = time.time()
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail("detect hung after its last worker died")
    assert proc.returncode == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "no dask worker left for 5 s" in lines[0], lines
    assert time.time() - killed < 5 + 20


def test_a_slurm_job_script_from_dask_configuration(tmp_path):
    pytest.importorskip("dask_jobqueue")
    import dask

    from rsmb.pipeline._scheduler import jobqueue_cluster

    settings = {"jobqueue.slurm.cores": 2, "jobqueue.slurm.memory": "8GB", "jobqueue.slurm.walltime": "02:00:00",
                "jobqueue.slurm.queue": "night", "jobqueue.slurm.scheduler-options": {"host": "127.0.0.1"},
                "jobqueue.slurm.log-directory": str(tmp_path)}
    with dask.config.set(settings):
        cluster = jobqueue_cluster("slurm")
        try:
            script = cluster.job_script()
        finally:
            cluster.close()
    assert script.startswith("#!/usr/bin/env bash") and "#SBATCH -p night" in script
    assert "#SBATCH -t 02:00:00" in script and "--nthreads" in script and "tcp://127.0.0.1:" in script


def test_slurm_without_configuration_is_bad_input(capsys):
    pytest.importorskip("dask_jobqueue")
    import dask

    with dask.config.set({"jobqueue.slurm.cores": None, "jobqueue.slurm.memory": None}):
        from rsmb.ops import InputError
        from rsmb.pipeline._scheduler import jobqueue_cluster

        with pytest.raises(InputError, match="slurm"):
            jobqueue_cluster("slurm")
    assert os.environ.get("SLURM_JOB_ID") is None  # nothing was submitted: no SLURM here


def test_tasks_leave_a_shared_workers_thread_settings_as_they_found_them(tmp_path, small_pair_files, dask_cluster):
    """A cluster worker (not rsmb's) with OpenCV at 3 threads and its BLAS
    libraries at their own counts: after an rsmb run on it, the same counts."""
    from distributed import Client

    file, _ = dask_cluster
    _, ref, dist = small_pair_files

    def settings(threads=None):
        import cv2
        from threadpoolctl import threadpool_info

        if threads is not None:
            cv2.setNumThreads(threads)
        return cv2.getNumThreads(), {i["filepath"]: i["num_threads"] for i in threadpool_info()
                                     if i["user_api"] == "blas"}

    with Client(scheduler_file=str(file), timeout="30s") as client:
        client.wait_for_workers(1, timeout=60)
        before = list(client.run(settings, 3).values())[0]
        assert before[0] == 3
        assert main(["-q", "detect", str(ref), str(dist), "-o", str(tmp_path / "o.zarr"), "--tile-size", "128",
                     "--scheduler", str(file)]) == 0
        after = list(client.run(settings).values())[0]
    assert after[0] == before[0] == 3 and before[1]
    # every BLAS the worker had keeps its count (one the tasks loaded, by importing scipy, keeps its default)
    assert {path: after[1][path] for path in before[1]} == before[1]


def test_a_stopped_runner_cancels_its_cluster_tasks(dask_cluster):
    """Runner.stop on a dask.distributed runner: the map under way cancels its
    tasks not finished and raises within about a second, not after them."""
    import threading

    from rsmb.ops import RunError
    from rsmb.pipeline._scheduler import open_runner

    scheduler_file, _ = dask_cluster
    with open_runner(str(scheduler_file), progress=False) as runner:
        threading.Timer(1.0, runner.stop).start()
        start = time.monotonic()
        with pytest.raises(RunError, match="stopped"):
            runner.map("nap", time.sleep, [(3.0,) for _ in range(8)])  # 12 s on the worker's two threads
        assert time.monotonic() - start < 5
