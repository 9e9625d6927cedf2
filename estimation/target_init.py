"""A target's first estimate from its first range readings, for a run without an informed prior.

Khodayi-mehr et al. 2019 start the EKF from an informed prior (x^0 within about
a metre of each target, C(0) = 0.25 I). In a scene of the user's the targets'
whereabouts are unknown, and a range-only EKF started far off settles on points
that fit the ranges but are not the targets. Range-only SLAM's answer is
delayed initialisation: keep a target's readings aside until, together, they
pin it down, solve for its position by multilateration (weighted nonlinear
least squares over the readings from several sensor positions), and let the
EKF take over from that position and its covariance.

- :func:`multilaterate` - the weighted least-squares position of a static
  point from ranges, with the checks that refuse a fix the readings do not
  support: too few readings, sensors on one line, a covariance above the
  accepted variance, residuals that do not fit the noise, or a second
  solution that fits almost as well (the mirror image across the line the
  sensors nearly lie on).
- :func:`carried_sensors` - readings of a moving target taken at earlier
  steps, made readings of its current position: the target model moves a
  target rigidly (a rotation about a circle's centre, or a translation), so
  moving the sensor positions with it keeps every distance.
- :class:`ReadingsInitialiser` - both together, as
  :class:`estimation.beliefs.Belief` asks for a target's fix at a step.

Sensors all in one plane (ground robots; within :data:`PLANE_THICKNESS_M` of
it) cannot tell a point from its mirror image across that plane; the fix
takes the image on the plane's upper side
(normal with positive z: targets are above the floor robots), as
:func:`estimation.ekf.reflect_below` does for the EKF.

Pure numpy; no MuJoCo, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from estimation.range_model import range_sigma
from estimation.target_motion import TargetMotion
from estimation.target_search import SearchSpace

# A fix is accepted once no direction of its covariance exceeds this, m^2 (1 m standard
# deviation): the paper's informed x^0 is up to 2.1 m off its targets, so the EKF starts from
# readings at least as close as it starts in the paper, and says how close.
ACCEPTED_VARIANCE_M2 = 1.0
# The readings' mean squared normalised residual above which they do not describe one
# point under the noise model (expected: about 1).
MAX_RESIDUAL_RATIO = 4.0
# A second local solution whose weighted squared residual is within this of the best one
# (a 4 sigma difference) makes the fix ambiguous, and it is deferred.
AMBIGUITY_CHI2 = 16.0
# Two local solutions closer than this are one, m.
SAME_SOLUTION_M = 0.05
# The sensors' baseline (root-mean-square spread across their long axis) must be at least this
# share of the mean range: from a short baseline the ranges fit a curved valley of points and the
# linearised covariance of any one of them is far too small (the EKF would then settle there).
BASELINE_SHARE = 0.15
# Sensors whose root-mean-square distance from their best-fit line is below this are on one line, m.
LINE_THICKNESS_M = 1e-6
# Sensors within this root-mean-square distance of their best-fit plane count as one plane, m: robots'
# sensors ride a few millimetres up and down, and the mirror image across the plane still fits as well.
PLANE_THICKNESS_M = 0.05
GAUSS_NEWTON_ITERATIONS = 50
_MIN_RANGE_M = 1e-9


@dataclass(frozen=True)
class PositionFix:
    """A multilateration result: position (3,), m; covariance (3, 3), m^2; the
    weighted squared residual chi2 over ``n_readings`` readings."""

    position: np.ndarray
    covariance: np.ndarray
    chi2: float
    n_readings: int


def _solve_linear(sensors: np.ndarray, ranges: np.ndarray, weights: np.ndarray, basis: np.ndarray,
                  centroid: np.ndarray) -> np.ndarray | None:
    """Closed-form start: subtracting the mean of ||x - p_i||^2 = r_i^2 leaves equations linear
    in x's coordinates along ``basis`` (rows: directions the sensors span)."""
    local = (sensors - centroid) @ basis.T  # (N, d)
    squares = ranges**2 - np.sum((sensors - centroid) ** 2, axis=1)
    w = weights / weights.sum()
    rows = -2.0 * (local - w @ local)
    rhs = squares - w @ squares
    root = np.sqrt(weights)
    solution, _, rank, _ = np.linalg.lstsq(rows * root[:, None], rhs * root, rcond=None)
    if rank < basis.shape[0]:
        return None
    return solution


