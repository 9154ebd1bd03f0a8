"""Keyframe export and loading: one compressed ``.npz`` per keyframe plus a JSON index.

::

    keyframes/
        keyframes.json              the index (schema darp-keyframes/1): survey, settings, counts per arm,
                                    and one entry per keyframe (file, arm, frame, time, split, view, pose)
        arm110/000123.npz           one keyframe (np.savez_compressed; arrays listed below)
        arm111/000456.npz
        observations/arm110.npz     one raw frame set per arm (unaligned RGB, depth, IR) for figures

Arrays of a keyframe ``.npz`` (zlib level 1; loadable with ``np.load(path)``, no pickle)::

    rgb               (H, W, 3) uint8   colour aligned to the depth image (darp.reconstruction.align), RGB
                                        order; 0 where the colour camera did not see the depth pixel
    depth             (H, W) uint16     raw Z16 depth (metres = depth * depth_scale; 0 = no depth)
    ir_left, ir_right (H, W) uint8      infrared 1 and 2 (the left imager is the depth frame)
    support_mask      (H, W) bool       conservative object support: the pixel's point lies in the
                                        envelope cylinder (+ margin) above the table plane
    intrinsics        (6,) float64      depth stream: width, height, fx, fy, ppx, ppy (pixel centres at integers)
    distortion_model  str               librealsense model name of the depth stream
    distortion_coeffs (5,) float64
    depth_scale       () float64        metres per depth unit
    T_world_cam       (4, 4) float64    world-from-camera pose of the depth (left IR) optical frame
    timestamp_ms      () float64        the depth frame's timestamp as recorded (camera clock)
    t_s               () float64        host time at which the pose was evaluated
    frame_number      () int64          device frame counter
    arm, serial, split  str             split is "fuse" or "heldout"
    view              () int64          the view (dwell) of its arm the keyframe comes from
    streams           (k,) str          which of depth, color, ir1, ir2 the recording had (missing: zeros)

Why ``.npz``: one self-describing file per keyframe that numpy reads without extra dependencies,
lossless for 16-bit depth, zlib-compressed, and written atomically like every darp output.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import DecodeError, FormatError, ReconstructionError
from darp.formats.atomic import atomic_open, write_json_atomic
from darp.formats.io_input import LIMITS, npz_input
from darp.formats.realsense.recording import Recording
from darp.formats.realsense.types import FrameSet, Intrinsics
from darp.formats.text import read_utf8_text
from darp.reconstruction.align import align_colour_to_depth, colour_to_rgb
from darp.reconstruction.backproject import DepthCorrectionModel, PosedDepth, correct_raw_depth, depth_to_metres
from darp.reconstruction.crop import EnvelopeCrop, support_mask
from darp.reconstruction.keyframes import FUSE, HELDOUT, ArmKeyframes

SCHEMA = "darp-keyframes/1"
INDEX_FILE = "keyframes.json"
OBSERVATIONS_DIR = "observations"
NPZ_COMPRESSLEVEL = 1
KEYFRAME_ARRAYS = ("rgb", "depth", "ir_left", "ir_right", "support_mask", "intrinsics", "distortion_model",
                   "distortion_coeffs", "depth_scale", "T_world_cam", "timestamp_ms", "t_s", "frame_number",
                   "arm", "serial", "split", "view", "streams")


@dataclass(frozen=True, eq=False)
class KeyframeMeta:
    """What a keyframe is and where it was taken (see the module docstring), without its pixels."""

    arm: str
    serial: str
    frame_number: int
    timestamp_ms: float
    t_s: float
    split: str
    view: int
    T_world_cam: np.ndarray


@dataclass(frozen=True, eq=False)
class Keyframe(KeyframeMeta):
    """One exported keyframe: images, calibration and pose (see the module docstring)."""

    rgb: np.ndarray
    depth: np.ndarray
    ir_left: np.ndarray
    ir_right: np.ndarray
    support_mask: np.ndarray
    intrinsics: Intrinsics
    depth_scale: float
    streams: tuple[str, ...] = ("depth", "color", "ir1", "ir2")

    @property
    def depth_m(self) -> np.ndarray:
        """Depth in metres (float32; 0 = no depth)."""
        return depth_to_metres(self.depth, self.depth_scale)

    def posed_depth(self, colour: bool = True) -> PosedDepth:
        """The frame as fusion and evaluation take it (frame id = device frame number)."""
        return PosedDepth(self.arm, self.frame_number, self.depth, self.depth_scale, self.intrinsics,
                          self.T_world_cam, self.rgb if colour else None)

    def index_entry(self, file: str) -> KeyframeInfo:
        """Its entry in ``keyframes.json``, for the file ``file`` (relative to the keyframes folder)."""
        meta = {f.name: getattr(self, f.name) for f in fields(KeyframeMeta)}
        return KeyframeInfo(**meta, file=file)


@dataclass(frozen=True, eq=False)
class KeyframeInfo(KeyframeMeta):
    """One index entry: where a keyframe's file is and what it is, without its pixels."""

    file: str  # relative to the keyframes folder

    def to_dict(self) -> dict[str, Any]:
        return {"file": self.file, "arm": self.arm, "serial": self.serial, "frame_number": self.frame_number,
                "timestamp_ms": self.timestamp_ms, "t_s": self.t_s, "split": self.split, "view": self.view,
                "T_world_cam": np.asarray(self.T_world_cam, float).tolist()}


