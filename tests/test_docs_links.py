"""The READMEs work in a plain clone: every relative Markdown link resolves to a file of
the repository, and nothing points into ``../shared`` (which a clone does not have) as a link."""

from __future__ import annotations

import re

import pytest

from conftest import REPO_ROOT

DOCS = ["README.md", "benchmarks/README.md", "docs/frontend.md"]
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
