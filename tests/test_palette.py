"""One palette for every picture: within each built-in's legend no two entries are closer in colour
than the palette's minimum distance, and everything drawn has its colour in the legend."""

from __future__ import annotations

import numpy as np
import pytest

from sim import palette
from sim.scenario import load
from tether.runner import build_simulation
from viz.decorations import frame_legend
from viz.scenery import scenery_legend
from viz.video import draw_decorations

# (scenario, overrides, ticks): every strategy a built-in runs, and a lossy radio's link scale.
CASES = {
    "hover": ("hover", [], 5),
    "connected": ("connected-office", [], 40),
    "connected-town": ("connected-town", [], 5),
    "connected-radio": ("connected-office", ['radio.preset="ieee802154"', "robots.0.count=6"], 5),
    "intermittent": ("intermittent-8", [], 30),
    "all_time": ("intermittent-8", ['strategy.kind="all_time"'], 30),
    "random_meeting": ("intermittent-8", ['strategy.kind="random_meeting"'], 30),
    "connected_tracking": ("intermittent-8", ['strategy.kind="connected_tracking"'], 30),
}


class Canvas:
    """What draw_decorations draws into: every capsule's and sphere's colour, recorded."""

    metres_per_px = 0.01

    def __init__(self, world):
        self.world = world
        self.colours: list[np.ndarray] = []

    def at_least(self, size_m, pixels):
        return max(size_m, pixels * self.metres_per_px)

    def _add_capsule(self, a, b, width, rgba):
        self.colours.append(np.asarray(rgba, dtype=float))

    def _add_sphere(self, p, radius, rgba):
        self.colours.append(np.asarray(rgba, dtype=float))


@pytest.fixture(scope="module", params=sorted(CASES))
def drawn(request):
    name, overrides, ticks = CASES[request.param]
    simulation = build_simulation(load(name, overrides, duration_s=5.0))
    for _ in range(ticks):
        frame, healthy = simulation.tick(decorations_wanted=True)
        assert healthy
    legend = frame_legend(frame, simulation.world.robot_kinds, scenery_legend(simulation.world.model))
    canvas = Canvas(simulation.world)
    draw_decorations(canvas, frame)
    return request.param, legend, canvas.colours


def test_no_two_legend_entries_share_a_colour(drawn):
    case, legend, _ = drawn
    assert len(legend) >= 3, case
    distance, a, b = palette.closest_pair(legend)
    assert distance >= palette.MIN_LEGEND_DISTANCE, f"{case}: {a!r} and {b!r} are {distance:.1f} apart"
    assert len({label for label, _ in legend}) == len(legend), case


def test_everything_drawn_has_its_colour_in_the_legend(drawn):
    case, legend, colours = drawn
    assert colours, case
    named = [np.asarray(rgba, dtype=float)[:3] for _, rgba in legend]
    for rgba in colours:
        # Links between the ramp's swatches are named by the ramp: blend the nearest two.
        nearest = min(palette.distance(rgba, c) for c in named)
        on_ramp = min(palette.distance(rgba, palette.link_rgba(v)) for v in np.linspace(0, 1, 21))
        assert min(nearest, on_ramp) < 8.0, (case, rgba)


def test_the_palette_holds_distinct_meanings_and_a_monotone_link_ramp():
    fixed = {"prime": palette.PRIME_TRAVELER, "secondary": palette.SECONDARY_TRAVELER, "anchor": palette.ANCHOR,
             "connector": palette.CONNECTOR, "goal": palette.GOAL, "target": palette.TARGET_TRUE,
             "reference": palette.REFERENCE, "idle": palette.IDLE, "link weak": palette.LINK_WEAK,
             "link strong": palette.LINK_STRONG}
    distance, a, b = palette.closest_pair(list(fixed.items()))
    assert distance >= palette.MIN_LEGEND_DISTANCE, (a, b, distance)
    teams = [(f"team {k}", palette.team(k)) for k in range(len(palette.TEAMS))]
    assert palette.closest_pair(teams)[0] >= palette.MIN_LEGEND_DISTANCE
    assert np.array_equal(palette.team(len(palette.TEAMS)), palette.team(0))  # cycled
    # CIELAB against a hand-computed reference: sRGB white is L = 100, a = b = 0; pure red (53.2, 80.1, 67.2).
    np.testing.assert_allclose(palette.lab((1, 1, 1)), (100, 0, 0), atol=0.05)
    np.testing.assert_allclose(palette.lab((1, 0, 0)), (53.24, 80.09, 67.20), atol=0.1)
    lightness = [palette.lab(palette.link_rgba(v))[0] for v in np.linspace(0, 1, 11)]
    assert np.all(np.diff(lightness) < 0)  # stronger links darker
    assert np.all(np.diff(palette.link_width_share(np.linspace(0, 1, 11))) > 0)  # ... and wider
    assert palette.hex_code(palette.hex_rgba("#0072B2")) == "#0072b2"
