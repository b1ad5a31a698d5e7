"""The pictures README.md and BENCHMARKS.md show are files in the repository.

Result folders get renamed when a grid is republished (results/republish/small became results/small, its
diagnose sheets went to results/small_s26); a link left behind shows a broken image on GitHub and in any
Markdown viewer, and nothing else would notice.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
IMAGE_LINK = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)")


def image_links(text: str) -> list[str]:
    """Relative targets of Markdown image links (web addresses are not ours to check)."""
    return [t for t in IMAGE_LINK.findall(text) if not re.match(r"[a-z]+://", t)]


def test_image_links_are_found_in_markdown():
    text = "a ![x](results/a.png) b ![](docs/b.png) c [not an image](c.png) ![w](https://e.org/d.png)"
    assert image_links(text) == ["results/a.png", "docs/b.png"]


@pytest.mark.parametrize("doc", ["README.md", "BENCHMARKS.md"])
def test_every_picture_a_document_shows_exists(doc):
    links = image_links((ROOT / doc).read_text(encoding="utf-8"))
    missing = [t for t in links if not (ROOT / t).is_file()]
    assert not missing, f"{doc} shows pictures that are not in the repository: {missing}"
