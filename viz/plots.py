"""Time-series plots of a run (matplotlib PNGs in ``plots/``), an observer.

Every run plots the foundation's series (tracking error, communication-graph
edges); strategies add theirs through ``commands.info['scalars']`` (name ->
value), each drawn in its own panel, and ``commands.info['robot_scalars']``
(name -> (N,) values, NaN where undefined), drawn as one line per robot in
one panel (e.g. seed 001's Fig. 14d: each robot's role), so a user can look
instead of reading JSON. Sampled every ``period_s`` of sim time; pages of
``PANELS_PER_FIGURE`` panels: ``timeseries.png``, ``timeseries_2.png``, ...
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.observers import Frame, tracking_errors

PANELS_PER_FIGURE = 6
LEGEND_MAX_ROBOTS = 12  # per-robot panels name their lines up to this many robots
PER_ROBOT_SUFFIX = " (per robot)"


class PlotRecorder:
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

    def reads_info(self, time_s: float) -> bool:
        """The strategy's scalars are read only on sampled ticks."""
        return time_s + 1e-9 >= self._next_time

    def on_tick(self, frame: Frame) -> None:
        t = frame.observation.time_s
        if t + 1e-9 < self._next_time:
            return
        self._next_time += self.period_s
        error = tracking_errors(self.kinds, frame.observation.position, frame.commands.position)
        self.series["tracking error, mean over robots (m)"].append((t, float(error.mean())))
        self.series["communication links"].append((t, float(len(frame.observation.links.edges))))
        for name, value in frame.commands.info.get("scalars", {}).items():
            self.series[name].append((t, float(value)))
        for name, values in frame.commands.info.get("robot_scalars", {}).items():
            self.robot_series[name].append((t, np.array(values, dtype=float)))

    def panels(self) -> list[str]:
        """Panel titles in drawing order: the series, then the per-robot series."""
        return list(self.series) + [name + PER_ROBOT_SUFFIX for name in self.robot_series]

    def close(self, status: str) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        self.folder.mkdir(parents=True, exist_ok=True)
        names = self.panels()
        for page, start in enumerate(range(0, len(names), PANELS_PER_FIGURE)):
            chunk = names[start : start + PANELS_PER_FIGURE]
            fig, axes = plt.subplots(len(chunk), 1, figsize=(8, 1.9 * len(chunk) + 0.6), sharex=True, squeeze=False)
            legend = True  # on the first per-robot panel of a page
            for ax, name in zip(axes[:, 0], chunk):
                if name in self.series:
                    data = np.array(self.series[name])
                    ax.plot(data[:, 0], data[:, 1], lw=1.2)
                else:
                    self._draw_per_robot(ax, self.robot_series[name[: -len(PER_ROBOT_SUFFIX)]], legend)
                    legend = False
                ax.set_ylabel(name, fontsize=8)
                ax.grid(alpha=0.3)
            axes[-1, 0].set_xlabel("sim time (s)")
            fig.suptitle(f"run {status}", fontsize=9)
            fig.tight_layout()
            path = self.folder / ("timeseries.png" if page == 0 else f"timeseries_{page + 1}.png")
            fig.savefig(path, dpi=110)
            plt.close(fig)
            self.files.append(str(path))

    def _draw_per_robot(self, ax, samples: list[tuple[float, np.ndarray]], legend: bool) -> None:
        times = np.array([t for t, _ in samples])
        values = np.array([v for _, v in samples])  # (samples, N)
        for robot in range(values.shape[1]):
            label = self.robot_names[robot] if self.robot_names is not None else f"robot {robot}"
            ax.plot(times, values[:, robot], lw=1.0, label=label)
        if legend and self.robot_names is not None and values.shape[1] <= LEGEND_MAX_ROBOTS:
            ax.legend(fontsize=6, ncol=min(values.shape[1], 6), loc="upper right")