def _gauss_newton(sensors: np.ndarray, ranges: np.ndarray, weights: np.ndarray, start: np.ndarray,
                  normal: np.ndarray | None, plane_offset: float,
                  height_prior: tuple[float, float] | None) -> tuple[np.ndarray, float]:
    """Weighted Gauss-Newton (Levenberg-damped) from ``start``; with a sensor plane (``normal``),
    the point is kept on its upper side (the cost is symmetric across the plane). Returns the
    point and its cost (the readings' weighted squared residuals, the height prior's term included)."""
    x = start.astype(float).copy()
    z_information = np.zeros((3, 3))
    if height_prior is not None:
        z_information[2, 2] = 1.0 / height_prior[1]

    def cost(point: np.ndarray) -> float:
        residual = np.linalg.norm(point - sensors, axis=1) - ranges
        prior = 0.0 if height_prior is None else (point[2] - height_prior[0]) ** 2 / height_prior[1]
        return float(np.sum(weights * residual**2) + prior)

    current = cost(x)
    damping = 1e-3
    for _ in range(GAUSS_NEWTON_ITERATIONS):
        diff = x - sensors
        distance = np.maximum(np.linalg.norm(diff, axis=1), _MIN_RANGE_M)
        jacobian = diff / distance[:, None]
        residual = distance - ranges
        information = jacobian.T @ (weights[:, None] * jacobian) + z_information
        gradient = jacobian.T @ (weights * residual)
        if height_prior is not None:
            gradient[2] += (x[2] - height_prior[0]) / height_prior[1]
        improved = False
        while damping < 1e9:
            step = np.linalg.solve(information + damping * np.eye(3) * max(np.trace(information), 1e-12) / 3,
                                   -gradient)
            candidate = x + step
            if normal is not None:
                height = candidate @ normal - plane_offset
                if height < 0:
                    candidate = candidate - 2.0 * height * normal
            trial = cost(candidate)
            if trial <= current:
                x, improved = candidate, True
                damping = max(damping / 10, 1e-12)
                break
            damping *= 10
        if not improved or abs(current - trial) <= 1e-12 * max(current, 1e-12) or np.linalg.norm(step) < 1e-10:
            current = min(current, trial) if improved else current
            break
        current = trial
    return x, current


