"""Concepts with one home: their values appear as code nowhere else in src/darp or benchmarks/.

Prose may quote a figure (a docstring saying what the paper reported); code must import it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import darp
from darp import paper

SRC = Path(darp.__file__).resolve().parent
ROOT = SRC.parents[1]
CODE = sorted([*SRC.rglob("*.py"), *(ROOT / "benchmarks").rglob("*.py"), *(ROOT / "studies").rglob("*.py")])
PAPER_VALUES = {float(v) for v in (*paper.HANDEYE_HELDOUT_MM.values(), *paper.HELDOUT.values())}


def numeric_constants(path: Path) -> list[tuple[int, float]]:
    """Every int or float literal in a module's code, with its line (docstrings and other strings skipped)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return [(node.lineno, float(node.value)) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, int | float)
            and not isinstance(node.value, bool)]


@pytest.mark.parametrize("path", [p for p in CODE if p != SRC / "paper.py"], ids=lambda p: str(p.relative_to(ROOT)))
def test_the_papers_figures_live_only_in_darp_paper(path: Path) -> None:
    copies = [f"line {line}: {value:g}" for line, value in numeric_constants(path)
              if value in PAPER_VALUES and value not in {224.0}]  # 224 is also a common image size
    assert not copies, f"{path.relative_to(ROOT)} repeats the paper's figures (import darp.paper): {copies}"


def test_the_checker_finds_a_copy(tmp_path: Path) -> None:
    copy = tmp_path / "copy.py"
    copy.write_text('"""quotes 3.58 in prose"""\nPAPER = {"median_mm": 2.13}\n')
    assert numeric_constants(copy) == [(2, 2.13)]
