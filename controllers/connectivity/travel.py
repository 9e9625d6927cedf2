"""Traveling, anchoring and efficiency laws of seed 001 (Secs. 3.6-3.7, eqs. 3-15).

Pure functions over arrays batched over robots: positions q (N, 3), m;
velocities (N, 3), m/s; forces (N, 3), N. A path reference (closest point,
velocity and acceleration of the virtual point travelling along gamma_i) is
computed per robot from its own path, then everything else is batched.

- eq. (3)  ``travel_force``: a_gamma + k_v (v_gamma - q') + k_p (q_gamma - q);
- (5)-(7)  ``anchor_potential`` / ``anchor_force``;
- (8)/(10) ``force_alignment`` Theta;
- (9)      ``efficiency`` Lambda(x, x_c, x_M);
- (11)     ``tracking_error`` e_i; (12) ``traveling_efficiency`` Lambda_i;
- (13)     ``consensus_step``: the efficiency estimate of the prime traveler,
           forward-Euler discretised and saturated to [0, 1];
- (14)-(15) ``adaptive_gain`` rho;
- Alg. 1 line 17 ``needs_replanning``: ||q - q_gamma|| > R_gamma.

Deviations from the paper
-------------------------
- Reference speed: the virtual point of eq. (3) moves at v_cruise except over
  the last ``braking_distance`` metres of the path, where its speed falls
  linearly with the remaining length d_gamma to 0 at the target, and a_gamma
  gains the matching tangential term v dv/ds. The paper's constant speed would
  carry travelers past their targets at cruise speed.
- eq. (3) is multiplied by the virtual mass m (M = m I): in the paper M = I is
  implicit (the feedforward a_gamma is an acceleration).
- eq. (7) is capped at ``max_force`` and keeps pointing to the target beyond
  R_z, where the paper's tan(.) changes sign: needed in discrete time.
- eq. (13) is integrated with forward Euler over the control period using the
  neighbours' estimates of the previous tick (one message exchange per tick).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.connectivity.path_batch import PathBatch
from controllers.connectivity.paths import SplinePath


@dataclass(frozen=True)
class PathReference:
    """The virtual point on gamma_i closest to each robot, all batched over P robots.

    arc_length: (P,) arc length of q_gamma along the path, m.
    point: (P, 3) q_gamma, the closest path point, m.
    velocity: (P, 3) v_gamma(v_cruise, q_gamma), m/s.
    acceleration: (P, 3) a_gamma(v_cruise, q_gamma), m/s^2.
    distance: (P,) ||q - q_gamma||, m.
    remaining: (P,) d_gamma, length of the remaining path, m.
    """

    arc_length: np.ndarray
    point: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    distance: np.ndarray
    remaining: np.ndarray

    def row(self, k: int) -> "PathReference":
        """Robot k's reference alone (P = 1)."""
        return PathReference(*(getattr(self, name)[k : k + 1] for name in PathReference.__dataclass_fields__))

    @staticmethod
    def stack(references: "list[PathReference]") -> "PathReference":
        """One reference per robot (P = 1 each) -> one batched reference."""
        return PathReference(
            *(np.concatenate([getattr(r, name) for r in references]) for name in PathReference.__dataclass_fields__)
        )


