"""Progress lines of long work: a steady interval, the step, values, time left."""

from __future__ import annotations

import io
import logging

from mogaf.progress import Progress, format_seconds


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_lines_come_at_the_interval_with_the_time_left(caplog):
    clock = FakeClock()
    caplog.set_level(logging.INFO, logger="mogaf.progress")
    bar = Progress("recon", 100, interval=10.0, bar=False, clock=clock)
    for step in range(1, 51):
        clock.now += 1.0  # one second a step
        bar.update(step, loss=0.5)
    bar.close()
    lines = [r.getMessage() for r in caplog.records]
    # one line every 10 s (steps 10, 20, ..., 50) and one at the close
    assert len(lines) == 6
    assert lines[0] == "recon: step 10/100 (10 %), loss 0.5, 10 s elapsed, about 1 min 30 s left"
    assert lines[-1].startswith("recon: step 50/100 (50 %)") and "about 50 s left" in lines[-1]


def test_resumed_work_estimates_from_its_own_steps(caplog):
    clock = FakeClock()
    caplog.set_level(logging.INFO, logger="mogaf.progress")
    bar = Progress("refine", 400, initial=300, interval=1e9, bar=False, clock=clock)
    clock.now += 20.0
    bar.update(310)
    assert bar.remaining_s() == 180.0  # 2 s a step since the resume, 90 steps left
    bar.close()
    assert caplog.records[-1].getMessage() == "refine: step 310/400 (78 %), 20 s elapsed, about 3 min 00 s left"


def test_nothing_done_logs_nothing_and_no_bar_off_a_terminal(caplog):
    caplog.set_level(logging.INFO, logger="mogaf.progress")
    stream = io.StringIO()  # not a terminal
    bar = Progress("forecast", 10, stream=stream)
    assert bar.bar is None
    bar.close()
    assert caplog.records == [] and stream.getvalue() == ""


def test_format_seconds():
    assert format_seconds(42.4) == "42 s"
    assert format_seconds(185) == "3 min 05 s"
    assert format_seconds(3720) == "1 h 02 min"
