"""``darp recording``: inspect (``info``) and export (``export``) RealSense recordings (.bag, .db3).

``export`` works like librealsense's rs-convert: one image file per frame, named by stream and frame
number, plus ``imu.csv``, ``intrinsics.json`` and ``frames.csv``. Every output file is written
atomically, so an interrupted export never leaves a half-written image behind.
"""

from __future__ import annotations

import contextlib
import csv
import math
import warnings
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from darp.cli._app import app
from darp.cli._options import ExportStream, input_argument, out_option
from darp.errors import DarpWarning, RecordingError

IMU_ABS_MAX = 1.0e4  # m/s^2 or rad/s: beyond any IMU's range (a D435i's: 16 g, 2000 deg/s)

recording_app = typer.Typer(help="Inspect and export RealSense recordings (.bag, .db3).", no_args_is_help=True)
app.add_typer(recording_app, name="recording")

RecordingFile = Annotated[Path, input_argument("A RealSense recording (.bag or .db3).")]


class ExportFormat(StrEnum):
    png = "png"
    npy = "npy"


# -- info ---------------------------------------------------------------------------------------------
def _compression(recording: Any) -> str:
    """The .db3 reader says ``compression`` (png/none); the .bag reader lists its chunks' ``compressions``."""
    compression = getattr(recording, "compression", None)
    if isinstance(compression, str):
        return compression
    return ", ".join(getattr(recording, "compressions", None) or ["unknown"])


def summarize(recording: Any) -> dict[str, Any]:
    """Everything ``darp recording info`` shows, as plain JSON-ready data."""
    is_db3 = type(recording).__name__ == "Db3Recording"
    streams: dict[str, Any] = {}
    first_ns, last_ns = [], []
    for key, profile in recording.streams.items():
        infos = recording.frame_infos(key)
        entry: dict[str, Any] = {
            "stream": profile.rs_name, "sensor": profile.sensor_index, "format": profile.format,
            "width": profile.width, "height": profile.height, "fps": profile.fps, "frames": len(infos),
            "first_timestamp_ms": infos[0].timestamp_ms if infos else None,
            "last_timestamp_ms": infos[-1].timestamp_ms if infos else None,
            "timestamp_domain": infos[0].timestamp_domain if infos else None,
            "measured_rate_hz": None, "intrinsics": None,
        }
        if len(infos) > 1 and infos[-1].timestamp_ms > infos[0].timestamp_ms:
            entry["measured_rate_hz"] = (len(infos) - 1) * 1000.0 / (infos[-1].timestamp_ms - infos[0].timestamp_ms)
        if infos:
            first_ns.append(infos[0].recording_time_ns)
            last_ns.append(infos[-1].recording_time_ns)
        if profile.intrinsics is not None:
            i = profile.intrinsics
            entry["intrinsics"] = {"fx": i.fx, "fy": i.fy, "ppx": i.ppx, "ppy": i.ppy, "model": i.model,
                                   "coeffs": list(i.coeffs)}
        streams[key] = entry
    extrinsics: dict[str, Any] = {}
    if "depth" in recording.streams:
        for key in recording.streams:
            if key == "depth":
                continue
            try:
                T = recording.extrinsics("depth", key)
            except RecordingError:
                continue
            extrinsics[key] = {
                "T_" + key + "_depth": T.tolist(),
                "translation_mm": (T[:3, 3] * 1000.0).tolist(),
                "rotation_deg": math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(T[:3, :3]) - 1.0) / 2.0)))),
            }
    device = recording.device
    return {
        "file": str(recording.path),
        "size_bytes": recording.size_bytes,
        "format": "ROS2 .db3 (sqlite3, CDR)" if is_db3 else "ROS1 bag 2.0",
        "file_version": recording.file_version,
        "compression": _compression(recording),
        "device": {"name": device.name, "serial": device.serial, "firmware": device.firmware,
                   "product_id": device.product_id},
        "depth_scale_m": recording.depth_scale,
        "duration_s": (max(last_ns) - min(first_ns)) / 1e9 if first_ns else 0.0,
        "salvaged": None if recording.salvage is None else recording.salvage.as_dict(),
        "streams": streams,
        "extrinsics_from_depth": extrinsics,
    }


