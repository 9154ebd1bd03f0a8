"""The guard every command runs through (issue 32): before a command's body runs, every float option is checked to
be finite (NaN passes click's ranges), and each of its outputs
(``-o/--out``, ``--report``, ``--save``) is checked against each of its inputs (every path parameter, plus the
paths a command adds with :func:`add_input`) and locked.

- An output that **is** an input, or lies **inside** an input folder, is refused (exit 2, one line).
- A folder output (declared ``file_okay=False``, e.g. ``out_option(..., folder=True)``) that **holds** an
  input is refused too: the command writes into that folder.
- Each output is locked (:func:`darp.formats.io_output.output_lock`) for the whole command: a second run on
  the same output is refused with one line instead of colliding.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import typer

from darp.cli._options import refuse_output_over_inputs
from darp.formats.io_output import output_lock

OUTPUT_PARAMS = ("out", "report", "save")
_EXTRA_INPUTS: list[Path] = []


def add_input(path: str | Path) -> None:
    """Declare an input the command resolved itself (``--object mesh.ply``): outputs are checked against it
    too. Call it before writing; it raises ``typer.BadParameter`` on a clash with an output already guarded."""
    p = Path(path)
    _EXTRA_INPUTS.append(p)
    for option, out, folder in _current:
        _check(out, folder, [p], option)


_current: list[tuple[str, Path, bool]] = []


def _paths(value: Any) -> Iterable[Path]:
    if isinstance(value, Path):
        yield value
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _paths(v)


def _folder_only(param: Any) -> bool:
    """Whether a path parameter is declared ``file_okay=False`` (typer's parameter info, or click's type)."""
    info = getattr(getattr(param, "type_descriptor", None), "parameter_info", None)
    source = info if info is not None else getattr(param, "type", None)
    return getattr(source, "file_okay", True) is False


def _check(out: Path, folder: bool, inputs: Iterable[Path], option: str) -> None:
    refuse_output_over_inputs(out, [source for source in inputs if source.exists()], option, folder_output=folder)


def _check_finite(param: Any, value: Any) -> None:
    """No option takes NaN or infinity (click's ranges let NaN through: every comparison with it is false)."""
    values = value if isinstance(value, (list, tuple)) else [value]
    for v in values:
        if isinstance(v, float) and not math.isfinite(v):
            option = max(getattr(param, "opts", None) or [param.name], key=len)
            raise typer.BadParameter(f"must be a finite number, got {v!r}", param_hint=f"'{option}'")


def guarded(invoke: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """Wrap a click command's ``invoke``: check its outputs against its inputs and lock them around the call."""

    def run(ctx: Any) -> Any:
        params = {p.name: p for p in ctx.command.params}
        outputs: list[tuple[str, Path, bool]] = []
        inputs: list[Path] = []
        for name, value in ctx.params.items():
            param = params.get(name)
            if param is None or value is None:
                continue
            _check_finite(param, value)
            if name in OUTPUT_PARAMS and isinstance(value, Path):
                option = max(getattr(param, "opts", [f"--{name}"]), key=len)
                outputs.append((option, value, _folder_only(param)))
            elif name not in OUTPUT_PARAMS:
                inputs.extend(_paths(value))  # every path a command is given is an input
        for option, out, folder in outputs:
            _check(out, folder, inputs, option)
        with contextlib.ExitStack() as stack:
            seen: set[Path] = set()
            for _, out, _ in outputs:
                key = out.expanduser().absolute()
                if key not in seen:
                    seen.add(key)
                    stack.enter_context(output_lock(out))
            saved = _current[:], _EXTRA_INPUTS[:]  # a command that runs others (darp demo) nests
            _current[:] = outputs
            _EXTRA_INPUTS.clear()
            try:
                return invoke(ctx)
            finally:
                _current[:], _EXTRA_INPUTS[:] = saved

    return run


def guard_commands(command: Any) -> Any:
    """Wrap every leaf command of the click tree under ``command`` with :func:`guarded`; returns ``command``."""
    children = getattr(command, "commands", None)
    if children:
        for child in children.values():
            guard_commands(child)
    else:
        command.invoke = guarded(command.invoke)
    return command


__all__ = ["OUTPUT_PARAMS", "add_input", "guard_commands", "guarded"]
