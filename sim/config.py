"""TOML tables -> frozen dataclasses, with errors that name the field.

Every parameter dataclass in tether is built through :func:`build`: unknown
keys are errors, types are checked, and ``__post_init__`` validation errors
(ValueError) are re-raised with the full dotted field path. The CLI turns a
:class:`ConfigError` into one line and exit code 2.

Parameters declare their unit and bounds with :func:`param` (field metadata
``unit``, ``min``, ``max``, ``step``, ``min_exclusive``, ``note``); :func:`build`
enforces the bounds for every table it reads, so a scenario file, a ``--set``
override and the tuning page are refused by the same rule, and a parameter
class calls :func:`check_params` in ``__post_init__`` so an object built in
code is held to them too. Checks that relate two fields stay in
``__post_init__`` through :func:`require`. The tuning page reads the same
metadata to draw sliders, :func:`keys_table` to write the documentation's
tables of keys.

A parameter class may declare two class attributes that :func:`build` reads:
``REMOVED_KEYS`` (key -> what to set instead: a table that still sets the key
is refused with that one line) and ``TABLE_SHARED_WITH`` (parameter classes
whose keys a table may also hold: checked by their class and not kept, so one
scenario file runs under several strategy kinds).
"""

from __future__ import annotations

import dataclasses
import inspect
import io
import math
import sys
import tokenize
import types
import typing
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints


MAX_INT = 2**63 - 1  # integers beyond int64 are refused wherever they go
MAX_TOML_BYTES = 1_000_000  # a scenario or sweep file is a short text
MAX_NESTING = 32  # lists and tables inside each other: a scenario needs 4, a sweep's grid one more


def _number_text(value: float) -> str:
    return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)


def allows_infinity(f: dataclasses.Field) -> bool:
    """Whether a float field may be +-inf: its metadata says ``allow_inf`` or
    its default is infinite (e.g. an uncapped force limit). NaN never is."""
    if f.metadata.get("allow_inf"):
        return True
    return isinstance(f.default, float) and math.isinf(f.default)


class ConfigError(ValueError):
    """A scenario value is wrong; ``field`` is its dotted path."""

    def __init__(self, field: str, problem: str):
        super().__init__(f"{field}: {problem}")
        self.field = field
        self.problem = problem


def nesting_depth(value: Any) -> int:
    """How deeply lists and tables nest in ``value`` (a scalar: 0), without recursion."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, dict):
            node = list(node.values())
        if isinstance(node, (list, tuple)):
            deepest = max(deepest, depth + 1)
            if depth + 1 > MAX_NESTING:
                return depth + 1
            stack.extend((child, depth + 1) for child in node)
    return deepest


def check_nesting(value: Any, field: str) -> Any:
    """ConfigError (naming ``field``) for lists or tables nested deeper than ``MAX_NESTING``."""
    if nesting_depth(value) > MAX_NESTING:
        raise ConfigError(field, f"lists or tables nested more than {MAX_NESTING} deep")
    return value


def parse_toml(text: str, field: str, what: str) -> dict:
    """``tomllib.loads`` with its failures (nesting too deep for the parser included) as one
    ConfigError naming ``field``; ``what`` says what the text is in the message."""
    import tomllib

    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(field, f"{what} is not valid TOML: {err}") from None
    except RecursionError:
        raise ConfigError(field, f"{what} is not valid TOML: lists or tables nested too deeply") from None
    return check_nesting(table, field)


def read_toml_file(path: Path, field: str) -> dict:
    """A TOML file's table, its size bounded before it is read (``MAX_TOML_BYTES``): one
    ConfigError naming ``field`` for a file that cannot be read, is too large, is not UTF-8
    text, is not TOML or nests too deeply."""
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_TOML_BYTES + 1)
    except OSError as err:
        raise ConfigError(field, f"cannot read {path}: {err.strerror or err}") from None
    if len(raw) > MAX_TOML_BYTES:
        raise ConfigError(field, f"{path} is larger than {MAX_TOML_BYTES} bytes; not a {field} file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(field, f"{path} is not a text file (byte {err.start} is not UTF-8)") from None
    if "\0" in text:
        raise ConfigError(field, f"{path} is not a text file (it holds NUL bytes)")
    return parse_toml(text, field, str(path))


def builtin_descriptions(folder: Path) -> dict[str, str]:
    """Built-in name -> its file's ``description``, for every TOML file in ``folder``."""
    import tomllib

    out = {}
    for path in sorted(folder.glob("*.toml")):
        with open(path, "rb") as f:
            out[path.stem] = tomllib.load(f).get("description", "")
    return out


