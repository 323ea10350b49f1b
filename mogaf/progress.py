"""Progress of long work: a log line at a steady interval, a bar on a terminal.

A stage that runs longer than a few seconds reports through `Progress`:
every `interval` seconds (and at the end) one log line with the step, the
latest values (loss, PSNR, ...), the elapsed time and an estimate of the time
left; on a terminal a tqdm bar as well. The estimate is the mean time per
step since this process started the loop, times the steps left.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

log = logging.getLogger("mogaf.progress")

DEFAULT_INTERVAL_S = 10.0


def format_seconds(seconds: float) -> str:
    """'42 s', '3 min 05 s', '1 h 02 min'."""
    s = max(0.0, float(seconds))
    if s < 60:
        return f"{s:.0f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


def _value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


class Progress:
    """Reports `what` (e.g. "recon") going from `initial` to `total` steps."""

    def __init__(
        self,
        what: str,
        total: int,
        *,
        initial: int = 0,
        interval: float = DEFAULT_INTERVAL_S,
        bar: bool | None = None,
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.what = what
        self.total = int(total)
        self.start_step = self.step = int(initial)
        self.interval = float(interval)
        self.clock = clock
        self.t0 = self.last = clock()
        self.values: dict[str, Any] = {}
        stream = sys.stderr if stream is None else stream
        if bar is None:
            bar = bool(getattr(stream, "isatty", lambda: False)())
        self.bar = None
        if bar:
            from tqdm import tqdm

            self.bar = tqdm(
                total=self.total, initial=self.step, file=stream, desc=what, dynamic_ncols=True, leave=False
            )

    def remaining_s(self) -> float | None:
        done = self.step - self.start_step
        if done <= 0:
            return None
        return (self.clock() - self.t0) / done * max(0, self.total - self.step)

    def line(self) -> str:
        parts = [f"{self.what}: step {self.step}/{self.total}"]
        if self.total > 0:
            parts[0] += f" ({100.0 * self.step / self.total:.0f} %)"
        parts += [f"{k} {_value(v)}" for k, v in self.values.items()]
        parts.append(f"{format_seconds(self.clock() - self.t0)} elapsed")
        left = self.remaining_s()
        if left is not None and self.step < self.total:
            parts.append(f"about {format_seconds(left)} left")
        return ", ".join(parts)

    def update(self, step: int | None = None, **values: Any) -> None:
        """Move to `step` (default: one more) with the latest `values`."""
        new = self.step + 1 if step is None else int(step)
        if self.bar is not None:
            self.bar.update(new - self.step)
            if values:
                self.bar.set_postfix({k: _value(v) for k, v in values.items()}, refresh=False)
        self.step = new
        self.values.update(values)
        now = self.clock()
        if now - self.last >= self.interval:
            self.last = now
            log.info("%s", self.line())

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        if self.step > self.start_step:
            log.info("%s", self.line())
