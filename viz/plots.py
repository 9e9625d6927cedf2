"""Time-series plots of a run (matplotlib PNGs in ``plots/``), an observer.

Every run plots the foundation's series (tracking error, communication-graph
edges); strategies add theirs through ``commands.info['scalars']`` (name ->
value), each drawn in its own panel, and ``commands.info['robot_scalars']``
(name -> (N,) values, NaN where undefined), drawn as one line per robot in
one panel (e.g. seed 001's Fig. 14d: each robot's role; codes named on the
axis from ``commands.info['robot_scalar_levels']``), so a user can look
instead of reading JSON. NaN (undefined, e.g. t*(t) before the first
agreement) is a gap, never a value. Sampled every ``period_s`` of sim time; pages of
``PANELS_PER_FIGURE`` panels: ``timeseries.png``, ``timeseries_2.png``, ...
Drawn by a :class:`Painter` process that imports matplotlib while the run
goes on, so a run's end waits for the drawing only.
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
        self._painter = Painter()
        self.levels: dict[str, dict[float, str]] = {}  # coded per-robot series: value -> label

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
        for name, levels in frame.commands.info.get("robot_scalar_levels", {}).items():
            self.levels[name] = levels

    def panels(self) -> list[str]:
        """Panel titles in drawing order: the series, then the per-robot series."""
        return list(self.series) + [name + PER_ROBOT_SUFFIX for name in self.robot_series]

    def close(self, status: str) -> None:
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
        self.folder.mkdir(parents=True, exist_ok=True)
        self.files += self._painter.draw(pages, f"run {status}", self.robot_names)


class Painter:
    """Draws plot pages in a process of its own, started when the run starts.

    Importing matplotlib costs about a second of CPU, more than drawing a
    run's pages: the child pays it while the simulation runs, so the end of a
    run only waits for the drawing. Where no child process can be started
    (a daemonic pool worker, say) the pages are drawn in this process.
    """

    def __init__(self):
        import multiprocessing

        self._conn = self._process = None
        try:
            context = multiprocessing.get_context("spawn")
            self._conn, child = context.Pipe()
            self._process = context.Process(target=_paint_worker, args=(child,), daemon=True, name="plot-painter")
            self._process.start()
            child.close()
        except (AssertionError, OSError, RuntimeError):  # no child processes here
            self._conn = self._process = None

    def draw(self, pages, title: str, robot_names) -> list[str]:
        """Draw ``pages`` [(png path, [(panel title, times or (T, 2) series, None or (T, N) values)])]."""
        if self._process is not None:
            try:
                self._conn.send((pages, title, robot_names))
                files = self._conn.recv()
                self._process.join()
                return files
            except (EOFError, OSError, BrokenPipeError):  # the child died: draw here instead
                self._process = None
        return draw_pages(pages, title, robot_names)


def _paint_worker(conn) -> None:
    _matplotlib()  # the expensive import, while the run goes on
    try:
        pages, title, robot_names = conn.recv()
    except EOFError:  # the run ended without plots
        return
    conn.send(draw_pages(pages, title, robot_names))


def _matplotlib():
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    return Figure


def draw_pages(pages, title: str, robot_names) -> list[str]:
    """Write one PNG per page; returns the paths. A panel is (title, data,
    values, levels): data (T, 2) [time, value] for a series, or times (T,)
    with values (T, N) for a per-robot series, whose codes ``levels``
    [(value, label)] (or None) are named on the axis."""
    figure_class = _matplotlib()
    files = []
    for path, panels in pages:
        height = 1.9 * len(panels) + 0.6
        # The Figure API (no pyplot state) and fixed margins: tight_layout took a fifth of the drawing.
        fig = figure_class(figsize=(8, height))
        axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)
        fig.subplots_adjust(left=0.11, right=0.98, top=1.0 - 0.35 / height, bottom=0.45 / height, hspace=0.12)
        legend = True  # on the first per-robot panel of a page
        for ax, (name, data, values, levels) in zip(axes[:, 0], panels):
            if values is None:
                ax.plot(data[:, 0], data[:, 1], lw=1.2)
            else:
                _draw_per_robot(ax, data, values, robot_names, legend)
                legend = False
                if levels:  # codes (e.g. roles): name each level on the axis
                    ax.set_yticks([v for v, _ in levels], [label for _, label in levels], fontsize=7)
                    ax.set_ylim(levels[0][0] - 0.5, levels[-1][0] + 0.5)
            ax.set_ylabel(name, fontsize=8)
            ax.grid(alpha=0.3)
        axes[-1, 0].set_xlabel("sim time (s)")
        fig.suptitle(title, fontsize=9)
        fig.savefig(path, dpi=110, pil_kwargs={"compress_level": 1})  # zlib level 6 took an eighth of the drawing
        files.append(path)
    return files


def _draw_per_robot(ax, times: np.ndarray, values: np.ndarray, robot_names, legend: bool) -> None:
    for robot in range(values.shape[1]):
        label = robot_names[robot] if robot_names is not None else f"robot {robot}"
        ax.plot(times, values[:, robot], lw=1.0, label=label)
    if legend and robot_names is not None and values.shape[1] <= LEGEND_MAX_ROBOTS:
        ax.legend(fontsize=6, ncol=min(values.shape[1], 6), loc="upper right")
