"""The radio map's computation: mean received power from one transmitter on a grid of receivers.

A grid of receivers at the transmitter's height over a floor plan, one
segment per receiver, the walls each crosses batched in one call
(``sim.radio.walls.SceneWalls``), and the link budget of ``sim.radio.channel``
(log-distance path loss + walls). Shadowing and fading are random and are left
out: the map is the mean power. Pure numpy, no MuJoCo, no I/O; ``tether
radiomap`` draws it (``tether.radiomap``), the recording logs it
(``viz.recording``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.geometry import Boxes
from sim.radio import channel
from sim.radio.config import RadioConfig
from sim.radio.walls import SceneWalls

MAP_CELLS = 240  # receivers along the longer side of the floor plan
CONTOUR_DELIVERY = 0.5  # the contour: received power at which the reference packet arrives half the time
COLOUR_RANGE_DB = 30.0  # the colour scale reaches this far under the contour


@dataclass(frozen=True)
class RadioMap:
    """Mean received power on a grid of receivers at ``height_m``."""

    x: np.ndarray  # (nx,) cell centres, m
    y: np.ndarray  # (ny,) cell centres, m
    height_m: float  # receivers' (and the transmitter's) height, m
    transmitter: np.ndarray  # (3,) m
    power_dbm: np.ndarray  # (ny, nx) mean received power, dBm: tx power - PL(d) - walls
    walls: np.ndarray  # (ny, nx) int: obstacle boxes crossed on the way
    wall_loss_db: np.ndarray  # (ny, nx) dB: their summed loss
    sensitivity_dbm: float  # received power at CONTOUR_DELIVERY delivery of the reference packet, dBm
    preset: str  # the scenario's radio.preset


def loss_per_box_db(config: RadioConfig, scene_wall_loss_db: np.ndarray | None, count: int) -> np.ndarray:
    """Each box's loss, dB: the scene's figure where it gives one, ``radio.wall_loss_db`` elsewhere."""
    scene = np.full(count, np.nan) if scene_wall_loss_db is None else np.asarray(scene_wall_loss_db, dtype=float)
    return np.where(np.isnan(scene), config.wall_loss_db, scene)


def reference_sensitivity_dbm(config: RadioConfig, delivery: float = CONTOUR_DELIVERY) -> float:
    """Received power (dBm) at which the reference packet (``config.reference_length_bits``) arrives with
    probability ``delivery`` at the mean SNR (``channel.sensitivity_dbm`` on the preset's PER curve)."""
    radio = config.radio

    def per(power_dbm: float) -> float:
        return float(channel.packet_error_rate_at_power(
            power_dbm, config.reference_length_bits, modulation=radio.modulation,
            noise_floor_dbm=config.noise_floor_dbm, bandwidth_hz=radio.bandwidth_hz,
            bitrate_bps=config.bitrate_bps))

    floor = config.noise_floor_dbm
    return channel.sensitivity_dbm(per, 1.0 - delivery, low_dbm=floor - 80.0, high_dbm=floor + 120.0)


def radio_map(config: RadioConfig, obstacles: Boxes, scene_wall_loss_db: np.ndarray | None, bounds: np.ndarray,
              transmitter: np.ndarray, cells: int = MAP_CELLS) -> RadioMap:
    """Mean received power from ``transmitter`` ((3,), m) at receivers on a grid over ``bounds``' floor
    plan ((2, 3) min and max corners, m; ``cells`` along the longer side) at the transmitter's height."""
    transmitter = np.asarray(transmitter, dtype=float)
    lo, hi = np.asarray(bounds, dtype=float)
    step = max(hi[0] - lo[0], hi[1] - lo[1]) / cells
    nx = max(2, int(round((hi[0] - lo[0]) / step)))
    ny = max(2, int(round((hi[1] - lo[1]) / step)))
    x = lo[0] + (np.arange(nx) + 0.5) * (hi[0] - lo[0]) / nx
    y = lo[1] + (np.arange(ny) + 0.5) * (hi[1] - lo[1]) / ny
    gx, gy = np.meshgrid(x, y)
    receivers = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, transmitter[2])])
    starts = np.broadcast_to(transmitter, receivers.shape)
    walls = SceneWalls(obstacles, loss_per_box_db(config, scene_wall_loss_db, len(obstacles)))
    crossed = walls.crossed(starts, receivers)
    distance = np.linalg.norm(receivers - transmitter, axis=1)
    path_loss = channel.log_distance_path_loss_db(distance, config.path_loss_exponent, config.reference_loss_db,
                                                  total_wall_loss_db=crossed.loss_db)
    power = channel.received_power_dbm(config.tx_power_dbm, path_loss)
    shape = gx.shape
    return RadioMap(x, y, float(transmitter[2]), transmitter, power.reshape(shape), crossed.count.reshape(shape),
                    crossed.loss_db.reshape(shape), reference_sensitivity_dbm(config), config.preset)


def colour_limits(radio: RadioMap) -> tuple[float, float]:
    """(low, high) dBm of the colour scale: from 30 dB under the contour to the strongest power."""
    high = float(np.nanmax(radio.power_dbm))
    low = max(float(np.nanmin(radio.power_dbm)), radio.sensitivity_dbm - COLOUR_RANGE_DB)
    return (min(low, high - 1.0), high)