@dataclass
class KeyframeIndex:
    """The contents of ``keyframes.json``."""

    folder: Path
    survey: str
    object_name: str | None
    pose_source: str  # "calibration" or "truth"
    settings: dict[str, Any]
    arms: dict[str, dict[str, Any]]  # per arm: serial, counts of the selection
    keyframes: list[KeyframeInfo] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def select(self, split: str | None = None, arm: str | None = None) -> list[KeyframeInfo]:
        """Entries of one split (``fuse``/``heldout``) and/or one arm, in index order."""
        if split not in (None, FUSE, HELDOUT):
            raise ReconstructionError(f"unknown split {split!r} (splits: {FUSE}, {HELDOUT})")
        return [k for k in self.keyframes if (split is None or k.split == split) and (arm is None or k.arm == arm)]

    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "survey": self.survey, "object": self.object_name,
                "pose_source": self.pose_source, "format": "npz (numpy savez_compressed), one file per keyframe",
                "settings": self.settings, "arms": self.arms, **self.extra,
                "keyframes": [k.to_dict() for k in self.keyframes]}


# -- one keyframe -------------------------------------------------------------------------------------
def write_keyframe(path: str | Path, kf: Keyframe) -> Path:
    """Write one keyframe ``.npz`` atomically (compressed)."""
    path = Path(path)
    i = kf.intrinsics
    arrays: dict[str, np.ndarray | np.generic] = {
        "rgb": np.asarray(kf.rgb, np.uint8), "depth": np.asarray(kf.depth, np.uint16),
        "ir_left": np.asarray(kf.ir_left, np.uint8), "ir_right": np.asarray(kf.ir_right, np.uint8),
        "support_mask": np.asarray(kf.support_mask, bool),
        "intrinsics": np.array([i.width, i.height, i.fx, i.fy, i.ppx, i.ppy], np.float64),
        "distortion_model": np.array(i.model), "distortion_coeffs": np.array(i.coeffs, np.float64),
        "depth_scale": np.float64(kf.depth_scale), "T_world_cam": np.asarray(kf.T_world_cam, np.float64),
        "timestamp_ms": np.float64(kf.timestamp_ms), "t_s": np.float64(kf.t_s),
        "frame_number": np.int64(kf.frame_number), "arm": np.array(kf.arm), "serial": np.array(kf.serial),
        "split": np.array(kf.split), "view": np.int64(kf.view), "streams": np.array(kf.streams, dtype=str),
    }
    h, w = arrays["depth"].shape
    for name in ("rgb", "ir_left", "ir_right", "support_mask"):
        if arrays[name].shape[:2] != (h, w):
            raise ReconstructionError(f"keyframe {kf.arm}/{kf.frame_number}: {name} {arrays[name].shape} is not "
                                      f"the depth image's size {w}x{h}")
    save_npz(path, arrays)
    return path


def save_npz(path: str | Path, arrays: Mapping[str, np.ndarray | np.generic],
             compresslevel: int = NPZ_COMPRESSLEVEL) -> Path:
    """An ``np.savez_compressed``-compatible archive written atomically, at a chosen zlib level.

    Level 1 is about five times faster than numpy's default (6) on depth, colour and speckled IR
    images, for files 5-8 % larger: the export's time goes into compression otherwise.
    """
    with atomic_open(path, "wb") as handle, zipfile.ZipFile(handle, "w", zipfile.ZIP_DEFLATED,
                                                           compresslevel=compresslevel) as archive:
        for name, array in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)
    return Path(path)


