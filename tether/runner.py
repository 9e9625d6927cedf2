"""A run, composed: the scenario's strategy and low-level control, the
observers a run asks for, the staging folder, ``metrics.json``.

:func:`run` is importable and headless; the CLI and the sweeps are thin
layers over it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

import tether.catalog  # noqa: F401 (registers the built-in strategies and scenarios)
from controllers.lowlevel.actuation import LowLevelControl
from sim.config import ConfigError
from sim.estimation_observer import EstimationMetrics
from sim.faults import seconds
from sim.loop import Simulation, mujoco_warnings, run_ticks, timing_summary
from sim.observers import LinkMetrics, Observer, TrackingMetrics
from sim.outputs import ProgressFile, Staging, json_safe, non_finite_fields, write_json
from sim.scenario import Scenario
from sim.strategy import Status, build_strategy
from sim.validate import check_output_folder, check_scenario


@dataclass
class RunResult:
    status: Status
    metrics: dict[str, Any]
    out_dir: Path | None
    files: dict[str, str] = field(default_factory=dict)
    trajectory: np.ndarray | None = None  # (ticks, N, 3) body positions, when asked


def build_simulation(scenario: Scenario, rng: np.random.Generator | None = None) -> Simulation:
    """The scenario's world with its registered strategy and the robots' low-level control."""
    kind = scenario.strategy.kind
    return Simulation(scenario, lambda params: build_strategy(kind, params), LowLevelControl, rng)


def _observers(sim: Simulation, folder: Path | None, video: bool, rrd: bool, live: Any,
               final: Callable[[str], str]) -> tuple[list[Observer], dict[str, Any], dict[str, str]]:
    """The run's observers, writing into ``folder`` (the staging folder);
    ``final(name)`` is where a file ends up. Returns (observers, named
    observers, files)."""
    scenario = sim.scenario
    named: dict[str, Any] = {"estimation": EstimationMetrics(), "tracking": TrackingMetrics(sim.world.robot_kinds),
                             "links": LinkMetrics()}
    observers: list[Observer] = list(named.values())
    files: dict[str, str] = {}
    if folder is None:
        return observers, named, files
    from viz.plots import PlotRecorder, run_title

    named["plots"] = PlotRecorder(sim.world.robot_kinds, folder / "plots", robot_names=sim.world.robot_names,
                                  title=run_title(scenario.name, scenario.strategy.kind, scenario.seed))
    named["progress"] = ProgressFile(folder / "progress.json")
    # Progress closes first: its status leaves "running" as closing starts (the video may drain for a while).
    observers.append(named["progress"])
    if video:
        from viz.video import VideoRecorder

        files["video"] = final("video.mp4")
        observers.append(VideoRecorder(sim.world, scenario.video, str(folder / "video.mp4"), sim.dt))
    if rrd or live is not None:
        from viz.recording import RerunRecorder

        files["recording"] = final("run.rrd")
        named["recorder"] = RerunRecorder(sim.world, str(folder / "run.rrd"), scenario.name, live_stream=live)
        if not scenario.radio.is_ideal:  # the radio map of robot 0 at its start, once (docs/radio.md)
            from tether.radiomap import RECORDING_CELLS, world_radio_map

            named["recorder"].log_radio_map(world_radio_map(sim.world, scenario.radio, cells=RECORDING_CELLS),
                                            sim.world.robot_names[0])
        observers.append(named["recorder"])
    # The plots close last: a recording given up on a full disk has removed its files by then, and the
    # pages fit where they can (their painters start drawing when closing starts, for all observers).
    observers.append(named["plots"])
    return observers, named, files


def run(
    scenario: Scenario,
    out_dir: str | Path | None = None,
    video: bool = False,
    rrd: bool = False,
    live: Any = None,
    keep_trajectory: bool = False,
    progress: Callable[[Simulation], None] | None = None,
    extra_observers: Sequence[Observer] = (),
) -> RunResult:
    """Run a scenario headless; write metrics.json (+ video.mp4, run.rrd, plots/) to out_dir.

    Every input is checked first (ConfigError, nothing built or written:
    sim.validate). The run writes into a staging folder beside ``out_dir``
    and moves its files into place when it ends (sim.outputs), so a refused
    or crashed run leaves earlier results untouched. Status: see
    :class:`sim.strategy.Status` and :func:`sim.loop.end_of_run`.
    ``extra_observers`` see every tick after the built-in ones and are closed
    with them. ``progress`` is called with the :class:`Simulation` every 100
    ticks (e.g. :class:`tether.progress.RunProgress`).
    """
    wall_start = time.perf_counter()
    mujoco_warnings.clear()
    out = Path(out_dir) if out_dir is not None else None
    if out is None and (video or rrd or live is not None):
        raise ConfigError("--out", "a video or a recording needs an output folder")
    if out is not None:
        check_output_folder(out)
    check_scenario(scenario)
    sim = build_simulation(scenario)
    if video:
        from viz.video import resolve_camera

        resolve_camera(sim.world.model, scenario.video.camera)  # refuse before writing anything
    from viz.painter import children_killed_on_error  # here: a signal in its import leaves no staging folder

    staging = Staging(out) if out is not None else None
    try:
        with children_killed_on_error():
            observers, named, files = _observers(sim, staging.path if staging else None, video, rrd, live,
                                                 staging.final if staging else str)
    except BaseException:
        if staging is not None:
            staging.discard()
        raise
    observers += list(extra_observers)
    setup_s = time.perf_counter() - wall_start
    written: dict[str, Any] = {}

    def write_metrics(status: Status, message: str, closing_s: float) -> None:
        written["metrics"] = _metrics(scenario, sim, status, message, time.perf_counter() - wall_start, named,
                                      timing_summary(sim.timing, setup_s, closing_s))
        if staging is not None:
            write_json(staging.path / "metrics.json", written["metrics"])
            staging.commit()

    try:
        outcome = run_ticks(sim, observers, scenario.duration_s, progress, keep_trajectory, write_metrics)
    except BaseException:  # a bug (or a forced stop): keep the earlier results
        if staging is not None:
            staging.discard()
        raise
    if staging is not None:
        files = {name: path for name, path in files.items() if Path(path).exists()}  # e.g. a recording given up
        if named["plots"].files:
            files["plots"] = staging.final("plots")
        files["metrics"] = staging.final("metrics.json")
    return RunResult(outcome.status, written["metrics"], out, files, outcome.trajectory)


def _failure_detections(metrics: dict[str, Any]) -> None:
    """Each failed robot's ``detected_after_s`` in ``faults``: from its failure to the first time a team
    mate counted it silent (the strategy's ``silence_detected_s``; null: never within the run). Only for
    strategies that watch heartbeats."""
    detected = metrics.get("silence_detected_s")
    if "faults" not in metrics:
        return
    drops = metrics.get("dropped_robots", ())
    failed = set()
    for fault in metrics["faults"]:
        if fault["kind"] != "robot_failure" or not fault["happened"]:
            continue
        robot = fault["robot"]
        failed.add(robot)
        if detected is not None:
            after = [round(t - fault["at_s"], 6) for t in detected[robot] if t >= fault["at_s"]]
            fault["detected_after_s"] = min(after) if after else None
            noticed = (f"noticed by a team mate {min(after):.2f} s after its failure" if after
                       else "never noticed by its team mates")
            metrics["message"] += f"; robot {robot}'s silence {noticed}"
        if "dropped_robots" in metrics:  # a strategy that drops silent robots from its team
            after_failure = [d for d in drops if d["robot"] == robot and d["dropped_at_s"] >= fault["at_s"] - 1e-9]
            _failure_consequence(metrics, fault, after_failure[0] if after_failure else None)
    _drops_of_healthy_robots(metrics, [d for d in drops if d["robot"] not in failed])


def _drops_of_healthy_robots(metrics: dict[str, Any], drops: list[dict[str, Any]]) -> None:
    """The run's message names each robot that no fault failed but that its team dropped as silent (behind a
    blackout, say), and when it was taken back."""
    for robot in sorted({drop["robot"] for drop in drops}):
        own = [drop for drop in drops if drop["robot"] == robot]
        text = f"; robot {robot} dropped as silent at {seconds(own[0]['dropped_at_s'])} s"
        if len(own) > 1:
            text += f" (and {len(own) - 1} more times)"
        back = own[-1].get("taken_back_at_s")
        text += f", taken back at {seconds(back)} s" if back is not None else ", not taken back"
        for drop in own:
            if drop.get("token_reissued_to") is not None:
                text += f"; the token was re-issued to robot {drop['token_reissued_to']}"
        metrics["message"] += text


def _failure_consequence(metrics: dict[str, Any], fault: dict[str, Any], dropped: dict[str, Any] | None) -> None:
    """A failed robot's ``dropped_after_s``, ``targets_reassigned`` and ``targets_lost`` in ``faults``
    (the strategy's ``dropped_robots``), and the consequence in the run's message."""
    robot, at_s = fault["robot"], fault["at_s"]
    if dropped is None or dropped["dropped_at_s"] < at_s - 1e-9:
        fault.update(dropped_after_s=None, targets_reassigned=0, targets_lost=0)
        metrics["message"] += f"; robot {robot} failed at {seconds(at_s)} s and was never dropped from the team"
        return
    reassigned, lost = dropped["targets_reassigned"], dropped["targets_lost"]
    after = round(dropped["dropped_at_s"] - at_s, 6)
    fault.update(dropped_after_s=after, targets_reassigned=reassigned, targets_lost=lost)
    fault.setdefault("detected_after_s", after)
    text = f"; robot {robot} failed at {seconds(at_s)} s"
    total = reassigned + lost
    text += f"; {reassigned} of its {total} targets reassigned" if total else "; it had no target to hand on"
    if lost:
        text += f", {lost} lost (no explorer left)"
    if dropped["token_reissued_to"] is not None:
        text += f"; the token was re-issued to robot {dropped['token_reissued_to']}"
    metrics["message"] += text


def _meetings_without_failed(metrics: dict[str, Any]) -> None:
    """For the meeting methods: each failed robot's ``detected_after_s``, from its failure to the
    first meeting that went on without it (``members_given_up``; null: none within the run)."""
    given_up = metrics.get("members_given_up")
    if given_up is None or "faults" not in metrics:
        return
    for fault in metrics["faults"]:
        if fault["kind"] == "robot_failure" and fault["happened"]:
            after = [t - fault["at_s"] for r, t in given_up if r == fault["robot"] and t >= fault["at_s"]]
            fault["detected_after_s"] = min(after) if after else None


def _errors_around_failure(metrics: dict[str, Any], estimation: EstimationMetrics) -> None:
    """Mean e_g before and after the first robot failure that happened, for a tracking run."""
    failures = [f for f in metrics.get("faults", ()) if f["kind"] == "robot_failure" and f["happened"]]
    if not failures or not estimation.steps:
        return
    around = estimation.around(min(f["at_s"] for f in failures))
    metrics.update(around)
    if around["e_g_before_fault_m"] is not None and around["e_g_after_fault_m"] is not None:
        metrics["message"] += (f"; e_g {around['e_g_before_fault_m']:.2f} m before, "
                               f"{around['e_g_after_fault_m']:.2f} m after")


def _metrics(scenario: Scenario, sim: Simulation, status: Status, message: str, wall: float,
             named: dict[str, Any], timing: dict[str, Any]) -> dict[str, Any]:
    """The run's metrics.json: the foundation's figures and the strategy's
    summary; a non-finite figure becomes null and the message names it."""
    metrics: dict[str, Any] = {
        "scenario": scenario.name,
        "strategy": scenario.strategy.kind,
        "seed": scenario.seed,
        "status": status.value,
        "message": message,
        "sim_time_s": sim.time_s,
        "wall_time_s": wall,
        "real_time_factor": sim.time_s / wall if wall > 0 else None,
        "n_robots": sim.world.n_robots,
        "n_quadrotors": int(len(sim.world.kind_index["quadrotor"])),
        "n_ground_robots": int(len(sim.world.kind_index["ground"])),
        # The scene's moving targets ([[targets]], tracked by range sensors), not
        # the connected method's points to visit (its targets_to_visit).
        "n_moving_targets": sim.targets.n_targets,
        "control_ticks": sim.tick_count,
        "timing": timing,
        **named["tracking"].summary(),
        **named["links"].summary(),
        **named["estimation"].summary(),
        **sim.radio_summary(),
        **sim.fault_summary(),
        **sim.strategy.summary(),
    }
    _failure_detections(metrics)
    _meetings_without_failed(metrics)
    _errors_around_failure(metrics, named["estimation"])
    missing = non_finite_fields(metrics)
    if missing:
        note = f"not finite, written as null: {', '.join(missing)}"
        metrics["message"] = f"{message}; {note}" if message else note
    return json_safe(metrics)
