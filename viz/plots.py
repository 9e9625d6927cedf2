"""Time-series plots of a run (matplotlib PNGs in ``plots/``), an observer.

Every run plots the foundation's series (tracking error, communication-graph
edges); strategies add theirs through ``commands.info['scalars']`` (name ->
value), each drawn in its own panel so a user can look instead of reading
JSON. Sampled every ``period_s`` of sim time.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.observers import Frame, tracking_errors

PANELS_PER_FIGURE = 6


class PlotRecorder:
    def __init__(self, robot_kinds: tuple[str, ...], folder: str | Path, period_s: float = 0.1):
        self.folder = Path(folder)
        self.period_s = period_s
        self.kinds = robot_kinds
        self.series: dict[str, list[tuple[float, float]]] = defaultdict(list)
        self._next_time = 0.0
        self.files: list[str] = []

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

    def close(self, status: str) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        self.folder.mkdir(parents=True, exist_ok=True)
        names = list(self.series)
        for page, start in enumerate(range(0, len(names), PANELS_PER_FIGURE)):
            chunk = names[start : start + PANELS_PER_FIGURE]
            fig, axes = plt.subplots(len(chunk), 1, figsize=(8, 1.9 * len(chunk) + 0.6), sharex=True, squeeze=False)
            for ax, name in zip(axes[:, 0], chunk):
                data = np.array(self.series[name])
                ax.plot(data[:, 0], data[:, 1], lw=1.2)
                ax.set_ylabel(name, fontsize=8)
                ax.grid(alpha=0.3)
            axes[-1, 0].set_xlabel("sim time (s)")
            fig.suptitle(f"run {status}", fontsize=9)
            fig.tight_layout()
            path = self.folder / ("timeseries.png" if page == 0 else f"timeseries_{page + 1}.png")
            fig.savefig(path, dpi=110)
            plt.close(fig)
            self.files.append(str(path))
