"""Traveling, anchoring and efficiency laws of Nestmeyer et al. 2017 (Secs. 3.6-3.7, eqs. 3-15).

Pure functions over arrays batched over robots: positions q (N, 3), m;
velocities (N, 3), m/s; forces (N, 3), N. A path reference (closest point,
velocity and acceleration of the virtual point travelling along gamma_i) is
computed per robot from its own path, then everything else is batched.
Each law is also a compiled per-robot kernel (``_travel_force_row``,
``_consensus_kernel``, ...): the batched functions here loop over them, and
the exploration layer runs them for the whole team in one compiled pass.

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
  Over the message bus the neighbours are the robots whose ``"consensus"``
  message reached the robot since the last tick, with the value it carried.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.connectivity.path_batch import PathBatch
from controllers.connectivity.paths import SplinePath
from sim.compiled import kernel


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
    pairs = [_reference_speed_scalar(value, float(cruise_speed), float(braking_distance)) for value in remaining.ravel()]
    speed = np.reshape([pair[0] for pair in pairs], remaining.shape)
    slope = np.reshape([pair[1] for pair in pairs], remaining.shape)
    return speed, slope


@kernel
def _reference_speed_scalar(remaining, cruise_speed, braking_distance):
    """``reference_speed`` of one robot: (speed, dv/ds)."""
    if remaining < braking_distance:
        ahead = remaining if (remaining != remaining or remaining > 0.0) else 0.0  # np.maximum(remaining, 0)
        return cruise_speed * (ahead / braking_distance), -cruise_speed / braking_distance  # d_gamma falls as s grows
    return cruise_speed * 1.0, 0.0


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
    arc = np.asarray(arc, dtype=float)
    remaining = np.empty(len(arc))
    velocity, acceleration = np.empty((len(arc), 3)), np.empty((len(arc), 3))
    length = np.full(arc.shape, length) if np.ndim(length) == 0 else np.asarray(length, dtype=float)
    _reference_kernel(length, arc, np.asarray(tangent, dtype=float),
                      np.asarray(curvature, dtype=float), float(cruise_speed), float(braking_distance), remaining,
                      velocity, acceleration)
    return PathReference(arc, closest, velocity, acceleration, distance, remaining)


@kernel
def _reference_kernel(length, arc, tangent, curvature, cruise_speed, braking_distance, remaining, velocity,
                      acceleration):
    """Remaining length, v_gamma and a_gamma of each robot's virtual point from its closest-point frame."""
    for r in range(arc.shape[0]):
        remaining[r] = length[r] - arc[r]
        speed, slope = _reference_speed_scalar(remaining[r], cruise_speed, braking_distance)
        for k in range(3):
            velocity[r, k] = speed * tangent[r, k]
            # d/dt (v t) = v dv/ds t + v^2 dt/ds along the path.
            acceleration[r, k] = (speed * slope) * tangent[r, k] + (speed * speed) * curvature[r, k]


def travel_force(
    positions, velocities, reference: PathReference, position_gain: float, velocity_gain: float, mass: float = 1.0,
    max_force: float = np.inf,
) -> np.ndarray:
    """Eq. (3): f_travel (P, 3), N = m [a_gamma + k_v (v_gamma - q') + k_p (q_gamma - q)],
    magnitude capped at ``max_force`` (direction kept)."""
    positions = np.atleast_2d(np.asarray(positions, dtype=float))
    velocities = np.atleast_2d(np.asarray(velocities, dtype=float))
    force = np.empty((len(positions), 3))
    for k in range(len(positions)):
        _travel_force_row(positions[k], velocities[k], reference.point[k], reference.velocity[k],
                          reference.acceleration[k], position_gain, velocity_gain, mass, max_force, force[k])
    return force


@kernel
def _norm3(x0, x1, x2):
    """Length of (x0, x1, x2), summed in numpy's order: sqrt((x0^2 + x1^2) + x2^2)."""
    return np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


