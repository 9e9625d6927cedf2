"""Both paradigms on one task: the continuous-connectivity paper's controller on the intermittent paper's ground
robots and task (``connected_tracking``), on the small test room (4 e-pucks, 2
moving targets, R = 0.2 m), short runs with real MuJoCo, planner and EKF."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.connectivity.graph import connectivity_state
from controllers.connectivity.roles import Role
from estimation.range_model import covariance_predict, covariance_update
from estimation.viewpoints import block_lambda_max, predicted_lambda_max, readings_needed
from intermittent_helpers import room_scenario
from tether.cli import main
from sim.geometry import point_clearance
from sim.loop import Simulation
from tether.runner import build_simulation
from sim.scenario import load

GROUND_CONNECTED = """
preset = "ground"
targets = "random"
target_counts = [1, 0, 0, 1]
"""


class GroundInvariants:
    """The continuous-connectivity paper's invariants on every tick, recomputed from the references the
    wheels received (virtual points): lambda2 > lambda2_min, points farther
    than R_c apart and than R_o from walls, at most one prime traveler."""

    def __init__(self, sim: Simulation):
        self.core = getattr(sim.strategy, "core", sim.strategy)
        self.params = self.core.params
        self.ticks = 0
        self.lambda2_min = np.inf

    def check(self, frame) -> None:
        q = frame.commands.position
        c = self.params
        t = frame.observation.time_s
        assert np.allclose(q[:, 2], self.core.plane_z), "virtual points left the sensors' plane"
        lambda2 = connectivity_state(q, self.core.boxes, c).lambda2
        distance = np.linalg.norm(q[:, None] - q[None], axis=-1)[np.triu_indices(len(q), 1)].min()
        clearance = point_clearance(self.core.boxes, q).min()
        primes = int(np.sum(self.core.roles == Role.PRIME_TRAVELER))
        assert lambda2 > c.lambda2_min + 1e-9, f"t = {t:.2f} s: lambda2 = {lambda2}"
        assert distance > c.min_robot_distance_m, f"t = {t:.2f} s: virtual points {distance:.3f} m apart"
        assert clearance > c.min_obstacle_clearance_m, f"t = {t:.2f} s: virtual point {clearance:.3f} m from a wall"
        assert primes <= 1, f"t = {t:.2f} s: {primes} prime travelers"
        self.ticks += 1
        self.lambda2_min = min(self.lambda2_min, lambda2)


def _run(path, seconds: float, each=None) -> Simulation:
    sim = build_simulation(load(str(path)))
    for _ in range(int(round(seconds / sim.dt))):
        frame, healthy = sim.tick()
        assert healthy, f"physics diverged at t = {sim.time_s:.2f} s"
        if each is not None:
            each(sim, frame)
    return sim


def test_connected_strategy_drives_ground_robots_with_its_invariants(tmp_path):
    path = room_scenario(tmp_path, kind="connected", duration=12.0, extra=GROUND_CONNECTED)
    text = path.read_text()
    # The Khodayi-mehr et al. 2019 keys are not the connected strategy's: keep only its table.
    head, _, rest = text.partition("[strategy]")
    strategy_table = 'kind = "connected"\n' + GROUND_CONNECTED
    path.write_text(head + "[strategy]\n" + strategy_table + "\n[[robots]]" + rest.split("[[robots]]", 1)[1])
    checks: list[GroundInvariants] = []

    def each(sim, frame):
        if not checks:
            checks.append(GroundInvariants(sim))
        checks[0].check(frame)

    sim = _run(path, 12.0, each)
    core = sim.strategy
    assert core.planar and checks[0].ticks == 600
    summary = core.summary()
    assert summary["prime_travelers_max"] == 1  # someone travelled
    assert summary["mean_travel_m"] > 0.2
    # The bodies follow their points in the plane.
    assert np.linalg.norm(sim.observe().position[:, :2] - core.q[:, :2], axis=1).max() < 0.1


def test_fixed_targets_of_ground_robots_are_places_in_the_sensors_plane(tmp_path):
    """A target list written with a height (as for quadrotors) still works on ground robots: each
    target is the point of the sensors' plane below it, and the explorer steers there."""
    path = room_scenario(tmp_path, kind="connected", duration=5.0)
    head, _, rest = path.read_text().partition("[strategy]")
    table = ('kind = "connected"\npreset = "ground"\ntargets = "fixed"\n'
             "target_lists = [[[1.0, 1.0, 1.2], [1.0, 2.5, 0.8]], [], [], []]\n")
    path.write_text(head + "[strategy]\n" + table + "\n[[robots]]" + rest.split("[[robots]]", 1)[1])
    sim = _run(path, 2.0)
    core = sim.strategy
    assert core.targets_total == 2
    target = core.last.targets[0]  # robot 0's current target z_0
    assert target == pytest.approx([1.0, 1.0, core.plane_z])
    assert core.last.remaining[0] < 1.5  # on its way: the path reaches the target from the start


