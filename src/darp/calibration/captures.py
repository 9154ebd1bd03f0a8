"""The calibration capture folder: one image and one JSON record per capture, plus an index.

Layout (every file written atomically; the index is rewritten after each capture, so an interrupted
run leaves a readable folder of the captures taken so far)::

    captures.json          schema "darp-calib-captures/1": board spec, source, notes, list of captures
    arm110_000.png         the image (8-bit grey or BGR) exactly as the camera gave it
    arm110_000.json        schema "darp-calib-capture/1": the capture's record (below)
    arm110_000_depth.png   optional: the depth image (16-bit PNG, depth frame, units of depth_unit_m)
    ...
    truth/calibration.json optional (twin captures): the true calibration, for evaluation only

A capture record holds what the solver needs and nothing it has to guess::

    id             "arm110_000"
    arm            arm id
    camera_serial  serial of the camera on that arm's wrist
    time_s         host-clock time of the capture
    q_rad          joint angles as the arm reported them (SDK angles, radians, no joint-zero correction)
    q_std_rad      spread of the joint readings averaged into q_rad (optional)
    stream         image stream: "color" or "ir1"
    image          image file name (PNG), relative to the folder
    image_size     [width, height]
    intrinsics     the stream's intrinsics as the camera reports them: fx, fy, ppx, ppy, model, coeffs
    T_depth_stream 4x4 pose of the stream's optical frame in the depth (left IR) optical frame; the
                   hand-eye is calibrated for the depth frame, so colour captures carry the factory
                   depth-to-colour extrinsic (identity for ir1)
    depth_image    optional: the depth image file (16-bit PNG in the depth optical frame as the camera
                   gave it, not aligned to the stream; 0 = no depth), with ``depth_unit_m`` (metres per
                   unit) and ``depth_intrinsics``. Folders without it still solve; the depth correction
                   (``darp.calibration.depth_fit``) needs it.
    extra          optional, free-form; captures taken by darp (``capture_run``) carry
                   ``planned_q_rad``, ``frame_time_s`` and ``move_direction`` (6 x -1 / 0 / +1: the direction
                   each joint last moved in before the capture, which side of its backlash the link sits on;
                   the ``kinematic+compliance+backlash`` model needs it, folders without it solve without
                   the backlash term)
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from darp.errors import CalibrationError, FormatError
from darp.formats.atomic import UNFINISHED_FILE, atomic_path
from darp.formats.calibration import CharucoBoardSpec
from darp.formats.calibration import board_from_dict as parse_board
from darp.formats.io_input import decode_image
from darp.formats.limits import JOINT_ABS_MAX_RAD
from darp.formats.realsense.types import Intrinsics
from darp.formats.schema import (
    as_array,
    as_dict,
    as_float,
    as_int,
    as_rigid_transform,
    as_str,
    load_json_object,
    write_json_checked,
)
from darp.formats.survey import DEFAULT_SERIAL_TO_ARM

INDEX_FILE = "captures.json"
INDEX_SCHEMA = "darp-calib-captures/1"
RECORD_SCHEMA = "darp-calib-capture/1"
STREAMS = ("color", "ir1")
TRUTH_CALIBRATION = Path("truth") / "calibration.json"


@dataclass(frozen=True, eq=False)
class CaptureRecord:
    """One capture: which arm, its joints as logged, and how to read and model its image."""

    capture_id: str
    arm: str
    camera_serial: str
    time_s: float
    q_rad: np.ndarray  # (6,)
    stream: str
    image_file: str
    intrinsics: Intrinsics
    T_depth_stream: np.ndarray
    q_std_rad: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    depth_file: str | None = None  # optional 16-bit depth PNG (depth optical frame)
    depth_unit_m: float | None = None
    depth_intrinsics: Intrinsics | None = None

    @property
    def has_depth(self) -> bool:
        return self.depth_file is not None and self.depth_intrinsics is not None and self.depth_unit_m is not None

    @property
    def image_size(self) -> tuple[int, int]:
        return self.intrinsics.width, self.intrinsics.height


@dataclass
class CaptureSet:
    """A capture folder: board, records, and image access."""

    folder: Path
    board: CharucoBoardSpec
    captures: list[CaptureRecord]
    source: str = ""
    notes: dict[str, Any] = field(default_factory=dict)
    created: str = ""

    @property
    def arms(self) -> tuple[str, ...]:
        """Arm ids in order of first appearance."""
        return tuple(dict.fromkeys(c.arm for c in self.captures))

    def for_arm(self, arm: str) -> list[CaptureRecord]:
        return [c for c in self.captures if c.arm == arm]

    def image_path(self, record: CaptureRecord) -> Path:
        return self.folder / record.image_file

    def load_image(self, record: CaptureRecord) -> np.ndarray:
        """The capture's image as 8-bit grey; its size must match the recorded intrinsics."""
        path = self.image_path(record)
        if not path.is_file():
            raise FormatError(f"capture {record.capture_id}: image file is missing", path)
        image = decode_image(path, cv2.IMREAD_UNCHANGED, "a capture image")  # libpng's lines silenced
        if image is None:
            raise FormatError(f"capture {record.capture_id}: not a readable image", path)
        if image.dtype != np.uint8:
            raise FormatError(f"capture {record.capture_id}: expected an 8-bit image, got {image.dtype}", path)
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        h, w = image.shape[:2]
        if (w, h) != record.image_size:
            raise FormatError(f"capture {record.capture_id}: image is {w}x{h} but its intrinsics say "
                              f"{record.image_size[0]}x{record.image_size[1]}", path)
        return image

    def load_depth(self, record: CaptureRecord) -> np.ndarray:
        """The capture's depth image in metres (float64, 0 = no depth); the record must have one."""
        if not record.has_depth:
            raise FormatError(f"capture {record.capture_id}: has no depth image", self.folder / INDEX_FILE)
        assert record.depth_file is not None and record.depth_intrinsics is not None
        path = self.folder / record.depth_file
        if not path.is_file():
            raise FormatError(f"capture {record.capture_id}: depth image file is missing", path)
        depth = decode_image(path, cv2.IMREAD_UNCHANGED, "a depth image")
        if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
            raise FormatError(f"capture {record.capture_id}: not a 16-bit single-channel depth PNG", path)
        h, w = depth.shape
        if (w, h) != (record.depth_intrinsics.width, record.depth_intrinsics.height):
            raise FormatError(f"capture {record.capture_id}: depth image is {w}x{h} but its depth intrinsics say "
                              f"{record.depth_intrinsics.width}x{record.depth_intrinsics.height}", path)
        return depth.astype(np.float64) * float(record.depth_unit_m or 0.0)

    def truth_calibration_path(self) -> Path | None:
        """``truth/calibration.json`` of twin captures, if present."""
        path = self.folder / TRUTH_CALIBRATION
        return path if path.is_file() else None


