"""Progress for a log: where a progress bar would fill a scheduler's log (``--no-progress``),
a line every so often."""

from __future__ import annotations

import sys
import time
from typing import Callable

from jaxflex import checks


class Heartbeat:
    """Prints ``"<what>: <done> of <total> <unit> (<pct> %) after <s> s, about <s> s left"``
    once ``every_s`` seconds have passed since the last line, and when ``done`` reaches
    ``total``. The time left comes from the rate since the first update, whose own time held
    the compile (a 16 s first step in a run of 0.1 s steps)."""

    def __init__(self, what: str, unit: str, total: int, done: int = 0, every_s: float = 30.0, clock: Callable[[], float] = time.monotonic):
        total = checks.integer("total", total)
        done = checks.integer("done", done, 0, high=total)
        every_s = checks.number("every_s", every_s, strict=True, unit="seconds")
        self.what, self.unit, self.total, self.done, self.every_s, self.clock = what, unit, total, done, every_s, clock
        self.start = self.last = clock()
        self.first: tuple[float, int] | None = None  # (time, done) at the first update

    def update(self, n: int, note: str = "") -> None:
        """``n`` more done; ``note`` ends the line when one is printed."""
        self.done += n
        now = self.clock()
        if self.first is None:
            self.first = (now, self.done)
        if now - self.last < self.every_s and self.done < self.total:
            return
        self.last = now
        since, at = self.first
        left = "" if self.done >= self.total or self.done == at else f", about {(now - since) * (self.total - self.done) / (self.done - at):.0f} s left"
        print(f"{self.what}: {self.done} of {self.total} {self.unit} ({100 * self.done / self.total:.0f} %) after {now - self.start:.0f} s{left}{note}",
              file=sys.stderr, flush=True)
