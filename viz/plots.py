"""Time-series plots of a run (matplotlib PNGs in ``plots/``), an observer.

Every run plots the foundation's series (tracking error, communication-graph
edges); strategies add theirs through ``commands.scalars`` (name -> value;
with the loop's ``e_g_m``: ``frame.scalars``), each drawn in its own panel,
and ``commands.decorations.robot_scalars`` (name -> (N,) values, NaN where
undefined), drawn as one line per robot in one panel (e.g. the continuous-connectivity paper's Fig.
14d: each robot's role; codes named on the axis from
``commands.decorations.robot_scalar_levels``), so a user can look
instead of reading JSON. NaN (undefined, e.g. t*(t) before the first
agreement) is a gap, never a value. Sampled every ``period_s`` of sim time; pages of
``PANELS_PER_FIGURE`` panels: ``timeseries.png``, ``timeseries_2.png``, ...
Drawn by painter processes (viz.painter) that build the pages' figures
while the run goes on, so a run's end waits only for filling them in.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.observers import Frame, Observer, link_figures, tracking_errors
from viz.painter import Painters, page_layout

PANELS_PER_FIGURE = 6
PER_ROBOT_SUFFIX = " (per robot)"


class PlotRecorder(Observer):
    def __init__(self, robot_kinds: tuple[str, ...], folder: str | Path, period_s: float = 0.1,
                 robot_names: tuple[str, ...] | None = None):
        self.folder = Path(folder)
        self.period_s = period_s
        self.kinds = robot_kinds
        self.robot_names = robot_names
        self.series: dict[str, list[tuple[float, float]]] = defaultdict(list)
        self.robot_series: dict[str, list[tuple[float, np.ndarray]]] = defaultdict(list)
        self._next_time = 0.0
        self.files: list[str] = []
        self.levels: dict[str, dict[float, str]] = {}  # coded per-robot series: value -> label
        self._painters = Painters(robot_names)
        self._planned: tuple[int, int, int] = (0, 0, 0)  # series, per-robot series, levels: when planned
        self._closing = False

    def reads_decorations(self, time_s: float) -> bool:
        """The strategy's scalars are read only on sampled ticks."""
        return time_s + 1e-9 >= self._next_time

    def on_tick(self, frame: Frame) -> None:
        t = frame.observation.time_s
        if t + 1e-9 < self._next_time:
            return
        self._next_time += self.period_s
        error = tracking_errors(self.kinds, frame.observation.position, frame.commands.position)
        self.series["tracking error, mean over robots (m)"].append((t, float(error.mean())))
        figures = link_figures(frame.observation)
        self.series["communication links"].append((t, float(figures.edges)))
        self.series["communication graph lambda2"].append((t, figures.comm_lambda2))
        self.series["radio delivery mean, pairs in comm range"].append((t, figures.radio_delivery_mean))
        for name, value in frame.scalars.items():
            self.series[name].append((t, float(value)))
        decorations = frame.commands.decorations
        for name, values in decorations.robot_scalars.items():
            self.robot_series[name].append((t, np.array(values, dtype=float)))
        for name, levels in decorations.robot_scalar_levels.items():
            self.levels[name] = levels
        if (len(self.series), len(self.robot_series), len(self.levels)) != self._planned:
            # Series only ever appear: a new count is a new layout for the painters to build.
            self._planned = (len(self.series), len(self.robot_series), len(self.levels))
            self._painters.plan([(path, page_layout(panels)) for path, panels in self._pages()])

    def panels(self) -> list[str]:
        """Panel titles in drawing order: the series, then the per-robot series."""
        return list(self.series) + [name + PER_ROBOT_SUFFIX for name in self.robot_series]

    def start_closing(self, status: str) -> None:
        """Hand the data to the painters; they draw while the other observers close."""
        self.folder.mkdir(parents=True, exist_ok=True)
        self._painters.start(self._pages(), f"run {status}")
        self._closing = True

    def close(self, status: str) -> None:
        if not self._closing:
            self.start_closing(status)
        self.files += self._painters.finish()

    def _pages(self) -> list[tuple[str, list]]:
        """[(png path, panels)], ``PANELS_PER_FIGURE`` panels a page (see viz.painter.Panel)."""
        pages = []
        names = self.panels()
        for page, start in enumerate(range(0, len(names), PANELS_PER_FIGURE)):
            panels = []
            for name in names[start : start + PANELS_PER_FIGURE]:
                if name in self.series:
                    panels.append((name, np.array(self.series[name]), None, None))
                else:
                    series = name[: -len(PER_ROBOT_SUFFIX)]
                    samples = self.robot_series[series]
                    levels = sorted(self.levels[series].items()) if series in self.levels else None
                    panels.append((name, np.array([t for t, _ in samples]), np.array([v for _, v in samples]), levels))
            path = self.folder / ("timeseries.png" if page == 0 else f"timeseries_{page + 1}.png")
            pages.append((str(path), panels))
        return pages
