"""Plot pages drawn by painter processes: figures built during the run, filled at its end.

A page is a column of panels; a panel is one series (times, values) or one
line per robot. What a page shows (its panels' titles, line counts and coded
levels: its *layout*) is known a few ticks into a run, its data only at the
end. Most of a page's cost is matplotlib's: importing it (about a second of
CPU), building the axes and their ticks, rasterising the fonts. So
:class:`Painters` starts painter processes that pay for all of that while the
simulation runs, each for its share of the pages (one process per page, up
to the CPUs this process may use), and at the end of the run only set the
lines' data and write the PNGs, in parallel. Where no child process can be
started (a daemonic pool worker, say), or a painter dies, pages are drawn in
this process by :func:`draw_pages`, through the same three steps.

Child processes (the painters, the video renderer of viz.video) are
supervised: they are started with SIGINT and SIGTERM held back
(:func:`group_signals_deferred`) and ignore both from their first
instruction on (:func:`ignore_group_signals`), so a terminal's Ctrl-C to the
process group, or a SIGTERM to it, reaches only the run, which stops them in
order; every wait on one is bounded and checks that it is alive; and any
still running when the run's process exits is killed (:func:`supervise`),
never left behind nor waited for without end.

This module imports only numpy at the top: a painter process starts from it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import textwrap
import threading
import time
from typing import Any, NamedTuple

import numpy as np

SAVE_DPI = 110
# Reports' figures (table1.png, paradigms.png, grid.png, the study's): a slide shows them at half their
# size or less, so they are saved at twice a screen's dpi (at 110, 10-point text was 7 px at 50 %).
REPORT_DPI = 200
ROBOT_LINE_STYLES = ("-", "--", ":")  # per robot, each after the palette's colours ran out
LEGEND_MAX_ROBOTS = 12  # per-robot panels name their lines up to this many robots
LEVELS_LEGEND_ROOM = 1.4  # a levels panel with the robots' legend reaches this far above its top level
LEFT, RIGHT = 0.11, 0.98  # the axes' edges, as fractions of the page's width
LABEL_OFFSET_IN = 0.55  # a panel's title (its y label) from the axes' left edge
LABEL_WRAP_CHARS = 28  # a panel's title wraps onto a second line beyond this many characters
LEVELS_LABEL_OFFSET_IN = 0.74  # ... beyond coded levels' names ("secondary" at 7 pt)
MAX_PAINTERS = 4  # beyond this, another process's import costs more than the pages it would draw
PAINTER_TIMEOUT_S = 20.0  # a painter that has not sent its pages by then is stopped; they are drawn here
STOP_WAIT_S = 2.0  # how long a child that should end is waited for before it is killed
GROUP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def group_signals_deferred():
    """SIGINT and SIGTERM held back while a child process is started: the
    child inherits them blocked (a spawned child keeps the mask across exec)
    and ignores them before it unblocks them, so a Ctrl-C during its start
    cannot print its bootstrap's traceback; in this process a signal that
    came meanwhile is handled (by the handler in place before) once the
    child is started and registered."""
    from multiprocessing import resource_tracker

    # Its launch (at a spawned child's first start) unblocks SIGINT and SIGTERM when done: it goes first.
    resource_tracker.ensure_running()
    caught: list[int] = []
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in GROUP_SIGNALS:
            previous[sig] = signal.signal(sig, lambda signum, _frame: caught.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, GROUP_SIGNALS)
    try:
        yield
    finally:
        for sig, handler in previous.items():  # still blocked: nothing can run between these
            signal.signal(sig, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a pending one runs the handler in place now
        for sig in dict.fromkeys(caught):
            signal.raise_signal(sig)  # the handler in place before decides


def ignore_group_signals() -> None:
    """In a child process, first thing: SIGINT and SIGTERM sent to the process
    group are the run's to handle (it stops its children in order)."""
    for sig in GROUP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, GROUP_SIGNALS)  # what came during the start is dropped


_supervised: list[Any] = []  # child processes to kill, should they outlive their run, at exit


def supervise(process) -> None:
    """Kill ``process`` at this process's exit if it is still running. Called
    after multiprocessing is imported, so this runs before multiprocessing's
    own exit hook, which would SIGTERM (ignored) and join without end."""
    import atexit

    _supervised[:] = [p for p in _supervised if p.exitcode is None]
    if not _supervised:
        atexit.unregister(_reap)
        atexit.register(_reap)
    _supervised.append(process)


@contextlib.contextmanager
def children_killed_on_error():
    """The children started inside are killed (SIGKILL) if it raises. A
    spawned child may still be starting: it opens its queue's semaphores by
    name, which this process unlinks once it drops them, and would print its
    bootstrap's traceback (FileNotFoundError) after this process has reported
    its interrupt or error."""
    before = list(_supervised)
    try:
        yield
    except BaseException:
        started = [process for process in _supervised if all(process is not old for old in before)]
        for process in started:
            if process.exitcode is None:
                process.kill()
        for process in started:
            process.join(STOP_WAIT_S)
        raise


