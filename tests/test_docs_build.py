"""The documentation site builds: ``mkdocs build --strict`` (every page in the nav, every
link and anchor between pages, every ``:::`` API reference resolvable from the
docstrings), into a temporary folder, with every fenced block rendered as code."""

from __future__ import annotations

import os
import subprocess
import sys

from conftest import REPO_ROOT


def test_mkdocs_build_strict(tmp_path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=REPO_ROOT, capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    api = (tmp_path / "site" / "api" / "index.html").read_text(encoding="utf-8")
    assert "pop_final_poses" in api and "FilterOptions" in api  # mkdocstrings rendered the reference
    assert (tmp_path / "site" / "img" / "dense-0027-slam.png").is_file()
    # every fenced block rendered as code: a fence left as text (``` in a paragraph) is a
    # page whose examples run together with its prose (the pages' test tags did that)
    raw = [p.relative_to(tmp_path / "site").as_posix() for p in (tmp_path / "site").rglob("*.html")
           if "<p>```" in p.read_text(encoding="utf-8")]
    assert not raw, raw
