"""Every shell and Python example of README.md and docs/ runs, and so do the scripts of
examples/ — what a reader copies is what the commands do today.

Fenced blocks, by info string (docs/index.md explains them to readers):

* ``bash`` — each line is run in a temporary folder, one per page, blocks in page order
  (``vislam ...`` lines in this process through :func:`vislam.cli.main`, others by bash);
* ``bash shared`` — the same when the shared data is there (``../shared`` of the page's
  folder points at it), skipped without it;
* ``bash slow`` / ``bash shared slow`` — too long for the tests: each ``vislam`` line is
  parsed by vislam's argument parser (so a renamed or misspelt flag fails) and the block
  by ``bash -n``;
* ``bash setup`` — the installation commands (CI runs them): the README must hold the
  test command CI depends on;
* ``python`` / ``python shared`` — executed in the page's folder;
* ``yaml`` whose first line is ``# NAME.yaml`` — written there, and loaded as vislam
  loads an options file or a sweep spec.

On README.md, the SLAM row of sparse 0027 in the results table is compared with the
``bash shared`` run of the same command.
"""

from __future__ import annotations

import os
import re
import runpy
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO_ROOT, SHARED_DATA

PAGES = ["README.md", *sorted(str(p.relative_to(REPO_ROOT)) for p in (REPO_ROOT / "docs").rglob("*.md"))]
EXAMPLES = sorted((REPO_ROOT / "examples").glob("*.py"))
FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", re.M | re.S)
CI_TEST_COMMAND = 'python3 -m venv .venv && . .venv/bin/activate && pip install -e ".[test]" && python -m pytest -q -n auto --dist loadfile'
KNOWN_TAGS = {"bash", "python", "yaml", "text", "shared", "slow", "setup", "toml", "console"}


def fenced_blocks(path: Path) -> list[tuple[list[str], str]]:
    """[(info tokens, code)] of the fenced blocks of a Markdown file, in order."""
    return [(info.split(), code) for info, code in FENCE.findall(path.read_text(encoding="utf-8"))]


def command_lines(code: str) -> list[list[str]]:
    """The commands of a shell block (comments and blank lines dropped), split like bash."""
    out = []
    for line in code.splitlines():
        argv = shlex.split(line, comments=True)
        if argv:
            out.append(argv)
    return out


def _have_shared() -> bool:
    return (SHARED_DATA / "sparse" / "0027.npz").is_file()


def _page_folder(tmp_path: Path) -> Path:
    """A working folder whose ``../shared/data`` is the shared data (when it exists)."""
    work = tmp_path / "work"
    work.mkdir()
    if SHARED_DATA.is_dir():
        (tmp_path / "shared").mkdir()
        (tmp_path / "shared" / "data").symlink_to(SHARED_DATA.resolve(), target_is_directory=True)
    return work


def _run_vislam(argv: list[str], where: str) -> None:
    from vislam.cli import main

    try:
        code = main(argv[1:])
    except SystemExit as exc:  # argparse: a bad flag in the docs
        code = exc.code
    assert code == 0, f"{where}: `{shlex.join(argv)}` exited with {code}"


def _parse_only(argv: list[str], where: str) -> None:
    from vislam.cli import build_parser

    try:
        args = build_parser().parse_args(argv[1:])
    except SystemExit as exc:
        pytest.fail(f"{where}: `{shlex.join(argv)}` is not a valid command line (exit {exc.code})")
    assert getattr(args, "func", None), f"{where}: `{shlex.join(argv)}` names no command"


def _write_yaml(code: str, folder: Path, where: str) -> None:
    first = code.splitlines()[0] if code.strip() else ""
    match = re.match(r"#\s*(\S+\.ya?ml)\b", first)
    if not match:
        return
    path = folder / match.group(1)
    path.write_text(code, encoding="utf-8")
    import yaml

    doc = yaml.safe_load(code)
    if isinstance(doc, dict) and "datasets" in doc:  # a sweep spec
        if "shared/data" in code and not _have_shared():
            return
        from vislam.tools.sweep import load_spec

        cwd = os.getcwd()
        os.chdir(folder)
        try:
            load_spec(path)
        finally:
            os.chdir(cwd)
    else:
        from vislam.tools.config import resolve_options

        resolve_options(path)  # raises ConfigError naming the key


