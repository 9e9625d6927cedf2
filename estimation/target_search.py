"""Where a target not yet fixed can be: a set of hypotheses weighed by every reading and non-reading.

Range-only SLAM and active search keep, for a landmark not yet initialised,
a discrete set of position hypotheses (a grid or a particle set over the free
space) and weigh each by the sensing history. Range sensing has a maximum
range and needs line of sight, so it informs twice:

- a reading r of target a from sensor p multiplies each hypothesis x by the
  Gaussian likelihood of r given ||x - p|| (:func:`reading_log_likelihood`);
- a robot whose readings of a step hold none of target a says that a is not
  within range and in sight of its sensor: hypotheses there are multiplied by
  the probability of such a miss (:func:`miss_log_likelihood`).

The weights are a product of per-reading factors, so their order does not
matter (records may arrive late). Targets move; the hypotheses are positions
at the belief's first step, carried to step k by the known model
(:class:`HypothesisMotion`: the model moves a target rigidly, x(k) = M_k x(0) + c_k),
and a reading at step k counts with the variance the process noise adds by then.

Once the weighted set is unimodal and tight, its moments are a Gaussian the EKF
can take over from (:func:`collapse`): no direction of the covariance, the
grid's own cell spread included, above the accepted variance. A set spread
over two places has a large covariance along the line between them, so the
test also refuses a set with two modes.

Pure numpy; line of sight is a callable the caller supplies (the scene's
obstacles live above this package). No MuJoCo, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from estimation.range_model import range_sigma
from estimation.target_motion import TargetMotion

# The probability that a target in range and in sight gives no reading: the simulated sensors
# never miss, but a small value keeps one wrong non-reading (a target just at the range's edge
# after the model's drift) from wiping a hypothesis out.
MISS_PROBABILITY = 0.05
# Hypotheses whose log-weight is this far below the best one are left out of the line-of-sight
# tests of non-readings (their weight is already below e^-30 of the best).
NEGLIGIBLE_LOG_WEIGHT = 30.0
# A set collapses once no direction of its covariance exceeds this, m^2 (as target_init's fixes).
COLLAPSE_VARIANCE_M2 = 1.0

LineOfSight = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (K, 3), (K, 3) -> (K,) bool: clear


@dataclass(frozen=True, eq=False)  # arrays: compared by identity
class SearchSpace:
    """The hypotheses of a target's position at the belief's first step and how sensing is modelled.

    points: (N, 3) m, a grid over the scene's free space; spacing: (3,) m, the
    grid's cell size per axis (its own spread, spacing^2 / 12 per axis, is added
    to every covariance; half a cell diagonal widens every reading's noise);
    sensing_range_m: the sensors' maximum range; line_of_sight: clear
    segments, None: nothing ever blocks; miss_probability: see
    :data:`MISS_PROBABILITY`; bounds: (2, 3) the scene's box (low, high), m, which the
    targets never leave, so a hypothesis the model carries out of it is as unlikely as one a
    look missed (None: unbounded).
    """

    points: np.ndarray
    spacing: np.ndarray
    sensing_range_m: float
    line_of_sight: LineOfSight | None = None
    miss_probability: float = MISS_PROBABILITY
    bounds: np.ndarray | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0 or not np.all(np.isfinite(points)):
            raise ValueError("points: need a finite (N, 3) array with N >= 1")
        spacing = np.broadcast_to(np.asarray(self.spacing, dtype=float), (3,)).copy()
        if np.any(spacing < 0) or not np.all(np.isfinite(spacing)):
            raise ValueError(f"spacing: must be finite and >= 0, got {spacing}")
        if not self.sensing_range_m > 0:
            raise ValueError(f"sensing_range_m: must be positive, got {self.sensing_range_m}")
        if not 0 < self.miss_probability < 1:
            raise ValueError(f"miss_probability: must be in (0, 1), got {self.miss_probability}")
        if self.bounds is not None:
            bounds = np.asarray(self.bounds, dtype=float)
            if bounds.shape != (2, 3) or not np.all(bounds[1] >= bounds[0]):
                raise ValueError(f"bounds: need (2, 3) low <= high, got {self.bounds}")
            bounds.setflags(write=False)
            object.__setattr__(self, "bounds", bounds)
        points.setflags(write=False)
        spacing.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "spacing", spacing)

    @property
    def n_hypotheses(self) -> int:
        return len(self.points)

    @property
    def cell_covariance(self) -> np.ndarray:
        """(3, 3) m^2: the spread of a uniform grid cell."""
        return np.diag(self.spacing**2 / 12.0)

    @property
    def cell_radius_m(self) -> float:
        """Half a cell's diagonal, m: how far a grid point is from any point of its cell."""
        return float(np.linalg.norm(self.spacing) / 2.0)


