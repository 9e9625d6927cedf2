"""The message bus in the loop: Commands.outbox in, the next Observation.inbox out, radio_* in metrics.json."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np
import pytest

import tether.catalog  # noqa: F401 (registers the built-in scenarios)
from controllers.lowlevel.actuation import LowLevelControl
from sim.loop import Simulation
from sim.radio.bus import Message
from sim.scenario import StrategyConfig, load
import sim.strategy
from sim.strategy import Strategy, StrategyKind
from sim.types import Commands

# The hover scene with quadrotor 1 moved next to quadrotor 0 (1 m, line of sight); quadrotor 2 is far, walls between.
NEAR = 'robots.0.starts=[[1.0, 4.0, 1.0], [2.0, 4.0, 1.0], [8.8, 5.5, 1.0], [5.0, 6.0, 1.2]]'
IEEE = 'radio.preset="ieee802154"'
TICKS = 30
SIZE_BYTES = 20


@dataclass(frozen=True)
class ChatterParams:
    sender: int = 0
    receiver: int = 1
    send: bool = True


class Chatter(Strategy):
    """Holds every robot at its start; robot ``sender`` sends its tick number to ``receiver`` every tick."""

    def __init__(self, params: ChatterParams = ChatterParams()):
        self.params = params
        self.inboxes: list = []

    def reset(self, world, initial, rng) -> None:
        self.hold = np.array(initial.position)
        self.inboxes = []

    def step(self, observation) -> Commands:
        self.inboxes.append(observation.inbox)
        n = len(self.hold)
        zeros = np.zeros((n, 3))
        p = self.params
        outbox = (Message("test", p.sender, (p.receiver,), observation.tick, SIZE_BYTES),) if p.send else ()
        return Commands(self.hold, zeros, zeros, np.zeros(n), outbox=outbox)



def simulate(overrides: list[str], params: ChatterParams = ChatterParams(), ticks: int = TICKS, seed: int = 0):
    scenario = load("hover", [NEAR, *overrides], seed=seed, duration_s=1.0)
    sim = Simulation(scenario, lambda _: Chatter(params), LowLevelControl)
    frames = [sim.tick()[0] for _ in range(ticks)]
    return sim, frames


def arrivals(sim, robot: int):
    """(tick seen, delivery) of every delivery at ``robot``."""
    return [(tick, d) for tick, inbox in enumerate(sim.strategy.inboxes) for d in inbox[robot]]


def test_ideal_delivers_at_the_next_tick_with_latency_zero():
    sim, frames = simulate([])
    got = arrivals(sim, 1)
    assert [tick for tick, _ in got] == list(range(1, TICKS))
    assert all(d.message.payload == tick - 1 and d.latency_s == 0.0 and d.receiver == 1 for tick, d in got)
    assert all(len(inbox) == sim.world.n_robots for inbox in sim.strategy.inboxes)
    assert not any(inbox[r] for inbox in sim.strategy.inboxes for r in range(sim.world.n_robots) if r != 1)
    assert sim.strategy.inboxes[0] == ((),) * sim.world.n_robots
    assert frames[-1].scalars["radio_tick_delivery_ratio"] == 1.0
    assert frames[-1].scalars["radio_tick_latency_mean_s"] == 0.0
    summary = sim.radio_summary()
    assert summary["radio_packets_sent"] == TICKS and summary["radio_delivery_ratio"] == 1.0
    assert summary["radio_test_bytes_sent"] == TICKS * SIZE_BYTES


def test_ideal_needs_a_link():
    sim, _ = simulate([], ChatterParams(receiver=2))  # 7.9 m away, walls between
    assert not arrivals(sim, 2)
    assert sim.radio_summary()["radio_delivery_ratio"] == 0.0


def test_ieee802154_latency_is_the_airtime():
    sim, frames = simulate([IEEE, "radio.fading=\"none\""])
    got = arrivals(sim, 1)
    assert len(got) == TICKS - 1  # 1 m, no fading: every frame arrives
    airtime = float(sim.bus.params.airtime_s(SIZE_BYTES))
    assert airtime > 0
    assert all(tick == d.message.payload + 1 and d.latency_s == pytest.approx(airtime) for tick, d in got)
    assert frames[-1].scalars["radio_tick_latency_mean_s"] == pytest.approx(airtime)


def test_ieee802154_far_behind_walls_loses_messages():
    sim, _ = simulate([IEEE, "radio.tx_power_dbm=-40.0"], ChatterParams(receiver=2))
    got = arrivals(sim, 2)
    assert len(got) < TICKS - 1
    assert all(d.latency_s > 0 for _, d in got)
    summary = sim.radio_summary()
    assert summary["radio_packets_sent"] == TICKS and summary["radio_delivery_ratio"] < 1.0


def test_same_seed_same_inboxes():
    runs = [simulate([IEEE, "radio.tx_power_dbm=-40.0"], ChatterParams(receiver=2), seed=3)[0] for _ in range(2)]
    first, second = ([(t, d.message.payload, d.arrival_s) for t, d in arrivals(sim, 2)] for sim in runs)
    assert first == second


def test_silent_ieee802154_moves_like_ideal():
    scenario = dict(seed=0, duration_s=1.0)
    trajectories = []
    for overrides in ([], [IEEE]):
        sim = Simulation(load("hover", overrides, **scenario), _waypoints, LowLevelControl)
        trajectories.append(np.array([sim.tick()[0].observation.position for _ in range(40)]))
        assert sim.radio_summary()["radio_packets_sent"] == 0
    assert np.array_equal(*trajectories)


def _waypoints(params):
    from sim.strategy import build_strategy

    return build_strategy("waypoints", params)


def test_metrics_json_has_the_radio_keys(tmp_path, monkeypatch):
    from tether.runner import run

    # A test-only kind, registered for this test alone (the contract tests go through every registered kind).
    monkeypatch.setitem(sim.strategy._KINDS, "test_chatter",
                        StrategyKind(ChatterParams, Chatter, "test only: one message a tick"))

    scenario = load("hover", [NEAR], seed=0, duration_s=0.2)
    for name, params in (("sent", ChatterParams()), ("silent", ChatterParams(send=False))):
        result = run(dataclasses.replace(scenario, strategy=StrategyConfig("test_chatter", params)), tmp_path / name)
        metrics = json.loads((tmp_path / name / "metrics.json").read_text())
        for key in ("radio_packets_sent", "radio_packets_delivered", "radio_delivery_ratio", "radio_bytes_sent",
                    "radio_latency_mean_s", "radio_latency_p95_s", "radio_airtime_max_share"):
            assert key in metrics, key
        assert "not finite" not in metrics["message"]
        if name == "sent":
            assert metrics["radio_packets_sent"] == 20 and metrics["radio_delivery_ratio"] == 1.0
            assert metrics["radio_test_packets_sent"] == 20 and metrics["radio_latency_p95_s"] == 0.0
        else:
            assert metrics["radio_packets_sent"] == 0 and metrics["radio_delivery_ratio"] is None
            assert metrics["radio_latency_mean_s"] is None
        assert result.status.finished


def test_bus_parameters_and_carrier_sense_from_the_radio_table():
    from sim.config import build
    from sim.radio.config import RadioConfig

    radio = build(RadioConfig, {"preset": "ieee802154"})
    assert radio.carrier_sense_dbm == -98.0  # the CC2420's -95 dBm sensitivity - 3 dB
    params = build(RadioConfig, {"preset": "ieee802154", "bitrate_bps": 125e3, "fading": "rician",
                                 "rician_k_db": 10.0, "carrier_sense_dbm": -85.0}).bus_parameters
    assert (params.bitrate_bps, params.fading_model, params.rician_k) == (125e3, "rician", pytest.approx(10.0))
    assert build(RadioConfig, {}).bus_parameters.is_ideal


def test_an_idle_bus_step_reads_no_link():
    from sim.radio.bus import BusParameters, MessageBus
    from sim.radio.presets import IEEE802154

    bus = MessageBus(BusParameters.from_preset(IEEE802154), np.random.default_rng(0), 0.01, robot_count=3)
    assert bus.idle and bus.step(0.0, None) == [[], [], []]
    assert np.isnan(bus.last_tick.delivery_ratio) and bus.summary()["radio_packets_sent"] == 0
