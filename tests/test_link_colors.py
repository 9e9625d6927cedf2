"""Link colours in the pictures: by delivery probability under a real radio, today's under ideal."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from sim.scenario import load
from tether.runner import build_simulation
from viz.decorations import delivery_rgba, frame_legend, link_delivery_colors
from viz.video import LINK_RGBA, FrameView, draw_decorations, link_color


class Canvas:
    """What draw_decorations draws into, recorded: capsules (links, paths) and spheres."""

    metres_per_px = 0.01

    def __init__(self, world):
        self.world = world
        self.capsules: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def at_least(self, size_m, pixels):
        return max(size_m, pixels * self.metres_per_px)

    def _add_capsule(self, a, b, width, rgba):
        self.capsules.append((np.array(a), np.array(b), np.array(rgba, dtype=np.float32)))

    def _add_sphere(self, p, radius, rgba):
        pass


def _frame(preset: str, ticks: int = 20):
    scenario = load("connected-office", ["robots.0.count=6", f'radio.preset="{preset}"', "radio.tx_power_dbm=-56"],
                    duration_s=1.0)
    simulation = build_simulation(scenario)
    for _ in range(ticks):
        frame, healthy = simulation.tick(decorations_wanted=True)
        assert healthy
    return simulation, frame


def _link_colours(simulation, frame) -> list[np.ndarray]:
    canvas = Canvas(simulation.world)
    draw_decorations(canvas, frame)
    positions = frame.observation.position
    edges = frame.observation.links.edges
    links = canvas.capsules[: len(edges)]  # links are drawn first, in edge order
    for (a, b, _), (i, j) in zip(links, edges):
        assert np.allclose(a, positions[i]) and np.allclose(b, positions[j])
    return [rgba for _, _, rgba in links]


def test_links_follow_the_delivery_under_ieee802154():
    simulation, frame = _frame("ieee802154")
    edges = frame.observation.links.edges
    assert len(edges) >= 3
    delivery = frame.observation.radio.delivery
    values = np.array([delivery[i, j] for i, j in edges])
    assert values.min() < 0.99  # the low power puts some links on the slope, not all at 1
    expected = delivery_rgba(values)
    colours = _link_colours(simulation, frame)
    assert np.array_equal(np.array(colours), expected)
    assert np.array_equal(link_delivery_colors(frame), expected)
    # The video draws a picklable view of the frame: the same colours in the renderer process.
    view = pickle.loads(pickle.dumps(FrameView.of(frame)))
    assert np.array_equal(np.array(_link_colours(simulation, view)), expected)
    # A monotone ramp: higher delivery, brighter (viridis' lightness rises from 0 to 1).
    ramp = delivery_rgba(np.linspace(0, 1, 11))[:, :3] @ np.array([0.2126, 0.7152, 0.0722])
    assert np.all(np.diff(ramp) > 0)
    labels = [label for label, _ in frame_legend(frame)]
    assert {"link delivery 0", "link delivery 0.5", "link delivery 1"} <= set(labels)
    assert [label for label, _ in frame_legend(view)] == labels


def test_links_keep_todays_colours_under_ideal():
    simulation, frame = _frame("ideal")
    weights = frame.commands.decorations.link_weights
    assert weights is not None and link_delivery_colors(frame) is None
    colours = _link_colours(simulation, frame)
    assert colours and all(np.array_equal(c, link_color(weights[i, j]))
                           for c, (i, j) in zip(colours, frame.observation.links.edges))
    assert not any("delivery" in label for label, _ in frame_legend(frame))
    view = FrameView.of(frame)
    assert view.observation.radio is None
    assert np.array_equal(LINK_RGBA, np.array([0.1, 0.75, 0.2, 0.9], dtype=np.float32))  # unchanged default


@pytest.mark.parametrize("preset", ["ideal", "ieee802154"])
def test_the_recording_legend_names_the_link_colours(preset):
    from viz.recording import RerunRecorder

    simulation, frame = _frame(preset, ticks=2)
    legend = RerunRecorder.legend(_LegendOnly(simulation.world), frame)
    assert ("link delivery 0.5" in legend) == (preset != "ideal")
    assert ("link of full weight" in legend) == (preset == "ideal")


class _LegendOnly:
    """The recorder's state its legend reads."""

    def __init__(self, world):
        self.world = world
        self._radio_map_note = ""