def test_connected_tracking_invariants_readings_and_targets(tmp_path):
    """One 20 s run checks, on every tick: the continuous-connectivity paper's invariants on the ground
    robots; every reading of a reading tick is in the EKF that tick and the
    reported estimate is that tick's; each issued viewpoint serves the most
    uncertain target not assigned to another explorer (or an earlier-ranked
    target has no viewpoint)."""
    path = room_scenario(tmp_path, kind="connected_tracking", duration=20.0)
    state = {"checks": None, "issued": 0, "readings": 0, "ranked_first": 0}

    def each(sim, frame):
        strategy = sim.strategy
        if state["checks"] is None:
            state["checks"] = GroundInvariants(sim)
            state["issued"] = len(strategy.generator.history)
        state["checks"].check(frame)
        obs = frame.observation
        if obs.target_ranges is not None:
            step = obs.target_step
            taken = {(step, r, int(a)) for r, a in zip(*np.nonzero(np.isfinite(obs.target_ranges)))}
            assert set(strategy.belief.keys_at(step)) == taken
            assert frame.commands.estimate.step == step
            assert strategy.belief.computed_until >= step
            state["readings"] += len(taken)
        generator = strategy.generator
        for entry in generator.history[state["issued"]:]:
            _, robot, target = entry
            estimate = strategy.series.last
            uncertainty = block_lambda_max(estimate.covariance, estimate.n_targets)
            others = {s.target for r, s in generator.assigned.items() if s is not None and r != robot}
            ranked = [int(a) for a in np.argsort(-uncertainty, kind="stable") if int(a) not in others]
            if target in ranked:
                before = ranked[:ranked.index(target)]
                position = strategy.core.q[robot]
                skipped = [b for b in before if generator.viewpoint(b, estimate, position) is not None]
                # Passed over only when its dwell just ended below delta (the next target is then sought).
                assert all(uncertainty[b] < generator.params.delta_m2 for b in skipped), (entry, uncertainty)
                state["ranked_first"] += int(not before)
        state["issued"] = len(generator.history)

    sim = _run(path, 20.0, each)
    strategy = sim.strategy
    assert state["checks"].ticks == 1000
    assert state["readings"] > 0 and strategy.readings_fused == state["readings"]
    assert state["ranked_first"] >= 1
    summary = strategy.summary()
    assert summary["prime_travelers_max"] <= 1 and summary["lambda2_min"] > 0
    assert summary["lambda_bar_mean_m2"] < 0.25  # the readings shrank the prior (C(0) = 0.25 I)


