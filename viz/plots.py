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

import errno
from collections import defaultdict
from pathlib import Path

import numpy as np

from sim.loop import ObserverFailure
from sim.observers import Frame, Observer, link_figures, tracking_errors
from viz.painter import Painters, page_layout

PANELS_PER_FIGURE = 6
PER_ROBOT_SUFFIX = ", per robot"
# The foundation's series (keys; their labels in LABELS).
TRACKING_ERROR, LINKS, COMM_LAMBDA2, DELIVERY = ("tracking_error_mean_m", "links", "comm_lambda2",
                                                 "radio_delivery_mean")
# Each method's headline metrics first, in this order (the intermittent paper's e_g and lambda-bar;
# the continuous-connectivity paper's lambda2, targets visited and stretch).
HEADLINE = ("e_g_m", "lambda_max_m2", "lambda2", "targets_visited", "stretch_m")
# A strategy's series that says what a foundation series says: the foundation's is left out.
SAME_AS = {"edges": LINKS}
# Axis labels: words and a unit ("1" for a pure number). Keys not listed are spelled out from the
# key, the unit read from its suffix (UNIT_SUFFIXES).
LABELS = {
    TRACKING_ERROR: "tracking error, mean over robots (m)",
    LINKS: "communication links (count)",
    COMM_LAMBDA2: "lambda2, communication graph (1)",
    DELIVERY: "radio delivery, mean over pairs in range (ratio)",
    "e_g_m": "e_g, global target error (m)",
    "lambda_max_m2": "lambda-bar, largest covariance eigenvalue (m²)",
    "t_star_s": "t*(t), last agreed step (s)",
    "t_star_lag_s": "t*(t) lag behind sim time (s)",
    "local_error_m": "local target error (m)",
    "lambda2": "lambda2, weighted sensing graph (1)",
    "lambda2_estimate_mean": "lambda2, robots' mean estimate (1)",
    "edges": "graph edges (count)",
    "stretch_m": "stretch (m)",
    "targets_visited": "targets visited (count)",
    "prime_traveler": "prime traveler (robot index)",
    "prime_efficiency": "prime traveler's efficiency (1)",
    "prime_efficiency_estimate_mean": "prime's efficiency, mean estimate (1)",
    "alignment_mean": "alignment, mean over robots (1)",
    "gain_mean": "gain, mean over robots (1)",
    "connectivity_force_max_n": "connectivity force, largest (N)",
    "min_robot_distance_m": "closest robot pair (m)",
    "min_obstacle_distance_m": "closest robot to an obstacle (m)",
    "radio_tick_delivery_ratio": "radio delivery this tick (ratio)",
    "radio_tick_latency_mean_s": "radio latency, mean this tick (s)",
    "formation_connected_share": "formation connected (share)",
    "role": "role",
}
UNIT_SUFFIXES = (("_m2", "m²"), ("_mps", "m/s"), ("_m", "m"), ("_s", "s"), ("_n", "N"), ("_ratio", "ratio"),
                 ("_share", "share"))


def axis_label(key: str, integer: bool = False) -> str:
    """Words and a unit for a series ``key``: :data:`LABELS`, else the key spelled out with
    the unit of its suffix ("count" for integer values, "1" for other pure numbers)."""
    if key in LABELS:
        return LABELS[key]
    for suffix, unit in UNIT_SUFFIXES:
        if key.endswith(suffix):
            return f"{key[: -len(suffix)].replace('_', ' ')} ({unit})"
    return f"{key.replace('_', ' ')} ({'count' if integer else '1'})"


def per_robot(label: str) -> str:
    """"gain (1)" -> "gain, per robot (1)"."""
    words, unit = (label[: label.rindex(" (")], label[label.rindex(" ("):]) if label.endswith(")") else (label, "")
    return f"{words}{PER_ROBOT_SUFFIX}{unit}"


def _is_integer(values: np.ndarray) -> bool:
    finite = values[np.isfinite(values)]
    return bool(finite.size) and bool(np.all(finite == np.round(finite)))


