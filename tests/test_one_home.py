"""Concepts with one home: their values appear as code nowhere else in src/darp or benchmarks/.

Prose may quote a figure (a docstring saying what the paper reported); code must import it.
"""

from __future__ import annotations

import ast
import builtins
from pathlib import Path

import pytest

import darp
from darp import paper
from darp.colours import ARM_COLOURS

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


# -- shared geometry and file formats: one definition each --------------------------------------------------------
# name -> the one module (under src/darp) that may define it; None: no module may (an old private copy's name).
HOMES: dict[str, str | None] = {
    **dict.fromkeys(("transform_points", "transform_columns", "skew", "rotvec_to_rotation", "quaternion_to_rotation",
                     "rotation_to_quaternion", "orthonormalize"), "geometry/transforms.py"),
    **dict.fromkeys(("check_rigid", "orthonormalised", "rotation_error"), "geometry/rigid.py"),
    **dict.fromkeys(("normalised_pixels", "backproject_rays", "distort_normalised", "undistort_normalised"),
                    "geometry/pinhole.py"),
    "min_enclosing_circle": "geometry/circle.py",
    **dict.fromkeys(("read_tum", "read_tum_trajectory", "write_tum", "tum_text"), "formats/trajectories.py"),
    **dict.fromkeys(("load_intrinsics", "read_open3d_intrinsic", "open3d_intrinsic_json"), "formats/intrinsics.py"),
    **dict.fromkeys(("transform", "_transform_points", "_to_world", "_skew", "hat", "_rigid", "_as_rigid", "rodrigues",
                     "_distort", "_brown", "format_tum"), None),
}
# Kept on purpose: the twin's camera extrinsics come from this unit-axis Rodrigues; geometry's rotvec_to_rotation
# differs from it in the last bit for most rotations, which would change every twin recording's bytes.
ALLOWED_COPIES = {("twin/camera/spec.py", "_rotvec_to_matrix")}
TOLERANCE_WORDS = ("RIGID", "ORTHONORMAL")  # a module-level constant with these in its name is a rigidity tolerance


def own_definitions(path: Path) -> list[tuple[int, str]]:
    """Functions (not methods) defined anywhere in a module, and module-level rigidity tolerance constants."""
    found: list[tuple[int, str]] = []

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                found.append((child.lineno, child.name))
                visit(child)
            elif not isinstance(child, ast.ClassDef):
                visit(child)

    tree = ast.parse(path.read_text(encoding="utf-8"))
    visit(tree)
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
            node, ast.AnnAssign) else []
        found += [(node.lineno, t.id) for t in targets
                  if isinstance(t, ast.Name) and any(w in t.id for w in TOLERANCE_WORDS)]
    return found


def copies_outside_home(path: Path, where: str) -> list[str]:
    out = []
    for line, name in own_definitions(path):
        if (where, name) in ALLOWED_COPIES:
            continue
        if any(w in name for w in TOLERANCE_WORDS) and name.isupper():
            if where != "geometry/rigid.py":
                out.append(f"line {line}: {name} (the rigidity rule is darp.geometry.rigid's)")
        elif name in HOMES and HOMES[name] != where:
            out.append(f"line {line}: {name} (its home: {HOMES[name] or 'none, a removed copy'})")
    return out


@pytest.mark.parametrize("path", sorted(SRC.rglob("*.py")), ids=lambda p: str(p.relative_to(SRC)))
def test_shared_geometry_and_formats_are_defined_once(path: Path) -> None:
    where = path.relative_to(SRC).as_posix()
    copies = copies_outside_home(path, where)
    assert not copies, f"{where} defines its own copy of a shared concept (import it from its home): {copies}"


def test_every_home_exists() -> None:
    for name, home in HOMES.items():
        if home is not None:
            assert name in {n for _, n in own_definitions(SRC / home)}, f"{name} is not in {home}"


def test_the_checker_finds_a_geometry_copy(tmp_path: Path) -> None:
    copy = tmp_path / "copy.py"
    copy.write_text("import numpy as np\nRIGID_TOLERANCE = 1e-6\n\n\ndef _skew(v):\n    return v\n\n\n"
                    "class Reader:\n    def transform(self, key):\n        return key\n\n\n"
                    "def outer():\n    def transform_points(T, p):\n        return p\n    return transform_points\n")
    assert copies_outside_home(copy, "reconstruction/copy.py") == [
        "line 5: _skew (its home: none, a removed copy)",
        "line 15: transform_points (its home: geometry/transforms.py)",
        "line 2: RIGID_TOLERANCE (the rigidity rule is darp.geometry.rigid's)"]
    assert copies_outside_home(SRC / "geometry" / "transforms.py", "geometry/transforms.py") == []


