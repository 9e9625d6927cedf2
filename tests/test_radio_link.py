"""The radio channel in the simulation: the [radio] table, walls from the scene, the per-tick link state."""

from __future__ import annotations

import math
import textwrap
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from sim.config import ConfigError, build
from sim.geometry import Boxes
from sim.radio.config import RadioConfig
from sim.radio.link import RadioChannel, _shadowing_step_at
from sim.radio.presets import IEEE802154
from sim.radio.walls import walls_crossed
from sim.scenario import load, to_scenario_table, from_table
from sim.types import Links
from sim.world import extract_obstacles, obstacle_wall_losses
from tether.runner import build_simulation, run

# Three parallel walls (the last one turned 30 degrees about z) and a pillar; the pillar has its own loss.
WALLS_SCENE = """
<mujoco model="three_walls">
  <custom>
    <numeric name="tether_bounds" data="0 0 0 10 10 5"/>
    <numeric name="tether_wall_loss_db" data="5"/>
    <numeric name="tether_wall_loss_db/pillar" data="12"/>
  </custom>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.05" pos="5 5 0" group="0"/>
    <geom name="wall_a" type="box" size="0.05 4 2" pos="2 5 2" group="0"/>
    <geom name="wall_b" type="box" size="0.1 4 2" pos="4 5 2" group="0"/>
    <geom name="wall_c" type="box" size="0.05 4 2" pos="6 5 2" euler="0 0 30" group="0"/>
    <geom name="pillar" type="box" size="0.3 0.3 2" pos="8.5 8.5 2" group="0"/>
    <geom name="decor" type="box" size="0.3 0.3 0.3" pos="8.5 1.5 1" group="1"/>
  </worldbody>
</mujoco>
"""


def _scene(xml: str = WALLS_SCENE):
    model = mujoco.MjModel.from_xml_string(textwrap.dedent(xml))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return extract_obstacles(model, data), obstacle_wall_losses(model)


def _sampled_count(boxes: Boxes, start, end, samples: int = 20001) -> int:
    """Boxes that some of ``samples`` points along the segment lie inside."""
    points = start + np.linspace(0.0, 1.0, samples)[:, None] * (end - start)
    local = boxes.to_local(points)  # (P, K, 3)
    inside = np.all(np.abs(local) <= boxes.half_sizes[None], axis=-1)
    return int(np.count_nonzero(inside.any(axis=0)))


def test_walls_crossed_match_a_dense_sampling_of_the_segment():
    boxes, losses = _scene()
    # the floor (a slab below z = 0) has no figure of its own: the scene's default applies
    assert losses.tolist() == [5.0, 5.0, 5.0, 5.0, 12.0]
    cases = [((0.5, 5.0, 1.0), (1.5, 7.0, 1.0), 0, 0.0),  # before the first wall
             ((1.0, 5.0, 1.0), (3.0, 4.0, 1.5), 1, 5.0),  # through wall_a
             ((1.0, 5.0, 1.0), (7.5, 5.5, 1.0), 3, 15.0),  # through a, b and the turned c
             ((7.5, 7.5, 1.0), (9.5, 9.5, 1.0), 1, 12.0),  # through the pillar
             ((4.0, 5.0, 1.0), (4.5, 5.0, 1.0), 1, 5.0)]  # starts inside wall_b: it counts
    starts = np.array([c[0] for c in cases], dtype=float)
    ends = np.array([c[1] for c in cases], dtype=float)
    crossed = walls_crossed(starts, ends, boxes, losses)
    for (start, end, count, loss), got, got_loss in zip(cases, crossed.count, crossed.loss_db):
        assert got == count == _sampled_count(boxes, np.array(start), np.array(end)), (start, end)
        assert got_loss == pytest.approx(loss)


def test_wall_loss_numerics_are_checked():
    bad_value = WALLS_SCENE.replace('name="tether_wall_loss_db" data="5"', 'name="tether_wall_loss_db" data="-1"')
    with pytest.raises(ConfigError, match="tether_wall_loss_db"):
        _scene(bad_value)
    no_geom = WALLS_SCENE.replace("tether_wall_loss_db/pillar", "tether_wall_loss_db/decor")
    with pytest.raises(ConfigError, match="names no static obstacle geom"):
        _scene(no_geom)