def grid_points(low: np.ndarray, high: np.ndarray, spacing: np.ndarray,
                free: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """(N, 3) cell centres of a grid over the box [low, high] with cells of ``spacing`` (3,), m
    (at least one cell per axis), keeping those ``free`` (a (K, 3) -> (K,) bool test) says are free."""
    low, high, spacing = (np.asarray(v, dtype=float).reshape(3) for v in (low, high, spacing))
    if not np.all(high > low) or not np.all(spacing > 0):
        raise ValueError(f"grid: need low < high and spacing > 0, got {low}, {high}, {spacing}")
    axes = []
    for a in range(3):
        count = max(1, int(np.floor((high[a] - low[a]) / spacing[a] + 1e-9)))
        step = (high[a] - low[a]) / count
        axes.append(low[a] + step * (np.arange(count) + 0.5))
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if free is not None:
        points = points[np.asarray(free(points), dtype=bool)]
    return points


class HypothesisMotion:
    """The affine map x(k) = M_k x(origin) + c_k of each target's noise-free model, memoised.

    The target model moves a target rigidly (a rotation about a circle's centre
    or a translation, :class:`estimation.target_motion.TargetMotion`), the same
    map for every hypothesis of one target.
    """

    def __init__(self, motion: TargetMotion, origin: int = 0):
        self.motion = motion
        self.origin = int(origin)
        self._maps: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}

    def map(self, target: int, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(M_k (3, 3), c_k (3,)) of ``target`` from the origin step to ``step``."""
        if step < self.origin:
            raise ValueError(f"step: {step} is before the hypotheses' step {self.origin}")
        maps = self._maps.setdefault(target, [(np.eye(3), np.zeros(3))])
        block = slice(3 * target, 3 * target + 3)
        rotation = self.motion.transition[block, block]
        while len(maps) <= step - self.origin:
            matrix, offset = maps[-1]
            k = self.origin + len(maps) - 1
            maps.append((rotation @ matrix, rotation @ offset + self.motion.input(k)[block]))
        return maps[step - self.origin]

    def positions(self, points: np.ndarray, target: int, step: int) -> np.ndarray:
        """(N, 3) the hypotheses ``points`` (at the origin step) carried to ``step``."""
        matrix, offset = self.map(target, step)
        return points @ matrix.T + offset


def reading_log_likelihood(positions: np.ndarray, sensor: np.ndarray, measured: float,
                           extra_variance: float = 0.0) -> np.ndarray:
    """(N,) log-likelihood, up to a constant, of a reading ``measured`` from ``sensor`` (3,) for a
    target at each of ``positions`` (N, 3): Gaussian in the range with variance sigma(l)^2 (eq. 12,
    at the measured range) plus ``extra_variance`` (the model's drift, the grid's cell), m^2."""
    distance = np.linalg.norm(positions - np.asarray(sensor, dtype=float), axis=1)
    variance = float(range_sigma(np.array(measured))) ** 2 + float(extra_variance)
    return -0.5 * (distance - float(measured)) ** 2 / variance


def miss_log_likelihood(positions: np.ndarray, sensor: np.ndarray, sensing_range_m: float,
                        miss_probability: float, margin_m: float = 0.0,
                        line_of_sight: LineOfSight | None = None,
                        consider: np.ndarray | None = None) -> np.ndarray:
    """(N,) log-likelihood of no reading from ``sensor`` (3,) for a target at each of ``positions``:
    log(miss_probability) where the target would be seen (closer than sensing_range_m - margin_m, in
    sight), 0 elsewhere. ``consider`` (N,) bool limits the line-of-sight tests to those hypotheses
    (the others get 0: they carry no weight worth testing)."""
    sensor = np.asarray(sensor, dtype=float)
    out = np.zeros(len(positions))
    distance = np.linalg.norm(positions - sensor, axis=1)
    seen = distance < sensing_range_m - margin_m
    if consider is not None:
        seen &= np.asarray(consider, dtype=bool)
    index = np.flatnonzero(seen)
    if len(index) and line_of_sight is not None:
        clear = np.asarray(line_of_sight(np.broadcast_to(sensor, (len(index), 3)), positions[index]), dtype=bool)
        index = index[clear]
    out[index] = np.log(miss_probability)
    return out


def outside_log_likelihood(positions: np.ndarray, bounds: np.ndarray, miss_probability: float,
                           margin_m: float = 0.0) -> np.ndarray:
    """(N,) log(miss_probability) for the ``positions`` (N, 3) farther than ``margin_m`` outside the box
    ``bounds`` (2, 3) (low, high) on some axis, 0 for the others."""
    positions = np.asarray(positions, dtype=float)
    low, high = np.asarray(bounds, dtype=float)
    outside = np.any((positions < low - margin_m) | (positions > high + margin_m), axis=1)
    return np.where(outside, np.log(miss_probability), 0.0)


def normalised(log_weights: np.ndarray) -> np.ndarray:
    """(N,) weights summing to 1 from log-weights."""
    log_weights = np.asarray(log_weights, dtype=float)
    w = np.exp(log_weights - log_weights.max())
    return w / w.sum()


def moments(positions: np.ndarray, log_weights: np.ndarray, cell_covariance: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (3,) and covariance (3, 3) of the hypotheses, the cell's spread added."""
    w = normalised(log_weights)
    mean = w @ positions
    centred = positions - mean
    covariance = (centred * w[:, None]).T @ centred
    if cell_covariance is not None:
        covariance = covariance + cell_covariance
    return mean, 0.5 * (covariance + covariance.T)


def collapse(positions: np.ndarray, log_weights: np.ndarray, cell_covariance: np.ndarray | None = None,
             accepted_variance_m2: float = COLLAPSE_VARIANCE_M2) -> tuple[np.ndarray, np.ndarray] | None:
    """The Gaussian (mean, covariance) of the hypothesis set once no direction of its covariance
    exceeds ``accepted_variance_m2`` (a tight, one-mode set), else None."""
    mean, covariance = moments(positions, log_weights, cell_covariance)
    if np.linalg.eigvalsh(covariance)[-1] > accepted_variance_m2:
        return None
    return mean, covariance


@dataclass
class StepLooks:
    """What one robot's readings of one step say about the targets: its sensor (3,), m, and
    {target: measured range, m} of the targets it read (every other one it did not see)."""

    sensor: np.ndarray
    ranges: dict[int, float] = field(default_factory=dict)


def update_log_weights(space: SearchSpace, positions: np.ndarray, log_weights: np.ndarray, target: int,
                       looks: list[StepLooks], drift_variance: float) -> np.ndarray:
    """``log_weights`` (N,) of ``target``'s hypotheses (at ``positions`` (N, 3), this step) after one
    step's looks: a reading's likelihood where a robot read the target, a miss where it did not, and
    (with the space's bounds) a miss where the model carried the hypothesis out of the scene.
    drift_variance: the model's process noise accumulated since the hypotheses' step, m^2 per axis."""
    out = np.array(log_weights, dtype=float)
    cell = space.cell_radius_m
    drift = float(np.sqrt(max(drift_variance, 0.0)))
    if space.bounds is not None and looks:
        out += outside_log_likelihood(positions, space.bounds, space.miss_probability, cell + 2.0 * drift)
    for look in looks:
        measured = look.ranges.get(target)
        if measured is not None:
            out += reading_log_likelihood(positions, look.sensor, measured, cell**2 + drift_variance)
        else:
            consider = out > out.max() - NEGLIGIBLE_LOG_WEIGHT
            # A hypothesis within a cell (and the drift) of the range's edge may be just out of it.
            out += miss_log_likelihood(positions, look.sensor, space.sensing_range_m, space.miss_probability,
                                       margin_m=cell + 2.0 * drift, line_of_sight=space.line_of_sight,
                                       consider=consider)
    return out - out.max()


def visible(space: SearchSpace, viewpoint: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(N,) bool: the hypotheses at ``positions`` (N, 3) that a sensor at ``viewpoint`` (3,) would
    see: closer than the sensing range less a cell (the margin a non-reading leaves untouched,
    :func:`update_log_weights`) and in line of sight."""
    viewpoint = np.asarray(viewpoint, dtype=float).reshape(3)
    positions = np.asarray(positions, dtype=float)
    seen = np.linalg.norm(positions - viewpoint, axis=1) < space.sensing_range_m - space.cell_radius_m
    near = np.flatnonzero(seen)
    if len(near) and space.line_of_sight is not None:
        clear = np.asarray(space.line_of_sight(np.broadcast_to(viewpoint, (len(near), 3)), positions[near]),
                           dtype=bool)
        seen[near[~clear]] = False
    return seen


def visible_mass(space: SearchSpace, viewpoints: np.ndarray, positions: np.ndarray,
                 weights: np.ndarray) -> np.ndarray:
    """(V,) the summed ``weights`` (N,) of the hypotheses at ``positions`` (N, 3) that a sensor at
    each of ``viewpoints`` (V, 3) would see (:func:`visible`)."""
    viewpoints = np.atleast_2d(np.asarray(viewpoints, dtype=float))
    weights = np.asarray(weights, dtype=float)
    return np.array([weights[visible(space, v, positions)].sum() for v in viewpoints])