METHOD_NAMES = {
    "connected": "continuous connectivity (Nestmeyer et al. 2017)",
    "intermittent": "intermittent connectivity (Khodayi-mehr et al. 2019)",
    "all_time": "all-time connected formation (baseline)",
    "random_meeting": "random meeting points (baseline)",
    "connected_tracking": "connected tracking (continuous connectivity on the tracking task)",
    "waypoints": "waypoints",
}


def run_title(scenario: str, method: str, seed: int | None) -> str:
    """A plot page's title: scenario, method and seed (the run's status is added at its end)."""
    return f"{scenario} · {METHOD_NAMES.get(method, method)}" + ("" if seed is None else f" · seed {seed}")


class PlotRecorder(Observer):
    def __init__(self, robot_kinds: tuple[str, ...], folder: str | Path, period_s: float = 0.1,
                 robot_names: tuple[str, ...] | None = None, title: str = "run"):
        self.folder = Path(folder)
        self.title = title  # scenario, method and seed (run_title)
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
        self.series[TRACKING_ERROR].append((t, float(error.mean())))
        figures = link_figures(frame.observation, frame.failed)
        self.series[LINKS].append((t, float(figures.edges)))
        self.series[COMM_LAMBDA2].append((t, figures.comm_lambda2))
        self.series[DELIVERY].append((t, figures.radio_delivery_mean))
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
        """Panel keys in drawing order: the headline metrics, the other series, then the
        per-robot series (suffixed ``PER_ROBOT_SUFFIX``); a series with no value yet (all NaN)
        and a foundation series a strategy's repeats (:data:`SAME_AS`) get no panel."""
        repeated = {SAME_AS[key] for key in self.series if key in SAME_AS}
        series = [key for key in self.series if key not in repeated
                  and np.isfinite(np.array([v for _, v in self.series[key]], dtype=float)).any()]
        first = [key for key in HEADLINE if key in series]
        return first + [key for key in series if key not in first] + \
            [name + PER_ROBOT_SUFFIX for name in self.robot_series]

    def start_closing(self, status: str) -> None:
        """Hand the data to the painters; they draw while the other observers close."""
        self.folder.mkdir(parents=True, exist_ok=True)
        self._painters.start(self._pages(), f"{self.title} · run {status}")
        self._closing = True

    def close(self, status: str) -> None:
        if not self._closing:
            self.start_closing(status)
        try:
            self.files += self._painters.finish()
        except OSError as err:  # a full disk: the pages written stay, the run ends "failed" naming it
            self.files += [path for path, _ in self._pages() if Path(path).is_file()]
            code = errno.errorcode.get(err.errno, err.errno)
            raise ObserverFailure(f"plots failed, not every page written: {err.strerror} ({code})") from None

    def _pages(self) -> list[tuple[str, list]]:
        """[(png path, panels)], ``PANELS_PER_FIGURE`` panels a page (see viz.painter.Panel)."""
        pages = []
        names = self.panels()
        for page, start in enumerate(range(0, len(names), PANELS_PER_FIGURE)):
            panels = []
            for name in names[start : start + PANELS_PER_FIGURE]:
                if name in self.series:
                    data = np.array(self.series[name])
                    integer = _is_integer(data[:, 1])
                    panels.append((axis_label(name, integer), data, None, None, integer))
                else:
                    series = name[: -len(PER_ROBOT_SUFFIX)]
                    samples = self.robot_series[series]
                    levels = sorted(self.levels[series].items()) if series in self.levels else None
                    values = np.array([v for _, v in samples])
                    integer = levels is None and _is_integer(values)
                    panels.append((per_robot(axis_label(series, integer)), np.array([t for t, _ in samples]),
                                   values, levels, integer))
            path = self.folder / ("timeseries.png" if page == 0 else f"timeseries_{page + 1}.png")
            pages.append((str(path), panels))
        return pages
