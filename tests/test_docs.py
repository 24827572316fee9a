"""The docs are docs: the README is a landing page, every internal link resolves, and every file
of the checkout a page names exists (a page that names a moved module fails here)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.harness.paths import REPO

PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
#: A path of the checkout named in a page: under one of its top-level folders, with a file ending.
NAMED = re.compile(r"(?<![\w./-])((?:afmctl|drivers|profiles|tests|benchmarks|docs)/"
                   r"[\w./*-]*\w(?:\.py|\.md|\.toml|/))")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown page."""
    out = set()
    for line in page.read_text().splitlines():
        if line.startswith("#"):
            text = line.lstrip("#").strip().lower()
            out.add(re.sub(r"[^\w\- ]", "", text).replace(" ", "-"))
    return out


def test_the_readme_is_a_landing_page() -> None:
    assert len((REPO / "README.md").read_text().splitlines()) <= 200


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_link_resolves(page: Path) -> None:
    for target in LINK.findall(page.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), f"{page.name}: link to {target} (no such file)"
        if anchor and dest.suffix == ".md":
            assert anchor in _anchors(dest), f"{page.name}: link to {target} (no such heading)"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_file_a_page_names_exists(page: Path) -> None:
    missing = [name for name in NAMED.findall(page.read_text())
               if not (list(REPO.glob(name.rstrip("/"))) if "*" in name else (REPO / name).exists())]
    assert not missing, f"{page.name} names files that do not exist: {sorted(set(missing))}"
