"""Parameters of the continuous-connectivity layer (Nestmeyer et al. 2017, Appendix A, Tables 2-3).

Symbols follow Nestmeyer et al. (2017). The link weight W_ij of Appendix A is
the product of three factors, each with a hard limit where it vanishes and a
second ("primed") distance where it reaches one:

- range:            full up to R'_s, fades to zero at R_s            (R'_s < R_s);
- line of sight:    zero at clearance R_o, full from R'_o on          (R_o < R'_o);
- inter-robot:      zero at distance R_c, full from R'_c on           (R_c < R'_c).

Table 2 of the paper lost its column alignment in the available text: the rows
are (R'_s, R_s), (R_o, R'_o), (R_c, R'_c), (lambda2_min, lambda2_null),
R_grid, sigma, v_cruise, (x_c, x_M), Delta t, R_z, as in Table 3. Only the
first four rows belong to this layer.

Deviations from the paper
-------------------------
- The paper does not report M, B, the potential gain or the estimator gains;
  the defaults below are ours: M = 1 kg and B = 2 N s/m (velocity time
  constant 0.5 s); k_lambda = 5 J holds a six-robot office chain dragged by a
  3 N pull at lambda2 ~ 0.17, where the default estimator tracks lambda2 to a
  few percent; the estimator gains converge within a few seconds on
  10-robot graphs (see FiedlerEstimatorParams).
- M and B are isotropic scalars shared by all robots (the paper allows 3x3
  positive-definite matrices per robot); all robots of a team are identical.
- ``lambda2_guard`` has no counterpart in the paper: in continuous time the
  potential's slope is unbounded at lambda2_min; a sampled-data controller
  (or an estimator transient) can hand it lambda2 <= lambda2_min, where the
  slope is then held at its value at lambda2_min + lambda2_guard so the force
  stays finite and points the right way instead of becoming inf/nan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


def _require_positive(obj, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def _require_less(obj, smaller: str, larger: str, why: str) -> None:
    if not getattr(obj, smaller) < getattr(obj, larger):
        raise ValueError(
            f"{smaller} ({getattr(obj, smaller)}) must be smaller than "
            f"{larger} ({getattr(obj, larger)}): {why}"
        )


@dataclass(frozen=True)
class ConnectivityParams:
    """Sensor model, connectivity potential and virtual dynamics of Nestmeyer et al. 2017."""

    # Range factor of the link weight.
    sensing_range: float  # R_s, m: weight vanishes at and beyond this distance
    full_weight_range: float  # R'_s, m: weight starts to fade beyond this distance
    # Line-of-sight factor: d_ijo = clearance of segment q_i -> q_j from obstacles.
    min_obstacle_clearance: float  # R_o, m: weight vanishes at and below this clearance
    full_weight_obstacle_clearance: float  # R'_o, m: factor is 1 from this clearance on
    # Inter-robot factor: every distance d_ik, k != i, enters robot i's weights.
    min_robot_distance: float  # R_c, m: weight vanishes at and below this distance
    full_weight_robot_distance: float  # R'_c, m: factor is 1 from this distance on
    # Connectivity potential V(lambda2); lambda2 is in weight units (W_ij is in [0, 1]).
    lambda2_min: float = 0.0  # potential grows unbounded as lambda2 -> lambda2_min+
    lambda2_null: float = 1.0  # potential and its slope are zero for lambda2 >= this
    potential_gain: float = 5.0  # k_lambda, J: scale of V (see potential.py)
    lambda2_guard: float = 1e-3  # lambda2 units: slope held below lambda2_min + this
    # Virtual point dynamics M v' = -B v + f_lambda + f.
    virtual_mass: float = 1.0  # M, kg
    damping: float = 2.0  # B, N s / m

    def __post_init__(self) -> None:
        _require_positive(
            self,
            "sensing_range",
            "full_weight_range",
            "min_obstacle_clearance",
            "full_weight_obstacle_clearance",
            "min_robot_distance",
            "full_weight_robot_distance",
            "potential_gain",
            "lambda2_guard",
            "virtual_mass",
            "damping",
        )
        _require_less(self, "full_weight_range", "sensing_range", "the range weight fades from R'_s to R_s")
        _require_less(
            self,
            "min_obstacle_clearance",
            "full_weight_obstacle_clearance",
            "the line-of-sight weight rises from R_o to R'_o",
        )
        _require_less(
            self,
            "min_robot_distance",
            "full_weight_robot_distance",
            "the inter-robot weight rises from R_c to R'_c",
        )
        _require_less(self, "min_robot_distance", "sensing_range", "robots must be able to link without colliding")
        if not self.full_weight_robot_distance <= self.sensing_range:
            raise ValueError(
                f"full_weight_robot_distance ({self.full_weight_robot_distance}) must not exceed "
                f"sensing_range ({self.sensing_range}): a robot must sense every distance its weights depend on"
            )
        if not (math.isfinite(self.lambda2_min) and self.lambda2_min >= 0):
            raise ValueError(f"lambda2_min must be a non-negative finite number, got {self.lambda2_min!r}")
        if not math.isfinite(self.lambda2_null):
            raise ValueError(f"lambda2_null must be finite, got {self.lambda2_null!r}")
        _require_less(self, "lambda2_min", "lambda2_null", "the potential acts between lambda2_min and lambda2_null")
        if not self.lambda2_guard < self.lambda2_null - self.lambda2_min:
            raise ValueError(
                f"lambda2_guard ({self.lambda2_guard}) must be smaller than lambda2_null - lambda2_min "
                f"({self.lambda2_null - self.lambda2_min})"
            )

    @classmethod
    def office(cls, **overrides: float) -> "ConnectivityParams":
        """Table 2, indoor office-like environment (about 10 m x 15 m)."""
        values = dict(
            sensing_range=2.5,
            full_weight_range=1.1,
            min_obstacle_clearance=0.25,
            full_weight_obstacle_clearance=0.6,
            min_robot_distance=0.8,
            full_weight_robot_distance=1.1,
            lambda2_min=0.0,
            lambda2_null=1.0,
        )
        return cls(**{**values, **overrides})

    @classmethod
    def outdoor(cls, **overrides: float) -> "ConnectivityParams":
        """Table 2, outdoor scenes (empty space and town, 50 m x 70 m)."""
        values = dict(
            sensing_range=6.0,
            full_weight_range=2.5,
            min_obstacle_clearance=0.75,
            full_weight_obstacle_clearance=1.75,
            min_robot_distance=1.0,
            full_weight_robot_distance=2.5,
            lambda2_min=0.0,
            lambda2_null=1.0,
        )
        return cls(**{**values, **overrides})

    @classmethod
    def experiment(cls, **overrides: float) -> "ConnectivityParams":
        """Table 3, the six-quadrotor indoor experiment."""
        values = dict(
            sensing_range=2.5,
            full_weight_range=1.4,
            min_obstacle_clearance=0.5,
            full_weight_obstacle_clearance=0.75,
            min_robot_distance=1.0,
            full_weight_robot_distance=1.4,
            lambda2_min=0.0,
            lambda2_null=1.0,
        )
        return cls(**{**values, **overrides})


@dataclass(frozen=True)
class FiedlerEstimatorParams:
    """Gains of the decentralised lambda2 / Fiedler-vector estimator (Yang et al. 2010).

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

    Time scales (defaults): the consensus must be faster than the power
    iteration, K_P lambda2 >> gamma >~ k1; for graphs with lambda2 ~ 0.05-0.5
    the defaults converge in about 1-3 s. The substep shrinks as
    1 / (k2 lambda_max(L) + k1 + k3) (the consensus loops are integrated
    exactly, estimator.py): the cost grows with the power-iteration gains.
    """

    mean_removal_gain: float = 15.0  # k1, 1/s: drives Ave(x) -> 0 (deflates the 1 eigenvector)
    laplacian_gain: float = 10.0  # k2, 1/s per unit weight: the power-iteration step -k2 L x
    normalisation_gain: float = 40.0  # k3, 1/s: drives Ave(x^2) towards 1 - k2 lambda2 / k3
    consensus_input_gain: float = 20.0  # gamma, 1/s: pull of y_i towards the local input a_i
    consensus_proportional_gain: float = 400.0  # K_P, 1/s per unit weight
    consensus_integral_gain: float = 400.0  # K_I, 1/s per unit weight
    max_substep: float = 1e-3  # s: longest integration substep (accuracy of the Euler power iteration)
    dither: float = 1e-4  # 1/sqrt(s): intensity of the white noise each robot adds to x_i (0: none)

    def __post_init__(self) -> None:
        _require_positive(self, *(f.name for f in fields(self) if f.name != "dither"))
        if not (isinstance(self.dither, (int, float)) and math.isfinite(self.dither) and self.dither >= 0):
            raise ValueError(f"dither must be a non-negative finite number, got {self.dither!r}")

    @property
    def lambda2_ceiling(self) -> float:
        """Largest lambda2 (weight units) the estimator can converge to."""
        return min(self.mean_removal_gain, self.normalisation_gain) / self.laplacian_gain
