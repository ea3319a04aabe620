"""Architecture rules that a refactor could silently break (style.md habits 1 and 12)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
    return out


def _files(pkg: str) -> list[Path]:
    files = sorted((ROOT / pkg).rglob("*.py"))
    assert files, f"no sources under {pkg}"
    return files


@pytest.mark.parametrize(
    ("pkg", "other"), [("companion", "sim_bridge"), ("sim_bridge", "companion")]
)
def test_emulator_and_companion_never_import_each_other(pkg: str, other: str) -> None:
    for f in _files(pkg):
        bad = {m for m in _imports(f) if m == other or m.startswith(other + ".")}
        assert not bad, f"{f.relative_to(ROOT)} imports {bad}: they may meet only on the wire"


FORBIDDEN_IN_PURE = ("asyncio", "socket", "time", "pymavlink", "mcap", "cv2", "threading")


@pytest.mark.parametrize("pure", ["companion/core", "sim_bridge/physics"])
def test_pure_cores_do_no_io(pure: str) -> None:
    base = ROOT / pure
    files = sorted(base.rglob("*.py")) if base.is_dir() else [base.with_suffix(".py")]
    files = [f for f in files if f.exists()]
    assert files, f"{pure} is missing"
    for f in files:
        bad = {m for m in _imports(f) if m.split(".")[0] in FORBIDDEN_IN_PURE}
        assert not bad, f"{f.relative_to(ROOT)} imports {bad}: the math must stay pure"


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def test_core_never_imports_the_shell() -> None:
    """The pure core owns its parameter types and error root: nothing in ``companion.core``
    imports the shell (``companion.config``, ``companion`` itself, the link, logs...)."""
    for f in _files("companion/core"):
        bad = {m for m in _imports(f)
               if (m == "companion" or m.startswith("companion.")) and
               not (m == "companion.core" or m.startswith("companion.core."))}
        assert not bad, f"{f.relative_to(ROOT)} imports {bad}: the core must not use the shell"


def test_core_has_no_import_cycle() -> None:
    """Imports inside the core (function-level ones included) form no cycle."""
    files = _files("companion/core")
    names = {_module_name(f) for f in files}
    graph = {_module_name(f): {m for m in _imports(f) if m in names} for f in files}
    state: dict[str, int] = {}  # 1 = on the DFS stack, 2 = done

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = [*path[path.index(nxt):], nxt] if nxt in path else [node, nxt]
                raise AssertionError(f"import cycle in the core: {' -> '.join(cycle)}")
            if nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [n])


def test_boundary_checks_catch_a_violation(tmp_path: Path) -> None:
    """The import scanner itself sees a shell import and a cross import (so the rules above
    cannot pass vacuously)."""
    f = tmp_path / "bad.py"
    f.write_text("def f():\n    from companion.config import load_config\n"
                 "import sim_bridge.camera\n")
    found = _imports(f)
    assert "companion.config" in found and "sim_bridge.camera" in found


def test_repository_stands_alone() -> None:
    """No tracked file points outside the repository (the developers' notes folder is not
    shipped): every reference a user follows must resolve inside the clone."""
    import subprocess

    needle = "shared" + "/"
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    hits = []
    for name in files:
        path = ROOT / name
        if path.suffix in {".png", ".mcap", ".parquet"} or not path.is_file():
            continue
        text = path.read_text(errors="ignore")
        hits += [f"{name}:{i + 1}" for i, line in enumerate(text.splitlines()) if needle in line]
    assert not hits, f"references outside the repository: {hits[:10]}"


def test_nothing_imports_the_commands() -> None:
    """``companion/commands`` are the CLI's thin entry points: a library (the campaign, the
    flight orchestration), a bench or a test reaching up into one would make the CLI a
    dependency; what they share lives in a module below (``companion/flight.py``). The CLI's
    dispatcher (``companion/cli.py``) loads them by name, not by import."""
    files = [*_files("companion"), *_files("bench"), *_files("tests")]
    for f in files:
        if f.is_relative_to(ROOT / "companion" / "commands"):
            continue
        bad = {m for m in _imports(f)
               if m == "companion.commands" or m.startswith("companion.commands.")}
        assert not bad, f"{f.relative_to(ROOT)} imports {bad}: use companion.flight"
