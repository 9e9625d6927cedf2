"""The one palette of every picture tether draws: video, recording, viewer, tuning page, plots, reports.

Colours come from two colour-blind-safe sets: Okabe and Ito's eight
(Okabe & Ito, "Color Universal Design", 2002; the ``OKABE_ITO`` names) and
Paul Tol's "muted" qualitative scheme (Tol, "Colour Schemes", SRON
technical note, 2021; ``TOL_MUTED``) for the teams, which need more hues
than Okabe-Ito has. Every meaning has one colour (RGBA, 0..1, float32);
within any one picture's legend no two entries are closer than
:data:`MIN_LEGEND_DISTANCE` in CIELAB (tests/test_palette.py checks every
built-in's legend). docs/viewing.md lists what each colour means.

Link quality (a connected strategy's link weight, or a non-ideal radio's
delivery probability) is a neutral ramp, pale grey (0) to charcoal (1), the
only greys of the palette: it shares no hue with any robot, target or team.
Weak links are also thinner and fainter (:func:`link_width_share`), so a
start cluster's many weak links recede behind its few strong ones.

Pure data and arithmetic: no MuJoCo, no I/O.
"""

from __future__ import annotations

import numpy as np


def hex_rgba(code: str, alpha: float = 1.0) -> np.ndarray:
    """``#rrggbb`` -> RGBA (0..1, float32)."""
    code = code.lstrip("#")
    return np.array([int(code[k:k + 2], 16) / 255 for k in (0, 2, 4)] + [alpha], dtype=np.float32)


OKABE_ITO = {
    "black": "#000000", "orange": "#E69F00", "sky blue": "#56B4E9", "bluish green": "#009E73",
    "yellow": "#F0E442", "blue": "#0072B2", "vermillion": "#D55E00", "reddish purple": "#CC79A7",
}
TOL_MUTED = {
    "indigo": "#332288", "cyan": "#88CCEE", "teal": "#44AA99", "green": "#117733", "olive": "#999933",
    "sand": "#DDCC77", "rose": "#CC6677", "wine": "#882255", "purple": "#AA4499",
}
MIN_LEGEND_DISTANCE = 20.0  # CIE76 delta E: two legend entries of one picture at least this far apart

# The connected strategy's roles (Nestmeyer et al. 2017), each with its path in the same colour.
PRIME_TRAVELER = hex_rgba(OKABE_ITO["vermillion"])
SECONDARY_TRAVELER = hex_rgba(OKABE_ITO["blue"])
ANCHOR = hex_rgba(OKABE_ITO["reddish purple"])
CONNECTOR = hex_rgba(OKABE_ITO["sky blue"])
GOAL = hex_rgba(OKABE_ITO["orange"])  # a connected traveler's current target point
# Robots that no strategy colours (e.g. hover), by kind.
KIND = {"quadrotor": hex_rgba(OKABE_ITO["blue"]), "ground": hex_rgba(OKABE_ITO["bluish green"])}
# Whoever drives: the true targets, the EKF's estimates of them, each robot's reference.
TARGET_TRUE = hex_rgba(OKABE_ITO["yellow"])
TARGET_ESTIMATE = hex_rgba("#EE3377", 0.6)  # Tol's "vibrant" magenta
REFERENCE = hex_rgba(OKABE_ITO["black"], 0.8)
# The meeting methods: one colour per team (cycled), white for a robot with no meeting planned.
TEAMS = np.stack([hex_rgba(code) for code in TOL_MUTED.values()])
IDLE = hex_rgba("#FFFFFF")
DROPPED = IDLE  # continuous connectivity: a robot its team dropped as silent (no role, no links): white too
# Link quality ramp: value 0 (about to break / never delivered) to 1 (strong / always delivered).
LINK_WEAK = hex_rgba("#BBBBBB")
LINK_STRONG = hex_rgba("#333333")
LINK_ALPHA = (0.35, 0.95)  # at value 0 and 1
LINK_WIDTH_SHARE = (0.35, 1.0)  # a link's width at value 0 and 1, as a share of the full width
LINK_SCALE = (0.0, 0.5, 1.0)  # the values whose swatches the legends show
# Reports and plots: one colour per method, the same in every figure.
METHOD = {
    "intermittent": hex_rgba(OKABE_ITO["blue"]), "random_meeting": hex_rgba(OKABE_ITO["orange"]),
    "all_time": hex_rgba("#777777"), "connected_tracking": hex_rgba(OKABE_ITO["bluish green"]),
    "connected": hex_rgba(OKABE_ITO["vermillion"]),
}
PAPER = hex_rgba(OKABE_ITO["black"])  # a paper's reference values beside ours
SERIES = [hex_rgba(code) for code in ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9",
                                      "#000000", "#F0E442")]  # plots' per-robot lines, cycled
