"""Rooms one idea each (issue 25, CONTRIBUTING.md "Rooms"): module and function sizes, by ast.

- no module in ``companion/`` or ``sim_bridge/`` over ``MODULE_MAX`` lines, except those listed
  with a reason in CONTRIBUTING.md (each at most ``EXCEPTION_MAX``);
- no function over ``FUNCTION_MAX`` lines in the hot path (``HOT_PATH``).

``SPLITTING`` names the rooms still too big while issue 25's split is under way, each with
who is on it; an entry that has come within the rule fails the test (stale), so the list only
shrinks and the rule holds for every new module and function from now on.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
MODULE_MAX = 500
EXCEPTION_MAX = 700
FUNCTION_MAX = 80
PACKAGES = ("companion", "sim_bridge")
HOT_PATH = ("companion/control", "companion/link", "companion/perception", "companion/core")

#: too big today, being split under issue 25 (path or path::function -> who / why)
SPLITTING: dict[str, str] = {
}

_EXCEPTION_LINE = re.compile(r"^- `(?P<path>[^`]+)` \(max (?P<max>\d+) lines\): (?P<why>\S.*)$")


def parse_exceptions(text: str) -> dict[str, int]:
    """The module exceptions of CONTRIBUTING.md's "Rooms" list: path -> its line bound."""
    m = re.search(r"<!-- rooms: exceptions[^>]*-->\n(.*?)<!-- /rooms -->", text, re.S)
    assert m is not None, "CONTRIBUTING.md has no rooms exception list"
    out: dict[str, int] = {}
    for line in m.group(1).splitlines():
        if not line.strip():
            continue
        e = _EXCEPTION_LINE.match(line.strip())
        assert e is not None, f"CONTRIBUTING.md rooms list: cannot read {line!r}"
        out[e["path"]] = int(e["max"])
    return out


def module_lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def long_functions(path: Path, limit: int) -> dict[str, int]:
    """Functions (and methods, nested ones too) of ``path`` longer than ``limit`` lines:
    qualified name -> lines (decorators excluded, docstring included)."""
    found: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    n = (child.end_lineno or child.lineno) - child.lineno + 1
                    if n > limit:
                        found[name] = n
                visit(child, name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(path.read_text(), filename=str(path)), "")
    return found


def _sources(*dirs: str) -> list[Path]:
    return sorted(f for d in dirs for f in (ROOT / d).rglob("*.py"))


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def test_modules_are_small_rooms() -> None:
    exceptions = parse_exceptions((ROOT / "CONTRIBUTING.md").read_text())
    for path, bound in exceptions.items():
        assert bound <= EXCEPTION_MAX, f"{path}: an exception goes to {EXCEPTION_MAX} at most"
        assert (ROOT / path).is_file(), f"CONTRIBUTING.md names {path}, which does not exist"
    too_big = {}
    for f in _sources(*PACKAGES):
        rel, n = _rel(f), module_lines(f)
        bound = exceptions.get(rel, MODULE_MAX)
        if rel in SPLITTING:
            assert n > bound, f"{rel} is {n} lines now: take it off test_rooms.SPLITTING"
        elif n > bound:
            too_big[rel] = n
    assert not too_big, (f"modules over {MODULE_MAX} lines (split them along a seam, or name "
                         f"the exception and its reason in CONTRIBUTING.md): {too_big}")


def test_hot_path_functions_are_short() -> None:
    too_long = {}
    for f in _sources(*HOT_PATH):
        for name, n in long_functions(f, FUNCTION_MAX).items():
            key = f"{_rel(f)}::{name}"
            if key not in SPLITTING:
                too_long[key] = n
    stale = [k for k in SPLITTING if "::" in k
             and k.split("::")[1] not in long_functions(ROOT / k.split("::")[0], FUNCTION_MAX)]
    assert not stale, f"within the rule now: take them off test_rooms.SPLITTING: {stale}"
    assert not too_long, f"hot-path functions over {FUNCTION_MAX} lines: {too_long}"


def test_the_measures_see_a_violation(tmp_path: Path) -> None:
    """The measures themselves (so the rules cannot pass vacuously): a long method nested in
    a class, a long module, an exception line read and a malformed one refused."""
    body = "\n".join(f"        x{i} = {i}" for i in range(85))
    f = tmp_path / "big.py"
    f.write_text(f"class A:\n    def m(self) -> None:\n{body}\n" + "\n" * 500)
    assert long_functions(f, FUNCTION_MAX) == {"A.m": 86}
    assert module_lines(f) > MODULE_MAX
    text = ("<!-- rooms: exceptions -->\n- `companion/x.py` (max 650 lines): one state machine"
            "\n<!-- /rooms -->\n")
    assert parse_exceptions(text) == {"companion/x.py": 650}
    with pytest.raises(AssertionError):
        parse_exceptions("<!-- rooms: exceptions -->\n- companion/x.py 650\n<!-- /rooms -->\n")