def stop_process(process, wait_s: float = STOP_WAIT_S) -> None:
    """Wait up to ``wait_s`` for ``process`` to end, then kill it (SIGKILL: it
    ignores SIGTERM) and reap it."""
    process.join(wait_s)
    if process.exitcode is None:
        process.kill()
        process.join(wait_s)


def _reap() -> None:
    for process in _supervised:
        if process.exitcode is None:
            process.kill()
    for process in _supervised:
        process.join(STOP_WAIT_S)
    _supervised.clear()


def exit_reason(exitcode: int | None) -> str:
    """``exit -9 (SIGKILL)`` for a child killed by a signal, ``exit 1`` otherwise."""
    if exitcode is not None and exitcode < 0:
        try:
            return f"exit {exitcode}, {signal.Signals(-exitcode).name}"
        except ValueError:
            pass
    return f"exit {exitcode}"

# A panel's data: (title, data, values, levels[, integer]). data is (T, 2) [time, value] for
# a series (values None), or times (T,) with values (T, N) for a per-robot series,
# whose codes ``levels`` [(value, label)] (or None) are named on the axis; ``integer``
# (optional, False): the values are counts or indices, on an integer axis, drawn as steps.
Panel = tuple
# A panel's layout: (title, lines per robot or None for one series, levels or None[, integer]).
PanelLayout = tuple


def panel_layout(panel: Panel) -> PanelLayout:
    title, _, values, levels = panel[:4]
    integer = bool(panel[4]) if len(panel) > 4 else False
    return title, None if values is None else int(values.shape[1]), tuple(levels) if levels else None, integer


class Page(NamedTuple):
    figure: Any
    axes: list[Any]
    lines: list[list[Any]]  # per panel, its lines
    title: Any  # the page's title (the run's status)


def build_page(layout: tuple[PanelLayout, ...], robot_names: tuple[str, ...] | None) -> Page:
    """The figure of one page, with empty lines, labels, legend and coded levels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    from sim.palette import SERIES

    height = 1.9 * len(layout) + 0.6
    # The Figure API (no pyplot state) and fixed margins: tight_layout took a fifth of the drawing.
    figure = Figure(figsize=(8, height), dpi=SAVE_DPI)  # drawn at the dpi it is saved at: caches stay valid
    FigureCanvasAgg(figure)
    axes = list(figure.subplots(len(layout), 1, sharex=True, squeeze=False)[:, 0])
    figure.subplots_adjust(left=LEFT, right=RIGHT, top=1.0 - 0.35 / height, bottom=0.45 / height, hspace=0.12)
    lines = []
    legend = True  # on the first per-robot panel of a page
    for ax, (panel_title, n_lines, levels, *flags) in zip(axes, layout):
        integer = bool(flags and flags[0])
        drawstyle = "steps-post" if integer else "default"  # a count changes in steps, never in between
        ax.set_prop_cycle(color=[tuple(c) for c in SERIES])
        if n_lines is None:
            lines.append(ax.plot([], [], lw=1.2, drawstyle=drawstyle))
        else:
            names = robot_names if robot_names is not None else [f"robot {i}" for i in range(n_lines)]
            named = legend and robot_names is not None and n_lines <= LEGEND_MAX_ROBOTS
            # Past the palette's colours the robots differ by their line too (robot 8 was robot 0's twin).
            lines.append([ax.plot([], [], lw=1.0, label=names[i], drawstyle=drawstyle,
                                  ls=ROBOT_LINE_STYLES[(i // len(SERIES)) % len(ROBOT_LINE_STYLES)])[0]
                          for i in range(n_lines)])
            if named:
                ax.legend(fontsize=6, ncol=min(n_lines, 6), loc="upper right")
            legend = False
            if levels:  # codes (e.g. roles): name each level on the axis
                # One word a line: "secondary traveler" on one line ran past the page's left edge.
                ax.set_yticks([v for v, _ in levels], [label.replace(" ", "\n") for _, label in levels], fontsize=7)
                # Room above the top level for the robots' legend, which covered that level's lines.
                ax.set_ylim(levels[0][0] - 0.5, levels[-1][0] + (LEVELS_LEGEND_ROOM if named else 0.5))
        if not levels:  # counts: whole-number ticks only, one if that is all there is room for
            ax.yaxis.set_major_locator(MaxNLocator(nbins=4, steps=[1, 2, 5, 10], integer=integer,
                                                   min_n_ticks=1 if integer else 2))
        ax.set_ylabel(textwrap.fill(panel_title, LABEL_WRAP_CHARS), fontsize=8)
        # At a fixed distance left of the axes, beyond 8 pt tick labels: placing it after the tick labels'
        # extents (matplotlib's default) took a third of a page's drawing.
        offset_in = LEVELS_LABEL_OFFSET_IN if levels else LABEL_OFFSET_IN
        ax.yaxis.set_label_coords(-offset_in / (figure.get_figwidth() * (RIGHT - LEFT)), 0.5)
        ax.grid(alpha=0.3)
        ax.tick_params(bottom=False, left=False, labelsize=8)  # the grid marks the ticks; each mark is a line
    axes[-1].set_xlabel("sim time (s)")
    # Six time ticks, not nine (and four on each panel's value axis): ticks and their labels are most of a
    # page's drawing.
    axes[0].xaxis.set_major_locator(MaxNLocator(nbins=6, steps=[1, 2, 5, 10]))
    # 0.1 in below the page's top: at matplotlib's 2 % of a tall page it touched the first panel.
    title_text = figure.suptitle("run", fontsize=9, y=1.0 - 0.1 / height)
    return Page(figure, axes, lines, title_text)


def fill_page(page: Page, panels: list[Panel], title: str) -> None:
    """Give the page's lines their data (NaN is a gap) and its axes their limits."""
    for ax, lines, panel in zip(page.axes, page.lines, panels):
        _, data, values, levels = panel[:4]
        if values is None:
            lines[0].set_data(data[:, 0], data[:, 1])
        else:
            for robot, line in enumerate(lines):
                line.set_data(data, values[:, robot])
        ax.relim()
        ax.autoscale_view()
        shown = (data[:, 1] if values is None else values).astype(float)
        shown = shown[np.isfinite(shown)]
        if levels or not shown.size:
            continue
        if len(panel) > 4 and panel[4]:  # counts: from 0 (when none is negative), at least 0..1
            low = min(0.0, shown.min())
            high = max(shown.max(), low + 1.0)
            pad = 0.05 * (high - low)
            ax.set_ylim(low - pad, high + pad)
        elif panel[0].endswith("(ratio)") and shown.min() >= 0 and shown.max() <= 1:  # a share: 0 to 1
            ax.set_ylim(-0.03, 1.03)
        else:
            axis_from_zero(ax, shown.min(), shown.max())
    page.title.set_text(title)


