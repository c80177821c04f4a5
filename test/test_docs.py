"""The docs, checked (issue 27): generated reference pages and measured-figure blocks equal what
``tools/gen_reference.py`` renders from the code and the committed results files; no page over 3,000 words; every
relative link (and ``#anchor``) resolves; README and the tutorials quote measured figures only inside generated
blocks."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_WORDS = 3000
FIX = "run `python tools/gen_reference.py` and commit the result"


def _gen() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_reference", ROOT / "tools" / "gen_reference.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("gen_reference", mod)
    spec.loader.exec_module(mod)
    return mod


GEN = _gen()
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FIGURE_PAGES = [ROOT / "README.md", *sorted((ROOT / "docs" / "tutorials").glob("*.md"))]


def _rel(p: Path) -> str:
    return str(p.relative_to(ROOT))


@pytest.mark.parametrize("rel", sorted(GEN.PAGES))
def test_reference_page_is_regenerated(rel, tmp_path):
    """Each reference page, rendered from the code now, equals the committed file."""
    out = tmp_path / Path(rel).name
    out.write_text(GEN.PAGES[rel]())
    committed = ROOT / rel
    assert committed.exists(), f"{rel} is missing: {FIX}"
    assert out.read_text() == committed.read_text(), f"{rel} is out of date with the code: {FIX}"


def test_generated_blocks_match_the_results_files():
    """README / docs blocks between the generated markers equal what the results files give."""
    stale = [_rel(p) for p, text in GEN.expected().items()
             if _rel(p) not in GEN.PAGES and p.read_text() != text]
    assert not stale, f"generated blocks out of date in {stale}: {FIX}"


def test_readme_and_tutorials_have_their_blocks():
    """The figures README and the tutorials quote are the generated ones (the blocks are there and filled)."""
    readme = (ROOT / "README.md").read_text()
    for name in ("study-mae", "default-card", "parts", "real-data"):
        m = re.search(rf"<!-- BEGIN generated:{name} -->\n(.+?)<!-- END generated:{name} -->", readme, re.S)
        assert m and m.group(1).strip(), f"README lacks the filled block {name}: {FIX}"


def test_no_page_over_the_word_limit():
    """`wc -w` of every page of README.md and docs/**/*.md is at most 3,000."""
    over = {_rel(p): n for p in PAGES if (n := len(p.read_text().split())) > MAX_WORDS}
    assert not over, f"pages over {MAX_WORDS} words (split them): {over}"


_FENCE = re.compile(r"^```.*?^```", re.S | re.M)
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _prose(text: str) -> str:
    """Text without fenced code blocks and inline code spans."""
    return re.sub(r"`[^`\n]*`", "", _FENCE.sub("", text))


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    s = heading.strip().lower().replace("`", "")
    s = "".join(c for c in s if c.isalnum() or c in " -_")
    return s.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in _FENCE.sub("", path.read_text()).splitlines():
        m = re.match(r"#{1,6}\s+(.*)$", line)
        if m:
            slug = _slug(m.group(1))
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def test_relative_links_resolve():
    """Every relative link of README and docs names an existing file, and its #anchor an existing heading."""
    broken = []
    for page in PAGES:
        for target in _LINK.findall(_prose(page.read_text())):
            if re.match(r"[a-z]+:", target):
                continue  # http(s), mailto
            file, _, anchor = target.partition("#")
            dest = (page.parent / file).resolve() if file else page
            if not dest.exists():
                broken.append(f"{_rel(page)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
                broken.append(f"{_rel(page)}: {target} (no such heading)")
    assert not broken, "\n".join(broken)


# A measured figure: a number with a unit of a measurement (95 % is the confidence level U is stated at).
_FIGURE = re.compile(r"(?<![\w.])(?!95 %)\d[\d,.]*\s?(?:µm|um\b|%|ms\b|MB\b|GB\b|×|GFLOP)")


@pytest.mark.parametrize("page", FIGURE_PAGES, ids=_rel)
def test_figures_only_in_generated_blocks(page):
    """README and the tutorials quote measured figures only through generated blocks (other figures live on the
    pages that hold their commands)."""
    text = GEN.BLOCK_RE.sub("", page.read_text())
    found = _FIGURE.findall(_prose(text))
    assert not found, f"{_rel(page)} quotes figures outside generated blocks: {found}"
