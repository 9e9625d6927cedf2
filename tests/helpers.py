"""Small builders shared by tests: write a scenario (and scene) to a folder."""

from __future__ import annotations

import textwrap
from pathlib import Path

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
