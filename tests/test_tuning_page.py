"""The tuning page: parameter metadata and live updates (pure), then
`tether tune hover` driven in a real browser (Playwright on Debian's
/usr/bin/chromium, never a downloaded browser)."""

import dataclasses
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
import tomllib
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from controllers.waypoints import WaypointParams
from sim.config import ConfigError, build
from tether.runner import build_simulation, run
from sim.scenario import dumps_toml, from_table, load, to_scenario_table
from sim.types import Decorations
from viz.tuning import describe_params

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


# --------------------------------------------------------------------------- without a browser


def test_waypoint_params_describe_units_bounds_and_help():
    fields = {f["name"]: f for f in describe_params(WaypointParams, WaypointParams())}
    assert set(fields) == {"speed_mps", "ground_speed_mps", "dwell_s", "routes"}
    speed = fields["speed_mps"]
    assert (speed["kind"], speed["unit"], speed["min"], speed["max"]) == ("float", "m/s", 0.05, 3.0)
    assert speed["value"] == 0.5
    assert 0 < speed["step"] <= 0.03 and "peak speed" in speed["help"]
    assert fields["dwell_s"]["unit"] == "s" and fields["routes"]["kind"] == "toml"


def test_bounds_are_enforced_by_build_for_files_overrides_and_the_page():
    with pytest.raises(ConfigError, match=r"strategy\.speed_mps: must be in \[0\.05, 3\] m/s, got 99"):
        load("hover", ["strategy.speed_mps=99"])
    with pytest.raises(ConfigError, match=r"strategy\.dwell_s: must be in \[0, 10\] s, got -1"):
        build(WaypointParams, {"dwell_s": -1.0}, "strategy")
    assert build(WaypointParams, {"speed_mps": 3}, "strategy").speed_mps == 3.0


def test_speed_change_keeps_the_reference_continuous_and_scales_velocity():
    scenario = load("hover")
    sim = build_simulation(scenario)
    for _ in range(250):
        frame, _ = sim.tick()
    before = sim.strategy.step(sim.observe(read_targets=False))
    params = build(WaypointParams, {**_table(scenario.strategy.params), "speed_mps": 1.0}, "strategy")
    assert sim.set_strategy_params(params) == "updated"
    after = sim.strategy.step(sim.observe(read_targets=False))
    quads = [i for i, k in enumerate(sim.world.robot_kinds) if k == "quadrotor"]
    np.testing.assert_allclose(after.position, before.position, atol=1e-9)
    np.testing.assert_allclose(after.velocity[quads], 2.0 * before.velocity[quads], atol=1e-9)
    assert sim.scenario.strategy.params.speed_mps == 1.0
    # New routes restart the strategy from where the robots are.
    routes = tuple(((1.0, 1.0, 1.0),) for _ in range(sim.world.n_robots))
    params = build(WaypointParams, {**_table(params), "routes": [list(map(list, r)) for r in routes]}, "strategy")
    assert sim.set_strategy_params(params) == "restarted"
    frame, healthy = sim.tick()
    assert healthy
    np.testing.assert_allclose(frame.commands.position, frame.observation.position, atol=0.05)


def _table(params):
    from sim.config import to_table

    return to_table(params)


def test_scenario_toml_round_trips_and_keeps_unknown_key_checks(tmp_path):
    scenario = load("hover", ["strategy.speed_mps=1.25", "video.camera=\"follow:quad1\""])
    text = dumps_toml(to_scenario_table(scenario))
    path = tmp_path / "saved.toml"
    path.write_text(text)
    back = load(str(path))
    assert back.strategy == scenario.strategy and back.robots == scenario.robots
    assert back.targets == scenario.targets and back.video == scenario.video and back.physics == scenario.physics
    table = tomllib.loads(text)
    table["strategy"]["colour"] = 3
    with pytest.raises(ConfigError, match=r"strategy\.colour: unknown key"):
        from_table(table, str(path))


def test_every_field_of_the_connected_strategy_is_offered_in_groups():
    import dataclasses

    from controllers.connectivity.connected_params import ConnectedParams

    scenario = load("connected-office")
    fields = describe_params(ConnectedParams, scenario.strategy.params)
    assert [f["name"] for f in fields] == [f.name for f in dataclasses.fields(ConnectedParams) if f.init]
    groups = {f["group"] for f in fields}
    assert {"connectivity", "travel", "roles", "estimator", "path planning", "targets"} <= groups
    by_name = {f["name"]: f for f in fields}
    assert by_name["cruise_speed_mps"]["group"] == "travel" and not by_name["cruise_speed_mps"]["restarts"]
    assert by_name["grid_resolution_m"]["restarts"] and by_name["lambda2_source"]["kind"] == "choice"
    assert by_name["target_lists"]["kind"] == "toml" and by_name["estimator_modes"]["group"] == "estimator"
    # Group headers are not anyone's help text; every field has its own.
    assert all(f["help"] and not f["help"].startswith("--") for f in fields)


