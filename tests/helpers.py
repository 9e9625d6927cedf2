"""Small builders shared by tests: write a scenario (and scene) to a folder."""

from __future__ import annotations

import textwrap
from pathlib import Path

from sim.observers import Observer

WALL_SCENE = """
<mujoco model="one_wall">
  <custom><numeric name="tether_bounds" data="0 0 0 10 10 5"/></custom>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.05" pos="5 5 0" group="0"/>
    <geom name="wall" type="box" size="0.1 3 2" pos="5 5 2" group="0"/>
    <camera name="top" pos="5 5 12" xyaxes="1 0 0 0 1 0" projection="orthographic" fovy="10.6"/>
  </worldbody>
</mujoco>
"""


def write_scene(folder: Path, xml: str = WALL_SCENE, name: str = "scene.xml") -> Path:
    path = folder / name
    path.write_text(textwrap.dedent(xml))
    return path


def write_scenario(folder: Path, body: str, name: str = "scenario.toml") -> Path:
    path = folder / name
    path.write_text(textwrap.dedent(body))
    return path


def rrd_chunks(path) -> dict[str, list]:
    """Entity path -> the chunks of a Rerun file, read back through RrdReader."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(str(path)).store().stream().to_chunks():
        out.setdefault(chunk.entity_path, []).append(chunk)
    return out


def rrd_rows(chunks) -> int:
    return sum(c.num_rows for c in chunks)


def rrd_scalars(chunks, timeline: str = "sim_time") -> tuple[list, list]:
    """(times, values) of a Scalars entity, sorted by time."""
    pairs = []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        names = batch.schema.names
        times = batch.column(names.index(timeline)).to_pylist()
        values = batch.column(next(i for i, n in enumerate(names) if n.endswith("scalars"))).to_pylist()
        pairs += [(t, v[0] if isinstance(v, list) else v) for t, v in zip(times, values)]
    pairs.sort(key=lambda p: p[0])
    return [p[0] for p in pairs], [p[1] for p in pairs]


def rrd_texts(chunks, timeline: str = "tick") -> list[tuple]:
    """(time on ``timeline`` or None, text) of a TextLog entity, in file order."""
    out = []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        names = batch.schema.names
        times = batch.column(names.index(timeline)).to_pylist() if timeline in names else [None] * batch.num_rows
        texts = batch.column(next(i for i, n in enumerate(names) if n.endswith("text"))).to_pylist()
        out += [(t, str(v[0] if isinstance(v, list) else v)) for t, v in zip(times, texts)]
    return out


def rrd_column(chunks, suffix: str, timeline: str = "tick") -> list[tuple]:
    """(time on ``timeline``, value) of the component column ending in ``suffix``
    (e.g. ``"Points3D:colors"``) over the temporal chunks that hold it, sorted by time."""
    out = []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if timeline not in names or not any(n.endswith(suffix) for n in names):
            continue
        column = batch.column(next(i for i, n in enumerate(names) if n.endswith(suffix))).to_pylist()
        out += list(zip(batch.column(names.index(timeline)).to_pylist(), column))
    out.sort(key=lambda p: p[0])
    return out


def recorded_ticks(n_ticks: int, ticks_per_row: int) -> list[int]:
    """The ticks a recording with a period of ``ticks_per_row`` control ticks
    holds for a run of ``n_ticks``: every period and the last tick."""
    return sorted(set(range(0, n_ticks, ticks_per_row)) | {n_ticks - 1})


class TickLog(Observer):
    """An observer keeping, for every tick, a copy of ``frame.scalars`` and
    the number of communication links (pass it to ``tether.runner.run`` as an
    extra observer)."""

    def __init__(self):
        self.scalars: list[dict] = []
        self.links: list[int] = []
        self.times: list[float] = []
        self.robot_scalar_names: set[str] = set()

    def on_tick(self, frame) -> None:
        assert frame.observation.tick == len(self.scalars)
        self.scalars.append(dict(frame.scalars))
        self.links.append(len(frame.observation.links.edges))
        self.times.append(frame.observation.time_s)
        self.robot_scalar_names |= set(frame.commands.decorations.robot_scalars)

    def close(self, status: str) -> None:
        pass

    def series(self, name: str):
        import numpy as np

        return np.array([s[name] for s in self.scalars], dtype=float)


def check_static_once_and_both_timelines(chunks: dict, control_period_s: float) -> None:
    """Static entities hold one row (logged once); every temporal row is on
    both timelines, with sim_time = tick x control period."""
    for entity, parts in chunks.items():
        assert rrd_rows([c for c in parts if c.is_static]) <= 1, entity
        for chunk in parts:
            if chunk.is_static:
                continue
            batch = chunk.to_record_batch()
            names = batch.schema.names
            assert "sim_time" in names and "tick" in names, (entity, names)
            for time, tick in zip(batch.column("sim_time").to_pylist(), batch.column("tick").to_pylist()):
                assert abs(time.total_seconds() - tick * control_period_s) < 1e-6, (entity, time, tick)


def unpack_rgba(packed: int) -> tuple[int, int, int, int]:
    """Rerun's packed 0xRRGGBBAA colour as (r, g, b, a)."""
    return (packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255, packed & 255


def png_is_a_drawn_figure(path) -> bool:
    """A PNG of a real figure: PNG signature, a sizeable canvas, and ink on it."""
    import imageio.v2 as imageio

    if path.read_bytes()[:8] != b"\x89PNG\r\n\x1a\n":
        return False
    image = imageio.imread(path)
    return image.shape[0] > 200 and image.shape[1] > 200 and float(image.std()) > 10
