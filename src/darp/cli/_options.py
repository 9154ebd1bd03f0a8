"""What the darp commands share: checked choices, parsed values and the options every command spells alike.

The convention (docs/DEVELOPING.md, "CLI"; ``tests/test_cli_convention.py`` walks every command):

- options are declared one way: ``name: Annotated[type, typer.Option("--long-name", help=...)] = default``;
- ``-o/--out`` is the output path (file or folder) and nothing else is ``-o``; ``-c/--calibration``,
  ``-q/--quiet``, ``-f/--format`` and ``-w/--waypoints`` are the only other short forms;
- ``--json`` is a flag that prints JSON on stdout instead of the tables; a JSON file is written with ``--out``;
- the rig file is always ``--rig RIG.yaml`` (default: the packaged rig) and a calibration always
  ``-c/--calibration FILE``; both are checked paths, never positional; ``--twin`` / ``--hardware`` are flags;
- every input path is checked (``exists=True``); outputs are ``--out`` (and ``--report``);
- a value with a unit names it: ``--distance-m``, ``--elevation-deg``, ``--dwell-s``, ``--timeout-s``;
- one name per concept (``--captures``, ``--stream``, ``--object``); a list repeats the option;
- a closed set is an Enum below (help lists the choices, anything else exits 2);
- a bad argument raises ``typer.BadParameter``: from a ``parser=`` below for one value, in the command for a
  combination; :func:`darp.cli._app.run` prints it as one ``darp: error:`` line and exits 2.

The Enums are written out so that importing the CLI stays light; the test checks each against the list in
the library it mirrors.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer


class Profile(StrEnum):
    """Error profiles of the twin (darp.twin.settings.PROFILES)."""

    ideal = "ideal"
    realistic = "realistic"
    paper = "paper"


class CalibModel(StrEnum):
    """Arm models of the calibration solve (darp.calibration.kinematic_ident.MODELS)."""

    paper = "paper"
    kinematic = "kinematic"
    kinematic_compliance = "kinematic+compliance"
    kinematic_compliance_backlash = "kinematic+compliance+backlash"


class CaptureStream(StrEnum):
    """The image a calibration capture detects the board in (darp.calibration.capture_run)."""

    color = "color"
    ir1 = "ir1"


class ImageStream(StrEnum):
    """A camera's image streams (darp.formats.realsense.types.IMAGE_STREAMS)."""

    depth = "depth"
    color = "color"
    ir1 = "ir1"
    ir2 = "ir2"


class ExportStream(StrEnum):
    """What ``darp recording export`` writes: image streams, and IMU samples (imu: accel and gyro)."""

    depth = "depth"
    color = "color"
    ir1 = "ir1"
    ir2 = "ir2"
    imu = "imu"
    accel = "accel"
    gyro = "gyro"


class ExportFormat(StrEnum):
    """What ``darp export`` writes (darp.export.FORMATS)."""

    nerfstudio = "nerfstudio"
    colmap = "colmap"
    open3d = "open3d"
    tum = "tum"
    bop = "bop"
    completion = "completion"


class Paper(StrEnum):
    """Page of the printed board: auto (the smallest that fits) or darp.calibration.board.PAPER_SIZES_MM."""

    auto = "auto"
    A4 = "A4"
    A3 = "A3"
    A2 = "A2"
    A1 = "A1"
    A0 = "A0"
    letter = "letter"
    tabloid = "tabloid"


class Dictionary(StrEnum):
    """OpenCV's predefined ArUco dictionaries a board may use (darp.calibration.board.ARUCO_DICTIONARIES)."""

    DICT_4X4_50 = "DICT_4X4_50"
    DICT_4X4_100 = "DICT_4X4_100"
    DICT_4X4_250 = "DICT_4X4_250"
    DICT_4X4_1000 = "DICT_4X4_1000"
    DICT_5X5_50 = "DICT_5X5_50"
    DICT_5X5_100 = "DICT_5X5_100"
    DICT_5X5_250 = "DICT_5X5_250"
    DICT_5X5_1000 = "DICT_5X5_1000"
    DICT_6X6_50 = "DICT_6X6_50"
    DICT_6X6_100 = "DICT_6X6_100"
    DICT_6X6_250 = "DICT_6X6_250"
    DICT_6X6_1000 = "DICT_6X6_1000"
    DICT_7X7_50 = "DICT_7X7_50"
    DICT_7X7_100 = "DICT_7X7_100"
    DICT_7X7_250 = "DICT_7X7_250"
    DICT_7X7_1000 = "DICT_7X7_1000"


