"""Parameters of the multi-target exploration layer of Nestmeyer et al. 2017 (Secs. 3.2-3.7, Tables 2-3).

Symbols follow Nestmeyer et al. (2017). Table 2 lost its column alignment in
the available text; read in the order of Table 3 its exploration rows are

    parameter          empty space / town     office
    R_grid             0.75 m                 0.25 m
    sigma              3                      3
    v_cruise           3 m/s                  1 m/s
    (x_c, x_M)         (0.1, 0.6) v_cruise    (0.1, 0.6) v_cruise
    Delta t            3 s                    3 s
    R_z                1.8 m                  1 m

and Table 3 (six-quadrotor experiment) gives R_grid 0.2 m, sigma 3,
v_cruise 0.5 m/s, (x_c, x_M) = (0.2, 0.7) v_cruise, Delta t 3 s, R_z 0.75 m,
with k_A = 1 (Sec. 4.2).

Deviations from the paper
-------------------------
The paper does not report the following; the defaults are ours:

- Travel gains k_p, k_v (eq. 3): critically damped lateral error
  (k_p = k_v^2 / 4) with k_v = 10 1/s, high enough that the damping force
  f_B = -B v of the connectivity layer (B = 2 N s/m for 1 kg) costs only
  B / (k_v + B) ~ 17 % of cruise speed on straight legs.
- alpha_A = 0: Sec. 4.2 reads Lambda_p = 1 as "at least 80 % of cruise speed"
  and Lambda_p = 0 as "less than 30 %" for (x_c, x_M) = (0.2, 0.7) v_cruise,
  i.e. the tracking error (11) is the velocity error alone.
- R_gamma (replanning distance), k_z (anchor gain): not given; R_gamma is a
  few grid cells, k_z makes the anchor pull comparable to the travel force.
- ``braking_distance``: the virtual point of eq. (3) slows linearly to rest
  over the last ``braking_distance`` metres of the path so that travelers
  arrive at their target instead of overshooting it at cruise speed
  (Table 1 calls v_cruise the *maximum* cruise speed).
- ``travel_force_limit``: eq. (3) grows without bound with the distance to
  the path (k_p (q_gamma - q)), while Problem 1 asks for a bounded f_i; the
  magnitude is capped (direction kept). Default: no cap.
- ``anchor_force_limit``: eq. (7) is unbounded at ||q - z|| = R_z; a
  sampled-data controller can step past R_z, so the anchor force magnitude is
  capped (and points back to the target beyond R_z).
- ``path_clearance`` / ``path_min_clearance`` / ``smoothing_tolerance``: the
  paper's grid search + smoothing "is not guaranteed to leave enough
  clearance" and relies on f_lambda; we plan with a margin instead (see
  paths.py): first ``path_clearance`` (R'_o, where the line-of-sight weight is
  full), then ``path_min_clearance`` (R_o) for narrow passages.
- ``message_latency_ticks``: flooding messages hop one graph edge per this
  many control ticks; the paper counts "steps" without a duration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


def _require_positive(obj, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def _require_non_negative(obj, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a non-negative finite number, got {value!r}")


@dataclass(frozen=True)
class ExplorationParams:
    """Travel, anchor, efficiency, consensus, planning and election parameters."""

    # Travel force, eq. (3).
    cruise_speed: float  # v_cruise, m/s: tangential speed of the path reference
    position_gain: float = 25.0  # k_p, 1/s^2 (per kg of virtual mass)
    velocity_gain: float = 10.0  # k_v, 1/s (per kg of virtual mass)
    virtual_mass: float = 1.0  # M, kg: eq. (3) is an acceleration times M; keep = ConnectivityParams.virtual_mass
    braking_distance: float = 2.0  # m: reference speed ramps to 0 over the last metres
    replan_distance: float = 1.0  # R_gamma, m: secondary travelers replan beyond this
    # Targets and anchor force, eqs. (5)-(7).
    target_radius: float = 1.0  # R_z, m: visit / anchor sphere radius
    dwell_time: float = 3.0  # Delta t, s: default time to stay within R_z
    anchor_gain: float = 1.0  # k_z, N
    anchor_force_limit: float = 20.0  # N: cap on |f_anchor|
    travel_force_limit: float = math.inf  # N: cap on |f_travel| (Problem 1 asks for a bounded f_i)
    # Traveling efficiency, eqs. (9), (11), (12).
    efficiency_error_full: float = 0.1  # x_c, m/s: Lambda = 1 for errors up to this
    efficiency_error_zero: float = 0.6  # x_M, m/s: Lambda = 0 from this error on
    position_error_weight: float = 0.0  # alpha_A in [0, 1]: weight of ||q_gamma - q|| in e_i
    # Consensus on the prime traveler's efficiency, eq. (13), and adaptive gain, eq. (14).
    consensus_gain: float = 1.0  # k_A, 1/s
    sigma: float = 3.0  # sigma >= 1: weight of alignment vs efficiency in rho
    # Path planning (Sec. 3.2, start-up line 6).
    grid_resolution: float = 0.25  # R_grid, m: planning grid spacing
    path_clearance: float = 0.6  # m: preferred path distance to obstacles
    path_min_clearance: float = 0.25  # m: fallback distance in narrow passages
    smoothing_tolerance: float = 0.15  # m: max distance of the spline from the grid path
    # Election by flooding (Sec. 3.3).
    message_latency_ticks: int = 1  # control ticks per message hop
    election_host: int = 0  # robot hosting the start-up election ("robot 1")

    def __post_init__(self) -> None:
        _require_positive(
            self,
            "cruise_speed",
            "position_gain",
            "velocity_gain",
            "virtual_mass",
            "braking_distance",
            "replan_distance",
            "target_radius",
            "anchor_gain",
            "anchor_force_limit",
            "efficiency_error_zero",
            "consensus_gain",
            "grid_resolution",
            "path_clearance",
            "path_min_clearance",
        )
        _require_non_negative(self, "dwell_time", "efficiency_error_full", "smoothing_tolerance")
        if not (isinstance(self.travel_force_limit, (int, float)) and self.travel_force_limit > 0):
            raise ValueError(f"travel_force_limit must be a positive number (inf: no cap), got {self.travel_force_limit!r}")
        if not self.efficiency_error_full < self.efficiency_error_zero:
            raise ValueError(
                f"efficiency_error_full ({self.efficiency_error_full}) must be smaller than "
                f"efficiency_error_zero ({self.efficiency_error_zero}): eq. (9) needs 0 <= x_c < x_M"
            )
        if not 0.0 <= self.position_error_weight <= 1.0:
            raise ValueError(f"position_error_weight must lie in [0, 1], got {self.position_error_weight!r}")
        if not (math.isfinite(self.sigma) and self.sigma >= 1.0):
            raise ValueError(f"sigma must be a finite number >= 1 (eq. 14), got {self.sigma!r}")
        if not self.path_min_clearance <= self.path_clearance:
            raise ValueError(
                f"path_min_clearance ({self.path_min_clearance}) must not exceed "
                f"path_clearance ({self.path_clearance})"
            )
        if not (isinstance(self.message_latency_ticks, int) and self.message_latency_ticks >= 1):
            raise ValueError(f"message_latency_ticks must be an integer >= 1, got {self.message_latency_ticks!r}")
        if not (isinstance(self.election_host, int) and self.election_host >= 0):
            raise ValueError(f"election_host must be a non-negative robot index, got {self.election_host!r}")

    @classmethod
    def office(cls, **overrides) -> "ExplorationParams":
        """Table 2, indoor office-like environment (about 10 m x 15 m)."""
        cruise = overrides.get("cruise_speed", 1.0)
        values = dict(
            cruise_speed=cruise,
            efficiency_error_full=0.1 * cruise,
            efficiency_error_zero=0.6 * cruise,
            sigma=3.0,
            dwell_time=3.0,
            target_radius=1.0,
            grid_resolution=0.25,
            braking_distance=2.0,
            replan_distance=1.0,
            path_clearance=0.6,  # R'_o of the office preset
            path_min_clearance=0.25,  # R_o of the office preset
            smoothing_tolerance=0.15,
        )
        return cls(**{**values, **overrides})

    @classmethod
    def outdoor(cls, **overrides) -> "ExplorationParams":
        """Table 2, outdoor scenes (empty space and town, 50 m x 70 m)."""
        cruise = overrides.get("cruise_speed", 3.0)
        values = dict(
            cruise_speed=cruise,
            efficiency_error_full=0.1 * cruise,
            efficiency_error_zero=0.6 * cruise,
            sigma=3.0,
            dwell_time=3.0,
            target_radius=1.8,
            grid_resolution=0.75,
            braking_distance=6.0,
            replan_distance=3.0,
            anchor_gain=3.0,
            anchor_force_limit=60.0,
            path_clearance=1.75,  # R'_o of the outdoor preset
            path_min_clearance=0.75,  # R_o of the outdoor preset
            smoothing_tolerance=0.4,
        )
        return cls(**{**values, **overrides})

    @classmethod
    def experiment(cls, **overrides) -> "ExplorationParams":
        """Table 3, the six-quadrotor indoor experiment (k_A = 1, Sec. 4.2)."""
        cruise = overrides.get("cruise_speed", 0.5)
        values = dict(
            cruise_speed=cruise,
            efficiency_error_full=0.2 * cruise,
            efficiency_error_zero=0.7 * cruise,
            sigma=3.0,
            dwell_time=3.0,
            target_radius=0.75,
            grid_resolution=0.2,
            braking_distance=1.0,
            replan_distance=0.75,
            consensus_gain=1.0,
            path_clearance=0.75,  # R'_o of Table 3
            path_min_clearance=0.5,  # R_o of Table 3
            smoothing_tolerance=0.1,
        )
        return cls(**{**values, **overrides})