def test_the_strategy_legend_reaches_the_page_status():
    from sim import palette
    from viz.tuning import TuningSession

    session = TuningSession(load("hover"), build_simulation)
    frame, _ = session.sim.tick()
    legend = Decorations(legend=[("anchor", (1.0, 0.6, 0.1, 1.0)), ("team 0", np.array([0.2, 0.4, 1.0, 1.0]))])
    frame = dataclasses.replace(frame, commands=dataclasses.replace(frame.commands, decorations=legend))
    session._sample(frame)
    # The pictures' one legend: the strategy's entries, the robots' kinds (hover flies and drives; the strategy colours none),
    # the references, the links, the scene's walls, then the true targets (hover has 8), in the palette's colours.
    assert session.status()["legend"] == [{"label": "anchor", "color": "#ff991a"},
                                          {"label": "team 0", "color": "#3366ff"},
                                          {"label": "quadrotor robot", "color": palette.hex_code(palette.KIND["quadrotor"])},
                                          {"label": "ground robot", "color": palette.hex_code(palette.KIND["ground"])},
                                          {"label": "reference (point steered to)", "color": "#000000"},
                                          {"label": "communication link", "color": palette.hex_code(palette.LINK_STRONG)},
                                          {"label": "wall", "color": "#b28257"},  # the office's walls as drawn
                                          {"label": "target (true)", "color": palette.hex_code(palette.TARGET_TRUE)}]
    assert session.status()["overlay"].startswith("t = ")


def test_the_radio_keys_are_controls_and_retune_the_running_channel():
    from viz.tuning import TuningSession

    scenario = load("connected-office", ["robots.0.count=6", 'radio.preset="ieee802154"'], duration_s=5.0)
    session = TuningSession(scenario, build_simulation)
    fields = {f["name"]: f for f in session.params_schema()["fields"]}
    power = fields["radio.tx_power_dbm"]
    assert (power["kind"], power["unit"], power["min"], power["max"]) == ("float", "dBm", -60.0, 40.0)
    assert power["group"].startswith("radio") and power["value"] == 0.0
    assert fields["radio.preset"]["kind"] == "choice" and "wifi" in fields["radio.preset"]["choices"]
    assert fields["radio.bitrate_bps"]["restarts"]
    for _ in range(5):
        session.sim.tick()
    before = session.sim.radio
    tick = session.sim.tick_count
    result = session.set_params({"radio.tx_power_dbm": -50.0})
    # Live: the same run goes on (no reset), its channel now at -50 dBm.
    assert result["how"] == "updated" and session.sim.tick_count == tick and not session._reset_requested
    assert session.sim.radio is not before and session.sim.radio.config.tx_power_dbm == -50.0
    assert session.status()["params"]["radio.tx_power_dbm"] == -50.0
    frame, healthy = session.sim.tick()
    assert healthy and np.nanmax(frame.observation.radio.rx_power_dbm) < -40.0
    with pytest.raises(ConfigError, match=r"radio\.path_loss_exponent: must be in \[1, 8\]"):
        session.set_params({"radio.path_loss_exponent": 0.5})
    # A new preset takes its own figures, and the run restarts from t = 0 with it.
    assert session.set_params({"radio.preset": "wifi"})["how"] == "restarted from t = 0"
    assert session._reset_requested and session.sim.scenario.radio.preset == "wifi"
    assert session.sim.scenario.radio.tx_power_dbm != -50.0


# --------------------------------------------------------------------------- in a real browser


def _get(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=10) as response:
        return json.load(response)


