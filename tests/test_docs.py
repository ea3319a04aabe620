"""The docs hold together: every relative link resolves (file and heading), every page opens
with the question it answers, the README stays one page without commit hashes, every key of
``config/*.toml`` is in the config reference, and every ``docs/...`` path the code cites exists."""

from __future__ import annotations

import re
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent

# Pages other branches add at the same time as this test (links to them are written already).
# The integrator empties this list once they are merged.
ALLOWED_MISSING = frozenset({
})

# Where the pages cited by old paths went (a failure names the new path).
MOVED = {
    "docs/architecture.md": "docs/reference/architecture.md",
    "docs/math.md": "docs/reference/math.md",
    "docs/wire.md": "docs/reference/wire.md",
    "docs/limits.md": "docs/reference/limits.md",
    "docs/reliability.md": "docs/reference/reliability.md",
    "docs/px4-offboard.md": "docs/reference/px4-offboard.md",
    "docs/pitfalls.md": "docs/reference/pitfalls.md",
    "docs/perception.md": "docs/reference/perception.md",
    "docs/logging.md": "docs/reference/logging.md",
    "docs/emulator-vehicle.md": "docs/reference/emulator.md",
    "docs/foxglove-and-gcs.md": "docs/guides/foxglove-and-gcs.md",
    "docs/offset-free.md": "docs/reference/estimator.md (design, keys) or "
                           "docs/records/2026-11-offset-free.md (sections 3, 4: measurements)",
    "docs/visibility.md": "docs/reference/visibility.md (sections 1-3) or "
                          "docs/records/2026-11-visibility.md (sections 4-6)",
    "docs/attitude-lag.md": "docs/guides/tune.md or docs/records/2026-11-attitude-lag.md",
    "docs/campaigns/README.md": "docs/reference/campaigns.md or docs/guides/campaigns.md",
    "bench/README.md history": "docs/records/2026-11-bench.md",
}