class ArmConfig(StrEnum):
    """A configuration for both arms: park, or one of darp.kinematics.z1.NAMED_CONFIGS."""

    park = "park"
    zero = "zero"
    forward = "forward"
    startFlat = "startFlat"
    show_mid = "show_mid"
    stow = "stow"
    pounce = "pounce"


class TwinObject(StrEnum):
    """The twin's built-in objects (darp.twin.objects.model.OBJECT_NAMES)."""

    red_bull = "red_bull"
    dumbbell = "dumbbell"
    controller = "controller"
    cube = "cube"
    ketchup = "ketchup"
    picture_frame = "picture_frame"
    mug = "mug"
    paperweight = "paperweight"
    clock = "clock"
    cup = "cup"


# -- parsed values: a parser raises typer.BadParameter, which click names with the option -------------------
def _numbers(text: str) -> list[str]:
    return [p for p in text.replace(",", " ").split() if p]


@dataclass(frozen=True)
class Placement:
    """An object on the table: x, y in metres, yaw in degrees."""

    x_m: float
    y_m: float
    yaw_deg: float

    def __str__(self) -> str:
        return f"{self.x_m:g},{self.y_m:g},{self.yaw_deg:g}"


def parse_placement(text: str | Placement) -> Placement:
    if isinstance(text, Placement):
        return text
    try:
        x, y, yaw = (float(p) for p in _numbers(text))
    except ValueError:
        raise typer.BadParameter(f"expected x,y,yaw_deg (metres, metres, degrees), got {text!r}") from None
    from darp.formats.limits import ANGLE_ABS_MAX_DEG, POSITION_ABS_MAX_M, out_of_range

    if out_of_range(x, -POSITION_ABS_MAX_M, POSITION_ABS_MAX_M) or out_of_range(y, -POSITION_ABS_MAX_M,
                                                                                 POSITION_ABS_MAX_M) \
            or out_of_range(yaw, -ANGLE_ABS_MAX_DEG, ANGLE_ABS_MAX_DEG):
        raise typer.BadParameter(f"expected finite x,y within +-{POSITION_ABS_MAX_M:g} m and yaw_deg within "
                                 f"+-{ANGLE_ABS_MAX_DEG:g}, got {text!r}")
    return Placement(x, y, yaw)


@dataclass(frozen=True)
class Resolution:
    """Image size in pixels."""

    width: int
    height: int

    def __str__(self) -> str:
        return f"{self.width}x{self.height}"


def parse_resolution(text: str | Resolution) -> Resolution:
    if isinstance(text, Resolution):
        return text
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected WIDTHxHEIGHT, e.g. 640x480, got {text!r}") from None
    from darp.formats.limits import IMAGE_SIDE_MAX_PX

    if not (0 < w <= IMAGE_SIDE_MAX_PX and 0 < h <= IMAGE_SIDE_MAX_PX):
        raise typer.BadParameter(f"expected WIDTHxHEIGHT, each from 1 to {IMAGE_SIDE_MAX_PX} px, got {text!r}")
    return Resolution(w, h)


@dataclass(frozen=True)
class Joints:
    """Six joint angles in radians."""

    rad: tuple[float, ...]

    def __str__(self) -> str:
        return ",".join(f"{v:g}" for v in self.rad)


def parse_joints(text: str | Joints) -> Joints:
    if isinstance(text, Joints):
        return text
    import math

    parts = _numbers(text)
    try:
        q = tuple(float(p) for p in parts)
    except ValueError:
        raise typer.BadParameter(f"expected 6 numbers (radians), got {text!r}") from None
    if len(q) != 6 or not all(math.isfinite(v) for v in q):
        raise typer.BadParameter(f"expected 6 finite numbers (radians), got {len(parts)} in {text!r}")
    return Joints(q)


@dataclass(frozen=True)
class CameraArm:
    """Which arm carries the camera with this serial."""

    serial: str
    arm: str

    def __str__(self) -> str:
        return f"{self.serial}={self.arm}"


