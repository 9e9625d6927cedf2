"""Every import points down: estimation, then sim, then controllers and viz, then tether.

Read from the source (every ``import``, lazy ones inside functions included),
so a layer cannot reach up even where it would only do so at run time.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("models", "estimation", "sim", "controllers", "viz", "tether")
# What each layer may import of the project's packages (besides itself).
ALLOWED = {
    "models": set(),
    "estimation": set(),
    "sim": {"estimation", "models"},
    "controllers": {"sim", "estimation"},
    "viz": {"sim", "estimation"},
    "tether": {"sim", "estimation", "controllers", "viz", "models"},
}
# Third-party modules a layer must not import.
FORBIDDEN_LIBRARIES = {"estimation": {"mujoco"}}


def imports_of(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in the file; relative imports stay in the package."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
    return found


def layer_violations(package: str) -> list[str]:
    problems = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for line, module in imports_of(path):
            top = module.split(".")[0]
            if top in PACKAGES and top != package and top not in ALLOWED[package]:
                problems.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
            if top in FORBIDDEN_LIBRARIES.get(package, ()):
                problems.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    return problems


@pytest.mark.parametrize("package", PACKAGES)
def test_every_import_points_down(package):
    assert (ROOT / package / "__init__.py").is_file()
    assert layer_violations(package) == []


def test_the_reader_sees_lazy_imports(tmp_path):
    """The check itself: an import inside a function is found."""
    source = tmp_path / "lazy.py"
    source.write_text("def f():\n    from viz.video import VideoRecorder\n    import controllers.task\n")
    assert [module for _, module in imports_of(source)] == ["viz.video", "controllers.task"]