def axis_from_zero(ax, lowest: float, highest: float) -> None:
    """A never-negative quantity's value axis (``lowest`` >= 0 of what is drawn) starts at 0: it does not
    pretend the value could be negative (matplotlib pads a flat line by +-0.5, or 5 % below its lowest)."""
    low, high = ax.get_ylim()
    if lowest >= 0 and low < 0:
        high = max(high, 1.0) if highest == 0 else high
        ax.set_ylim(-0.03 * high, high)


def save_page(page: Page, path: str) -> str:
    """Draw the page and write it as an RGB PNG at zlib level 1: Pillow's row filters cost
    a third less on RGB than on savefig's RGBA, and the page is opaque, so nothing is lost."""
    from PIL import Image

    canvas = page.figure.canvas
    canvas.draw()
    rgba = canvas.buffer_rgba()
    Image.frombuffer("RGBA", (rgba.shape[1], rgba.shape[0]), rgba, "raw", "RGBA", 0, 1).convert("RGB").save(
        path, format="png", compress_level=1)
    return path


def page_layout(panels: list[Panel]) -> tuple[PanelLayout, ...]:
    return tuple(panel_layout(panel) for panel in panels)


def draw_pages(pages: list[tuple[str, list[Panel]]], title: str, robot_names: tuple[str, ...] | None,
               built: dict[str, tuple[tuple[PanelLayout, ...], Page]] | None = None) -> list[str]:
    """Write one PNG per page [(path, panels)]; returns the paths. A page in ``built``
    (path -> (layout, page), a painter's figures built ahead) is filled if its layout
    still holds, else built here."""
    _matplotlib()
    files = []
    for path, panels in pages:
        layout = page_layout(panels)
        ahead = (built or {}).get(path)
        page = ahead[1] if ahead is not None and ahead[0] == layout else build_page(layout, robot_names)
        fill_page(page, panels, title)
        files.append(save_page(page, path))
    return files


def _matplotlib() -> None:
    import matplotlib

    matplotlib.use("Agg")


def usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


