"""Every model compiles and steps 1 s warning-free; robot files are fully named."""

import mujoco
import numpy as np
import pytest

from sim.scenario import MODELS_DIR, builtin_scenarios, load
from tether.runner import build_simulation

SCENES = sorted((MODELS_DIR / "scenes").glob("*.xml"))
ROBOTS = sorted((MODELS_DIR / "robots").glob("*.xml"))


def _warnings(data):
    return {mujoco.mjtWarning(i).name: int(w.number) for i, w in enumerate(data.warning) if w.number}


@pytest.mark.parametrize("path", SCENES + ROBOTS, ids=lambda p: p.stem)
def test_model_compiles_and_steps_one_second(path):
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    for _ in range(int(1.0 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    assert not _warnings(data)
    assert np.all(np.isfinite(data.qpos))


@pytest.mark.parametrize("path", ROBOTS, ids=lambda p: p.stem)
def test_robot_file_elements_are_named(path):
    model = mujoco.MjModel.from_xml_path(str(path))
    kinds = {
        "body": (model.nbody, mujoco.mjtObj.mjOBJ_BODY),
        "joint": (model.njnt, mujoco.mjtObj.mjOBJ_JOINT),
        "geom": (model.ngeom, mujoco.mjtObj.mjOBJ_GEOM),
        "site": (model.nsite, mujoco.mjtObj.mjOBJ_SITE),
        "actuator": (model.nu, mujoco.mjtObj.mjOBJ_ACTUATOR),
    }
    for kind, (count, obj) in kinds.items():
        start = 1 if kind == "body" else 0  # the world body has no name
        for i in range(start, count):
            assert mujoco.mj_id2name(model, obj, i), f"{path.name}: unnamed {kind} {i}"


def test_robot_visual_and_collision_geoms_are_in_separate_groups():
    for path in ROBOTS:
        model = mujoco.MjModel.from_xml_path(str(path))
        for g in range(model.ngeom):
            collides = model.geom_contype[g] or model.geom_conaffinity[g]
            if collides:
                assert model.geom_group[g] == 1, f"{path.name}: colliding geom {g} not in group 1"
            else:
                assert model.geom_group[g] in (2, 3), f"{path.name}: visual geom {g} in group {model.geom_group[g]}"


@pytest.mark.parametrize("name", sorted(builtin_scenarios()))
def test_builtin_scenario_world_steps_one_second_without_warnings(name):
    sim = build_simulation(load(name, duration_s=1.0))
    for _ in range(int(round(1.0 / sim.dt))):
        _, healthy = sim.tick()
        assert healthy
    assert not _warnings(sim.world.data)
