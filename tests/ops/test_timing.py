"""CPU-seconds per stage: nested stages are exclusive, so the stages add up."""

import time

from rsmb.ops._timing import UNTIMED, StageClock


def _spin(seconds):
    """Burn ``seconds`` of this thread's CPU."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_nested_stages_are_charged_to_themselves_only():
    clock = StageClock()
    start = time.thread_time()
    with clock.stage("outer"):
        _spin(0.05)
        with clock.stage("inner"):
            _spin(0.1)
        _spin(0.05)
    spent = time.thread_time() - start
    s = clock.seconds
    assert set(s) == {"outer_s", "inner_s"}
    assert 0.1 <= s["inner_s"] < 0.13
    assert 0.1 <= s["outer_s"] < 0.13  # the inner 0.1 s is not charged to the outer stage
    assert abs(s["outer_s"] + s["inner_s"] - spent) < 0.01


def test_sleeping_is_not_cpu_and_repeated_stages_add():
    clock = StageClock({"rows_s": 1.0})
    with clock.stage("rows"):
        time.sleep(0.05)
    with clock.stage("rows"):
        _spin(0.02)
    assert 1.02 <= clock.seconds["rows_s"] < 1.04
    with UNTIMED.stage("rows"):
        pass