# -- (de)serialisation ------------------------------------------------------------------------------

def board_to_dict(board: CharucoBoardSpec) -> dict[str, Any]:
    return {"squares_x": board.squares_x, "squares_y": board.squares_y,
            "square_length_m": board.square_length_m, "marker_length_m": board.marker_length_m,
            "dictionary": board.dictionary}


def board_from_dict(value: Any, path: Path | None) -> CharucoBoardSpec:
    """The file format's board record, plus the checks detection needs (dictionary size, etc.)."""
    from darp.calibration.board import validate_board

    spec = parse_board(value, path)
    try:
        validate_board(spec)
    except CalibrationError as err:
        raise FormatError(f"board: {err.message}", path) from None
    return spec


def intrinsics_to_dict(intr: Intrinsics) -> dict[str, Any]:
    return {"width": intr.width, "height": intr.height, "fx": intr.fx, "fy": intr.fy, "ppx": intr.ppx,
            "ppy": intr.ppy, "model": intr.model, "coeffs": list(intr.coeffs)}


def intrinsics_from_dict(value: Any, where: str, path: Path | None) -> Intrinsics:
    data = as_dict(value, where, path)
    missing = [k for k in ("width", "height", "fx", "fy", "ppx", "ppy") if k not in data]
    if missing:
        raise FormatError(f"{where}: missing {', '.join(missing)}", path)
    coeffs = as_array(data.get("coeffs", [0.0] * 5), f"{where}.coeffs", path, (5,))
    return Intrinsics(
        width=as_int(data["width"], f"{where}.width", path, minimum=1),
        height=as_int(data["height"], f"{where}.height", path, minimum=1),
        fx=as_float(data["fx"], f"{where}.fx", path, positive=True),
        fy=as_float(data["fy"], f"{where}.fy", path, positive=True),
        ppx=as_float(data["ppx"], f"{where}.ppx", path),
        ppy=as_float(data["ppy"], f"{where}.ppy", path),
        model=as_str(data.get("model", "Brown Conrady"), f"{where}.model", path),
        coeffs=tuple(float(c) for c in coeffs),  # type: ignore[arg-type]
    )