_coordinate = st.floats(-3.0, 3.0, allow_nan=False)
_point = st.tuples(_coordinate, _coordinate, _coordinate)


@st.composite
def _boxes(draw):
    k = draw(st.integers(1, 5))
    centers = np.array([draw(_point) for _ in range(k)])
    halves = np.array([draw(st.tuples(*[st.floats(0.05, 1.0)] * 3)) for _ in range(k)])
    rotations = []
    for _ in range(k):
        a, b = draw(st.floats(-math.pi, math.pi)), draw(st.floats(-math.pi, math.pi))
        rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
        rotations.append(rz @ rx)
    return Boxes(centers, halves, np.array(rotations))


@settings(max_examples=60, deadline=None)
@given(_boxes(), _point, _point, st.floats(1.0, 3.0))
def test_walls_are_symmetric_and_never_fewer_on_a_longer_segment(boxes, start, end, stretch):
    start, end = np.array(start), np.array(end)
    losses = np.arange(1.0, len(boxes) + 1)
    forward = walls_crossed(start[None], end[None], boxes, losses)
    backward = walls_crossed(end[None], start[None], boxes, losses)
    assert forward.count[0] == backward.count[0]
    assert forward.loss_db[0] == pytest.approx(backward.loss_db[0])
    longer = walls_crossed(start[None], (start + stretch * (end - start))[None], boxes, losses)
    assert longer.count[0] >= forward.count[0]
    assert longer.loss_db[0] >= forward.loss_db[0] - 1e-12


def test_walls_of_pairs_are_the_walls_of_their_segments():
    from sim.radio.walls import SceneWalls

    boxes, losses = _scene()
    walls = SceneWalls(boxes, np.where(np.isnan(losses), 3.4, losses))
    positions = np.random.default_rng(2).uniform([0.0, 0.0, 0.0], [10.0, 10.0, 4.5], (25, 3))
    first, second = np.triu_indices(25, 1)
    pairs, segments = walls.crossed_pairs(positions, first, second), walls.crossed(positions[first], positions[second])
    assert pairs.count.max() >= 3
    np.testing.assert_array_equal(pairs.count, segments.count)
    np.testing.assert_array_equal(pairs.loss_db, segments.loss_db)


def test_the_preset_fills_the_keys_and_every_key_overrides():
    ideal = RadioConfig()
    assert ideal.is_ideal and ideal.delivery_threshold == 0.5
    radio = build(RadioConfig, {"preset": "ieee802154", "wall_loss_db": 6.9, "fading": "rician", "rician_k_db": 6.0})
    assert radio.tx_power_dbm == IEEE802154.tx_power_dbm
    assert radio.noise_floor_dbm == pytest.approx(IEEE802154.noise_floor_dbm)
    assert (radio.wall_loss_db, radio.fading, radio.rician_k_db) == (6.9, "rician", 6.0)
    scenario = load("connected-office", ['radio.preset="nrf24"', "radio.shadowing_correlation_s=inf"])
    again = from_table(to_scenario_table(scenario), scenario.source)  # a saved scenario reads back the same
    assert again.radio == scenario.radio and again.radio.bitrate_bps == 2e6
    with pytest.raises(ConfigError, match="radio.reference_payload_bytes"):
        load("connected-office", ['radio.preset="nrf24"', "radio.reference_payload_bytes=100"])


def test_spawning_the_radio_stream_leaves_the_parent_draws_unchanged():
    parent, untouched = np.random.default_rng(7), np.random.default_rng(7)
    child = parent.spawn(1)[0]
    child.standard_normal(100)
    assert np.array_equal(parent.random(20), untouched.random(20))


def _ticks(scenario, ticks: int):
    simulation = build_simulation(scenario)
    frames = []
    for _ in range(ticks):
        frame, healthy = simulation.tick(decorations_wanted=False)
        assert healthy
        frames.append(frame)
    return frames


