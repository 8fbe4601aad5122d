"""The README, docs/ and the experiment log (experiments/) link to each other, to figures and to
code: a moved or renamed file must not leave a dead link behind (sections move between them as the
project grows)."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "experiments").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_relative_link_and_figure_resolves(page):
    links = [m.group(1) for m in LINK.finditer(page.read_text())]
    dead = [t for t in links if "://" not in t and not (page.parent / t).exists()]
    assert dead == [], f"{page.name} links to missing files: {dead}"


def test_the_link_pattern_sees_links_and_figures():
    text = "see [speed](experiments/log.md) and ![plot](docs/figures/a.png), [web](https://x.org/a)"
    assert [m.group(1) for m in LINK.finditer(text)] == ["experiments/log.md", "docs/figures/a.png", "https://x.org/a"]
