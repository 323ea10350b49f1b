"""Where a stage's time goes: named phases timed with a monotonic clock.

`PhaseClock.phase(name)` adds the time spent inside a `with` block to `name`;
nested phases are allowed (an outer phase includes its inner ones).
`KERNELS` is the clock of the CPU rasterizer's four calls (projection and
compositing, forward and backward): the training loops read it to split the
autograd backward into the rasterizer's part and the rest. The stages write
the totals into their artefacts (attr `time_breakdown_s`), and
`python -m mogaf.bench pipeline` prints them.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager


class PhaseClock:
    """`sync`, called at every phase's start and end, waits for queued device
    work (torch.cuda.synchronize on a GPU), so that each phase is charged with
    its own kernels rather than with whichever phase waits for them first."""

    def __init__(self, sync: Callable[[], None] | None = None) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.sync = sync

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        if self.sync is not None:
            self.sync()
        start = time.perf_counter()
        try:
            yield
        finally:
            if self.sync is not None:
                self.sync()
            self.seconds[name] += time.perf_counter() - start

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] += float(seconds)

    def total(self, name: str) -> float:
        return float(self.seconds.get(name, 0.0))

    def reset(self) -> None:
        self.seconds.clear()


KERNELS = PhaseClock()