def _wait_for(predicate, timeout_s: float = 15.0, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    if not CHROMIUM.exists():
        pytest.skip("Debian's chromium (/usr/bin/chromium) is not installed: run `make system-deps`")
    folder = tmp_path_factory.mktemp("tune")
    save = folder / "hover_tuned.toml"
    stderr = open(folder / "stderr.txt", "w+")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tether.cli", "tune", "hover", "--port", "0", "--view-fps", "5",
         "--video-size", "320x240", "--save", str(save)],
        stdout=subprocess.PIPE, stderr=stderr, text=True, env=ENV,
    )
    ready, _, _ = select.select([proc.stdout], [], [], 120)
    line = proc.stdout.readline() if ready else ""
    match = re.search(r"http://127\.0\.0\.1:\d+/", line)
    if not match:
        proc.kill()
        stderr.seek(0)
        raise AssertionError(f"no URL printed: {line!r} {stderr.read()}")
    url = match.group(0)
    status = lambda: _get(url + "api/status?since=1000000000")  # noqa: E731  (figures, no series)
    yield SimpleNamespace(url=url, save=save, proc=proc, status=status)
    proc.send_signal(signal.SIGINT)
    try:
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        stderr.close()


@pytest.fixture(scope="module")
def page(server):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1300, "height": 1000})
        errors = []
        page.on("pageerror", lambda err: errors.append(str(err)))
        page.goto(server.url)
        page.errors = errors
        yield page
        browser.close()


def ticks_advance(server, wait_s: float = 0.6) -> bool:
    first = server.status()["tick"]
    time.sleep(wait_s)
    return server.status()["tick"] > first


def test_page_shows_live_view_parameters_and_plots(page, server):
    page.wait_for_selector("#range-speed_mps")
    for name in ("speed_mps", "ground_speed_mps", "dwell_s"):
        assert page.locator(f"#range-{name}").is_visible() and page.locator(f"#num-{name}").is_visible()
    assert page.locator("#text-routes").is_visible()
    assert page.get_attribute("#range-speed_mps", "min") == "0.05"
    assert page.get_attribute("#range-speed_mps", "max") == "3"
    assert "m/s" in page.inner_text('.param[data-name="speed_mps"]')
    # Live view: the MJPEG stream shows frames of the requested height (the scene at its aspect).
    page.wait_for_function("document.getElementById('view').naturalHeight === 240", timeout=15000)
    # Live plots of the foundation's figures and the strategy's scalars.
    for name in ("tracking_error_mean_m", "links", "reference_speed_max_mps"):
        page.wait_for_selector(f'.plot[data-name="{name}"] canvas', timeout=15000)
    _wait_for(lambda: float(page.inner_text("#time")) > 0.5, what="sim time on the page")
    assert ticks_advance(server)
    assert not page.errors


@pytest.mark.parametrize("size", [(1600, 1000), (1280, 800)])
def test_sliders_sit_in_the_first_screen_beside_the_view_and_every_field_has_a_control(page, server, size, tmp_path):
    width, height = size
    page.set_viewport_size({"width": width, "height": height})
    page.wait_for_selector('.plot[data-name="links"] canvas', timeout=15000)
    page.screenshot(path=str(tmp_path / f"tune-{width}x{height}.png"))
    view = page.locator("#view").bounding_box()
    slider = page.locator("#range-speed_mps").bounding_box()
    plot = page.locator('.plot[data-name="links"]').bounding_box()
    # The page's purpose, the sliders, within the first screen, at the right of the view; the figures under it.
    assert slider["y"] + slider["height"] <= height and slider["x"] >= view["x"] + view["width"] - 1
    assert plot["y"] >= view["y"] + view["height"] - 1
    # Wide enough to pick a value to 1 % of its range: at least 3 px per percent.
    assert slider["width"] >= 300
    # One legend: the page's, under the view; the image is the scene alone (no panel burned in).
    assert page.locator("#legend .item").count() >= 3
    assert page.evaluate("document.getElementById('view').naturalHeight") == 240
    assert page.evaluate("document.getElementById('view').naturalWidth") < 320
    # The real-time factor, in the header.
    _wait_for(lambda: page.inner_text("#rtf").startswith("x"), what="the real-time factor")
    schema = _get(server.url + "api/params")
    for field in schema["fields"]:
        control = page.locator(f'fieldset.group[data-group="{field["group"]}"] .param[data-name="{field["name"]}"]')
        assert control.count() == 1, field["name"]
        assert control.locator("input, select, textarea").count() >= 1, field["name"]
    assert any(f["name"] == "radio.tx_power_dbm" for f in schema["fields"])
    page.set_viewport_size({"width": 1300, "height": 1000})