def row_norm(x: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """Euclidean norm of each row of a float (P, 3) array: np.linalg.norm(x, axis=1)'s very sum
    (the same bits) without its argument checks, which cost more than the sum at this size."""
    return np.sqrt(np.add.reduce(x * x, axis=1, keepdims=keepdims))


def reference_speed(remaining, cruise_speed: float, braking_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Speed (P,), m/s, of the virtual point with ``remaining`` (P,) metres to go,
    and its derivative along the path dv/ds (P,), 1/s."""
    remaining = np.asarray(remaining, dtype=float)
    braking = remaining < braking_distance
    speed = cruise_speed * np.where(braking, np.maximum(remaining, 0.0) / braking_distance, 1.0)
    slope = np.where(braking, -cruise_speed / braking_distance, 0.0)  # d_gamma decreases as s grows
    return speed, slope


def path_reference(path: SplinePath, positions, cruise_speed: float, braking_distance: float) -> PathReference:
    """Closest point, velocity and acceleration of the virtual point on ``path``
    for robots at ``positions`` (P, 3) following it at up to ``cruise_speed``."""
    positions = np.atleast_2d(np.asarray(positions, dtype=float))
    return _reference(path.length, *path.closest_frame(positions), cruise_speed, braking_distance)


def batch_path_reference(batch: PathBatch, positions, cruise_speed: float, braking_distance: float) -> PathReference:
    """``path_reference`` of robot r on path r of ``batch`` for all r at once
    (positions (R, 3)); the same numbers, one numpy pass."""
    positions = np.atleast_2d(np.asarray(positions, dtype=float))
    return _reference(batch.lengths, *batch.closest_frame(positions), cruise_speed, braking_distance)


def _reference(length, arc, closest, tangent, curvature, distance, cruise_speed, braking_distance) -> PathReference:
    remaining = length - arc
    speed, slope = reference_speed(remaining, cruise_speed, braking_distance)
    velocity = speed[:, None] * tangent
    # d/dt (v t) = v dv/ds t + v^2 dt/ds along the path.
    acceleration = (speed * slope)[:, None] * tangent + (speed**2)[:, None] * curvature
    return PathReference(arc, closest, velocity, acceleration, distance, remaining)


def travel_force(
    positions, velocities, reference: PathReference, position_gain: float, velocity_gain: float, mass: float = 1.0,
    max_force: float = np.inf,
) -> np.ndarray:
    """Eq. (3): f_travel (P, 3), N = m [a_gamma + k_v (v_gamma - q') + k_p (q_gamma - q)],
    magnitude capped at ``max_force`` (direction kept)."""
    positions = np.atleast_2d(positions)
    velocities = np.atleast_2d(velocities)
    force = mass * (
        reference.acceleration
        + velocity_gain * (reference.velocity - velocities)
        + position_gain * (reference.point - positions)
    )
    if np.isfinite(max_force):
        magnitude = row_norm(force, keepdims=True)
        force *= np.minimum(1.0, max_force / np.maximum(magnitude, 1e-12))
    return force


def needs_replanning(reference: PathReference, replan_distance: float) -> np.ndarray:
    """Alg. 1 line 17: boolean (P,), the robot is farther than R_gamma from its path."""
    return reference.distance > replan_distance


def anchor_potential(distance, radius: float, gain: float) -> np.ndarray:
    """Eq. (6): V_anchor(l) = -k_z (2 R_z / pi) ln cos(l pi / (2 R_z)), J; inf for l >= R_z."""
    distance = np.asarray(distance, dtype=float)
    inside = distance < radius
    angle = np.where(inside, distance, 0.0) * np.pi / (2.0 * radius)
    return np.where(inside, -gain * (2.0 * radius / np.pi) * np.log(np.cos(angle)), np.inf)


def anchor_force(positions, targets, radius: float, gain: float, max_force: float = np.inf) -> np.ndarray:
    """Eqs. (5), (7): f_anchor (P, 3), N = -k_z tan(l pi / (2 R_z)) (q - z) / l,
    magnitude capped at ``max_force``; at ``max_force`` towards z for l >= R_z."""
    offset = np.atleast_2d(positions) - np.atleast_2d(targets)
    distance = row_norm(offset)
    inside = distance < radius
    magnitude = np.where(inside, gain * np.tan(np.where(inside, distance, 0.0) * np.pi / (2.0 * radius)), np.inf)
    magnitude = np.minimum(magnitude, max_force)
    direction = np.where(distance[:, None] > 0, offset / np.where(distance > 0, distance, 1.0)[:, None], 0.0)
    return -magnitude[:, None] * direction


def force_alignment(x, y) -> np.ndarray:
    """Eqs. (8), (10): Theta (P,) = (1 + cos angle(x, y)) / 2 in [0, 1]; 1 if either is zero."""
    x = np.atleast_2d(x)
    y = np.atleast_2d(y)
    nx = row_norm(x)
    ny = row_norm(y)
    both = (nx > 0) & (ny > 0)
    cosine = np.sum(x * y, axis=1) / np.where(both, nx * ny, 1.0)
    # np.minimum(np.maximum(.)) here and below: np.clip's own arithmetic (NaN kept), without its ~4 us dispatch
    return np.where(both, 0.5 * (1.0 + np.minimum(np.maximum(cosine, -1.0), 1.0)), 1.0)


def efficiency(x, x_full: float, x_zero: float) -> np.ndarray:
    """Eq. (9): Lambda(x, x_c, x_M): 1 up to x_c, raised cosine down to 0 at x_M, 0 beyond."""
    if not 0 <= x_full < x_zero:
        raise ValueError(f"eq. (9) needs 0 <= x_c < x_M, got x_c={x_full!r}, x_M={x_zero!r}")
    x = np.asarray(x, dtype=float)
    phase = np.minimum(np.maximum((x - x_full) / (x_zero - x_full), 0.0), 1.0)
    return 0.5 + 0.5 * np.cos(np.pi * phase)


def tracking_error(positions, velocities, reference: PathReference, position_weight: float) -> np.ndarray:
    """Eq. (11): e_i (P,) = (1 - alpha_A) ||v_gamma - q'|| + alpha_A ||q_gamma - q||."""
    velocity_error = row_norm(reference.velocity - np.atleast_2d(velocities))
    position_error = row_norm(reference.point - np.atleast_2d(positions))
    return (1.0 - position_weight) * velocity_error + position_weight * position_error


def traveling_efficiency(
    positions, velocities, reference: PathReference, position_weight: float, x_full: float, x_zero: float
) -> np.ndarray:
    """Eq. (12): Lambda_i (P,) = Lambda(e_i, x_c, x_M)."""
    return efficiency(tracking_error(positions, velocities, reference, position_weight), x_full, x_zero)


def consensus_step(estimates, adjacency, is_prime, prime_efficiency, gain: float, dt: float) -> np.ndarray:
    """Eq. (13) over one control period ``dt`` (s), saturated to [0, 1].

    estimates: (N,) current hat-Lambda_p^i; adjacency: (N, N) bool or weights
    (only W_ij > 0 matters: eq. 13 sums over neighbours); is_prime: (N,) bool;
    prime_efficiency: (N,) Lambda_i, read where is_prime. Non-prime robots move
    towards their neighbours' previous estimates at rate k_A = ``gain`` (1/s).
    """
    estimates = np.asarray(estimates, dtype=float)
    neighbours = np.asarray(adjacency) > 0
    np.fill_diagonal(neighbours, False)  # a robot is not its own neighbour
    disagreement = neighbours.astype(float) @ estimates - neighbours.sum(axis=1) * estimates
    updated = np.minimum(np.maximum(estimates + dt * gain * disagreement, 0.0), 1.0)
    return np.where(is_prime, np.minimum(np.maximum(prime_efficiency, 0.0), 1.0), updated)


def adaptive_gain(alignment, efficiency_estimate, sigma: float) -> np.ndarray:
    """Eqs. (14)-(15): rho = (1 - Theta) hat-Lambda^sigma + Theta (1 - (1 - hat-Lambda)^sigma)."""
    if not sigma >= 1.0:
        raise ValueError(f"sigma must be >= 1 (eq. 14), got {sigma!r}")
    x = np.minimum(np.maximum(np.asarray(alignment, dtype=float), 0.0), 1.0)
    y = np.minimum(np.maximum(np.asarray(efficiency_estimate, dtype=float), 0.0), 1.0)
    return (1.0 - x) * y**sigma + x * (1.0 - (1.0 - y) ** sigma)