def _table(title: str, columns: list[str], rows: list[list[str]]) -> Any:
    from rich import box
    from rich.table import Table

    table = Table(title=title, box=box.SIMPLE_HEAD, title_justify="left", title_style="bold")
    for n, column in enumerate(columns):
        table.add_column(column, justify="left" if n == 0 or column in ("format", "model", "domain") else "right")
    for row in rows:
        table.add_row(*row)
    return table


def _print_summary(summary: dict[str, Any]) -> None:
    """Readable tables that fit an 80-column terminal."""
    from rich.console import Console

    def num(value: float | None, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    console = Console()
    dev, streams = summary["device"], summary["streams"]
    console.print(f"[bold]{summary['file']}[/bold]")
    console.print(f"  {summary['format']}, file version {summary['file_version']}, "
                  f"compression {summary['compression']}, {summary['size_bytes'] / 1e6:.2f} MB")
    console.print(f"  device {dev['name']}, serial {dev['serial']}, firmware {dev['firmware']}")
    console.print(f"  depth scale {summary['depth_scale_m']:.9g} m/unit, duration {summary['duration_s']:.3f} s")
    if summary["salvaged"] is not None:
        from rich.markup import escape

        salvaged = summary["salvaged"]
        console.print(f"  [bold yellow]salvaged:[/bold yellow] {escape('; '.join(salvaged['missing']))}")
        console.print(f"  {escape(salvaged['recovered'])}")
    console.print(_table("streams", ["stream", "format", "size", "fps", "frames", "rate Hz"], [
        [k, s["format"], f"{s['width']}x{s['height']}" if s["width"] else "-", str(s["fps"]), str(s["frames"]),
         num(s["measured_rate_hz"], ".2f")] for k, s in streams.items()]))
    console.print(_table("timestamps", ["stream", "domain", "first ms", "last ms"], [
        [k, s["timestamp_domain"] or "-", num(s["first_timestamp_ms"], ".3f"), num(s["last_timestamp_ms"], ".3f")]
        for k, s in streams.items()]))
    console.print(_table("intrinsics", ["stream", "fx", "fy", "ppx", "ppy", "model"], [
        [k, *(f"{s['intrinsics'][n]:.3f}" for n in ("fx", "fy", "ppx", "ppy")), s["intrinsics"]["model"]]
        for k, s in streams.items() if s["intrinsics"]]))
    if summary["extrinsics_from_depth"]:
        console.print(_table("extrinsics depth -> stream", ["stream", "tx mm", "ty mm", "tz mm", "rotation deg"], [
            [k, *(f"{v:.3f}" for v in e["translation_mm"]), f"{e['rotation_deg']:.4f}"]
            for k, e in summary["extrinsics_from_depth"].items()]))


@recording_app.command("info")
def info_command(
    file: RecordingFile,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of tables.")] = False,
) -> None:
    """Device, streams (format, size, fps, intrinsics, frames, timestamps, rate), extrinsics, depth scale."""
    import json

    from darp.formats.realsense.recording import open_recording

    with open_recording(file) as recording:
        summary = summarize(recording)
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
    else:
        _print_summary(summary)


# -- export -------------------------------------------------------------------------------------------
def _export_keys(streams: list[ExportStream] | None, recording: Any) -> list[str]:
    """Stream keys to export (default: every stream present); ``imu`` stands for accel and gyro."""
    names = [s.value for s in streams] if streams else [
        k for k in ("depth", "color", "ir1", "ir2", "accel", "gyro") if k in recording.streams]
    keys: list[str] = []
    for name in names:
        wanted = [k for k in ("accel", "gyro") if k in recording.streams] if name == "imu" else [name]
        if not wanted:
            raise RecordingError("no IMU streams (accel, gyro) in this recording", recording.path)
        for key in wanted:
            recording.stream(key)  # a clear error when the recording lacks it
            if key not in keys:
                keys.append(key)
    if not keys:
        raise RecordingError("nothing to export: the recording has no streams", recording.path)
    return keys


def _select(recording: Any, keys: list[str], start_ms: float | None, stop_ms: float | None,
            every: int) -> list[tuple[int, str, int]]:
    """(recording time, stream, index) of the frames to export, in recording order. The window is on
    the recording time (one clock for all streams, unlike device timestamps and their domains)."""
    chosen = []
    for key in keys:
        window = [info for info in recording.frame_infos(key)
                  if (start_ms is None or info.recording_time_ns / 1e6 >= start_ms)
                  and (stop_ms is None or info.recording_time_ns / 1e6 < stop_ms)]
        step = every if recording.streams[key].is_image else 1
        chosen += [(info.recording_time_ns, key, info.index) for info in window[::step]]
    return sorted(chosen)


def _encode(frame: Any, fmt: str, stream_format: str) -> bytes:
    """Image bytes for one frame: PNG (true colours on disk) or .npy (the array as stored)."""
    import io

    import cv2

    if fmt == "npy":
        buffer = io.BytesIO()
        np.save(buffer, frame.data)
        return buffer.getvalue()
    image = frame.data
    if stream_format in ("rgb8", "rgba8"):  # OpenCV writes BGR(A) as true colours
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR if image.shape[-1] == 3 else cv2.COLOR_RGBA2BGRA)
    elif image.ndim == 3 and image.shape[-1] == 2:
        raise RecordingError(f"cannot write {stream_format} frames as PNG; use --format npy")
    ok, png = cv2.imencode(".png", image)
    if not ok:
        raise RecordingError(f"PNG encoding failed for a {stream_format} frame")
    return png.tobytes()