SKIPPABLE = {"rgb": np.uint8, "ir_left": np.uint8, "ir_right": np.uint8, "support_mask": np.bool_}
"""Images a reader may leave undecoded (:func:`read_keyframe`'s ``skip``): they come back empty, shape (0,)."""
DEPTH_ONLY = ("rgb", "ir_left", "ir_right", "support_mask")  # what a posed depth without colour does not use
FOR_FUSION = ("ir_left", "ir_right", "support_mask")  # what a coloured posed depth does not use


def read_keyframe(path: str | Path, skip: Iterable[str] = ()) -> Keyframe:
    """Read one keyframe ``.npz``; FormatError names the file and what is missing.

    ``skip``: images of :data:`SKIPPABLE` not to decompress (a ``.npz`` member is decoded only when read):
    they come back as empty arrays (shape ``(0,)``), so a use of one fails rather than sees zeros.
    Fusion reads :data:`FOR_FUSION`-less keyframes, evaluation :data:`DEPTH_ONLY` ones."""
    path = Path(path)
    skipped = set(skip)
    unknown = skipped - set(SKIPPABLE)
    if unknown:
        raise ReconstructionError(f"cannot skip {', '.join(sorted(unknown))} (skippable: {', '.join(SKIPPABLE)})")
    try:
        with npz_input(path, "a keyframe .npz") as data:
            missing = [name for name in KEYFRAME_ARRAYS if name not in data.files]
            if missing:
                raise FormatError(f"not a darp keyframe: missing array(s) {', '.join(missing)}", path)
            a = {name: np.empty(0, SKIPPABLE[name]) if name in skipped else data[name] for name in KEYFRAME_ARRAYS}
    except FileNotFoundError:
        raise FormatError("no such keyframe file", path) from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise FormatError(f"not a readable keyframe .npz: {err}", path) from err
    w, h, fx, fy, ppx, ppy = (float(v) for v in a["intrinsics"])
    coeffs = tuple(float(c) for c in a["distortion_coeffs"])
    if len(coeffs) != 5:
        raise FormatError(f"not a darp keyframe: distortion_coeffs has {len(coeffs)} values, not 5", path)
    k1, k2, k3, k4, k5 = coeffs
    intrinsics = Intrinsics(int(w), int(h), fx, fy, ppx, ppy, str(a["distortion_model"]), (k1, k2, k3, k4, k5))
    return Keyframe(
        arm=str(a["arm"]), serial=str(a["serial"]), frame_number=int(a["frame_number"]),
        timestamp_ms=float(a["timestamp_ms"]), t_s=float(a["t_s"]), split=str(a["split"]), view=int(a["view"]),
        rgb=a["rgb"], depth=a["depth"], ir_left=a["ir_left"], ir_right=a["ir_right"],
        support_mask=a["support_mask"].astype(bool), intrinsics=intrinsics, depth_scale=float(a["depth_scale"]),
        T_world_cam=a["T_world_cam"], streams=tuple(str(s) for s in a["streams"]),
    )


# -- the index ---------------------------------------------------------------------------------------
def write_keyframe_index(index: KeyframeIndex) -> Path:
    """Write ``keyframes.json`` into the index's folder (atomically)."""
    path = index.folder / INDEX_FILE
    write_json_atomic(path, index.to_dict())
    return path


def read_keyframe_index(folder: str | Path) -> KeyframeIndex:
    """Read ``<folder>/keyframes.json`` (``folder`` may also be the file itself)."""
    folder = Path(folder)
    path = folder if folder.exists() and not folder.is_dir() else folder / INDEX_FILE
    if not path.exists():  # a pipe or a device is refused by the reading below, in its own words
        raise FormatError(f"no {INDEX_FILE} here (not a keyframes folder)", folder)
    try:
        payload = json.loads(read_utf8_text(path, "a JSON file", limit=LIMITS["json"]))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise FormatError(f"invalid JSON: {err}", path) from err
    if not isinstance(payload, dict) or payload.get("schema") != SCHEMA:
        found = payload.get("schema") if isinstance(payload, dict) else None
        raise FormatError(f"schema is {found!r}, expected {SCHEMA!r}", path)
    entries = []
    for n, entry in enumerate(payload.get("keyframes", [])):
        try:
            T = np.array(entry["T_world_cam"], np.float64)
            if T.shape != (4, 4) or entry["split"] not in (FUSE, HELDOUT):
                raise DecodeError("bad pose or split")
            entries.append(KeyframeInfo(file=str(entry["file"]), arm=str(entry["arm"]), serial=str(entry["serial"]),
                                        frame_number=int(entry["frame_number"]),
                                        timestamp_ms=float(entry["timestamp_ms"]), t_s=float(entry["t_s"]),
                                        split=entry["split"], view=int(entry["view"]), T_world_cam=T))
        except (KeyError, TypeError, ValueError) as err:
            raise FormatError(f"keyframes[{n}]: {err}", path) from None
    known = {"schema", "survey", "object", "pose_source", "format", "settings", "arms", "keyframes"}
    return KeyframeIndex(
        folder=path.parent, survey=str(payload.get("survey", "")), object_name=payload.get("object"),
        pose_source=str(payload.get("pose_source", "calibration")), settings=dict(payload.get("settings", {})),
        arms=dict(payload.get("arms", {})), keyframes=entries,
        extra={k: v for k, v in payload.items() if k not in known},
    )