def multilaterate(sensors: np.ndarray, ranges: np.ndarray, sigmas: np.ndarray,
                  accepted_variance_m2: float = ACCEPTED_VARIANCE_M2,
                  height_prior: tuple[float, float] | None = None) -> PositionFix | None:
    """The position of a static point from range readings, or None when the readings do not fix it.

    sensors: (N, 3) sensor positions, m; ranges: (N,) measured distances, m;
    sigmas: (N,) their standard deviations, m. The fix minimises
    sum ((||x - p_i|| - r_i) / sigma_i)^2 by Gauss-Newton from the closed-form
    solution of the squared-range differences; its covariance is
    (J^T W J)^-1 at the solution, inflated by the residual ratio when that
    exceeds 1. Refused (None): fewer than 3 readings; sensors on one line (a
    circle of solutions about it) or a baseline across that line shorter than
    :data:`BASELINE_SHARE` of the mean range; a residual ratio above
    :data:`MAX_RESIDUAL_RATIO`; a covariance eigenvalue above
    ``accepted_variance_m2``; or a second solution within
    :data:`AMBIGUITY_CHI2` of the best. Sensors in one plane: the point on the
    plane's upper side (see the module's text).

    height_prior: optional (mean, variance) of the point's z (m, m^2), one more
    term of the least squares: sensors in one plane and nearly on one line
    leave the point free to turn about that line, trading height for offset,
    and what is known of the height (the scene's floor and ceiling) ties it.
    """
    sensors = np.asarray(sensors, dtype=float).reshape(-1, 3)
    ranges = np.asarray(ranges, dtype=float).reshape(-1)
    sigmas = np.asarray(sigmas, dtype=float).reshape(-1)
    n = len(ranges)
    if not (len(sensors) == n == len(sigmas)):
        raise ValueError(f"sensors/ranges/sigmas: lengths differ ({len(sensors)}, {n}, {len(sigmas)})")
    if np.any(sigmas <= 0) or not np.all(np.isfinite(sigmas)):
        raise ValueError("sigmas: must be finite and positive")
    if n < 3:
        return None
    weights = 1.0 / sigmas**2
    centroid = sensors.mean(axis=0)
    _, spread, directions = np.linalg.svd(sensors - centroid, full_matrices=True)
    rms = np.concatenate([spread, np.zeros(3 - len(spread))]) / np.sqrt(n)
    if rms[1] <= LINE_THICKNESS_M:
        return None  # collinear (or one point): the point may turn about the line
    if rms[1] < BASELINE_SHARE * float(ranges.mean()):
        return None
    planar = rms[2] <= PLANE_THICKNESS_M
    normal = None
    plane_offset = 0.0
    if planar:
        normal = directions[2] * (1.0 if directions[2][2] >= 0 else -1.0)
        if abs(normal[2]) < 1e-9:
            normal = directions[2] * (1.0 if tuple(directions[2]) > (0.0, 0.0, 0.0) else -1.0)
        plane_offset = float(centroid @ normal)
        flat = sensors - np.outer((sensors - centroid) @ normal, normal)
        in_plane = _solve_linear(flat, ranges, weights, directions[:2], centroid)
        if in_plane is None:
            return None
        foot = centroid + in_plane @ directions[:2]
        height_sq = float(np.average(ranges**2 - np.sum((sensors - foot) ** 2, axis=1), weights=weights))
        start = foot + np.sqrt(max(height_sq, 0.0)) * normal
    else:
        solution = _solve_linear(sensors, ranges, weights, directions, centroid)
        if solution is None:
            return None
        start = centroid + solution @ directions
    # A second solution fits almost as well when the sensors nearly lie on a line (in-plane: the
    # image across their long axis) or, not in one plane, nearly in one (the image across it): try it.
    side = directions[1] if planar else directions[2]
    mirrored = start - 2.0 * ((start - centroid) @ side) * side
    solutions = [_gauss_newton(sensors, ranges, weights, s, normal, plane_offset, height_prior)
                 for s in (start, mirrored)]
    best_index = int(np.argmin([c for _, c in solutions]))
    best, chi2 = solutions[best_index]
    other, other_chi2 = solutions[1 - best_index]
    if np.linalg.norm(other - best) > SAME_SOLUTION_M and other_chi2 - chi2 < AMBIGUITY_CHI2:
        return None
    ratio = chi2 / max(n - 3, 1)
    if ratio > MAX_RESIDUAL_RATIO:
        return None
    diff = best - sensors
    jacobian = diff / np.maximum(np.linalg.norm(diff, axis=1), _MIN_RANGE_M)[:, None]
    information = jacobian.T @ (weights[:, None] * jacobian)
    if height_prior is not None:
        information[2, 2] += 1.0 / height_prior[1]
    eigenvalues = np.linalg.eigvalsh(information)
    if eigenvalues[0] <= 1.0 / accepted_variance_m2:
        return None
    covariance = np.linalg.inv(information) * max(1.0, ratio)
    covariance = 0.5 * (covariance + covariance.T)
    if np.linalg.eigvalsh(covariance)[-1] > accepted_variance_m2:
        return None
    return PositionFix(best, covariance, float(chi2), n)


