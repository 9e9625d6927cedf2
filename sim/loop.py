"""The step loop: sense -> strategy -> low-level control -> physics -> observers.

:class:`Simulation` is composed, not hard-wired: it is handed a strategy
factory (parameters -> :class:`sim.strategy.Strategy`) and a low-level
control factory (world -> :class:`LowLevel`), and :func:`run_ticks` is handed
the observers; the application (``tether.runner``) picks them. One
``np.random.Generator`` (seeded from the scenario) is created here and passed
down in a fixed order: target motion noise, range noise, then the strategy;
the radio channel and then the message bus get streams spawned from it
(spawning draws nothing). Each tick the strategy's ``Commands.outbox`` goes
through the bus; its deliveries are the next ``Observation.inbox``.
Observers only read, so video and recording never change the trajectory.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import gc
import math
import operator
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Callable, Mapping, Protocol, Sequence

import mujoco
import numpy as np

from sim.config import ConfigError
from sim.faults import FaultState
from sim.observers import EstimationError, Frame, Observer, PhysicsState, estimation_error
from sim.radio.bus import Broadcasts, LinkState, Message, MessageBus, link_conditions, link_from_pairs
from sim.radio.config import RadioConfig
from sim.radio.link import RadioChannel
from sim.scenario import Scenario, StrategyConfig
from sim.sensing import RaySensors
from sim.strategy import Status, Strategy
from sim.targets import TargetDriver, nominal_path_samples
from sim.types import NO_ARRIVALS, Commands, Links, Observation, WorldInfo, readonly
from sim.validate import NON_FINITE, sanity_limits, tick_sanity, tick_violation
from sim.world import World, build_world

_WARNINGS_THAT_DIVERGE = tuple(int(w) for w in (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADCTRL,
))


mujoco_warnings: list[str] = []  # this run's MuJoCo warnings, newest last (cleared by the runner)

# Stages of a control tick timed by the loop (wall seconds, time.perf_counter),
# reported as metrics.json's ``timing`` block.
TIMED_STAGES = ("physics", "sensing", "strategy", "lowlevel", "observers")


def _collect_warning(text: str) -> None:
    # MuJoCo would print and append to MUJOCO_LOG.TXT in the working folder;
    # the loop reports divergence itself, with the first warning's text.
    mujoco_warnings.append(text.strip())


mujoco.set_mju_user_warning(_collect_warning)


class LowLevel(Protocol):
    """Turns references into actuator commands (``data.ctrl``) for every robot."""

    def hover_ctrl(self) -> None:
        """Initial actuator commands, before the first tick."""

    def apply(self, observation: Observation, commands: Commands) -> None:
        """Write ``data.ctrl`` for the references in ``commands``."""


StrategyFactory = Callable[[Any], Strategy]  # validated parameters -> a fresh strategy (not reset)
LowLevelFactory = Callable[[World], LowLevel]


@contextlib.contextmanager
def frozen_heap():
    """Keep the cyclic garbage collector's full passes off every object that exists now.

    A run's heap after setup is ~10^5 objects (modules, numba, the world, the
    first plans) that live to its end; as intermittent-8's beliefs grow, a
    full pass over all of them came every ~10 s simulated and cost ~0.15 s, a
    quarter of that span's control stack. Frozen objects are still freed by
    reference counting; on exit they are handed back to the collector, so a
    process that runs again collects them as before."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def end_of_run(strategy: Strategy, mission_ended: bool, duration_s: float, time_s: float) -> tuple[Status, str]:
    """Status and message of a run that did not diverge.

    A strategy whose mission can end (:attr:`Strategy.mission_can_end`) and
    whose duration ran out first stopped at its "time limit", which a user
    must not read as "completed"; any other strategy has done its job when it
    ran the full duration. :meth:`Strategy.progress` says how far the
    mission got (e.g. "7/25 targets visited") in either case.
    """
    progress = strategy.progress()
    detail = f": {progress}" if progress else ""
    if mission_ended:
        return Status.COMPLETED, f"mission completed at t = {time_s:.1f} s{detail}"
    if strategy.mission_can_end:
        return Status.TIME_LIMIT, f"stopped at the {duration_s:g} s time limit before the mission ended{detail}"
    return Status.COMPLETED, f"ran the full {duration_s:g} s{detail}"


