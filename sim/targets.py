"""Ground-truth target motion in the simulation (Khodayi-mehr et al. 2019, eq. 11).

The discrete model advances every ``target_motion.step_s``; between steps the
mocap bodies move linearly from x(k) to x(k+1), so videos stay smooth while
the states at the step instants are exactly the model's.
"""

from __future__ import annotations

import math

import numpy as np

from estimation.target_motion import CircularPath, LinearPath, TargetMotion
from sim.compiled import kernel
from sim.scenario import Scenario, TargetConfig

PATH_SAMPLES = 200  # nominal-path points checked against obstacles and bounds


def target_path(config: TargetConfig):
    if config.path == "circular":
        return CircularPath(config.center, config.radius_m, config.speed_mps, config.phase_rad)
    if config.path == "static":
        return LinearPath(config.start, config.start, 0.0)
    return LinearPath(config.start, config.end, config.speed_mps)


def nominal_path_samples(config: TargetConfig) -> np.ndarray:
    """Points (PATH_SAMPLES, 3) along a target's noise-free path."""
    s = np.linspace(0.0, 1.0, PATH_SAMPLES)[:, None]
    if config.path == "circular":
        angle = config.phase_rad + 2 * np.pi * s[:, 0]
        c = np.array(config.center)
        return c + config.radius_m * np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
    start = np.array(config.start, dtype=float)
    end = start if config.path == "static" else np.array(config.end, dtype=float)
    return start + s * (end - start)


class TargetDriver:
    def __init__(self, scenario: Scenario, rng: np.random.Generator):
        self.step_s = scenario.target_motion.step_s
        self.motion = TargetMotion([target_path(t) for t in scenario.targets], self.step_s,
                                   scenario.target_motion.noise_std_m)
        self.rng = rng
        self.states = [self.motion.initial_state()]  # x(0), x(1), ... as drawn

    @property
    def n_targets(self) -> int:
        return self.motion.n_targets

    def state_at_step(self, k: int) -> np.ndarray:
        while len(self.states) <= k:
            j = len(self.states) - 1
            self.states.append(self.motion.step(self.states[j], j, self.rng))
        return self.states[k]

    def positions(self, t: float) -> np.ndarray:
        """(M, 3) true target positions at sim time t."""
        k = math.floor(t / self.step_s + 1e-9)
        alpha = t / self.step_s - k
        return _blend(self.state_at_step(k), self.state_at_step(k + 1), alpha).reshape(-1, 3)


@kernel
def _blend(before, after, alpha):
    """(1 - alpha) before + alpha after, elementwise, in numpy's order (one call instead of four)."""
    out = np.empty(before.shape[0])
    for i in range(before.shape[0]):
        out[i] = (1 - alpha) * before[i] + alpha * after[i]
    return out