def iter_keyframes(folder: str | Path, split: str | None = None, arm: str | None = None,
                   skip: Iterable[str] = ()) -> Iterator[Keyframe]:
    """Keyframes of a folder one at a time (lazy: one keyframe's pixels in memory at once); ``skip``: images
    left undecoded (:func:`read_keyframe`)."""
    index = read_keyframe_index(folder)
    skip = tuple(skip)
    for info in index.select(split, arm):
        yield read_keyframe(index.folder / info.file, skip)


def load_keyframes(folder: str | Path, split: str | None = None, arm: str | None = None) -> list[Keyframe]:
    """Every keyframe of a folder (optionally one split and/or arm), in index order."""
    return list(iter_keyframes(folder, split, arm))


# -- export from a recording ------------------------------------------------------------------------------
def frameset_at(recording: Recording, depth_index: int) -> FrameSet:
    """The frame set (depth, both IR, nearest colour) of depth frame ``depth_index``, decoding only it."""
    info = recording.frame_infos("depth")[depth_index]
    fps = recording.stream("depth").fps or 30
    half_ms = 0.5 * 1000.0 / fps
    for frameset in recording.framesets(start_ms=info.timestamp_ms - half_ms, stop_ms=info.timestamp_ms + half_ms):
        if frameset.depth is not None and frameset.depth.info.index == depth_index:
            return frameset
    raise ReconstructionError(f"depth frame {depth_index} (#{info.frame_number}) not found in its time window",
                              recording.path)


def keyframe_from_frameset(frameset: FrameSet, recording: Recording, *, arm: str, serial: str, t_s: float,
                           split: str, view: int, T_world_cam: np.ndarray, crop: EnvelopeCrop | None,
                           depth_correction: DepthCorrectionModel | None = None) -> Keyframe:
    """Build a keyframe: colour aligned to depth, the support mask, pose and metadata.

    With ``depth_correction`` the stored depth is the corrected one (:func:`correct_raw_depth`, its own
    depth scale), so fusion, held-out evaluation and every export of the keyframe see the same depth.
    """
    assert frameset.depth is not None
    depth = np.asarray(frameset.depth.data, np.uint16)
    depth_scale = float(recording.depth_scale)
    if depth_correction is not None:
        depth, depth_scale = correct_raw_depth(depth, depth_scale, depth_correction)
    h, w = depth.shape
    d_intr = recording.stream("depth").intrinsics
    if d_intr is None:
        raise ReconstructionError("the depth stream has no intrinsics", recording.path)
    streams = ["depth"]
    rgb = np.zeros((h, w, 3), np.uint8)
    if frameset.color is not None:
        profile = recording.stream("color")
        if profile.intrinsics is None:
            raise ReconstructionError("the colour stream has no intrinsics", recording.path)
        colour = colour_to_rgb(frameset.color.data, profile.format)
        rgb = align_colour_to_depth(depth, depth_scale, d_intr, colour, profile.intrinsics,
                                    recording.extrinsics("depth", "color"))
        streams.append("color")
    ir = {}
    for key in ("ir1", "ir2"):
        frame = getattr(frameset, key)
        ir[key] = np.zeros((h, w), np.uint8) if frame is None else np.asarray(frame.data)
        if frame is not None:
            streams.append(key)
            if ir[key].dtype != np.uint8:  # y16 infrared: keep the top 8 bits (the Y8 view)
                ir[key] = (ir[key] >> 8).astype(np.uint8)
    mask = (np.zeros((h, w), bool) if crop is None
            else support_mask(depth, d_intr, T_world_cam, crop, depth_scale=depth_scale))
    return Keyframe(arm=arm, serial=serial, frame_number=frameset.depth.info.frame_number,
                    timestamp_ms=frameset.depth.info.timestamp_ms, t_s=float(t_s), split=split, view=int(view),
                    rgb=rgb, depth=depth, ir_left=ir["ir1"], ir_right=ir["ir2"], support_mask=mask,
                    intrinsics=d_intr, depth_scale=depth_scale,
                    T_world_cam=np.asarray(T_world_cam, np.float64), streams=tuple(streams))


