"""The radio map (``tether radiomap``): the formulas at a few points, the PNG, bad input refused."""

from __future__ import annotations

import math
import textwrap

import mujoco
import numpy as np
import pytest
from PIL import Image

from helpers import write_scenario, write_scene
from sim.radio.config import RadioConfig
from sim.scenario import load
from sim.world import extract_obstacles, obstacle_wall_losses
from tether.cli import main
from sim.radio.radiomap import radio_map, reference_sensitivity_dbm
from tether.radiomap import FIGURE_DPI, FIGURE_SIZE_IN, transmitter_of

# Two walls across the room: wall_a (x = 3) takes radio.wall_loss_db, wall_b (x = 6) its own 9 dB.
# The floor plane lies below every receiver and is crossed by no segment.
SCENE = """
<mujoco model="two_walls">
  <custom>
    <numeric name="tether_bounds" data="0 0 0 10 10 5"/>
    <numeric name="tether_wall_loss_db/wall_b" data="9"/>
  </custom>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.05" pos="5 5 0" group="0"/>
    <geom name="wall_a" type="box" size="0.05 4 2" pos="3 5 2" group="0"/>
    <geom name="wall_b" type="box" size="0.05 4 2" pos="6 5 2" group="0"/>
  </worldbody>
</mujoco>
"""

SCENARIO = """
scene = "scene.xml"
duration_s = 1.0

[strategy]
kind = "waypoints"

[[robots]]
kind = "quadrotor"
starts = [[1.0, 5.0, 1.0]]

[[robots]]
kind = "ground"
starts = [[1.0, 2.0, 0.0]]

[radio]
preset = "ieee802154"
wall_loss_db = 5.0
"""


def _scene():
    model = mujoco.MjModel.from_xml_string(textwrap.dedent(SCENE))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return extract_obstacles(model, data), obstacle_wall_losses(model)


def test_the_map_is_the_link_budget_with_the_walls_counted_by_hand():
    config = RadioConfig(preset="ieee802154", wall_loss_db=5.0)
    boxes, losses = _scene()
    transmitter = np.array([1.0, 5.0, 1.0])
    radio = radio_map(config, boxes, losses, np.array([[0, 0, 0], [10, 10, 5]], float), transmitter, cells=100)
    assert radio.power_dbm.shape == (100, 100) and radio.height_m == 1.0
    # (receiver near, walls crossed by hand, their loss): in the first room; behind wall_a; behind both
    # (straight and slanting: y = 4 and 2.5 where it meets them); past wall_a's end (y > 9.3 at x = 3).
    cases = [((2.0, 5.0), 0, 0.0), ((1.2, 5.1), 0, 0.0), ((4.5, 5.0), 1, 5.0), ((8.0, 5.0), 2, 14.0),
             ((8.0, 1.5), 2, 14.0), ((3.3, 9.95), 0, 0.0)]
    for (px, py), walls, loss in cases:
        i, j = int(np.argmin(np.abs(radio.y - py))), int(np.argmin(np.abs(radio.x - px)))
        x, y = radio.x[j], radio.y[i]
        d = math.hypot(x - 1.0, y - 5.0)
        reference = config.reference_loss_db  # P.1238 at 2.44 GHz: 39.7 dB
        expected = 0.0 - (reference + 10 * 3.0 * math.log10(max(d, 1.0)) + loss)  # 802.15.4: 0 dBm, n = 3
        assert config.tx_power_dbm == 0.0 and config.path_loss_exponent == 3.0
        assert reference == pytest.approx(39.7, abs=0.1)
        assert radio.walls[i, j] == walls, (px, py)
        assert radio.power_dbm[i, j] == pytest.approx(expected, abs=1e-9), (px, py)
    # The contour's power: the reference packet's delivery is 50 % there.
    sensitivity = reference_sensitivity_dbm(config)
    assert radio.sensitivity_dbm == sensitivity
    from sim.radio.link import RadioChannel

    channel = RadioChannel(config, boxes, losses, 2.5, np.random.default_rng(0))
    snr = sensitivity - config.noise_floor_dbm
    assert float(channel.delivery_at_snr(np.array(snr))) == pytest.approx(0.5, abs=1e-3)
    assert -100.0 < sensitivity < -90.0


