"""The plot pages: painter processes draw what this process would draw, pixel
for pixel, whether their figures were built ahead of the data or not, when the
layout changes after it was planned, when a painter dies, and where no child
process can be started (a daemonic pool worker)."""

import multiprocessing
import os
import signal
import time

import numpy as np
import pytest
from PIL import Image

from viz.painter import Painters, build_page, draw_pages, fill_page, page_layout, save_page

ROBOTS = ("quad0", "quad1", "quad2")
ROLES = [(0.0, "prime traveler"), (1.0, "secondary traveler"), (2.0, "anchor")]


def _pages(folder, n_series: int = 7, n_samples: int = 120) -> list:
    """Series with NaN gaps (undefined at first), then a coded per-robot series: two pages."""
    rng = np.random.default_rng(0)
    times = np.arange(n_samples) * 0.1
    panels = []
    for k in range(n_series):
        values = np.cumsum(rng.normal(size=n_samples)) * (k + 1)
        values[: 5 * k] = np.nan  # t*(t)-like: a gap until first defined
        panels.append((f"series {k} (m)", np.column_stack([times, values]), None, None))
    roles = rng.integers(0, 3, size=(n_samples, len(ROBOTS))).astype(float)
    panels.append(("role (per robot)", times, roles, ROLES))
    return [(str(folder / "timeseries.png"), panels[:6]), (str(folder / "timeseries_2.png"), panels[6:])]


def _layouts(pages) -> list:
    return [(path, page_layout(panels)) for path, panels in pages]