def write_observation(path: str | Path, frameset: FrameSet, recording: Recording, arm: str) -> Path:
    """Save one raw frame set (unaligned RGB, depth, IR left/right) for the observations figure."""
    arrays: dict[str, np.ndarray | np.generic] = {"arm": np.array(arm), "serial": np.array(recording.device.serial),
                                                  "depth_scale": np.float64(recording.depth_scale)}
    if frameset.depth is not None:
        arrays["depth"] = np.asarray(frameset.depth.data, np.uint16)
        arrays["frame_number"] = np.int64(frameset.depth.info.frame_number)
    if frameset.color is not None:
        arrays["rgb"] = colour_to_rgb(frameset.color.data, recording.stream("color").format)
    for key, name in (("ir1", "ir_left"), ("ir2", "ir_right")):
        frame = getattr(frameset, key)
        if frame is not None:
            arrays[name] = np.asarray(frame.data)
    return save_npz(path, arrays)


def export_arm_keyframes(recording: Recording, selection: ArmKeyframes, trajectory: Any, out_dir: str | Path, *,
                         crop: EnvelopeCrop | None,
                         progress: Callable[[int], None] | None = None,
                         depth_correction: DepthCorrectionModel | None = None) -> list[KeyframeInfo]:
    """Export one arm's keyframes (``trajectory`` is its ``CameraTrajectory``); returns their index entries.

    Frames are decoded one keyframe at a time (a time window around each), so memory does not grow
    with the survey's length. One raw frame set, the middle keyframe's, goes to ``observations/``.
    """
    out = Path(out_dir)
    arm, serial = selection.arm, trajectory.serial
    entries: list[KeyframeInfo] = []
    middle = len(selection) // 2
    for k, (index, view, held) in enumerate(zip(selection.indices.tolist(), selection.view_ids.tolist(),
                                                selection.heldout.tolist(), strict=True)):
        frameset = frameset_at(recording, index)
        T = trajectory.poses.T_world_cam[index]
        kf = keyframe_from_frameset(frameset, recording, arm=arm, serial=serial, t_s=trajectory.poses.t_s[index],
                                    split=HELDOUT if held else FUSE, view=view, T_world_cam=T, crop=crop,
                                    depth_correction=depth_correction)
        rel = f"{arm}/{kf.frame_number:06d}.npz"
        write_keyframe(out / rel, kf)
        entries.append(kf.index_entry(rel))
        if k == middle:
            write_observation(out / OBSERVATIONS_DIR / f"{arm}.npz", frameset, recording, arm)
        if progress is not None:
            progress(1)
    return entries


def read_observation(path: str | Path) -> dict[str, np.ndarray]:
    """Arrays of an ``observations/<arm>.npz`` file."""
    path = Path(path)
    try:
        with npz_input(path, "an observation .npz") as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise FormatError(f"not a readable observation .npz: {err}", path) from err


def posed_frames(keyframes: Iterable[Keyframe], colour: bool = True) -> Iterator[PosedDepth]:
    """``PosedDepth`` of each keyframe (lazy)."""
    for kf in keyframes:
        yield kf.posed_depth(colour)


__all__ = [
    "DEPTH_ONLY",
    "FOR_FUSION",
    "SKIPPABLE",
    "INDEX_FILE",
    "KEYFRAME_ARRAYS",
    "OBSERVATIONS_DIR",
    "SCHEMA",
    "Keyframe",
    "KeyframeIndex",
    "KeyframeInfo",
    "KeyframeMeta",
    "export_arm_keyframes",
    "frameset_at",
    "iter_keyframes",
    "keyframe_from_frameset",
    "load_keyframes",
    "posed_frames",
    "read_keyframe",
    "read_keyframe_index",
    "read_observation",
    "save_npz",
    "write_keyframe",
    "write_keyframe_index",
    "write_observation",
]
