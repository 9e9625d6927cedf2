"""Yang et al. (2010)'s lambda2 / Fiedler-vector estimator fed by the message bus.

The in-process estimators (estimator.py) integrate the whole team's
continuous-time system inside one control period: over a substep the exact
consensus flow moves information across every hop. Robots that talk by radio
cannot: robot i only learns a neighbour's state from that neighbour's
message, one broadcast a tick at most. :class:`MessageFedEstimator` is that
estimator:

- Each robot keeps its own state, the K-vector subspace form of Yang et al.'s
  power iteration with PI average consensus (estimator.SubspaceEstimator's
  equations and Rayleigh-Ritz; K = 1 is Yang et al.'s single vector), and a
  table of the last state it received from every other robot, with the time
  of arrival.
- Each tick every robot broadcasts its state once ("lambda2_estimate",
  :func:`estimator_message_bytes`): float32 values, so a receiver holds the
  rounded copy. The bus supersedes a robot's earlier estimator message that
  has not gone out yet (Message.latest_only): only the newest state
  counts, and the queue stays bounded when the air is full.
- Robot i's links this tick are those with W_ij > 0 over which a message
  arrived within ``timeout_s``; its rows of the Laplacian use only them, with
  the neighbours' last received values held over the tick. Lost messages
  therefore drop links from robot i's own row only: the rows of two robots
  need not agree, and the estimate is of a graph the robots do not share.
- A robot the team drops as silent (the method's heartbeat timeout,
  failures.py) leaves the estimator (:meth:`MessageFedEstimator.drop`): no
  robot uses a link to it or a message from it again, it broadcasts no
  more, and the averages, the Ritz values and the Fiedler vector's
  normalisation are those of the robots still in the team. Every other
  robot's state, its consensus integrals included, carries over: the
  averages do not depend on the integrals' sum (1^T L_c z = 0 for a
  symmetric L_c), and a restart would need every robot to restart in the
  same tick while messages with the old integrals are still in the air.
- The step is a discrete-time iteration, one exchange per tick: one forward
  Euler step over the control period, the neighbours' values held (more
  Euler substeps against frozen neighbours only let a robot's own state run
  away from the values it couples to). The consensus loops use Metropolis
  weights (Xiao and Boyd 2004), c_ij = a_ij / (1 + max(deg_i, deg_j)), with
  a_ij the link (1, or W_ij) and deg_j the neighbour's own degree carried in
  its message: every row of the consensus Laplacian then sums to at most 1
  and the iteration is stable for K_P dt <= 1 whatever the graph. Unit
  weights would need K_P dt deg_max <= 1.

Why it is slower than the in-process estimator: with one exchange per 10 ms
tick, the consensus step K_P dt must stay at most 1 (``check_gains``): the
gains can be at most 1 / (K_P dt) of the library's (0.25 at 10 ms), against
10x in process, and information crosses one hop a tick. When the air carries
fewer than one message per robot a tick (802.15.4: about four of ten
robots' 38-byte states a tick), the held values are several ticks old and
lower gains are needed again (ConnectedParams.estimator_message_speedup).
See docs/radio.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.connectivity.connected_params import FiedlerEstimatorParams
from controllers.connectivity.estimator import SubspaceEstimate, SubspaceEstimator
from sim.radio.bus import INDEX_BYTES, Message

LAMBDA2_ESTIMATE_KIND = "lambda2_estimate"
# A message's values go out as float32.
_VALUE_BYTES = 4
# Largest consensus step K_P dt (and input step gamma dt) the discrete iteration takes.
MAX_CONSENSUS_STEP = 1.0


def estimator_message_bytes(modes: int) -> int:
    """Payload of one robot's estimator message, bytes: its K components, the D consensus
    estimates and their D integrals, its degree and its Fiedler component (float32 each), with a
    uint16 round number."""
    k = int(modes)
    channels = k + k * (k + 1) // 2 + k * k
    return _VALUE_BYTES * (k + 2 * channels + 2) + INDEX_BYTES


@dataclass(frozen=True)
class EstimatorState:
    """What a robot broadcasts: its estimator state, float32."""

    components: np.ndarray  # (K,) its rows of X
    consensus: np.ndarray  # (D,) its consensus estimates y
    consensus_integral: np.ndarray  # (D,) their integrals z
    degree: float  # sum of its consensus links' a_ij at its last step (Metropolis weights)
    fiedler: float  # its estimate of its own unit Fiedler-vector component (the force's eq. 17 terms)
    round: int  # its step count, modulo 2^16


class MessageFedEstimator:
    """N robots' estimators, each fed only by the messages it received (see the module docstring).

    ``consensus`` is "links" (a_ij = 1 on every used link) or "weights" (a_ij = W_ij)."""

    def __init__(self, num_robots: int, params: FiedlerEstimatorParams, rng: np.random.Generator, modes: int,
                 timeout_s: float, consensus: str = "links"):
        if not timeout_s >= 0:
            raise ValueError(f"timeout_s must be at least 0, got {timeout_s}")
        if consensus not in ("links", "weights"):
            raise ValueError(f"consensus must be 'links' or 'weights', got {consensus!r}")
        self.num_robots = n = num_robots
        self.modes = int(modes)
        self.params = params
        self.timeout_s = float(timeout_s)
        self.consensus_links = consensus
        self._core = SubspaceEstimator(n, params, rng, self.modes)  # the equations' layout and Rayleigh-Ritz
        self._rng = rng
        k, d = self.modes, self._core.channels
        self._slices = (slice(0, k), slice(k, k + d), slice(k + d, k + 2 * d))
        self.heard = np.zeros((n, n, k + 2 * d))  # [i, j]: robot j's last state as robot i received it
        self.heard_degree = np.zeros((n, n))
        self.heard_fiedler = np.zeros((n, n))
        self.heard_s = np.full((n, n), -np.inf)  # when robot i received it, s
        self.used = np.zeros((n, n), dtype=bool)  # the links of the last step, row i: robot i's
        self.degree = np.zeros(n)
        self.rounds = 0
        self.failure = ""  # why the estimate is no longer usable ("" while it is)
        self.members = np.ones(n, dtype=bool)  # robots not dropped from the team (drop)
        self._estimate = self._core.estimate

    @property
    def estimate(self) -> SubspaceEstimate:
        return self._estimate

    def check_gains(self, dt: float) -> None:
        """ValueError unless the discrete iteration's consensus steps stay at most MAX_CONSENSUS_STEP."""
        p = self.params
        step = max(p.consensus_proportional_gain, p.consensus_integral_gain, p.consensus_input_gain) * dt
        if step > MAX_CONSENSUS_STEP:
            raise ValueError(f"consensus gain x control period = {step:.3g} above {MAX_CONSENSUS_STEP:g}: "
                             f"the message-fed estimator would be unstable at a {dt:g} s control period")

    # -- the radio ----------------------------------------------------------------------------------

    def state_of(self, robot: int) -> EstimatorState:
        core = self._core
        with np.errstate(over="ignore"):  # a diverged state (``failure``) rounds to inf
            return EstimatorState(core.components[robot].astype(np.float32),
                                  core.consensus[robot].astype(np.float32),
                                  core.consensus_integral[robot].astype(np.float32),
                                  float(np.float32(self.degree[robot])),
                                  float(np.float32(self._estimate.fiedler[robot])), self.rounds % 65536)

    def messages(self) -> tuple[Message, ...]:
        """Every robot's broadcast of its current state; each supersedes its own that is still queued."""
        size = estimator_message_bytes(self.modes)
        return tuple(Message(LAMBDA2_ESTIMATE_KIND, i, None, self.state_of(i), size, latest_only=True)
                     for i in range(self.num_robots) if self.members[i])

    def drop(self, robot: int) -> None:
        """Take ``robot`` out for good (the team dropped it as silent): from now on nobody uses a link to it
        or stores its messages, it is not stepped and sends nothing, and the estimate is of the robots still
        in (its row: lambda2 NaN, Fiedler component 0)."""
        self.members[robot] = False
        self.heard_s[:, robot] = -np.inf
        self.heard_s[robot, :] = -np.inf
        self.used[:, robot] = self.used[robot, :] = False
        self.degree[robot] = 0.0
        self._estimate = self._members_estimate()

    def _members_estimate(self) -> SubspaceEstimate:
        """Every robot's estimate; with robots dropped, the Rayleigh-Ritz of the team without them."""
        core = self._core
        if self.members.all():
            return core.estimate
        keep = self.members
        part = core.restricted(keep).estimate
        n, k = self.num_robots, self.modes
        out = SubspaceEstimate(lambda2=np.full(n, np.nan), values=np.full((n, k), np.nan),
                               valid=np.zeros((n, k), dtype=bool), coefficients=np.full((n, k, k), np.nan),
                               components=np.array(core.components, dtype=float), fiedler=np.zeros(n))
        out.lambda2[keep], out.values[keep], out.valid[keep] = part.lambda2, part.values, part.valid
        out.coefficients[keep], out.fiedler[keep] = part.coefficients, part.fiedler
        return out

    def receive(self, receiver: int, sender: int, state: EstimatorState, time_s: float) -> None:
        """Robot ``receiver`` stores ``sender``'s state, received at ``time_s``."""
        xs, ys, zs = self._slices
        row = self.heard[receiver, sender]
        row[xs], row[ys], row[zs] = state.components, state.consensus, state.consensus_integral
        self.heard_degree[receiver, sender] = state.degree
        self.heard_fiedler[receiver, sender] = state.fiedler
        self.heard_s[receiver, sender] = time_s

    def receive_inbox(self, inbox, time_s: float) -> int:
        """Store every estimator message of the tick's inbox (per robot, Deliveries); returns how many."""
        count = 0
        for receiver, deliveries in enumerate(inbox):
            for delivery in deliveries:
                message = delivery.message
                if message.kind == LAMBDA2_ESTIMATE_KIND and self.members[receiver] and self.members[message.sender]:
                    self.receive(receiver, message.sender, message.payload, delivery.arrival_s)
                    count += 1
        return count

    def used_links(self, weights: np.ndarray, time_s: float) -> np.ndarray:
        """(N, N) bool, row i: robot i's links this tick, W_ij > 0 and a message from j within the timeout."""
        fresh = self.heard_s >= time_s - self.timeout_s - 1e-9
        used = fresh & (np.asarray(weights) > 0) & self.members[:, None] & self.members[None, :]
        np.fill_diagonal(used, False)
        return used

    # -- one tick ----------------------------------------------------------------------------------

    def step(self, weights, dt: float, time_s: float, inbox=()) -> SubspaceEstimate:
        """Take the tick's estimator messages from ``inbox`` (per robot, sim.radio.bus.Delivery tuples), then
        advance every robot by ``dt`` (s) with its own row of the (N, N) weights restricted to the links it
        heard, the neighbours' values held. Once a state turns non-finite, ``failure`` says so and the last
        finite estimate is kept."""
        n = self.num_robots
        weights = np.asarray(weights, dtype=float)
        if weights.shape != (n, n):
            raise ValueError(f"weights must have shape ({n}, {n}), got {weights.shape}")
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        self.receive_inbox(inbox, time_s)
        if self.failure:
            return self._estimate
        used = self.used = self.used_links(weights, time_s)
        w = np.where(used, weights, 0.0)
        links = used.astype(float) if self.consensus_links == "links" else w
        degree = links.sum(axis=1)
        # Metropolis weights from the neighbour's degree as it last reported it.
        c = links / (1.0 + np.maximum(degree[:, None], np.where(used, self.heard_degree, 0.0)))
        xs, ys, zs = self._slices
        held_x, held_y, held_z = self.heard[:, :, xs], self.heard[:, :, ys], self.heard[:, :, zs]
        # Neighbour sums with held values, fixed over the tick: sum_j w_ij s_j.
        wx, cy, cz = (np.einsum("ij,ijk->ik", w, held_x), np.einsum("ij,ijk->ik", c, held_y),
                      np.einsum("ij,ijk->ik", c, held_z))
        w_degree, c_degree = w.sum(axis=1)[:, None], c.sum(axis=1)[:, None]
        core, p = self._core, self.params
        x, y, z = core.components.copy(), core.consensus.copy(), core.consensus_integral.copy()
        with np.errstate(all="ignore"):
            lx = w_degree * x - wx
            ly, lz = c_degree * y - cy, c_degree * z - cz
            rate_x = core._power_rate(x, lx, y)
            rate_y = (p.consensus_input_gain * (core._inputs(x, lx) - y) - p.consensus_proportional_gain * ly
                      + p.consensus_integral_gain * lz)
            rate_z = -p.consensus_integral_gain * ly
            x, y, z = x + dt * rate_x, y + dt * rate_y, z + dt * rate_z
            if p.dither > 0:
                x = x + p.dither * np.sqrt(dt) * self._rng.standard_normal(x.shape)
        out = ~self.members
        if out.any():  # a dropped robot's state stays as it was
            x[out], y[out], z[out] = core.components[out], core.consensus[out], core.consensus_integral[out]
        self.degree = degree
        self.rounds += 1
        if not (np.isfinite(x).all() and np.isfinite(y).all() and np.isfinite(z).all()):
            self.failure = f"the lambda2 estimator over the radio diverged at t = {time_s:.2f} s"
            return self._estimate
        core.components, core.consensus, core.consensus_integral = x, y, z
        self._estimate = self._members_estimate()
        return self._estimate

    def fiedler_views(self) -> np.ndarray:
        """(N, N): column i is the Fiedler vector as robot i knows it, its own component and the last
        received ones of the neighbours it used in the last step; a robot it did not hear gets its own
        value (that link adds nothing to its eq. 17)."""
        own = self._estimate.fiedler
        views = np.where(self.used.T, self.heard_fiedler.T, own[None, :])
        np.fill_diagonal(views, own)
        return views

    def warm_up(self, weights, dt: float, steps: int) -> SubspaceEstimate:
        """``steps`` ticks on a fixed graph with every message delivered at once: the exchange on the ground
        before the mission, which can repeat until every message arrives."""
        n = self.num_robots
        used = np.asarray(weights) > 0
        np.fill_diagonal(used, False)
        for tick in range(int(steps)):
            time_s = (tick - int(steps)) * dt  # before the mission's t = 0
            for sender in range(n):
                state = self.state_of(sender)
                for receiver in np.flatnonzero(used[sender]):
                    self.receive(int(receiver), sender, state, time_s)
            self.step(weights, dt, time_s)
        return self._estimate