def test_under_ideal_the_delivery_is_the_adjacency_on_a_run():
    frames = _ticks(load("connected-office", ["robots.0.count=10"], duration_s=1.0), 60)
    for frame in frames[::5]:
        radio, links = frame.observation.radio, frame.observation.links
        assert np.array_equal(radio.delivery, links.adjacency.astype(float))
        assert np.array_equal(radio.comm_adjacency, links.adjacency)
        assert np.all(np.isnan(radio.rx_power_dbm)) and not radio.delivery.flags.writeable


def test_the_communication_graph_from_the_pairs_is_the_delivery_matrix_at_the_threshold():
    """``RadioState.comm_adjacency``, read from the pairs, is ``delivery >= delivery_threshold`` of the
    delivery matrix, under a real radio (some pairs below the threshold) and read before or after it."""
    frames = _ticks(load("intermittent-8", ['radio.preset="ieee802154"', "radio.tx_power_dbm=-60"], duration_s=1.0),
                    30)
    for k, frame in enumerate(frames[::3]):
        radio = frame.observation.radio
        first = radio.comm_adjacency if k % 2 else None
        expected = radio.delivery >= radio.delivery_threshold
        assert np.array_equal(radio.comm_adjacency, expected) and not radio.comm_adjacency.flags.writeable
        assert first is None or first is radio.comm_adjacency
    pairs = np.concatenate([frame.observation.radio.comm_adjacency[~np.eye(8, dtype=bool)] for frame in frames])
    assert pairs.any() and not pairs.all()  # linked pairs and pairs below the threshold


def test_under_ideal_nothing_is_drawn():
    simulation = build_simulation(load("connected-office", ["robots.0.count=6"], duration_s=1.0))
    before = simulation.radio.rng.bit_generator.state
    for _ in range(5):
        frame, _ = simulation.tick()
        frame.observation.radio.delivery
    assert simulation.radio.rng.bit_generator.state == before


def _indoor_channel(**keys) -> RadioChannel:
    scenario = load("intermittent-4", [f"radio.{key}={value!r}" if isinstance(value, str) else f"radio.{key}={value}"
                                       for key, value in {"preset": "ieee802154", **keys}.items()])
    simulation = build_simulation(scenario)
    world = simulation.world
    return RadioChannel(scenario.radio, world.obstacles, world.wall_loss_db, 2.5, np.random.default_rng(0))


def _links(positions: np.ndarray) -> Links:
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    n = len(positions)
    return Links(distance, np.ones((n, n), bool), np.zeros((n, n), bool))


def test_under_ieee802154_delivery_falls_with_distance_and_with_walls():
    # Weak transmitter and no shadowing: the indoor scene's 10 m span the whole PER curve.
    channel = _indoor_channel(tx_power_dbm=-45.0, shadowing_sigma_db=0.0)
    # In the south-east room's open south half (y < 5), along x: robot 0 at x = 0.5, the others further.
    along = np.array([[0.5, 4.0, 1.0]] + [[0.5 + d, 4.0, 1.0] for d in (1.0, 2.0, 2.5, 3.0, 3.5)])
    state = channel.state(0.0, along, _links(along))
    delivery = state.delivery[0, 1:]
    assert np.all(np.diff(delivery) <= 0) and delivery[0] > 0.99 and delivery[-1] < 0.01
    assert np.all(np.diff(state.rx_power_dbm[0, 1:]) < 0)
    # The same 3 m with the wall at y = 5 between them, against 3 m in the open.
    pairs = np.array([[1.0, 3.5, 1.0], [1.0, 6.5, 1.0], [0.5, 4.0, 1.0], [3.5, 4.0, 1.0]])
    state = channel.state(0.0, pairs, _links(pairs))
    assert state.walls[0, 1] == 1 and state.walls[2, 3] == 0
    assert state.wall_loss_db[0, 1] == pytest.approx(IEEE802154.path_loss.loss_per_wall_db)
    assert state.rx_power_dbm[0, 1] == pytest.approx(state.rx_power_dbm[2, 3] - state.wall_loss_db[0, 1])
    assert state.delivery[0, 1] < state.delivery[2, 3]
    np.testing.assert_array_equal(state.delivery, state.delivery.T)


