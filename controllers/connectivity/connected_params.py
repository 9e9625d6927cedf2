"""Parameters of the ``connected`` strategy: the continuous-connectivity method (Nestmeyer et al. 2017).

One frozen dataclass, :class:`ConnectedParams`, is both the scenario's
``[strategy]`` table (built through :func:`sim.config.build`: unknown keys are
errors, every problem names its key) and what the library modules read
(graph.py, potential.py, dynamics.py, exploration.py, paths.py, mission.py):
a key's name is the name the code uses. Units are in the names (``_m``, ``_s``,
``_mps``, ``_n``, ``_j``, ``_kg``, ``_nspm`` = N s/m); the field metadata
carries unit and bounds (the tuning page's sliders; ``build`` and
``__post_init__`` enforce them).

Presets. :data:`PRESETS` holds the method's tables in one place: Table 2's
office and outdoor columns, and ``ground`` (this controller on the
intermittent method's e-puck ground robots). ``preset`` fills every key the
scenario leaves out; a key given explicitly wins. A value shared by every
preset is the field's default. The path planner's clearances default to the
link weights' obstacle clearances (R'_o preferred, R_o in narrow passages).
Fields are plain numbers after construction, so ``sim.config.to_table``
writes a complete table (changing ``preset`` later changes only the fields
still unset: none once a table has been written back); the ground preset's
values that scale with R_s stay unset (None) until :meth:`ConnectedParams.at_range`.

R_s. The method takes the sensing and the communication graph as one (Sec. 2):
R_s is the scenario's ``sensing.comm_range_m``, the range of the simulator's
communication graph that carries the election and consensus messages, not a
key of its own. :meth:`ConnectedParams.at_range` gives the parameters a run
uses: R_s set, the ground preset's R_s-scaled values filled, and the sensor
model's checks made (they relate R_s, R'_s, R_c and R'_c).

Table 2 lost its column alignment in the available text; its rows are read in
the order of Table 3: (R'_s, R_s), (R_o, R'_o), (R_c, R'_c), (lambda2_min,
lambda2_null), R_grid, sigma, v_cruise, (x_c, x_M), Delta t, R_z. Table 3 (the
six-quadrotor experiment) is the scenario ``connected-lab``.

Deviations from the paper (the values marked "ours" in :data:`PRESETS`)
-----------------------------------------------------------------------
- The paper does not report M, B, the potential gain, k_p, k_v, R_gamma, k_z
  or the estimator gains. M = 1 kg and B = 2 N s/m (velocity time constant
  0.5 s); k_lambda = 5 J holds a six-robot office chain dragged by a 3 N pull
  at lambda2 ~ 0.17, where the default estimator tracks lambda2 to a few
  percent, and scales with the cruise speed outdoors (a prime traveler pulls
  with up to k_v v_cruise), so the barrier holds a pulled link about as far
  from R_s outdoors as indoors. k_v = 10 1/s with k_p = k_v^2 / 4 (critically
  damped lateral error), high enough that f_B = -B v costs only
  B / (k_v + B) ~ 17 % of cruise speed on straight legs. R_gamma is a few
  grid cells; k_z makes the anchor pull comparable to the travel force.
- M and B are isotropic scalars shared by all robots (the paper allows 3x3
  positive-definite matrices per robot).
- alpha_A = 0: Sec. 4.2 reads Lambda_p = 1 as "at least 80 % of cruise speed"
  and Lambda_p = 0 as "less than 30 %", i.e. the tracking error (11) is the
  velocity error alone.
- ``lambda2_guard``: in continuous time the potential's slope is unbounded at
  lambda2_min; a sampled-data controller (or an estimator transient) can hand
  it lambda2 <= lambda2_min, where the slope is then held at its value at
  lambda2_min + lambda2_guard so the force stays finite and points the right way.
- ``braking_distance_m``: the path reference slows linearly to rest over the
  last metres so travelers arrive instead of overshooting at cruise speed
  (Table 1 calls v_cruise the *maximum* cruise speed).
- ``travel_force_limit_n``: eq. (3) grows without bound with the distance to
  the path, while Problem 1 asks for a bounded f_i: capped at twice
  k_v v_cruise. ``anchor_force_limit_n``: eq. (7) is unbounded at
  ||q - z|| = R_z and a sampled-data controller can step past R_z: capped at
  twice the travel cap, so an anchor is not dragged out of R_z by a prime
  traveler's pull (its dwell clock would restart and the team could deadlock).
- ``path_clearance_m`` / ``path_min_clearance_m`` / ``smoothing_tolerance_m``:
  the paper's grid search + smoothing "is not guaranteed to leave enough
  clearance" and relies on f_lambda; we plan with a margin instead (paths.py).
- ``message_latency_ticks``: flooding messages hop one graph edge per this
  many control ticks; the paper counts "steps" without a duration.
- Random targets (where they lie, how far from obstacles): not in the paper.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import ClassVar, Literal

from sim.config import check_params, param, require

Vec3 = tuple[float, float, float]

# Marks a field the preset fills (a NaN a scenario cannot write: bounds refuse it).
PRESET = math.nan

# The method's presets, key -> value; a key missing here takes the field's default.
PRESETS: dict[str, dict[str, float]] = {
    # Table 2, indoor office-like environment (about 10 m x 15 m).
    "office": dict(
        full_weight_range_m=1.1,  # R'_s (R_s = 2.5 m: the scenario's comm range)
        min_obstacle_clearance_m=0.25,  # R_o
        full_weight_obstacle_clearance_m=0.6,  # R'_o
        min_robot_distance_m=0.8,  # R_c
        full_weight_robot_distance_m=1.1,  # R'_c
        grid_resolution_m=0.25,  # R_grid
        cruise_speed_mps=1.0,  # v_cruise
        target_radius_m=1.0,  # R_z
        # ours
        potential_gain_j=5.0,
        braking_distance_m=2.0,
        replan_distance_m=1.0,
        anchor_gain_n=1.0,
        travel_force_limit_n=20.0,
        anchor_force_limit_n=40.0,
        smoothing_tolerance_m=0.15,
        target_clearance_m=0.6,
        target_height_min_m=0.6,
        target_height_max_m=4.4,
    ),
    # Table 2, outdoor scenes (empty space and town, 50 m x 70 m).
    "outdoor": dict(
        full_weight_range_m=2.5,  # R'_s (R_s = 6 m)
        min_obstacle_clearance_m=0.75,  # R_o
        full_weight_obstacle_clearance_m=1.75,  # R'_o
        min_robot_distance_m=1.0,  # R_c
        full_weight_robot_distance_m=2.5,  # R'_c
        grid_resolution_m=0.75,  # R_grid
        cruise_speed_mps=3.0,  # v_cruise
        target_radius_m=1.8,  # R_z
        # ours
        potential_gain_j=15.0,
        braking_distance_m=6.0,
        replan_distance_m=3.0,
        anchor_gain_n=3.0,
        travel_force_limit_n=60.0,
        anchor_force_limit_n=120.0,
        smoothing_tolerance_m=0.4,
        target_clearance_m=1.75,
        target_height_min_m=2.0,
        target_height_max_m=12.0,
    ),
    # Not in the paper: the intermittent method's e-puck-sized ground robots (body radius 0.036 m,
    # wheel limit 0.154 m/s), virtual points in the plane of the range sensors. Body-scale ranges are
    # fixed; forces scale with the cruise speed (0.1 m/s against the office's 1 m/s). docs/paradigms.md
    # gives the why of every value; GROUND_PER_RANGE the values that scale with R_s.
    "ground": dict(
        min_robot_distance_m=0.08,  # R_c: two bodies touch at 0.072 m, plus ~1 cm
        full_weight_robot_distance_m=0.10,  # R'_c
        min_obstacle_clearance_m=0.05,  # R_o: body radius 0.036 m plus ~1.4 cm
        full_weight_obstacle_clearance_m=0.08,  # R'_o: the intermittent method's clearance_m
        cruise_speed_mps=0.1,  # the intermittent method's |u| <= 0.1 m per 1 s step
        braking_distance_m=0.2,  # office 2 m at 1 m/s: the same braking time at 0.1 m/s
        target_radius_m=0.1,  # R_z
        anchor_gain_n=0.1,  # office 1 N x 0.1 (speed ratio)
        anchor_force_limit_n=4.0,  # 4 k_v v_cruise, as the office's 40 N
        travel_force_limit_n=2.0,  # 2 k_v v_cruise, as the office's 20 N
        grid_resolution_m=0.1,
        smoothing_tolerance_m=0.02,
        target_clearance_m=0.1,
        target_height_min_m=0.0,
        target_height_max_m=0.5,
    ),
}
# The ground preset's values per metre of R_s (office ratios: R'_s 1.1 / 2.5, R_gamma 1.0 / 2.5;
# k_lambda: the office's 5 J at R_s = 2.5 m and 1 m/s, times 0.1 (speed) x R_s / 2.5 (length)).
GROUND_PER_RANGE: dict[str, float] = dict(full_weight_range_m=0.44, replan_distance_m=0.4, potential_gain_j=0.2)

MAX_TARGETS_PER_ROBOT = 1000  # random targets per robot (drawing them costs time before the run starts)


@dataclass(frozen=True)
class FiedlerEstimatorParams:
    """Gains of the decentralised lambda2 / Fiedler-vector estimator (Yang et al. 2010).

    Not keys of their own: :attr:`ConnectedParams.estimator` scales these by
    ``estimator_speedup``.

    Power iteration per robot i (x_i: its component of the eigenvector estimate):
        x_i' = -k1 y1_i - k2 sum_j W_ij (x_i - x_j) - k3 (y2_i - 1) x_i
    with y1_i, y2_i PI average-consensus estimates of Ave(x) and Ave(x^2)
    (Freeman et al. 2006):
        y_i' = gamma (a_i - y_i) - K_P sum_j W_ij (y_i - y_j) + K_I sum_j W_ij (z_i - z_j)
        z_i' = -K_I sum_j W_ij (y_i - y_j)
    and lambda2_i = (k3 / k2) (1 - y2_i).

    Equilibrium x = +-v2 needs k1 > k2 lambda2 (the constant mode is deflated)
    and k3 > k2 lambda2 (the amplitude stays positive). With k1 < k3, as here,
    a lambda2 above ``lambda2_ceiling`` = k1 / k2 makes x drift to the
    constant vector and the estimate saturate at the ceiling, from which it
    recovers as soon as lambda2 drops (rather than x collapsing to 0, which
    it would do first if k3 < k1). Keep the ceiling above lambda2_null, and
    gamma > k1: the saturated state is stable only if y1 follows Ave(x)
    faster than the deflation acts (otherwise x oscillates along 1).

    ``dither`` (not in Yang et al.) keeps x from collapsing exactly onto a
    symmetric state: on a dense graph above the ceiling every component but
    the constant one decays towards round-off, and without noise a robot team
    on a symmetric graph could never leave the constant vector again.

    Time scales (defaults, ours): the consensus must be faster than the power
    iteration, K_P lambda2 >> gamma >~ k1; for graphs with lambda2 ~ 0.05-0.5
    the defaults converge in about 1-3 s (10-robot graphs). The substep
    shrinks as 1 / (k2 lambda_max(L) + k1 + k3) (the consensus loops are
    integrated exactly, estimator.py): the cost grows with the power-iteration gains.
    """

    mean_removal_gain: float = param(15.0, unit="1/s", above=0.0)  # k1: drives Ave(x) -> 0 (deflates 1)
    laplacian_gain: float = param(10.0, unit="1/s", above=0.0)  # k2, per unit weight: the step -k2 L x
    normalisation_gain: float = param(40.0, unit="1/s", above=0.0)  # k3: Ave(x^2) -> 1 - k2 lambda2 / k3
    consensus_input_gain: float = param(20.0, unit="1/s", above=0.0)  # gamma: pull of y_i towards a_i
    consensus_proportional_gain: float = param(400.0, unit="1/s", above=0.0)  # K_P, per unit weight
    consensus_integral_gain: float = param(400.0, unit="1/s", above=0.0)  # K_I, per unit weight
    max_substep: float = param(1e-3, unit="s", above=0.0)  # longest substep (accuracy of the Euler power iteration)
    dither: float = param(1e-4, unit="1/sqrt(s)", min=0.0)  # white noise each robot adds to x_i (0: none)

    def __post_init__(self) -> None:
        check_params(self)

    @property
    def lambda2_ceiling(self) -> float:
        """Largest lambda2 (weight units) the estimator can converge to."""
        return min(self.mean_removal_gain, self.normalisation_gain) / self.laplacian_gain


@dataclass(frozen=True)
class ConnectedParams:
    # -- general (group headers "# -- NAME, ..." group the fields on the tuning page)

    # Which of the method's presets fills every key left out: "office" (Table 2, indoor),
    # "outdoor" (Table 2, empty space and town) or "ground" (the intermittent method's e-puck ground robots)
    preset: Literal["office", "outdoor", "ground"] = param("office", tunable=False)
    # Where lambda2 and the Fiedler vector come from: "exact" (centralised eigh) or
    # "estimator" (decentralised, Yang et al. 2010)
    lambda2_source: Literal["exact", "estimator"] = param("exact", tunable=False)

    # -- estimator, lambda2 and the decentralised estimator (Yang et al. 2010)

    # Exact mode and estimator with estimator_modes >= 2: kappa of the smooth lower bound of lambda2 that
    # drives V (0: the paper's lambda2; see smooth_spectrum.py; the estimator takes the soft minimum of its
    # Ritz values)
    spectrum_smoothing: float = param(0.0, min=0.0, max=1.0)
    # Estimator only: seconds of estimator iterations on the start graph before the mission starts
    estimator_warmup_s: float = param(5.0, unit="s", min=0.0, max=60.0, tunable=False)
    # Estimator only: all its gains times this and its substep divided by it (faster convergence, proportionally
    # more computation)
    estimator_speedup: float = param(10.0, min=0.1, max=20.0, tunable=False)
    # Estimator only: the graph its two average-consensus loops run on: "links" (every message link
    # with weight 1) or "weights" (W, as in Yang et al.; consensus slows down as lambda2 -> 0)
    estimator_consensus: Literal["links", "weights"] = param("links", tunable=False)
    # Estimator only: the links its messages travel on, i.e. the graph whose lambda2 the robots estimate and
    # control: "sensing" (G^lambda, W_ij > 0, as in the paper) or "messages" (W o A: also in the
    # simulator's body-to-body communication graph A; f_lambda is then the gradient of lambda2(W o A))
    estimator_links: Literal["sensing", "messages"] = param("sensing", tunable=False)
    # Estimator only: V' is evaluated at no less than lambda2_min + this (an estimator transient below the
    # true lambda2 must not launch the virtual points)
    estimator_floor: float = param(0.003, min=0.0, max=1.0)
    # Estimator only: eigenpairs tracked. 1: Yang et al.'s single power-iteration vector (FiedlerEstimator);
    # K >= 2: K vectors (subspace iteration) with Rayleigh-Ritz, lambda2..lambda_{K+1} (SubspaceEstimator);
    # under a radio preset other than "ideal" always 1
    estimator_modes: int = param(2, min=1, max=5, tunable=False)
    # Estimator under a radio preset other than "ideal" (its state travels as messages, one exchange a tick):
    # its gains times this instead of estimator_speedup (one exchange per 10 ms tick is stable up to 0.25; lower
    # holds when the air lets each robot send only every few ticks)
    estimator_message_speedup: float = param(0.1, min=0.01, max=1.0, tunable=False)
    # Estimator under a real radio: a neighbour's last received state counts for this long, s
    estimator_message_timeout_s: float = param(0.2, unit="s", min=0.0, max=1.0, tunable=False)
    # Under a real radio: a robot counts a neighbour it heard as failed once nothing from it has arrived
    # for this long (any message is a heartbeat; reported in silent_neighbour_detections), s
    heartbeat_timeout_s: float = param(1.0, unit="s", above=0.0, max=600.0, tunable=False)

    # -- connectivity, Appendix A (link weight W_ij = range x line of sight x inter-robot factors;
    # R_s, where the range factor vanishes, is sensing.comm_range_m)

    # R'_s: range factor is 1 up to this distance (below R_s)
    full_weight_range_m: float = param(PRESET, unit="m", min=0.01, max=50.0)
    # R_o: weights vanish when the line of sight passes this close to an obstacle
    min_obstacle_clearance_m: float = param(PRESET, unit="m", min=0.01, max=10.0)
    # R'_o: line-of-sight factor is 1 from this clearance on
    full_weight_obstacle_clearance_m: float = param(PRESET, unit="m", min=0.02, max=10.0)
    # R_c: a robot's weights vanish when another robot comes this close (below R_s)
    min_robot_distance_m: float = param(PRESET, unit="m", min=0.05, max=20.0)
    # R'_c: inter-robot factor is 1 from this distance on (at most R_s)
    full_weight_robot_distance_m: float = param(PRESET, unit="m", min=0.1, max=20.0)
    # lambda2_min: the potential grows unbounded as lambda2 falls to this (Table 2)
    lambda2_min: float = param(0.0, min=0.0, max=5.0)
    # lambda2_null: potential and force vanish above this lambda2 (Table 2)
    lambda2_null: float = param(1.0, min=0.01, max=10.0)
    # k_lambda: scale of the connectivity potential V(lambda2)
    potential_gain_j: float = param(PRESET, unit="J", min=0.001, max=100.0)
    # V' is held at its value at lambda2_min + this below it (sampled-data safety)
    lambda2_guard: float = param(1e-5, min=1e-9, max=0.1, tunable=False)
    # M: mass of each virtual point
    virtual_mass_kg: float = param(1.0, unit="kg", min=0.1, max=10.0)
    # B: damping of each virtual point, f_B = -B v
    damping_nspm: float = param(2.0, unit="N s/m", min=0.05, max=50.0)

    # -- travel, Secs. 3.2 and 3.4 (the exploration layer)

    # v_cruise: speed of the path reference, eq. (3)
    cruise_speed_mps: float = param(PRESET, unit="m/s", min=0.1, max=10.0)
    # k_p of eq. (3), per kg of virtual mass
    position_gain: float = param(25.0, unit="1/s^2", min=0.1, max=400.0)
    # k_v of eq. (3), per kg of virtual mass
    velocity_gain: float = param(10.0, unit="1/s", min=0.1, max=100.0)
    # the path reference slows to rest over this last stretch
    braking_distance_m: float = param(PRESET, unit="m", min=0.05, max=30.0)
    # R_gamma: a secondary traveler farther than this from its path replans
    replan_distance_m: float = param(PRESET, unit="m", min=0.01, max=30.0)
    # cap on the travel force (eq. 3 grows with the distance to the path)
    travel_force_limit_n: float = param(PRESET, unit="N", min=0.1, max=500.0)

    # -- roles, election and consensus, Secs. 3.3-3.7

    # R_z: target visit / anchor radius
    target_radius_m: float = param(PRESET, unit="m", min=0.05, max=20.0)
    # Delta t: time to stay within R_z of each target (Table 2)
    dwell_time_s: float = param(3.0, unit="s", min=0.0, max=120.0)
    # k_z of eqs. (6)-(7)
    anchor_gain_n: float = param(PRESET, unit="N", min=0.01, max=100.0)
    # cap on the anchor force (eq. 7 is unbounded at R_z)
    anchor_force_limit_n: float = param(PRESET, unit="N", min=0.1, max=500.0)
    # x_c / v_cruise: traveling efficiency is 1 below this tracking error, eq. (9) (Table 2)
    efficiency_error_full_ratio: float = param(0.1, min=0.0, max=5.0)
    # x_M / v_cruise: traveling efficiency is 0 above this tracking error, eq. (9) (Table 2)
    efficiency_error_zero_ratio: float = param(0.6, min=0.01, max=10.0)
    # alpha_A of eq. (11): weight of the position error against the velocity error
    position_error_weight: float = param(0.0, min=0.0, max=1.0)
    # k_A of eq. (13): consensus gain on the prime traveler's efficiency (Sec. 4.2)
    consensus_gain: float = param(1.0, unit="1/s", min=0.01, max=100.0)
    # sigma of eq. (14): weight of force alignment against efficiency in rho (Table 2)
    sigma: float = param(3.0, min=1.0, max=50.0)
    # control ticks per hop of an election message (flooding, Sec. 3.3)
    message_latency_ticks: int = param(1, unit="ticks", min=1, max=100)
    # robot hosting the start-up election ("robot 1" of the paper)
    election_host: int = param(0, min=0, tunable=False)

    # -- path planning, Sec. 3.2

    # R_grid: path-planning grid spacing
    grid_resolution_m: float = param(PRESET, unit="m", min=0.05, max=5.0, tunable=False)
    # preferred clearance of planned paths from obstacles (default R'_o, where the line-of-sight weight is full)
    path_clearance_m: float = param(PRESET, unit="m", min=0.01, max=10.0, tunable=False)
    # fallback clearance of planned paths in narrow passages (default R_o)
    path_min_clearance_m: float = param(PRESET, unit="m", min=0.0, max=10.0, tunable=False)
    # how far the smoothing spline may round the grid path's corners
    smoothing_tolerance_m: float = param(PRESET, unit="m", min=0.0, max=5.0, tunable=False)

    # -- targets, the target generator of Secs. 2.1 / 4.1

    # "random": uniform free-space targets drawn with the run's generator; "fixed": target_lists
    targets: Literal["random", "fixed"] = param("random", tunable=False)
    # random: targets per robot in robot order; empty: the paper's 3 x 5 robots, 2 x 5 robots, 0 for the rest
    target_counts: tuple[int, ...] = param((), min=0, max=MAX_TARGETS_PER_ROBOT, tunable=False)
    # fixed: one list of [x, y, z] targets per robot (m), robot order; missing robots get none
    target_lists: tuple[tuple[Vec3, ...], ...] = param((), tunable=False)
    # random targets keep at least this distance from obstacles and scene bounds
    target_clearance_m: float = param(PRESET, unit="m", min=0.0, max=20.0, tunable=False)
    # random targets lie at or above this height
    target_height_min_m: float = param(PRESET, unit="m", min=-100.0, max=1000.0, tunable=False)
    # random targets lie at or below this height
    target_height_max_m: float = param(PRESET, unit="m", min=-100.0, max=1000.0, tunable=False)

    # Not a key: R_s, set by at_range from the scenario's sensing.comm_range_m.
    sensing_range_m: float | None = dataclasses.field(default=None, init=False)

    REMOVED_KEYS: ClassVar[dict[str, str]] = {
        "sensing_range_m": "set sensing.comm_range_m (R_s is the communication range: one graph for sensing and "
                           "communication, Sec. 2)",
    }

    def __post_init__(self) -> None:
        values = PRESETS[self.preset]
        per_range = GROUND_PER_RANGE if self.preset == "ground" else {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.init and isinstance(value, float) and math.isnan(value):
                if f.name in values:
                    object.__setattr__(self, f.name, float(values[f.name]))
                elif f.name in per_range:
                    object.__setattr__(self, f.name, None)  # at_range fills it
        if math.isnan(self.path_clearance_m):
            object.__setattr__(self, "path_clearance_m", self.full_weight_obstacle_clearance_m)
        if math.isnan(self.path_min_clearance_m):
            object.__setattr__(self, "path_min_clearance_m", self.min_obstacle_clearance_m)
        check_params(self)
        require(self.min_obstacle_clearance_m < self.full_weight_obstacle_clearance_m, "min_obstacle_clearance_m",
                f"R_o ({self.min_obstacle_clearance_m:g} m) must be smaller than R'_o = "
                f"full_weight_obstacle_clearance_m ({self.full_weight_obstacle_clearance_m:g} m): "
                f"the line-of-sight weight rises from R_o to R'_o")
        require(self.lambda2_min < self.lambda2_null, "lambda2_min",
                f"({self.lambda2_min:g}) must be smaller than lambda2_null ({self.lambda2_null:g}): "
                f"the potential acts between the two")
        require(self.lambda2_guard < self.lambda2_null - self.lambda2_min, "lambda2_guard",
                f"({self.lambda2_guard:g}) must be smaller than lambda2_null - lambda2_min "
                f"({self.lambda2_null - self.lambda2_min:g})")
        require(self.efficiency_error_full_ratio < self.efficiency_error_zero_ratio, "efficiency_error_full_ratio",
                f"({self.efficiency_error_full_ratio:g}) must be smaller than efficiency_error_zero_ratio "
                f"({self.efficiency_error_zero_ratio:g}): eq. (9) needs 0 <= x_c < x_M")
        require(self.path_min_clearance_m <= self.path_clearance_m, "path_min_clearance_m",
                f"({self.path_min_clearance_m:g} m) must not exceed path_clearance_m ({self.path_clearance_m:g} m)")
        require(self.target_height_min_m <= self.target_height_max_m, "target_height_max_m",
                f"must not be below target_height_min_m ({self.target_height_min_m:g} m), "
                f"got {self.target_height_max_m:g}")
        if self.targets == "fixed":
            require(any(len(route) for route in self.target_lists), "target_lists",
                    "must list at least one target with targets = \"fixed\"")

    def at_range(self, sensing_range_m: float) -> "ConnectedParams":
        """These parameters on a graph of range R_s = ``sensing_range_m`` (m, the scenario's
        ``sensing.comm_range_m``): R_s set, the ground preset's R_s-scaled values filled and the
        sensor model checked (ValueError 'key: problem')."""
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.init}
        for name, per_metre in (GROUND_PER_RANGE if self.preset == "ground" else {}).items():
            if values[name] is None:
                values[name] = round(per_metre * sensing_range_m, 12)
        out = ConnectedParams(**values)
        object.__setattr__(out, "sensing_range_m", float(sensing_range_m))
        out._check_sensor_model()
        return out

    def _check_sensor_model(self) -> None:
        r_s = self.sensing_range_m
        where = f"R_s = sensing.comm_range_m ({r_s:g} m)"
        require(self.min_robot_distance_m < r_s, "min_robot_distance_m",
                f"R_c ({self.min_robot_distance_m:g} m) must be smaller than {where}: "
                f"robots could not link without colliding")
        require(self.full_weight_range_m < r_s, "full_weight_range_m",
                f"R'_s ({self.full_weight_range_m:g} m) must be smaller than {where}: "
                f"the range weight fades from R'_s to R_s")
        require(self.min_robot_distance_m < self.full_weight_robot_distance_m, "min_robot_distance_m",
                f"R_c ({self.min_robot_distance_m:g} m) must be smaller than R'_c = full_weight_robot_distance_m "
                f"({self.full_weight_robot_distance_m:g} m): the inter-robot weight rises from R_c to R'_c")
        require(self.full_weight_robot_distance_m <= r_s, "full_weight_robot_distance_m",
                f"R'_c ({self.full_weight_robot_distance_m:g} m) must not exceed {where}: "
                f"a robot must sense every distance its weights depend on")

    @property
    def efficiency_error_full_mps(self) -> float:
        """x_c of eq. (9), m/s."""
        return self.efficiency_error_full_ratio * self.cruise_speed_mps

    @property
    def efficiency_error_zero_mps(self) -> float:
        """x_M of eq. (9), m/s."""
        return self.efficiency_error_zero_ratio * self.cruise_speed_mps

    @property
    def estimator(self) -> FiedlerEstimatorParams:
        """The estimator's gains: the defaults times ``estimator_speedup``, the substep divided by it."""
        base = FiedlerEstimatorParams()
        rates = ("mean_removal_gain", "laplacian_gain", "normalisation_gain", "consensus_input_gain",
                 "consensus_proportional_gain", "consensus_integral_gain")
        return dataclasses.replace(base, **{name: getattr(base, name) * self.estimator_speedup for name in rates},
                                   max_substep=base.max_substep / self.estimator_speedup)

    @property
    def message_estimator(self) -> FiedlerEstimatorParams:
        """The gains of the estimator over the radio: the defaults times ``estimator_message_speedup``."""
        base = FiedlerEstimatorParams()
        rates = ("mean_removal_gain", "laplacian_gain", "normalisation_gain", "consensus_input_gain",
                 "consensus_proportional_gain", "consensus_integral_gain")
        speedup = self.estimator_message_speedup
        return dataclasses.replace(base, **{name: getattr(base, name) * speedup for name in rates},
                                   max_substep=base.max_substep / speedup)

    @classmethod
    def examples(cls) -> dict[str, "ConnectedParams"]:
        """Each preset as a run uses it (the ground preset at the intermittent method's R = 0.2 m):
        the columns of the documentation's table of keys."""
        ranges = {"office": 2.5, "outdoor": 6.0, "ground": 0.2}
        return {f"{name} at R_s = {ranges[name]:g} m": cls(preset=name).at_range(ranges[name]) for name in PRESETS}
