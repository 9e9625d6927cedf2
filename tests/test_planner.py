"""Joint-space informative path planner of Khodayi-mehr et al. 2019 (Algorithms 1-4, 6, goal set 6).

Every property of a returned plan is re-checked here with independent code:
the reference geometry (``segments_free``), the reference covariance
functions (``covariance_predict`` / ``covariance_update``) and a plain
Laplacian, never the planner's own helpers.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.intermittent.planner import (
    PlannerParams,
    PlanningProblem,
    RobotPath,
    arrival_times,
    near_radius,
    plan_meeting,
    steer,
)
from controllers.intermittent.planner_belief import PredictedBelief
from controllers.intermittent.planner_geometry import (
    algebraic_connectivity,
    edges_free,
    is_connected,
    lift,
    segments_blocked,
)
from controllers.intermittent.planner_kernels import max_eigenvalue_sym3
from estimation.range_model import covariance_predict, covariance_update
from estimation.target_motion import CircularPath, LinearPath, TargetMotion
from sim.geometry import Boxes, segments_free

Z_S = 0.035  # sensor height, m
RADIUS = 0.035  # robot radius, m
BOUNDS = np.array([[0.0, 0.0], [6.0, 6.0]])
WALL_HALF_HEIGHT = 1.25  # 2.5 m tall walls: no line of sight over them


def wall(x0, y0, x1, y1, thickness=0.1):
    """Axis-aligned wall from (x0, y0) to (x1, y1), as (center, half size)."""
    center = [(x0 + x1) / 2, (y0 + y1) / 2, WALL_HALF_HEIGHT]
    half = [
        max(abs(x1 - x0) / 2, thickness / 2),
        max(abs(y1 - y0) / 2, thickness / 2),
        WALL_HALF_HEIGHT,
    ]
    return center, half


def boxes_of(walls):
    centers, halves = zip(*walls)
    return Boxes.axis_aligned(centers, halves)


# Two walls splitting the room; optionally a sealed cell around (5.2, 5.2).
ROOM_WALLS = [wall(3.0, 0.0, 3.0, 3.5), wall(1.0, 4.0, 3.0, 4.0)]
CELL_WALLS = [wall(4.6, 4.6, 5.8, 4.6), wall(4.6, 5.8, 5.8, 5.8), wall(4.6, 4.6, 4.6, 5.8), wall(5.8, 4.6, 5.8, 5.8)]


def make_problem(target_paths, variances, walls, *, start_times=(0, 4), prefix=True):
    motion = TargetMotion(target_paths, dt=1.0, noise_std=0.01)
    estimate = motion.initial_state() + 0.1
    covariance = np.diag(np.repeat(variances, 3)).astype(float)
    starts = np.array([[1.0, 1.0], [2.0, 2.5]])
    t0 = np.array(start_times)
    prefixes = None
    if prefix:  # robot 1 is still driving to its start until t0[1]
        prefixes = (None, RobotPath(np.array([0, t0[1]]), np.array([[2.0, 2.1], starts[1]])))
    return PlanningProblem(
        start_positions=starts,
        start_times=t0,
        estimate=estimate,
        covariance=covariance,
        belief_time=0,
        motion=motion,
        boxes=boxes_of(walls),
        bounds=BOUNDS,
        prefixes=prefixes,
    )


TARGETS = [CircularPath((1.5, 2.0, 1.3), 0.4, 0.05), LinearPath((4.0, 1.0, 1.0), (5.0, 1.5, 1.0), 0.05)]
PARAMS = PlannerParams(n_sample=300, n_uniform=100, robot_radius=RADIUS, sensor_height=Z_S)


@pytest.fixture(scope="module")
def problem():
    return make_problem(TARGETS, [0.25, 0.3], ROOM_WALLS)


@pytest.fixture(scope="module")
def result(problem):
    res = plan_meeting(problem, PARAMS, np.random.default_rng(7))
    print(f"\nplan: {res.wall_time_s:.3f} s wall, {res.cost_time_share:.0%} in cost, {res.n_nodes} nodes")
    return res


# ---------------------------------------------------------------------------
# Independent checks
# ---------------------------------------------------------------------------


def lambda2(positions, boxes, comm_range):
    n = len(positions)
    adjacency = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            close = np.linalg.norm(positions[i] - positions[j]) <= comm_range
            sight = segments_free(boxes, lift(positions[i], Z_S)[None], lift(positions[j], Z_S)[None])[0]
            adjacency[i, j] = adjacency[j, i] = float(close and sight)
    laplacian = np.diag(adjacency.sum(1)) - adjacency
    return np.linalg.eigvalsh(laplacian)[1]


def position(problem, plan, j, t):
    """Robot j at step t: on the plan from t_0,j, on its prefix before, else None."""
    if t >= problem.start_times[j]:
        return plan.paths[j].position_at(t)
    prefix = problem.prefixes[j] if problem.prefixes is not None else None
    if prefix is not None and prefix.start_time <= t <= prefix.end_time:
        return prefix.position_at(t)
    return None


def recompute(problem, params, plan):
    """Algorithm 4 from scratch along the returned paths: (cost, C(t_f), x_hat(t_f))."""
    motion = problem.motion
    x, cov = np.array(problem.estimate), np.array(problem.covariance)
    t_start = problem.start_times.min()
    cost = 0.0
    for k in range(problem.belief_time, plan.meeting_time):
        t = k + 1
        x = motion.predict(x, k)
        cov = covariance_predict(cov, motion.transition, motion.process_noise)
        sensors = [position(problem, plan, j, t) for j in range(problem.n_robots)]
        sensors = np.array([lift(p, Z_S) for p in sensors if p is not None])
        if len(sensors):
            targets = x.reshape(-1, 3)
            visible = np.zeros((len(sensors), len(targets)), dtype=bool)
            for r, s in enumerate(sensors):
                for a, target in enumerate(targets):
                    in_range = np.linalg.norm(target - s) <= params.sensing_range
                    visible[r, a] = in_range and segments_free(problem.boxes, s[None], target[None])[0]
            cov = covariance_update(cov, x, sensors, visible)
        if t > t_start:
            cost += np.linalg.eigvalsh(cov)[-1]
    return cost, cov, x


# ---------------------------------------------------------------------------
# Steering (Algorithm 6, Appendix A) and time matching
# ---------------------------------------------------------------------------

coords = st.floats(0.0, 10.0, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(2, 4),
    data=st.data(),
    step=st.floats(0.05, 2.0),
    u_max=st.floats(0.02, 0.5),
)
def test_steer_matches_appendix_a(n, data, step, u_max):
    q = np.array(data.draw(st.lists(st.tuples(coords, coords), min_size=n, max_size=n)))
    q_rand = np.array(data.draw(st.lists(st.tuples(coords, coords), min_size=n, max_size=n)))
    t = np.array(data.draw(st.lists(st.integers(0, 40), min_size=n, max_size=n)))
    out = steer(q, t, q_rand, step, u_max)
    d = q_rand - q
    norms = np.linalg.norm(d, axis=1)
    s = min(step, norms.min())
    if out is None:
        assert s <= 1e-12
        return
    q_new, t_new = out
    dt_s = max(int(np.ceil(s / u_max - 1e-9)), 1)
    t_min = t.min()
    moved = np.linalg.norm(q_new - q, axis=1)
    for j in range(n):
        if t[j] - t_min < dt_s:  # Delta t_c > 0: moves along d_ij and arrives at t_min + Delta t_s
            assert t_new[j] == t_min + dt_s
            assert moved[j] == pytest.approx(s * (dt_s - (t[j] - t_min)) / dt_s, rel=1e-9, abs=1e-12)
            assert moved[j] <= norms[j] + 1e-12
            step_j = q_new[j] - q[j]
            cross = step_j[0] * d[j, 1] - step_j[1] * d[j, 0]
            assert cross == pytest.approx(0.0, abs=1e-9 * max(1.0, norms[j]))
            assert (q_new[j] - q[j]) @ d[j] > 0
        else:  # ahead: stays, keeps its time
            assert t_new[j] == t[j] and np.array_equal(q_new[j], q[j])
        assert moved[j] <= u_max * (t_new[j] - t[j]) * (1 + 1e-9) + 1e-12
    lagging = t == t_min
    assert np.allclose(moved[lagging], s)  # the lagging robot moves exactly s
    delay, new_delay = t.max() - t.min(), t_new.max() - t_new.min()
    assert new_delay == max(0, delay - dt_s) <= delay
    # The general arrival-time rule reproduces Steer's times.
    assert np.array_equal(arrival_times(t, q, q_new, u_max), t_new)


def test_repeated_steering_removes_the_delay():
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(0, 10, (3, 2))
        t = rng.integers(0, 60, 3)
        delays = [t.max() - t.min()]
        for _ in range(200):
            out = steer(q, t, rng.uniform(0, 10, (3, 2)), 0.5, 0.1)
            if out is None:
                continue
            q, t = out
            delays.append(t.max() - t.min())
            if delays[-1] == 0:
                break
        assert all(b <= a for a, b in zip(delays, delays[1:]))  # never increases
        assert delays[-1] == 0  # reaches zero


def test_arrival_times_synchronise_and_respect_speed():
    q_parent = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    q_child = np.array([[0.35, 0.0], [1.0, 0.0], [2.0, 0.1]])
    times = arrival_times(np.array([10, 10, 10]), q_parent, q_child, 0.1)
    assert list(times) == [14, 14, 14]  # standing robot waits, all arrive together
    ahead = arrival_times(np.array([10, 30, 10]), q_parent, q_child, 0.1)
    assert list(ahead) == [14, 30, 14]  # the standing robot ahead keeps its time
    assert arrival_times(np.zeros(3, int), q_parent, q_parent, 0.1) is None


def test_near_radius_shrinks_and_is_capped():
    radii = [near_radius(n, 2, 36.0, 1.0, 1.1) for n in (2, 10, 100, 10_000, 10**8)]
    assert radii[0] == pytest.approx(np.sqrt(2))  # capped by the longest Steer move
    assert all(b <= a for a, b in zip(radii, radii[1:])) and radii[-1] < radii[0]


# ---------------------------------------------------------------------------
# Helpers against references
# ---------------------------------------------------------------------------


def test_line_of_sight_matches_segments_free():
    rng = np.random.default_rng(0)
    boxes = boxes_of(ROOM_WALLS + CELL_WALLS)
    a = np.column_stack([rng.uniform(0, 6, (400, 2)), np.full(400, Z_S)])
    b = np.column_stack([rng.uniform(0, 6, (400, 2)), rng.uniform(0.5, 2.0, 400)])
    assert np.array_equal(segments_blocked(boxes, a, b), ~segments_free(boxes, a, b, 0.0))


def test_collision_free_certificate_gives_the_exact_answer():
    rng = np.random.default_rng(5)
    boxes = boxes_of(ROOM_WALLS + CELL_WALLS)
    a = rng.uniform(0, 6, (600, 2))
    b = a + rng.uniform(-1.0, 1.0, (600, 2))
    exact = segments_free(boxes, lift(a, Z_S), lift(b, Z_S), RADIUS)
    assert 0 < exact.sum() < len(exact)
    assert np.array_equal(edges_free(boxes, a, b, Z_S, RADIUS), exact)


def test_max_eigenvalue_matches_eigvalsh_including_repeated_eigenvalues():
    rng = np.random.default_rng(2)
    for k in range(3000):
        basis, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        eigenvalues = rng.uniform(0.0, 1.0, 3) * 10.0 ** rng.uniform(-6, 2)
        if k % 3 == 0:  # the two largest equal: where a closed-form cubic loses half its digits
            eigenvalues[1] = eigenvalues.max()
        elif k % 3 == 1:  # isotropic
            eigenvalues[:] = eigenvalues[0]
        c = (basis * eigenvalues) @ basis.T
        c = 0.5 * (c + c.T)
        assert abs(max_eigenvalue_sym3(c) - np.linalg.eigvalsh(c)[-1]) <= 1e-14 * np.abs(c).max()


def test_reachability_agrees_with_algebraic_connectivity():
    rng = np.random.default_rng(3)
    for _ in range(300):
        n = int(rng.integers(1, 7))
        upper = np.triu(rng.random((n, n)) < 0.4, k=1)
        adjacency = upper | upper.T
        assert is_connected(adjacency) == (algebraic_connectivity(adjacency) > 1e-9)


def test_block_and_full_covariance_propagation_agree(problem):
    kwargs = dict(
        motion=problem.motion, estimate=problem.estimate, covariance=problem.covariance,
        belief_time=0, boxes=problem.boxes, sensor_height=Z_S, sensing_range=5.0,
    )
    fast, reference = PredictedBelief(**kwargs), PredictedBelief(**kwargs, full=True)
    assert fast.blocks and not reference.blocks
    rng = np.random.default_rng(1)
    positions = rng.uniform(0, 6, (3, 2, 12, 2))
    positions[1, 0, 5:] = np.nan  # an absent robot takes no reading
    t0, steps = np.array([0, 3, 7]), np.array([12, 9, 4])
    p_fast = fast.propagate(np.stack([fast.initial_covariance] * 3), t0, steps, positions)
    p_ref = reference.propagate(np.stack([reference.initial_covariance] * 3), t0, steps, positions)
    assert np.allclose(p_fast.cost, p_ref.cost, rtol=1e-10)
    assert np.allclose([fast.full_covariance(c) for c in p_fast.covariance], p_ref.covariance, atol=1e-12)
    assert np.allclose(p_fast.target_uncertainty, p_ref.target_uncertainty, rtol=1e-10)


# ---------------------------------------------------------------------------
# The returned plan
# ---------------------------------------------------------------------------


def test_plan_found_and_fast(result):
    assert result.success, result.reason
    assert result.reason == ""
    assert result.n_goal_nodes >= 1
    assert 0.0 < result.cost_time_s <= result.wall_time_s
    assert result.wall_time_s < 10.0  # well under a few seconds on an idle core


def test_paths_start_at_starts_and_end_synchronised(problem, result):
    plan = result.plan
    for j, path in enumerate(plan.paths):
        assert path.start_time == problem.start_times[j]
        assert np.array_equal(path.positions[0], problem.start_positions[j])
        assert path.end_time == plan.meeting_time  # same arrival time, no waiting
        assert np.array_equal(path.positions[-1], plan.meeting_positions[j])
    assert np.array_equal(plan.positions_at(plan.meeting_time), plan.meeting_positions)


def test_paths_respect_speed_bound(problem, result):
    plan = result.plan
    for j, path in enumerate(plan.paths):
        steps = np.arange(path.start_time, path.end_time + 1)
        moves = np.linalg.norm(np.diff(path.position_at(steps), axis=0), axis=1)
        assert np.all(moves <= PARAMS.u_max * (1 + 1e-9))
        speeds = np.linalg.norm(np.diff(path.positions, axis=0), axis=1) / np.diff(path.times)
        assert np.all(speeds <= PARAMS.u_max * (1 + 1e-9))


def test_paths_collision_free_with_margin(problem, result):
    for path in result.plan.paths:
        a, b = lift(path.positions[:-1], Z_S), lift(path.positions[1:], Z_S)
        if len(a):
            assert np.all(segments_free(problem.boxes, a, b, RADIUS))
        assert np.all(path.positions >= BOUNDS[0] + RADIUS) and np.all(path.positions <= BOUNDS[1] - RADIUS)


def test_meeting_configuration_connected(problem, result):
    plan = result.plan
    lam2 = lambda2(plan.meeting_positions, problem.boxes, PARAMS.comm_range)
    assert lam2 > 0
    assert plan.meeting_lambda2 == pytest.approx(lam2)


def test_cost_matches_independent_recomputation(problem, result):
    plan = result.plan
    cost, cov, x = recompute(problem, PARAMS, plan)
    assert plan.cost == pytest.approx(cost, rel=1e-9)
    assert np.allclose(plan.meeting_covariance, cov, atol=1e-12)
    assert np.allclose(plan.meeting_estimate, x)
    # Goal condition (iii) in the prediction: the most uncertain target below delta.
    a = plan.target
    assert plan.target_rank == 0 and a == int(np.argmax(np.diag(problem.covariance)[::3]))
    block = cov[3 * a : 3 * a + 3, 3 * a : 3 * a + 3]
    assert np.linalg.eigvalsh(block)[-1] <= PARAMS.delta
    assert plan.target_uncertainty == pytest.approx(np.linalg.eigvalsh(block)[-1])


def test_tree_edges_feasible_and_time_matched(result):
    q, t, parent = result.tree_positions, result.tree_times, result.tree_parents
    assert parent[0] == -1 and np.all(parent[1:] >= 0)
    child = np.arange(1, len(parent))
    dt = t[child] - t[parent[child]]
    moves = np.linalg.norm(q[child] - q[parent[child]], axis=2)
    assert np.all(dt >= 0) and np.all(moves <= PARAMS.u_max * dt * (1 + 1e-9) + 1e-12)
    delay = t.max(1) - t.min(1)
    assert np.all(delay[child] <= delay[parent[child]])  # time matching never loses ground
    assert np.all(delay[child][delay[parent[child]] == 0] == 0)  # synchronised stays so


def test_same_seed_same_plan(problem, result):
    again = plan_meeting(problem, PARAMS, np.random.default_rng(7))
    assert again.plan.cost == result.plan.cost
    assert again.plan.meeting_time == result.plan.meeting_time
    for p, r in zip(again.plan.paths, result.plan.paths):
        assert np.array_equal(p.times, r.times) and np.array_equal(p.positions, r.positions)
    assert np.array_equal(again.tree_positions, result.tree_positions)


def test_late_start_with_committed_prefix():
    """Robot 1 joins 27 steps after robot 0 (its other meeting): several
    unsynchronised nodes carry its prefix readings before the paths sync."""
    motion = TargetMotion(TARGETS, dt=1.0, noise_std=0.01)
    starts = np.array([[1.0, 1.0], [2.0, 2.5]])
    prefix = RobotPath(np.array([0, 30]), np.array([[2.5, 0.5], starts[1]]))
    problem = PlanningProblem(
        start_positions=starts, start_times=np.array([3, 30]),
        estimate=motion.initial_state() + 0.1, covariance=np.diag(np.repeat([0.25, 0.3], 3)),
        belief_time=0, motion=motion, boxes=boxes_of(ROOM_WALLS), bounds=BOUNDS,
        prefixes=(None, prefix),
    )
    res = plan_meeting(problem, PARAMS, np.random.default_rng(1))
    assert res.success, res.reason
    plan = res.plan
    assert [p.start_time for p in plan.paths] == [3, 30] and plan.meeting_time > 30
    assert np.allclose(plan.positions_at(10)[1], np.nan, equal_nan=True)  # not started yet
    for path in plan.paths:
        assert path.end_time == plan.meeting_time
        steps = np.arange(path.start_time, path.end_time + 1)
        moves = np.linalg.norm(np.diff(path.position_at(steps), axis=0), axis=1)
        assert np.all(moves <= PARAMS.u_max * (1 + 1e-9))
        a, b = lift(path.positions[:-1], Z_S), lift(path.positions[1:], Z_S)
        assert np.all(segments_free(problem.boxes, a, b, RADIUS))
    assert lambda2(plan.meeting_positions, problem.boxes, PARAMS.comm_range) > 0
    cost, cov, _ = recompute(problem, PARAMS, plan)
    assert plan.cost == pytest.approx(cost, rel=1e-9)
    assert np.allclose(plan.meeting_covariance, cov, atol=1e-12)
    delay = res.tree_times.max(1) - res.tree_times.min(1)
    assert np.count_nonzero(delay > 0) > 1  # the tree did carry unsynchronised nodes


# ---------------------------------------------------------------------------
# Fallback and failure
# ---------------------------------------------------------------------------


def test_falls_back_to_next_target_when_most_uncertain_is_unreachable():
    # Target 0 is the most uncertain but sealed in a walled cell in the far corner.
    targets = [CircularPath((5.2, 5.2, 1.3), 0.2, 0.03)] + TARGETS
    problem = make_problem(targets, [0.5, 0.25, 0.3], ROOM_WALLS + CELL_WALLS)
    res = plan_meeting(problem, PARAMS, np.random.default_rng(7))
    assert res.success, res.reason
    assert res.plan.target_rank == 1 and res.plan.target == 2  # next most uncertain
    cost, cov, _ = recompute(problem, PARAMS, res.plan)
    assert res.plan.cost == pytest.approx(cost, rel=1e-9)
    assert np.linalg.eigvalsh(cov[0:3, 0:3])[-1] > PARAMS.delta  # hidden target stays uncertain
    assert np.linalg.eigvalsh(cov[6:9, 6:9])[-1] <= PARAMS.delta


def test_reports_failure_when_no_target_is_reachable():
    targets = [CircularPath((5.2, 5.2, 1.3), 0.2, 0.03)]
    problem = make_problem(targets, [0.5], ROOM_WALLS + CELL_WALLS)
    res = plan_meeting(problem, dataclasses.replace(PARAMS, n_sample=80), np.random.default_rng(0))
    assert not res.success and res.plan is None
    assert "no goal node" in res.reason
    assert res.n_nodes >= 1 and res.n_samples == 80


def test_start_in_collision_is_a_failure_not_a_path():
    problem = make_problem(TARGETS, [0.25, 0.3], ROOM_WALLS + [wall(0.5, 1.0, 1.5, 1.0)], prefix=False)
    res = plan_meeting(problem, dataclasses.replace(PARAMS, n_sample=20), np.random.default_rng(0))
    assert not res.success and "free space" in res.reason


# ---------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("n_sample", 0), ("n_sample", 2.5), ("n_uniform", -1), ("step_size", 0.0),
        ("u_max", -0.1), ("comm_range", 0.0), ("delta", 0.0), ("delta", float("nan")),
        ("sensor_height", -0.01), ("robot_radius", -0.01), ("sensing_range", 0.0),
        ("measurement_period", 0), ("gamma_scale", 0.0), ("max_sample_tries", 0),
        ("step_size", float("inf")), ("n_sample", True),
    ],
)
def test_invalid_params_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        PlannerParams(**{field: value})


def test_invalid_problem_names_the_field(problem):
    fields = {f.name: getattr(problem, f.name) for f in dataclasses.fields(problem)}
    bad = {
        "start_positions": np.zeros((2, 3)),
        "start_times": np.array([0.5, 1.0]),
        "estimate": np.zeros(4),
        "covariance": np.ones((6, 5)),
        "belief_time": 10,
        "bounds": np.array([[1.0, 1.0], [0.0, 2.0]]),
        "prefixes": (None, RobotPath(np.array([0, 3]), np.zeros((2, 2)))),
    }
    for name, value in bad.items():
        with pytest.raises(ValueError, match=name):
            PlanningProblem(**{**fields, name: value})
    with pytest.raises(ValueError, match="rng"):
        plan_meeting(problem, PARAMS, 7)
