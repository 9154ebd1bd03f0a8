"""Every darp command follows one option convention (docs/DEVELOPING.md, section "CLI").

The test walks the whole command tree (typer's registrations for the Python types, click's command for
the option names as a user types them) and fails on the first kind of breach it finds, listing every
command and option in breach.
"""

from __future__ import annotations

import enum
import re
import types
import typing
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import typer
import typer.main
import typer.utils

from darp.cli import app

# A short form always stands for the same long name, and a long name that has one has it everywhere.
SHORT_FORMS = {"-o": "--out", "-c": "--calibration", "-q": "--quiet", "-f": "--format", "-w": "--waypoints",
               "-n": "--surveys"}  # darp twin generate -n N
# Path-valued options: outputs (written) and inputs (must exist). Any other path option is a breach.
OUTPUT_PATHS = {"--out", "--report", "--save"}  # --save: darp view's recording (no window)
INPUT_PATHS = {"--rig", "--calibration", "--settings", "--plan", "--truth", "--waypoints", "--intrinsics",
               "--trajectory", "--flange-poses", "--envelope", "--extend", "--hand-eye", "--order", "--folds-file",
               "--heldout-list"}
FILE_ONLY = {"--rig", "--calibration", "--plan", "--truth", "--waypoints", "--settings", "--intrinsics",
             "--envelope", "--hand-eye", "--order", "--folds-file", "--heldout-list"}
# Closed sets: these options take a checked choice (an Enum), never a free string.
CHOICE_OPTIONS = {"--profile", "--stream", "--paper", "--dictionary", "--format", "--config", "--model"}
# Words that name a physical quantity: an option containing one ends in its unit.
UNIT_WORDS = {"distance", "elevation", "azimuth", "dwell", "timeout", "tolerance", "gap", "offset", "speed",
              "radius", "height", "angle", "yaw", "pitch", "roll", "length", "size", "duration", "delay", "start",
              "stop", "time", "standoff", "clearance", "margin", "square", "marker", "rate"}
UNIT_SUFFIXES = {"m", "mm", "cm", "deg", "rad", "s", "ms", "hz", "px"}
JOINTS = re.compile(r"^q\d+$")  # a joint vector (--q110-rad)
DIMENSIONLESS = {"--scale"}  # float options without a unit
KEBAB = re.compile(r"^--[a-z][a-z0-9]*(-[a-z0-9]+)*$")


@dataclass(frozen=True)
class Param:
    command: str  # "calib capture"
    name: str  # the Python parameter name
    kind: str  # "option" or "argument"
    opts: tuple[str, ...]  # primary declarations, long and short
    secondary: tuple[str, ...]  # --no-x of a flag pair
    is_flag: bool
    help: str
    annotation: Any  # Python type, Optional and list unwrapped
    is_list: bool
    info: Any  # typer's OptionInfo / ArgumentInfo
    callback: Callable[..., Any]

    @property
    def long(self) -> str:
        return next((o for o in self.opts if o.startswith("--")), self.name)

    def __str__(self) -> str:
        return f"darp {self.command} {self.long if self.kind == 'option' else self.name.upper()}"


