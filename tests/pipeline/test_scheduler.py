"""The task runner: results in order, tasks started in the order given, and
process-wide settings only in worker processes."""

import contextlib
import os
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from rsmb.pipeline import _scheduler
from rsmb.pipeline._scheduler import Runner


@pytest.mark.parametrize("scheduler, workers", [("threads", 1), ("synchronous", None)])
def test_tasks_start_in_the_order_of_the_list(scheduler, workers):
    started = []

    def task(i):
        started.append(i)
        return i * i

    out = Runner(scheduler, workers=workers).map("order", task, [(i,) for i in range(20)])
    assert out == [i * i for i in range(20)]
    assert started == list(range(20))  # callers put the longest tiles first


def test_results_in_order_with_two_threads():
    def task(i):
        return -i

    runner = Runner("threads", workers=2)
    assert runner.map("two", task, [(i,) for i in range(50)]) == [-i for i in range(50)]


def _opencv_threads(_):
    import cv2

    return os.getpid(), cv2.getNumThreads()


@pytest.mark.parametrize("scheduler, workers", [("threads", 2), ("synchronous", None)])
def test_a_run_in_the_calling_process_leaves_it_as_it_was(scheduler, workers, monkeypatch):
    cv2 = pytest.importorskip("cv2")
    before = cv2.getNumThreads()
    configured = []
    monkeypatch.setattr(_scheduler, "configure_process", lambda: configured.append(os.getpid()))
    cv2.setNumThreads(3)
    try:
        out = Runner(scheduler, workers=workers).map("cv", _opencv_threads, [(i,) for i in range(6)])
        assert {pid for pid, _ in out} == {os.getpid()}
        assert {n for _, n in out} == {1}  # one OpenCV thread while the tasks ran
        assert cv2.getNumThreads() == 3  # the caller's setting is back
        assert configured == []  # no process-wide setting in a library caller
    finally:
        cv2.setNumThreads(before)


def test_worker_processes_get_the_process_settings():
    cv2 = pytest.importorskip("cv2")
    before = cv2.getNumThreads()
    out = Runner("processes", workers=1).map("cv", _opencv_threads, [(0,), (1,)])
    assert all(pid != os.getpid() and n == 1 for pid, n in out)
    assert cv2.getNumThreads() == before


def _negate(i):
    return -i


def test_one_shared_runner_serves_concurrent_runs():

    from rsmb.pipeline._scheduler import open_runner

    with open_runner("threads", workers=2, shared=True, progress=False) as runner:
        with ThreadPoolExecutor(3) as driver:
            runs = [driver.submit(runner.map, "run", _negate, [(i + 100 * r,) for i in range(30)]) for r in range(3)]
            results = [f.result() for f in runs]
    assert results == [[-(i + 100 * r) for i in range(30)] for r in range(3)]