def test_the_channel_is_the_formulas_chain_exactly():
    """Pairs whose delivery is certain (exactly 0 or 1) skip the BER; the shadowing's AR(1) keeps its
    coefficients: both give channel.py's numbers to the bit."""
    from sim.radio import channel as formulas

    channel = _indoor_channel(tx_power_dbm=-45.0)
    positions = np.random.default_rng(1).uniform([0.3, 0.3, 0.5], [9.7, 9.7, 2.0], (30, 3))
    previous = channel.state(0.0, positions, _links(positions)).shadowing_db.copy()
    state = channel.state(0.01, positions, _links(positions))
    off = ~np.eye(30, dtype=bool)
    assert 0.0 < state.delivery[off].mean() < 1.0
    np.testing.assert_array_equal(state.delivery[off], channel.delivery_at_snr(state.snr_db[off]))
    replay = np.random.default_rng(0)
    replay.standard_normal(435)  # the first tick's stationary draw
    expected = formulas.shadowing_step_db(previous[np.triu_indices(30, 1)], 0.01, 4.0, 2.0, rng=replay)
    np.testing.assert_array_equal(state.shadowing_db[np.triu_indices(30, 1)], expected)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), exponent=st.floats(1.0, 8.0), reference_loss_db=st.floats(0.0, 200.0),
       tx_power_dbm=st.floats(-60.0, 40.0), noise_floor_dbm=st.floats(-200.0, 0.0),
       preset=st.sampled_from(["ieee802154", "nrf24", "wifi"]))
def test_pair_figures_are_the_formulas_chain_to_the_bit(seed, exponent, reference_loss_db, tx_power_dbm,
                                                         noise_floor_dbm, preset):
    """The compiled pass over the pairs against channel.py's functions, the reference they replace."""
    from sim.radio import channel as formulas

    overrides = {"path_loss_exponent": exponent, "reference_loss_db": reference_loss_db,
                 "tx_power_dbm": tx_power_dbm, "noise_floor_dbm": noise_floor_dbm}
    config = build(RadioConfig, {"preset": preset, **overrides}, "radio")
    boxes, _ = _scene()
    channel = RadioChannel(config, boxes, None, 10.0, np.random.default_rng(0))
    rng = np.random.default_rng(seed)
    pairs = 300
    distance = np.concatenate([rng.uniform(0.0, 200.0, pairs - 3), [0.0, 0.5, 1.0]])
    walls = rng.integers(0, 5, pairs) * rng.uniform(0.0, 10.0, pairs)
    shadowing = rng.normal(0.0, 8.0, pairs)
    path_loss = formulas.log_distance_path_loss_db(distance, exponent, reference_loss_db, total_wall_loss_db=walls)
    rx = formulas.received_power_dbm(tx_power_dbm, path_loss, shadowing)
    snr = formulas.snr_db(rx, noise_floor_dbm)
    got = channel.pair_figures(distance, walls, shadowing)
    np.testing.assert_array_equal(got["rx_power_dbm"], rx)
    np.testing.assert_array_equal(got["snr_db"], snr)
    np.testing.assert_array_equal(got["shadowing_db"], shadowing)
    np.testing.assert_array_equal(got["delivery"], channel.delivery_at_snr(snr))


def _radio_run(preset: str, seed: int, ticks: int = 40):
    scenario = load("connected-office", ["robots.0.count=6", f'radio.preset="{preset}"'], seed=seed, duration_s=1.0)
    return _ticks(scenario, ticks)


def test_same_seed_same_delivery_and_the_radio_never_moves_the_robots():
    first, second = _radio_run("ieee802154", 3), _radio_run("ieee802154", 3)
    other_seed = _radio_run("ieee802154", 4)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a.observation.radio.delivery, b.observation.radio.delivery)
        np.testing.assert_array_equal(a.observation.radio.shadowing_db, b.observation.radio.shadowing_db)
    assert not np.array_equal(first[-1].observation.radio.shadowing_db, other_seed[-1].observation.radio.shadowing_db)
    # A strategy that sends nothing moves exactly as under ideal: the radio's stream is spawned, not shared.
    silent = _ticks(load("hover", ['radio.preset="ieee802154"'], seed=3, duration_s=1.0), 40)
    silent_ideal = _ticks(load("hover", [], seed=3, duration_s=1.0), 40)
    for a, b in zip(silent, silent_ideal):
        np.testing.assert_array_equal(a.observation.position, b.observation.position)
        np.testing.assert_array_equal(a.commands.position, b.commands.position)
    # Shadowing is an AR(1) with correlation exp(-dt / tau): successive ticks stay close.
    steps = np.diff([f.observation.radio.shadowing_db[0, 1] for f in first])
    assert np.all(np.abs(steps) < 4.0 * 4.0 * math.sqrt(1 - math.exp(-2 * 0.01 / 2.0)))


