"""Load a ``benchmarks/`` or ``studies/`` script as a module, so tests can call its pure functions."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS = ROOT / "benchmarks"
STUDIES = ROOT / "studies"


def _load(folder: Path, prefix: str, name: str) -> ModuleType:
    """``<folder>/<name>.py`` as module ``<prefix>_<name>`` (its folder on ``sys.path`` for its own imports)."""
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    spec = importlib.util.spec_from_file_location(f"{prefix}_{name}", folder / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` as module ``bench_<name>``."""
    return _load(BENCHMARKS, "bench", name)


def load_study(name: str) -> ModuleType:
    """``studies/<name>.py`` as module ``study_<name>``."""
    return _load(STUDIES, "study", name)
