"""A small room scenario for fast real runs of the intermittent-task strategies.

4 x 4 m, one interior wall that blocks line of sight, 4 e-puck ground robots
in the paper's 4-team ring, 2 moving targets. Epochs are short (tens of
seconds), so a 100 s run holds many meetings and delivers packets to every
team. Real MuJoCo, the real planner and the real EKF.
"""

from __future__ import annotations

from pathlib import Path

from helpers import write_scenario, write_scene

ROOM_SCENE = """
<mujoco model="small_room">
  <custom><numeric name="tether_bounds" data="0 0 0 4 4 3"/></custom>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.05" pos="2 2 0" group="0"/>
    <geom name="wall_s" type="box" size="2.1 0.05 1.5" pos="2 -0.05 1.5" group="0"/>
    <geom name="wall_n" type="box" size="2.1 0.05 1.5" pos="2 4.05 1.5" group="0"/>
    <geom name="wall_w" type="box" size="0.05 2 1.5" pos="-0.05 2 1.5" group="0"/>
    <geom name="wall_e" type="box" size="0.05 2 1.5" pos="4.05 2 1.5" group="0"/>
    <geom name="wall_mid" type="box" size="0.05 1.0 1.5" pos="2.0 3.0 1.5" group="0"/>
    <camera name="top" pos="2 2 6" xyaxes="1 0 0 0 1 0" projection="orthographic" fovy="4.4"/>
  </worldbody>
</mujoco>
"""

ROOM_SCENARIO = """
description = "test room"
scene = "room.xml"
duration_s = {duration}
seed = {seed}

[physics]
timestep_s = 0.005
control_period_s = 0.02

[target_motion]
noise_std_m = 0.02

[sensing]
comm_range_m = 0.2
target_range_m = 5.0
period_s = 1.0

[strategy]
kind = "{kind}"
teams = [[0, 1], [0, 2], [2, 3], [1, 3]]
n_sample = {n_sample}
n_uniform = 50
prior_mean = [[1.0, 3.0, 1.0], [3.2, 3.2, 1.0]]
{extra}

[[robots]]
kind = "ground"
starts = [[1.94, 0.94, 0.0], [2.06, 0.94, 0.0], [1.94, 1.06, 0.0], [2.06, 1.06, 0.0]]

[[targets]]
path = "linear"
start = [1.0, 3.3, 1.0]
end = [1.0, 2.3, 1.0]
speed_mps = 0.05

[[targets]]
path = "circular"
center = [3.0, 3.0, 1.2]
radius_m = 0.3
speed_mps = 0.05
"""


def room_scenario(folder: Path, kind: str = "intermittent", duration: float = 60.0, seed: int = 0,
                  n_sample: int = 150, extra: str = "") -> Path:
    write_scene(folder, ROOM_SCENE, "room.xml")
    text = ROOM_SCENARIO.format(kind=kind, duration=duration, seed=seed, n_sample=n_sample, extra=extra)
    return write_scenario(folder, text, f"room_{kind}_{seed}.toml")
