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
