"""Every package states its job and exports its contract; importing a package or the light entry points loads no
heavy library (the lazy exports of darp.lazy)."""

from __future__ import annotations

import ast
import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import darp
from darp.lazy import LazyExports

SRC = Path(darp.__file__).resolve().parent
LAYER_PACKAGES = ["acquisition", "batch", "calibration", "evaluation", "export", "formats", "geometry", "hardware",
                  "kinematics", "reconstruction", "twin", "formats.realsense", "cli"]
HEAVY = ("cv2", "open3d", "mujoco", "matplotlib", "ray", "rerun", "torch")


def packages() -> list[Path]:
    return sorted(SRC.rglob("__init__.py"))


@pytest.mark.parametrize("path", packages(), ids=lambda p: str(p.parent.relative_to(SRC.parent)))
def test_every_package_states_its_job(path: Path) -> None:
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    assert len(doc.split()) >= 12, f"{path.relative_to(SRC.parent)}: the docstring does not say what it is for"


@pytest.mark.parametrize("name", LAYER_PACKAGES)
def test_every_layer_package_exports_its_contract(name: str) -> None:
    package = importlib.import_module(f"darp.{name}")
    exported = list(getattr(package, "__all__", []))
    assert exported, f"darp.{name} has no __all__"
    submodules = {p.stem for p in (SRC / name.replace(".", "/")).glob("*.py")} | {
        p.parent.name for p in (SRC / name.replace(".", "/")).glob("*/__init__.py")}
    for export in exported:
        assert getattr(package, export) is not None
        # a lazy name equal to a submodule's would be replaced by the module once that module is imported
        if isinstance(getattr(package, "_lazy", None), LazyExports):
            assert export not in submodules, f"darp.{name}.{export} is also a submodule"
    assert set(exported) <= set(dir(package))


def test_calibrations_docstring_names_every_public_module() -> None:
    doc = importlib.import_module("darp.calibration").__doc__ or ""
    public = {p.stem for p in (SRC / "calibration").glob("*.py") if not p.stem.startswith("_")}
    missing = sorted(m for m in public if f":mod:`.{m}`" not in doc)
    assert not missing, f"darp.calibration's docstring does not name {missing}"


def test_a_lazy_export_loads_on_first_use_only() -> None:
    module = type(sys)("darp_lazy_probe")
    lazy = LazyExports("darp_lazy_probe", {"json": ("dumps",)})
    sys.modules["darp_lazy_probe"] = module
    try:
        assert "dumps" not in vars(module)
        assert lazy.attribute("dumps") is json.dumps and vars(module)["dumps"] is json.dumps
        assert "dumps" in lazy.names()
        with pytest.raises(AttributeError, match="no attribute 'loads'"):
            lazy.attribute("loads")
    finally:
        del sys.modules["darp_lazy_probe"]


def heavy_after_import(module: str) -> list[str]:
    code = f"import sys, json; import {module}; print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC.parent), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return list(json.loads(out.stdout))


# What each import loaded before the packages exported their contracts (measured with python -X importtime):
# darp.dataset, darp.export and darp.view loaded OpenCV through reconstruction.backproject's depth edges; now cv2
# loads where depth images are filtered or aligned.
LOADED_BEFORE: dict[str, list[str]] = {"darp.dataset": [], "darp.export": [], "darp.view": []}


@pytest.mark.parametrize("module", [*(f"darp.{p}" for p in LAYER_PACKAGES if p != "cli"), *LOADED_BEFORE])
def test_importing_a_package_loads_no_heavy_library(module: str) -> None:
    assert heavy_after_import(module) == LOADED_BEFORE.get(module, [])


def test_the_cli_export_choices_are_the_export_registry() -> None:
    from darp.cli._options import ExportFormat
    from darp.export import FORMATS

    assert sorted(f.value for f in ExportFormat) == sorted(FORMATS)


@pytest.mark.parametrize("package", sorted(p.name for p in SRC.iterdir() if (p / "__init__.py").is_file()))
def test_every_package_docstring_names_each_of_its_modules(package: str) -> None:
    """A newcomer reads a package's docstring to find its modules: each public one is named there."""
    import importlib
    import pkgutil

    doc = importlib.import_module(f"darp.{package}").__doc__ or ""
    modules = [m.name for m in pkgutil.iter_modules([str(SRC / package)]) if not m.name.startswith("_")]
    assert not [m for m in modules if f".{m}" not in doc], f"darp.{package}'s docstring does not name them"