def test_robots_are_named_as_the_world_names_them(tmp_path):
    write_scene(tmp_path, SCENE)
    scenario = load(str(write_scenario(tmp_path, SCENARIO)))
    assert transmitter_of(scenario, None)[:2] == (0, "quad0")
    index, name, position = transmitter_of(scenario, "ground0")
    assert (index, name) == (1, "ground0") and 0.0 < position[2] < 0.1  # the wheel-contact height
    assert transmitter_of(scenario, "1")[1] == "ground0"


def test_the_png_is_written_readable_and_replaced_only_when_tether_wrote_it(tmp_path, capsys):
    write_scene(tmp_path, SCENE)
    scenario = write_scenario(tmp_path, SCENARIO)
    out = tmp_path / "maps" / "map.png"
    assert main(["radiomap", str(scenario), "--out", str(out)]) == 0
    with Image.open(out) as image:
        assert image.size == (round(FIGURE_SIZE_IN[0] * FIGURE_DPI), round(FIGURE_SIZE_IN[1] * FIGURE_DPI))
        pixels = np.asarray(image.convert("RGB"))
    assert pixels.std() > 20 and len(np.unique(pixels.reshape(-1, 3), axis=0)) > 200  # not blank
    assert main(["radiomap", str(scenario), "--out", str(out), "--from", "ground0",
                 "--set", "radio.tx_power_dbm=-30"]) == 0  # its own file: replaced
    foreign = tmp_path / "photo.png"
    Image.new("RGB", (4, 4)).save(foreign)
    before = foreign.read_bytes()
    capsys.readouterr()
    assert main(["radiomap", str(scenario), "--out", str(foreign)]) == 2
    assert "not a radio map tether wrote" in capsys.readouterr().err
    assert foreign.read_bytes() == before


@pytest.mark.parametrize("args, expected", [
    (["--from", "quad7"], "--from: no robot 'quad7'"),
    (["--from", "5"], "--from: no robot '5'"),
    (["--set", "radio.colour=3"], "radio.colour: unknown key"),
    (["--set", "radio.tx_power_dbm=loud"], "radio.tx_power_dbm"),
    (["--set", 'radio.preset="morse"'], "unknown radio preset 'morse'"),
    (["--out", "map.jpg"], "--out: must name a .png file"),
])
def test_bad_input_is_one_line_exit_2_and_nothing_written(tmp_path, capsys, args, expected):
    write_scene(tmp_path, SCENE)
    scenario = write_scenario(tmp_path, SCENARIO)
    out = tmp_path / "out" / "map.png"
    full = ["radiomap", str(scenario), *args]
    if "--out" not in args:
        full += ["--out", str(out)]
    assert main(full) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0], err
    assert not (tmp_path / "out").exists() and not (tmp_path / "map.jpg").exists()


def test_the_ideal_radio_maps_the_ieee802154_figures_with_a_note(tmp_path, capsys):
    write_scene(tmp_path, SCENE)
    scenario = write_scenario(tmp_path, SCENARIO.replace('preset = "ieee802154"', 'preset = "ideal"'))
    out = tmp_path / "ideal.png"
    assert main(["radiomap", str(scenario), "--out", str(out)]) == 0
    assert "ieee802154 figures" in capsys.readouterr().err and out.exists()


@pytest.mark.parametrize("preset", ["ieee802154", "ideal"])
def test_the_recording_holds_the_radio_map_of_robot_0_under_a_real_radio(tmp_path, preset):
    from helpers import rrd_chunks
    from tether.radiomap import RECORDING_CELLS
    from tether.runner import run

    write_scene(tmp_path, SCENE)
    scenario = load(str(write_scenario(tmp_path, SCENARIO.replace('preset = "ieee802154"', f'preset = "{preset}"'))),
                    duration_s=0.1)
    run(scenario, tmp_path / "out", rrd=True)
    chunks = rrd_chunks(tmp_path / "out" / "run.rrd")
    if preset == "ideal":
        assert "/world/radio_map" not in chunks
        return
    (chunk,) = chunks["/world/radio_map"]
    assert chunk.is_static
    batch = chunk.to_record_batch()
    vertices = np.array(batch.column("Mesh3D:vertex_positions").to_pylist()[0])
    colours = batch.column("Mesh3D:vertex_colors").to_pylist()[0]
    assert vertices.shape == (RECORDING_CELLS ** 2, 3) and len(colours) == len(vertices)
    assert np.all(vertices[:, 2] < 0.05)  # on the floor
    assert len(set(colours)) > 50  # coloured by power, not one colour
    legend = chunks["/legend"][0].to_record_batch().column("TextDocument:text").to_pylist()[0]
    assert "mean received power from quad0" in str(legend)
