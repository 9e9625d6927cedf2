"""A scenario written out as a commented TOML file (``tether init``).

Every key of every table is written, each under a comment with its meaning,
unit, default and accepted range. Nothing is written by hand per scenario:
the meaning is the field's source comment (:func:`sim.config.field_comments`,
the same help the tuning page shows), unit and range come from the field's
:func:`sim.config.param` metadata or its name, the default from the
dataclass. Unset optional keys are written commented out, so a user sees
they exist. The file reads back through :func:`sim.scenario.load` to the
same scenario.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import textwrap
import typing
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

from sim.config import bounds_text, field_comments, keys_table, replace_generated, to_table, unit_from_name
from sim.strategy import strategy_kind, strategy_kinds, strategy_params_class
from sim.scenario import Scenario, ScenarioBody, toml_value
from tether.strategies import BUILTIN_STRATEGIES

COMMENT_WIDTH = 100
# Top-level fields never written: a file takes its name from its own file name.
NOT_WRITTEN = ("name",)


def _default_text(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        default = f.default
    elif f.default_factory is not dataclasses.MISSING:
        default = f.default_factory()
        if dataclasses.is_dataclass(default):
            return ""
    else:
        return "required"
    if isinstance(default, float) and math.isnan(default):
        return "from the preset"
    if default is None:
        return "unset"
    return toml_value(to_table(default))


def _facts(f: dataclasses.Field, tp: Any) -> str:
    """"unit m/s; default 0.5; 0.05 to 3; one of ..." for one field."""
    meta = f.metadata
    parts = []
    unit = meta.get("unit") or unit_from_name(f.name)
    if unit:
        parts.append(f"unit {unit}")
    default = _default_text(f)
    if default:
        parts.append(default if default == "required" else f"default {default}")
    if bounds_text(f):
        parts.append(bounds_text(f))
    if get_origin(tp) is typing.Literal:
        parts.append("one of " + ", ".join(toml_value(a) for a in get_args(tp)))
    return "; ".join(parts)


def _comment(text: str) -> list[str]:
    return [f"# {line}" for line in textwrap.wrap(text, COMMENT_WIDTH - 2)] if text else []


def _key_lines(f: dataclasses.Field, tp: Any, value: Any, meaning: str) -> list[str]:
    # The meaning first, then the facts on a line of their own just above the key.
    lines = _comment(meaning) + [f"# [{_facts(f, tp)}]"]
    if value is None:
        lines.append(f"# {f.name} =   (unset)")
    else:
        lines.append(f"{f.name} = {toml_value(to_table(value))}")
    return lines


def _table_lines(obj: Any, skip: tuple[str, ...] = ()) -> tuple[list[str], list[tuple[dataclasses.Field, Any]]]:
    """The plain keys of dataclass ``obj`` as commented lines, and its fields
    that are sub-tables or arrays of tables (written after, as TOML requires)."""
    cls = type(obj)
    hints = get_type_hints(cls)
    comments = field_comments(cls)
    lines, nested = [], []
    for f in dataclasses.fields(cls):
        if not f.init or f.name in skip:
            continue
        value = getattr(obj, f.name)
        is_table_array = isinstance(value, tuple) and value and all(dataclasses.is_dataclass(v) for v in value)
        if dataclasses.is_dataclass(value) or is_table_array or _is_table_array_type(hints[f.name]):
            nested.append((f, value))
            continue
        lines += [""] + _key_lines(f, hints[f.name], value, comments.get(f.name, ""))
    return lines, nested


def _is_table_array_type(tp: Any) -> bool:
    if get_origin(tp) is not tuple:
        return False
    args = get_args(tp)
    return len(args) == 2 and args[1] is Ellipsis and dataclasses.is_dataclass(args[0])


def annotated_scenario(scenario: Scenario, scene_text: str | None = None, header: list[str] = ()) -> str:
    """``scenario`` as commented TOML. ``scene_text`` replaces the ``scene`` value
    (e.g. the path as the user typed it); ``header`` lines open the file."""
    body = ScenarioBody(**{k: getattr(scenario, k) for k in ScenarioBody.__dataclass_fields__})
    if scene_text is not None:
        body = dataclasses.replace(body, scene=scene_text)
    out = [f"# {line}" if line else "#" for line in header]
    lines, nested = _table_lines(body, skip=NOT_WRITTEN)
    out += lines
    comments = field_comments(ScenarioBody)
    arrays = []
    for f, value in nested:
        if isinstance(value, tuple):
            arrays.append((f, value))
            continue
        out += ["", ""] + _comment(comments.get(f.name, "")) + [f"[{f.name}]"]
        out += _table_lines(value)[0]
    kind = scenario.strategy.kind
    out += ["", "", "[strategy]"]
    out += _comment(f"the method that drives the robots ({kind}: {strategy_kind(kind).summary}); its keys follow")
    out.append(f"# [required; one of {', '.join(strategy_kinds())}]")
    out.append(f"kind = {toml_value(kind)}")
    out += _table_lines(scenario.strategy.params)[0]
    for f, entries in arrays:
        out += ["", ""] + _comment(comments.get(f.name, ""))
        if not entries:
            out.append(f"# (no [[{f.name}]] entries)")
        for entry in entries:
            out += ["", f"[[{f.name}]]"] + _table_lines(entry)[0]
    return "\n".join(out).replace("\n\n\n\n", "\n\n\n") + "\n"


def strategy_keys_section() -> str:
    """The documentation's tables of strategy keys: one per parameter class of the registered kinds."""
    kinds: dict[type, list[str]] = {}
    for kind in BUILTIN_STRATEGIES:
        kinds.setdefault(strategy_params_class(kind), []).append(kind)
    parts = []
    for cls, names in kinds.items():
        parts.append(f"Keys of {', '.join(f'`{name}`' for name in names)} (`{cls.__name__}`):")
        parts.append(keys_table(cls))
        for other in getattr(cls, "TABLE_SHARED_WITH", ()):
            parts.append(f"A table may also hold the keys of `{other.__name__}` (checked there, not used).")
        for key, instead in getattr(cls, "REMOVED_KEYS", {}).items():
            parts.append(f"`strategy.{key}` is no longer a key: {instead}.")
    return "\n\n".join(parts)


if __name__ == "__main__":
    target = Path(sys.argv[1])
    target.write_text(replace_generated(target.read_text(), strategy_keys_section()))