def carried_sensors(motion: TargetMotion, target: int, sensors: np.ndarray, steps: np.ndarray,
                    to_step: int) -> np.ndarray:
    """(N, 3) sensor positions of readings of ``target`` taken at ``steps`` (N,), moved by the
    target's noise-free model from each reading's step to ``to_step``: the distance from a moved
    sensor to the target at ``to_step`` is the reading's (the model moves a target rigidly)."""
    sensors = np.asarray(sensors, dtype=float).reshape(-1, 3)
    steps = np.asarray(steps, dtype=int).reshape(-1)
    if len(steps) != len(sensors):
        raise ValueError(f"steps: {len(steps)} for {len(sensors)} sensors")
    if len(steps) and steps.max() > to_step:
        raise ValueError(f"steps: a reading of step {steps.max()} is after step {to_step}")
    block = slice(3 * target, 3 * target + 3)
    rotation = motion.transition[block, block]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-9):
        raise ValueError(f"target {target}: its motion is not rigid, readings cannot be carried")
    out = sensors.copy()
    if not len(steps):
        return out
    first = int(steps.min())
    # Affine map from step s to to_step, built backwards: M_s = M_{s+1} A, c_s = M_{s+1} b_s + c_{s+1}.
    maps: dict[int, tuple[np.ndarray, np.ndarray]] = {to_step: (np.eye(3), np.zeros(3))}
    matrix, offset = np.eye(3), np.zeros(3)
    for s in range(to_step - 1, first - 1, -1):
        offset = matrix @ motion.input(s)[block] + offset
        matrix = matrix @ rotation
        maps[s] = (matrix, offset)
    for i, s in enumerate(steps):
        matrix, offset = maps[int(s)]
        out[i] = matrix @ sensors[i] + offset
    return out


@dataclass(frozen=True)
class ReadingsInitialiser:
    """Fixes a target from its readings of the last ``window_steps`` steps (see the module's text).

    A reading taken k - s steps before the fix counts with variance
    sigma(l)^2 + (k - s) q, q the target model's process noise per step and axis.
    height_range: optional (low, high) z of the targets, m (the scene's floor and
    ceiling): a uniform height prior, mean (low + high) / 2, variance (high - low)^2 / 12.
    search: optional hypotheses over the scene's free space
    (:mod:`estimation.target_search`): a belief then weighs them by every reading and
    non-reading of a target not yet fixed, reports their moments as its estimate,
    and fixes the target from them once they collapse (when multilateration cannot yet).
    """

    window_steps: int = 60
    accepted_variance_m2: float = ACCEPTED_VARIANCE_M2
    height_range: tuple[float, float] | None = None
    search: SearchSpace | None = None

    def __post_init__(self) -> None:
        if self.window_steps < 1:
            raise ValueError(f"window_steps: must be >= 1, got {self.window_steps}")
        if not self.accepted_variance_m2 > 0:
            raise ValueError(f"accepted_variance_m2: must be positive, got {self.accepted_variance_m2}")
        if self.height_range is not None and not self.height_range[1] > self.height_range[0]:
            raise ValueError(f"height_range: need low < high, got {self.height_range}")

    def fix(self, motion: TargetMotion, target: int, step: int, steps: Sequence[int], sensors: np.ndarray,
            ranges: np.ndarray) -> PositionFix | None:
        """The fix of ``target`` at ``step`` from its readings (their ``steps``, ``sensors``, ``ranges``), or None."""
        steps = np.asarray(steps, dtype=int).reshape(-1)
        ranges = np.asarray(ranges, dtype=float).reshape(-1)
        carried = carried_sensors(motion, target, sensors, steps, step)
        q = float(motion.process_noise[3 * target, 3 * target])
        sigmas = np.sqrt(range_sigma(ranges) ** 2 + (step - steps) * q)
        height = None
        if self.height_range is not None:
            low, high = self.height_range
            height = (0.5 * (low + high), (high - low) ** 2 / 12.0)
        return multilaterate(carried, ranges, sigmas, self.accepted_variance_m2, height)