# -- arm colours and error classes --------------------------------------------------------------------------------
ARM_HEX = {code.lower() for code in ARM_COLOURS.values()}


def colour_copies(path: Path) -> list[str]:
    """String constants in a module's code that spell an arm's colour (its home is darp/colours.py)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return [f"line {node.lineno}: {node.value!r}" for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str)
            and any(code in node.value.lower() for code in ARM_HEX)]


@pytest.mark.parametrize("path", [p for p in CODE if p != SRC / "colours.py"], ids=lambda p: str(p.relative_to(ROOT)))
def test_the_arm_colours_live_only_in_darp_colours(path: Path) -> None:
    copies = colour_copies(path)
    assert not copies, f"{path.relative_to(ROOT)} spells an arm colour (import darp.colours): {copies}"


def bare_errors(path: Path) -> list[str]:
    """``raise ValueError`` (darp raises its own classes) and exception classes deriving from ValueError outside
    darp/errors.py."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Raise) and node.exc is not None:
            exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            if isinstance(exc, ast.Name) and exc.id == "ValueError":
                out.append(f"line {node.lineno}: raise ValueError")
        elif isinstance(node, ast.ClassDef) and any(isinstance(b, ast.Name) and b.id == "ValueError"
                                                    for b in node.bases):
            out.append(f"line {node.lineno}: class {node.name}(ValueError)")
    return out


@pytest.mark.parametrize("path", [p for p in sorted(SRC.rglob("*.py")) if p != SRC / "errors.py"],
                         ids=lambda p: str(p.relative_to(SRC)))
def test_no_bare_value_error_in_src(path: Path) -> None:
    found = bare_errors(path)
    assert not found, f"{path.relative_to(SRC)}: raise a darp.errors class (DecodeError deep in a reader): {found}"


# Internal control flow, caught inside the module that raises it (never reaching a caller).
INTERNAL_EXCEPTIONS = {("acquisition/survey.py", "_Terminated"), ("formats/realsense/rosbag1/records.py", "Incomplete")}
BUILTIN_EXCEPTIONS = {name for name in dir(builtins) if name.endswith(("Error", "Exception"))}


def error_classes_outside_the_hierarchy(path: Path, where: str) -> list[str]:
    """Exception classes deriving from a builtin exception directly: darp's derive from darp.errors."""
    return [f"line {node.lineno}: class {node.name}" for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
            if isinstance(node, ast.ClassDef) and (where, node.name) not in INTERNAL_EXCEPTIONS
            and any(isinstance(b, ast.Name) and b.id in BUILTIN_EXCEPTIONS for b in node.bases)]


@pytest.mark.parametrize("path", [p for p in sorted(SRC.rglob("*.py")) if p != SRC / "errors.py"],
                         ids=lambda p: str(p.relative_to(SRC)))
def test_every_error_class_is_in_the_hierarchy(path: Path) -> None:
    found = error_classes_outside_the_hierarchy(path, path.relative_to(SRC).as_posix())
    assert not found, f"{path.relative_to(SRC)}: derive from a darp.errors class (one per layer): {found}"


def test_the_checkers_find_a_colour_and_a_bare_error(tmp_path: Path) -> None:
    copy = tmp_path / "copy.py"
    copy.write_text('"""#D62728 in prose is a string too"""\nRED = "#D62728"\n\n\n'
                    'class Bad(ValueError):\n    pass\n\n\n'
                    'def f():\n    raise ValueError("x")\n\n\ndef g():\n    raise ValueError\n')
    assert colour_copies(copy) == ["line 1: '#D62728 in prose is a string too'", "line 2: '#D62728'"]
    assert bare_errors(copy) == ["line 5: class Bad(ValueError)", "line 10: raise ValueError",
                                 "line 14: raise ValueError"]
    assert error_classes_outside_the_hierarchy(copy, "x.py") == ["line 5: class Bad"]
