"""The task runner: results in order, tasks started in the order given."""

import pytest

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
    assert runner.tasks_run == 50
