"""The README's commands run, so the README cannot go stale.

Every ``tether`` line of the README's ```sh blocks is run through the CLI's
``main`` (what ``.venv/bin/tether`` calls), in order, in a scratch folder:
runs get a short ``--duration`` and their own ``--out``, the intermittent
methods plan with fewer RRT* samples (their a priori plans would otherwise
cost most of the test), and a ``> FILE`` redirect writes the scratch folder.
Commands that cannot finish by themselves or take long are skipped by name,
each with its reason below; ``make demo`` and ``make test`` are what this
suite and the demo run are.
"""

import contextlib
import io
import re
import shlex
from pathlib import Path


from tether.cli import _parser, main
from sim.scenario import load

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
SHORT_DURATION_S = "0.2"
# Fewer RRT* samples for the intermittent methods' a priori plans (300 and 100 in the scenarios).
CHEAP_PLANNING = ["--set", "strategy.n_sample=40", "--set", "strategy.n_uniform=20"]
RRT_KINDS = ("intermittent", "all_time", "random_meeting")  # the kinds that read those fields
# Subcommands and programs not run here, and why.
SKIPPED = {
    "make": "make demo / make test: this suite is make test, and make demo is a run like the ones below",
    "rerun": "opens the Rerun viewer, a window that stays open",
    "view": "opens MuJoCo's viewer window until closed (tests/test_viewer.py drives it under Xvfb)",
    "tune": "serves the tuning page until Ctrl-C (tests/test_tuning_page.py drives it in a browser)",
    "sweep": "runs 60 to 180 trials of up to 900 s each (the sweep's own tests run small sweeps)",
    "report": "reads a sweep's results folder, which the skipped sweep would have written",
}


def readme_commands() -> list[str]:
    """The command lines of the README's sh blocks (continuations joined, comments cut)."""
    blocks = re.findall(r"```sh\n(.*?)```", README.read_text(), flags=re.S)
    commands = []
    for block in blocks:
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #", 1)[0].strip()
            if line and not line.startswith("#"):
                commands.append(line)
    return commands


def program_and_subcommand(command: str) -> tuple[str, str]:
    words = shlex.split(command)
    return Path(words[0]).name, (words[1] if len(words) > 1 else "")


def test_readme_starts_with_the_two_commands():
    assert readme_commands()[:2] == ["make demo", "make test"]


def test_every_readme_command_is_run_or_skipped_for_a_listed_reason():
    subcommands = set(_parser()._subparsers._group_actions[0].choices)
    for command in readme_commands():
        program, sub = program_and_subcommand(command)
        assert program == "tether" or program in SKIPPED, command
        if program == "tether":
            assert sub in subcommands or sub in SKIPPED, command


def short(argv: list[str], out_dir: Path, scratch: Path) -> list[str]:
    """A run's argv with a short duration, an output folder in ``scratch``, and
    cheap planning for the intermittent methods."""
    argv = [str(scratch / a) if a.endswith(".toml") and not Path(a).exists() else a for a in argv]
    if "--duration" in argv:
        i = argv.index("--duration")
        argv[i + 1] = SHORT_DURATION_S
    else:
        argv += ["--duration", SHORT_DURATION_S]
    argv += ["--out", str(out_dir)]
    scenario = argv[1]
    overrides = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
    if load(scenario, overrides).strategy.kind in RRT_KINDS:
        argv += CHEAP_PLANNING
    return argv


def test_readme_commands_run(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)  # the README's paths are relative to the repository
    ran = []
    for index, command in enumerate(readme_commands()):
        program, sub = program_and_subcommand(command)
        if program != "tether" or sub in SKIPPED:
            continue
        command, _, redirect = command.partition(">")
        argv = shlex.split(command)[1:]
        if sub == "run":
            argv = short(argv, tmp_path / f"run{index}", tmp_path)
        if sub == "radiomap":  # into the scratch folder, not the repository's runs/
            argv += ["--out", str(tmp_path / f"radiomap{index}.png")]
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            code = main(argv)
        assert code == 0, f"{command}: exit {code}"
        if redirect.strip():
            (tmp_path / redirect.strip()).write_text(out.getvalue())
        if sub == "run":
            assert (tmp_path / f"run{index}" / "metrics.json").is_file(), command
            for flag, name in (("--video", "video.mp4"), ("--rrd", "run.rrd")):
                assert (flag not in argv) or (tmp_path / f"run{index}" / name).stat().st_size > 0, command
        ran.append(sub)
    assert ran.count("run") >= 5 and "init" in ran and "scenarios" in ran
