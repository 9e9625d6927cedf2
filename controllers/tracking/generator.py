"""The EKF as the continuous-connectivity paper's target generator (Sec. 2.1: active localization).

Each explorer's next target z_i is a *viewpoint* for the currently most
uncertain target (largest lambda_max of its 3 x 3 covariance block) that no
other explorer is assigned: a free point in the sensors' plane, in line of
sight of the target's estimate and within the sensors' range, chosen among
``viewpoint_radii_m`` x ``viewpoint_bearings`` points around the estimate as
the one whose predicted lambda_max (estimation.viewpoints: prediction while
the explorer drives there in a straight line at v_cruise, then one reading per
step) is smallest after ``max_dwell_s``. The near ones read with sigma(l)
~ 0.01-0.03 m (eq. 12: the targets fly 0.8-1.5 m above the sensors), the far
ones see the target from a flatter angle, i.e. teach its horizontal position
rather than its height; the prediction weighs both. Its dwell time Delta t is
the time its readings need (``readings_needed``: until lambda_max < delta or
a reading stops helping).

Re-issuing (``update``, every tick; estimates change on reading ticks):
- an explorer without a target (start, or its visit just ended) gets one;
- its target's lambda_max fell below delta: an anchor's dwell ends (dwell time
  set to what it has spent: it becomes a connector on the next tick and gets
  a new target); a traveler is sent to a viewpoint of the next target;
- a traveler's target estimate moved more than ``reissue_distance_m`` since
  its viewpoint was chosen: a new viewpoint for the same target (replanned).
An anchor keeps its place: the readings from there are what it is for.

Without an informed prior (``space`` given), while some target is not yet fixed
an explorer is sent to *look* for it instead (``_search``): the free viewpoint,
reachable from it, that would see (in range, in line of sight) the most weight
of the search's hypotheses, summed over the targets not fixed and less what the
other explorers' looks will see, per second of travel plus
:data:`SEARCH_LOOK_HORIZON_S`; it dwells :data:`SEARCH_DWELL_S` there. A
traveler's look is re-chosen once the weight it would see has halved (looks on
the way saw it). Once every target is fixed, viewpoints are chosen as above.

The generator talks to the continuous-connectivity paper's exploration layer only through its
interfaces: ``TargetQueues.push`` (new targets) and
``ExplorationController.retarget`` (re-issued ones), reading the roles and
current targets it exposes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from controllers.connectivity.exploration import ExplorationController
from controllers.connectivity.paths import GridPlanner
from controllers.connectivity.roles import Role
from controllers.connectivity.targets import TargetQueues
from estimation.ekf import FilterState
from estimation.target_motion import TargetMotion
from estimation.target_search import SearchSpace, visible, visible_mass
from estimation.viewpoints import block_lambda_max, predicted_lambda_max, readings_needed
from sim.geometry import Boxes, segments_free


# Searching for targets not yet fixed (docs/intermittent.md, "Targets without an informed prior"):
SEARCH_VIEW_SPACING_M = 0.5  # candidate search viewpoints: a grid of this pitch over the free plane
SEARCH_DWELL_S = 2.0  # a look: one non-reading divides a hypothesis' weight by 20, a second by 400
# A viewpoint is scored by the weight it would see per (travel time + this), s: a horizon that keeps a
# near viewpoint with little weight from beating a far one with much (at 0.1 m/s, 30 s is 3 m; in the
# held-out room, seed 1, 2 s and 15 s did worse, 60 s as well; docs/intermittent.md).
SEARCH_LOOK_HORIZON_S = 30.0
# Hypotheses below this fraction of a target's heaviest are left out of the search's sums (a look
# ruled them out already)
SEARCH_LEAST_WEIGHT = 0.01
# A search viewpoint is re-chosen once the weight it would see has fallen below this fraction of what it
# had when chosen (others' looks on the way saw it)
SEARCH_REISSUE_FRACTION = 0.5

# {target not yet fixed: (hypotheses (N, 3) at the estimate's step, m, their weights (N,))}
Hypotheses = dict[int, tuple[np.ndarray, np.ndarray]]


@dataclass
class Assignment:
    """The target an explorer's current viewpoint serves (``search``: a look for the targets
    not yet fixed, ``target`` -1, ``mass`` the hypotheses' weight it would see)."""

    target: int  # index a of the tracked target
    estimate: np.ndarray  # (3,) its estimate when the viewpoint was chosen, m
    viewpoint: np.ndarray  # (3,) m
    dwell_s: float
    search: bool = False
    mass: float = 0.0


