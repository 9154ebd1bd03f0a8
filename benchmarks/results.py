"""The peer benchmarks' results: a row per case (darp, its peer, the ratio, the target, the verdict) and the
machine they ran on, written as ONE markdown table and ONE JSON file (atomically) by ``benchmarks/run.py``.

Each benchmark script keeps printing its own detailed report when run alone, and exposes ``rows() ->
list[Row]`` with defaults small enough for a 2-core machine; the runner calls that, never parses output.

- ``ratio`` is always darp / peer in the row's unit (for a time, below 1 is faster; for a rate, above 1).
- ``target`` is the one the script states (the issue's "at least 5x", "at most 2 ms", ...), on the ratio
  or on darp's own value; ``verdict`` is ``met``, ``not met``, ``no target``, ``not measured`` (a target
  whose value is missing: no peer installed, no data) or ``error`` (the benchmark failed).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import math
import os
import platform
from pathlib import Path
from typing import Any, Literal

VERDICTS = ("met", "not met", "no target", "not measured", "error")
# distribution names whose versions the table records (the first installed name of each entry)
LIBRARIES = {"darp": ("darp",), "numpy": ("numpy",), "open3d": ("open3d",),
             "opencv": ("opencv-python-headless", "opencv-python", "opencv-contrib-python",
                        "opencv-contrib-python-headless"),
             "mujoco": ("mujoco",), "pinocchio": ("pin",), "pyrealsense2": ("pyrealsense2",), "libigl": ("libigl",),
             "scipy": ("scipy",)}


@dataclasses.dataclass(frozen=True)
class Target:
    """``<on> <op> <value>``: on the ratio darp/peer, or on darp's own value (in the row's unit)."""

    on: Literal["ratio", "darp"]
    op: Literal[">=", "<="]
    value: float
    source: str = ""  # where the target is stated, e.g. "issue 3"

    def met(self, darp: float | None, ratio: float | None) -> bool | None:
        """Whether the row meets the target; None when the value it is on was not measured."""
        x = ratio if self.on == "ratio" else darp
        if x is None or not math.isfinite(x):
            return None
        return x >= self.value if self.op == ">=" else x <= self.value

    def text(self, unit: str) -> str:
        value = f"{self.value:g}x" if self.on == "ratio" else f"{self.value:g} {unit}".strip()
        return f"{self.on} {self.op} {value}" + (f" ({self.source})" if self.source else "")


@dataclasses.dataclass(frozen=True)
class Row:
    """One case: darp's value and its peer's in ``unit``; ``peer`` None when the case has no peer."""

    benchmark: str
    case: str
    unit: str
    darp: float | None
    peer: float | None = None
    peer_name: str = ""
    target: Target | None = None
    note: str = ""
    error: str = ""

    @property
    def ratio(self) -> float | None:
        if self.darp is None or self.peer is None or self.peer == 0:
            return None
        r = self.darp / self.peer
        return r if math.isfinite(r) else None

    @property
    def verdict(self) -> str:
        if self.error:
            return "error"
        if self.target is None:
            return "no target"
        met = self.target.met(self.darp, self.ratio)
        return "not measured" if met is None else ("met" if met else "not met")

    def record(self) -> dict[str, Any]:
        """The row as JSON: its fields, the ratio, the target's text and the verdict."""
        out = dataclasses.asdict(self)
        out.update(ratio=self.ratio, verdict=self.verdict,
                   target_text=self.target.text(self.unit) if self.target else "")
        return out

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> Row:
        names = {f.name for f in dataclasses.fields(cls)}
        fields = {k: v for k, v in record.items() if k in names}
        if fields.get("target") is not None:
            fields["target"] = Target(**fields["target"])
        return cls(**fields)


def _number(v: float | None) -> float | None:
    """A plain float for JSON (None for a missing or non-finite value)."""
    return None if v is None or not math.isfinite(float(v)) else float(v)


def row(benchmark: str, case: str, unit: str, darp: float | None, peer: float | None = None, peer_name: str = "",
        target: Target | None = None, note: str = "") -> Row:
    """A :class:`Row` with numpy scalars and NaN turned into floats and None."""
    return Row(benchmark, case, unit, _number(darp), _number(peer), peer_name, target, note)


# -- the machine --------------------------------------------------------------------------------------------
def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(names: tuple[str, ...]) -> str:
    for name in names:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return "not installed"


def machine() -> dict[str, Any]:
    """CPU model, cores (all, and usable by this process), Python, the key libraries' versions, load average."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": _cpu_model(), "cores": os.cpu_count(), "usable_cores": usable,
            "python": platform.python_version(), "system": f"{platform.system()} {platform.release()}",
            "libraries": {k: _version(v) for k, v in LIBRARIES.items()},
            "load_average": [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None}


# -- the table ----------------------------------------------------------------------------------------------
def fmt(v: float | None) -> str:
    if v is None:
        return "-"
    if abs(v) >= 1000:
        return f"{v:,.0f}"
    return f"{v:.3g}" if abs(v) < 100 else f"{v:.1f}"


def _cell(text: str) -> str:
    return text.replace("|", "/").replace("\n", " ")


def markdown(rows: list[Row], info: dict[str, Any], runs: dict[str, dict[str, Any]]) -> str:
    """The results table with the machine above it and each benchmark's time below."""
    libs = ", ".join(f"{k} {v}" for k, v in info["libraries"].items())
    load = info.get("load_average")
    lines = ["# darp next to its peers", "",
             f"Machine: {info['cpu']}, {info['cores']} cores ({info['usable_cores']} usable), Python {info['python']}, "
             f"{info['system']}; load average at start {load}.", f"Libraries: {libs}.", "",
             "ratio = darp / peer in the row's unit (a time: below 1 is faster; a rate: above 1 is faster).", "",
             "| benchmark | case | unit | darp | peer | ratio | target | verdict |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        peer = f"{fmt(r.peer)} ({r.peer_name})" if r.peer_name else fmt(r.peer)
        case = r.case + (f" [{r.note}]" if r.note else "") + (f" [{r.error}]" if r.error else "")
        ratio = "-" if r.ratio is None else f"{r.ratio:.2f}x"
        target = r.target.text(r.unit) if r.target else "-"
        lines.append(f"| {r.benchmark} | {_cell(case)} | {r.unit} | {fmt(r.darp)} | {_cell(peer)} | {ratio} | "
                     f"{_cell(target)} | {r.verdict} |")
    counts = {v: sum(r.verdict == v for r in rows) for v in VERDICTS}
    lines += ["", "Verdicts: " + ", ".join(f"{n} {v}" for v, n in counts.items() if n) + ".", ""]
    lines.append("| benchmark | seconds | rows |")
    lines.append("|---|---|---|")
    for name, run in runs.items():
        lines.append(f"| {name} | {run['seconds']:.0f} | {run['rows']} |")
    lines.append(f"| total | {sum(r['seconds'] for r in runs.values()):.0f} | {len(rows)} |")
    return "\n".join(lines) + "\n"


def write(folder: Path, rows: list[Row], info: dict[str, Any], runs: dict[str, dict[str, Any]]) -> tuple[Path, Path]:
    """``results.md`` and ``results.json`` in ``folder``, each written atomically; returns both paths."""
    from darp.formats.atomic import write_json_atomic, write_text_atomic

    folder.mkdir(parents=True, exist_ok=True)
    md, js = folder / "results.md", folder / "results.json"
    write_json_atomic(js, {"machine": info, "benchmarks": runs, "rows": [r.record() for r in rows]})
    write_text_atomic(md, markdown(rows, info, runs))
    return md, js