class Simulation:
    """Owns the world and the per-tick pieces; ``tick()`` advances one control period."""

    def __init__(self, scenario: Scenario, strategy_factory: StrategyFactory, lowlevel_factory: LowLevelFactory,
                 rng: np.random.Generator | None = None):
        self.scenario = scenario
        self.strategy_factory = strategy_factory
        self.rng = rng if rng is not None else np.random.default_rng(scenario.seed)
        self.targets = TargetDriver(scenario, self.rng)
        starts = self.targets.positions(0.0)
        samples = [nominal_path_samples(t) for t in scenario.targets]
        self.world: World = build_world(scenario, starts, samples)
        self.sensors = RaySensors(self.world, scenario.sensing.comm_range_m, scenario.sensing.target_range_m,
                                  scenario.sensing.range_noise)
        # Spawned, not drawn from: the run's own stream (targets, ranges, strategy) is unchanged by the radio.
        self.radio = RadioChannel(scenario.radio, self.world.obstacles, self.world.wall_loss_db,
                                  scenario.sensing.comm_range_m, self.rng.spawn(1)[0])
        # The message bus: Commands.outbox in, the next Observation.inbox out. Its stream is spawned after
        # the channel's, so the channel's draws are those of a run without a bus.
        self.bus = MessageBus(scenario.radio.bus_parameters, self.rng.spawn(1)[0],
                              scenario.physics.control_period_s, robot_count=self.world.n_robots)
        # The scenario's faults (None without any): spawned after the bus, and only when position noise needs
        # a stream, so a run without faults draws and spawns exactly as before.
        self.faults: FaultState | None = None
        if scenario.faults:
            self.faults = FaultState(scenario.faults, self.world.n_robots,
                                     ideal_radio=scenario.radio.preset == "ideal")
            if self.faults.noise is not None:
                self.faults.rng = self.rng.spawn(1)[0]
            self._robot_actuators = _robot_actuators(self.world)
            self._hold: dict[int, tuple[np.ndarray, float]] = {}  # stopped robot -> (position m, yaw rad) it holds
            self._frozen_ctrl: dict[int, np.ndarray] = {}  # drifting robot -> its actuators' last command
        self._no_inbox: tuple[tuple, ...] = ((),) * self.world.n_robots
        self._inbox = self._no_inbox  # the deliveries of the last tick's bus step, for the next observation
        self._arrivals: Mapping[str, Any] = NO_ARRIVALS  # and its arrivals sent as_arrays (MessageBus.arrivals)
        self._bus_flowed = False  # some tick's step had messages: the bus's per-tick scalars are reported
        self.control = lowlevel_factory(self.world)
        self.substeps = scenario.physics.substeps
        self.world.model.opt.timestep = scenario.physics.timestep_s
        self.dt = scenario.physics.control_period_s
        self.tick_count = 0
        self.time_s = 0.0
        self.divergence = ""  # why the last unhealthy tick was unhealthy
        self._next_reading_s = 0.0
        self._warning_numbers = self.world.data.warning.number  # (mjNWARNING,) view, updated by mj_step
        # Views of MjData's arrays kept once (each attribute read builds a new array object).
        self._qpos, self._qvel, self._mocap_pos = self.world.data.qpos, self.world.data.qvel, self.world.data.mocap_pos
        data = self.world.data
        self._state_arrays = (data.qpos, data.qvel, data.act, data.mocap_pos, data.mocap_quat)  # PhysicsState's
        self._sanity_limits = sanity_limits(self.world)
        self._warnings = self._warning_count()
        # Index arrays for reading every robot's free-joint state in one fancy-index each.
        self._qpos_adr = np.asarray(self.world.qpos_adr, dtype=np.int64)
        qpos_adr = self._qpos_adr[:, None]
        qvel_adr = np.asarray(self.world.qvel_adr)[:, None]
        self._position_index = qpos_adr + np.arange(3)
        self._quaternion_index = qpos_adr + np.arange(3, 7)
        self._velocity_index = qvel_adr + np.arange(3)
        self._angular_index = qvel_adr + np.arange(3, 6)
        self.timing = dict.fromkeys(TIMED_STAGES, 0.0)  # wall s per stage, summed over ticks
        self._estimation: EstimationError | None = None  # the latest e_g (Frame.estimation)
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
        self._start_height = np.array([self.world.data.qpos[a + 2] for a in self.world.qpos_adr])
        self.strategy: Strategy = strategy_factory(scenario.strategy.params)
        self.strategy.reset(self.info, self.observe(read_targets=False), self.rng)

    def set_strategy_params(self, params: Any) -> str:
        """Swap the running strategy's parameters between ticks (the next tick
        uses them): the strategy's own ``update_params`` when it accepts them
        ("updated"), else a fresh strategy reset at the current state
        ("restarted"). ``params`` must already be validated (built
        through sim.config.build); ConfigError if the strategy refuses them,
        in which case the running strategy is kept unchanged."""
        kind = self.scenario.strategy.kind
        try:
            if self.strategy.update_params(params):
                how = "updated"
            else:
                fresh = self.strategy_factory(params)
                fresh.reset(self.info, self.observe(read_targets=False), self.rng)
                self.strategy = fresh
                how = "restarted"
        except ConfigError:
            raise  # already names a scenario field (e.g. sensing.comm_range_m)
        except ValueError as err:
            name, sep, problem = str(err).partition(": ")
            if sep and " " not in name:
                raise ConfigError(f"strategy.{name}", problem) from None
            raise ConfigError("strategy", str(err)) from None
        self.scenario = dataclasses.replace(self.scenario, strategy=StrategyConfig(kind, params))
        return how

    def set_radio(self, config: RadioConfig) -> str:
        """Retune the radio between ticks (the tuning page): the channel takes ``config`` at
        once, with its own random stream continued, and the message bus its new parameters
        (messages in flight keep their schedule). ``config`` must already be validated.
        Returns "updated"."""
        self.radio = RadioChannel(config, self.world.obstacles, self.world.wall_loss_db,
                                  self.scenario.sensing.comm_range_m, self.radio.rng)
        self.bus.params = config.bus_parameters
        self.scenario = dataclasses.replace(self.scenario, radio=config)
        return "updated"

    def _warning_count(self) -> int:
        # A live view of the counters, indexed with plain ints: a few hundred ns a tick.
        number = self._warning_numbers
        return int(sum(number[w] for w in _WARNINGS_THAT_DIVERGE))

    def _move_targets(self) -> np.ndarray:
        if not self.targets.n_targets:  # nothing to move (and no state to draw)
            return np.zeros((0, 3))
        positions = self.targets.positions(self.time_s)
        if len(positions):
            self._mocap_pos[self.world.target_mocap_ids] = positions
        return positions

    def observe(self, read_targets: bool = True, decorations_wanted: bool = True) -> Observation:
        """Read the state and sense; target ranges only at reading instants
        (every ``sensing.period_s``) and when ``read_targets``.
        ``decorations_wanted`` goes into the observation (see
        :class:`sim.types.Observation`)."""
        world = self.world
        qpos, qvel = self._qpos, self._qvel
        position = qpos[self._position_index]
        quaternion = qpos[self._quaternion_index]
        velocity = qvel[self._velocity_index]
        angular = qvel[self._angular_index]
        sensors = self.sensors.sensor_positions()
        ranges, step = None, None
        if read_targets and self.targets.n_targets and self.time_s + 1e-9 >= self._next_reading_s:
            ranges = self.sensors.target_ranges(sensors, self._mocap_pos[world.target_mocap_ids], self.rng)
            step = int(round(self.time_s / self.scenario.target_motion.step_s))
            self._next_reading_s += self.scenario.sensing.period_s
        links = self.sensors.links(position)
        faults = self.faults
        if faults is not None and self.scenario.radio.is_ideal:
            # The ideal radio's channel is the disk itself: a silent robot's links and those in a deep
            # enough blackout are cut there (sim.faults.IDEAL_BLACKOUT_CUT_DB).
            adjacency = faults.cut_adjacency(self.time_s, position, links.adjacency)
            if adjacency is not links.adjacency:
                links = dataclasses.replace(links, adjacency=readonly(adjacency))
        return Observation(
            time_s=self.time_s, tick=self.tick_count, position=position, velocity=velocity,
            quaternion=quaternion, angular_velocity=angular, sensor_position=sensors,
            links=links, target_ranges=ranges, target_step=step,
            decorations_wanted=decorations_wanted, radio=self._radio_state(position, links),
            inbox=self._inbox, arrivals=self._arrivals,
        )

    def _radio_state(self, position: np.ndarray, links: Links):
        """The channel at this tick, with the faults' dead links and blackout losses under a real radio."""
        faults = self.faults
        if faults is None or self.scenario.radio.is_ideal:
            return self.radio.state(self.time_s, position, links)
        first, second = self.radio.pairs(len(position))
        extra = faults.extra_loss_pairs_db(self.time_s, position, first, second)
        silent = faults.failed if faults.any_failed else None
        return self.radio.state(self.time_s, position, links, extra_loss_db=extra, silent=silent)

    def _fail_robots(self) -> None:
        """Robots whose failure time has come: what their actuators will do from now on."""
        newly = self.faults.advance(self.time_s)
        for robot in newly:
            robot = int(robot)
            if self.faults.fail_mode[robot] == "stop":
                adr = self.world.qpos_adr[robot]
                w, x, y, z = self._qpos[adr + 3: adr + 7]
                yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
                self._hold[robot] = (self._qpos[adr: adr + 3].copy(), yaw)
            else:
                self._frozen_ctrl[robot] = self.world.data.ctrl[self._robot_actuators[robot]].copy()

    def _failed_commands(self, commands: Commands) -> Commands:
        """``commands`` with the failed robots' part overridden: a stopped robot holds its place, and no
        failed robot sends anything (the drifting ones' actuators are frozen after the low-level control)."""
        failed = self.faults.failed
        outbox = tuple(_sent_by_working(commands.outbox, failed))
        if not self._hold:
            unchanged = len(outbox) == len(commands.outbox) and all(map(operator.is_, outbox, commands.outbox))
            return commands if unchanged else dataclasses.replace(commands, outbox=outbox)
        position, velocity = np.array(commands.position), np.array(commands.velocity)
        acceleration, yaw = np.array(commands.acceleration), np.array(commands.yaw)
        for robot, (held, held_yaw) in self._hold.items():
            position[robot], velocity[robot], acceleration[robot], yaw[robot] = held, 0.0, 0.0, held_yaw
        return dataclasses.replace(commands, position=position, velocity=velocity, acceleration=acceleration,
                                   yaw=yaw, outbox=outbox)

    def strategy_view(self, observation: Observation) -> Observation:
        """What the strategy reads: ``observation`` with the position noise's positions and the distances
        between them (line of sight, adjacency and the channel stay the truth)."""
        noisy = self.faults.noisy_positions(observation.time_s, observation.position)
        distance = np.linalg.norm(noisy[:, None, :] - noisy[None, :, :], axis=-1)
        links = dataclasses.replace(observation.links, distance=distance)
        return dataclasses.replace(observation, position=noisy, links=links, position_error=noisy - observation.position)

    def tick(self, decorations_wanted: bool = True) -> tuple[Frame, bool]:
        """One control period. Returns the frame (state before the step,
        immutable) and whether the state after it is sane
        (``self.divergence`` says why not: :meth:`_check`).

        ``decorations_wanted``: whether an observer reads the strategy's
        scalars and decorations this tick (see :class:`sim.types.Observation`).
        Each stage's wall time is added to ``self.timing``."""
        timing = self.timing
        start = time.perf_counter()
        faults = self.faults
        if faults is not None:
            self._fail_robots()
        observation = self.observe(decorations_wanted=decorations_wanted)
        sensed = time.perf_counter()
        if faults is None:
            commands = self.strategy.step(observation)
        else:
            commands = self.strategy.step(self.strategy_view(observation) if faults.noise else observation)
            if faults.any_failed:
                commands = self._failed_commands(commands)
        self._exchange(observation, commands)
        planned = time.perf_counter()
        self.control.apply(observation, commands)
        if faults is not None and self._frozen_ctrl:
            ctrl = self.world.data.ctrl
            for robot, frozen in self._frozen_ctrl.items():
                ctrl[self._robot_actuators[robot]] = frozen
        frame = self._frame(observation, commands)
        controlled = time.perf_counter()
        model, data = self.world.model, self.world.data
        for _ in range(self.substeps):
            mujoco.mj_step(model, data)
        stepped = time.perf_counter()
        self.tick_count += 1
        self.time_s = self.tick_count * self.dt
        self._move_targets()
        self.divergence = self._check(commands)
        timing["sensing"] += sensed - start
        timing["strategy"] += planned - sensed
        timing["lowlevel"] += controlled - planned
        timing["physics"] += stepped - controlled
        return frame, not self.divergence

    def _exchange(self, observation: Observation, commands: Commands) -> None:
        """The tick's messages: ``commands.outbox`` to the bus at the tick's time, one bus step over
        [t, t + control period) with this tick's link state, its deliveries the next observation's inbox."""
        bus = self.bus
        rows = bus.exchange(commands.outbox, observation.time_s, lambda: self.bus_link(observation))
        if rows is False:  # no message anywhere: no link state read, nothing drawn
            self._inbox = self._no_inbox
            self._arrivals = NO_ARRIVALS
            return
        arrivals = bus.arrivals  # rows None: no delivery in the rows (most ticks)
        if self.faults is not None and self.faults.any_failed:  # a silent robot hears nothing
            failed = self.faults.failed
            if rows is not None:
                rows = tuple(() if failed[robot] else row for robot, row in enumerate(rows))
            arrivals = {kind: columns.where(~np.asarray(failed, dtype=bool)[columns.receiver])
                        for kind, columns in arrivals.items()}
        self._inbox = rows if rows is not None and any(rows) else self._no_inbox
        self._arrivals = MappingProxyType(arrivals) if arrivals else NO_ARRIVALS
        self._bus_flowed = True

    def bus_link(self, observation: Observation) -> LinkState:
        """The bus's view of the tick's channel: the mean SNR of every pair and who shares the air.

        Carrier sense: the pairs whose mean received power reaches ``radio.carrier_sense_dbm``.
        Under ``ideal``: the disk (comm range with line of sight) for both, an infinite SNR on it."""
        if self.scenario.radio.is_ideal:
            adjacency = observation.links.adjacency
            return link_conditions(np.where(adjacency, np.inf, -np.inf), adjacency)
        radio = observation.radio
        channel = radio.channel_pairs
        made = channel.get("link_matrices")  # the channel's own, made with its figures (RadioChannel.state)
        if made is not None:
            return made
        return link_from_pairs(len(radio.distance), radio.pairs, channel["snr_db"], channel["rx_power_dbm"],
                               self.scenario.radio.carrier_sense_dbm)

    def fault_summary(self) -> dict[str, Any]:
        """metrics.json's ``faults`` (what was injected, and whether it came to pass); {} without faults, so
        a run without any writes the metrics it always did."""
        return {} if self.faults is None else {"faults": self.faults.summary()}

    def radio_summary(self) -> dict[str, float | int | None]:
        """The bus's ``radio_*`` metrics over the run (``MessageBus.summary``); a ratio or latency over no
        packets is None (null in metrics.json: empty, not a failed figure)."""
        return {key: (None if isinstance(value, float) and math.isnan(value) else value)
                for key, value in self.bus.summary().items()}

    def _frame(self, observation: Observation, commands: Commands) -> Frame:
        """The observers' frame of this tick, before the step: read-only views of
        the observation, the physics state, and the derived figures (e_g)."""
        truth = readonly(self._mocap_pos[self.world.target_mocap_ids])  # a copy (index array)
        e_g = estimation_error(commands.estimate, observation.target_step, truth)
        if e_g is not None:
            self._estimation = EstimationError(e_g, int(observation.target_step), fresh=True)
        elif self._estimation is not None and self._estimation.fresh:
            self._estimation = dataclasses.replace(self._estimation, fresh=False)
        radio = None
        if self._bus_flowed:
            last = self.bus.last_tick
            radio = {"radio_tick_delivery_ratio": last.delivery_ratio, "radio_tick_latency_mean_s": last.latency_mean_s}
        failed = readonly(self.faults.failed.copy()) if self.faults is not None and self.faults.any_failed else None
        return Frame(_readonly_observation(observation), commands, truth, PhysicsState.of(*self._state_arrays),
                     self._estimation, radio, failed)

    def _check(self, commands) -> str:
        """Why the state after this tick is not sane ("" if it is): non-finite
        physics, a MuJoCo warning, a robot out of the scene, fallen or tipped
        over (sim.validate), or the strategy's own invariant
        (:meth:`Strategy.violation`)."""
        code, robot = tick_sanity(self.world, self._qpos, self._qvel, self._qpos_adr, self._start_height,
                                  self._sanity_limits)
        if code == NON_FINITE:
            return "physics: non-finite state"
        count = self._warning_count()
        if count != self._warnings:
            self._warnings = count
            return "physics: " + (mujoco_warnings[-1] if mujoco_warnings else "MuJoCo warning")
        reason = tick_violation(self.world, code, robot, self._qpos, self._qpos_adr)
        if reason:
            return reason
        return self.strategy.violation(commands) or ""