QUESTION = "> **Answers:**"
LINK = re.compile(r"(?<!!)\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
HASH = re.compile(r"(?<![\w/-])[0-9a-f]{7,40}(?![\w/-])")


def _markdown_files() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", ROOT / "bench" / "README.md"]
    files += sorted((ROOT / "docs").rglob("*.md"))
    return [f for f in files if f.exists()]


def _generated_output(page: Path) -> bool:
    """A campaign's summary.md is written by `companion campaign`, not by hand."""
    rel = page.relative_to(ROOT).as_posix()
    return rel.startswith("docs/campaigns/") and rel.endswith("/summary.md")


def _rel(p: Path) -> str:
    return p.resolve().relative_to(ROOT).as_posix()


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`|\*\*|\*|_(?=\W)|\[|\]\([^)]*\)", "", heading.strip()).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out: set[str] = set()
    for line in FENCE.sub("", page.read_text()).splitlines():
        if m := re.match(r"^#{1,6}\s+(.*)$", line):
            s = _slug(m.group(1))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}-{n}")
    return out


def _links(page: Path) -> Iterator[str]:
    yield from LINK.findall(FENCE.sub("", page.read_text()))


def test_every_relative_link_resolves() -> None:
    broken: list[str] = []
    waiting: set[str] = set()
    for page in _markdown_files():
        for target in _links(page):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                continue
            path_part, _, anchor = target.partition("#")
            dest = (page.parent / path_part).resolve() if path_part else page
            where = f"{_rel(page)}: ({target})"
            if not dest.exists():
                rel = dest.relative_to(ROOT).as_posix() if dest.is_relative_to(ROOT) else str(dest)
                if rel in ALLOWED_MISSING:
                    waiting.add(rel)
                else:
                    broken.append(f"{where} -> {rel} does not exist"
                                  + (f" (moved to {MOVED[rel]})" if rel in MOVED else ""))
                continue
            if anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
                broken.append(f"{where} -> no heading #{anchor} in {_rel(dest)}")
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_every_docs_page_opens_with_its_question() -> None:
    missing = []
    for page in sorted((ROOT / "docs").rglob("*.md")):
        if _generated_output(page):
            continue
        lines = [ln for ln in page.read_text().splitlines() if ln.strip()]
        if len(lines) < 2 or not lines[0].startswith("# ") or not lines[1].startswith(QUESTION):
            missing.append(_rel(page))
    assert not missing, (f"pages without a title followed by '{QUESTION} ...?':\n"
                         + "\n".join(missing))


def test_readme_is_one_page_without_commit_hashes() -> None:
    text = (ROOT / "README.md").read_text()
    n = len(text.splitlines())
    assert n < 250, f"README.md has {n} lines (a page is < 250)"
    hashes = [h for h in HASH.findall(text)
              if re.search(r"[a-f]", h) and re.search(r"[0-9]", h)]
    assert not hashes, f"README.md holds commit hashes: {hashes}"


def _keys(table: dict[str, Any], prefix: str = "") -> Iterator[str]:
    for k, v in table.items():
        name = f"{prefix}.{k}" if prefix else k
        if name == "base":
            continue
        if isinstance(v, dict):
            if prefix == "sim" and k == "scenarios":
                for scenario in v.values():
                    yield from _keys(scenario, "sim.scenarios.NAME")
            else:
                yield from _keys(v, name)
        else:
            yield name


def _documented_keys() -> set[str]:
    keys: set[str] = set()
    table = ""
    for line in (ROOT / "docs" / "reference" / "config.md").read_text().splitlines():
        if m := re.match(r"^## `\[([^\]]+)\]`", line):
            table = m.group(1)
        elif table and (m := re.match(r"^\| `([^`]+)` \|", line)):
            keys.add(f"{table}.{m.group(1)}")
    return keys


@pytest.mark.parametrize("config", sorted((ROOT / "config").glob("*.toml")),
                         ids=lambda p: p.name)
def test_every_config_key_is_in_the_config_reference(config: Path) -> None:
    documented = _documented_keys()
    keys = set(_keys(tomllib.loads(config.read_text())))
    missing = sorted(keys - documented)
    assert not missing, (f"{config.name}: keys missing from docs/reference/config.md (run "
                         f"`python docs/gen_config_reference.py`): {missing}")


def test_docs_paths_cited_by_the_code_exist() -> None:
    cited = re.compile(r"docs/[A-Za-z0-9_./-]*[A-Za-z0-9_-]\.md")
    sources = [ROOT / "pyproject.toml", ROOT / "CONTRIBUTING.md"]
    for folder in ("companion", "sim_bridge", "bench", "tests", "config", ".ci"):
        sources += [p for p in (ROOT / folder).rglob("*")
                    if p.suffix in (".py", ".toml", ".md", ".yaml", "") and p.is_file()]
    missing: list[str] = []
    for src in sources:
        if src == Path(__file__).resolve():
            continue
        for path in set(cited.findall(src.read_text(errors="replace"))):
            if not (ROOT / path).exists() and path not in ALLOWED_MISSING:
                hint = f" (moved to {MOVED[path]})" if path in MOVED else ""
                missing.append(f"{_rel(src)}: {path}{hint}")
    assert not missing, "docs paths cited that do not exist:\n" + "\n".join(sorted(missing))


def test_repository_paths_named_by_the_docs_exist() -> None:
    """Guides, reference pages, the README and CONTRIBUTING name source files (`path.py`); after
    a module moves, this lists the pages to update. Records keep the paths of their day."""
    named = re.compile(r"(?<![\w/.-])((?:companion|sim_bridge|tests|bench|config|foxglove)"
                       r"/[A-Za-z0-9_./-]+\.(?:py|toml|json|yaml))")
    pages = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", ROOT / "bench" / "README.md"]
    pages += sorted((ROOT / "docs" / "guides").glob("*.md"))
    pages += sorted((ROOT / "docs" / "reference").glob("*.md"))
    missing = sorted({f"{_rel(page)}: {path}" for page in pages if page.exists()
                      for path in named.findall(page.read_text()) if not (ROOT / path).exists()})
    assert not missing, "paths named by the docs that do not exist:\n" + "\n".join(missing)