def test_connected_tracking_first_targets_follow_the_prior_uncertainty(tmp_path):
    """With target 1 the more uncertain in the prior, the first explorer is sent to it."""
    extra = "prior_variance_m2 = 0.25\n"
    path = room_scenario(tmp_path, kind="connected_tracking", duration=1.0, extra=extra)
    sim = build_simulation(load(str(path)))
    strategy = sim.strategy
    generator = strategy.generator
    prior = strategy.prior
    covariance = prior.covariance.copy()
    covariance[3:6, 3:6] *= 2.0  # target 1 twice as uncertain
    from estimation.ekf import FilterState
    estimate = FilterState(prior.step, prior.mean, covariance)
    generator.assigned = {i: None for i in generator.assigned}
    queues = generator.first_targets(4, strategy.core.q, estimate)
    first, second = (int(i) for i in generator.explorers)
    assert generator.assigned[first].target == 1
    assert generator.assigned[second].target == 0
    assert queues.pending()[[first, second]].all()


def test_connected_tracking_is_deterministic_for_a_seed(tmp_path):
    path = room_scenario(tmp_path, kind="connected_tracking", duration=6.0, seed=3)
    runs = []
    for _ in range(2):
        positions = []
        sim = _run(path, 6.0, lambda s, f: positions.append(f.commands.position.copy()))
        runs.append((np.array(positions), sim.strategy.series.last.mean, sim.observe().position))
    assert np.array_equal(runs[0][0], runs[1][0])
    assert np.array_equal(runs[0][1], runs[1][1])
    assert np.array_equal(runs[0][2], runs[1][2])


def test_connected_tracking_run_that_lasts_its_duration_is_completed(tmp_path):
    """Tracking has no mission end: like the other methods of the intermittent paper's task, a run that lasts its
    duration is "completed" (not "time limit"), its message saying what the team did."""
    from tether.runner import run

    result = run(load(str(room_scenario(tmp_path, kind="connected_tracking", duration=2.0))), tmp_path / "out")
    assert result.status == "completed"
    assert result.metrics["message"].startswith("ran the full 2 s: ")
    assert f"{result.metrics['readings_fused']} readings fused, 0 viewpoints visited" in result.metrics["message"]


@pytest.mark.parametrize("range_m, expected", [
    (0.1, "robots: the starting graph is disconnected"),
    (0.05, "sensing.comm_range_m: 0.05 m is unusable for connected_tracking"),
])
def test_connected_tracking_refuses_a_disconnected_start(tmp_path, capsys, range_m, expected):
    path = room_scenario(tmp_path, kind="connected_tracking", duration=1.0)
    out = tmp_path / "out"
    code = main(["run", str(path), "--out", str(out), "--quiet", "--set", f"sensing.comm_range_m={range_m}"])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert expected in lines[0], lines[0]
    if range_m == 0.1:
        assert "ground1, ground2, ground3 cannot reach ground0" in lines[0], lines[0]
    assert not out.exists()


def test_predicted_lambda_max_matches_the_ekf_covariance_update():
    """The viewpoint prediction (one block, batched over viewpoints) against the
    planner's full-state EKF covariance update (estimation.range_model)."""
    rng = np.random.default_rng(0)
    m = 2
    root = rng.normal(size=(6, 6))
    covariance = root @ root.T * 0.02 + 0.05 * np.eye(6)
    covariance[:3, 3:] = covariance[3:, :3] = 0.0
    x = np.array([1.0, 2.0, 1.2, 3.0, 1.0, 0.9])
    a = np.eye(6)
    q = 4e-4 * np.eye(6)
    sensors = np.array([[0.5, 1.5, 0.04], [2.0, 2.5, 0.04]])
    series = predicted_lambda_max(covariance[3:, 3:], a[3:, 3:], q[3:, 3:], x[3:], sensors, np.array([2, 0]), 4)
    for k, sensor in enumerate(sensors):
        full = covariance.copy()
        for _ in range([2, 0][k]):
            full = covariance_predict(full, a, q)
        expected = [block_lambda_max(full, m)[1]]
        visible = np.array([[False, True]])
        for _ in range(4):
            full = covariance_update(covariance_predict(full, a, q), x, sensor[None], visible)
            expected.append(block_lambda_max(full, m)[1])
        assert np.allclose(series[k], expected, rtol=1e-10, atol=1e-14)
    # Readings needed: below delta first, else where one more stops helping.
    assert readings_needed(np.array([1.0, 0.5, 0.1, 0.05]), 0.2, 0.0) == 2
    assert readings_needed(np.array([1.0, 0.5, 0.495, 0.49]), 0.01, 0.05) == 1
    assert readings_needed(np.array([1.0, 0.5, 0.3, 0.2]), 0.01, 0.05) == 3