def _sent_by_working(outbox: Sequence[Message | Broadcasts], failed: np.ndarray):
    """The outbox's items without what the ``failed`` robots ((N,) bool) send: a message of theirs is left
    out, a ``Broadcasts`` item keeps the others' (and is left out when none is left)."""
    for item in outbox:
        if type(item) is Broadcasts:
            senders = item.sender_indices()
            if failed[senders].any():
                item = item.kept(~np.asarray(failed, dtype=bool))
            if len(item):
                yield item
        elif not failed[item.sender]:
            yield item


def _robot_actuators(world: World) -> list[np.ndarray]:
    """Per robot (in robot order), the ids of its actuators."""
    out: list[np.ndarray] = [np.zeros(0, dtype=int)] * world.n_robots
    for kind, robots in world.kind_index.items():
        for row, robot in enumerate(robots):
            out[int(robot)] = np.asarray(world.actuator_ids[kind][row], dtype=int)
    return out


def _readonly_observation(observation: Observation) -> Observation:
    """``observation`` with read-only views of its arrays (the strategy's own stay
    writeable); the links' figures already computed are kept."""
    links = observation.links
    # Built through __dict__, every tick: a frozen dataclass's __init__ sets each field through object.__setattr__.
    frame_links = object.__new__(Links)
    frame_links.__dict__.update(links.__dict__)
    frame_links.__dict__.update(distance=readonly(links.distance), line_of_sight=readonly(links.line_of_sight),
                                adjacency=readonly(links.adjacency))  # (edges, computed or not, are read-only)
    if "clearance" in links.__dict__:
        frame_links.__dict__["clearance"] = readonly(links.clearance)
    frame = object.__new__(Observation)
    fields = frame.__dict__
    fields.update(observation.__dict__)
    fields.update(position=readonly(observation.position), velocity=readonly(observation.velocity),
                  quaternion=readonly(observation.quaternion),
                  angular_velocity=readonly(observation.angular_velocity),
                  sensor_position=readonly(observation.sensor_position), links=frame_links)
    if observation.target_ranges is not None:
        fields["target_ranges"] = readonly(observation.target_ranges)
    return frame


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


