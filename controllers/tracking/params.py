"""Parameters of ``connected_tracking``: the continuous-connectivity paper's controller on the intermittent paper's task.

The intermittent paper's fields (:class:`IntermittentParams`: prior, delta, step, speed
limit...) are inherited unchanged, so a Khodayi-mehr et al. 2019 scenario such as
``intermittent-8`` runs with ``--set strategy.kind=connected_tracking`` and
all four methods share the prior, delta and speed limit (``teams`` and the
RRT* fields are ignored here). The fields below drive the EKF target
generator; the continuous-connectivity paper's controller takes the ``ground`` preset of
:mod:`controllers.connectivity.connected_params` with R_s =
``sensing.comm_range_m`` and v_cruise = ``speed_mps``. docs/paradigms.md
explains every value.
"""

from __future__ import annotations

from dataclasses import dataclass

from controllers.intermittent.params import IntermittentParams
from sim.config import param, require


@dataclass(frozen=True)
class ConnectedTrackingParams(IntermittentParams):
    # Robots that explore (travel to viewpoints and anchor there); the others connect. Chosen at the
    # start by farthest-point order from the team's centroid (the ends of the start cluster).
    explorers: int = param(2, min=1, max=64, tunable=False)
    # Planar distances from a target's estimate at which viewpoints are tried, m
    viewpoint_radii_m: tuple[float, ...] = param((0.3, 0.6, 1.0, 1.5), unit="m", tunable=False)
    # Bearings tried per distance, evenly spaced
    viewpoint_bearings: int = param(12, min=1, max=64, tunable=False)
    # Longest dwell at one viewpoint (the readings' predicted need is cut here), s
    max_dwell_s: float = param(30.0, unit="s", min=1.0, max=600.0)
    # A dwell ends when one more reading would shrink the target's lambda_max by less than this fraction
    dwell_stall: float = param(0.02, min=0.0, max=1.0)
    # A traveler's viewpoint is re-issued when its target's estimate has moved this far since, m
    reissue_distance_m: float = param(0.3, unit="m", min=0.01, max=10.0)

    def __post_init__(self):
        super().__post_init__()
        require(isinstance(self.explorers, int) and self.explorers >= 1, "explorers",
                f"must be an integer >= 1, got {self.explorers!r}")
        require(len(self.viewpoint_radii_m) > 0 and all(r > 0 for r in self.viewpoint_radii_m),
                "viewpoint_radii_m", f"must list positive distances, got {list(self.viewpoint_radii_m)}")
        require(self.viewpoint_bearings >= 1, "viewpoint_bearings", f"must be >= 1, got {self.viewpoint_bearings}")
        require(self.max_dwell_s > 0, "max_dwell_s", f"must be positive, got {self.max_dwell_s}")
        require(0 <= self.dwell_stall < 1, "dwell_stall", f"must lie in [0, 1), got {self.dwell_stall}")
        require(self.reissue_distance_m > 0, "reissue_distance_m", f"must be positive, got {self.reissue_distance_m}")
