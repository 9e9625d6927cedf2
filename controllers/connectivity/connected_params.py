"""Parameters of the ``connected`` strategy (Nestmeyer et al. 2017 on MuJoCo quadrotors).

One frozen dataclass, built from a scenario's ``[strategy]`` table through
:func:`sim.config.build` (unknown keys are errors, every problem names its
field). It gathers the connectivity layer (:class:`ConnectivityParams`,
Appendix A), the exploration layer (:class:`ExplorationParams`, Secs. 3.2-3.7),
the target generator (Sec. 2.1, the Monte Carlo trials of Sec. 4.1) and the
choice of lambda2 source (exact eigendecomposition or the decentralised
estimator of Yang et al. 2010).

Presets. ``preset = "office"`` or ``"outdoor"`` (Table 2) fills every field
the scenario leaves out; a field given explicitly wins. Fields are plain
numbers after construction (the preset is resolved in ``__post_init__``), so
``sim.config.to_table`` writes a complete table and the tuning page shows
concrete values. Changing ``preset`` later changes only the fields that are
still unset, i.e. none once a table has been written back.

Units are in the field names (``_m``, ``_s``, ``_mps``, ``_n``, ``_j``,
``_kg``, ``_nspm`` = N s/m); field metadata carries unit and bounds (the
tuning page draws sliders from them; :func:`sim.config.build` enforces them).

R_s and the simulator's communication range: Nestmeyer et al. 2017 takes the sensing and
communication graphs as one (Sec. 2). The loop's communication graph
(``sensing.comm_range_m`` plus ``mj_ray`` line of sight) carries the
election and consensus messages, so a scenario must set
``sensing.comm_range_m`` equal to R_s (``sensing_range_m``); the strategy
refuses a mismatch (exit 2) rather than silently using two ranges.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field, fields
from typing import Literal

from controllers.connectivity.exploration_params import ExplorationParams
from controllers.connectivity.params import ConnectivityParams, FiedlerEstimatorParams
from sim.config import param, require

Vec3 = tuple[float, float, float]

# Marks a field the preset fills (a NaN a scenario cannot write: bounds refuse it).
PRESET = math.nan

# Values of Table 2 beyond the two library presets: where random targets may
# lie (height band, m) and how far from obstacles (m).
_TARGET_DEFAULTS = {
    "office": dict(target_clearance_m=0.6, target_height_min_m=0.6, target_height_max_m=4.4),
    "outdoor": dict(target_clearance_m=1.75, target_height_min_m=2.0, target_height_max_m=12.0),
}
# Not in the paper (see docs/deviations.md): k_lambda scaled with the cruise speed (a prime traveler
# pulls with up to k_v v_cruise), so the barrier holds a pulled link about as far from R_s outdoors
# as indoors; f_travel capped at twice k_v v_cruise (Problem 1 asks for a bounded f_i); the anchor
# force cap twice that, so an anchor is not dragged out of R_z by a prime traveler's pull (its dwell
# clock would restart and the team could deadlock).
_OUR_DEFAULTS = {
    "office": dict(potential_gain_j=5.0, travel_force_limit_n=20.0, anchor_force_limit_n=40.0),
    "outdoor": dict(potential_gain_j=15.0, travel_force_limit_n=60.0, anchor_force_limit_n=120.0),
}

# strategy key -> ConnectivityParams field
_CONNECTIVITY_FIELDS = {
    "sensing_range_m": "sensing_range",
    "full_weight_range_m": "full_weight_range",
    "min_obstacle_clearance_m": "min_obstacle_clearance",
    "full_weight_obstacle_clearance_m": "full_weight_obstacle_clearance",
    "min_robot_distance_m": "min_robot_distance",
    "full_weight_robot_distance_m": "full_weight_robot_distance",
    "lambda2_min": "lambda2_min",
    "lambda2_null": "lambda2_null",
    "potential_gain_j": "potential_gain",
    "lambda2_guard": "lambda2_guard",
    "virtual_mass_kg": "virtual_mass",
    "damping_nspm": "damping",
}
# strategy key -> ExplorationParams field (the two efficiency thresholds are
# given as fractions of the cruise speed, as Table 2 does)
_EXPLORATION_FIELDS = {
    "cruise_speed_mps": "cruise_speed",
    "position_gain": "position_gain",
    "velocity_gain": "velocity_gain",
    "virtual_mass_kg": "virtual_mass",
    "braking_distance_m": "braking_distance",
    "replan_distance_m": "replan_distance",
    "target_radius_m": "target_radius",
    "dwell_time_s": "dwell_time",
    "anchor_gain_n": "anchor_gain",
    "anchor_force_limit_n": "anchor_force_limit",
    "travel_force_limit_n": "travel_force_limit",
    "position_error_weight": "position_error_weight",
    "consensus_gain": "consensus_gain",
    "sigma": "sigma",
    "grid_resolution_m": "grid_resolution",
    "path_clearance_m": "path_clearance",
    "path_min_clearance_m": "path_min_clearance",
    "smoothing_tolerance_m": "smoothing_tolerance",
    "message_latency_ticks": "message_latency_ticks",
    "election_host": "election_host",
}


# The "ground" preset (not in the paper): the continuous-connectivity paper's controller on the intermittent paper's
# e-puck-sized ground robots (body radius 0.036 m, wheel limit 0.154 m/s),
# virtual points in the plane of the range sensors. Body-scale ranges are
# fixed; R'_s scales with R_s (office ratio 1.1 / 2.5); forces scale with the
# cruise speed (the intermittent paper's u_max = 0.1 m/s against the office's 1 m/s) and
# k_lambda with force x length (R_s), so the barrier holds a pulled link at
# the same fraction of R_s as in the office. docs/paradigms.md gives the why.
GROUND_BODY = dict(
    min_robot_distance_m=0.08,  # R_c: two bodies touch at 0.072 m, plus ~1 cm
    full_weight_robot_distance_m=0.10,  # R'_c
    min_obstacle_clearance_m=0.05,  # R_o: body radius 0.036 m plus ~1.4 cm
    full_weight_obstacle_clearance_m=0.08,  # R'_o = the intermittent paper's clearance_m
    lambda2_min=0.0,
    lambda2_null=1.0,
    virtual_mass_kg=1.0,
    damping_nspm=2.0,
    cruise_speed_mps=0.1,  # the intermittent paper's |u| <= 0.1 m per 1 s step
    position_gain=25.0,
    velocity_gain=10.0,
    braking_distance_m=0.2,  # office 2 m at 1 m/s: the same braking time at 0.1 m/s
    target_radius_m=0.1,  # R_z
    dwell_time_s=3.0,
    anchor_gain_n=0.1,  # office 1 N x 0.1 (speed ratio)
    anchor_force_limit_n=4.0,  # 4 k_v v_cruise, as the office's 40 N
    travel_force_limit_n=2.0,  # 2 k_v v_cruise, as the office's 20 N
    position_error_weight=0.0,
    consensus_gain=1.0,
    sigma=3.0,
    grid_resolution_m=0.1,
    path_clearance_m=0.08,  # R'_o
    path_min_clearance_m=0.05,  # R_o
    smoothing_tolerance_m=0.02,
    efficiency_error_full_ratio=0.1,
    efficiency_error_zero_ratio=0.6,
    target_clearance_m=0.1,
    target_height_min_m=0.0,
    target_height_max_m=0.5,
)
GROUND_DEFAULT_RANGE_M = 0.2  # R_s when the scenario does not give it (the intermittent paper's R)


def ground_preset_values(sensing_range: float) -> dict[str, float]:
    """The "ground" preset for R_s = ``sensing_range`` (m), strategy key -> value."""
    values = dict(GROUND_BODY)
    values["sensing_range_m"] = sensing_range
    values["full_weight_range_m"] = round(0.44 * sensing_range, 12)  # R'_s / R_s of the office preset
    values["replan_distance_m"] = round(0.4 * sensing_range, 12)  # R_gamma / R_s of the office preset
    # office: 5 J at R_s = 2.5 m and 1 m/s -> 5 J x (0.1 / 1) x (R_s / 2.5)
    values["potential_gain_j"] = round(0.2 * sensing_range, 12)
    return values


def preset_values(preset: str, sensing_range: float = math.nan) -> dict[str, float]:
    """Every preset-filled field of ``preset`` ("office" | "outdoor" | "ground"), strategy key -> value
    (``sensing_range``: R_s the ground preset scales with, default 0.2 m)."""
    if preset == "ground":
        return ground_preset_values(GROUND_DEFAULT_RANGE_M if math.isnan(sensing_range) else sensing_range)
    connectivity = getattr(ConnectivityParams, preset)()
    exploration = getattr(ExplorationParams, preset)()
    out = {key: getattr(connectivity, name) for key, name in _CONNECTIVITY_FIELDS.items()}
    out.update({key: getattr(exploration, name) for key, name in _EXPLORATION_FIELDS.items()})
    out["efficiency_error_full_ratio"] = round(exploration.efficiency_error_full / exploration.cruise_speed, 12)
    out["efficiency_error_zero_ratio"] = round(exploration.efficiency_error_zero / exploration.cruise_speed, 12)
    out.update(_TARGET_DEFAULTS[preset])
    out.update(_OUR_DEFAULTS[preset])
    return out


MAX_TARGETS_PER_ROBOT = 1000  # random targets per robot (drawing them costs time before the run starts)


@dataclass(frozen=True)
class ConnectedParams:
    # -- general (group headers "# -- NAME, ..." group the fields on the tuning page)

    # Table 2 column that fills every field left out: "office" (indoor) or "outdoor" (empty space, town)
    # "ground": the intermittent paper's e-puck ground robots, ranges scaled from R_s (see GROUND_BODY)
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
    # K >= 2: K vectors (subspace iteration) with Rayleigh-Ritz, lambda2..lambda_{K+1} (SubspaceEstimator)
    estimator_modes: int = param(2, min=1, max=5, tunable=False)

    # -- connectivity, Appendix A (link weight W_ij = range x line of sight x inter-robot factors)

    # R_s: weights vanish at this distance; must equal sensing.comm_range_m
    sensing_range_m: float = param(PRESET, unit="m", min=0.2, max=50.0, tunable=False)
    # R'_s: range factor is 1 up to this distance
    full_weight_range_m: float = param(PRESET, unit="m", min=0.01, max=50.0)
    # R_o: weights vanish when the line of sight passes this close to an obstacle
    min_obstacle_clearance_m: float = param(PRESET, unit="m", min=0.01, max=10.0)
    # R'_o: line-of-sight factor is 1 from this clearance on
    full_weight_obstacle_clearance_m: float = param(PRESET, unit="m", min=0.02, max=10.0)
    # R_c: a robot's weights vanish when another robot comes this close
    min_robot_distance_m: float = param(PRESET, unit="m", min=0.05, max=20.0)
    # R'_c: inter-robot factor is 1 from this distance on
    full_weight_robot_distance_m: float = param(PRESET, unit="m", min=0.1, max=20.0)
    # lambda2_min: the potential grows unbounded as lambda2 falls to this
    lambda2_min: float = param(PRESET, min=0.0, max=5.0)
    # lambda2_null: potential and force vanish above this lambda2
    lambda2_null: float = param(PRESET, min=0.01, max=10.0)
    # k_lambda: scale of the connectivity potential V(lambda2)
    potential_gain_j: float = param(PRESET, unit="J", min=0.001, max=100.0)
    # V' is held at its value at lambda2_min + this below it (sampled-data safety; see params.py)
    lambda2_guard: float = param(1e-5, min=1e-9, max=0.1, tunable=False)
    # M: mass of each virtual point
    virtual_mass_kg: float = param(PRESET, unit="kg", min=0.1, max=10.0)
    # B: damping of each virtual point, f_B = -B v
    damping_nspm: float = param(PRESET, unit="N s/m", min=0.05, max=50.0)

    # -- travel, Secs. 3.2 and 3.4 (the exploration layer)

    # v_cruise: speed of the path reference, eq. (3)
    cruise_speed_mps: float = param(PRESET, unit="m/s", min=0.1, max=10.0)
    # k_p of eq. (3), per kg of virtual mass
    position_gain: float = param(PRESET, unit="1/s^2", min=0.1, max=400.0)
    # k_v of eq. (3), per kg of virtual mass
    velocity_gain: float = param(PRESET, unit="1/s", min=0.1, max=100.0)
    # the path reference slows to rest over this last stretch
    braking_distance_m: float = param(PRESET, unit="m", min=0.05, max=30.0)
    # R_gamma: a secondary traveler farther than this from its path replans
    replan_distance_m: float = param(PRESET, unit="m", min=0.05, max=30.0)
    # cap on the travel force (eq. 3 grows with the distance to the path)
    travel_force_limit_n: float = param(PRESET, unit="N", min=0.1, max=500.0)

    # -- roles, election and consensus, Secs. 3.3-3.7

    # R_z: target visit / anchor radius
    target_radius_m: float = param(PRESET, unit="m", min=0.05, max=20.0)
    # Delta t: time to stay within R_z of each target
    dwell_time_s: float = param(PRESET, unit="s", min=0.0, max=120.0)
    # k_z of eqs. (6)-(7)
    anchor_gain_n: float = param(PRESET, unit="N", min=0.01, max=100.0)
    # cap on the anchor force (eq. 7 is unbounded at R_z)
    anchor_force_limit_n: float = param(PRESET, unit="N", min=0.1, max=500.0)
    # x_c / v_cruise: traveling efficiency is 1 below this tracking error, eq. (9)
    efficiency_error_full_ratio: float = param(PRESET, min=0.0, max=5.0)
    # x_M / v_cruise: traveling efficiency is 0 above this tracking error, eq. (9)
    efficiency_error_zero_ratio: float = param(PRESET, min=0.01, max=10.0)
    # alpha_A of eq. (11): weight of the position error against the velocity error
    position_error_weight: float = param(PRESET, min=0.0, max=1.0)
    # k_A of eq. (13): consensus gain on the prime traveler's efficiency
    consensus_gain: float = param(PRESET, unit="1/s", min=0.01, max=100.0)
    # sigma of eq. (14): weight of force alignment against efficiency in rho
    sigma: float = param(PRESET, min=1.0, max=50.0)
    # control ticks per hop of an election message (flooding, Sec. 3.3)
    message_latency_ticks: int = param(1, unit="ticks", min=1, max=100)
    # robot hosting the start-up election ("robot 1" of the paper)
    election_host: int = param(0, min=0, tunable=False)

    # -- path planning, Sec. 3.2

    # R_grid: path-planning grid spacing
    grid_resolution_m: float = param(PRESET, unit="m", min=0.05, max=5.0, tunable=False)
    # preferred clearance of planned paths from obstacles
    path_clearance_m: float = param(PRESET, unit="m", min=0.01, max=10.0, tunable=False)
    # fallback clearance of planned paths in narrow passages
    path_min_clearance_m: float = param(PRESET, unit="m", min=0.0, max=10.0, tunable=False)
    # how far the smoothing spline may round the grid path's corners
    smoothing_tolerance_m: float = param(PRESET, unit="m", min=0.0, max=5.0, tunable=False)

    # -- targets, the target generator of Secs. 2.1 / 4.1

    # "random": uniform free-space targets drawn with the run's generator; "fixed": target_lists
    targets: Literal["random", "fixed"] = param("random", tunable=False)
    # random: targets per robot in robot order; empty: the paper's 3 x 5 robots, 2 x 5 robots, 0 for the rest
    target_counts: tuple[int, ...] = param((), tunable=False)
    # fixed: one list of [x, y, z] targets per robot (m), robot order; missing robots get none
    target_lists: tuple[tuple[Vec3, ...], ...] = param((), tunable=False)
    # random targets keep at least this distance from obstacles and scene bounds
    target_clearance_m: float = param(PRESET, unit="m", min=0.0, max=20.0, tunable=False)
    # random targets lie at or above this height
    target_height_min_m: float = param(PRESET, unit="m", min=-100.0, max=1000.0, tunable=False)
    # random targets lie at or below this height
    target_height_max_m: float = param(PRESET, unit="m", min=-100.0, max=1000.0, tunable=False)

    # Derived (not in the table): the library parameter objects.
    connectivity: ConnectivityParams = field(init=False, repr=False, compare=False)
    exploration: ExplorationParams = field(init=False, repr=False, compare=False)
    estimator: FiedlerEstimatorParams = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        require(self.preset in ("office", "outdoor", "ground"), "preset",
                f"must be 'office', 'outdoor' or 'ground', got {self.preset!r}")
        defaults = preset_values(self.preset, self.sensing_range_m)
        for f in fields(self):
            if f.init and isinstance(getattr(self, f.name), float) and math.isnan(getattr(self, f.name)):
                object.__setattr__(self, f.name, float(defaults[f.name]))
        require(self.min_robot_distance_m < self.sensing_range_m, "min_robot_distance_m",
                f"R_c ({self.min_robot_distance_m:g} m) must be smaller than R_s = sensing_range_m "
                f"({self.sensing_range_m:g} m): robots could not link without colliding")
        require(self.target_height_min_m <= self.target_height_max_m, "target_height_max_m",
                f"must not be below target_height_min_m ({self.target_height_min_m:g} m), "
                f"got {self.target_height_max_m:g}")
        require(all(isinstance(c, int) and c >= 0 for c in self.target_counts), "target_counts",
                f"must be non-negative integers, got {list(self.target_counts)}")
        require(all(c <= MAX_TARGETS_PER_ROBOT for c in self.target_counts), "target_counts",
                f"must be at most {MAX_TARGETS_PER_ROBOT} targets per robot, got {max(self.target_counts, default=0)}")
        if self.targets == "fixed":
            require(any(len(route) for route in self.target_lists), "target_lists",
                    "must list at least one target with targets = \"fixed\"")
        connectivity = _translated(ConnectivityParams, {
            name: getattr(self, key) for key, name in _CONNECTIVITY_FIELDS.items()}, _CONNECTIVITY_FIELDS)
        values = {name: getattr(self, key) for key, name in _EXPLORATION_FIELDS.items()}
        values["efficiency_error_full"] = self.efficiency_error_full_ratio * self.cruise_speed_mps
        values["efficiency_error_zero"] = self.efficiency_error_zero_ratio * self.cruise_speed_mps
        exploration = _translated(ExplorationParams, values, {
            **_EXPLORATION_FIELDS, "efficiency_error_full_ratio": "efficiency_error_full",
            "efficiency_error_zero_ratio": "efficiency_error_zero"})
        object.__setattr__(self, "connectivity", connectivity)
        object.__setattr__(self, "exploration", exploration)
        base = FiedlerEstimatorParams()
        rates = ("mean_removal_gain", "laplacian_gain", "normalisation_gain", "consensus_input_gain",
                 "consensus_proportional_gain", "consensus_integral_gain")
        estimator = dataclasses.replace(base, **{name: getattr(base, name) * self.estimator_speedup for name in rates},
                                        max_substep=base.max_substep / self.estimator_speedup)
        object.__setattr__(self, "estimator", estimator)


def _translated(cls: type, values: dict, names: dict[str, str]):
    """``cls(**values)``; a ValueError is re-raised as 'strategy_key: message'
    with the library's field names replaced by the strategy's keys (the key
    named first in the message leads)."""
    try:
        return cls(**values)
    except ValueError as err:
        text = str(err)
        reverse: dict[str, str] = {}
        for key, name in names.items():
            reverse.setdefault(name, key)
        hits = [(m.start(), name) for name in reverse for m in [re.search(rf"\b{name}\b", text)] if m]
        first = reverse[min(hits)[1]] if hits else cls.__name__
        for name in sorted(reverse, key=len, reverse=True):
            text = re.sub(rf"\b{name}\b", reverse[name], text)
        raise ValueError(f"{first}: {text}") from None
