"""Paths in line styles: the pieces a dashed or dotted polyline is drawn as (hand-computed), and the
intermittent method's teams named in the legend with the style their paths are drawn in."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.intermittent.runtime import team_path_style
from sim.types import PATH_STYLES, Decorations
from viz.decorations import DASH_ON_SHARE, STYLE_PERIOD_SHARE, merged_polyline, styled_segments

L_SHAPE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.5, 0.0]])  # 1.5 m along, a corner at 1 m


def test_solid_is_the_polyline_s_segments_without_zero_length_ones():
    points = np.vstack([L_SHAPE[:2], L_SHAPE[1:]])  # the corner repeated: a zero-length segment
    pieces = styled_segments(points, "solid", 0.3)
    assert len(pieces) == 2
    np.testing.assert_allclose(pieces[1][0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(pieces[1][1], [1.0, 0.5, 0.0])


def test_a_solid_path_s_nearly_collinear_vertices_are_merged_and_its_corners_kept():
    # 0 .. 1 m along x with a 1 mm bump at 0.5 m, then a corner up to (1, 0.5): the bump is within
    # 2 mm of the chord and goes; the corner (0.5 m off the chord from the start to the end) stays.
    points = np.array([[0.0, 0, 0], [0.25, 0, 0], [0.5, 0.001, 0], [0.75, 0, 0], [1.0, 0, 0], [1.0, 0.25, 0],
                       [1.0, 0.5, 0]])
    np.testing.assert_allclose(merged_polyline(points, 0.002), [[0, 0, 0], [1, 0, 0], [1, 0.5, 0]])
    # Under a tolerance below the bump (its neighbours are 0.5 mm off the chords past them) they stay;
    # the vertex on the straight last leg still goes.
    np.testing.assert_allclose(merged_polyline(points, 0.0001), points[[0, 1, 2, 3, 4, 6]])
    np.testing.assert_allclose(merged_polyline(points[:2], 0.002), points[:2])
    np.testing.assert_allclose(merged_polyline(points, 0.0), points)


@pytest.mark.parametrize("style", ["dashed", "dotted"])
def test_dashes_start_every_period_and_cover_their_share_of_it(style):
    period = 0.5 / STYLE_PERIOD_SHARE[style]  # the style's own period is 0.5 m
    pieces = styled_segments(L_SHAPE, style, period)
    assert len(pieces) == 3  # starts at 0, 0.5, 1.0 m along
    np.testing.assert_allclose([a for a, _ in pieces], [[0, 0, 0], [0.5, 0, 0], [1.0, 0, 0]], atol=1e-12)
    on = DASH_ON_SHARE[style] * 0.5
    np.testing.assert_allclose(pieces[0][1], [on, 0, 0], atol=1e-12)
    np.testing.assert_allclose(pieces[2][1], [1.0, on, 0], atol=1e-12)  # the third runs up the second leg
    drawn = sum(np.linalg.norm(b - a) for a, b in pieces)
    assert drawn == pytest.approx(3 * on)


def test_dots_come_at_half_the_dashes_pitch():
    dashes, dots = (styled_segments(L_SHAPE, style, 0.5) for style in ("dashed", "dotted"))
    assert len(dots) == 2 * len(dashes)


def test_neighbouring_teams_differ_in_line_style_and_unknown_styles_are_refused():
    styles = [team_path_style(k) for k in range(8)]
    assert set(styles) == set(PATH_STYLES)
    assert all(a != b for a, b in zip(styles, styles[1:]))
    with pytest.raises(ValueError, match="path_styles"):
        Decorations(paths=((L_SHAPE, np.ones(4)),), path_styles=("wavy",))


def test_the_intermittent_legend_names_each_team_s_line_style_as_drawn():
    from sim.loop import run_ticks
    from sim.observers import Observer
    from sim.scenario import load
    from tether.runner import build_simulation

    class Last(Observer):
        frame = None

        def on_tick(self, frame):
            self.frame = frame

    scenario = load("intermittent-4", duration_s=0.5)
    sim = build_simulation(scenario)
    last = Last()
    run_ticks(sim, [last], scenario.duration_s)
    decorations = last.frame.commands.decorations
    assert decorations.path_styles is not None and len(decorations.path_styles) == len(decorations.paths)
    legend = dict((label, np.asarray(rgba)) for label, rgba in decorations.legend)
    for (points, rgba), style in zip(decorations.paths, decorations.path_styles):
        named = [label for label, colour in legend.items()
                 if label.startswith("team ") and np.allclose(colour[:3], np.asarray(rgba)[:3])]
        assert named and all(label.endswith(f", {style} path") for label in named), (named, style)
