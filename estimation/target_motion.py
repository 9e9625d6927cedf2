"""Target motion model of Khodayi-mehr et al. 2019, eq. (11): x_a(t+1) = A_a x_a(t) + B_a u_a(t) + w_a(t).

Pure numpy. Targets follow linear (back and forth between two points) or
circular paths, each step corrupted by Gaussian process noise w_a ~ N(0, Q_a).
Both kinds are linear in the state, so the stacked model is exactly the LTI
system the EKF predicts with:

- circular, centre c, angular rate omega: A_a = Rz(omega dt), B_a u_a = (I - A_a) c;
- linear, velocity v: A_a = I, B_a u_a = +/- v dt (the sign flips when the
  nominal position reaches an end point, keeping the target on its segment).

The nominal input is a function of the nominal (noise-free) path only, so the
estimator knows it without seeing the true state. The true state is pulled
back toward the nominal path by the same A (circular) or stays within noise
of it (linear): the noise is small (Q_a = q I, q ~ 1e-4 m^2 per step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LinearPath:
    """Back-and-forth motion between ``start`` and ``end`` (m) at ``speed`` m/s."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    speed: float


@dataclass(frozen=True)
class CircularPath:
    """Circle in a horizontal plane: ``center`` (m), ``radius`` (m), start ``phase`` (rad),
    ``speed`` m/s along the circle (sign gives the direction)."""

    center: tuple[float, float, float]
    radius: float
    speed: float
    phase: float = 0.0


TargetPath = LinearPath | CircularPath


def _rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def path_start(path: TargetPath) -> np.ndarray:
    """Initial nominal position (3,), m."""
    if isinstance(path, LinearPath):
        return np.array(path.start, dtype=float)
    c = np.array(path.center, dtype=float)
    return c + path.radius * np.array([np.cos(path.phase), np.sin(path.phase), 0.0])


class TargetMotion:
    """Stacked LTI motion of M targets with a fixed step ``dt`` (s).

    ``transition`` is A (3M, 3M); ``input(k)`` is B u(k) (3M,) for step k -> k+1;
    ``process_noise`` is Q (3M, 3M), m^2.
    """

    def __init__(self, paths: list[TargetPath], dt: float, noise_std: float):
        if dt <= 0:
            raise ValueError(f"dt: must be positive, got {dt}")
        if noise_std < 0:
            raise ValueError(f"noise_std: must be non-negative, got {noise_std}")
        self.paths = list(paths)
        self.dt = dt
        self.noise_std = noise_std
        m = len(self.paths)
        self.transition = np.eye(3 * m)
        for a, path in enumerate(self.paths):
            if isinstance(path, CircularPath):
                omega = path.speed / path.radius
                self.transition[3 * a : 3 * a + 3, 3 * a : 3 * a + 3] = _rotation_z(omega * dt)
        self.process_noise = noise_std**2 * np.eye(3 * m)
        self._nominal = np.concatenate([path_start(p) for p in self.paths]) if m else np.zeros(0)
        self._inputs: list[np.ndarray] = []
        self._headings: dict[int, float] = {}  # linear paths: +1 toward end, -1 back

    @property
    def n_targets(self) -> int:
        return len(self.paths)

    def initial_state(self) -> np.ndarray:
        return np.concatenate([path_start(p) for p in self.paths]) if self.paths else np.zeros(0)

    def _nominal_input(self, nominal: np.ndarray) -> np.ndarray:
        u = np.zeros_like(nominal)
        for a, path in enumerate(self.paths):
            block = slice(3 * a, 3 * a + 3)
            if isinstance(path, CircularPath):
                c = np.array(path.center, dtype=float)
                u[block] = c - self.transition[block, block] @ c
            else:
                u[block] = self._linear_step(path, nominal[block], a)
        return u

    def _linear_step(self, path: LinearPath, position: np.ndarray, index: int) -> np.ndarray:
        start, end = np.array(path.start, float), np.array(path.end, float)
        span = end - start
        length = np.linalg.norm(span)
        if length == 0 or path.speed == 0:
            return np.zeros(3)
        direction = span / length
        step = path.speed * self.dt
        heading = self._headings.get(index, 1.0)
        along = float((position - start) @ direction)
        if heading > 0 and along + step > length:
            heading = -1.0
        elif heading < 0 and along - step < 0:
            heading = 1.0
        self._headings[index] = heading
        return heading * step * direction

    def input(self, k: int) -> np.ndarray:
        """B u(k), m: the known input from step k to k + 1 (memoised, any order)."""
        while len(self._inputs) <= k:
            u = self._nominal_input(self._nominal)
            self._inputs.append(u)
            self._nominal = self.transition @ self._nominal + u
        return self._inputs[k]

    def step(self, x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
        """True state at k + 1 from x at k, with process noise drawn from ``rng``."""
        noise = rng.normal(0.0, self.noise_std, size=x.shape)
        return self.transition @ x + self.input(k) + noise

    def predict(self, x: np.ndarray, k: int) -> np.ndarray:
        """Noise-free prediction of the state at k + 1 (what the EKF uses)."""
        return self.transition @ x + self.input(k)
