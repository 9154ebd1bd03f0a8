"""benchmarks/ and studies/ as laid out: no generated image in git, no import of the command line's internals,
and studies/README.md an index of every study whose links lead somewhere."""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from helpers.script_modules import BENCHMARKS, ROOT, STUDIES

SCRIPTS = sorted([*BENCHMARKS.glob("*.py"), *STUDIES.glob("*.py")])


def test_git_tracks_no_image_under_benchmarks_or_studies() -> None:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    tracked = subprocess.run(["git", "ls-files", "--", "benchmarks", "studies"], cwd=ROOT, capture_output=True,
                             text=True, check=True).stdout.split()
    assert tracked, "git lists nothing under benchmarks/ and studies/"
    images = [p for p in tracked if p.lower().endswith((".png", ".jpg", ".jpeg", ".svg", ".pdf"))]
    assert not images, f"generated images belong under .bench/ or docs/images/, not in git here: {images}"


def _imports(path: Path) -> list[str]:
    names = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.append(node.module)
        elif isinstance(node, ast.Import):
            names += [a.name for a in node.names]
    return names


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_no_benchmark_or_study_uses_the_command_lines_internals(path: Path) -> None:
    """The library is their API; a script that wants the command line runs ``python -m darp`` as a child."""
    bad = [name for name in _imports(path) if name == "darp.cli" or name.startswith("darp.cli.")]
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}"
    assert "darp.cli" not in path.read_text(encoding="utf-8")  # nor reaches it through a child's -c code


def test_the_checker_sees_an_import_of_the_cli(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from darp.cli._app import run\n")
    assert _imports(bad) == ["darp.cli._app"]


def _slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading."""
    text = heading.lstrip("#").strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def test_the_studies_index_names_every_study_and_its_links_resolve() -> None:
    index = (STUDIES / "README.md").read_text(encoding="utf-8")
    listed = set(re.findall(r"^\| \[(\w+\.py)\]\(\1\) \|", index, flags=re.M))
    assert listed == {p.name for p in STUDIES.glob("*.py")}
    for target in re.findall(r"\]\(([^)]+)\)", index):
        file, _, anchor = target.partition("#")
        path = (STUDIES / file).resolve()
        assert path.exists(), f"studies/README.md links to {target}: no such file"
        if anchor:
            headings = [line for line in path.read_text(encoding="utf-8").splitlines() if line.startswith("#")]
            assert anchor in {_slug(h) for h in headings}, f"studies/README.md links to {target}: no such heading"
    for path in STUDIES.glob("*.py"):  # each row says which doc it feeds
        row = next(line for line in index.splitlines() if line.startswith(f"| [{path.name}]"))
        assert "../docs/" in row, f"studies/README.md: {path.name} names no doc"