class ObserverFailure(RuntimeError):
    """An observer cannot go on (its child process died, e.g. the video
    renderer): the run ends "failed" with this message and writes its files."""


class _Interrupts:
    """While a run ticks, SIGINT (Ctrl-C) and SIGTERM only set ``requested``
    (the signal's name): the loop stops at the next tick and closes the run
    as "interrupted". A second signal during the ticks stops the tick at
    once; once the loop is over (``closing``), a signal never raises: it is
    noted (``late``) and tells every observer with an ``abandon()`` to finish
    at once (the video stops rendering its queue), so closing stays short.
    Handlers are installed only in the main thread (Python's rule)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, observers: Sequence[Any] = ()):
        self.requested = ""
        self.late = ""  # a signal that came while the observers closed
        self.closing = False  # once the loop is over, signals wait for the files to be closed
        self._observers = observers
        self._previous: dict = {}

    def _handle(self, signum, _frame) -> None:
        name = signal.Signals(signum).name
        if self.closing:
            self.requested = self.requested or name
            self.late = self.late or name
            self.abandon()
            return
        if self.requested:
            raise KeyboardInterrupt
        self.requested = name

    def abandon(self) -> None:
        """Ask every observer that can to finish at once (it only sets a flag)."""
        for observer in self._observers:
            abandon = getattr(observer, "abandon", None)
            if abandon is not None:
                abandon()

    def __enter__(self) -> "_Interrupts":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


@dataclass
class TickOutcome:
    """How :func:`run_ticks` ended."""

    status: Status
    message: str
    closing_s: float  # wall s spent closing the observers
    trajectory: np.ndarray | None = None  # (ticks, N, 3) body positions, when asked


def run_ticks(sim: Simulation, observers: Sequence[Observer], duration_s: float,
              progress: Callable[[Simulation], None] | None = None, keep_trajectory: bool = False,
              on_closed: Callable[[Status, str], None] | None = None) -> TickOutcome:
    """Tick ``sim`` for ``duration_s`` with ``observers``, then close them.

    Stops early when the strategy's mission ends (:attr:`Strategy.finished`),
    the state diverges (``sim.divergence``), an observer fails
    (:class:`ObserverFailure`: "failed") or SIGINT / SIGTERM arrives (the
    run stops at the next tick: "interrupted"; one while the observers close
    makes them hurry and the run "interrupted" too). ``progress`` is called every
    100 ticks. ``on_closed(status, message, closing_s)`` runs after every observer
    closed, still under the signal guard (the caller writes its files
    there). On an exception the observers are closed "failed" and it
    propagates.
    """
    n_ticks = int(round(duration_s / sim.dt))
    status, message = Status.COMPLETED, ""
    mission_ended = False
    trajectory = [] if keep_trajectory else None
    readers = [observer.reads_decorations for observer in observers]
    timing = sim.timing
    closed = False
    try:
        with _Interrupts(observers) as interrupts, frozen_heap():
            try:
                for _ in range(n_ticks):
                    if interrupts.requested:
                        status = Status.INTERRUPTED
                        message = f"interrupted ({interrupts.requested}) at t = {sim.time_s:.3f} s"
                        break
                    decorations_wanted = any(reader(sim.time_s) for reader in readers)
                    frame, healthy = sim.tick(decorations_wanted)
                    observed = time.perf_counter()
                    for observer in observers:
                        observer.on_tick(frame)
                    timing["observers"] += time.perf_counter() - observed
                    if trajectory is not None:
                        trajectory.append(frame.observation.position)
                    if not healthy:
                        status = Status.DIVERGED
                        message = f"diverged at t = {sim.time_s:.3f} s: {sim.divergence}"
                        break
                    if progress is not None and sim.tick_count % 100 == 0:
                        progress(sim)
                    if sim.strategy.finished:
                        for observer in observers:
                            observer.on_event(sim.time_s, f"strategy finished at t = {sim.time_s:.2f} s",
                                              tick=sim.tick_count)
                        mission_ended = True
                        break
            except KeyboardInterrupt:  # a second Ctrl-C, or one before the handlers were in place
                status = Status.INTERRUPTED
                message = f"interrupted ({interrupts.requested or 'SIGINT'}) at t = {sim.time_s:.3f} s"
            except ObserverFailure as failure:  # e.g. the video renderer died
                status = Status.FAILED
                message = f"failed at t = {sim.time_s:.3f} s: {failure}"
            if status == Status.COMPLETED:  # ran to its end: the mission's end or the time limit
                status, message = end_of_run(sim.strategy, mission_ended, duration_s, sim.time_s)
            if sim.faults is not None and sim.faults.events:  # what was injected and what it did
                message = f"{message}; faults: {sim.faults.message()}"
            interrupts.closing = True
            if interrupts.requested and status not in (Status.INTERRUPTED, Status.FAILED):
                # came after the last tick's look: the run is interrupted all the same
                status, message = Status.INTERRUPTED, (f"interrupted ({interrupts.requested}) at t = "
                                                       f"{sim.time_s:.3f} s, as the run ended ({status}: {message})")
            if status in (Status.DIVERGED, Status.INTERRUPTED, Status.FAILED):
                level = "WARN" if status == Status.INTERRUPTED else "ERROR"
                for observer in observers:
                    observer.on_event(sim.time_s, message, level=level, tick=sim.tick_count)
            closed = True
            closing = time.perf_counter()
            for observer in observers:  # work that can go on while the others close (plots' painters)
                observer.start_closing(status)
            failures = []
            for observer in observers:
                try:
                    observer.close(status)
                except ObserverFailure as failure:  # the others still close and the files are written
                    failures.append(str(failure))
            if failures:
                status, message = Status.FAILED, "; ".join([*failures, message] if message else failures)
            elif interrupts.late and status != Status.INTERRUPTED:
                status, message = Status.INTERRUPTED, (f"interrupted ({interrupts.late}) while closing, "
                                                       f"after the run ended ({status}: {message})")
            closing_s = time.perf_counter() - closing
            if on_closed is not None:
                on_closed(status, message, closing_s)
    except BaseException:  # a bug (or a forced stop): close what is open
        if not closed:
            for observer in observers:
                try:
                    observer.close(Status.FAILED)
                except Exception:  # noqa: BLE001 (the first error is the one to report)
                    pass
        raise
    return TickOutcome(status, message, closing_s, np.array(trajectory) if trajectory is not None else None)