def test_plot_ticks_are_1_2_5_steps_from_0_for_non_negative_figures(page, server):
    page.wait_for_selector('.plot[data-name="links"] canvas', timeout=15000)
    axes = page.evaluate("""[[0.03, 1.47], [2, 38], [-0.4, 0.9], [0, 0], [0.25, 0.26]].map(([lo, hi]) => niceAxis(lo, hi))""")
    for axis, (lo, hi) in zip(axes, [(0.03, 1.47), (2, 38), (-0.4, 0.9), (0, 0), (0.25, 0.26)]):
        ticks = axis["ticks"]
        step = ticks[1] - ticks[0]
        mantissa = step / 10 ** np.floor(np.log10(step))
        assert min(abs(mantissa - m) for m in (1, 2, 5)) < 1e-6, (lo, hi, ticks)
        assert 3 <= len(ticks) <= 6 and ticks[0] <= lo + 1e-12 and ticks[-1] >= hi - 1e-12, (lo, hi, ticks)
        if lo >= 0:
            assert ticks[0] == 0, (lo, hi, ticks)  # a non-negative quantity's axis starts at 0
    assert axes[0]["ticks"] == [0, 0.5, 1, 1.5]


def test_a_radio_slider_retunes_the_channel_live(page, server):
    page.wait_for_selector('[id="range-radio.tx_power_dbm"]')
    epoch = server.status()["epoch"]
    page.fill('[id="range-radio.tx_power_dbm"]', "-10")
    _wait_for(lambda: server.status()["params"]["radio.tx_power_dbm"] == -10.0, what="radio.tx_power_dbm = -10")
    page.wait_for_function("document.getElementById('message').textContent.includes('updated')")
    assert server.status()["epoch"] == epoch and ticks_advance(server)  # live, not a restart


def test_slider_changes_the_running_strategy(page, server):
    before = server.status()
    assert before["params"]["speed_mps"] == 0.5
    assert before["figures"]["reference_speed_max_mps"] <= 0.5 + 1e-6
    page.fill("#range-speed_mps", "1.5")  # dispatches input + change, like a drag
    after = _wait_for(lambda: (s := server.status())["params"]["speed_mps"] == 1.5 and s, what="speed_mps = 1.5")
    assert after["params_tick"] >= before["tick"]
    assert page.input_value("#num-speed_mps") == "1.5"
    page.wait_for_function("document.getElementById('message').textContent.includes('applied')")
    # The quadrotors now fly their segments up to three times faster.
    _wait_for(lambda: server.status()["figures"]["reference_speed_max_mps"] > 0.75, what="faster references")


def test_out_of_range_value_is_refused_visibly_and_the_sim_keeps_going(page, server):
    field = page.locator("#num-speed_mps")
    field.fill("99")
    field.press("Tab")  # commit: the change event
    message = page.locator("#message")
    page.wait_for_function("document.getElementById('message').classList.contains('error')")
    assert message.is_visible()
    assert "strategy.speed_mps: must be in [0.05, 3] m/s, got 99" in message.inner_text()
    assert server.status()["params"]["speed_mps"] == 1.5
    page.wait_for_function("document.getElementById('num-speed_mps').value === '1.5'")
    assert ticks_advance(server)


def test_pause_step_resume_and_reset(page, server):
    page.click("#pause")
    _wait_for(lambda: server.status()["paused"], what="paused")
    assert not ticks_advance(server, 0.4)
    tick = server.status()["tick"]
    page.click("#step")
    _wait_for(lambda: server.status()["tick"] == tick + 1, what="one step")
    page.click("#pause")  # now labelled Resume
    _wait_for(lambda: not server.status()["paused"], what="running")
    assert ticks_advance(server)
    epoch, t = server.status()["epoch"], server.status()["time_s"]
    page.click("#reset")
    after = _wait_for(lambda: (s := server.status())["epoch"] == epoch + 1 and s, what="reset")
    assert after["time_s"] < t
    assert after["params"]["speed_mps"] == 1.5  # a reset keeps the tuned parameters
    assert ticks_advance(server)


def test_save_as_scenario_toml_reloads_with_tether_run(page, server, tmp_path):
    page.click("#save")
    page.wait_for_function("document.getElementById('message').textContent.includes('saved to')")
    assert server.save.is_file()
    with page.expect_download() as download:
        page.click("#download")
    assert Path(download.value.path()).read_text().split("\n", 1)[1] == server.save.read_text().split("\n", 1)[1]
    scenario = load(str(server.save), duration_s=0.2)
    assert scenario.strategy.params.speed_mps == 1.5
    result = run(scenario, tmp_path / "out")
    assert result.status == "completed"
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["scenario"] == "hover_tuned"
