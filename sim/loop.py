"""The step loop: sense -> strategy -> low-level control -> physics -> observers.

``run`` is importable and headless; the CLI is a thin layer over it. One
``np.random.Generator`` (seeded from the scenario) is created here and passed
down in a fixed order: target motion noise, range noise, then the strategy.
Observers only read, so video and recording never change the trajectory.
"""

from __future__ import annotations

import dataclasses
import copy
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import mujoco
import numpy as np

from sim.actuation import LowLevelControl
from sim.estimation_observer import EstimationMetrics
from sim.observers import Frame, LinkMetrics, Observer, TrackingMetrics
from sim.registry import strategy_class
from sim.config import ConfigError
from sim.scenario import Scenario, StrategyConfig
from sim.sensing import RaySensors
from sim.targets import TargetDriver, nominal_path_samples
from sim.types import Observation, WorldInfo
from sim.world import World, build_world

_WARNINGS_THAT_DIVERGE = tuple(int(w) for w in (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADCTRL,
))


_mujoco_warnings: list[str] = []

# Stages of a control tick timed by the loop (wall seconds, time.perf_counter),
# reported as metrics.json's ``timing`` block.
TIMED_STAGES = ("physics", "sensing", "strategy", "lowlevel", "observers")


def _collect_warning(text: str) -> None:
    # MuJoCo would print and append to MUJOCO_LOG.TXT in the working folder;
    # the loop reports divergence itself, with the first warning's text.
    _mujoco_warnings.append(text.strip())


mujoco.set_mju_user_warning(_collect_warning)


@dataclass
class RunResult:
    status: str  # "completed" | "diverged"
    metrics: dict[str, Any]
    out_dir: Path | None
    files: dict[str, str] = field(default_factory=dict)
    trajectory: np.ndarray | None = None  # (ticks, N, 3) body positions, when asked