def _metadata_json(recording: Any, keys: list[str]) -> dict[str, Any]:
    summary = summarize(recording)
    streams = {}
    for key in keys:
        profile = recording.streams[key]
        entry: dict[str, Any] = {"format": profile.format, "fps": profile.fps}
        if profile.intrinsics is not None:
            entry.update(summary["streams"][key]["intrinsics"], width=profile.width, height=profile.height,
                         K=profile.intrinsics.K.tolist())
        if profile.motion_intrinsics is not None:
            m = profile.motion_intrinsics
            entry["motion_intrinsics"] = {"data_3x4": np.reshape(m.data, (3, 4)).tolist(),
                                          "noise_variances": list(m.noise_variances),
                                          "bias_variances": list(m.bias_variances)}
        streams[key] = entry
    extrinsics = {f"T_{k}_depth": e[f"T_{k}_depth"] for k, e in summary["extrinsics_from_depth"].items()}
    return {"source": summary["file"], "device": summary["device"], "depth_scale_m": summary["depth_scale_m"],
            "streams": streams, "extrinsics": extrinsics,
            "conventions": "T_a_b maps points from frame b to frame a (metres); colour .npy keeps the stored "
                           "channel order (see format); PNGs hold true colours"}


@recording_app.command("export")
def export_command(
    file: RecordingFile,
    out: Annotated[Path, out_option("Output folder.", folder=True)],
    streams: Annotated[list[ExportStream] | None, typer.Option(
        "--stream", help="Stream to export; repeat per stream (imu: accel and gyro; default: every stream "
        "present).", show_default=False)] = None,
    fmt: Annotated[ExportFormat, typer.Option("--format", "-f", help="Image file format.")] = ExportFormat.png,
    start_ms: Annotated[float | None, typer.Option(
        "--start-ms", help="Export frames recorded from this time on (ms since the recording started).",
        show_default=False)] = None,
    stop_ms: Annotated[float | None, typer.Option(
        "--stop-ms", help="Export frames recorded before this time (ms since the recording started).",
        show_default=False)] = None,
    every: Annotated[int, typer.Option("--every", min=1, help="Keep every N-th image frame of each stream.")] = 1,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Write into a non-empty output folder.")] = False,
) -> None:
    """Write one file per frame (depth 16-bit, colour, IR 8-bit), imu.csv, intrinsics.json and frames.csv."""
    if start_ms is not None and stop_ms is not None and start_ms >= stop_ms:
        raise typer.BadParameter(f"--start-ms {start_ms:g} is not before --stop-ms {stop_ms:g}: no frame is between",
                                 param_hint="'--start-ms' / '--stop-ms'")
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from darp.formats.atomic import atomic_open, atomic_path, write_json_atomic
    from darp.formats.io_output import unfinished_folder
    from darp.formats.realsense.recording import open_recording

    with open_recording(file) as recording:
        keys = _export_keys(streams, recording)
        if out.exists() and not out.is_dir():
            raise RecordingError("exists and is not a folder", out)
        if out.is_dir() and any(out.iterdir()) and not overwrite:
            raise RecordingError("output folder is not empty (use --overwrite to write into it)", out)
        chosen = _select(recording, keys, start_ms, stop_ms, every)
        image_keys = [k for k in keys if recording.streams[k].is_image]
        infos = {k: recording.frame_infos(k) for k in keys}
        numbers: dict[str, list[int]] = {k: [] for k in image_keys}
        for _, key, index in chosen:
            if key in numbers:
                numbers[key].append(infos[key][index].frame_number)
        by_index = {k for k, n in numbers.items() if len(set(n)) != len(n)}  # frame counters repeat
        suffix = "." + fmt.value
        counts = dict.fromkeys(keys, 0)
        console = Console(stderr=True)
        damaged: list[str] = []
        with contextlib.ExitStack() as stack:
            stack.enter_context(unfinished_folder(out, "darp recording export"))  # entered first, left last
            frames_csv = csv.writer(stack.enter_context(atomic_open(out / "frames.csv", "w", newline="")))
            frames_csv.writerow(["stream", "index", "frame_number", "timestamp_ms", "timestamp_domain", "file",
                                 "recording_time_ns"])
            imu_csv = None
            if {"accel", "gyro"} & set(keys):
                imu_csv = csv.writer(stack.enter_context(atomic_open(out / "imu.csv", "w", newline="")))
                imu_csv.writerow(["stream", "index", "frame_number", "timestamp_ms", "timestamp_domain",
                                  "x", "y", "z"])
            progress = stack.enter_context(Progress(
                TextColumn("exporting"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                console=console, transient=True, disable=not console.is_terminal))
            task = progress.add_task("export", total=len(chosen))
            for _, key, index in chosen:
                info = infos[key][index]
                if key in ("accel", "gyro"):
                    sample = recording.read_frame(key, index).data
                    assert imu_csv is not None
                    if not all(math.isfinite(float(v)) and abs(float(v)) <= IMU_ABS_MAX for v in sample):
                        damaged.append(f"{key} {index}")  # a corrupt sample: left out, and said so below
                        progress.advance(task)
                        continue
                    imu_csv.writerow([key, index, info.frame_number, repr(info.timestamp_ms), info.timestamp_domain,
                                      *(repr(float(v)) for v in sample)])
                else:
                    name = f"{key}_{index if key in by_index else info.frame_number:06d}{suffix}"
                    payload = _encode(recording.read_frame(key, index), fmt.value, recording.streams[key].format)
                    with atomic_path(out / name) as tmp:
                        tmp.write_bytes(payload)
                    frames_csv.writerow([key, index, info.frame_number, repr(info.timestamp_ms),
                                         info.timestamp_domain, name, info.recording_time_ns])
                counts[key] += 1
                progress.advance(task)
            write_json_atomic(out / "intrinsics.json", _metadata_json(recording, keys))
    if damaged:
        warnings.warn(DarpWarning(f"{len(damaged)} IMU sample(s) with non-finite or impossible values left out of "
                                  f"imu.csv (first: {damaged[0]})", file), stacklevel=1)
    done = ", ".join(f"{n} {k}" for k, n in counts.items())
    typer.echo(f"exported {done} frames from {file} to {out}")
