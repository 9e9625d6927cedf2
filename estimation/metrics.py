"""Estimation metrics of Khodayi-mehr et al. 2019, Sec. IV: localization error, uncertainty,
their time averages (eqs. 13a, 13b), t*(t) and the local error e_i(t)
(eq. 14), and information delays in epochs against Proposition III.2.

Pure numpy over arrays and :mod:`estimation.beliefs` objects; no I/O.

Deviations from the paper:
- Eq. (14) is illegible in our copy of the seed. From its text (t*(t) is the
  last time up to which the team estimate equals x_g; the metric "encapsulates
  the average delay with which team T_i receives information") we use the
  mean discrepancy over the window where they differ:
      e_i(t) = 1 / (t - t*(t)) * sum_{s = t*(t)+1}^{t} ||x_g(s) - x_Ti(s)||,
  with x_Ti(s) the team's filtered estimate of step s given what it knows at
  time t, and e_i(t) = 0 when t*(t) = t.
- Eqs. (13a), (13b) average over t = 1..t_end (t_end terms); the "+/-" of
  Table I is read as the population standard deviation of the same terms.
- Delay of a packet: epochs from the collecting robot's last meeting before
  collection to the epoch the last team receives it (the counting of the proof
  of Proposition III.2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

if TYPE_CHECKING:  # beliefs imports this module for eq. (14)
    from estimation.beliefs import NetworkBeliefs, PacketId


def localization_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """e(t) = ||x_hat(t) - x(t)||, m (estimate and truth (3M,))."""
    return float(np.linalg.norm(np.asarray(estimate, float) - np.asarray(truth, float)))


def max_eigenvalue(covariance: np.ndarray) -> float:
    """lambda_max(C(t)), m^2, of a symmetric covariance."""
    return float(np.linalg.eigvalsh(np.asarray(covariance, float))[-1])


def localization_error_series(estimates: np.ndarray, truths: np.ndarray) -> np.ndarray:
    """(n,) errors of (n, 3M) estimates against (n, 3M) true states, m."""
    estimates, truths = np.asarray(estimates, float), np.asarray(truths, float)
    if estimates.shape != truths.shape:
        raise ValueError(f"estimates/truths: shapes differ {estimates.shape} vs {truths.shape}")
    return np.linalg.norm(estimates - truths, axis=-1)


def uncertainty_series(covariances: np.ndarray) -> np.ndarray:
    """(n,) lambda_max of (n, 3M, 3M) covariances, m^2."""
    return np.linalg.eigvalsh(np.asarray(covariances, float))[:, -1]


@dataclass(frozen=True)
class TimeAverage:
    """Mean and population standard deviation over t = 1..t_end (unit of the series)."""

    mean: float
    std: float
    n_steps: int


def time_average(series_from_t0: np.ndarray) -> TimeAverage:
    """Eqs. (13a)/(13b): (1/t_end) sum_{t=1}^{t_end} of a series sampled at
    t = 0..t_end (entry 0, the initialisation, is left out)."""
    series = np.asarray(series_from_t0, float).reshape(-1)
    if series.size < 2:
        raise ValueError(f"series_from_t0: need samples at t = 0..t_end with t_end >= 1, got {series.size}")
    terms = series[1:]
    return TimeAverage(float(terms.mean()), float(terms.std()), terms.size)


def local_error(global_means: np.ndarray, team_means: np.ndarray) -> float:
    """Eq. (14) over a window: mean ||x_g(s) - x_Ti(s)||, m, of (w, 3M) arrays
    for s = t*(t)+1..t; 0 for an empty window."""
    global_means, team_means = np.asarray(global_means, float), np.asarray(team_means, float)
    if global_means.shape != team_means.shape:
        raise ValueError(f"global_means/team_means: shapes differ {global_means.shape} vs {team_means.shape}")
    if len(global_means) == 0:
        return 0.0
    return float(np.linalg.norm(global_means - team_means, axis=-1).mean())


@dataclass(frozen=True)
class TeamLag:
    """t*(t) (steps, -1 when nothing agrees) and e_i(t) (m) of one team at step t."""

    step: int
    agreement_step: int
    local_error: float


def team_lag(network: "NetworkBeliefs", team: int, step: int) -> TeamLag:
    """t*(t) and e_i(t) of ``team`` at t = ``step`` from what the beliefs
    hold now. Both depend on the knowledge at time t, so call this during the
    run, once per step (or per meeting, as Fig. 7 does), and keep the results."""
    return TeamLag(step, network.agreement_horizon(team, step), network.local_error(team, step))


def lag_series(lags: Sequence[TeamLag]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arrays (t, t*(t), e_i(t)) of recorded lags, for plots like Fig. 7."""
    return (
        np.array([lag.step for lag in lags], dtype=int),
        np.array([lag.agreement_step for lag in lags], dtype=int),
        np.array([lag.local_error for lag in lags], dtype=float),
    )


@dataclass(frozen=True)
class DelayReport:
    """Observed packet delays, epochs, against the bound D of Proposition III.2.

    delays: one entry per packet that has reached every team; worst/mean:
    their max and mean (0 if none); bound: D; pending: packets still missing
    some team; overdue: of those, the ones older than D epochs at the epoch
    the report was made for (0 when it was not given).
    """

    delays: np.ndarray
    worst: int
    mean: float
    bound: int
    pending: int
    overdue: int = 0

    @property
    def within_bound(self) -> bool:
        """No packet took longer than D, nor is still on its way after D (as far as it is known)."""
        return self.worst <= self.bound and self.overdue == 0


def packet_delays(deliveries: Mapping["PacketId", Mapping[int, int]], n_teams: int) -> tuple[np.ndarray, int]:
    """Delays (epochs) of the packets that reached all ``n_teams`` teams, and
    the number still pending."""
    delays = []
    pending = 0
    for packet, reached in deliveries.items():
        if len(reached) == n_teams:
            delays.append(max(reached.values()) - packet.epoch)
        else:
            pending += 1
    return np.array(delays, dtype=int), pending


def delay_report(network: "NetworkBeliefs", bound: int, epoch: int | None = None) -> DelayReport:
    """Observed delays of every completed packet of ``network`` vs ``bound``; with ``epoch`` (the
    latest epoch the teams met at), also the pending packets already older than ``bound``."""
    deliveries = network.deliveries
    delays, pending = packet_delays(deliveries, network.teams.n_teams)
    worst = int(delays.max()) if delays.size else 0
    mean = float(delays.mean()) if delays.size else 0.0
    overdue = 0
    if epoch is not None:
        overdue = sum(len(reached) < network.teams.n_teams and epoch - packet.epoch > bound
                      for packet, reached in deliveries.items())
    return DelayReport(delays, worst, mean, int(bound), pending, int(overdue))