def record_to_dict(rec: CaptureRecord) -> dict[str, Any]:
    out: dict[str, Any] = {
        "schema": RECORD_SCHEMA, "id": rec.capture_id, "arm": rec.arm, "camera_serial": rec.camera_serial,
        "time_s": rec.time_s, "q_rad": np.asarray(rec.q_rad, float).tolist(),
    }
    if rec.q_std_rad is not None:
        out["q_std_rad"] = np.asarray(rec.q_std_rad, float).tolist()
    out.update({"stream": rec.stream, "image": rec.image_file, "image_size": list(rec.image_size),
                "intrinsics": intrinsics_to_dict(rec.intrinsics),
                "T_depth_stream": np.asarray(rec.T_depth_stream, float).tolist()})
    if rec.has_depth:
        assert rec.depth_intrinsics is not None
        out.update({"depth_image": rec.depth_file, "depth_unit_m": rec.depth_unit_m,
                    "depth_intrinsics": intrinsics_to_dict(rec.depth_intrinsics)})
    if rec.extra:
        out["extra"] = rec.extra
    return out


def record_from_dict(data: dict[str, Any], path: Path | None) -> CaptureRecord:
    schema = data.get("schema")
    if schema != RECORD_SCHEMA:
        raise FormatError(f"schema: expected {RECORD_SCHEMA!r}, got {schema!r}", path)
    missing = [k for k in ("id", "arm", "camera_serial", "time_s", "q_rad", "stream", "image", "intrinsics",
                           "T_depth_stream") if k not in data]
    if missing:
        raise FormatError(f"missing {', '.join(missing)}", path)
    stream = as_str(data["stream"], "stream", path)
    if stream not in STREAMS:
        raise FormatError(f"stream: must be one of {', '.join(STREAMS)}, got {stream!r}", path)
    image = as_str(data["image"], "image", path)
    if Path(image).is_absolute() or ".." in Path(image).parts:
        raise FormatError(f"image: must be a file name inside the capture folder, got {image!r}", path)
    intr = intrinsics_from_dict(data["intrinsics"], "intrinsics", path)
    if "image_size" in data:
        size = as_array(data["image_size"], "image_size", path, (2,))
        if (int(size[0]), int(size[1])) != (intr.width, intr.height):
            raise FormatError(f"image_size {size.astype(int).tolist()} differs from the intrinsics' "
                              f"{intr.width}x{intr.height}", path)
    std = data.get("q_std_rad")
    arm = as_str(data["arm"], "arm", path)
    on_arm = DEFAULT_SERIAL_TO_ARM.get(str(data["camera_serial"]))
    if not arm.strip() or (on_arm is not None and arm != on_arm):
        raise FormatError(f"arm: {arm!r} does not carry camera {data['camera_serial']} (it is on {on_arm})", path)
    depth_file = depth_unit = depth_intr = None
    if data.get("depth_image") is not None:
        depth_file = as_str(data["depth_image"], "depth_image", path)
        if Path(depth_file).is_absolute() or ".." in Path(depth_file).parts:
            raise FormatError(f"depth_image: must be a file name inside the capture folder, got {depth_file!r}", path)
        if "depth_unit_m" not in data or "depth_intrinsics" not in data:
            raise FormatError("depth_image needs depth_unit_m and depth_intrinsics", path)
        depth_unit = as_float(data["depth_unit_m"], "depth_unit_m", path, positive=True)
        depth_intr = intrinsics_from_dict(data["depth_intrinsics"], "depth_intrinsics", path)
    q = as_array(data["q_rad"], "q_rad", path, (6,))
    if float(np.max(np.abs(q))) > JOINT_ABS_MAX_RAD:
        raise FormatError(f"q_rad: {float(q[np.argmax(np.abs(q))])!r} rad is not a joint angle (beyond "
                          f"+-{JOINT_ABS_MAX_RAD:.4f})", path)
    return CaptureRecord(
        capture_id=as_str(data["id"], "id", path),
        arm=arm,
        camera_serial=str(data["camera_serial"]),
        time_s=as_float(data["time_s"], "time_s", path),
        q_rad=q,
        stream=stream,
        image_file=image,
        intrinsics=intr,
        T_depth_stream=as_rigid_transform(data["T_depth_stream"], "T_depth_stream", path),
        q_std_rad=None if std is None else as_array(std, "q_std_rad", path, (6,)),
        extra=as_dict(data.get("extra", {}), "extra", path),
        depth_file=depth_file, depth_unit_m=depth_unit, depth_intrinsics=depth_intr,
    )


