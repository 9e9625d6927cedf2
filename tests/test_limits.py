"""Every size is bounded before it is allocated (docs/robustness.md): a sweep's
trial count, its seeds, its file's size, nesting in sweep files and ``--set``,
``--workers``, and the geodesic planner's grid. Each case is a real
``tether`` process given the huge input: exit 2, one line naming the field, no
traceback, within seconds and a small amount of memory, nothing written.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sim.config import ConfigError

REPO = Path(__file__).resolve().parents[1]
LIMIT_S = 60.0  # a refusal takes 1-3 s; the unbounded versions took 20-60 s and gigabytes
MEMORY_LIMIT = 2 * 1024**3  # address space of the refused process: the unbounded versions needed more


def tether(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OPENBLAS_NUM_THREADS": "1", "MUJOCO_GL": "egl"}

    def bounded() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT * 4, MEMORY_LIMIT * 4))  # numba/LLVM reserve a lot

    start = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "tether.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=LIMIT_S * 2, preexec_fn=bounded)
    proc.took_s = time.monotonic() - start
    return proc


def assert_refused(proc: subprocess.CompletedProcess, *words: str) -> str:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr[-2000:]
    assert lines[0].startswith("tether: error: "), lines[0]
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert proc.took_s < LIMIT_S, f"{proc.took_s:.0f} s to refuse"
    return lines[0]


def sweep_file(folder: Path, body: str, name: str = "big.toml") -> Path:
    path = folder / name
    path.write_text(f'scenario = "hover"\nduration_s = 0.05\n{body}')
    return path


BIG_SWEEPS = {
    "a grid of 10^7 trials": ('seeds = 10\n[grid]\n"strategy.speed_mps" = [' + ", ".join(f"{v}.5" for v in range(1000))
                              + ']\n"robots.0.count" = [' + ", ".join(str(v) for v in range(1, 1001)) + "]\n",
                              ("grid:", "10000000 trials", "100000")),
    "a million seeds": ("seeds = 1000000\n", ("seeds:", "100000")),
    "a seed beyond int64": ("seeds = [0, 9223372036854775808]\n", ("seeds:", "9223372036854775808")),
    "a seed of 10^29": ("seeds = [0, 1, 100000000000000000000000000000]\n", ("seeds:",)),
    "a negative seed": ("seeds = [3, -1]\n", ("seeds:", "-1")),
    "seeds nested 5000 deep": ("seeds = " + "[" * 5000 + "0" + "]" * 5000 + "\n", ("sweep:", "nested")),
    "a grid value nested 40 deep": ('[grid]\n"strategy.speed_mps" = [' + "[" * 40 + "1" + "]" * 40 + "]\n",
                                    ("sweep:", "nested more than 32")),
    "a TOML datetime in the grid": ('[grid]\n"strategy.speed_mps" = [1979-05-27T07:32:00Z]\n',
                                    ("grid.strategy.speed_mps:", "datetime")),
}


@pytest.mark.parametrize("case", sorted(BIG_SWEEPS))
def test_a_huge_sweep_is_refused_before_it_is_expanded(case, tmp_path):
    body, words = BIG_SWEEPS[case]
    path = sweep_file(tmp_path, body)
    assert_refused(tether(["sweep", str(path), "--out", "out"], tmp_path), *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.toml"]


def test_a_sweep_file_over_a_megabyte_is_not_read(tmp_path):
    path = sweep_file(tmp_path, 'description = "' + "x" * 20_000_000 + '"\n')
    assert_refused(tether(["sweep", str(path), "--list"], tmp_path), "sweep:", "larger than 1000000 bytes")


@pytest.mark.parametrize("value", ["[" * 3000, "[" * 3000 + "]" * 3000, "[" * 40 + "1" + "]" * 40],
                         ids=["3000-open", "3000-closed", "40-deep"])
def test_set_nested_too_deep_is_one_line(value, tmp_path):
    proc = tether(["run", "hover", "--duration", "0.05", "--out", "out", "--set", f"strategy.speed_mps={value}"],
                  tmp_path)
    assert_refused(proc, "strategy.speed_mps:", "nested")
    assert not list(tmp_path.iterdir())


def test_workers_beyond_a_few_per_core_are_refused(tmp_path):
    path = sweep_file(tmp_path, "seeds = 2\n")
    line = assert_refused(tether(["sweep", str(path), "--out", "out", "--workers", "100000"], tmp_path),
                          "--workers:", "100000")
    assert str(4 * (os.cpu_count() or 1)) in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("seed", [str(2**63), str(2**64 - 1), "-1"])
def test_seeds_have_one_range_for_runs_and_sweeps(seed, tmp_path):
    """[0, 2**63 - 1] everywhere (a sweep stores seeds as int64): a run refuses what a sweep would."""
    assert_refused(tether(["run", "hover", "--duration", "0.05", "--out", "out", "--seed", seed], tmp_path), "seed")
    path = sweep_file(tmp_path, f"seeds = [{seed}]\n")
    assert_refused(tether(["sweep", str(path), "--list"], tmp_path), "seeds")


def test_the_largest_seed_runs_and_is_stored(tmp_path):
    path = sweep_file(tmp_path, f"seeds = [{2**63 - 1}]\n")
    proc = tether(["sweep", str(path), "--out", "out", "--workers", "1", "--no-report"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    import pyarrow.parquet as pq

    assert pq.read_table(tmp_path / "out" / "results.parquet").column("seed").to_pylist() == [2**63 - 1]


# ---------------------------------------------------------------- the geodesic planner's grid

def test_the_geodesic_grid_is_capped_before_it_is_allocated():
    from controllers.baselines.geodesic import MAX_CELLS, GeodesicPlanner
    from sim.geometry import Boxes

    no_boxes = Boxes(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    start = time.monotonic()
    with pytest.raises(ConfigError) as refused:
        GeodesicPlanner(no_boxes, np.array([[0.0, 0.0], [1000.0, 1000.0]]), 1.0, 0.3)
    assert time.monotonic() - start < 1.0
    assert refused.value.field == "scene" and f"{MAX_CELLS:,}" in refused.value.problem
    assert MAX_CELLS >= 1001 * 1401  # the 50 x 70 m outdoor scenes keep their 5 cm cells


@pytest.mark.slow
def test_intermittent_in_a_1_km_scene_is_one_line(tmp_path):
    scene = (REPO / "models" / "scenes" / "empty.xml").read_text()
    scene = scene.replace("0 0 0 50 70 20", "0 0 0 1000 1000 20").replace('size="25 35 0.1" pos="25 35 0"',
                                                                          'size="500 500 0.1" pos="500 500 0"')
    (tmp_path / "km.xml").write_text(scene)
    proc = tether(["run", "intermittent-4", "--scene", "km.xml", "--duration", "1", "--out", "out", "--quiet"],
                  tmp_path)
    assert_refused(proc, "scene:", "geodesic planner", "cells")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["km.xml"]


def test_connected_office_in_a_1_km_office_names_the_coarsened_grid(tmp_path):
    """The office's walls in 1 km bounds: the connectivity planner's 400,000-cell cap coarsens its
    0.25 m cells to 2.7 m, which cuts the start room off. The refusal names that, not the targets'
    clearance, and comes before 10^5 draws are each tested for a path."""
    scene = (REPO / "models" / "scenes" / "indoor.xml").read_text().replace('data="0 0 0 10 10 5"',
                                                                            'data="0 0 0 1000 1000 5"')
    (tmp_path / "km.xml").write_text(scene)
    proc = tether(["run", "connected-office", "--scene", "km.xml", "--duration", "1", "--out", "out", "--quiet"],
                  tmp_path)
    line = assert_refused(proc, "scene:", "connectivity planner's grid is coarsened from 0.25 m to 2.7 m",
                          "400,000 cells", "smaller scene")
    assert "target_clearance_m" not in line
    assert proc.took_s < 20.0, f"{proc.took_s:.0f} s to refuse"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["km.xml"]


def test_connected_to_answers_as_connected_one_point_at_a_time():
    from controllers.connectivity.paths import GridPlanner
    from sim.geometry import Boxes

    # a wall across the room with a door: two rooms, and points inside the wall
    wall = Boxes(np.array([[2.0, 5.0, 2.5], [7.5, 5.0, 2.5]]), np.array([[2.0, 0.1, 2.5], [2.5, 0.1, 2.5]]),
                 np.repeat(np.eye(3)[None], 2, axis=0))
    closed = Boxes(np.array([[5.0, 5.0, 2.5]]), np.array([[5.0, 0.1, 2.5]]), np.eye(3)[None])
    points = np.random.default_rng(3).uniform([0, 0, 0], [10, 10, 5], size=(300, 3))
    for boxes in (wall, closed):
        planner = GridPlanner(boxes, [0, 0, 0], [10, 10, 5], 0.5, 0.4, 0.2)
        one_by_one = np.array([planner.connected([1.0, 1.0, 1.0], p) for p in points])
        assert np.array_equal(planner.connected_to([1.0, 1.0, 1.0], points), one_by_one)
        assert 0 < one_by_one.sum() < len(points)
        assert not planner.coarsened
    coarse = GridPlanner(wall, [0, 0, 0], [10, 10, 5], 0.05, 0.4, 0.2)
    assert coarse.coarsened and "coarsened from 0.05 m to" in coarse.coarsening()
