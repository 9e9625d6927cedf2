"""Progress of a long ``tether run`` on stderr.

On a terminal: a tqdm bar over simulated seconds with the real-time factor
and the strategy's headline figure (targets visited, meetings held) from its
``summary()``. Into a pipe or a log: one plain line every 10 % of the
duration cap or every 30 s of wall time, whichever comes first, so logs get
no carriage returns. A mission that ends before the cap ends the bar where
it stopped (``close``), with its status.

A run that compiles kernels (the first of each scenario on a machine: numba's
cache then holds them) says so when the compile starts and, at the end, how
long it took, so the slow first seconds are explained.
"""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

from sim.compiled import CompileWatch

PLAIN_EVERY_FRACTION = 0.1  # plain lines: every 10 % of the duration ...
PLAIN_EVERY_WALL_S = 30.0  # ... or every 30 s of wall time
BAR_HEADLINE_EVERY_S = 1.0  # the bar's headline figure is refreshed at most this often (wall s)


def headline(summary: dict[str, Any]) -> str:
    """The one figure a user watches, from a strategy's ``summary()``: targets
    visited (Nestmeyer et al. 2017), meetings held (Khodayi-mehr et al. 2019), else nothing."""
    if "targets_visited" in summary and "targets_total" in summary:
        return f"targets {summary['targets_visited']}/{summary['targets_total']}"
    if summary.get("meetings_scheduled"):
        return f"meetings {summary['meetings_held']}/{summary['meetings_scheduled']}"
    if "meetings_held" in summary and "plans" in summary:
        return f"paths planned {summary['plans']}"
    return ""


def _strategy_headline(sim) -> str:
    summary = getattr(sim.strategy, "summary", None)
    return headline(summary()) if callable(summary) else ""


class RunProgress:
    """The ``progress`` callback of :func:`tether.runner.run`: called with the
    :class:`sim.loop.Simulation` every so many ticks; ``close`` after the run."""

    def __init__(self, duration_s: float, stream: TextIO | None = None, bar: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        self.duration_s = duration_s
        self.bar_on = self.stream.isatty() if bar is None else bar
        self.start = time.perf_counter()
        self._bar = None
        self._last_headline_wall = -float("inf")
        self._next_fraction = PLAIN_EVERY_FRACTION
        self._next_wall = PLAIN_EVERY_WALL_S
        self.lines = 0
        self._time_s = 0.0
        self._headline = ""
        self.compiles = CompileWatch(on_first=lambda: self._say(
            "compiling kernels (once: later runs load them from the cache) ...")).open()
        if self.bar_on:
            from tqdm import tqdm

            self._bar = tqdm(total=round(duration_s, 2), unit="sim s", file=self.stream, dynamic_ncols=True,
                             bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} sim s [{elapsed}<{remaining}{postfix}]")

    def _rate(self, wall: float) -> float:
        return self._time_s / wall if wall > 0 else 0.0

    def __call__(self, sim) -> None:
        self._time_s = float(sim.time_s)
        wall = time.perf_counter() - self.start
        if self._bar is not None:
            if wall - self._last_headline_wall >= BAR_HEADLINE_EVERY_S:
                self._headline = _strategy_headline(sim)
                self._last_headline_wall = wall
            self._bar.update(round(self._time_s - self._bar.n, 2))
            postfix = f"x{self._rate(wall):.2f} real time"
            self._bar.set_postfix_str(f"{postfix}, {self._headline}" if self._headline else postfix, refresh=False)
            return
        fraction = self._time_s / self.duration_s if self.duration_s > 0 else 1.0
        if fraction + 1e-9 >= self._next_fraction or wall >= self._next_wall:
            while self._next_fraction <= fraction + 1e-9:
                self._next_fraction += PLAIN_EVERY_FRACTION
            self._next_wall = wall + PLAIN_EVERY_WALL_S
            self._line(self._time_s, wall, _strategy_headline(sim))

    def _line(self, time_s: float, wall: float, figure: str) -> None:
        parts = [f"t = {time_s:.1f}/{self.duration_s:.1f} s ({100 * time_s / self.duration_s:.0f} %)",
                 f"{wall:.0f} s wall", f"x{time_s / wall if wall > 0 else 0.0:.2f} real time"]
        if figure:
            parts.append(figure)
        print("  " + ", ".join(parts), file=self.stream, flush=True)
        self.lines += 1

    def _say(self, text: str) -> None:
        if self._bar is not None:
            self._bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def close(self, metrics: dict[str, Any] | None = None) -> None:
        """End the bar where the run stopped (a mission may end before the
        cap) with the final headline, and say how long compiling took."""
        self.compiles.close()
        if self._bar is None:
            self._compile_note()
            return
        if metrics is not None:
            self._time_s = float(metrics.get("sim_time_s", self._time_s))
            self._headline = headline(metrics) or self._headline
            self._bar.total = round(self._time_s, 2)  # a mission that ended early: the bar ends full
        self._bar.update(round(self._time_s - self._bar.n, 2))
        wall = time.perf_counter() - self.start
        postfix = f"x{self._rate(wall):.2f} real time"
        self._bar.set_postfix_str(f"{postfix}, {self._headline}" if self._headline else postfix, refresh=False)
        self._bar.close()
        self._bar = None
        self._compile_note()

    def _compile_note(self) -> None:
        if self.compiles.count:
            self._say(f"compiled kernels in {self.compiles.seconds:.0f} s (once; the next run loads them from the "
                      "cache)")
            self.compiles.count = 0  # said once, however often close is called