def read_captures(folder: str | Path, *, unfinished_ok: bool = False) -> CaptureSet:
    """Read and validate a capture folder (index and every record; images are read on demand). A folder still
    marked unfinished is refused unless ``unfinished_ok`` (the writer checking what it has just written, before
    its run removes the mark)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FormatError("not a capture folder (no such directory)", folder)
    index_path = folder / INDEX_FILE
    if not unfinished_ok and (folder / UNFINISHED_FILE).is_file():
        raise FormatError(f"unfinished capture folder ({UNFINISHED_FILE}: its capture run did not complete)", folder)
    index = load_json_object(index_path)
    if index.get("schema") != INDEX_SCHEMA:
        raise FormatError(f"schema: expected {INDEX_SCHEMA!r}, got {index.get('schema')!r}", index_path)
    if "board" not in index or "captures" not in index:
        raise FormatError("missing board or captures", index_path)
    board = board_from_dict(index["board"], index_path)
    entries = index["captures"]
    if not isinstance(entries, list):
        raise FormatError("captures: expected a list", index_path)
    records: list[CaptureRecord] = []
    seen: set[str] = set()
    for k, entry in enumerate(entries):
        entry = as_dict(entry, f"captures[{k}]", index_path)
        meta = as_str(entry.get("meta"), f"captures[{k}].meta", index_path)
        if Path(meta).is_absolute() or ".." in Path(meta).parts:
            raise FormatError(f"captures[{k}].meta: must be a file name inside the folder", index_path)
        record = record_from_dict(load_json_object(folder / meta), folder / meta)
        if record.capture_id in seen:
            raise FormatError(f"captures[{k}]: duplicate capture id {record.capture_id!r}", index_path)
        seen.add(record.capture_id)
        records.append(record)
    return CaptureSet(folder=folder, board=board, captures=records,
                      source=str(index.get("source", "")), notes=as_dict(index.get("notes", {}), "notes",
                                                                         index_path),
                      created=str(index.get("created", "")))


def check_capture_output(folder: Path, overwrite: bool) -> None:
    """Refuse an output folder a capture run may not write into: one that holds captures (without ``overwrite``)
    or one that is not empty and holds none (a survey, a user's files: never darp's to replace)."""
    if (folder / INDEX_FILE).exists() and not overwrite:
        raise CalibrationError("already holds captures (captures.json); choose another folder", folder)
    if folder.is_dir() and not (folder / INDEX_FILE).exists() and any(
            p.name != UNFINISHED_FILE for p in folder.iterdir()):
        raise CalibrationError("is not empty and holds no captures (captures.json): choose a new or empty folder",
                               folder)


class CaptureWriter:
    """Writes a capture folder one capture at a time (PNG + JSON, then the index, all atomic)."""

    def __init__(self, folder: str | Path, board: CharucoBoardSpec, *, source: str = "",
                 notes: dict[str, Any] | None = None, overwrite: bool = False) -> None:
        self.folder = Path(folder)
        check_capture_output(self.folder, overwrite)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.board = board
        self.source = source
        self.notes = dict(notes or {})
        self.created = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
        self.records: list[CaptureRecord] = []
        self._counts: dict[str, int] = {}
        self._write_index()

    def add(self, *, arm: str, camera_serial: str, time_s: float, q_rad: np.ndarray, image: np.ndarray,
            intrinsics: Intrinsics, T_depth_stream: np.ndarray, stream: str = "color",
            q_std_rad: np.ndarray | None = None, extra: dict[str, Any] | None = None,
            depth_m: np.ndarray | None = None, depth_intrinsics: Intrinsics | None = None,
            depth_unit_m: float = 0.001) -> CaptureRecord:
        """Write one capture (with its depth image when ``depth_m``, metres, is given); returns its record."""
        if stream not in STREAMS:
            raise CalibrationError(f"stream must be one of {', '.join(STREAMS)}, got {stream!r}")
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise CalibrationError(f"capture image must be 8-bit grey or colour, got {image.dtype} {image.shape}")
        h, w = image.shape[:2]
        if (w, h) != (intrinsics.width, intrinsics.height):
            raise CalibrationError(f"image is {w}x{h} but the intrinsics are for "
                                   f"{intrinsics.width}x{intrinsics.height}")
        n = self._counts.get(arm, 0)
        self._counts[arm] = n + 1
        capture_id = f"{arm}_{n:03d}"
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise CalibrationError(f"cannot encode capture {capture_id} as PNG")
        depth_file = None
        if depth_m is not None:
            if depth_intrinsics is None:
                raise CalibrationError("a capture's depth image needs the depth intrinsics")
            depth = np.asarray(depth_m, dtype=np.float64)
            if depth.shape != (depth_intrinsics.height, depth_intrinsics.width):
                raise CalibrationError(f"depth image is {depth.shape[1]}x{depth.shape[0]} but the depth intrinsics "
                                       f"are for {depth_intrinsics.width}x{depth_intrinsics.height}")
            units = np.rint(np.where(np.isfinite(depth) & (depth > 0), depth, 0.0) / depth_unit_m)
            units = np.where(units > 65535, 0, units).astype(np.uint16)  # beyond the unit's range: no depth
            ok, dpng = cv2.imencode(".png", units)
            if not ok:
                raise CalibrationError(f"cannot encode capture {capture_id}'s depth as PNG")
            depth_file = f"{capture_id}_depth.png"
            with atomic_path(self.folder / depth_file) as tmp:
                tmp.write_bytes(dpng.tobytes())
        with atomic_path(self.folder / f"{capture_id}.png") as tmp:
            tmp.write_bytes(png.tobytes())
        record = CaptureRecord(capture_id=capture_id, arm=arm, camera_serial=str(camera_serial),
                               time_s=float(time_s), q_rad=np.asarray(q_rad, float).copy(), stream=stream,
                               image_file=f"{capture_id}.png", intrinsics=intrinsics,
                               T_depth_stream=np.asarray(T_depth_stream, float).copy(),
                               q_std_rad=None if q_std_rad is None else np.asarray(q_std_rad, float).copy(),
                               extra=dict(extra or {}), depth_file=depth_file,
                               depth_unit_m=None if depth_file is None else float(depth_unit_m),
                               depth_intrinsics=None if depth_file is None else depth_intrinsics)
        write_json_checked(self.folder / f"{capture_id}.json", record_to_dict(record))
        self.records.append(record)
        self._write_index()
        return record

    def _write_index(self) -> None:
        payload = {"schema": INDEX_SCHEMA, "created": self.created, "source": self.source,
                   "board": board_to_dict(self.board), "notes": self.notes,
                   "captures": [{"id": r.capture_id, "arm": r.arm, "meta": f"{r.capture_id}.json"}
                                for r in self.records]}
        write_json_checked(self.folder / INDEX_FILE, payload)

    def close(self) -> CaptureSet:
        """Final index; returns the folder as read back."""
        self._write_index()
        return read_captures(self.folder, unfinished_ok=True)


__all__ = [
    "INDEX_FILE", "STREAMS", "CaptureRecord", "CaptureSet", "CaptureWriter", "board_from_dict", "board_to_dict",
    "check_capture_output",
    "intrinsics_from_dict", "intrinsics_to_dict", "read_captures", "record_from_dict", "record_to_dict",
]
