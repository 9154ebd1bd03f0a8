"""The layer order of docs/architecture.md, checked on every import in src/darp (module-level and lazy)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import darp

SRC = Path(darp.__file__).resolve().parent

# Each layer and the layers it may import (besides itself). Lower layers never import higher ones.
BASE = {"errors", "paper"}
ALLOWED: dict[str, set[str]] = {
    "errors": set(),
    "paper": set(),
    "geometry": BASE,  # the bottom: numpy, scipy and darp.errors
    "formats.realsense": BASE | {"geometry", "formats"},  # formats here: atomic writes and text reading only
    "formats": BASE | {"geometry", "formats.realsense"},
    "kinematics": BASE | {"geometry", "formats", "formats.realsense"},
    "backend": BASE | {"geometry", "formats", "formats.realsense", "kinematics"},
    "calibration": BASE | {"formats", "formats.realsense", "kinematics", "backend", "geometry"},
    "acquisition": BASE | {"formats", "formats.realsense", "kinematics", "backend", "geometry", "calibration"},
    "twin": BASE | {"formats", "formats.realsense", "kinematics", "backend", "geometry", "calibration"},
    "hardware": BASE | {"formats", "formats.realsense", "kinematics", "backend", "geometry", "calibration"},
    "reconstruction": BASE | {"formats", "formats.realsense", "kinematics", "geometry"},
    "evaluation": BASE | {"formats", "formats.realsense", "kinematics", "geometry", "reconstruction"},
    "processing": BASE | {"formats", "formats.realsense", "kinematics", "geometry", "reconstruction", "evaluation"},
    "dataset": BASE | {"formats", "formats.realsense", "kinematics", "geometry", "reconstruction", "evaluation"},
    "export": BASE | {"formats", "formats.realsense", "kinematics", "geometry", "reconstruction", "evaluation",
                      "dataset"},
    "view": BASE | {"formats", "formats.realsense", "kinematics", "geometry", "reconstruction", "evaluation",
                    "dataset"},
    "batch": BASE | {"formats", "formats.realsense", "kinematics", "backend", "geometry", "calibration",
                     "acquisition", "twin", "reconstruction", "evaluation", "processing"},
    "cli": set(),  # the top: anything
    "__main__": {"cli"} | BASE,  # the console entry point: loads the cli
}
REALSENSE_MAY_USE = {"darp.formats.atomic", "darp.formats.text"}


def layer_of(parts: tuple[str, ...]) -> str:
    if parts[0] == "formats" and len(parts) > 1 and parts[1] == "realsense":
        return "formats.realsense"
    return parts[0]


def darp_imports(path: Path) -> list[tuple[int, str]]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module.startswith("darp."):
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.startswith("darp.")]
    return found


def modules() -> list[Path]:
    return sorted(p for p in SRC.rglob("*.py") if p != SRC / "__init__.py")


def test_every_layer_is_known() -> None:
    tops = {layer_of(p.relative_to(SRC).with_suffix("").parts) for p in modules()}
    assert tops <= set(ALLOWED), f"layers missing from docs/architecture.md and this test: {tops - set(ALLOWED)}"


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_imports_follow_the_layer_order(path: Path) -> None:
    layer = layer_of(path.relative_to(SRC).with_suffix("").parts)
    if layer == "cli":
        return
    breaches = []
    for line, name in darp_imports(path):
        target = layer_of(tuple(name.split(".")[1:]) or ("darp",))
        if target == layer:
            continue
        if layer == "formats.realsense" and target == "formats" and name not in REALSENSE_MAY_USE:
            breaches.append(f"line {line}: {name} (recordings use only {sorted(REALSENSE_MAY_USE)})")
        elif target not in ALLOWED[layer]:
            breaches.append(f"line {line}: {name} ({layer} may import {sorted(ALLOWED[layer])})")
    assert not breaches, f"{path.relative_to(SRC)}: " + "; ".join(breaches)


def test_the_checker_sees_a_breach(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from darp.processing.pipeline import SurveyJob\n")
    assert darp_imports(bad) == [(2, "darp.processing.pipeline")]
    assert "processing" not in ALLOWED["reconstruction"]
