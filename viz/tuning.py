"""The tuning page (``tether tune SCENARIO``): a local web server over a running simulation.

A :class:`TuningSession` runs :class:`sim.loop.Simulation` continuously in a
background thread (paced to real time by default) and renders the view there
with :class:`viz.video.FrameRenderer` (the GL context stays in that thread).
:class:`TuningServer` (standard-library ``http.server``) serves one plain
HTML + JS page (``viz/static/tune.html``; no build step, nothing fetched from
outside) and a small JSON API:

  GET  /                  the page
  GET  /stream.mjpg       live view, multipart JPEG;  GET /frame.jpg: the latest frame
  GET  /api/status?since=SEQ   time, tick, state, current parameters, latest
                          figures and the plot samples after SEQ
  GET  /api/params        the strategy's parameter fields: name, kind, unit, bounds, help, value
  POST /api/params        {"changes": {name: value}}: validated by sim.config.build
                          (field metadata bounds + the dataclass's __post_init__), then
                          applied between two ticks; 400 {"error": "strategy.NAME: ..."} if refused
  POST /api/control       {"action": "pause" | "resume" | "step" | "reset" | "camera", "camera": NAME}
  POST /api/save          write the scenario with the current parameters as TOML (the server's
                          save path; ``tether run`` reloads it)
  GET  /scenario.toml     the same TOML as a download

Plots: the foundation's tracking error and link count plus every
``frame.scalars`` entry the strategy reports (and the loop's ``e_g_m``), sampled every
``SAMPLE_PERIOD_S`` of sim time. Requests from another origin (or with a
foreign Host header) are refused, so other web pages cannot drive the server.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import threading
import time
import tomllib
import typing
from collections import deque
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints
from urllib.parse import parse_qs, urlparse

import numpy as np

from sim.config import MAX_NESTING, ConfigError, build, check_nesting, field_comments, to_table, unit_from_name
from sim.palette import PLOT_LINE_ON_DARK, hex_code
from sim.radio.config import RadioConfig
from sim.loop import Simulation
from sim.observers import Frame, tracking_errors
from sim.scenario import Scenario, dumps_toml, to_scenario_table, toml_value
from sim.strategy import Status
from sim.types import Commands
from sim.validate import check_scenario

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
MAX_BODY_BYTES = 1_000_000  # a request body holds a few parameter values
MAX_JSON_DIGITS = 20  # digits of an integer in a request (int64 has 19)
MAX_SEQ_DIGITS = 18  # digits of ?since= (a sample count)
LISTEN_BACKLOG = 128  # connections the kernel queues while every handler thread is busy (http.server: 5)
REQUEST_TIMEOUT_S = 5.0  # s a request may take to arrive
SAMPLE_PERIOD_S = 0.1  # plot sampling, s of sim time
HISTORY_POINTS = 3000  # plot samples kept (5 min of sim time)
JPEG_QUALITY = 80
MAX_LAG_S = 0.5  # further behind real time than this: stop catching up
PAGE = Path(__file__).parent / "static" / "tune.html"
GROUP_MARK = "--"  # a comment line "# -- NAME, ..." in a parameter class starts the group NAME
GENERAL_GROUP = "general"
RADIO_PREFIX = "radio."  # the page's names of the radio's keys (the scenario's [radio] table)
RADIO_GROUP = "radio"  # ... their group on the page; a sub-group's name follows it ("radio: propagation")


def axis_label(name: str) -> str:
    from viz.plots import axis_label as plots_label

    return plots_label(name)


def figure_labels() -> dict[str, str]:
    """The plots' axis labels (words and a unit) of the figures the page draws."""
    from viz.plots import LABELS, TRACKING_ERROR

    return {**LABELS, "tracking_error_mean_m": LABELS[TRACKING_ERROR]}


FIGURE_LABELS = figure_labels()


# --------------------------------------------------------------------------- parameter fields


