"""tether as an installed package: the wheel, built and installed in a clean venv.

``python -m build`` makes the sdist and, from it, the wheel (so no stale
``build/`` folder of the work tree can leak into it); its output must hold no
warning. The wheel must hold every module of the packages and every data file
they read (MJCF models, scenarios, sweeps, static pages), and nothing of
tests/, docs/ or bench/. Installed into a fresh venv (no site packages, no
PYTHONPATH) and run from a folder outside the repository, the ``tether``
script must run the built-in scenarios, list scenarios and sweeps, write a
scenario and run one in an installed scene file. ``make wheel-check`` runs
this test, and CI runs that after ``make test``. Slow: about two minutes,
most of it installing the dependencies into the fresh venv.
"""

import os
import shutil
import subprocess
import sys
import time
import venv
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ["tether", "sim", "controllers", "viz", "estimation", "models"]
# Data folders: every file in them (any suffix) must be in the wheel.
DATA_DIRS = ["models", "tether/scenarios", "tether/sweeps", "viz/static"]
NOT_SHIPPED = ["tests/", "docs/", "bench/"]
RUNS = [
    ["run", "hover", "--duration", "2", "--out", "OUT"],
    ["run", "connected-office", "--duration", "5", "--out", "OUT2"],
    ["run", "intermittent-4", "--duration", "10", "--out", "OUT3"],
]


def expected_files() -> set[str]:
    """What the wheel must hold: the packages' .py files and their data files."""
    files = set()
    for package in PACKAGES:
        files |= {p.relative_to(REPO).as_posix() for p in (REPO / package).rglob("*.py")}
    for folder in DATA_DIRS:
        files |= {p.relative_to(REPO).as_posix() for p in (REPO / folder).rglob("*") if p.is_file()}
    return {f for f in files if "__pycache__" not in f and not f.endswith((".pyc", ".pyo"))}


def clean_env() -> dict[str, str]:
    """The environment without anything that points Python at the repository."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    # Set on some machines; it only makes distutils print "byte-compiling is
    # disabled" warnings (a wheel holds no .pyc either way).
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def run(argv, cwd, env, timeout=300) -> subprocess.CompletedProcess:
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    output = done.stdout + done.stderr
    assert done.returncode == 0, f"{' '.join(map(str, argv))} exited {done.returncode}:\n{output[-4000:]}"
    return done


def test_wheel_installs_and_runs_outside_the_repo(tmp_path):
    start = time.monotonic()
    env = clean_env()
    dist = tmp_path / "dist"
    egg_info = REPO / "tether.egg-info"
    had_egg_info = egg_info.exists()
    try:
        build = run([sys.executable, "-m", "build", "--outdir", str(dist), str(REPO)], tmp_path, env)
    finally:
        if not had_egg_info:  # the sdist step writes it into the source tree
            shutil.rmtree(egg_info, ignore_errors=True)
    warnings = [line for line in (build.stdout + build.stderr).splitlines() if "warn" in line.lower()]
    assert not warnings, "the build warned:\n" + "\n".join(warnings)

    built = time.monotonic()
    (wheel,) = dist.glob("*.whl")
    names = {n for n in zipfile.ZipFile(wheel).namelist() if ".dist-info/" not in n}
    missing = expected_files() - names
    assert not missing, f"not in the wheel: {sorted(missing)}"
    shipped = [n for n in names if n.startswith(tuple(NOT_SHIPPED))]
    assert not shipped, f"in the wheel but not package files: {shipped}"
    assert {n.split("/")[0] for n in names} == set(PACKAGES)

    # A fresh venv, run from a folder outside the repository.
    venv.create(tmp_path / "venv", with_pip=True)
    bin_dir = tmp_path / "venv" / "bin"
    work = tmp_path / "work"
    work.mkdir()
    run([bin_dir / "python", "-m", "pip", "install", "-q", wheel], work, env, timeout=600)
    installed = time.monotonic()
    where_code = "import tether, models; print(tether.__file__); print(models.MODELS_DIR)"
    where = run([bin_dir / "python", "-c", where_code], work, env).stdout
    tether_file, models_dir = where.split()
    assert Path(tether_file).is_relative_to(tmp_path / "venv"), tether_file
    flat = Path(models_dir) / "scenes" / "examples" / "flat.xml"
    assert flat.is_file()

    tether = str(bin_dir / "tether")
    for argv in RUNS:
        run([tether, *argv, "--quiet"], work, env)
        assert (work / argv[-1] / "metrics.json").is_file(), argv
    assert "hover" in run([tether, "scenarios"], work, env).stdout
    assert "fig9" in run([tether, "sweeps"], work, env).stdout
    written = run([tether, "init", "hover"], work, env).stdout
    assert 'scene = "indoor"' in written
    (work / "hover.toml").write_text(written)
    run([tether, "run", "hover.toml", "--duration", "1", "--out", "OUT5", "--quiet"], work, env)
    own_scene = ["run", "intermittent-4", "--scene", str(flat), "--duration", "2", "--out", "OUT4", "--quiet"]
    run([tether, *own_scene], work, env)
    assert (work / "OUT4" / "metrics.json").is_file()
    end = time.monotonic()
    print(
        f"wheel check: {end - start:.0f} s (build {built - start:.0f} s, venv and install "
        f"{installed - built:.0f} s, commands {end - installed:.0f} s)"
    )