def test_metrics_report_both_graphs_lambda2_and_the_delivery():
    scenario = load("connected-office", ["robots.0.count=6", 'radio.preset="ieee802154"',
                                         "radio.tx_power_dbm=-40"], duration_s=0.3)
    metrics = run(scenario).metrics
    for key in ("sensing_lambda2_mean", "sensing_lambda2_min", "comm_lambda2_mean", "comm_lambda2_min",
                "radio_delivery_mean"):
        assert metrics[key] is not None and metrics[key] >= 0, key
    assert metrics["comm_lambda2_min"] <= metrics["comm_lambda2_mean"]
    assert 0.0 <= metrics["radio_delivery_mean"] <= 1.0


def test_graph_lambda2_of_known_graphs():
    from sim.observers import graph_lambda2

    path = np.zeros((3, 3), bool)
    path[0, 1] = path[1, 0] = path[1, 2] = path[2, 1] = True
    assert graph_lambda2(path) == pytest.approx(1.0)
    complete = ~np.eye(5, dtype=bool)
    assert graph_lambda2(complete) == pytest.approx(5.0)
    split = np.zeros((4, 4), bool)
    split[0, 1] = split[1, 0] = split[2, 3] = split[3, 2] = True
    assert graph_lambda2(split) == pytest.approx(0.0, abs=1e-12)
    assert graph_lambda2(np.zeros((1, 1), bool)) == 0.0


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 12), seed=st.integers(0, 2**32 - 1), density=st.floats(0.0, 1.0))
def test_lambda2_from_pairs_is_the_matrix_graphs(n, seed, density):
    """The link metrics read the communication graph from the pairs; the value is the (N, N) graph's."""
    from sim import observers

    first, second = np.triu_indices(n, 1)
    edges = np.random.default_rng(seed).random(len(first)) < density
    adjacency = np.zeros((n, n), bool)
    adjacency[first, second] = adjacency[second, first] = edges
    observers._LAMBDA2_SEEN.clear()
    from_pairs = observers.pairs_graph_lambda2(n, (first, second), edges)
    observers._LAMBDA2_SEEN.clear()
    assert from_pairs == observers.graph_lambda2(adjacency)
    assert observers.pairs_graph_lambda2(n, (first, second), edges) == from_pairs  # remembered


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), pairs=st.integers(1, 700),
       steps=st.lists(st.sampled_from([0.01, 0.02, 0.02 + 1e-12, 0.05, 0.3]), min_size=1, max_size=8))
def test_the_compiled_shadowing_step_is_numpys(seed, pairs, steps):
    """The AR(1) shadowing step in one compiled pass (``_shadowing_step_at``) draws what
    ``Generator.standard_normal`` draws and rounds as the numpy expression does: the same values and the
    same generator state after every step, whatever the step lengths."""
    config = build(RadioConfig, {"preset": "ieee802154"}, "radio")
    boxes, _ = _scene()
    compiled, plain = (RadioChannel(config, boxes, None, 10.0, np.random.default_rng(seed)) for _ in range(2))
    plain._rng_pointers = (plain.rng, None)  # the numpy expression
    time_s = 0.0
    for dt in [0.0, *steps]:
        time_s += dt
        assert np.array_equal(compiled._advance_shadowing(time_s, pairs), plain._advance_shadowing(time_s, pairs))
        assert compiled.rng.bit_generator.state == plain.rng.bit_generator.state
    assert compiled._rng_pointers[1] is not None or getattr(_shadowing_step_at, "overloads", None) is None