class Simulation:
    """Owns the world and the per-tick pieces; ``tick()`` advances one control period."""

    def __init__(self, scenario: Scenario, rng: np.random.Generator | None = None):
        self.scenario = scenario
        self.rng = rng if rng is not None else np.random.default_rng(scenario.seed)
        self.targets = TargetDriver(scenario, self.rng)
        starts = self.targets.positions(0.0)
        samples = [nominal_path_samples(t) for t in scenario.targets]
        self.world: World = build_world(scenario, starts, samples)
        self.sensors = RaySensors(self.world, scenario.sensing.comm_range_m, scenario.sensing.target_range_m,
                                  scenario.sensing.range_noise)
        self.control = LowLevelControl(self.world)
        self.substeps = scenario.physics.substeps
        self.world.model.opt.timestep = scenario.physics.timestep_s
        self.dt = scenario.physics.control_period_s
        self.tick_count = 0
        self.time_s = 0.0
        self._next_reading_s = 0.0
        self._warning_numbers = self.world.data.warning.number  # (mjNWARNING,) view, updated by mj_step
        self._warnings = self._warning_count()
        # Index arrays for reading every robot's free-joint state in one fancy-index each.
        qpos_adr = np.asarray(self.world.qpos_adr)[:, None]
        qvel_adr = np.asarray(self.world.qvel_adr)[:, None]
        self._position_index = qpos_adr + np.arange(3)
        self._quaternion_index = qpos_adr + np.arange(3, 7)
        self._velocity_index = qvel_adr + np.arange(3)
        self._angular_index = qvel_adr + np.arange(3, 6)
        self.timing = dict.fromkeys(TIMED_STAGES, 0.0)  # wall s per stage, summed over ticks
        self.info = WorldInfo(
            robot_names=self.world.robot_names, robot_kinds=self.world.robot_kinds,
            obstacles=self.world.obstacles, bounds=self.world.bounds,
            control_period_s=self.dt, comm_range_m=scenario.sensing.comm_range_m,
            target_range_m=scenario.sensing.target_range_m, n_targets=self.targets.n_targets,
            sensing_period_s=scenario.sensing.period_s, target_motion=copy.deepcopy(self.targets.motion),
        )
        self._move_targets()
        self.control.hover_ctrl()
        mujoco.mj_forward(self.world.model, self.world.data)
        self.strategy = strategy_class(scenario.strategy.kind)(scenario.strategy.params)
        self.strategy.reset(self.info, self.observe(read_targets=False), self.rng)

    def set_strategy_params(self, params: Any) -> str:
        """Swap the running strategy's parameters between ticks (the next tick
        uses them): the strategy's own ``update_params`` when it has one and
        accepts them ("updated"), else a fresh strategy reset at the current
        state ("restarted"). ``params`` must already be validated (built
        through sim.config.build); ConfigError if the strategy refuses them,
        in which case the running strategy is kept unchanged."""
        kind = self.scenario.strategy.kind
        update = getattr(self.strategy, "update_params", None)
        try:
            if callable(update) and update(params):
                how = "updated"
            else:
                fresh = strategy_class(kind)(params)
                fresh.reset(self.info, self.observe(read_targets=False), self.rng)
                self.strategy = fresh
                how = "restarted"
        except ValueError as err:
            name, sep, problem = str(err).partition(": ")
            if sep and " " not in name:
                raise ConfigError(f"strategy.{name}", problem) from None
            raise ConfigError("strategy", str(err)) from None
        self.scenario = dataclasses.replace(self.scenario, strategy=StrategyConfig(kind, params))
        return how

    def _warning_count(self) -> int:
        # A live view of the counters, indexed with plain ints: a few hundred ns a tick.
        number = self._warning_numbers
        return int(sum(number[w] for w in _WARNINGS_THAT_DIVERGE))

    def _diverged(self) -> bool:
        """Non-finite state, or a divergence warning since the last check."""
        data = self.world.data
        if not (np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()):
            return True
        count = self._warning_count()
        diverged, self._warnings = count != self._warnings, count
        return diverged

    def _move_targets(self) -> np.ndarray:
        positions = self.targets.positions(self.time_s)
        if len(positions):
            self.world.data.mocap_pos[self.world.target_mocap_ids] = positions
        return positions

    def observe(self, read_targets: bool = True, info_wanted: bool = True) -> Observation:
        """Read the state and sense; target ranges only at reading instants
        (every ``sensing.period_s``) and when ``read_targets``. ``info_wanted``
        goes into the observation (see :class:`sim.types.Observation`)."""
        world, data = self.world, self.world.data
        qpos, qvel = data.qpos, data.qvel
        position = qpos[self._position_index]
        quaternion = qpos[self._quaternion_index]
        velocity = qvel[self._velocity_index]
        angular = qvel[self._angular_index]
        sensors = self.sensors.sensor_positions()
        ranges, step = None, None
        if read_targets and self.targets.n_targets and self.time_s + 1e-9 >= self._next_reading_s:
            ranges = self.sensors.target_ranges(sensors, data.mocap_pos[world.target_mocap_ids], self.rng)
            step = int(round(self.time_s / self.scenario.target_motion.step_s))
            self._next_reading_s += self.scenario.sensing.period_s
        return Observation(
            time_s=self.time_s, tick=self.tick_count, position=position, velocity=velocity,
            quaternion=quaternion, angular_velocity=angular, sensor_position=sensors,
            links=self.sensors.links(position), target_ranges=ranges, target_step=step, info_wanted=info_wanted,
        )

    def tick(self, info_wanted: bool = True) -> tuple[Frame, bool]:
        """One control period. Returns the frame (state before the step) and
        whether the physics stayed finite and warning-free.

        ``info_wanted``: whether an observer reads the strategy's figures and
        decorations (``commands.info``) this tick (see :class:`sim.types.Observation`).
        Each stage's wall time is added to ``self.timing``."""
        timing = self.timing
        start = time.perf_counter()
        observation = self.observe(info_wanted=info_wanted)
        sensed = time.perf_counter()
        commands = self.strategy.step(observation)
        planned = time.perf_counter()
        self.control.apply(observation, commands)
        frame = Frame(observation, commands, self.world.data.mocap_pos[self.world.target_mocap_ids].copy())
        controlled = time.perf_counter()
        model, data = self.world.model, self.world.data
        for _ in range(self.substeps):
            mujoco.mj_step(model, data)
        stepped = time.perf_counter()
        self.tick_count += 1
        self.time_s = self.tick_count * self.dt
        self._move_targets()
        healthy = not self._diverged()
        timing["sensing"] += sensed - start
        timing["strategy"] += planned - sensed
        timing["lowlevel"] += controlled - planned
        timing["physics"] += stepped - controlled
        return frame, healthy


def timing_summary(timing: dict[str, float], setup_s: float, closing_s: float) -> dict[str, float | None]:
    """metrics.json's ``timing`` block: wall seconds per tick stage summed over
    the run (``physics_s``: mj_step; ``sensing_s``: state read-out, mj_ray
    links and target ranges; ``strategy_s``; ``lowlevel_s``: rotor / wheel
    commands; ``observers_s``: metrics, plots' sampling, video, recording),
    ``setup_s`` (world build and strategy reset), ``closing_s`` (observers'
    close: plots, video encoding), and ``stack_to_physics``: the per-tick
    stages other than physics over physics."""
    stack = sum(timing[stage] for stage in TIMED_STAGES if stage != "physics")
    physics = timing["physics"]
    return {
        **{f"{stage}_s": timing[stage] for stage in TIMED_STAGES},
        "setup_s": setup_s,
        "closing_s": closing_s,
        "stack_to_physics": stack / physics if physics > 0 else None,
    }


