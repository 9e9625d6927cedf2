"""Sweep throughput, measured in one run (a benchmark, not a test).

Prints markdown: the cost of short slices of ``fig9-small`` and ``table1``
per simulated second and its honest extrapolation to whole trials; the
speed-up of 2 pool workers over 1 on the same slice; a local single-node
Ray cluster against the pool; the driver's memory as rows accumulate.

    .venv/bin/python bench/bench_sweep.py [--out runs/bench_sweep]

Extrapolation: a trial's cost = its fixed part (loading, worker imports,
world build) + (simulated seconds) x (measured wall per simulated second).
Short slices overstate the per-second cost a little (the world build is in
the run's wall time); whole trials are what docs/sweeps.md projects from.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from sim.sweep import ProcessPool, RayCluster, ResultsFolder, load_sweep, read_results, run_sweep  # noqa: E402

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
    assert outcome.completed == outcome.total, f"{sweep_path.name}: {outcome}"
    return wall, read_results(folder).to_pylist()


def projected_trial_s(row: dict, sim_s: float) -> float:
    fixed = row["wall_time_s"] - row["metrics_wall_s"]
    return fixed + row["metrics_wall_s"] * sim_s / row["sim_time_s"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/bench_sweep")
    parser.add_argument("--slice-s", type=float, default=4.0, help="simulated seconds of a slice trial")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0]
    print(f"machine: {os.cpu_count()} cores, load average {load:.1f} at the start\n")

    # 1. Slices of the built-in sweeps, 2 workers.
    fig9 = sweep_file(out, "fig9-slice", f'scenario = "connected-office"\nduration_s = {args.slice_s}\nseeds = [1]\n'
                      '[grid]\nscenario = ["connected-office", "connected-empty", "connected-town"]\n'
                      '"robots.0.count" = [10, 35]\n')
    table1 = sweep_file(out, "table1-slice", f'scenario = "intermittent-4"\nduration_s = {4 * args.slice_s}\n'
                        'seeds = [0]\n[grid]\nscenario = ["intermittent-4", "intermittent-8"]\n'
                        '"strategy.kind" = ["all_time", "random_meeting", "intermittent"]\n')
    print("| slice | trial | simulated s | trial wall s | of which fixed s | projected whole trial s |")
    print("| --- | --- | --- | --- | --- | --- |")
    projections = {}
    for name, path in (("fig9-small", fig9), ("table1", table1)):
        _, rows = run(out / name, path, ProcessPool(2))
        costs = []
        for r in rows:
            r["metrics_wall_s"] = r["run_wall_time_s"]
            label = Path(r["scenario"]).stem
            typical = TYPICAL_SIM_S[label]
            cost = projected_trial_s(r, typical)
            costs.append(cost)
            what = f"{label} n={r['n_robots']}" if name == "fig9-small" else f"{label} {r['strategy']}"
            print(f"| {name} | {what} | {r['sim_time_s']:.1f} | {r['wall_time_s']:.1f} | "
                  f"{r['wall_time_s'] - r['metrics_wall_s']:.1f} | {cost:.0f} (at {typical:.0f} s simulated) |")
        projections[name] = sum(costs) / len(costs)
    print()
    for name, mean_cost in projections.items():
        print(f"- {name}: projected mean cost {mean_cost:.0f} s per trial (one core) -> "
              f"{3600 / mean_cost:.1f} trials/hour per core, {2 * 3600 / mean_cost:.1f} on 2 workers")
    fig9_trials = 1800
    print(f"- fig9 ({fig9_trials} trials): {fig9_trials * projections['fig9-small'] / 3600:.0f} core-hours projected; "
          f"fig9-small (180): {180 * projections['fig9-small'] / 3600:.1f} core-hours\n")

    # 2. 1 worker against 2, and 3. Ray against the pool, on one slice.
    same = sweep_file(out, "scaling", f'scenario = "connected-office"\nduration_s = {args.slice_s}\n'
                      'seeds = [1, 2, 3, 4, 5, 6]\n')
    one, _ = run(out / "scaling1", same, ProcessPool(1))
    two, _ = run(out / "scaling2", same, ProcessPool(2))
    print(f"- 6 trials (connected-office, 10 robots, {args.slice_s:g} s): 1 worker {one:.1f} s, 2 workers {two:.1f} s "
          f"-> speed-up {one / two:.2f}x")
    ray_bin = Path(sys.executable).parent / "ray"
    if ray_bin.exists():
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        started = time.perf_counter()
        subprocess.run([str(ray_bin), "start", "--head", f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
                        "--disable-usage-stats"], check=True, capture_output=True)
        ray_start = time.perf_counter() - started
        try:
            on_ray, _ = run(out / "scaling-ray", same, RayCluster(f"127.0.0.1:{port}"))
        finally:
            subprocess.run([str(ray_bin), "stop", "--force"], capture_output=True)
        print(f"- same 6 trials on a local Ray cluster (2 CPUs): {on_ray:.1f} s against the pool's {two:.1f} s "
              f"({on_ray / two:.2f}x; `ray start` itself took {ray_start:.0f} s, not counted)")
    else:
        print("- Ray is not installed: no Ray figure")

    # 4. The driver's memory as rows accumulate.
    tiny = sweep_file(out, "memory", 'scenario = "hover"\nduration_s = 0.05\nseeds = 120\n')
    samples = {}

    def sample(row: dict) -> None:
        samples[len(samples) + 1] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    run(out / "memory", tiny, ProcessPool(2), on_row=sample)
    marks = [m for m in (1, 10, 30, 60, 120) if m in samples]
    print("- driver peak RSS after " + ", ".join(f"{m} rows: {samples[m]:.0f} MiB" for m in marks))
    print(f"\nload average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
