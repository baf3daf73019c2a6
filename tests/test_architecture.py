"""The wings keep their import directions and their size (groundstation/__init__.py says why)."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GS = ROOT / "groundstation"

# wing -> wings it must not import
FORBIDDEN = {
    "io": {"jobs", "sim", "station", "cli"},
    "jobs": {"sim", "station", "cli"},
    "sim": {"jobs", "station", "cli"},
    "station": {"sim", "cli"},
}


def _imports(path: Path) -> list[str]:
    """Absolute module names imported by a file (relative imports resolved)."""
    pkg = list(path.relative_to(ROOT).with_suffix("").parts[:-1])
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg[: len(pkg) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
                names += [mod] + [f"{mod}.{a.name}" for a in node.names]
            elif node.module:
                names += [node.module] + [f"{node.module}.{a.name}" for a in node.names]
    return names


def _wing(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "groundstation" and len(parts) > 1 else None


@pytest.mark.parametrize("wing", sorted(FORBIDDEN))
def test_wing_import_directions(wing):
    for path in (GS / wing).rglob("*.py"):
        for name in _imports(path):
            target = _wing(name)
            assert target not in FORBIDDEN[wing], f"{path.relative_to(ROOT)} imports {name}"
            if wing == "station":
                assert not name.startswith("groundstation.jobs.fleet"), f"{path} imports {name}"


def test_only_cli_tests_and_benchmarks_import_the_station():
    for path in GS.rglob("*.py"):
        rel = path.relative_to(GS)
        if rel.parts[0] == "station" or rel.name == "cli.py":
            continue
        for name in _imports(path):
            assert _wing(name) != "station", f"{path.relative_to(ROOT)} imports {name}"


def test_estimators_import_no_wing_and_no_simulator():
    for path in (ROOT / "estimators").glob("*.py"):
        for name in _imports(path):
            assert not name.startswith("groundstation"), f"{path.name} imports {name}"
        assert "sim" not in path.stem, f"a simulator in estimators/: {path.name}"


def test_module_and_function_sizes():
    """No module over ~500 lines, no function over ~80 lines in groundstation/."""
    too_big = []
    for path in GS.rglob("*.py"):
        src = path.read_text()
        if src.count("\n") > 500:
            too_big.append(f"{path.relative_to(ROOT)}: {src.count(chr(10))} lines")
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > 80:
                    too_big.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}() {n} lines")
    assert not too_big, "\n".join(too_big)
