"""The READMEs and the documentation work in a plain clone: every relative Markdown link
resolves to a file of the repository (and an anchor to a heading of the page it names),
and nothing points into ``../shared`` (which a clone does not have) as a link."""

from __future__ import annotations

import re

import pytest

from conftest import REPO_ROOT

DOCS = ["README.md", "benchmarks/README.md", "CHANGELOG.md", "examples/README.md",
        *sorted(str(p.relative_to(REPO_ROOT)) for p in (REPO_ROOT / "docs").rglob("*.md"))]
# [text](target) and [text](target "title"); images too
LINK = re.compile(r"!?\[[^\]]*\]\(\s*([^)\s]+)(?:\s+\"[^\"]*\")?\s*\)")


def _relative_links(text: str) -> list[str]:
    targets = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
            continue  # absolute URL, mailto:, in-page anchor
        targets.append(target.split("#", 1)[0])
    return targets


def test_link_pattern_finds_relative_links():
    text = 'see [a](docs/a.md#part), [`b`](b.json), ![fig](img/x.png "t"), [web](https://x.org) and [top](#top)'
    assert _relative_links(text) == ["docs/a.md", "b.json", "img/x.png"]


@pytest.mark.parametrize("doc", DOCS)
def test_relative_links_resolve_in_the_repository(doc):
    path = REPO_ROOT / doc
    text = path.read_text(encoding="utf-8")
    for target in _relative_links(text):
        resolved = (path.parent / target).resolve()
        assert resolved.is_relative_to(REPO_ROOT), f"{doc}: link {target} leaves the repository"
        assert resolved.exists(), f"{doc}: link {target} does not resolve"


@pytest.mark.parametrize("doc", DOCS)
def test_no_reference_to_the_spec_outside_the_repository(doc):
    assert "../shared/spec" not in (REPO_ROOT / doc).read_text(encoding="utf-8")


def _anchors(text: str) -> set[str]:
    """The heading ids MkDocs (toc) gives a page: lower case, punctuation dropped, spaces -> -."""
    out = set()
    for heading in re.findall(r"^#{1,6}\s+(.*?)\s*$", text, re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.replace("`", "")).strip().lower()
        out.add(re.sub(r"[\s]+", "-", slug))
    return out


@pytest.mark.parametrize("doc", DOCS)
def test_anchors_name_headings(doc):
    path = REPO_ROOT / doc
    for target in LINK.findall(path.read_text(encoding="utf-8")):
        if "#" not in target or re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):
            continue
        file_part, anchor = target.split("#", 1)
        page = (path.parent / file_part).resolve() if file_part else path
        if page.suffix == ".md" and page.exists():
            assert anchor in _anchors(page.read_text(encoding="utf-8")), f"{doc}: no heading for #{anchor} in {page.name}"


def test_every_docs_page_is_in_the_nav():
    import yaml

    nav = yaml.safe_load((REPO_ROOT / "mkdocs.yml").read_text(encoding="utf-8"))["nav"]

    def pages(items):
        for item in items:
            for value in item.values():
                yield from (pages(value) if isinstance(value, list) else [value])

    listed = set(pages(nav))
    on_disk = {str(p.relative_to(REPO_ROOT / "docs")) for p in (REPO_ROOT / "docs").rglob("*.md")}
    assert on_disk == listed
