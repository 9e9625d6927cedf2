"""The radio map: mean received power from one robot over a scene's floor plan (``tether radiomap``).

The computation is ``sim.radio.radiomap.radio_map`` (pure); here: the
transmitting robot, the scene, and the figure. Under ``ideal`` the
``[radio]`` table's 802.15.4 figures are used (``RadioConfig`` fills them).
:func:`write_radio_map_png` draws it with matplotlib (Agg): walls, the 50 %
delivery contour (``channel.sensitivity_dbm``), the transmitter, a colour bar.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from sim.config import ConfigError
from sim.geometry import Boxes
from sim.radio.config import RadioConfig
from sim.radio.radiomap import MAP_CELLS, RadioMap, colour_limits, radio_map

RECORDING_CELLS = 160  # receivers along the longer side in the recording's mesh (a vertex each)
PNG_SOFTWARE = "tether radiomap"  # the PNG's Software text: a file tether wrote (may be replaced)
FIGURE_SIZE_IN = (8.0, 6.5)
FIGURE_DPI = 150  # 1200 x 975 px
INFINITE_BOX_M = 100.0  # boxes wider than this (planes' slabs) are no walls in the picture


# --- The transmitter ------------------------------------------------------------------------------

def robot_names(kinds: list[str]) -> list[str]:
    """The robots' names in robot order, as the world names them (quad0, ground0, ...)."""
    from sim.world import ROBOT_PREFIX

    counters = {kind: 0 for kind in ROBOT_PREFIX}
    names = []
    for kind in kinds:
        names.append(f"{ROBOT_PREFIX[kind]}{counters[kind]}")
        counters[kind] += 1
    return names


def _ground_height_m() -> float:
    """A ground robot's body height, m (its model file's base: where ``sim.world.place_robots`` puts it)."""
    import mujoco

    from sim.world import ROBOT_FILES

    return float(mujoco.MjSpec.from_file(str(ROBOT_FILES["ground"])).compile().body("base").pos[2])


def transmitter_of(scenario, robot: str | None) -> tuple[int, str, np.ndarray]:
    """(index, name, start position (3,), m) of ``robot`` (a name like quad0 or an index; None: robot 0);
    ConfigError('--from') for an unknown one."""
    starts = scenario.robot_starts()
    kinds = [kind for kind, _ in starts]
    names = robot_names(kinds)
    if robot is None:
        index = 0
    elif robot in names:
        index = names.index(robot)
    elif robot.strip().isdigit() and int(robot) < len(names):
        index = int(robot)
    else:
        shown = ", ".join(names) if len(names) <= 12 else f"{', '.join(names[:12])}, ..."
        raise ConfigError("--from", f"no robot {robot!r} (robots: {shown}, or an index 0 to {len(names) - 1})")
    position = np.array(starts[index][1], dtype=float)
    if kinds[index] == "ground":
        position[2] = _ground_height_m()
    return index, names[index], position


def scenario_radio_map(scenario, robot: str | None = None) -> tuple[RadioMap, str, Boxes]:
    """The radio map of ``scenario`` from ``robot``'s start (see :func:`transmitter_of`), the robot's name and
    the scene's obstacle boxes."""
    import mujoco

    from sim.world import extract_obstacles, load_scene_spec, obstacle_wall_losses, scene_bounds

    _, name, position = transmitter_of(scenario, robot)
    model = load_scene_spec(scenario.scene_path).compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    obstacles = extract_obstacles(model, data)
    bounds = scene_bounds(model, obstacles)
    return radio_map(scenario.radio, obstacles, obstacle_wall_losses(model), bounds, position), name, obstacles


def world_radio_map(world, config: RadioConfig, robot: int = 0, cells: int = MAP_CELLS) -> RadioMap:
    """The radio map from ``robot``'s current position in a built ``sim.world.World``."""
    position = np.array(world.data.xpos[world.body_ids[robot]], dtype=float)
    return radio_map(config, world.obstacles, world.wall_loss_db, world.bounds, position, cells=cells)


# --- Pictures -------------------------------------------------------------------------------------

def wall_footprints(obstacles: Boxes, height_m: float | None = None) -> list[np.ndarray]:
    """The (k, 2) outlines (convex hulls of the projected corners) of the finite obstacle boxes, those
    reaching ``height_m`` when given (walls at the map's height, not the floor or a low table)."""
    from scipy.spatial import ConvexHull

    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    out = []
    for center, half, rotation in zip(obstacles.centers, obstacles.half_sizes, obstacles.rotations):
        if np.any(half[:2] > INFINITE_BOX_M):
            continue
        corners = center + (signs * half) @ rotation.T
        if height_m is not None and not corners[:, 2].min() <= height_m <= corners[:, 2].max():
            continue
        flat = corners[:, :2]
        try:
            out.append(flat[ConvexHull(flat).vertices])
        except Exception:  # a degenerate (zero-width) footprint: its bounding segment
            out.append(flat[[np.argmin(flat[:, 0]), np.argmax(flat[:, 0])]])
    return out


