"""Virtual second-order dynamics of Nestmeyer et al. 2017, eq. (1), batched over N robots.

    M v' = f_B + f_lambda + f,   q' = v,   f_B = -B v

q: (N, 3) virtual-point positions, m; v: (N, 3) velocities, m/s; forces in N.
The real quadrotor tracks the virtual point; this module only moves the point.

Integration (one control period dt): semi-implicit Euler with the damping
taken implicitly,

    v+ = (M v + dt (f_lambda(q) + f)) / (M + dt B),   q+ = q + dt v+.

Why: explicit Euler adds energy to every oscillation of the potential-driven
system, which would defeat the passivity argument behind the connectivity
guarantee (Robuffo Giordano et al. 2013); the symplectic (semi-implicit)
update keeps the energy of the conservative part bounded, and the implicit
damping term is dissipative for any dt (it never flips the sign of v, as
explicit damping does when dt B / M > 2). It costs the same as explicit Euler.

Deviations from the paper
-------------------------
- The paper integrates in continuous time (its Simulink controller ran at
  1 kHz); we integrate at the simulator's control period.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.connectivity.estimator import FiedlerEstimate
from controllers.connectivity.graph import ConnectivityState, connectivity_state, generalized_connectivity_force
from controllers.connectivity.connected_params import ConnectedParams
from sim.compiled import kernel
from sim.geometry import Boxes


def damping_force(velocities: np.ndarray, params: ConnectedParams) -> np.ndarray:
    """f_B = -B v, (N, 3), N."""
    return -params.damping_nspm * np.asarray(velocities, dtype=float)


def step_virtual_dynamics(
    positions: np.ndarray,
    velocities: np.ndarray,
    applied_force: np.ndarray,
    dt: float,
    params: ConnectedParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Advance (q, v) by ``dt`` (s) under f_B (implicit) + ``applied_force``.

    ``applied_force`` (N, 3), N, is everything except damping: f_lambda + f.
    Returns the new positions (N, 3), m, and velocities (N, 3), m/s.
    """
    positions = np.asarray(positions, dtype=float)
    velocities = np.asarray(velocities, dtype=float)
    applied_force = np.asarray(applied_force, dtype=float)
    if not (positions.shape == velocities.shape == applied_force.shape and positions.shape[-1] == 3):
        raise ValueError(
            f"positions, velocities and applied_force must share shape (N, 3), got "
            f"{positions.shape}, {velocities.shape}, {applied_force.shape}"
        )
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    mass = params.virtual_mass_kg
    new_velocities = (mass * velocities + dt * applied_force) / (mass + dt * params.damping_nspm)
    return positions + dt * new_velocities, new_velocities


def step_virtual_dynamics_applied(positions: np.ndarray, velocities: np.ndarray, connectivity_force: np.ndarray,
                                  other_force: np.ndarray, planar: bool, dt: float,
                                  params: ConnectedParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The control tick's integration in one compiled pass: the applied force f_lambda + f (its z
    component dropped when ``planar``), ``step_virtual_dynamics`` and the acceleration (v' - v) / dt,
    element by element in numpy's order (the same bits). Float (N, 3) arrays; returns (q', v', a)."""
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    new_positions, new_velocities, acceleration = (np.empty(positions.shape) for _ in range(3))
    _virtual_step_kernel(positions, velocities, connectivity_force, other_force, bool(planar), float(dt),
                         float(params.virtual_mass_kg), float(params.damping_nspm), new_positions, new_velocities,
                         acceleration)
    return new_positions, new_velocities, acceleration


@kernel
def _virtual_step_kernel(q, v, f_lambda, f_other, planar, dt, mass, damping, q_out, v_out, a_out):
    denominator = mass + dt * damping
    for i in range(q.shape[0]):
        for k in range(3):
            applied = f_lambda[i, k] + f_other[i, k]
            if planar and k == 2:
                applied = 0.0
            velocity = (mass * v[i, k] + dt * applied) / denominator
            v_out[i, k] = velocity
            q_out[i, k] = q[i, k] + dt * velocity
            a_out[i, k] = (velocity - v[i, k]) / dt


@dataclass(frozen=True)
class ConnectivityLayerForce:
    """Forces of the connectivity layer on every robot, (N, 3), N.

    damping: f_B = -B v at the current velocity.
    connectivity: f_lambda = -V'(lambda2) dlambda2/dq with the lambda2 and
        Fiedler vector that were used (exact or estimated).
    lambda2_used: (N,) the lambda2 each robot evaluated V' at.
    state: exact weights, Laplacian, lambda2 and Fiedler vector (for logging
        and comparison, whichever source drove the force).
    """

    damping: np.ndarray
    connectivity: np.ndarray
    lambda2_used: np.ndarray
    state: ConnectivityState

    @property
    def total(self) -> np.ndarray:
        """f_B + f_lambda."""
        return self.damping + self.connectivity


def connectivity_layer_force(
    positions: np.ndarray,
    velocities: np.ndarray,
    boxes: Boxes | None,
    params: ConnectedParams,
    estimate: FiedlerEstimate | None = None,
) -> ConnectivityLayerForce:
    """f_B + f_lambda for all robots.

    With ``estimate`` None the centralised oracle is used (exact lambda2 and
    Fiedler vector from one eigh); otherwise each robot i uses its own
    estimate.lambda2[i] and the estimated eigenvector components of itself
    and its neighbours, as the decentralised controller would.
    """
    state = connectivity_state(positions, boxes, params)
    n = len(state.fiedler)
    if estimate is None:
        lambda2 = np.full(n, state.lambda2)
        connectivity = generalized_connectivity_force(state.links, state.lambda2, state.fiedler, params)
    else:
        lambda2 = np.asarray(estimate.lambda2, dtype=float)
        if lambda2.shape != (n,) or np.shape(estimate.fiedler) != (n,):
            raise ValueError(f"estimate must hold ({n},) arrays, got {lambda2.shape} and {np.shape(estimate.fiedler)}")
        connectivity = generalized_connectivity_force(state.links, lambda2, estimate.fiedler, params)
    return ConnectivityLayerForce(
        damping=damping_force(velocities, params),
        connectivity=connectivity,
        lambda2_used=lambda2,
        state=state,
    )
