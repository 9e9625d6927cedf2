"""Parameters of ``connected_tracking``: the continuous-connectivity controller on the intermittent paper's task.

The task's keys (speed limit, delta, the EKF's prior: :data:`controllers.task.TASK_PARAMS`)
are those of the intermittent method and its baselines, so the four methods
share them; the other fields drive the EKF target generator. The controller
takes the ``ground`` preset of :mod:`controllers.connectivity.connected_params`
at R_s = ``sensing.comm_range_m``, with v_cruise = ``speed_mps``
(:func:`controllers.tracking.strategy.controller_params`). docs/paradigms.md
explains every value.

A scenario written for the intermittent method (``intermittent-8``) runs with
``--set strategy.kind=connected_tracking``: its own keys (``teams``, the RRT*
fields) are checked by :class:`IntermittentParams` and not used here
(``TABLE_SHARED_WITH``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from controllers.intermittent.params import IntermittentParams
from controllers.task import STEP_KEY_REMOVED, task_param
from sim.config import check_params, param, require

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class ConnectedTrackingParams:
    # -- task, the intermittent paper's (shared with intermittent, all_time and random_meeting)

    speed_mps: float = task_param("speed_mps")  # robot speed limit and the controller's v_cruise, m/s
    delta_m2: float = task_param("delta_m2")  # a target is served when its lambda_max falls below this, m^2
    # EKF initial estimate x^0 per target, m; empty: the paper's x^0
    prior_mean: tuple[Vec3, ...] = task_param("prior_mean")
    prior_variance_m2: float = task_param("prior_variance_m2")  # EKF initial covariance C(0) = this * I, m^2
    # Reflect estimates that fall below the sensors' plane (range readings cannot tell a target
    # from its mirror image); false: the paper's plain EKF.
    resolve_mirror: bool = task_param("resolve_mirror")
    # Without an informed prior: keep each target's readings out of the EKF until they fix its
    # position (multilateration), then start its estimate there (set in another scene, --scene)
    init_from_readings: bool = task_param("init_from_readings")
    # Under a real radio: a reading's message to the fusion robot without an ack this long is sent again, s
    retransmit_after_s: float = task_param("retransmit_after_s")

    # -- explorers, the EKF target generator

    # Robots that explore (travel to viewpoints and anchor there); the others connect. Chosen at the
    # start by farthest-point order from the team's centroid (the ends of the start cluster).
    explorers: int = param(2, min=1, max=64, tunable=False)
    # Planar distances from a target's estimate at which viewpoints are tried, m
    viewpoint_radii_m: tuple[float, ...] = param((0.3, 0.6, 1.0, 1.5), unit="m", above=0.0, tunable=False)
    # Bearings tried per distance, evenly spaced
    viewpoint_bearings: int = param(12, min=1, max=64, tunable=False)
    # Longest dwell at one viewpoint (the readings' predicted need is cut here), s
    max_dwell_s: float = param(30.0, unit="s", min=1.0, max=600.0)
    # A dwell ends when one more reading would shrink the target's lambda_max by less than this fraction
    dwell_stall: float = param(0.02, min=0.0, max=1.0)
    # A traveler's viewpoint is re-issued when its target's estimate has moved this far since, m
    reissue_distance_m: float = param(0.3, unit="m", min=0.01, max=10.0)

    TABLE_SHARED_WITH: ClassVar[tuple[type, ...]] = (IntermittentParams,)
    REMOVED_KEYS: ClassVar[dict[str, str]] = STEP_KEY_REMOVED

    def __post_init__(self):
        check_params(self)
        require(len(self.viewpoint_radii_m) > 0, "viewpoint_radii_m", "must list at least one distance")
