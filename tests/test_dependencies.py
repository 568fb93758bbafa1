"""pyproject.toml declares what the code imports: the runtime (estimator/, capture/, service/) its
dependencies and nothing more, tests and benchmarks their extras (issue 19)."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ("estimator", "capture", "service")
OPTIONAL = {"harvesters": "genicam"}
"""Imports the runtime makes only when asked for (guarded, with a message naming the extra)."""
NOT_IMPORTED = {"python-multipart": "FastAPI's form parsing imports it (as multipart)"}
"""Runtime dependencies no module of ours imports by name."""
ELSEWHERE = {"aniposelib": "bench/check_aniposelib.py"}
"""Imports of scripts that run in an environment of their own (their docstring says how): aniposelib needs
opencv-contrib-python, numba and jax, which do not sit beside posecal's headless OpenCV."""


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _third_party(*folders: str) -> dict[str, set[str]]:
    """Top-level modules imported under ``folders`` that are neither the standard library nor ours."""
    ours = set(RUNTIME) | {p.stem for f in ("tests", "bench") for p in (ROOT / f).glob("*.py")}
    found: dict[str, set[str]] = {}
    for folder in folders:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                    [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
                for name in names:
                    top = name.split(".")[0]
                    if top not in sys.stdlib_module_names and top not in ours:
                        found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def _declared(*extras: str) -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"]) + [r for e in extras for r in project["optional-dependencies"][e]]
    return {_norm(re.split(r"[<>=!~;\[ ]", r, maxsplit=1)[0]) for r in reqs}


def _distributions(module: str) -> set[str]:
    return {_norm(d) for d in packages_distributions().get(module, [])}


def test_the_runtime_imports_what_it_declares_and_declares_what_it_imports():
    runtime, imports = _declared(), _third_party(*RUNTIME)
    undeclared = {m: sorted(files)[:3] for m, files in imports.items()
                  if m not in OPTIONAL and not _distributions(m) & runtime}
    assert not undeclared, f"imported by the runtime, not in [project.dependencies]: {undeclared}"
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for module, extra in OPTIONAL.items():
        assert any(_norm(r).startswith(module) for r in extras[extra]), (module, extra)
    provided = set().union(*(_distributions(m) for m in imports)) | set(NOT_IMPORTED)
    unused = sorted(runtime - provided)
    assert not unused, f"in [project.dependencies] but not imported by the runtime (an extra?): {unused}"


def test_tests_and_benchmarks_imports_are_in_their_extras():
    declared = _declared("test", "eval")
    imports = _third_party("tests", "bench")
    undeclared = {m: sorted(files)[:3] for m, files in imports.items()
                  if not _distributions(m) & declared and sorted(files) != [ELSEWHERE.get(m)]}
    assert not undeclared, f"imported by tests/ or bench/, not declared (runtime, test or eval): {undeclared}"
    assert "matplotlib" in _declared("eval") - _declared(), "plots belong to the eval extra"