def run_page(page: str, folder: Path) -> dict:
    """Run the blocks of ``page`` in ``folder``; returns counts by kind."""
    counts = {"run": 0, "parsed": 0, "skipped": 0}
    for i, (info, code) in enumerate(fenced_blocks(REPO_ROOT / page)):
        where = f"{page} block {i + 1} ({' '.join(info) or 'no info'})"
        if not info:
            continue
        kind, tags = info[0], set(info[1:])
        assert {kind, *tags} <= KNOWN_TAGS, f"{where}: unknown info string {info}"
        if kind == "yaml":
            _write_yaml(code, folder, where)
            continue
        if kind not in ("bash", "python") or "setup" in tags:
            continue
        if "slow" in tags:
            if kind == "bash":
                subprocess.run(["bash", "-n"], input=code, text=True, check=True)
                for argv in command_lines(code):
                    if argv[0] == "vislam":
                        _parse_only(argv, where)
            counts["parsed"] += 1
            continue
        if "shared" in tags and not _have_shared():
            counts["skipped"] += 1
            continue
        if kind == "python":
            exec(compile(code, where, "exec"), {"__name__": "__docs__"})
        else:
            for argv in command_lines(code):
                if argv[0] == "vislam":
                    _run_vislam(argv, where)
                else:
                    subprocess.run(argv, check=True, cwd=folder)
        counts["run"] += 1
    return counts


@pytest.mark.parametrize("page", PAGES)
def test_page_examples_run(page, tmp_path, monkeypatch):
    folder = _page_folder(tmp_path)
    monkeypatch.chdir(folder)
    counts = run_page(page, folder)
    if page == "README.md" and _have_shared():
        _check_results_table(folder / "runs" / "0027-slam" / "summary.json")
    assert sum(counts.values()) or not any(k for k, _ in fenced_blocks(REPO_ROOT / page)), counts


def _check_results_table(summary_path: Path) -> None:
    """The README's sparse 0027 SLAM cells equal what the command beside them prints."""
    import json

    sys.path.insert(0, str(REPO_ROOT / "benchmarks"))
    try:
        from readme_results import parse_table
    finally:
        sys.path.pop(0)
    rows = parse_table((REPO_ROOT / "README.md").read_text(encoding="utf-8"))
    cells = rows["sparse 0027 (clean IMU)"]
    ev = json.loads(summary_path.read_text(encoding="utf-8"))["evaluation"]
    shown_ate = float(cells[1].split()[0])
    shown_t = float(cells[2].split()[0])
    assert abs(shown_ate - ev["cam_ape_rmse_m"]) <= 0.01, (cells, ev["cam_ape_rmse_m"])
    assert abs(shown_t - ev["cam_kitti_t_pct"]) <= 0.01, (cells, ev["cam_kitti_t_pct"])


def test_readme_keeps_the_two_set_up_commands():
    setup = [code.strip() for info, code in fenced_blocks(REPO_ROOT / "README.md") if info[:2] == ["bash", "setup"]]
    assert CI_TEST_COMMAND in setup  # .ci/run depends on it
    test_command = CI_TEST_COMMAND.rsplit(" && ", 1)[1]
    assert test_command in (REPO_ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()  # and runs it
    assert any(c.startswith("python3 -m venv .venv") and "vislam demo" in c for c in setup)


def test_command_lines_split_like_bash():
    code = "vislam run a.npz --out 'my runs'  # a comment\n\n# only a comment\nvislam info a.npz\n"
    assert command_lines(code) == [["vislam", "run", "a.npz", "--out", "my runs"], ["vislam", "info", "a.npz"]]


def test_slow_blocks_are_parsed(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("```bash slow\nvislam run a.npz --out o --velocty-noise 1\n```\n", encoding="utf-8")
    with pytest.raises(pytest.fail.Exception, match="not a valid command line"):
        for info, code in fenced_blocks(page):
            for argv in command_lines(code):
                _parse_only(argv, "p.md")


@pytest.mark.parametrize("script", EXAMPLES, ids=lambda p: p.name)
def test_example_runs(script, tmp_path, monkeypatch, capsys):
    text = script.read_text(encoding="utf-8")
    if "NEEDS_SHARED_DATA = True" in text and not _have_shared():
        pytest.skip(f"{script.name} needs the shared data ({SHARED_DATA})")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("VISLAM_SHARED_DATA", str(SHARED_DATA))
    monkeypatch.setattr(sys, "argv", [str(script)])
    runpy.run_path(str(script), run_name="__main__")
    assert capsys.readouterr().out.strip(), f"{script.name} printed nothing"


def test_results_tables_of_readme_and_docs_agree():
    sys.path.insert(0, str(REPO_ROOT / "benchmarks"))
    try:
        from readme_results import parse_table
    finally:
        sys.path.pop(0)
    readme = parse_table((REPO_ROOT / "README.md").read_text(encoding="utf-8"))
    docs = parse_table((REPO_ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8"))
    assert readme and readme == docs  # one script writes both (benchmarks/readme_results.py --write)
