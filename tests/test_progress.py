"""`tether run` progress: plain periodic lines into a pipe, a tqdm bar on a
terminal that ends cleanly when the mission ends early, nothing with --quiet."""

from __future__ import annotations

import io

from tether.cli import main
from tether.progress import RunProgress, headline


def test_plain_lines_into_a_pipe_and_quiet_prints_only_the_summary(tmp_path, capsys):
    assert main(["run", "hover", "--duration", "2", "--out", str(tmp_path / "a")]) == 0
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert "\r" not in captured.err
    # Every 10 % of 2 s (the loop reports once a simulated second): t = 1, 2 s.
    assert [line.split(",")[0].strip() for line in lines] == ["t = 1.0/2.0 s (50 %)", "t = 2.0/2.0 s (100 %)"]
    assert "real time" in lines[0]
    assert captured.out.startswith("completed: hover")

    assert main(["run", "hover", "--duration", "1", "--out", str(tmp_path / "b"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    assert len(captured.out.splitlines()) == 1 and captured.out.startswith("completed: hover")


class _FakeSim:
    def __init__(self, time_s: float, visited: int):
        self.time_s = time_s
        self.strategy = self
        self.visited = visited

    def summary(self) -> dict:
        return {"targets_visited": self.visited, "targets_total": 25}


def test_bar_on_a_terminal_ends_where_an_early_mission_stopped():
    stream = io.StringIO()
    progress = RunProgress(100.0, stream=stream, bar=True)
    for k in range(1, 5):
        progress(_FakeSim(float(k), visited=k))
    # The mission ends at 4.5 s of a 100 s cap: the bar closes full, with the final figure.
    progress.close({"sim_time_s": 4.5, "targets_visited": 7, "targets_total": 25})
    text = stream.getvalue()
    final = text.split("\r")[-1]
    assert "100%" in final and "4.5/4.5 sim s" in final and "targets 7/25" in final
    assert "real time" in final


def test_headline_of_each_strategy_family():
    assert headline({"targets_visited": 3, "targets_total": 25}) == "targets 3/25"
    assert headline({"meetings_held": 4, "meetings_scheduled": 6, "plans": 9}) == "meetings 4/6"
    assert headline({"meetings_held": 0, "meetings_scheduled": 0, "plans": 2}) == "paths planned 2"
    assert headline({}) == ""