def _blas_threads(_=None):
    """Thread count of every BLAS library loaded in this process: path -> count."""
    return {lib["filepath"]: lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


def test_a_run_in_the_calling_process_runs_one_blas_thread_and_restores_them():
    import numpy  # noqa: F401 - loads numpy's OpenBLAS

    before = _blas_threads()
    if not before:
        pytest.skip("no BLAS found in this process")
    with threadpool_limits(limits=2, user_api="blas"):  # a caller's setting that is not one
        caller = _blas_threads()  # (a single-threaded build stays at one)
        assert 2 in caller.values()
        out = Runner("threads", workers=2).map("blas", _blas_threads, [(i,) for i in range(4)])
        assert all(set(counts[path] for path in caller) == {1} for counts in out)  # one thread in tasks
        after = _blas_threads()
        assert {path: after[path] for path in caller} == caller  # the caller's setting is back
    assert {path: n for path, n in _blas_threads().items() if path in before} == before


def test_the_blas_libraries_are_found_again_only_after_an_import(monkeypatch):
    import sys
    import types

    _scheduler._as_blas_controller(_scheduler._one_blas_thread().restore_original_limits)
    found = _scheduler._blas_found[1]
    _scheduler._as_blas_controller(_scheduler._one_blas_thread().restore_original_limits)
    assert _scheduler._blas_found[1] is found  # nothing imported since: the same search
    monkeypatch.setitem(sys.modules, "rsmb_test_new_module", types.ModuleType("rsmb_test_new_module"))
    limiter = _scheduler._one_blas_thread()  # a module imported: its libraries may be new
    try:
        assert _scheduler._blas_found[1] is not found
        assert set(_blas_threads().values()) <= {1}
    finally:
        _scheduler._as_blas_controller(limiter.restore_original_limits)


def _blas_threads_slowly(_):
    time.sleep(0.01)  # runs overlap
    return _blas_threads()


@pytest.mark.parametrize("caller_limit", [None, 2])
def test_overlapping_runs_restore_the_callers_setting_when_the_last_ends(caller_limit):
    """Runs under way at once, started and ended in other threads than the
    caller's (a survey's drivers), with or without a limit the caller holds:
    one thread in every task of each, the caller's counts back after the last."""
    import numpy  # noqa: F401

    if not _blas_threads():
        pytest.skip("no BLAS found in this process")
    runner = Runner("threads", workers=2, progress=False)
    before = _blas_threads()
    with threadpool_limits(limits=caller_limit, user_api="blas"):
        caller = _blas_threads()
        with ThreadPoolExecutor(2) as driver:
            runs = [driver.submit(runner.map, "run", _blas_threads_slowly, [(i,) for i in range(20)])
                    for _ in range(2)]
            results = [f.result() for f in runs]
        assert all(set(counts[path] for path in caller) == {1} for run in results for counts in run)
        assert _blas_threads() == caller
        if caller_limit is None:
            with ThreadPoolExecutor(1) as other:  # the rsmb runs' threads left no hold on the setting
                other.submit(threadpool_limits, limits=1, user_api="blas").result()
            assert set(_blas_threads().values()) == {1}
    assert _blas_threads() == before


def test_worker_processes_run_one_blas_thread():
    out = Runner("processes", workers=1).map("blas", _blas_threads, [(0,), (1,)])
    assert all(counts and set(counts.values()) == {1} for counts in out)  # numpy's OpenBLAS at least


def _fail_or_write(path, delay):
    if path is None:
        raise ValueError("bad input")
    time.sleep(delay)
    path.write_text("written")


@pytest.mark.parametrize("shared", [False, True])
def test_a_failed_map_returns_after_its_running_tasks(tmp_path, shared):
    # the caller removes a failed run's store right after the error: no task of
    # that run may still write into it then
    with ThreadPoolExecutor(2) if shared else contextlib.nullcontext() as pool:
        runner = Runner("threads", workers=2, pool=pool, progress=False)
        late = tmp_path / "late.txt"
        with pytest.raises(ValueError, match="bad input"):
            runner.map("t", _fail_or_write, [(late, 0.5), (None, 0.0)])
        assert late.read_text() == "written"


@pytest.mark.parametrize("scheduler", ["threads", "processes", "synchronous"])
def test_a_local_scheduler_is_the_function_its_name_stands_for(scheduler):
    import dask.base

    assert _scheduler._local_get(scheduler) is dask.base.named_schedulers[scheduler]


def test_a_local_run_does_not_import_dask_distributed():
    """A threads run needs no cluster: dask.distributed (an import of a
    fraction of a second on the run's serial start) stays unloaded.  In a
    fresh interpreter, where nothing else has imported it."""
    import subprocess
    import sys

    code = ("import sys\nfrom rsmb.pipeline._scheduler import Runner\n"
            "assert Runner('threads', workers=2).map('t', abs, [(-1,), (-2,)]) == [1, 2]\n"
            "print('distributed' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_the_command_process_gets_a_short_switch_interval_a_library_caller_keeps_its_own():
    import subprocess
    import sys

    before = sys.getswitchinterval()
    Runner("threads", workers=2).map("local", abs, [(-i,) for i in range(4)])
    assert sys.getswitchinterval() == before  # a library run leaves the interpreter as it was
    code = ("import sys\n"
            "from rsmb.pipeline._scheduler import SWITCH_INTERVAL, configure_process\n"
            "configure_process()\n"
            "print(sys.getswitchinterval() == SWITCH_INTERVAL < 0.005)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "True"


def test_a_stopped_runner_starts_no_task_more():
    """Runner.stop (a night's abandoned captures): a map started after it
    raises, and the tasks a running map has not started yet fail instead of
    running; the running ones finish."""
    from rsmb.ops import RunError

    started = []

    def task(k):
        started.append(k)
        if k == 0:
            runner.stop()
            time.sleep(0.2)  # the others wait for a worker meanwhile
        return k

    with _scheduler.open_runner("threads", workers=1, shared=True, progress=False) as runner:
        with pytest.raises(RunError, match="stopped"):
            runner.map("t", task, [(k,) for k in range(4)])
        assert started == [0]
        with pytest.raises(RunError, match="stopped"):
            runner.map("t", task, [(0,)])
        assert started == [0]
