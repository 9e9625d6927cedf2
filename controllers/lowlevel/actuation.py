"""Strategy references -> actuator commands, for every robot kind at once.

Quadrotors: geometric SE(3) tracking + mixer (controllers.lowlevel.quadrotor).
Ground robots: the point-offset point follows the horizontal reference as a
single integrator, u = v_ref + k (p_ref - P_b), turned into wheel speeds
(controllers.lowlevel.ground). Parameters are read from the compiled model
once; each kind is one batched call.
"""

from __future__ import annotations

import numpy as np

from controllers.lowlevel import ground, quadrotor
from controllers.lowlevel.model_params import ground_robot_params, quadrotor_params
from sim.types import Commands, Observation
from sim.world import World

GROUND_POSITION_GAIN = 2.0  # 1/s: pulls the offset point onto the reference


def _rows(index):
    """``index`` (sorted ints) as an equivalent slice when consecutive, else as it is."""
    index = list(index)
    if index and index == list(range(index[0], index[-1] + 1)):
        return slice(index[0], index[-1] + 1)
    return np.asarray(index, dtype=int)


class LowLevelControl:
    def __init__(self, world: World):
        self.world = world
        self.quads = world.kind_index["quadrotor"]
        self.grounds = world.kind_index["ground"]
        names = world.robot_names
        self.quad_params = quadrotor_params(world.model, f"{names[self.quads[0]]}/") if len(self.quads) else None
        self.quad_gains = quadrotor.QuadrotorGains()
        self.ground_params = ground_robot_params(world.model, f"{names[self.grounds[0]]}/") if len(self.grounds) else None
        # Each kind's rows as a slice where they are consecutive (a view instead of a fancy-index copy).
        self.quad_rows, self.ground_rows = _rows(self.quads), _rows(self.grounds)
        self.quad_actuators = world.actuator_ids["quadrotor"]
        self.ground_actuators = world.actuator_ids["ground"]

    def hover_ctrl(self) -> None:
        """Initial rotor thrusts: each rotor carries a quarter of the weight."""
        if len(self.quads):
            self.world.data.ctrl[self.quad_actuators] = self.quad_params.hover_thrust / 4

    def apply(self, observation: Observation, commands: Commands) -> None:
        ctrl = self.world.data.ctrl
        if len(self.quads):
            q = self.quad_rows
            ctrl[self.quad_actuators] = quadrotor.track_reference(
                self.quad_params, self.quad_gains, observation.position[q], observation.velocity[q],
                observation.quaternion[q], observation.angular_velocity[q], commands.position[q],
                commands.velocity[q], commands.acceleration[q], commands.yaw[q],
            )
        if len(self.grounds):
            g = self.ground_rows
            ctrl[self.ground_actuators] = ground.track_reference(
                self.ground_params, observation.position[g], observation.quaternion[g], commands.position[g],
                commands.velocity[g], GROUND_POSITION_GAIN,
            )