@kernel
def _travel_force_row(q, v, point, velocity, acceleration, position_gain, velocity_gain, mass, max_force, out):
    """Eq. (3) for one robot into ``out`` (3,)."""
    for k in range(3):
        out[k] = mass * (acceleration[k] + velocity_gain * (velocity[k] - v[k]) + position_gain * (point[k] - q[k]))
    if np.isfinite(max_force):
        magnitude = _norm3(out[0], out[1], out[2])
        scale = min(1.0, max_force / max(magnitude, 1e-12))
        for k in range(3):
            out[k] *= scale


@kernel
def _tracking_error_row(q, v, point, velocity, position_weight):
    """Eq. (11) for one robot."""
    velocity_error = _norm3(velocity[0] - v[0], velocity[1] - v[1], velocity[2] - v[2])
    position_error = _norm3(point[0] - q[0], point[1] - q[1], point[2] - q[2])
    return (1.0 - position_weight) * velocity_error + position_weight * position_error


@kernel
def _clip01(x):
    """x clipped to [0, 1], NaN kept (as np.minimum(np.maximum(x, 0), 1))."""
    if x != x:
        return x
    return min(max(x, 0.0), 1.0)


@kernel
def _efficiency_scalar(x, x_full, x_zero):
    """Eq. (9) for one value."""
    phase = _clip01((x - x_full) / (x_zero - x_full))
    return 0.5 + 0.5 * np.cos(np.pi * phase)


@kernel
def _alignment_row(x, y):
    """Eqs. (8), (10) for one pair of (3,) forces."""
    nx = _norm3(x[0], x[1], x[2])
    ny = _norm3(y[0], y[1], y[2])
    if not (nx > 0 and ny > 0):
        return 1.0
    cosine = (x[0] * y[0] + x[1] * y[1] + x[2] * y[2]) / (nx * ny)
    return 0.5 * (1.0 + min(max(cosine, -1.0), 1.0)) if cosine == cosine else cosine


@kernel
def _adaptive_gain_scalar(alignment, estimate, sigma):
    """Eqs. (14)-(15) for one robot."""
    x = _clip01(alignment)
    y = _clip01(estimate)
    return (1.0 - x) * y**sigma + x * (1.0 - (1.0 - y) ** sigma)


@kernel
def _anchor_force_row(q, target, radius, gain, max_force, out):
    """Eqs. (5), (7) for one robot into ``out`` (3,)."""
    o0, o1, o2 = q[0] - target[0], q[1] - target[1], q[2] - target[2]
    distance = _norm3(o0, o1, o2)
    magnitude = gain * np.tan(distance * np.pi / (2.0 * radius)) if distance < radius else np.inf
    magnitude = min(magnitude, max_force)
    if distance > 0:
        out[0], out[1], out[2] = -magnitude * (o0 / distance), -magnitude * (o1 / distance), -magnitude * (o2 / distance)
    else:
        out[0], out[1], out[2] = -0.0 * magnitude, -0.0 * magnitude, -0.0 * magnitude


@kernel
def _consensus_kernel(estimates, heard, adjacency, is_prime, prime_efficiency, gain, dt, out):
    """Eq. (13) for every robot into ``out`` (N,); neighbours are j != i with adjacency[i, j] > 0, and
    heard[i, j] is robot i's value of robot j's estimate (all equal to estimates[j] in-process)."""
    n = estimates.shape[0]
    for i in range(n):
        if is_prime[i]:
            out[i] = _clip01(prime_efficiency[i])
            continue
        incoming, degree = 0.0, 0
        for j in range(n):
            if j != i and adjacency[i, j] > 0:
                incoming += heard[i, j]
                degree += 1
        out[i] = _clip01(estimates[i] + dt * gain * (incoming - degree * estimates[i]))


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
    positions = np.atleast_2d(np.asarray(positions, dtype=float))
    targets = np.broadcast_to(np.atleast_2d(np.asarray(targets, dtype=float)), positions.shape)
    force = np.empty((len(positions), 3))
    for k in range(len(positions)):
        _anchor_force_row(positions[k], targets[k], radius, gain, max_force, force[k])
    return force