def parse_camera_arm(text: str | CameraArm) -> CameraArm:
    if isinstance(text, CameraArm):
        return text
    serial, sep, arm = text.partition("=")
    if not sep or not serial.strip() or not arm.strip():
        raise typer.BadParameter(f"expected SERIAL=ARM (e.g. 348522076490=arm110), got {text!r}")
    return CameraArm(serial.strip(), arm.strip())


# -- the options every command spells alike ---------------------------------------------------------------
RIG_HELP = "Rig YAML file (default: the packaged rig)."


def out_option(help: str, *, show_default: bool = False, folder: bool = False) -> Any:
    """``-o/--out``: the output file or folder. ``folder``: the command writes into this folder, so it may not
    hold an input (checked for every command by :mod:`darp.cli._outputs`)."""
    if folder:
        return typer.Option("--out", "-o", help=help, show_default=show_default, file_okay=False)
    return typer.Option("--out", "-o", help=help, show_default=show_default)


def calibration_option(help: str) -> Any:
    """``-c/--calibration``: a calibration JSON that must exist."""
    return typer.Option("--calibration", "-c", help=help, exists=True, dir_okay=False, show_default=False)


def input_argument(help: str) -> Any:
    """A positional input (file or folder) that must exist."""
    return typer.Argument(help=help, exists=True, show_default=False)


RigFile = Annotated[Path | None, typer.Option("--rig", help=RIG_HELP, exists=True, dir_okay=False,
                                              show_default=False)]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")]
ProfileOption = Annotated[Profile, typer.Option("--profile", help="Twin error profile.")]
SettingsFile = Annotated[Path | None, typer.Option(
    "--settings", help="Twin settings YAML (replaces --profile; its seed is used unless --seed is given).",
    exists=True, dir_okay=False, show_default=False)]


def progress_bar(*columns: Any, quiet: bool = False, **kwargs: Any) -> Any:
    """A rich ``Progress`` on stderr, drawn only when stderr is a terminal and ``--quiet`` is not given: never into
    a log file or a pipe, never on stdout (which carries results)."""
    from rich.console import Console
    from rich.progress import Progress

    console = Console(stderr=True)
    return Progress(*columns, console=console, disable=quiet or not console.is_terminal, **kwargs)


def seed_given(name: str = "seed") -> bool:
    """Whether the running command's ``--seed`` (parameter ``name``) was given on the command line."""
    import click
    from click.core import ParameterSource

    ctx = click.get_current_context(silent=True)
    return ctx is not None and ctx.get_parameter_source(name) == ParameterSource.COMMANDLINE


def twin_settings(profile: Profile, seed: int, settings_file: Path | None) -> Any:
    """The twin settings of a twin command: ``--settings FILE`` (seed replaced only by an explicit ``--seed``)
    or the named ``--profile`` with ``--seed``. A bad file raises a ConfigError naming it."""
    import dataclasses

    from darp.twin.settings import TwinSettings

    if settings_file is None:
        return TwinSettings.from_profile(profile.value, seed=seed)
    settings = TwinSettings.load(settings_file)
    return dataclasses.replace(settings, seed=seed) if seed_given() else settings

__all__ = [
    "RIG_HELP", "ArmConfig", "CameraArm", "CaptureStream", "Dictionary", "ExportStream", "ImageStream", "Joints",
    "Paper", "Placement", "Profile", "ProfileOption", "Quiet", "Resolution", "RigFile", "SettingsFile", "TwinObject",
    "calibration_option", "input_argument", "out_option", "parse_camera_arm", "parse_joints", "parse_placement",
    "parse_resolution", "progress_bar", "seed_given", "twin_settings",
]


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def refuse_output_over_inputs(out: Path, inputs: list[Path], option: str = "--out", *,
                              folder_output: bool = False) -> None:
    """Refuse (exit 2) an output that is one of the inputs or lands inside an input folder; with
    ``folder_output`` (an output folder that may be filled or replaced) also one that holds an input."""
    target = out.expanduser().resolve()
    for source in inputs:
        held = source.expanduser().resolve()
        clash = _inside(target, held) or (folder_output and _inside(held, target))
        if clash:
            what = "is" if target == held else ("is inside" if _inside(target, held) else "holds")
            raise typer.BadParameter(f"{out} {what} the input {source}: refusing to write over an input",
                                     param_hint=f"'{option}'")
