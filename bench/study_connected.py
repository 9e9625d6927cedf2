"""Seed 001's team-size study (the trend of the paper's Fig. 9) on connected-office.

For every seed (one random target configuration each: one seed gives the same
25 targets whatever the team size) and every robot count, runs the scenario
to completion with real MuJoCo quadrotors and keeps its metrics.json in
``OUT/office_s{seed}_n{count}/``; runs already there are reused (resumable).
Prints one markdown row per team size: completion time, explorers' mean
travelled distance, max stretch between explorers, mean and min lambda2
(means over seeds, with the per-seed values of the completion time), and
optionally the same for the estimator mode and the paper's raw lambda2
gradient (``--variants``).

    .venv/bin/python bench/study_connected.py --seeds 1 2 3 4 --counts 10 20 35 --out runs/study
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sim  # noqa: E402,F401  (GL backend before mujoco)
from sim.loop import run  # noqa: E402
from sim.scenario import load  # noqa: E402

VARIANTS = {
    "estimator": ['strategy.lambda2_source="estimator"'],
    "raw": ["strategy.spectrum_smoothing=0.0"],
}


def metrics(out: Path, name: str, seed: int, overrides: list[str], duration: float | None) -> dict:
    folder = out / name
    path = folder / "metrics.json"
    if not path.exists():
        run(load("connected-office", overrides, seed=seed, duration_s=duration), folder)
    return json.loads(path.read_text())


def row(label: str, results: list[dict]) -> str:
    def mean(key):
        values = [r[key] for r in results if r[key] is not None]
        return sum(values) / len(values) if values else float("nan")

    done = [r["completion_time_s"] for r in results]
    per_seed = ", ".join("-" if t is None else f"{t:.0f}" for t in done)
    finished = [t for t in done if t is not None]
    completion = f"{sum(finished) / len(finished):.0f}" if finished else "-"
    return (f"| {label} | {completion} ({per_seed}) | {sum(r['targets_visited'] for r in results)}/"
            f"{sum(r['targets_to_visit'] for r in results)} | {mean('mean_travel_m'):.1f} | {mean('max_stretch_m'):.1f} | "
            f"{mean('lambda2_mean'):.3f} | {min(r['lambda2_min'] for r in results):.4f} | "
            f"{mean('tracking_error_mean_m'):.4f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    parser.add_argument("--counts", type=int, nargs="+", default=[10, 20, 35])
    parser.add_argument("--variants", nargs="*", default=[], choices=sorted(VARIANTS),
                        help="also run the 10-robot team in these modes on the same seeds")
    parser.add_argument("--variant-duration", type=float, default=300.0, help="time cap of a variant run, s")
    parser.add_argument("--out", default="runs/study")
    args = parser.parse_args()
    out = Path(args.out)

    print("| robots | completion s, mean (per seed) | targets visited | explorers' travel m | max stretch m | "
          "mean lambda2 | min lambda2 | tracking error m |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for count in args.counts:
        results = [metrics(out, f"office_s{seed}_n{count}", seed, [f"robots.0.count={count}"], None)
                   for seed in args.seeds]
        print(row(str(count), results))
    for variant in args.variants:
        results = [metrics(out, f"{variant}_s{seed}", seed, VARIANTS[variant], args.variant_duration)
                   for seed in args.seeds]
        print(row(f"10, {variant}", results))


if __name__ == "__main__":
    main()