def force_alignment(x, y) -> np.ndarray:
    """Eqs. (8), (10): Theta (P,) = (1 + cos angle(x, y)) / 2 in [0, 1]; 1 if either is zero."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    y = np.broadcast_to(np.atleast_2d(np.asarray(y, dtype=float)), x.shape)
    return np.array([_alignment_row(x[k], y[k]) for k in range(len(x))])


def efficiency(x, x_full: float, x_zero: float) -> np.ndarray:
    """Eq. (9): Lambda(x, x_c, x_M): 1 up to x_c, raised cosine down to 0 at x_M, 0 beyond."""
    if not 0 <= x_full < x_zero:
        raise ValueError(f"eq. (9) needs 0 <= x_c < x_M, got x_c={x_full!r}, x_M={x_zero!r}")
    x = np.asarray(x, dtype=float)
    return np.reshape([_efficiency_scalar(value, x_full, x_zero) for value in x.ravel()], x.shape)


def tracking_error(positions, velocities, reference: PathReference, position_weight: float) -> np.ndarray:
    """Eq. (11): e_i (P,) = (1 - alpha_A) ||v_gamma - q'|| + alpha_A ||q_gamma - q||."""
    positions = np.atleast_2d(np.asarray(positions, dtype=float))
    velocities = np.atleast_2d(np.asarray(velocities, dtype=float))
    return np.array([_tracking_error_row(positions[k], velocities[k], reference.point[k], reference.velocity[k],
                                         position_weight) for k in range(len(positions))])


def traveling_efficiency(
    positions, velocities, reference: PathReference, position_weight: float, x_full: float, x_zero: float
) -> np.ndarray:
    """Eq. (12): Lambda_i (P,) = Lambda(e_i, x_c, x_M)."""
    return efficiency(tracking_error(positions, velocities, reference, position_weight), x_full, x_zero)


def consensus_step(estimates, adjacency, is_prime, prime_efficiency, gain: float, dt: float,
                   heard=None) -> np.ndarray:
    """Eq. (13) over one control period ``dt`` (s), saturated to [0, 1].

    estimates: (N,) current hat-Lambda_p^i; adjacency: (N, N) bool or weights
    (only W_ij > 0 matters: eq. 13 sums over neighbours); is_prime: (N,) bool;
    prime_efficiency: (N,) Lambda_i, read where is_prime. Non-prime robots move
    towards their neighbours' previous estimates at rate k_A = ``gain`` (1/s).
    heard: (N, N), heard[i, j] the estimate of robot j that reached robot i
    (over the bus); None: every robot has every neighbour's ``estimates[j]``.
    """
    estimates = np.asarray(estimates, dtype=float)
    updated = np.empty_like(estimates)
    heard = np.broadcast_to(estimates, (len(estimates),) * 2) if heard is None else np.asarray(heard, dtype=float)
    _consensus_kernel(estimates, np.ascontiguousarray(heard), np.asarray(adjacency, dtype=float),
                      np.asarray(is_prime, dtype=bool),
                      np.broadcast_to(np.asarray(prime_efficiency, dtype=float), estimates.shape), float(gain),
                      float(dt), updated)
    return updated


def adaptive_gain(alignment, efficiency_estimate, sigma: float) -> np.ndarray:
    """Eqs. (14)-(15): rho = (1 - Theta) hat-Lambda^sigma + Theta (1 - (1 - hat-Lambda)^sigma)."""
    if not sigma >= 1.0:
        raise ValueError(f"sigma must be >= 1 (eq. 14), got {sigma!r}")
    x, y = np.broadcast_arrays(np.asarray(alignment, dtype=float), np.asarray(efficiency_estimate, dtype=float))
    return np.reshape([_adaptive_gain_scalar(a, b, float(sigma)) for a, b in zip(x.ravel(), y.ravel())], x.shape)