def _write_json(path: Path, payload: dict) -> None:
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=2, sort_keys=False)
        f.write("\n")
    os.replace(tmp, path)


def run(
    scenario: Scenario,
    out_dir: str | Path | None = None,
    video: bool = False,
    rrd: bool = False,
    live: Any = None,
    keep_trajectory: bool = False,
    progress: Callable[[float], None] | None = None,
    extra_observers: Sequence[Observer] = (),
) -> RunResult:
    """Run a scenario headless; write metrics.json (+ video.mp4, run.rrd) to out_dir.

    ``extra_observers`` see every tick after the built-in ones and are closed
    with them. Validation errors (ConfigError) are raised before anything is
    written.
    """
    wall_start = time.perf_counter()
    _mujoco_warnings.clear()
    sim = Simulation(scenario)
    out = Path(out_dir) if out_dir is not None else None
    if video:
        from viz.video import resolve_camera

        resolve_camera(sim.world.model, scenario.video.camera)  # refuse before writing anything
    observers: list[Any] = []
    estimation = EstimationMetrics()  # first: it adds e_g to the frame's scalars for the observers after it
    tracking = TrackingMetrics(sim.world.robot_kinds)
    links = LinkMetrics()
    observers += [estimation, tracking, links]
    files: dict[str, str] = {}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        for stale in ("metrics.json", "video.mp4", "run.rrd"):
            (out / stale).unlink(missing_ok=True)
        from viz.plots import PlotRecorder

        plots = PlotRecorder(sim.world.robot_kinds, out / "plots", robot_names=sim.world.robot_names)
        observers.append(plots)
    if video:
        from viz.video import VideoRecorder

        files["video"] = str(out / "video.mp4")
        observers.append(VideoRecorder(sim.world, scenario.video, files["video"], sim.dt))
    recorder = None
    if rrd or live is not None:
        from viz.recording import RerunRecorder

        files["recording"] = str(out / "run.rrd")
        recorder = RerunRecorder(sim.world, files["recording"], scenario.name, live_stream=live)
        observers.append(recorder)
    observers += list(extra_observers)

    n_ticks = int(round(scenario.duration_s / sim.dt))
    status = "completed"
    trajectory = [] if keep_trajectory else None
    message = ""
    info_readers = [getattr(observer, "reads_info", None) for observer in observers]
    always_info = any(reader is None for reader in info_readers)
    timing = sim.timing
    setup_s = time.perf_counter() - wall_start
    try:
        for _ in range(n_ticks):
            info_wanted = always_info or any(reader(sim.time_s) for reader in info_readers)
            frame, healthy = sim.tick(info_wanted)
            observed = time.perf_counter()
            for observer in observers:
                observer.on_tick(frame)
            timing["observers"] += time.perf_counter() - observed
            if trajectory is not None:
                trajectory.append(frame.observation.position)
            if not healthy:
                status = "diverged"
                detail = _mujoco_warnings[-1] if _mujoco_warnings else "non-finite state"
                message = f"physics diverged at t = {sim.time_s:.3f} s: {detail}"
                if recorder is not None:
                    recorder.event(sim.time_s, message, level="ERROR", tick=sim.tick_count)
                break
            if progress is not None and sim.tick_count % 100 == 0:
                progress(sim.time_s / scenario.duration_s)
            if getattr(sim.strategy, "finished", False):
                # The strategy's mission is over (e.g. every target visited): stop early.
                if recorder is not None:
                    recorder.event(sim.time_s, f"strategy finished at t = {sim.time_s:.2f} s", tick=sim.tick_count)
                break
    finally:
        closing = time.perf_counter()
        for observer in observers:
            observer.close(status)
        closing_s = time.perf_counter() - closing

    wall = time.perf_counter() - wall_start
    metrics: dict[str, Any] = {
        "scenario": scenario.name,
        "strategy": scenario.strategy.kind,
        "seed": scenario.seed,
        "status": status,
        "message": message,
        "sim_time_s": sim.time_s,
        "wall_time_s": wall,
        "real_time_factor": sim.time_s / wall if wall > 0 else None,
        "n_robots": sim.world.n_robots,
        "n_quadrotors": int(len(sim.world.kind_index["quadrotor"])),
        "n_ground_robots": int(len(sim.world.kind_index["ground"])),
        "n_targets": sim.targets.n_targets,
        "control_ticks": sim.tick_count,
        "timing": timing_summary(timing, setup_s, closing_s),
        **tracking.summary(),
        **links.summary(),
        **estimation.summary(),
    }
    summary = getattr(sim.strategy, "summary", None)
    if callable(summary):
        metrics.update(summary())
    if out is not None:
        files["plots"] = str(out / "plots")
        files["metrics"] = str(out / "metrics.json")
        _write_json(out / "metrics.json", metrics)
    return RunResult(status, metrics, out, files, np.array(trajectory) if trajectory is not None else None)