def _pixels(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGBA"))


def _reference(tmp_path, pages, title: str) -> list[np.ndarray]:
    """The same pages drawn in this process, from scratch."""
    folder = tmp_path / "reference"
    folder.mkdir()
    moved = [(str(folder / os.path.basename(path)), panels) for path, panels in pages]
    return [_pixels(path) for path in draw_pages(moved, title, ROBOTS)]


def _assert_drawn_as_here(tmp_path, files, pages, title: str) -> None:
    """``files`` are the pages' PNGs, in order, pixel for pixel what this process draws from scratch."""
    assert files == [path for path, _ in pages]
    for path, expected in zip(files, _reference(tmp_path, pages, title)):
        np.testing.assert_array_equal(_pixels(path), expected)


def test_a_page_built_and_drawn_before_its_data_comes_out_the_same(tmp_path):
    pages = _pages(tmp_path)
    reference = _reference(tmp_path, pages, "run completed")
    for (path, panels), expected in zip(pages, reference):
        page = build_page(page_layout(panels), ROBOTS)
        page.figure.canvas.draw()  # what a painter does while the run goes on: empty axes, default limits
        fill_page(page, panels, "run completed")
        np.testing.assert_array_equal(_pixels(save_page(page, path)), expected)


def test_painters_draw_the_planned_pages_in_parallel_as_this_process_would(tmp_path):
    pages = _pages(tmp_path)
    painters = Painters(ROBOTS, max_painters=2)
    painters.plan(_layouts(pages))
    assert len(painters._painters) == 2  # one per page
    time.sleep(3.0)  # let them build ahead (the result must not depend on it)
    painters.start(pages, "run completed")
    _assert_drawn_as_here(tmp_path, painters.finish(), pages, "run completed")


def test_a_layout_that_changes_after_the_plan_is_drawn_from_scratch(tmp_path):
    pages = _pages(tmp_path)
    painters = Painters(ROBOTS, max_painters=2)
    painters.plan(_layouts(_pages(tmp_path, n_series=4)))  # fewer series when planned: one page
    painters.plan(_layouts(_pages(tmp_path, n_series=5)))
    painters.start(pages, "run time limit")
    _assert_drawn_as_here(tmp_path, painters.finish(), pages, "run time limit")


def test_pages_of_a_painter_that_died_are_drawn_here(tmp_path):
    pages = _pages(tmp_path)
    painters = Painters(ROBOTS, max_painters=2)
    painters.plan(_layouts(pages))
    victim = painters._painters[1][0]
    os.kill(victim.pid, signal.SIGKILL)
    victim.join(timeout=30)
    painters.start(pages, "run completed")
    _assert_drawn_as_here(tmp_path, painters.finish(), pages, "run completed")


def test_a_run_that_ends_before_plotting_leaves_no_painter_behind(tmp_path):
    painters = Painters(ROBOTS, max_painters=2)
    processes = [process for process, _ in painters._painters]
    assert painters.finish() == []
    for process in processes:
        process.join(timeout=30)
        assert not process.is_alive()


def _draw_in_a_daemonic_worker(folder) -> tuple[int, list[str]]:
    from pathlib import Path

    painters = Painters(ROBOTS)
    pages = _pages(Path(folder))
    painters.plan(_layouts(pages))
    painters.start(pages, "run completed")
    return len(painters._painters), painters.finish()


def test_a_daemonic_pool_worker_draws_its_pages_itself(tmp_path):
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        n_painters, files = pool.apply(_draw_in_a_daemonic_worker, (str(tmp_path),))
    assert n_painters == 0  # a daemonic process may not have children
    _assert_drawn_as_here(tmp_path, files, _pages(tmp_path), "run completed")


@pytest.mark.parametrize("robot_names", [ROBOTS, None])
def test_per_robot_lines_are_named_by_robot(robot_names):
    page = build_page((("role (per robot)", 3, tuple(ROLES)),), robot_names)
    labels = [line.get_label() for line in page.lines[0]]
    assert labels == (list(ROBOTS) if robot_names else ["robot 0", "robot 1", "robot 2"])
    assert (page.axes[0].get_legend() is not None) == (robot_names is not None)
    assert [t.get_text() for t in page.axes[0].get_yticklabels()] == ["prime\ntraveler", "secondary\ntraveler",
                                                                       "anchor"]


def test_panels_put_the_headline_first_drop_repeats_and_empty_series_and_label_units(tmp_path):
    from viz.plots import COMM_LAMBDA2, LINKS, PlotRecorder, axis_label, per_robot, run_title

    recorder = PlotRecorder(("quadrotor",) * 3, tmp_path, robot_names=ROBOTS)
    try:
        for k in range(5):
            t = 0.1 * k
            recorder.series[LINKS].append((t, 3.0))
            recorder.series[COMM_LAMBDA2].append((t, 1.0))
            recorder.series["edges"].append((t, 3.0))
            recorder.series["t_star_s"].append((t, float("nan")))  # never agreed: no panel
            recorder.series["stretch_m"].append((t, 1.5 + 0.3 * k))
            recorder.series["lambda2"].append((t, 0.5))
            recorder.series["prime_traveler"].append((t, float(k % 3)))
            recorder.series["robots_waiting"].append((t, 0.0))  # a count that stays 0
        panels = recorder.panels()
        assert panels[:2] == ["lambda2", "stretch_m"]  # the continuous-connectivity paper's headline first
        assert LINKS not in panels and "edges" in panels and "t_star_s" not in panels
        (path, page), = recorder._pages()
        labels = [panel[0] for panel in page]
        assert all(label.endswith(")") and " (" in label for label in labels), labels
        integer = {panel[0]: panel[4] for panel in page}
        assert integer["prime traveler (robot index)"] and integer["graph edges (count)"]
        assert not integer["stretch (m)"]
        title = run_title("connected-office", "connected", 3)
        assert "connected-office" in title and "Nestmeyer" in title and "seed 3" in title
        assert axis_label("closing_s") == "closing (s)" and axis_label("plans", integer=True) == "plans (count)"
        assert per_robot("gain (1)") == "gain, per robot (1)"
        # Integer panels get whole-number ticks.
        page_figure = build_page(page_layout(page), ROBOTS)
        fill_page(page_figure, page, title)
        page_figure.figure.canvas.draw()
        index = labels.index("prime traveler (robot index)")
        ticks = page_figure.axes[index].get_yticks()
        assert np.allclose(ticks, np.round(ticks))
        # A count that stays 0: whole-number ticks on an axis from 0 (it once read -0.5, 0, 0.5).
        flat = page_figure.axes[labels.index("robots waiting (count)")]
        low, high = flat.get_ylim()
        shown = [tick for tick in flat.get_yticks() if low <= tick <= high]
        assert -0.1 < low < 0 and high >= 1 and shown == [0.0, 1.0], (low, high, shown)
    finally:
        recorder._painters.finish()