def check_png_target(path: Path) -> None:
    """ConfigError('--out') unless ``path`` is new or a PNG tether wrote (never replace anything else)."""
    if path.suffix.lower() != ".png":
        raise ConfigError("--out", f"must name a .png file, got {str(path)!r}")
    if not path.exists() and not path.is_symlink():
        return
    wrote = False
    if path.is_file() and not path.is_symlink():
        try:
            from PIL import Image

            with Image.open(path) as image:
                wrote = image.format == "PNG" and image.info.get("Software") == PNG_SOFTWARE
        except Exception:
            wrote = False
    if not wrote:
        raise ConfigError("--out", f"{path} exists and is not a radio map tether wrote; not replacing it")


def write_radio_map_png(radio: RadioMap, obstacles: Boxes, path: Path, title: str, robot_name: str) -> Path:
    """The figure of ``radio``: power in dBm, walls, the 50 % delivery contour, the transmitter, a colour
    bar, ``title``; written atomically to ``path`` (a PNG whose Software text marks it as tether's)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon

    import textwrap

    from matplotlib.lines import Line2D

    fig = Figure(figsize=FIGURE_SIZE_IN, dpi=FIGURE_DPI)
    ax = fig.add_axes((0.09, 0.21, 0.7, 0.7))
    cax = ax.inset_axes((1.04, 0.0, 0.035, 1.0))  # follows the axes' box, whatever the floor plan's aspect
    low, high = colour_limits(radio)
    dx = (radio.x[1] - radio.x[0]) / 2
    dy = (radio.y[1] - radio.y[0]) / 2
    extent = (radio.x[0] - dx, radio.x[-1] + dx, radio.y[0] - dy, radio.y[-1] + dy)
    image = ax.imshow(radio.power_dbm, origin="lower", extent=extent, cmap="viridis", vmin=low, vmax=high,
                      interpolation="nearest", aspect="equal")
    weakest = float(np.nanmin(radio.power_dbm))
    bar = fig.colorbar(image, cax=cax, extend="min" if weakest < low else "neither")
    bar.set_label("mean received power (dBm)", fontsize=11)
    bar.ax.tick_params(labelsize=10)
    sensitivity = f"{radio.sensitivity_dbm:.1f} dBm: 50 % delivery"
    handles = []
    reached = weakest < radio.sensitivity_dbm < float(np.nanmax(radio.power_dbm))
    if reached:
        ax.contour(radio.x, radio.y, radio.power_dbm, levels=[radio.sensitivity_dbm], colors="white",
                   linewidths=2.0, linestyles="--", zorder=2)
        bar.ax.axhline(radio.sensitivity_dbm, color="white", linewidth=2.0, linestyle="--")
        handles.append(Line2D([], [], color="white", linestyle="--", linewidth=2.0, label=sensitivity))
    for outline in wall_footprints(obstacles, radio.height_m):
        ax.add_patch(Polygon(outline, closed=True, facecolor="0.1", edgecolor="white", linewidth=0.6, zorder=3))
    handles.append(Polygon(np.zeros((3, 2)), facecolor="0.1", edgecolor="white", label="walls and obstacles"))
    tx = radio.transmitter
    ax.plot(tx[0], tx[1], marker="*", markersize=18, markerfacecolor="white", markeredgecolor="black",
            markeredgewidth=1.2, zorder=5, linestyle="none")
    handles.append(Line2D([], [], marker="*", markersize=14, markerfacecolor="white", markeredgecolor="black",
                          linestyle="none", label=f"transmitter {robot_name}"))
    fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.075), ncols=len(handles), fontsize=10,
               frameon=True,
               facecolor="0.35", labelcolor="white", edgecolor="none", handlelength=2.5)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("x (m)", fontsize=11)
    ax.set_ylabel("y (m)", fontsize=11)
    ax.tick_params(labelsize=10)
    fig.suptitle(title, fontsize=12, y=0.975)
    caption = (f"Mean received power at z = {radio.height_m:.2f} m, the transmitter's height: log-distance path "
               "loss and the walls crossed (each box once). Shadowing and fading are random and are left out.")
    if not reached:
        caption += (f" The 50 % delivery power ({radio.sensitivity_dbm:.1f} dBm) is "
                    f"{'not reached' if weakest > radio.sensitivity_dbm else 'not exceeded'} on this floor plan.")
    fig.text(0.02, 0.012, "\n".join(textwrap.wrap(caption, 118)), fontsize=9, va="bottom", ha="left")
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=".radiomap-", suffix=".png", dir=path.parent)
    os.close(handle)
    try:
        fig.savefig(temporary, dpi=FIGURE_DPI, metadata={"Software": PNG_SOFTWARE})
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)
    return path