@settings(max_examples=60, deadline=None)
@given(_boxes(), st.integers(2, 9), st.integers(0, 2**32 - 1), st.sampled_from(["ieee802154", "nrf24", "wifi"]),
       st.floats(-100.0, -60.0), st.sampled_from([0.05, 0.3, 0.9, 1.0]))
def test_the_walls_and_figures_in_one_call_are_the_separate_passes(boxes, n, seed, preset, carrier_sense_dbm,
                                                                   threshold):
    """``RadioChannel._walls_and_figures``' one compiled call gives what ``SceneWalls.crossed_pairs``,
    ``pair_figures`` and ``sim.radio.bus.link_from_pairs`` give one after the other, bit for bit."""
    from sim.radio.bus import link_from_pairs

    config = build(RadioConfig, {"preset": preset, "carrier_sense_dbm": carrier_sense_dbm,
                                 "delivery_threshold": threshold}, "radio")
    channel = RadioChannel(config, boxes, None, 5.0, np.random.default_rng(0))
    rng = np.random.default_rng(seed)
    positions = rng.uniform(-4.0, 4.0, (n, 3))
    positions[0] = positions[1]  # two robots at one place: a distance below the reference's 1 m
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    first, second = channel.pairs(n)
    shadowing = rng.normal(0.0, 8.0, len(first))
    got, wall_pairs = channel._walls_and_figures(positions, first, second, distance, shadowing)
    walls = channel.walls.crossed_pairs(positions, first, second)
    np.testing.assert_array_equal(wall_pairs["count"], walls.count)
    np.testing.assert_array_equal(wall_pairs["loss_db"], walls.loss_db)
    expected = channel.graph_figures(channel.pair_figures(distance[first, second], walls.loss_db, shadowing),
                                     distance[first, second], n)
    for key in ("rx_power_dbm", "snr_db", "shadowing_db", "delivery", "linked", "in_range", "comm_adjacency"):
        np.testing.assert_array_equal(got[key], expected[key])
    assert not got["comm_adjacency"].flags.writeable
    link = link_from_pairs(n, (first, second), expected["snr_db"], expected["rx_power_dbm"], carrier_sense_dbm)
    snr, sense = got["link_matrices"]
    np.testing.assert_array_equal(snr, link.snr_db)
    np.testing.assert_array_equal(sense, link.carrier_sense)
    assert not snr.flags.writeable and sense.dtype == bool


@settings(max_examples=20, deadline=None)
@given(_boxes(), st.integers(2, 9), st.integers(0, 2**32 - 1),
       st.lists(st.sampled_from([0.0, 0.01, 0.02, 0.3]), min_size=1, max_size=6))
def test_a_ticks_channel_in_one_call_is_the_step_by_step_channel(boxes, n, seed, steps):
    """``RadioChannel.state`` takes the shadowing's step inside its one compiled call; the path faults take
    (the step alone, then the figures of the pairs; here with a blackout of 0 dB) gives the same figures,
    walls and shadowing tick after tick, and leaves the generator in the same state."""
    config = build(RadioConfig, {"preset": "ieee802154"}, "radio")
    fused, stepwise = (RadioChannel(config, boxes, None, 5.0, np.random.default_rng(seed)) for _ in range(2))
    rng = np.random.default_rng(seed + 1)
    first, _ = fused.pairs(n)
    no_blackout = np.zeros(len(first))
    time_s = 0.0
    for dt in [0.0, *steps]:
        time_s += dt
        positions = rng.uniform(-4.0, 4.0, (n, 3))
        links = SimpleNamespace(distance=np.linalg.norm(positions[:, None] - positions[None], axis=-1))
        one = fused.state(time_s, positions, links)
        other = stepwise.state(time_s, positions, links, extra_loss_db=no_blackout)
        for key in ("rx_power_dbm", "snr_db", "shadowing_db", "delivery", "linked", "in_range", "comm_adjacency"):
            np.testing.assert_array_equal(one.channel_pairs[key], other.channel_pairs[key])
        for key in ("count", "loss_db"):
            np.testing.assert_array_equal(one.wall_pairs[key], other.wall_pairs[key])
        assert fused.rng.bit_generator.state == stepwise.rng.bit_generator.state
