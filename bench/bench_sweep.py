"""Sweep throughput, measured in one run (a benchmark, not a test).

Prints markdown: the cost of short slices of ``fig9-small`` and ``table1``
per simulated second and its honest extrapolation to whole trials; the
speed-up of 2 pool workers over 1 on the same slice; a local single-node
Ray cluster against the pool; the driver's memory as rows accumulate.

    .venv/bin/python bench/bench_sweep.py [--out runs/bench_sweep] [--parts slices scaling memory]

Extrapolation: each slice trial runs at two durations T1 and T2 = 3 T1; the
wall time per simulated second is (w2 - w1) / (T2 - T1), the fixed cost
(imports, world build, first plans) what remains of w1; a whole trial is
projected as fixed + (typical simulated seconds) x (wall per simulated
second). Typical simulated seconds: README's measured completions for the
connected scenes (a trial stops when every target is visited), 300 s for
table1. A mission's later phases may cost more or less per second than its
first seconds: the projection is an estimate, not a measurement.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from tether.sweep import (ProcessPool, RayCluster, ResultsFolder, load_sweep, local_ray_cluster,  # noqa: E402
                       read_results, run_sweep)

# Typical simulated seconds of a whole trial (README, seed 1-4 measurements):
# completion ends a connected trial early; table1/teams trials run 300 s.
TYPICAL_SIM_S = {"connected-office": 150.0, "connected-empty": 300.0, "connected-town": 290.0,
                 "intermittent-4": 300.0, "intermittent-8": 300.0}


def sweep_file(folder: Path, name: str, text: str) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(text)
    return path


def run(folder: Path, sweep_path: Path, engine, on_row=None) -> tuple[float, list[dict]]:
    if folder.exists():
        shutil.rmtree(folder)
    sweep = load_sweep(str(sweep_path))
    ResultsFolder(folder).claim(sweep)
    start = time.perf_counter()
    outcome = run_sweep(sweep, folder, engine, progress=False, on_row=on_row)
    wall = time.perf_counter() - start
    assert outcome.finished == outcome.total, f"{sweep_path.name}: {outcome}"
    return wall, read_results(folder).to_pylist()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/bench_sweep")
    parser.add_argument("--slice-s", type=float, default=2.0,
                        help="simulated seconds of the short fig9 slice trial (x3 the long one; table1: x2.5)")
    parser.add_argument("--parts", nargs="+", default=["slices", "scaling", "memory"],
                        choices=["slices", "scaling", "memory"],
                        help="what to measure: slice costs and projections, 1 against 2 workers and Ray, "
                             "the driver's memory (default: all)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0]
    print(f"machine: {os.cpu_count()} cores, load average {load:.1f} at the start\n")

    # 1. Slices of the built-in sweeps, 2 workers, each trial at two durations: the difference
    # is the cost of simulated time, the rest the fixed cost (imports, world build, first plans).
    def slice_file(name: str, duration: float) -> Path:
        if name == "fig9-small":
            return sweep_file(out, f"fig9-slice-{duration:g}", f'scenario = "connected-office"\nduration_s = {duration}\n'
                              'seeds = [1]\n[grid]\nscenario = ["connected-office", "connected-empty", "connected-town"]\n'
                              '"robots.0.count" = [10, 35]\n')
        return sweep_file(out, f"table1-slice-{duration:g}", f'scenario = "intermittent-4"\nduration_s = {duration}\n'
                          'seeds = [0]\n[grid]\nscenario = ["intermittent-4", "intermittent-8"]\n'
                          '"strategy.kind" = ["all_time", "random_meeting", "intermittent"]\n')

    if "slices" in args.parts:
        project(out, args.slice_s, slice_file)
    if "scaling" in args.parts:
        scaling(out, args.slice_s)
    if "memory" in args.parts:
        memory(out)
    print(f"\nload average at the end {os.getloadavg()[0]:.1f}")


def project(out: Path, slice_s: float, slice_file) -> None:
    print("| slice | trial | wall s at T1 / T2 simulated s | fixed s | wall per simulated s | "
          "projected whole trial s |")
    print("| --- | --- | --- | --- | --- | --- |")
    projections = {}
    for name, short in (("fig9-small", slice_s), ("table1", 2.5 * slice_s)):
        long = 3 * short
        rows = {}
        for duration in (short, long):
            _, found = run(out / f"{name}-{duration:g}", slice_file(name, duration), ProcessPool(2))
            for r in found:
                key = (Path(r["scenario"]).stem, r["n_robots"] if name == "fig9-small" else r["strategy"])
                rows.setdefault(key, {})[duration] = r["wall_time_s"]
        costs = []
        for (label, what), wall in rows.items():
            per_s = max(wall[long] - wall[short], 0.0) / (long - short)
            fixed = wall[short] - short * per_s
            typical = TYPICAL_SIM_S[label]
            cost = fixed + typical * per_s
            costs.append(cost)
            print(f"| {name} | {label} {'n=' if name == 'fig9-small' else ''}{what} | "
                  f"{wall[short]:.1f} / {wall[long]:.1f} at {short:g} / {long:g} | {fixed:.1f} | {per_s:.2f} | "
                  f"{cost:.0f} (at {typical:.0f} s simulated) |")
        projections[name] = sum(costs) / len(costs)
    print()
    for name, mean_cost in projections.items():
        print(f"- {name}: projected mean cost {mean_cost:.0f} s per trial on one worker -> "
              f"{3600 / mean_cost:.1f} trials/hour per worker, {2 * 3600 / mean_cost:.1f} on 2 workers")
    print(f"- fig9 (1,800 trials): {1800 * projections['fig9-small'] / 3600:.0f} core-hours projected; "
          f"fig9-small (180): {180 * projections['fig9-small'] / 3600:.1f} core-hours; "
          f"table1 (60): {60 * projections['table1'] / 3600:.1f} core-hours\n")


def scaling(out: Path, slice_s: float) -> None:
    """1 worker against 2, and Ray against the pool, on the same 6 trials."""
    same = sweep_file(out, "scaling", f'scenario = "connected-office"\nduration_s = {slice_s}\n'
                      'seeds = [1, 2, 3, 4, 5, 6]\n')
    one, _ = run(out / "scaling1", same, ProcessPool(1))
    two, _ = run(out / "scaling2", same, ProcessPool(2))
    print(f"- 6 trials (connected-office, 10 robots, {slice_s:g} s): 1 worker {one:.1f} s, 2 workers {two:.1f} s "
          f"-> speed-up {one / two:.2f}x")
    try:
        import ray  # noqa: F401
    except ImportError:
        print("- Ray is not installed: no Ray figure")
    else:
        started = time.perf_counter()
        with local_ray_cluster(num_cpus=2) as address:
            ray_start = time.perf_counter() - started
            on_ray, _ = run(out / "scaling-ray", same, RayCluster(address))
        print(f"- same 6 trials on a local Ray cluster (2 CPUs): {on_ray:.1f} s against the pool's {two:.1f} s "
              f"({on_ray / two:.2f}x; starting the cluster took {ray_start:.0f} s, not counted)")


def memory(out: Path) -> None:
    """The driver's peak memory as rows accumulate."""
    tiny = sweep_file(out, "memory", 'scenario = "hover"\nduration_s = 0.05\nseeds = 120\n')
    samples = {}

    def sample(row: dict) -> None:
        samples[len(samples) + 1] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    run(out / "memory", tiny, ProcessPool(2), on_row=sample)
    marks = [m for m in (1, 10, 30, 60, 120) if m in samples]
    print("- driver peak RSS after " + ", ".join(f"{m} rows: {samples[m]:.0f} MiB" for m in marks))


if __name__ == "__main__":
    main()
