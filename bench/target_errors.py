"""Where a tracking run's e_g comes from, per target: when it is fixed and how far off it is before and after.

    python bench/target_errors.py SCENARIO SCENE SEED DURATION [KEY=VALUE ...]

SCENE is a MuJoCo XML of your own (the scenario is moved there as ``--scene`` does) or ``own``
(the scenario's own scene). Prints one JSON line: e_g_mean (eq. 13a) and, per target, t_fix (the
first step at which its covariance has no variance above 1 m^2: a multilateration fix, the search's
collapse, or an informed prior from the start), its mean error before and after, and its share of
the summed squared error. Used for docs/intermittent.md's "Targets without an informed prior".
"""

from __future__ import annotations

import json
import sys

import numpy as np

from sim.config import ConfigError
from sim.observers import Frame, Observer
from sim.scenario import load
from tether.placement import load_in_scene
from tether.runner import run

FIXED_VARIANCE_M2 = 1.0


class PerTargetErrors(Observer):
    def __init__(self):
        self.steps: list[int] = []
        self.errors: list[np.ndarray] = []
        self.variances: list[np.ndarray] = []

    def reads_decorations(self, time_s: float) -> bool:
        return False

    def on_tick(self, frame: Frame) -> None:
        if frame.estimation is None or not frame.estimation.fresh:
            return
        estimate = frame.commands.estimate
        self.steps.append(estimate.step)
        self.errors.append(np.linalg.norm(np.asarray(estimate.mean) - frame.target_positions, axis=1))
        self.variances.append(np.linalg.eigvalsh(np.asarray(estimate.covariance))[:, -1])

    def close(self, status: str) -> None:
        pass

    def report(self) -> dict:
        steps, errors, variances = np.array(self.steps), np.array(self.errors), np.array(self.variances)
        keep = steps >= 1
        total = float((errors[keep] ** 2).sum())
        targets = []
        for a in range(errors.shape[1]):
            fixed = np.flatnonzero(variances[:, a] <= FIXED_VARIANCE_M2)
            first = int(fixed[0]) if len(fixed) else None
            targets.append({
                "t_fix": int(steps[first]) if first is not None else None,
                "error_before_fix_m": float(errors[:first, a].mean()) if first else None,
                "error_after_fix_m": float(errors[first:, a].mean()) if first is not None else None,
                "share_of_squared_error": float((errors[keep, a] ** 2).sum() / total) if total else 0.0,
            })
        return {"e_g_mean_m": float(np.linalg.norm(errors[keep], axis=1).mean()), "targets": targets}


def main(argv: list[str]) -> int:
    if len(argv) < 4:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    name, scene, seed, duration, overrides = argv[0], argv[1], int(argv[2]), float(argv[3]), argv[4:]
    errors = PerTargetErrors()
    try:
        if scene == "own":
            scenario = load(name, overrides, seed=seed, duration_s=duration)
        else:
            scenario, _ = load_in_scene(name, scene, overrides, seed=seed, duration_s=duration)
        run(scenario, extra_observers=[errors])
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(json.dumps({"scenario": name, "scene": scene, "seed": seed, **errors.report()}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