class Painters:
    """Painter processes for one run's pages; page ``i`` is drawn by painter ``i % n``.

    ``plan(layouts)`` (cheap, any number of times: the latest wins) tells the
    painters what the pages will look like, starting more painters when there
    are more pages; ``start(pages, title)`` hands them the data and returns at
    once; ``finish()`` waits for the PNGs.
    """

    def __init__(self, robot_names: tuple[str, ...] | None, max_painters: int | None = None):
        self.robot_names = robot_names
        self.max_painters = max_painters if max_painters is not None else min(MAX_PAINTERS, usable_cpus())
        self._painters: list[tuple[Any, Any]] = []  # (process, connection)
        self._can_spawn = True
        self._started: list[tuple[str, list[Panel]]] | None = None
        self._title = ""
        self._add_painter()  # at once: its matplotlib import runs alongside the simulation

    def plan(self, layouts: list[tuple[str, tuple[PanelLayout, ...]]]) -> None:
        while len(self._painters) < min(len(layouts), self.max_painters) and self._add_painter():
            pass
        self._send_shares("layout", layouts)

    def start(self, pages: list[tuple[str, list[Panel]]], title: str) -> None:
        self._started, self._title = pages, title
        self._send_shares("draw", pages, title)

    def finish(self) -> list[str]:
        """The PNG paths in page order; a painter that died, or sent nothing within
        ``PAINTER_TIMEOUT_S``, has its pages drawn here."""
        if self._started is None:  # nothing to draw: the painters see their pipe close and end
            for process, connection in self._painters:
                connection.close()
            for process, _ in self._painters:
                stop_process(process)
            self._painters = []
            return []
        pages, title = self._started, self._title
        files: list[str | None] = [None] * len(pages)
        n = len(self._painters)
        deadline = time.monotonic() + PAINTER_TIMEOUT_S
        for index, (process, connection) in enumerate(self._painters):
            share = list(range(index, len(pages), n))
            drawn = _receive(process, connection, deadline)
            if drawn is None:  # the painter died or hangs: draw its share here
                drawn = draw_pages([pages[i] for i in share], title, self.robot_names)
            for i, path in zip(share, drawn):
                files[i] = path
            connection.close()
            stop_process(process)
        if not self._painters:
            files = draw_pages(pages, title, self.robot_names)
        self._painters = []
        return [path for path in files if path is not None]

    def _send_shares(self, kind: str, pages: list, *extra: Any) -> None:
        n = len(self._painters)
        for index, (_, connection) in enumerate(self._painters):
            message = (kind, pages[index::n], *extra)
            if kind == "draw":  # the data can exceed the pipe's buffer: never wait on a painter here
                threading.Thread(target=_send_quietly, args=(connection, message), daemon=True,
                                 name=f"plot-painter-{index}-send").start()
            else:
                _send_quietly(connection, message)

    def _add_painter(self) -> bool:
        if not self._can_spawn:
            return False
        import multiprocessing

        try:
            context = multiprocessing.get_context("spawn")
            connection, child = context.Pipe()
            process = context.Process(target=_paint, args=(child, self.robot_names), daemon=True,
                                      name=f"plot-painter-{len(self._painters)}")
            with group_signals_deferred():
                process.start()
                supervise(process)
            child.close()
        except (AssertionError, OSError, RuntimeError):  # no child processes here (e.g. a daemonic worker)
            self._can_spawn = False
            return False
        self._painters.append((process, connection))
        return True


def _send_quietly(connection, message) -> None:
    try:
        connection.send(message)
    except (OSError, ValueError):  # a dead painter (or a closed pipe): finish() draws its share here
        pass


def _receive(process, connection, deadline: float) -> list[str] | None:
    """A painter's PNG paths; None once it is dead, or past ``deadline`` (it is then killed)."""
    while True:
        try:
            if connection.poll(0.1):
                return connection.recv()
        except (EOFError, OSError):
            return None
        if process.exitcode is not None and not connection.poll(0):
            return None
        if time.monotonic() > deadline:
            process.kill()
            return None


def _paint(connection, robot_names) -> None:
    """A painter process: build (and draw once, which creates the ticks and
    rasterises the fonts) the figures of the pages it is planned, then fill
    and save them when the data comes. Signals to the group are the run's."""
    ignore_group_signals()
    _matplotlib()
    from matplotlib.figure import Figure  # noqa: F401  (the expensive import, while the run goes on)

    built: dict[str, tuple[tuple[PanelLayout, ...], Page]] = {}
    while True:
        try:
            kind, pages, *extra = connection.recv()
        except (EOFError, OSError):  # the run ended without plots (or is gone)
            return
        if kind == "layout":
            for path, layout in pages:
                if connection.poll():  # newer news (a new layout or the data): that first
                    break
                if path not in built or built[path][0] != layout:
                    page = build_page(layout, robot_names)
                    page.figure.canvas.draw()
                    built[path] = (layout, page)
            continue
        (title,) = extra
        try:
            drawn = draw_pages(pages, title, robot_names, built)
        except OSError:  # a full disk, a folder gone: the run draws these pages itself and reports it
            os._exit(1)
        _send_quietly(connection, drawn)  # the run may be gone: nothing to tell then
        os._exit(0)  # at once: a normal exit tears down the figures while the run waits in join
