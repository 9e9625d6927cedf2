"""Parameters shared by the intermittent paper's method and its two baselines.

One frozen dataclass serves the three strategy kinds ``intermittent``,
``all_time`` and ``random_meeting``, so a scenario written for one runs with
``--set strategy.kind=...`` for the others; each kind reads the fields it
needs (``teams`` is ignored by ``all_time``; the planner fields by
``random_meeting``). Built through :func:`sim.config.build`: unknown keys are
errors and every problem names its field.

Time: one discrete step of the paper is ``step_s`` seconds of simulation
(1 s: range readings and the target model both tick once per step, so
``sensing.period_s`` and ``target_motion.step_s`` must equal it). The paper's
speed limit |u| <= 0.1 m per step is ``speed_mps`` = 0.1 m/s.
"""

from __future__ import annotations

from dataclasses import dataclass

from controllers.intermittent.teams import Teams
from sim.config import require

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
    n_sample: int = 300
    n_uniform: int = 100  # B: the first B samples are uniform (f1), then f2, -
    delta_m2: float = 0.0144  # goal threshold on lambda_max of a target block, m^2 (paper: 0.12^2)
    step_size_m: float = 1.0  # epsilon of Steer (Alg. 6): longest move of one robot per tree edge, m

    # -- motion and meetings

    speed_mps: float = 0.1  # robot speed limit, m/s (paper: 0.1 m per 1 s step)
    step_s: float = 1.0  # one discrete step, s (= sensing.period_s = target_motion.step_s)
    link_margin_m: float = 0.05  # plans keep meeting links within comm_range_m minus this, m
    clearance_m: float = 0.08  # clearance of planned paths from walls (robot radius 0.036 m + tracking), m
    arrival_tolerance_m: float = 0.05  # a robot has arrived when its body is this close to its meeting point, m
    gather_after_s: float = 5.0  # all arrived but the team graph not connected this long: close in on the centroid, s
    max_replans: int = 2  # extra planner runs (fresh samples) after a failed plan, before the fallback, -

    # -- estimator, the EKF

    prior_mean: tuple[Vec3, ...] = ()  # EKF initial estimate x^0 per target, m; empty: the paper's x^0
    prior_variance_m2: float = 0.25  # EKF initial covariance C(0) = this * I, m^2 (paper: 0.25)
    # Range readings from sensors all at one height cannot tell a target from
    # its mirror image below that plane; reflect estimates that fall below it
    # (targets are above the floor). false: the paper's plain EKF.
    resolve_mirror: bool = True

    # -- outputs and baselines

    lag_team: int = 1  # team whose t*(t) and e_i(t) are plotted (paper Fig. 7: T_2, index 1), -
    random_clearance_m: float = 0.3  # random_meeting: meeting points keep this from walls, m

    def __post_init__(self):
        require(isinstance(self.n_sample, int) and self.n_sample >= 1, "n_sample",
                f"must be an integer >= 1, got {self.n_sample!r}")
        require(self.n_sample <= MAX_SAMPLES, "n_sample",
                f"must be at most {MAX_SAMPLES} (one plan keeps every sample's belief), got {self.n_sample}")
        require(self.n_uniform >= 0, "n_uniform", f"must be >= 0, got {self.n_uniform}")
        require(self.delta_m2 > 0, "delta_m2", f"must be positive (a variance threshold, m^2), got {self.delta_m2}")
        for name in ("step_size_m", "speed_mps", "step_s", "clearance_m", "arrival_tolerance_m",
                     "prior_variance_m2", "random_clearance_m"):
            value = getattr(self, name)
            require(value > 0, name, f"must be positive, got {value}")
        for name in ("link_margin_m", "gather_after_s"):
            value = getattr(self, name)
            require(value >= 0, name, f"must be non-negative, got {value}")
        require(0 <= self.max_replans <= MAX_REPLANS, "max_replans",
                f"must be in [0, {MAX_REPLANS}], got {self.max_replans}")
        require(self.lag_team >= 0, "lag_team", f"must be >= 0, got {self.lag_team}")
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
                f"(the scenario has {n_robots} robots, indices 0..{n_robots - 1})")
        missing = sorted(set(range(n_robots)) - set(teams.robots))
        require(not missing, "teams", f"robot(s) {missing} belong to no team; every robot must belong to exactly two teams")
        require(self.lag_team < teams.n_teams, "lag_team",
                f"must be a team index below {teams.n_teams}, got {self.lag_team}")
        return teams
