"""Parameters shared by the intermittent method (Khodayi-mehr et al. 2019) and its two baselines.

One frozen dataclass serves the three strategy kinds ``intermittent``,
``all_time`` and ``random_meeting``, so a scenario written for one runs with
``--set strategy.kind=...`` for the others; each kind reads the fields it
needs (``teams`` is ignored by ``all_time``; the planner fields by
``random_meeting``). The task's keys (speed limit, delta, the EKF's prior) are
:data:`controllers.task.TASK_PARAMS`, shared with ``connected_tracking``.
Built through :func:`sim.config.build`: unknown keys are errors and every
problem names its field.

One discrete step of the paper is ``sensing.period_s`` (1 s; see
:mod:`controllers.task`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from controllers.intermittent.teams import Teams
from controllers.task import STEP_KEY_REMOVED, task_param
from sim.config import check_params, param, require

Vec3 = tuple[float, float, float]
MAX_SAMPLES = 100_000  # n_sample: what one plan may hold in memory
MAX_REPLANS = 100  # max_replans


@dataclass(frozen=True)
class IntermittentParams:
    # -- teams (group headers "# -- NAME, ..." group the fields on the tuning page)

    # Teams as lists of robot indices (robot order of the scenario, from 0);
    # every robot in exactly two teams, the graph of teams connected.
    teams: tuple[tuple[int, ...], ...] = ()

    # -- planner, the joint-space RRT* (Algorithm 1)

    # Samples of Algorithm 1 per plan of a 2-robot team, -; a team of n > 2 robots draws
    # n_sample * n / 2 (its joint space has 2n dimensions: see team_samples).
    n_sample: int = param(300, min=1, max=MAX_SAMPLES)
    n_uniform: int = param(100, min=0)  # B: the first B samples are uniform (f1), then f2, -
    # goal threshold on lambda_max of a target block, m^2 (paper: 0.12^2)
    delta_m2: float = task_param("delta_m2")
    # epsilon of Steer (Alg. 6): longest move of one robot per tree edge, m
    step_size_m: float = param(1.0, unit="m", above=0.0)

    # -- motion and meetings

    speed_mps: float = task_param("speed_mps")  # robot speed limit, m/s (paper: 0.1 m per 1 s step)
    # plans keep meeting links within comm_range_m minus this, m
    link_margin_m: float = param(0.05, unit="m", min=0.0)
    # clearance of planned paths from walls (robot radius 0.036 m + tracking), m
    clearance_m: float = param(0.08, unit="m", above=0.0)
    # a robot has arrived when its body is this close to its meeting point, m
    arrival_tolerance_m: float = param(0.05, unit="m", above=0.0)
    # all arrived but the team graph not connected this long: close in on the centroid, s
    gather_after_s: float = param(5.0, unit="s", min=0.0)
    # extra planner runs (fresh samples) after a failed plan, before the fallback, -
    max_replans: int = param(2, min=0, max=MAX_REPLANS)
    # Under a real radio: a meeting whose members' records have not all arrived this long after
    # its exchange began ends without them (counted in meetings_timed_out), s
    exchange_timeout_s: float = param(20.0, unit="s", above=0.0, max=3600.0)
    # a meeting whose present members have all waited this long at their points, and this long past its
    # planned time, for a member who has not arrived is held without it (counted in meetings_missed);
    # inf: wait for ever, as the schedule of Khodayi-mehr et al. 2019 assumes, s
    member_timeout_s: float = param(60.0, unit="s", above=0.0, allow_inf=True)
    # Under a real radio: a range-records message without an ack this long is sent again, s
    retransmit_after_s: float = task_param("retransmit_after_s")

    # -- estimator, the EKF

    # EKF initial estimate x^0 per target, m; empty: the paper's x^0
    prior_mean: tuple[Vec3, ...] = task_param("prior_mean")
    # EKF initial covariance C(0) = this * I, m^2 (paper: 0.25)
    prior_variance_m2: float = task_param("prior_variance_m2")
    # Range readings from sensors all at one height cannot tell a target from
    # its mirror image below that plane; reflect estimates that fall below it
    # (targets are above the floor). false: the paper's plain EKF.
    resolve_mirror: bool = task_param("resolve_mirror")
    # Without an informed prior: keep each target's readings out of the EKF until they fix its
    # position (multilateration), then start its estimate there (set in another scene, --scene)
    init_from_readings: bool = task_param("init_from_readings")

    # -- outputs and baselines

    lag_team: int = param(1, min=0)  # team whose t*(t) and e_i(t) are plotted (paper Fig. 7: T_2, index 1), -
    # random_meeting: meeting points keep this from walls, m
    random_clearance_m: float = param(0.3, unit="m", above=0.0)

    REMOVED_KEYS: ClassVar[dict[str, str]] = STEP_KEY_REMOVED

    def __post_init__(self):
        check_params(self)
        if self.teams:
            for index, team in enumerate(self.teams):
                negative = [r for r in team if r < 0]
                require(not negative, "teams", f"team {index} has a negative robot index {negative[0] if negative else ''}")
            try:
                Teams.from_lists(self.teams)
            except ValueError as err:
                problem = str(err).partition(": ")[2] or str(err)
                raise ValueError(f"teams: {problem}") from None

    def team_structure(self, n_robots: int) -> Teams:
        """The validated :class:`Teams` for ``n_robots`` robots (ValueError
        'teams: ...' when missing or when it does not cover robots 0..N-1)."""
        require(len(self.teams) > 0, "teams", "is required for this strategy (lists of robot indices, "
                "every robot in exactly two teams)")
        teams = Teams.from_lists(self.teams)
        outside = [r for r in teams.robots if r >= n_robots]
        require(not outside, "teams", f"robot index {outside[0] if outside else ''} does not exist "
                f"(the scenario has {n_robots} robots, indices 0..{n_robots - 1}); a team of another size "
                "needs its own strategy.teams (lists of robot indices, every robot in exactly two teams)")
        missing = sorted(set(range(n_robots)) - set(teams.robots))
        require(not missing, "teams", f"robot(s) {missing} belong to no team; every robot must belong to exactly two teams")
        require(self.lag_team < teams.n_teams, "lag_team",
                f"must be a team index below {teams.n_teams}, got {self.lag_team}")
        return teams