def test_report_section_of_the_range_sweep(tmp_path):
    """The paradigms section reads e_g / lambda-bar per method and range from rows alone;
    Table I leaves trials at a swept range out."""
    from tether.report import paradigms_section, table1_section

    rows = []
    for k, method in enumerate(("intermittent", "connected_tracking")):
        for rng in (0.2, 2.0):
            for seed in (0, 1):
                rows.append({"status": "completed", "strategy": method, "sensing.comm_range_m": rng, "seed": seed,
                             "n_moving_targets": 8, "e_g_mean_m": 1.0 + k + rng + 0.1 * seed,
                             "lambda_bar_mean_m2": 0.1 * (1 + k) + 0.01 * seed})
    rows.append({"status": "error", "strategy": "connected_tracking", "sensing.comm_range_m": 0.2, "seed": 2,
                 "error": "ConfigError: robots: the starting graph is disconnected"})
    lines, pngs = paradigms_section(rows, tmp_path)
    text = "\n".join(lines)
    assert "| intermittent | 1.250 ± 0.050 [1.200, 1.300] (n=2) | 3.050 ± 0.050 [3.000, 3.100] (n=2) |" in text
    assert "| connected (Nestmeyer et al. 2017) | 0.205 ± 0.005 [0.200, 0.210] (n=2)" in text
    assert pngs[0].is_file() and pngs[0].stat().st_size > 1000
    assert table1_section(rows, tmp_path) == ([], [])


def test_connected_strategy_refuses_a_mixed_team(tmp_path):
    """Ground robots and quadrotors in one connected team: refused, naming the ground robots."""
    path = room_scenario(tmp_path, kind="connected", duration=1.0)
    head, _, rest = path.read_text().partition("[strategy]")
    robots = "[[robots]]" + rest.split("[[robots]]", 1)[1]
    quads = '\n[[robots]]\nkind = "quadrotor"\nstarts = [[2.2, 1.0, 1.0], [2.3, 1.0, 1.0]]\n'
    path.write_text(head + '[strategy]\nkind = "connected"\npreset = "ground"\n\n' + robots.replace("[[targets]]", quads + "\n[[targets]]", 1))
    from sim.config import ConfigError
    with pytest.raises(ConfigError) as err:
        build_simulation(load(str(path)))
    assert err.value.field == "robots"
    assert "one kind of robot at a time" in err.value.problem and "ground0" in err.value.problem


def test_retarget_changes_what_the_exploration_layer_steers_to(tmp_path):
    """ExplorationController.retarget: a traveler's new point and path, an anchor's dwell ended."""
    path = room_scenario(tmp_path, kind="connected_tracking", duration=3.0)
    sim = _run(path, 1.5)  # the next tick (t = 1.5 s) takes no reading: the generator re-issues nothing
    core = sim.strategy.core
    explorer = core.explorer
    robot = next(i for i, t in enumerate(explorer.targets) if t is not None and explorer.paths[i] is not None)
    offsets = np.array([[0.3, 0.0, 0.0], [-0.3, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, -0.3, 0.0]])
    candidates = explorer.targets[robot].position + offsets
    free = core.planner.is_free(candidates, core.planner.clearance)
    goal = next(c for c, ok in zip(candidates, free) if ok and core.planner.connected(core.q[robot], c))
    old_path = explorer.paths[robot]
    explorer.retarget(robot, goal, 5.0, core.q[robot])
    assert explorer.paths[robot] is not old_path
    assert np.allclose(explorer.paths[robot].end, goal)
    frame, _ = sim.tick()
    assert np.allclose(sim.strategy.core.last.targets[robot], goal)