def _field_groups(cls: type) -> dict[str, str]:
    """Field name -> its group: the latest ``# -- group, ...`` comment line
    above it in the class source (``GENERAL_GROUP`` before any)."""
    import ast
    import inspect
    import textwrap

    try:
        source = textwrap.dedent(inspect.getsource(cls))
        tree = ast.parse(source)
    except (OSError, TypeError, SyntaxError):
        return {}
    lines = source.splitlines()
    headers = []  # (line number, group)
    for number, line in enumerate(lines, start=1):
        text = line.strip().lstrip("#").strip()
        if line.strip().startswith("#") and text.startswith(GROUP_MARK):
            title = text[len(GROUP_MARK):].strip()
            headers.append((number, title.split(",")[0].split("(")[0].strip() or GENERAL_GROUP))
    out: dict[str, str] = {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    for node in body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            above = [group for number, group in headers if number < node.lineno]
            out[node.target.id] = above[-1] if above else GENERAL_GROUP
    return out


def _field_kind(tp: Any) -> tuple[str, list | None]:
    if tp is bool:
        return "bool", None
    if tp is float:
        return "float", None
    if tp is int:
        return "int", None
    if get_origin(tp) is typing.Literal:
        return "choice", list(get_args(tp))
    if tp is str:
        return "str", None
    return "toml", None  # lists, tables, optional values: edited as a TOML value


def describe_params(cls: type, params: Any) -> list[dict[str, Any]]:
    """What the page needs to draw one control per field of ``cls`` (every
    field a scenario can set): name, kind (float, int, bool, choice, str,
    toml), unit, min, max, step, choices, help (the field's source comment),
    group (its ``# -- group`` comment), restarts (true for a field that
    shapes the set-up, ``tunable=False`` in its metadata: changing it restarts
    the strategy at the current state) and the current value."""
    hints = get_type_hints(cls)
    comments = field_comments(cls)
    groups = _field_groups(cls)
    out = []
    for f in dataclasses.fields(cls):
        meta = f.metadata
        if not f.init:
            continue
        kind, choices = _field_kind(hints[f.name])
        value = to_table(getattr(params, f.name))
        entry = {"name": f.name, "kind": kind, "unit": meta.get("unit") or unit_from_name(f.name),
                 "min": meta.get("min"), "max": meta.get("max"), "step": meta.get("step"), "choices": choices,
                 "help": comments.get(f.name, ""), "group": groups.get(f.name, GENERAL_GROUP),
                 "restarts": not meta.get("tunable", True), "value": value}
        if kind == "toml":
            entry["text"] = "" if value is None else toml_value(value)
        if kind in ("float", "int") and entry["step"] is None and entry["min"] is not None \
                and entry["max"] is not None:
            entry["step"] = 1 if kind == "int" else _nice_step(entry["max"] - entry["min"])
        out.append(entry)
    return out


def _nice_step(span: float) -> float:
    """A power of ten giving at least about 100 slider positions over ``span``."""
    return 10.0 ** math.floor(math.log10(span / 100)) if span > 0 else 1.0


def _css_color(rgba: Any) -> str:
    r, g, b = (int(round(255 * min(max(float(c), 0.0), 1.0))) for c in list(rgba)[:3])
    return f"#{r:02x}{g:02x}{b:02x}"


def _parse_toml_value(text: str, field: str) -> Any:
    try:
        return check_nesting(tomllib.loads(f"v = {text}")["v"], field)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(field, f"is not a valid TOML value: {err}") from None
    except RecursionError:
        raise ConfigError(field, "is not a valid TOML value: lists or tables nested too deeply") from None


def strict_count(text: str | None, field: str, max_digits: int) -> int:
    """A non-negative integer written in at most ``max_digits`` ASCII digits (``str.isdigit``
    also takes "²" and "٣", ``int`` also takes "+1", " 1" and "1_0"); ConfigError otherwise."""
    if text is None or not (text.isascii() and text.isdigit()) or len(text) > max_digits:
        shown = text if text is None or len(text) <= 40 else text[:40] + "..."
        raise ConfigError(field, f"must be a non-negative integer of at most {max_digits} digits, got {shown!r}")
    return int(text)


def _json_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_JSON_DIGITS:
        raise ValueError(f"an integer of {len(text)} digits (at most {MAX_JSON_DIGITS})")
    return int(text)


def parse_json_body(raw: bytes) -> dict:
    """A request body as a JSON object; ConfigError (field ``request``) for anything else:
    not UTF-8, not JSON, an integer longer than ``MAX_JSON_DIGITS``, nesting deeper than
    sim.config's cap (also where it would exhaust the parser's recursion)."""
    try:
        payload = json.loads(raw or b"{}", parse_int=_json_int)
    except RecursionError:
        raise ConfigError("request", f"lists or objects nested more than {MAX_NESTING} deep") from None
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError, an integer too long
        raise ConfigError("request", f"not JSON: {err}") from None
    if not isinstance(payload, dict):
        raise ConfigError("request", "expected a JSON object")
    return check_nesting(payload, "request")


# --------------------------------------------------------------------------- the running simulation


class TuningSession:
    """A simulation ticking in a background thread, with thread-safe controls.

    Everything that touches the simulation (tick, render, parameter swap)
    holds one lock, so a change lands between two ticks and takes effect on
    the next one.
    """

    def __init__(self, scenario: Scenario, make_simulation: typing.Callable[[Scenario], Simulation],
                 view_fps: float = 10.0, speed: float = 1.0, save_path: str | Path | None = None):
        from viz.video import resolve_camera

        check_scenario(scenario)  # the checks of `tether run`, before anything is built
        self.make_simulation = make_simulation
        self.sim = make_simulation(scenario)  # ConfigError for a bad world
        self.camera = resolve_camera(self.sim.world.model, scenario.video.camera)
        self.kind = scenario.strategy.kind
        self.params_cls = type(scenario.strategy.params)
        self.view_fps = view_fps
        self.speed = speed
        self.save_path = Path(save_path) if save_path else Path("runs") / "tune" / f"{scenario.name}_tuned.toml"
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._frame_ready = threading.Condition()
        self.paused = False
        self.state = Status.RUNNING  # RUNNING, DIVERGED (physics), FAILED (strategy raised), STOPPED
        self.message = ""
        self.params_tick = 0
        self.epoch = 0
        self._steps = 0
        self._reset_requested = False
        self._camera_request: str | None = None
        self._series: deque = deque(maxlen=HISTORY_POINTS)
        self._seq = 0
        self._next_sample = 0.0
        self.figures: dict[str, float] = {}
        self.overlay = ""  # the video's overlay line (time, links, the strategy's figures)
        self.legend: list[dict[str, str]] = []  # the strategy's decorations' legend: what the view's colours mean
        self._scenery: tuple | None = None  # (the model, its obstacles' legend entries): made once per simulation
        self.real_time_factor: float | None = None
        self._jpeg: bytes | None = None
        self.frame_seq = 0
        self._thread = threading.Thread(target=self._run, name="tether-tune-sim", daemon=True)
        self._error: BaseException | None = None

    # ---- lifecycle

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        with self._frame_ready:
            self._frame_ready.notify_all()
        self._thread.join(timeout=5)

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    # ---- the sim thread

    def _run(self) -> None:
        renderer = None
        try:
            renderer = self._renderer()
            frame = self._still_frame()
            self._render(renderer, frame)
            next_render = self.sim.time_s + 1.0 / self.view_fps
            anchor_wall, anchor_sim = time.perf_counter(), self.sim.time_s
            rate_wall, rate_sim = anchor_wall, anchor_sim
            while not self._stop.is_set():
                if self._reset_requested:
                    with self._lock:
                        if renderer is not None:
                            renderer.close()
                        self._rebuild()
                        renderer = self._renderer()
                        frame = self._still_frame()
                        self._render(renderer, frame)
                    next_render = 1.0 / self.view_fps
                    anchor_wall, anchor_sim = time.perf_counter(), self.sim.time_s
                    continue
                if self._camera_request is not None:
                    with self._lock:
                        if renderer is not None:
                            renderer.set_camera(self._camera_request)
                        self._camera_request = None
                        self._render(renderer, frame)
                if self.paused and self._steps == 0:
                    self._wake.wait(0.1)
                    self._wake.clear()
                    anchor_wall, anchor_sim = time.perf_counter(), self.sim.time_s
                    rate_wall, rate_sim = anchor_wall, anchor_sim
                    continue
                with self._lock:
                    if self.paused and self._steps == 0:  # paused while this thread waited for the lock
                        continue
                    stepping = self._steps > 0
                    if stepping:
                        self._steps -= 1
                    try:
                        frame, healthy = self.sim.tick()
                    except Exception as err:  # a strategy bug: pause, show it, keep serving
                        self.paused = True
                        self.state = Status.FAILED
                        self.message = (f"the simulation raised {type(err).__name__}: {err} at t = "
                                        f"{self.sim.time_s:.2f} s; change a parameter and resume, or reset")
                        continue
                    self._sample(frame)
                    if not healthy:
                        self.paused = True
                        self.state = Status.DIVERGED
                        self.message = (f"diverged: {self.sim.divergence} (t = {self.sim.time_s:.3f} s); "
                                        f"reset to start again")
                    if stepping or not healthy or self.sim.time_s + 1e-9 >= next_render:
                        next_render = self.sim.time_s + 1.0 / self.view_fps
                        self._render(renderer, frame)
                now = time.perf_counter()
                if now - rate_wall >= 1.0:
                    self.real_time_factor = (self.sim.time_s - rate_sim) / (now - rate_wall)
                    rate_wall, rate_sim = now, self.sim.time_s
                if self.speed > 0:
                    delay = anchor_wall + (self.sim.time_s - anchor_sim) / self.speed - now
                    if delay > 0:
                        self._stop.wait(delay)
                    elif delay < -MAX_LAG_S:
                        anchor_wall, anchor_sim = now, self.sim.time_s
        except Exception as err:  # keep serving the page; show what went wrong
            self.state = Status.STOPPED
            self.message = f"simulation stopped: {type(err).__name__}: {err}"
        finally:
            if renderer is not None:
                renderer.close()

    def _renderer(self):
        """A FrameRenderer for the current world, or None (and a message) if
        this machine cannot render: the page then works without the view."""
        from viz.video import FrameRenderer

        video = dataclasses.replace(self.sim.scenario.video, camera=self.camera)
        try:
            return FrameRenderer(self.sim.world, video)
        except Exception as err:
            self.message = f"no live view: rendering failed ({type(err).__name__}: {err})"
            return None

    def _render(self, renderer, frame: Frame) -> None:
        if renderer is not None:  # the scene alone: the page shows the legend and the figures itself
            self._publish(renderer.render_scene(frame))

    def _still_frame(self) -> Frame:
        """A frame of the current state for the first image (no strategy step:
        references drawn at the robots)."""
        obs = self.sim.observe(read_targets=False)
        n = len(obs.position)
        commands = Commands(obs.position.copy(), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n))
        targets = self.sim.world.data.mocap_pos[self.sim.world.target_mocap_ids].copy()
        return Frame(obs, commands, targets)

    def _rebuild(self) -> None:
        self.sim = self.make_simulation(self.sim.scenario)
        self._reset_requested = False
        self._series.clear()
        self._next_sample = 0.0
        self.figures = {}
        self.epoch += 1
        self.params_tick = 0
        if self.state in (Status.DIVERGED, Status.FAILED):
            self.state = Status.PAUSED
        self.message = "reset: restarted from t = 0 with the current parameters"

    def _sample(self, frame: Frame) -> None:
        t = frame.observation.time_s
        if t + 1e-9 < self._next_sample:
            return
        self._next_sample = t + SAMPLE_PERIOD_S
        obs, commands = frame.observation, frame.commands
        error = tracking_errors(self.sim.world.robot_kinds, obs.position, commands.position)
        values = {"tracking_error_mean_m": float(error.mean()), "links": float(len(obs.links.edges))}
        for name, value in frame.scalars.items():
            values[str(name)] = float(value)
        from viz.decorations import frame_legend
        from viz.scenery import scenery_legend
        from viz.video import overlay_text

        model = self.sim.world.model
        if self._scenery is None or self._scenery[0] is not model:  # once per simulation (a reset builds a new one)
            self._scenery = (model, scenery_legend(model))
        self.legend = [{"label": str(label), "color": _css_color(rgba)}
                       for label, rgba in frame_legend(frame, self.sim.world.robot_kinds, self._scenery[1])]
        self.overlay = overlay_text(frame)
        self._seq += 1
        self._series.append((self._seq, t, values))
        self.figures = values

    def _publish(self, image: np.ndarray) -> None:
        from PIL import Image

        buffer = io.BytesIO()
        Image.fromarray(image).save(buffer, format="JPEG", quality=JPEG_QUALITY)
        with self._frame_ready:
            self._jpeg = buffer.getvalue()
            self.frame_seq += 1
            self._frame_ready.notify_all()

    # ---- what the handlers call

    def latest_frame(self, after: int = -1, timeout: float = 1.0) -> tuple[int, bytes | None]:
        """The newest JPEG, waiting up to ``timeout`` for one newer than ``after``."""
        with self._frame_ready:
            if self.frame_seq <= after and not self._stop.is_set():
                self._frame_ready.wait(timeout)
            return self.frame_seq, self._jpeg

    def status(self, since: int = 0) -> dict[str, Any]:
        with self._lock:
            points = [p for p in self._series if p[0] > since]
            names = list(dict.fromkeys(name for p in points for name in p[2]))
            series = {
                "seq": [p[0] for p in points],
                "t": [p[1] for p in points],
                "values": {name: [p[2].get(name) for p in points] for name in names},
            }
            return {
                "scenario": self.sim.scenario.name,
                "strategy": self.kind,
                "state": str(self.state if self.state in (Status.DIVERGED, Status.FAILED, Status.STOPPED) else
                             (Status.PAUSED if self.paused else Status.RUNNING)),
                "paused": self.paused,
                "time_s": self.sim.time_s,
                "tick": self.sim.tick_count,
                "epoch": self.epoch,
                "real_time_factor": self.real_time_factor,
                "speed": self.speed,
                "message": self.message,
                "params": {**to_table(self.sim.scenario.strategy.params), **self._radio_values()},
                "params_tick": self.params_tick,
                "camera": self.camera,
                "figures": dict(self.figures),
                "legend": list(self.legend),
                "overlay": self.overlay,
                "labels": {**{name: axis_label(name) for name in self.figures}, **FIGURE_LABELS},
                "plot_color": hex_code(PLOT_LINE_ON_DARK),
                "last_seq": self._seq,
                "series": series,
                "frame_seq": self.frame_seq,
            }

    def params_schema(self) -> dict[str, Any]:
        with self._lock:
            params = self.sim.scenario.strategy.params
            return {"strategy": self.kind,
                    "fields": describe_params(self.params_cls, params) + self.radio_fields(),
                    "cameras": self.camera_choices()}

    def radio_fields(self) -> list[dict[str, Any]]:
        """The radio's keys as the page's controls, named ``radio.KEY`` in group "radio ..."; the
        preset a choice of the presets (a new preset takes its own figures)."""
        from sim.radio.presets import PRESETS

        fields = describe_params(RadioConfig, self.sim.scenario.radio)
        for f in fields:
            f["name"] = RADIO_PREFIX + f["name"]
            sub = f["group"]
            f["group"] = RADIO_GROUP if sub == GENERAL_GROUP else f"{RADIO_GROUP}: {sub}"
            if f["name"] == RADIO_PREFIX + "preset":
                f["kind"], f["choices"] = "choice", list(PRESETS)
                f["help"] = "a new preset takes its own figures for every key below"
            elif f["restarts"]:
                f["help"] = (f["help"] + "; " if f["help"] else "") + "the channel restarts from t = 0"
        return fields

    def _radio_values(self) -> dict[str, Any]:
        return {RADIO_PREFIX + k: v for k, v in to_table(self.sim.scenario.radio).items()}

    def _set_radio(self, changes: dict[str, Any]) -> str:
        """Apply ``radio.KEY`` changes: a new preset with its own figures, else the keys over the
        current table; keys that shape the channel's set-up (the bit rate) restart the run."""
        keys = {name[len(RADIO_PREFIX):]: value for name, value in changes.items()}
        if "preset" in keys:
            table = {"preset": keys.pop("preset"), **keys}
        else:
            table = {**to_table(self.sim.scenario.radio), **keys}
        config = build(RadioConfig, table, "radio")
        restart = {f.name for f in dataclasses.fields(RadioConfig) if not f.metadata.get("tunable", True)}
        if "preset" in table and table["preset"] != self.sim.scenario.radio.preset or restart & set(keys):
            self.sim.scenario = dataclasses.replace(self.sim.scenario, radio=config)
            self._reset_requested = True
            return "restarted from t = 0"
        return self.sim.set_radio(config)

    def camera_choices(self) -> list[str]:
        from viz.video import PRESET_CAMERAS

        model = self.sim.world.model
        scene = [model.camera(i).name for i in range(model.ncam)]
        follow = [f"follow:{name}" for name in self.sim.world.robot_names]
        return list(dict.fromkeys([*PRESET_CAMERAS, *scene, "free", *follow]))

    def set_params(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Validate ``changes`` (field -> value) with the parameter dataclass and
        apply them between two ticks; ConfigError (naming the field) if refused."""
        if not isinstance(changes, dict) or not changes:
            raise ConfigError("changes", "expected a table of parameter values")
        with self._lock:
            radio = {name: value for name, value in changes.items() if str(name).startswith(RADIO_PREFIX)}
            if radio:
                if len(radio) != len(changes):
                    raise ConfigError("changes", "change the radio's keys and the strategy's apart")
                how = self._set_radio(radio)
                self.params_tick = self.sim.tick_count
                shown = ", ".join(f"{k} = {v}" for k, v in changes.items())
                self.message = f"{shown}: applied from tick {self.params_tick} ({how})"
                self._wake.set()
                return {"ok": True, "how": how, "tick": self.params_tick, "message": self.message,
                        "params": {**to_table(self.sim.scenario.strategy.params), **self._radio_values()}}
            kinds = {f["name"]: f["kind"] for f in describe_params(self.params_cls, self.sim.scenario.strategy.params)}
            table = to_table(self.sim.scenario.strategy.params)
            for name, value in changes.items():
                if kinds.get(name) == "toml" and isinstance(value, str):
                    value = _parse_toml_value(value, f"strategy.{name}")
                table[name] = value
            params = build(self.params_cls, table, "strategy")
            how = self.sim.set_strategy_params(params)
            self.params_tick = self.sim.tick_count
            shown = ", ".join(f"{k} = {v}" for k, v in changes.items())
            self.message = f"{shown}: applied from tick {self.params_tick} ({how})"
            self._wake.set()
            return {"ok": True, "how": how, "tick": self.params_tick, "message": self.message,
                    "params": {**to_table(params), **self._radio_values()}}

    def control(self, action: str, camera: str | None = None) -> None:
        with self._lock:
            if action == "pause":
                self.paused = True
                self.message = f"paused at t = {self.sim.time_s:.2f} s"
            elif action == "resume":
                if self.state == Status.DIVERGED:
                    raise ConfigError("resume", "the physics diverged; reset first")
                self.paused = False
                self.state = Status.RUNNING
                self.message = "running"
            elif action == "step":
                if self.state == Status.DIVERGED:
                    raise ConfigError("step", "the physics diverged; reset first")
                self.paused = True
                self._steps += 1
                self.message = "one control tick"
            elif action == "reset":
                self._reset_requested = True
                self.message = "resetting"
            elif action == "camera":
                from viz.video import resolve_camera

                name = resolve_camera(self.sim.world.model, str(camera))
                self._camera_request = self.camera = name
                video = dataclasses.replace(self.sim.scenario.video, camera=name)
                self.sim.scenario = dataclasses.replace(self.sim.scenario, video=video)
                self.message = f"camera {name}"
            else:
                raise ConfigError("action", f"unknown action {action!r} (pause, resume, step, reset, camera)")
        self._wake.set()

    def scenario_toml(self) -> str:
        with self._lock:
            scenario = self.sim.scenario
            header = (f"# tether scenario {scenario.name!r} with the parameters tuned in `tether tune` "
                      f"(saved at sim time {self.sim.time_s:.1f} s). Run it with: tether run FILE\n")
            return header + dumps_toml(to_scenario_table(scenario))

    def save(self) -> Path:
        """Write the scenario TOML to the save path: a new file, or one tether
        wrote (sim.outputs.check_out_file); ConfigError otherwise."""
        from sim.outputs import check_out_file

        check_out_file(self.save_path, "--save")
        text = self.scenario_toml()
        self.save_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.save_path.with_suffix(self.save_path.suffix + ".tmp")
        tmp.write_text(text)
        tmp.replace(self.save_path)
        self.message = f"saved to {self.save_path}"
        return self.save_path


# --------------------------------------------------------------------------- HTTP


class TuningServer(ThreadingHTTPServer):
    """Standard-library HTTP server for one :class:`TuningSession`."""

    daemon_threads = True
    request_queue_size = LISTEN_BACKLOG

    def handle_error(self, request, client_address) -> None:
        """A connection that failed outside the handlers (a client gone
        mid-request): no traceback on the terminal."""

    def __init__(self, session: TuningSession, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT):
        super().__init__((host, port), _Handler)
        self.session = session
        self.host = host
        self.port = self.server_address[1]

    @property
    def url(self) -> str:
        host = self.host if ":" not in self.host else f"[{self.host}]"
        return f"http://{host}:{self.port}/"

    def allowed_hosts(self) -> set[str] | None:
        if self.host in ("0.0.0.0", "::", ""):
            return None  # bound everywhere: any address of this machine
        names = {self.host, "127.0.0.1", "localhost", "[::1]"}
        return {f"{n}:{self.port}" for n in names}


def _json_safe(obj: Any) -> Any:
    """JSON has no inf/nan: send them as null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


class _Handler(BaseHTTPRequestHandler):
    server: TuningServer
    server_version = "tether-tune"
    timeout = REQUEST_TIMEOUT_S  # a client that sends less than it announced gets a 400, not a hung thread

    def log_message(self, format: str, *args: Any) -> None:  # keep the terminal for the URL
        pass

    # ---- helpers

    def _send(self, status: int, body: bytes, content_type: str, extra: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, payload: Any, status: int = 200) -> None:
        self._send(status, json.dumps(_json_safe(payload), allow_nan=False).encode(), "application/json")

    def _error(self, status: int, message: str) -> None:
        self._json({"ok": False, "error": message}, status)

    def _trusted(self, post: bool) -> bool:
        allowed = self.server.allowed_hosts()
        host = self.headers.get("Host", "")
        if allowed is not None and host not in allowed:
            self._error(HTTPStatus.FORBIDDEN, f"unexpected Host header {host!r}")
            return False
        origin = self.headers.get("Origin")
        if post and origin is not None and origin != f"http://{host}":
            self._error(HTTPStatus.FORBIDDEN, f"requests from {origin} are not allowed")
            return False
        return True

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """http.server's own refusals (a malformed request line or header) as JSON."""
        try:
            self.close_connection = True
            if self.request_version == "HTTP/0.9":  # an unparsable request line: answer with headers anyway
                self.request_version = "HTTP/1.0"
            self._json({"ok": False, "error": message or HTTPStatus(code).phrase}, code)
        except OSError:
            pass

    def _body(self) -> dict:
        given = self.headers.get_all("Content-Length") or ["0"]
        if len(set(given)) > 1:
            self.close_connection = True
            raise ConfigError("Content-Length", f"given {len(given)} times with different values")
        try:
            length = strict_count(given[0].strip(), "Content-Length", len(str(MAX_BODY_BYTES)) + 1)
        except ConfigError:
            self.close_connection = True
            raise
        if length > MAX_BODY_BYTES:
            self.close_connection = True
            raise ConfigError("request", f"body too large ({length} bytes, at most {MAX_BODY_BYTES})")
        try:
            raw = self.rfile.read(length) if length else b"{}"
        except TimeoutError:
            raw = b""
        if len(raw) < length:
            self.close_connection = True
            raise ConfigError("request", f"body shorter than its Content-Length ({len(raw)} of {length} bytes)")
        return parse_json_body(raw)

    # ---- routes

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        if not self._trusted(post=False):
            return
        url = urlparse(self.path)
        session = self.server.session
        try:
            if url.path in ("/", "/index.html"):
                self._send(200, PAGE.read_bytes(), "text/html; charset=utf-8")
            elif url.path == "/api/status":
                since = parse_qs(url.query).get("since", ["0"])[-1]
                self._json(session.status(strict_count(since, "since", MAX_SEQ_DIGITS)))
            elif url.path == "/api/params":
                self._json(session.params_schema())
            elif url.path == "/frame.jpg":
                _, jpeg = session.latest_frame(timeout=5.0)
                if jpeg is None:
                    self._error(HTTPStatus.SERVICE_UNAVAILABLE, "no frame rendered yet")
                else:
                    self._send(200, jpeg, "image/jpeg")
            elif url.path == "/favicon.ico":
                self._send(HTTPStatus.NO_CONTENT, b"", "image/x-icon")
            elif url.path == "/stream.mjpg":
                self._stream()
            elif url.path == "/scenario.toml":
                name = f"{session.sim.scenario.name}_tuned.toml"
                self._send(200, session.scenario_toml().encode(), "application/toml; charset=utf-8",
                           {"Content-Disposition": f'attachment; filename="{name}"'})
            else:
                self._error(HTTPStatus.NOT_FOUND, f"no page {url.path}")
        except ConfigError as err:
            self._error(HTTPStatus.BAD_REQUEST, str(err))
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            pass
        except Exception as err:  # a bug: answer it, never a traceback in the terminal
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(err).__name__}: {err}")

    def do_POST(self) -> None:  # noqa: N802
        if not self._trusted(post=True):
            return
        session = self.server.session
        path = urlparse(self.path).path
        try:
            body = self._body()
            if path == "/api/params":
                self._json(session.set_params(body.get("changes")))
            elif path == "/api/control":
                session.control(str(body.get("action")), body.get("camera"))
                self._json({"ok": True, "message": session.message})
            elif path == "/api/save":
                saved = session.save()
                self._json({"ok": True, "path": str(saved), "message": session.message})
            else:
                self._error(HTTPStatus.NOT_FOUND, f"no endpoint {path}")
        except ConfigError as err:
            self._error(HTTPStatus.BAD_REQUEST, str(err))
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception as err:  # OSError while saving, or a bug: answer it, never a traceback
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(err).__name__}: {err}")

    def _stream(self) -> None:
        session = self.server.session
        self.send_response(200)
        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        seen = -1
        while not session.stopped:
            seq, jpeg = session.latest_frame(seen, timeout=1.0)
            if jpeg is None or seq == seen:
                continue
            seen = seq
            self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                             + str(len(jpeg)).encode() + b"\r\n\r\n" + jpeg + b"\r\n")
            self.wfile.flush()


def serve(scenario: Scenario, make_simulation: typing.Callable[[Scenario], Simulation], host: str = DEFAULT_HOST,
          port: int = DEFAULT_PORT, view_fps: float = 10.0,
          speed: float = 1.0, save_path: str | Path | None = None,
          ready: typing.Callable[[TuningServer], None] | None = None) -> None:
    """Run the tuning page until interrupted (KeyboardInterrupt). ConfigError
    for a bad scenario, OSError if the address cannot be bound."""
    session = TuningSession(scenario, make_simulation, view_fps=view_fps, speed=speed, save_path=save_path)
    server = TuningServer(session, host, port)
    try:
        session.start()
        if ready is not None:
            ready(server)
        server.serve_forever(poll_interval=0.2)
    finally:
        server.server_close()
        session.stop()