def spread_robots(starts: np.ndarray, count: int) -> np.ndarray:
    """``count`` robot indices in farthest-point order: first the robot farthest from
    the centroid, then each time the one farthest from those chosen (lowest index on ties)."""
    starts = np.asarray(starts, dtype=float)
    count = min(count, len(starts))
    chosen = [int(np.argmax(np.linalg.norm(starts - starts.mean(axis=0), axis=1)))]
    while len(chosen) < count:
        distance = np.linalg.norm(starts[:, None] - starts[chosen][None], axis=-1).min(axis=1)
        distance[chosen] = -1.0
        chosen.append(int(np.argmax(distance)))
    return np.array(sorted(chosen), dtype=int)


class EKFTargetGenerator:
    """Viewpoints from the network-wide EKF for the explorers (see the module docstring).

    params: ConnectedTrackingParams; planner: the controller's GridPlanner
    (planar); boxes: the obstacles of line of sight; plane_z: sensor height,
    m; motion: the targets' model (A, Q); explorers: robot indices;
    target_range: range sensors' limit, m; cruise_speed: m/s; step_s: one step of
    the task (the readings' period), s. space, hypotheses: without an informed prior, the
    beliefs' search space and the hypotheses of the targets not yet fixed at a step (None: the
    informed prior; explorers then never search).
    """

    def __init__(self, params, planner: GridPlanner, boxes: Boxes, plane_z: float, motion: TargetMotion,
                 explorers: np.ndarray, target_range: float, cruise_speed: float, step_s: float,
                 space: SearchSpace | None = None, hypotheses: Callable[[int], Hypotheses] | None = None) -> None:
        self.space = space
        self.hypotheses = hypotheses
        self._search_views: np.ndarray | None = None
        self.searches = 0  # search viewpoints issued
        self.params = params
        self.planner = planner
        self.boxes = boxes
        self.plane_z = plane_z
        self.motion = motion
        self.explorers = np.asarray(explorers, dtype=int)
        self.target_range = target_range
        self.cruise_speed = cruise_speed
        self.step_s = step_s
        self.horizon = max(1, int(math.ceil(params.max_dwell_s / step_s)))
        self.assigned: dict[int, Assignment | None] = {int(i): None for i in self.explorers}
        self.issued = 0  # viewpoints issued (new and re-issued)
        self.reissued = 0  # of which re-issued to a traveler
        self.ended = 0  # dwells ended early (lambda_max below delta)
        self.failed = 0  # searches that found no viewpoint for any target
        self._without_view: set[int] = set()
        self.history: list[tuple[int, int, int]] = []  # (step of the estimate, robot, target) per issue
        angles = 2 * np.pi * np.arange(params.viewpoint_bearings) / params.viewpoint_bearings
        rings = [r * np.stack([np.cos(angles), np.sin(angles)], axis=1) for r in params.viewpoint_radii_m]
        self._offsets = np.concatenate(rings)  # (K, 2) around the estimate, m

    # ------------------------------------------------------------ choosing
    def _block(self, matrix: np.ndarray, a: int) -> np.ndarray:
        return matrix[3 * a:3 * a + 3, 3 * a:3 * a + 3]

    def viewpoint(self, a: int, estimate: FilterState, position: np.ndarray) -> Assignment | None:
        """The best viewpoint for target ``a`` seen from an explorer at ``position`` (3,), or None."""
        target = estimate.mean[3 * a:3 * a + 3]
        points = np.empty((len(self._offsets), 3))
        points[:, :2] = target[:2] + self._offsets
        points[:, 2] = self.plane_z
        ok = self.planner.is_free(points, self.planner.clearance)
        ok &= np.linalg.norm(points - target, axis=1) < self.target_range
        if ok.any():
            candidates = np.flatnonzero(ok)
            ok[candidates] = segments_free(self.boxes, points[candidates],
                                           np.broadcast_to(target, (len(candidates), 3)), 0.0)
        for k in np.flatnonzero(ok):
            ok[k] = self.planner.connected(position, points[k])
        if not ok.any():
            return None
        candidates = np.flatnonzero(ok)
        distance = np.linalg.norm(points[candidates, :2] - position[:2], axis=1)
        travel = np.ceil(distance / (self.cruise_speed * self.step_s)).astype(int)
        series = predicted_lambda_max(self._block(estimate.covariance, a),
                                      self._block(self.motion.transition, a),
                                      self._block(self.motion.process_noise, a),
                                      target, points[candidates], travel, self.horizon)
        best = int(np.argmin(series[:, -1]))  # argmin: the first candidate on ties (deterministic)
        steps = readings_needed(series[best], self.params.delta_m2, self.params.dwell_stall)
        return Assignment(a, target.copy(), points[candidates[best]].copy(), steps * self.step_s)

    def search_views(self) -> np.ndarray:
        """(V, 3) candidate search viewpoints: a grid of :data:`SEARCH_VIEW_SPACING_M` over the
        planner's free plane at the sensors' height, m."""
        if self._search_views is None:
            low, high = self.planner.lower, self.planner.upper
            axes = [np.arange(low[a] + SEARCH_VIEW_SPACING_M / 2, high[a], SEARCH_VIEW_SPACING_M) for a in range(2)]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 2)
            points = np.column_stack([grid, np.full(len(grid), self.plane_z)])
            self._search_views = points[self.planner.is_free(points, self.planner.clearance)]
        return self._search_views

    def _unseen(self, robot: int, hypotheses: Hypotheses) -> Hypotheses:
        """The hypotheses' weights, those the other explorers' search viewpoints will see set to 0
        (their looks are under way), the negligible ones left out."""
        out: Hypotheses = {}
        others = [s.viewpoint for r, s in self.assigned.items() if s is not None and s.search and r != robot]
        for target, (positions, weights) in hypotheses.items():
            keep = weights > SEARCH_LEAST_WEIGHT * weights.max()
            positions, weights = positions[keep], weights[keep].copy()
            for viewpoint in others:
                weights[visible(self.space, viewpoint, positions)] = 0.0
            out[target] = (positions, weights)
        return out

    def _search(self, robot: int, step: int, position: np.ndarray) -> Assignment | None:
        """A look for the targets not yet fixed: the free, reachable viewpoint that would see the most
        hypothesis weight (summed over those targets, less what the other explorers' looks will see)
        per second of travel and look; None when every target is fixed or nothing is left to see."""
        if self.space is None or self.hypotheses is None:
            return None
        hypotheses = self.hypotheses(step)
        if not hypotheses:
            return None
        unseen = self._unseen(robot, hypotheses)
        views = self.search_views()
        mass = np.zeros(len(views))
        for positions, weights in unseen.values():
            mass += visible_mass(self.space, views, positions, weights)
        travel = np.linalg.norm(views[:, :2] - position[:2], axis=1) / self.cruise_speed
        score = mass / (travel + SEARCH_LOOK_HORIZON_S)
        for k in np.argsort(-score, kind="stable"):
            if mass[k] <= 0.0:
                return None
            if self.planner.connected(position, views[k]):
                self.searches += 1
                self.issued += 1
                self.history.append((step, robot, -1))
                return Assignment(-1, views[k].copy(), views[k].copy(), SEARCH_DWELL_S, search=True,
                                  mass=float(mass[k]))
        return None

    def _search_mass_left(self, served: Assignment, step: int) -> float:
        """The hypothesis weight the search viewpoint of ``served`` would still see."""
        hypotheses = self.hypotheses(step)
        return float(sum(visible_mass(self.space, served.viewpoint, p, w)[0] for p, w in hypotheses.values()))

    def _next(self, robot: int, estimate: FilterState, position: np.ndarray, exclude: set[int]) -> Assignment | None:
        """A look for the targets not yet fixed if any (:meth:`_search`), else a viewpoint for the most
        uncertain target not in ``exclude`` that has one."""
        search = self._search(robot, estimate.step, position)
        if search is not None:
            return search
        uncertainty = block_lambda_max(estimate.covariance, estimate.n_targets)
        for a in np.argsort(-uncertainty, kind="stable"):
            if int(a) in exclude:
                continue
            choice = self.viewpoint(int(a), estimate, position)
            if choice is not None:
                self.issued += 1
                self.history.append((estimate.step, robot, int(a)))
                return choice
        return None

    def _taken(self, robot: int) -> set[int]:
        return {s.target for r, s in self.assigned.items() if s is not None and not s.search and r != robot}

    # ------------------------------------------------------------ running
    def first_targets(self, n_robots: int, starts: np.ndarray, estimate: FilterState) -> TargetQueues:
        """Queues with one viewpoint per explorer (the rest connect), from the prior."""
        queues = TargetQueues(n_robots)
        for robot in self.explorers:
            choice = self._next(int(robot), estimate, starts[robot], self._taken(int(robot)))
            self.assigned[int(robot)] = choice
            if choice is None:
                self.failed += 1
            else:
                queues.push(int(robot), choice.viewpoint, choice.dwell_s)
        return queues

    def update(self, estimate: FilterState, positions: np.ndarray, controller: ExplorationController,
               queues: TargetQueues, readings_new: bool) -> None:
        """Issue and re-issue viewpoints (see the module docstring); ``readings_new``: the
        estimate changed since the last call (only then are targets re-examined)."""
        roles = controller.role_machine.roles
        pending = queues.pending()
        uncertainty = block_lambda_max(estimate.covariance, estimate.n_targets) if readings_new else None
        for robot in self.explorers:
            i = int(robot)
            current = controller.targets[i]
            if pending[i]:
                continue  # the controller extracts it on this tick
            if current is None:
                if i in self._without_view and not readings_new:
                    continue  # nothing found on this estimate; try again on the next one
                choice = self._next(i, estimate, positions[i], self._taken(i))
                self.assigned[i] = choice
                if choice is None:
                    self._without_view.add(i)
                    self.failed += 1
                else:
                    self._without_view.discard(i)
                    queues.push(i, choice.viewpoint, choice.dwell_s)
                continue
            served = self.assigned[i]
            if uncertainty is None or served is None:
                continue
            role = roles[i]
            if served.search:
                if role == Role.ANCHOR:
                    continue  # the look's short dwell ends by itself
                if self._search_mass_left(served, estimate.step) < SEARCH_REISSUE_FRACTION * served.mass:
                    choice = self._next(i, estimate, positions[i], self._taken(i))
                    if choice is not None:
                        self.assigned[i] = choice
                        controller.retarget(i, choice.viewpoint, choice.dwell_s, positions[i])
                        self.reissued += 1
                continue
            if uncertainty[served.target] < self.params.delta_m2:
                if role == Role.ANCHOR:
                    controller.retarget(i, current.position, 0.0)
                    self.ended += 1
                    continue
                exclude = self._taken(i) | {served.target}
                choice = self._next(i, estimate, positions[i], exclude)
                if choice is not None:
                    self.assigned[i] = choice
                    controller.retarget(i, choice.viewpoint, choice.dwell_s, positions[i])
                    self.reissued += 1
                continue
            moved = np.linalg.norm(estimate.mean[3 * served.target:3 * served.target + 3] - served.estimate)
            if role in (Role.PRIME_TRAVELER, Role.SECONDARY_TRAVELER) and moved > self.params.reissue_distance_m:
                choice = self.viewpoint(served.target, estimate, positions[i])
                if choice is not None:
                    self.issued += 1
                    self.reissued += 1
                    self.history.append((estimate.step, i, served.target))
                    self.assigned[i] = choice
                    controller.retarget(i, choice.viewpoint, choice.dwell_s, positions[i])

    def summary(self) -> dict:
        searched = {"search_viewpoints_issued": self.searches} if self.space is not None else {}
        return {"viewpoints_issued": self.issued, "viewpoints_reissued": self.reissued,
                "dwells_ended_early": self.ended, "viewpoint_failures": self.failed, **searched}
