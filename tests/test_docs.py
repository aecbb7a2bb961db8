"""The docs describe this repository: no path outside it, links that resolve, a layout table
that matches the tree, a README short enough to read."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", ROOT / "schemas" / "README.md", *(ROOT / "docs").glob("*.md")])
# paths that exist only on a developer's machine or beside the repository
OUTSIDE = re.compile(r"(\.\./shared|/work/|\bshared/(recordings|peer|docs|seeds)\b|/tmp/)")
LINK = re.compile(r"\]\(([^)#\s]+)(#[^)]*)?\)")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_path_outside_the_repository(doc):
    bad = [
        f"{doc.name}:{k}: {line.strip()[:80]}"
        for k, line in enumerate(doc.read_text().splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve_inside_the_repository(doc):
    for m in LINK.finditer(doc.read_text()):
        target = m.group(1)
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        path = (doc.parent / target).resolve()
        assert path.is_relative_to(ROOT), f"{doc.name}: {target} leaves the repository"
        assert path.exists(), f"{doc.name}: {target} does not exist"


def _layout_rows() -> list[str]:
    text = (ROOT / "docs" / "architecture.md").read_text()
    table = text[text.index("## Layout") :]
    return re.findall(r"^\| `([^`]+)`", table, flags=re.M)


def test_architecture_layout_matches_the_tree():
    rows = _layout_rows()
    assert len(rows) == len(set(rows)), (
        f"listed twice: {sorted({r for r in rows if rows.count(r) > 1})}"
    )
    for row in rows:
        assert (ROOT / row).exists(), f"docs/architecture.md lists {row}, which does not exist"
    packages = sorted(
        f"pipeline/{p.name}/" for p in (ROOT / "pipeline").iterdir() if (p / "__init__.py").exists()
    )
    missing = [p for p in packages if p not in rows]
    assert not missing, f"docs/architecture.md does not list {missing}"


def test_readme_is_at_most_150_lines():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150