def _unwrap(annotation: Any) -> tuple[Any, bool]:
    """(type, is_list) with ``X | None`` and ``list[X]`` unwrapped."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        annotation = args[0] if len(args) == 1 else annotation
    if typing.get_origin(annotation) is list:
        return typing.get_args(annotation)[0], True
    return annotation, False


def _commands(typer_app: typer.Typer, click_group: Any, prefix: str = "") -> Iterator[tuple[str, Any, Any]]:
    """(path, callback, click command) of every command, subcommands included."""
    for info in typer_app.registered_commands:
        name = info.name or info.callback.__name__.replace("_", "-")
        yield f"{prefix}{name}", info.callback, click_group.commands[name]
    for group in typer_app.registered_groups:
        yield from _commands(group.typer_instance, click_group.commands[group.name], f"{prefix}{group.name} ")


def _params() -> list[Param]:
    root = typer.main.get_command(app)
    params = []
    for path, callback, command in _commands(app, root):
        metas = typer.utils.get_params_from_function(callback)
        for p in command.params:
            if p.name == "help":
                continue
            annotation, is_list = _unwrap(metas[p.name].annotation)
            params.append(Param(path, p.name, p.param_type_name, tuple(p.opts), tuple(p.secondary_opts),
                                bool(getattr(p, "is_flag", False)), (p.help or "").strip(), annotation, is_list,
                                metas[p.name].default, callback))
    return params


PARAMS = _params()
OPTIONS = [p for p in PARAMS if p.kind == "option"]
ARGUMENTS = [p for p in PARAMS if p.kind == "argument"]


def _breaches(check: Callable[[Param], str | None], params: list[Param]) -> list[str]:
    return [f"{p}: {why}" for p in params if (why := check(p))]


def test_the_walk_sees_every_command() -> None:
    commands = {p.command for p in PARAMS}
    assert {"collect", "calib capture", "calib check", "hardware check", "twin waypoints", "poses"} <= commands
    assert len(OPTIONS) > 60


def test_every_command_is_registered_once_and_has_help() -> None:
    root = typer.main.get_command(app)
    seen = list(_commands(app, root))
    assert len({path for path, _, _ in seen}) == len(seen)
    assert not [path for path, _, cmd in seen if not (cmd.help or "").strip()]


def test_every_option_and_argument_has_help() -> None:
    assert not _breaches(lambda p: None if p.help else "no help text", PARAMS)


def test_options_are_declared_one_way() -> None:
    """``name: Annotated[type, typer.Option(...)] = default``, never ``name: type = typer.Option(...)``."""
    def check(p: Param) -> str | None:
        hints = typing.get_type_hints(p.callback, include_extras=True)
        if typing.get_origin(hints[p.name]) is not typing.Annotated:
            return "declared without Annotated[..., typer.Option/Argument(...)]"
        return None

    assert not _breaches(check, PARAMS)


def test_option_names_are_kebab_case_and_not_single_letters() -> None:
    def check(p: Param) -> str | None:
        for name in (*p.opts, *p.secondary):
            if name.startswith("--") and not KEBAB.match(name):
                return f"{name} is not --kebab-case (at least two letters)"
            if not name.startswith("--") and name not in SHORT_FORMS:
                return f"short form {name} is not one of {sorted(SHORT_FORMS)}"
        return None

    assert not _breaches(check, OPTIONS)


def test_a_short_form_means_one_long_name_everywhere() -> None:
    def check(p: Param) -> str | None:
        for short, long in SHORT_FORMS.items():
            if short in p.opts and p.long != long:
                return f"{short} must mean {long}"
            if p.long == long and short not in p.opts:
                return f"{long} must also answer to {short}"
        return None

    assert not _breaches(check, OPTIONS)


def test_one_name_per_concept() -> None:
    """No option is the plural of another (--streams beside --stream); counts of captures are --captures."""
    names = {p.long for p in OPTIONS}
    plural = [f"{p}: {p.long}s also exists" for p in OPTIONS if p.long + "s" in names]
    assert not plural
    assert not _breaches(lambda p: "a count of captures is --captures" if p.long in ("--n", "--count") else None,
                         OPTIONS)


def test_json_is_a_print_flag() -> None:
    def check(p: Param) -> str | None:
        if p.long == "--json" and not (p.is_flag and p.annotation is bool):
            return "--json prints JSON to stdout (a flag); write a JSON file with --out"
        return None

    assert not _breaches(check, OPTIONS)


def test_boolean_options_are_flags() -> None:
    assert not _breaches(lambda p: "a boolean option must be a flag" if p.annotation is bool and not p.is_flag
                         else None, OPTIONS)


def test_paths_are_out_or_checked_inputs() -> None:
    def check(p: Param) -> str | None:
        if p.annotation is not Path:
            return "--out is a path" if p.long in OUTPUT_PATHS | INPUT_PATHS else None
        if p.long in OUTPUT_PATHS:
            return None
        if p.long not in INPUT_PATHS:
            return f"a path option is {sorted(OUTPUT_PATHS)} (written) or one of {sorted(INPUT_PATHS)} (read)"
        if not p.info.exists:
            return "an input path is checked: typer.Option(..., exists=True)"
        if p.long in FILE_ONLY and p.info.dir_okay:
            return "names a file: typer.Option(..., dir_okay=False)"
        return None

    assert not _breaches(check, OPTIONS)


def test_positional_arguments_are_existing_inputs_never_the_rig_or_calibration() -> None:
    def check(p: Param) -> str | None:
        if "rig" in p.name or "calibration" in p.name:
            return "the rig file is --rig and a calibration is --calibration, never positional"
        if p.annotation is Path and not p.info.exists:
            return "a positional path is an input: exists=True (outputs are --out)"
        return None

    assert not _breaches(check, ARGUMENTS)


def test_closed_sets_are_choices() -> None:
    def check(p: Param) -> str | None:
        is_enum = isinstance(p.annotation, type) and issubclass(p.annotation, enum.Enum)
        return "a closed set is an Enum (typer.Option shows and checks the choices)" if (
            p.long in CHOICE_OPTIONS and not is_enum) else None

    assert not _breaches(check, OPTIONS)


def test_quantities_carry_their_unit() -> None:
    def check(p: Param) -> str | None:
        words = p.long.removeprefix("--").split("-")
        has_unit = words[-1] in UNIT_SUFFIXES and len(words) > 1
        if has_unit:
            return None
        if any(w in UNIT_WORDS or JOINTS.match(w) for w in words):
            return f"names a quantity: end it in its unit ({', '.join(sorted(UNIT_SUFFIXES))})"
        if p.annotation is float and p.long not in DIMENSIONLESS:
            return "a float option ends in its unit (or is listed dimensionless)"
        return None

    assert not _breaches(check, OPTIONS)


def test_the_rig_is_always_the_same_option() -> None:
    rigs = [p for p in OPTIONS if p.long == "--rig"]
    assert len(rigs) >= 8
    helps = {p.help for p in rigs}
    assert len(helps) == 1, helps


def test_twin_or_hardware_is_two_flags_with_the_rig_apart() -> None:
    for command in ("collect", "calib capture"):
        opts = {p.long: p for p in OPTIONS if p.command == command}
        assert opts["--twin"].is_flag and opts["--hardware"].is_flag and "--rig" in opts, command


@pytest.mark.parametrize("option, library", [
    ("--profile", "darp.twin.settings:PROFILES"),
    ("--paper", "darp.calibration.board:PAPER_CHOICES"),
    ("--dictionary", "darp.calibration.board:ARUCO_DICTIONARIES"),
    ("--config", "darp.kinematics.z1:NAMED_CONFIGS"),
    ("--model", "darp.calibration.kinematic_ident:MODELS"),
])
def test_choices_mirror_the_library(option: str, library: str) -> None:
    """The CLI's Enums are written out (so that `darp --help` imports nothing heavy); they must not drift."""
    import importlib

    module, name = library.split(":")
    if name == "PAPER_CHOICES":
        from darp.calibration.board import PAPER_SIZES_MM

        expected = {"auto", *PAPER_SIZES_MM}
    elif name == "NAMED_CONFIGS":
        expected = {"park", *importlib.import_module(module).NAMED_CONFIGS}
    else:
        expected = set(getattr(importlib.import_module(module), name))
    for p in (p for p in OPTIONS if p.long == option):
        assert {m.value for m in p.annotation} == expected, str(p)


def test_twin_objects_mirror_the_library() -> None:
    from darp.twin.objects.model import OBJECT_NAMES

    demo = next(p for p in OPTIONS if p.command == "demo" and p.long == "--object")
    assert {m.value for m in demo.annotation} == set(OBJECT_NAMES)
