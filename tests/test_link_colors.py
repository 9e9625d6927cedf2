"""Link colours in the pictures: the palette's link ramp, by delivery probability under a real radio,
by the connected strategy's weight under ideal."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from sim.scenario import load
from tether.runner import build_simulation
from sim import palette
from viz.decorations import delivery_rgba, frame_legend, link_delivery_colors
from viz.video import LINK_RGBA, FrameView, draw_decorations, link_color


class Canvas:
    """What draw_decorations draws into, recorded: capsules (links, paths) and spheres."""

    metres_per_px = 0.01

    def __init__(self, world):
        self.world = world
        self.capsules: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.widths: list[float] = []

    def at_least(self, size_m, pixels):
        return max(size_m, pixels * self.metres_per_px)

    def _add_capsule(self, a, b, width, rgba):
        self.capsules.append((np.array(a), np.array(b), np.array(rgba, dtype=np.float32)))
        self.widths.append(float(width))

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


def _link_colours(simulation, frame, widths: list | None = None) -> list[np.ndarray]:
    canvas = Canvas(simulation.world)
    draw_decorations(canvas, frame)
    positions = frame.observation.position
    edges = frame.observation.links.edges
    links = canvas.capsules[: len(edges)]  # links are drawn first, in edge order
    for (a, b, _), (i, j) in zip(links, edges):
        assert np.allclose(a, positions[i]) and np.allclose(b, positions[j])
    if widths is not None:
        widths[:] = canvas.widths[: len(edges)]
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
    # A monotone ramp: higher delivery, darker and more opaque (the link stands out from the floor).
    ramp = delivery_rgba(np.linspace(0, 1, 11))
    assert np.all(np.diff(ramp[:, :3] @ np.array([0.2126, 0.7152, 0.0722])) < 0)
    assert np.all(np.diff(ramp[:, 3]) > 0)
    labels = [label for label, _ in frame_legend(frame)]
    assert {"link delivery 0 (packets lost)", "link delivery 0.5", "link delivery 1 (all delivered)"} <= set(labels)
    assert [label for label, _ in frame_legend(view)] == labels


def test_links_follow_the_weight_under_ideal_weak_ones_thinner():
    simulation, frame = _frame("ideal")
    weights = frame.commands.decorations.link_weights
    assert weights is not None and link_delivery_colors(frame) is None
    widths: list[float] = []
    colours = _link_colours(simulation, frame, widths)
    edges = frame.observation.links.edges
    assert colours and all(np.array_equal(c, link_color(weights[i, j])) for c, (i, j) in zip(colours, edges))
    link_weights = np.array([weights[i, j] for i, j in edges])
    assert link_weights.min() < 0.9 < link_weights.max()
    # Thinner the weaker: the start cluster's weak links recede behind the strong ones.
    order = np.argsort(link_weights)
    assert np.all(np.diff(np.array(widths)[order]) >= -1e-12) and widths[order[0]] < widths[order[-1]]
    labels = [label for label, _ in frame_legend(frame)]
    assert not any("delivery" in label for label in labels)
    assert {"link weight 1 (strong)", "link weight 0 (about to break)"} <= set(labels)
    view = FrameView.of(frame)
    assert view.observation.radio is None
    assert np.array_equal(LINK_RGBA, palette.link_rgba(1.0))


@pytest.mark.parametrize("preset", ["ideal", "ieee802154"])
def test_the_recording_legend_names_the_link_colours(preset):
    from viz.recording import RerunRecorder

    simulation, frame = _frame(preset, ticks=2)
    legend = RerunRecorder.legend(_LegendOnly(simulation.world), frame)
    assert ("link delivery 0.5" in legend) == (preset != "ideal")
    assert ("link weight 1 (strong)" in legend) == (preset == "ideal")


class _LegendOnly:
    """The recorder's state its legend reads."""

    def __init__(self, world):
        self.world = world
        self._radio_map_note = ""