def builtin_or_file(name_or_path: str, folder: Path, what: str) -> Path:
    """``folder/NAME.toml`` for a built-in name, else the file at the path; ConfigError (field
    ``what``) naming the built-ins when it is neither."""
    builtin = folder / f"{name_or_path}.toml"
    path = builtin if builtin.is_file() else Path(name_or_path).expanduser()
    if not path.is_file():
        names = ", ".join(builtin_descriptions(folder))
        raise ConfigError(what, f"'{name_or_path}' is neither a built-in {what} ({names}) nor a file")
    return path


def _type_name(tp: Any) -> str:
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a string"
    origin = get_origin(tp)
    if origin in (tuple, list):
        return "a list"
    if dataclasses.is_dataclass(tp):
        return "a table"
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, field: str, allow_inf: bool = False) -> Any:
    """``value`` as type ``tp``; numbers must be finite (``allow_inf``: +-inf
    too, for fields whose default is infinite or whose metadata says so)."""
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = get_args(tp)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(value, option, field, allow_inf)
            except ConfigError as err:
                errors.append(err)
        # Report the most specific failure (deepest field path).
        raise max(errors, key=lambda e: len(e.field))
    if typing.get_origin(tp) is typing.Literal:
        if value not in get_args(tp):
            allowed = ", ".join(repr(a) for a in get_args(tp))
            raise ConfigError(field, f"must be one of {allowed}, got {value!r}")
        return value
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(field, f"must be true or false, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(field, f"must be a number, got {value!r}")
        try:
            number = float(value)
        except OverflowError:
            raise ConfigError(field, f"must be a number of at most {sys.float_info.max:.3g}, got {value}") from None
        if math.isnan(number) or (math.isinf(number) and not allow_inf):
            raise ConfigError(field, f"must be a finite number, got {_number_text(number)}")
        return number
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(field, f"must be an integer, got {value!r}")
        if abs(value) > MAX_INT:
            raise ConfigError(field, f"must be an integer of at most {MAX_INT} in size, got {value}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(field, f"must be a string, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(field, f"must be a list, got {value!r}")
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{field}.{i}", allow_inf) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(field, f"must have {len(args)} entries, got {len(value)}")
        return tuple(_convert(v, a, f"{field}.{i}", allow_inf) for i, (v, a) in enumerate(zip(value, args)))
    if dataclasses.is_dataclass(tp):
        return build(tp, value, field)
    raise TypeError(f"unsupported config type {tp!r} at {field}")


def build(cls: type, table: Any, field: str = "") -> Any:
    """Build dataclass ``cls`` from a TOML table; errors name ``field.key``."""
    if not isinstance(table, dict):
        raise ConfigError(field or cls.__name__, f"must be a table, got {table!r}")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    prefix = f"{field}." if field else ""
    for key in sorted(set(table) - names):
        if key in getattr(cls, "REMOVED_KEYS", {}):
            raise ConfigError(prefix + key, f"is no longer a key; {cls.REMOVED_KEYS[key]}")
    shared = getattr(cls, "TABLE_SHARED_WITH", ())
    for other in shared:
        theirs = {key: value for key, value in table.items()
                  if key not in names and key in {f.name for f in dataclasses.fields(other) if f.init}}
        if theirs:
            build(other, theirs, field)  # checked by their class, not kept here
        table = {key: value for key, value in table.items() if key not in theirs}
    unknown = sorted(set(table) - names)
    if unknown:
        also = "".join(f"; also {other.__name__}'s keys" for other in shared)
        raise ConfigError(
            f"{prefix}{unknown[0]}",
            f"unknown key (allowed: {', '.join(sorted(names))}{also})",
        )
    kwargs = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        if f.name in table:
            kwargs[f.name] = _convert(table[f.name], hints[f.name], prefix + f.name, allows_infinity(f))
            check_bounds(f, kwargs[f.name], prefix + f.name)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(prefix + f.name, "is required")
    try:
        return cls(**kwargs)
    except ConfigError as err:
        if field and not err.field.startswith(prefix):
            raise ConfigError(prefix + err.field, err.problem) from None
        raise
    except ValueError as err:
        # Parameter classes raise ValueError("name: problem"); attach the path.
        text = str(err)
        name, sep, problem = text.partition(": ")
        if sep and " " not in name:
            raise ConfigError(prefix + name, problem) from None
        raise ConfigError(field or cls.__name__, text) from None


def to_table(obj: Any) -> Any:
    """Dataclass -> plain dict/list tree suitable for TOML or JSON."""
    if dataclasses.is_dataclass(obj):
        return {
            f.name: to_table(getattr(obj, f.name))
            for f in dataclasses.fields(obj)
            if f.init and getattr(obj, f.name) is not None
        }
    if isinstance(obj, (list, tuple)):
        return [to_table(v) for v in obj]
    return obj


def param(default: Any = dataclasses.MISSING, *, unit: str = "", min: float | None = None,
          max: float | None = None, step: float | None = None, tunable: bool = True,
          allow_inf: bool = False, above: float | None = None, note: str = "") -> Any:
    """A dataclass field with its unit and bounds, e.g.
    ``speed_mps: float = param(0.5, unit="m/s", min=0.05, max=3.0)``.

    ``min`` and ``max`` are inclusive; ``above`` is an exclusive lower bound
    (``above=0.0``: must be positive). :func:`build` and :func:`check_params`
    refuse values outside them (``note``: why, in parentheses in the message);
    the tuning page draws a slider over the range (``step``: slider
    resolution, default range/100) and leaves out fields with
    ``tunable=False``. Numbers must be finite unless ``allow_inf`` (or the
    default is infinite). A tuple of numbers is held to the bounds entry by entry.
    """
    if above is not None and min is not None:
        raise TypeError("param takes min or above, not both")
    metadata = {"unit": unit, "min": above if above is not None else min, "max": max, "step": step,
                "tunable": tunable, "allow_inf": allow_inf, "min_exclusive": above is not None, "note": note}
    return dataclasses.field(default=default, metadata=metadata)


def _number(value: float) -> str:
    return f"{value:g}"


def bounds_text(f: dataclasses.Field) -> str:
    """The field's accepted range in words ("0.05 to 3", "above 0", "at least 1"), or ""."""
    low, high = f.metadata.get("min"), f.metadata.get("max")
    exclusive = f.metadata.get("min_exclusive", False)
    if low is not None and high is not None:
        return f"above {_number(low)}, at most {_number(high)}" if exclusive else f"{_number(low)} to {_number(high)}"
    if low is not None:
        return f"above {_number(low)}" if exclusive else f"at least {_number(low)}"
    if high is not None:
        return f"at most {_number(high)}"
    return ""


def _rule(f: dataclasses.Field, value: Any) -> str | None:
    """What ``value`` breaks of the field's bounds ("must be in [0, 1] m"), or None."""
    meta = f.metadata
    low, high, exclusive = meta.get("min"), meta.get("max"), meta.get("min_exclusive", False)
    too_low = low is not None and not (value > low if exclusive else value >= low)
    too_high = high is not None and not value <= high
    if not (too_low or too_high):
        return None
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    if isinstance(value, int):  # a count: the side it breaks
        if too_low:
            return f"must be an integer {'>' if exclusive else '>='} {_number(low)}"
        return f"must be at most {_number(high)}"
    if low is not None and high is not None:
        return f"must be in {'(' if exclusive else '['}{_number(low)}, {_number(high)}]{unit}"
    if low is not None:
        if exclusive:
            return "must be positive" if low == 0 else f"must be above {_number(low)}{unit}"
        return f"must be at least {_number(low)}{unit}"
    return f"must be at most {_number(high)}{unit}"


def check_bounds(f: dataclasses.Field, value: Any, field: str) -> None:
    """ConfigError if ``value`` (or an entry of a tuple of numbers) lies outside the field's bounds."""
    if f.metadata.get("min") is None and f.metadata.get("max") is None:
        return
    entries = enumerate(value) if isinstance(value, (tuple, list)) else [(None, value)]
    for i, entry in entries:
        if isinstance(entry, bool) or not isinstance(entry, (int, float)):
            continue
        rule = _rule(f, entry)
        if rule is not None:
            note = f" ({f.metadata['note']})" if f.metadata.get("note") else ""
            which = "" if i is None else f"entry {i} "
            raise ConfigError(field, f"{which}{rule}{note}, got {entry!r}")


def check_params(obj: Any) -> None:
    """ConfigError (a ValueError: 'name: problem') for the first field of dataclass ``obj``
    outside its :func:`param` bounds; for ``__post_init__``, so objects built in code are
    held to the bounds a table is."""
    for f in dataclasses.fields(obj):
        if f.init:
            check_bounds(f, getattr(obj, f.name), f.name)


def require(condition: bool, field: str, problem: str) -> None:
    """Raise ValueError('field: problem') for __post_init__ checks."""
    if not condition:
        raise ValueError(f"{field}: {problem}")


GROUP_MARK = "--"  # a comment line "# -- NAME, ..." in a parameter class starts the group NAME (not a field's help)


def field_comments(cls: type) -> dict[str, str]:
    """Field name -> its source comment (trailing, else the comment lines just above):
    the help of a field on the tuning page and in ``tether init``'s files."""
    try:
        source = inspect.getsource(cls)
    except (OSError, TypeError):
        return {}
    names = {f.name for f in dataclasses.fields(cls)}
    code: dict[int, list[str]] = {}  # line -> its code tokens
    comment: dict[int, str] = {}  # line -> its comment
    skip = (tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER)
    try:
        for tok in tokenize.generate_tokens(io.StringIO(source).readline):
            if tok.type == tokenize.COMMENT:
                comment[tok.start[0]] = tok.string.lstrip("#").strip()
            elif tok.type not in skip:
                code.setdefault(tok.start[0], []).append(tok.string)
    except (tokenize.TokenError, IndentationError, SyntaxError):
        return {}
    out: dict[str, str] = {}
    for row, tokens in sorted(code.items()):
        if len(tokens) < 2 or tokens[0] not in names or tokens[1] != ":" or tokens[0] in out:
            continue
        if row in comment:
            out[tokens[0]] = comment[row]
            continue
        above, r = [], row - 1
        while r in comment and r not in code and not comment[r].startswith(GROUP_MARK):
            above.insert(0, comment[r])
            r -= 1
        if above:
            out[tokens[0]] = " ".join(above)
    return out


# Units that field names end in (speed_mps, timestep_s, ...).
UNIT_SUFFIXES = {"_mps2": "m/s^2", "_mps": "m/s", "_m2": "m^2", "_m": "m", "_s": "s", "_rad": "rad",
                 "_deg": "deg", "_hz": "Hz", "_px": "px"}


def unit_from_name(name: str) -> str:
    """The unit a field's name ends in (``speed_mps`` -> "m/s"), or ""."""
    for suffix, unit in UNIT_SUFFIXES.items():
        if name.endswith(suffix):
            return unit
    return ""


# ----------------------------------------------------------------------------- documentation

DOCS_BEGIN = "<!-- generated by tether.annotated.strategy_keys_section; to rewrite: python -m tether.annotated FILE -->"
DOCS_END = "<!-- end of the generated section -->"


def _doc_value(value: Any) -> str:
    """A value as the documentation's tables write it."""
    import json

    if value is None:
        return "unset"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and math.isnan(value):
        return "preset"
    if isinstance(value, (int, float)):
        return f"{value:g}"
    return f"`{json.dumps(to_table(value))}`"


def keys_table(cls: type, prefix: str = "strategy.") -> str:
    """A Markdown table of the keys of parameter class ``cls``: unit, default, range and meaning,
    from the fields' :func:`param` metadata and source comments (the help ``tether init`` writes).
    A class with an ``examples()`` classmethod (name -> instance) gets one default per example."""
    comments = field_comments(cls)
    examples = cls.examples() if hasattr(cls, "examples") else {}
    default = f"default ({' / '.join(examples)})" if examples else "default"
    lines = [f"| key | unit | {default} | range | meaning |", "| --- | --- | --- | --- | --- |"]
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        if examples:
            values = [_doc_value(getattr(example, f.name)) for example in examples.values()]
            text = values[0] if len(set(values)) == 1 else " / ".join(values)
        elif f.default is not dataclasses.MISSING:
            text = _doc_value(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            text = _doc_value(f.default_factory())
        else:
            text = "required"
        unit = f.metadata.get("unit") or unit_from_name(f.name)
        meaning = comments.get(f.name, "").replace("|", "\\|")
        lines.append(f"| `{prefix}{f.name}` | {unit} | {text} | {bounds_text(f)} | {meaning} |")
    return "\n".join(lines)


def replace_generated(text: str, body: str) -> str:
    """``text`` with its section between :data:`DOCS_BEGIN` and :data:`DOCS_END` replaced by ``body``."""
    head, begin, rest = text.partition(DOCS_BEGIN)
    _, end, tail = rest.partition(DOCS_END)
    if not (begin and end):
        raise ValueError("the text has no generated section (its begin and end markers)")
    return f"{head}{DOCS_BEGIN}\n\n{body}\n\n{DOCS_END}{tail}"