# The tuning page's live plots: one light neutral on its dark page. Each plot has its title, and a plot of
# the prime travelers drawn in the connector's sky blue beside the legend said the wrong thing.
PLOT_LINE_ON_DARK = hex_rgba("#D8DCE6")


def team(index: int) -> np.ndarray:
    """Team ``index``'s colour (RGBA, 0..1), cycled over :data:`TEAMS`."""
    return TEAMS[index % len(TEAMS)]


def link_rgba(value) -> np.ndarray:
    """(..., 4) RGBA of link qualities ``value`` in [0, 1] (clipped) on the link ramp."""
    v = np.clip(np.asarray(value, dtype=float), 0.0, 1.0)[..., None]
    rgb = (1.0 - v) * LINK_WEAK[:3] + v * LINK_STRONG[:3]
    alpha = LINK_ALPHA[0] + (LINK_ALPHA[1] - LINK_ALPHA[0]) * v
    return np.concatenate([rgb, alpha], axis=-1).astype(np.float32)


def link_width_share(value) -> np.ndarray:
    """A link's width as a share of the full width, for qualities ``value`` in [0, 1]."""
    v = np.clip(np.asarray(value, dtype=float), 0.0, 1.0)
    return LINK_WIDTH_SHARE[0] + (LINK_WIDTH_SHARE[1] - LINK_WIDTH_SHARE[0]) * v


def rgb8(rgba) -> tuple[int, int, int]:
    """RGB (0..255) of a colour given in 0..1."""
    return tuple(int(round(255 * min(max(float(c), 0.0), 1.0))) for c in list(rgba)[:3])


def hex_code(rgba) -> str:
    """``#rrggbb`` of a colour given in 0..1."""
    return "#{:02x}{:02x}{:02x}".format(*rgb8(rgba))


def lab(rgba) -> np.ndarray:
    """CIELAB (D65) of an sRGB colour given in 0..1."""
    c = np.asarray(list(rgba)[:3], dtype=float)
    linear = np.where(c > 0.04045, ((c + 0.055) / 1.055) ** 2.4, c / 12.92)
    xyz = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]) @ linear
    f = xyz / np.array([0.95047, 1.0, 1.08883])
    f = np.where(f > 0.008856, np.cbrt(f), 7.787 * f + 16 / 116)
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


def distance(a, b) -> float:
    """CIE76 colour difference (delta E) of two colours given in 0..1."""
    return float(np.linalg.norm(lab(a) - lab(b)))


def closest_pair(legend) -> tuple[float, str, str]:
    """The two entries of ``legend`` [(label, rgba)] nearest in colour: (delta E, label, label);
    (inf, "", "") for fewer than two entries."""
    best = (float("inf"), "", "")
    for k, (label_a, a) in enumerate(legend):
        for label_b, b in legend[k + 1:]:
            best = min(best, (distance(a, b), label_a, label_b))
    return best


# Every colour's plain name, for pictures whose legend is text (the viewer's, the recording's).
NAMES = {**OKABE_ITO, **TOL_MUTED, "magenta": "#EE3377", "white": "#FFFFFF", "pale grey": "#BBBBBB",
         "grey": "#777777", "charcoal": "#333333",
         "blue grey": "#96A0AF"}  # the recording's see-through obstacles (named "pale grey", a weak link's, before)


def colour_name(rgba) -> str:
    """The name in :data:`NAMES` of the colour nearest to ``rgba`` (0..1) in CIELAB."""
    return min(NAMES, key=lambda name: distance(hex_rgba(NAMES[name]), rgba))
