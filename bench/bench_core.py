"""The core's speed: the full control stack against bare physics of the same world.

For each row one simulation is built and warmed up, then measured in blocks
of ``BLOCK_TICKS`` control ticks. Before each block, a copy of the world's
MjData (the current state) is stepped bare for the block's ``mj_step`` calls;
then the block runs the full tick (sensing, strategy, low-level control,
physics) and the metric observers a headless ``tether run`` has. Both are
timed with this thread's CPU time, interleaved, so the ratio

    full tick / bare mj_step of the same world (1.0 = nothing but physics)

survives a shared, busy machine. The real-time factor is simulated seconds
per wall second of the full ticks; the stage shares come from the loop's own
``timing`` (metrics.json's block). Then: the intermittent paper's plan time for 2- and
4-robot teams (bench/bench_intermittent.py's measurement), ``--video``'s
real-time factor against headless, and the fixed costs of a run as a user
starts it (``tether run NAME --duration 20 --out DIR``, a fresh process):
imports and start-up, set-up (world, strategy, a-priori plans), the ticks and
the closing (the end-of-run plots and files), in wall seconds.

    make bench            # or: .venv/bin/python bench/bench_core.py [--seconds S] [--quick]

``--radio ieee802154`` measures each row again with that radio preset and prints
the per-tick CPU time of each preset over the ideal radio's.

The radio section (in every run, ``--no-radio`` skips it) measures the
``ieee802154`` preset against ``ideal`` directly: two simulations of the same
scenario, one per preset, stepped in alternating blocks of ``BLOCK_TICKS``
ticks (the order swapped every block), each block timed with this thread's CPU
time; the median over the pairs of blocks of radio CPU / ideal CPU is the real
radio's cost per tick (``--radio-seconds`` simulated per row, default 4). Once
without extra messages (the methods' own traffic only), once with
``SyntheticLoad`` on both buses, so that the bus itself is measured.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import sim  # noqa: E402,F401  (GL backend before mujoco)
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from sim.estimation_observer import EstimationMetrics  # noqa: E402
from sim.loop import TIMED_STAGES, frozen_heap
from tether.runner import build_simulation, run  # noqa: E402
from sim import observers as observers_module  # noqa: E402
from sim.observers import LinkMetrics, TrackingMetrics  # noqa: E402
from sim.radio.bus import Message  # noqa: E402
from sim.scenario import load  # noqa: E402

BLOCK_TICKS = 20  # ticks per interleaved block (the open-loop bare copy is reset to the world each block)
ESTIMATOR = 'strategy.lambda2_source="estimator"'

# (label, scenario, overrides)
ROWS = (
    ("hover", "hover", []),
    ("connected-office 10", "connected-office", ["robots.0.count=10"]),
    ("connected-office 20", "connected-office", ["robots.0.count=20"]),
    ("connected-office 35", "connected-office", ["robots.0.count=35"]),
    ("connected-office 10 estimator", "connected-office", ["robots.0.count=10", ESTIMATOR]),
    ("connected-office 20 estimator", "connected-office", ["robots.0.count=20", ESTIMATOR]),
    ("connected-office 35 estimator", "connected-office", ["robots.0.count=35", ESTIMATOR]),
    ("connected-town 10", "connected-town", ["robots.0.count=10"]),
    ("intermittent-8", "intermittent-8", []),
)


def measure(scenario_name: str, overrides: list[str], seconds: float, warmup_s: float) -> dict:
    """Ratio, real-time factor and stage shares of one scenario (see the module docstring)."""
    simulation = build_simulation(load(scenario_name, overrides))
    observers = [EstimationMetrics(), TrackingMetrics(simulation.world.robot_kinds), LinkMetrics()]
    with frozen_heap():  # as sim.loop.run does around its ticks
        return _measure_ticks(simulation, observers, scenario_name, overrides, seconds, warmup_s)


def _measure_ticks(simulation, observers, scenario_name, overrides, seconds, warmup_s) -> dict:
    for _ in range(int(round(warmup_s / simulation.dt))):
        simulation.tick(decorations_wanted=False)
    model, world_data = simulation.world.model, simulation.world.data
    bare_data = mujoco.MjData(model)
    timing_before = dict(simulation.timing)
    ticks = max(BLOCK_TICKS, int(round(seconds / simulation.dt)))
    bare_cpu = full_cpu = full_wall = 0.0
    done = 0
    while done < ticks:
        block = min(BLOCK_TICKS, ticks - done)
        mujoco.mj_copyData(bare_data, model, world_data)
        start = time.thread_time()
        for _ in range(block * simulation.substeps):
            mujoco.mj_step(model, bare_data)
        bare_cpu += time.thread_time() - start
        start_wall, start = time.perf_counter(), time.thread_time()
        for _ in range(block):
            frame, healthy = simulation.tick(decorations_wanted=False)
            observed = time.perf_counter()
            for observer in observers:
                observer.on_tick(frame)
            simulation.timing["observers"] += time.perf_counter() - observed
            if not healthy:
                raise RuntimeError(f"{scenario_name} {overrides}: physics diverged")
        full_cpu += time.thread_time() - start
        full_wall += time.perf_counter() - start_wall
        done += block
    spent = {stage: simulation.timing[stage] - timing_before[stage] for stage in TIMED_STAGES}
    total = sum(spent.values())
    return {
        "bare_steps_per_s": ticks * simulation.substeps / bare_cpu,
        "real_time_factor": ticks * simulation.dt / full_wall,
        "ratio": full_cpu / bare_cpu,
        "shares": {stage: spent[stage] / total for stage in TIMED_STAGES},
    }


RADIO_PRESET = "ieee802154"
RADIO_TARGET = 1.15  # at most 15 % more per tick than the ideal radio (issue 20)
# (label, scenario, overrides) of the rows the radio's cost is held to
RADIO_ROWS = (
    ("connected-office 10", "connected-office", ["robots.0.count=10"]),
    ("connected-office 35", "connected-office", ["robots.0.count=35"]),
    ("intermittent-8", "intermittent-8", []),
)


class SyntheticLoad:
    """The traffic the methods will send, before they all do: every robot broadcasts a 40-byte message each
    tick (the lambda2 estimator's state) and, once a second at its own tick, 300 bytes to the next robot
    (15 range records, three 802.15.4 frames). A 40-byte 802.15.4 frame takes 2.1 ms of air, so robots in
    one another's carrier sense get 4-5 of them through a 10 ms tick: in connected-office the medium
    saturates and the queues grow, as they would; intermittent-8's 20 ms ticks carry its 8 robots'."""

    STATE_BYTES = 40
    RECORDS_BYTES = 300

    def __init__(self, n_robots: int, control_period_s: float):
        self.n = n_robots
        self.ticks_per_s = max(1, int(round(1.0 / control_period_s)))

    def send(self, simulation) -> None:
        """This tick's messages onto ``simulation``'s bus, at the tick's time (as ``Commands.outbox`` would)."""
        bus, time_s, tick = simulation.bus, simulation.time_s, simulation.tick_count
        for robot in range(self.n):
            bus.send(Message("bench_state", robot, None, None, self.STATE_BYTES), time_s)
            if self.n > 1 and (tick + robot * self.ticks_per_s // self.n) % self.ticks_per_s == 0:
                bus.send(Message("bench_records", robot, ((robot + 1) % self.n,), None, self.RECORDS_BYTES), time_s)


def radio_cost(scenario_name: str, overrides: list[str], seconds: float, warmup_s: float,
               synthetic: bool) -> dict:
    """CPU time per tick of ``RADIO_PRESET`` over ``ideal``, paired: both simulations in alternating blocks."""
    runs = []
    for preset in ("ideal", RADIO_PRESET):
        simulation = build_simulation(load(scenario_name, overrides + [f'radio.preset="{preset}"']))
        observers = [EstimationMetrics(), TrackingMetrics(simulation.world.robot_kinds), LinkMetrics()]
        traffic = SyntheticLoad(simulation.world.n_robots, simulation.dt) if synthetic else None
        runs.append((simulation, observers, traffic, {}))

    def ticks(run_, count: int) -> float:
        simulation, observers, traffic, lambda2_seen = run_
        # Each simulation keeps its own graphs' lambda2 memo, as it would alone in its process: the two
        # runs share their sensing graphs, and one must not compute the other's.
        observers_module._LAMBDA2_SEEN = lambda2_seen
        start = time.thread_time()
        for _ in range(count):
            if traffic is not None:
                traffic.send(simulation)
            frame, healthy = simulation.tick(decorations_wanted=False)
            for observer in observers:
                observer.on_tick(frame)
            if not healthy:
                raise RuntimeError(f"{scenario_name} {overrides}: physics diverged")
        return time.thread_time() - start

    with frozen_heap():
        for run_ in runs:
            ticks(run_, int(round(warmup_s / run_[0].dt)))
        total = max(BLOCK_TICKS, int(round(seconds / runs[0][0].dt)))
        cpu = [0.0, 0.0]
        pairs = []  # per pair of blocks, the two runs over the same ticks: radio CPU / ideal CPU
        done = 0
        while done < total:
            block = min(BLOCK_TICKS, total - done)
            order = (0, 1) if (done // BLOCK_TICKS) % 2 == 0 else (1, 0)
            spent = [0.0, 0.0]
            for index in order:
                spent[index] = ticks(runs[index], block)
                cpu[index] += spent[index]
            pairs.append(spent[1] / spent[0])
            done += block
    bus = runs[1][0].bus.summary()
    # The median over the pairs: a block that another process's burst slowed (its caches, its core) moves
    # the sums but not the median.
    return {"ideal_ms": 1e3 * cpu[0] / total, "radio_ms": 1e3 * cpu[1] / total, "ratio": float(np.median(pairs)),
            "ratio_of_sums": cpu[1] / cpu[0], "pairs": len(pairs), "frames": bus["radio_frames_sent"],
            "delivery": bus["radio_delivery_ratio"], "queued": bus["radio_packets_queued"]}


def radio_section(seconds: float, warmup_s: float, rows: list[str] | None, synthetic_load: bool = True) -> None:
    print(f"radio: {RADIO_PRESET} / ideal CPU time per tick, {seconds:g} s simulated after {warmup_s:g} s; ratio = "
          f"median over pairs of blocks of {BLOCK_TICKS} ticks, one per preset, alternating (target <= "
          f"{RADIO_TARGET:.2f}); ratio of sums beside it")
    print(f"| row | messages | ideal ms/tick | {RADIO_PRESET} ms/tick | ratio | ratio of sums | pairs | "
          f"{RADIO_PRESET} frames sent | delivery ratio | queued at the end |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for label, name, overrides in RADIO_ROWS:
        if rows and not any(key in label for key in rows):
            continue
        for synthetic in (False, True) if synthetic_load else (False,):
            cost = radio_cost(name, overrides, seconds, warmup_s, synthetic)
            load_name = "synthetic load" if synthetic else "the methods'"
            delivery = "-" if cost["delivery"] != cost["delivery"] else f"{cost['delivery']:.2f}"
            print(f"| {label} | {load_name} | {cost['ideal_ms']:.2f} | {cost['radio_ms']:.2f} | "
                  f"{cost['ratio']:.3f} | {cost['ratio_of_sums']:.3f} | {cost['pairs']} | {cost['frames']} | "
                  f"{delivery} | {cost['queued']} |", flush=True)


def plan_times(plans: int) -> list[str]:
    """The intermittent paper's plan time per team size at the strategy's own samples (n_sample for 2 robots,
    n_sample * n / 2 for n > 2), from bench/bench_intermittent.py's own measurement."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_intermittent as intermittent

    setup = intermittent.planner_setup()
    lines = []
    for size in (2, 4):
        result = intermittent.plan_times(size, plans, setup=setup)
        lines.append(f"| {size} robots | {result['n_sample']} | {result['found']}/{result['plans']} | "
                     f"{result['mean_s']:.2f} | {result['max_s']:.2f} |")
    return lines


VIDEO_RUNS = (("hover", 2.0), ("connected-office", 3.0))  # (scenario, the video's wall-time budget x headless)


def video_factor(name: str, seconds: float) -> tuple[float, float]:
    """Wall seconds of ``tether run NAME`` headless and with ``--video`` (both in this process, one after
    the other: the ratio of the two is the figure; each in a fresh process would add imports)."""
    scenario = load(name, duration_s=seconds)
    with tempfile.TemporaryDirectory() as out:
        headless = run(scenario, out).metrics["wall_time_s"]
        video = run(scenario, out, video=True).metrics["wall_time_s"]
    return headless, video


FIXED_COST_RUNS = ("hover", "connected-office", "intermittent-8")


def fixed_costs(name: str, duration_s: float) -> dict:
    """Wall seconds of one ``tether run`` as a user starts it, split with metrics.json's timing block."""
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "tether.cli", "run", name, "--duration", f"{duration_s:g}",
                        "--out", out, "--quiet"], check=True, capture_output=True)
        command_s = time.perf_counter() - start
        metrics = json.loads((Path(out) / "metrics.json").read_text())
        pages = len(list((Path(out) / "plots").glob("*.png")))
    timing = metrics["timing"]
    run_s = metrics["wall_time_s"]
    return {"command_s": command_s, "start_s": command_s - run_s, "setup_s": timing["setup_s"],
            "ticks_s": run_s - timing["setup_s"] - timing["closing_s"], "closing_s": timing["closing_s"],
            "pages": pages}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="simulated seconds measured per row")
    parser.add_argument("--warmup", type=float, default=0.5, help="simulated seconds run before measuring")
    parser.add_argument("--plans", type=int, default=8, help="intermittent plans per team size")
    parser.add_argument("--rows", nargs="*", help="only rows whose label contains one of these")
    parser.add_argument("--radio", nargs="*", default=[], metavar="PRESET",
                        help="also measure each chosen row with radio.preset=PRESET (e.g. ieee802154)")
    parser.add_argument("--radio-seconds", type=float, default=4.0,
                        help="simulated seconds measured per row of the radio section")
    parser.add_argument("--no-radio", action="store_true", help="skip the radio section")
    parser.add_argument("--radio-only", action="store_true", help="only the radio section")
    parser.add_argument("--no-synthetic", action="store_true",
                        help="the radio section under the methods' messages only (no synthetic-load rows)")
    parser.add_argument("--quick", action="store_true", help="core rows only: no planner, no video, no fixed costs")
    parser.add_argument("--video-duration", type=float, default=20.0, help="simulated seconds of the --video runs")
    parser.add_argument("--fixed-duration", type=float, default=20.0, help="simulated seconds of the fixed-cost runs")
    args = parser.parse_args()

    load_average = os.getloadavg()
    machine = (f"machine: {os.cpu_count()} cores, load average {load_average[0]:.2f} {load_average[1]:.2f} "
               f"{load_average[2]:.2f} (uptime)")
    if args.radio_only:
        print(machine)
        print()
        radio_section(args.radio_seconds, args.warmup, args.rows, not args.no_synthetic)
        return
    print(f"{machine}; {args.seconds:g} s simulated per row after {args.warmup:g} s")
    print("ratio = full tick / bare mj_step of the same world (thread CPU time, interleaved blocks)")
    print()
    stages = " | ".join(TIMED_STAGES)
    print(f"| row | bare steps/s | real-time factor | ratio | {stages} |")
    print("| --- | --- | --- | --- | " + " | ".join("---" for _ in TIMED_STAGES) + " |")
    radio_ratios = []
    for label, name, overrides in ROWS:
        if args.rows and not any(key in label for key in args.rows):
            continue
        ideal = None
        for preset in [None, *args.radio]:
            extra = [] if preset is None else [f'radio.preset="{preset}"']
            row = measure(name, overrides + extra, args.seconds, args.warmup)
            shares = " | ".join(f"{row['shares'][stage]:.0%}" for stage in TIMED_STAGES)
            shown = label if preset is None else f"{label} radio {preset}"
            print(f"| {shown} | {row['bare_steps_per_s']:.0f} | {row['real_time_factor']:.2f} | "
                  f"{row['ratio']:.2f} | {shares} |", flush=True)
            if preset is None:
                ideal = row
            else:  # both rows step the same world bare, so their ratios compare the full ticks' CPU time
                per_tick = row["ratio"] / ideal["ratio"]
                radio_ratios.append(f"{label}: {preset} / ideal per tick {per_tick:.3f}")
    if radio_ratios:
        print()
        print("\n".join(radio_ratios))
    if not args.no_radio:
        print()
        radio_section(args.radio_seconds, args.warmup, args.rows, not args.no_synthetic)
    if args.quick:
        return
    print()
    print("intermittent planner (bench/bench_intermittent.py, the strategy's samples; thread CPU s)")
    print("| team | samples | plans found | plan time mean (s) | max (s) |")
    print("| --- | --- | --- | --- | --- |")
    for line in plan_times(args.plans):
        print(line, flush=True)
    print()
    print(f"--video: wall time of the run with video / headless, {args.video_duration:g} s simulated")
    print("| run | headless s | --video s | ratio | budget |")
    print("| --- | --- | --- | --- | --- |")
    for name, budget in VIDEO_RUNS:
        headless, video = video_factor(name, args.video_duration)
        print(f"| {name} | {headless:.2f} | {video:.2f} | {video / headless:.2f} | {budget:g} |", flush=True)
    print()
    print(f"fixed costs: `tether run NAME --duration {args.fixed_duration:g} --out DIR` in a fresh process "
          "(wall s; start = imports, CLI and exit; closing = end-of-run plots and files)")
    print("| run | command | start | set-up | ticks | closing | plot pages |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name in FIXED_COST_RUNS:
        cost = fixed_costs(name, args.fixed_duration)
        print(f"| {name} | {cost['command_s']:.2f} | {cost['start_s']:.2f} | {cost['setup_s']:.2f} | "
              f"{cost['ticks_s']:.2f} | {cost['closing_s']:.2f} | {cost['pages']} |", flush=True)


if __name__ == "__main__":
    main()
