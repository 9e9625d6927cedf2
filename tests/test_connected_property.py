"""Property test: random target layouts for 10 quadrotors in the indoor office.

Hypothesis draws which robots get targets and where (free space, reachable),
the run flies real MuJoCo quadrotors for a short while, and the continuous-connectivity paper's
invariants are checked on every control tick: lambda2 > lambda2_min, virtual
points farther than R_c apart and than R_o from obstacles, at most one prime
traveler. The default set tries a few layouts; ``-m slow`` tries more, longer.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from connected_helpers import run_checked
from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.mission import shared_planner
from sim.scenario import load
from sim.world import build_world

SCENARIO = "connected-office"


def _planner():
    scenario = load(SCENARIO)
    world = build_world(scenario, np.zeros((0, 3)), [])
    return shared_planner(world.obstacles, world.bounds, ConnectedParams())


PLANNER = _planner()
point = st.tuples(st.floats(0.7, 9.3), st.floats(0.7, 9.3), st.floats(0.7, 4.3))


@st.composite
def layouts(draw, max_targets: int = 3):
    """Target lists for robots 0..9: each robot 0 to ``max_targets`` free targets."""
    lists = []
    for _ in range(10):
        count = draw(st.integers(0, max_targets))
        targets = [p for p in draw(st.lists(point, min_size=count, max_size=count))
                   if PLANNER.is_free(np.array([p]), 0.6)[0]]
        lists.append([list(map(float, p)) for p in targets])
    if not any(lists):
        lists[draw(st.integers(0, 9))] = [[5.25, 2.0, 2.0]]
    return lists


def _scenario(lists, seed: int):
    text = "[" + ", ".join("[" + ", ".join(f"[{x:.3f}, {y:.3f}, {z:.3f}]" for x, y, z in route) + "]"
                           for route in lists) + "]"
    return load(SCENARIO, ['strategy.targets="fixed"', f"strategy.target_lists={text}", "strategy.dwell_time_s=0.5"],
                seed=seed)


@settings(max_examples=3, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(lists=layouts(), seed=st.integers(0, 1000))
def test_invariants_hold_for_random_target_layouts(lists, seed):
    sim, log = run_checked(_scenario(lists, seed), 2.5)
    assert log.primes_max <= 1
    assert sim.strategy.targets_total == sum(len(route) for route in lists)


@pytest.mark.slow
@settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
@given(lists=layouts(), seed=st.integers(0, 1000))
def test_invariants_hold_for_random_target_layouts_longer(lists, seed):
    sim, log = run_checked(_scenario(lists, seed), 20.0)
    assert log.primes_max <= 1
