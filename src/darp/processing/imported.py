"""RGB-D sequences from any eye-in-hand camera (or any posed RGB-D set): ``darp import``, then fusion, mesh
and held-out evaluation like a DARP survey.

An **imported survey** is a folder in darp's own keyframe format (:mod:`darp.reconstruction.keyframe_io`)::

    OUT/
      keyframes/keyframes.json     index (pose_source "imported"), one arm ("arm" or --arm), every 5th held out
      keyframes/<arm>/<n>.npz      colour (registered to depth), 16-bit depth, depth scale, K, T_world_cam
      import.json                  what was read: files, conventions, checks and their numbers

The frames are already chosen by the user (every one is a keyframe, or every ``--every``-th); the split
is :func:`darp.evaluation.heldout.heldout_mask`'s. ``darp process`` on that folder then runs fusion,
meshing and the held-out point-to-mesh evaluation (:func:`process_imported`); there is one arm, so no
cross-arm section.

Poses come either as world-from-camera trajectories (:mod:`darp.formats.trajectories`) or as
base-from-flange poses with a hand-eye (``T_world_cam = T_world_base @ F @ X`` from a calibration file).
Checks on the data (each a one-line error or warning naming the file and the likely fix): depth not
registered to colour (sizes differ), a depth scale that puts the scene at an impossible distance,
missing or duplicated frames, and camera-from-world given as world-from-camera (consecutive frames'
back-projected points agree much better with the inverted poses: both numbers are given).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from darp import paper
from darp.errors import DarpWarning, FormatError, ReconstructionError
from darp.evaluation.heldout import evaluate_heldout, heldout_mask
from darp.evaluation.point_to_mesh import MeshDistance
from darp.formats.atomic import write_json_atomic
from darp.formats.io_input import decode_image
from darp.formats.realsense.types import Intrinsics
from darp.formats.schema import to_jsonable
from darp.formats.trajectories import frame_key
from darp.kinematics.transforms import invert_transform
from darp.processing.evaluate import EVALUATION_DIR, HELDOUT_DISTANCES, _save_arrays, draw_figures
from darp.processing.imported_surface import DEPTH_ONLY, resolve_method
from darp.processing.job import FIGURES_DIR
from darp.processing.results import RESULTS_FILE, SCHEMA
from darp.reconstruction.backproject import PosedDepth, backproject
from darp.reconstruction.fusion import FusionSettings, VoxelFusion, write_voxel_cloud
from darp.reconstruction.keyframe_io import (
    Keyframe,
    KeyframeIndex,
    iter_keyframes,
    read_keyframe_index,
    write_keyframe,
    write_keyframe_index,
)
from darp.reconstruction.keyframes import FUSE, HELDOUT
from darp.reconstruction.mesh import MeshSettings, ball_pivoting_mesh, mesh_area, write_mesh
from darp.reconstruction.tsdf_surface import SurfaceSettings

IMPORT_FILE = "import.json"
POSE_SOURCE = "imported"
COLOUR_WORDS = ("color", "colour", "rgb", "image")
DEPTH_WORDS = ("depth",)
MIN_DEPTH_M, MAX_DEPTH_M = 0.05, 20.0


class ImportWarning(DarpWarning):
    """Something in the imported data is worth a look (missing frames, ...)."""


@dataclass
class ImportSpec:
    """What to import (see ``darp import --help``)."""

    sequence: Path
    out: Path
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    depth_scale_m: float = 0.001
    poses: dict[str, np.ndarray] = field(default_factory=dict)  # world-from-camera by frame key
    pose_source: str = ""
    arm: str = "arm"
    every: int = 1
    heldout_every: int = 5
    heldout_offset: int = 2  # frame i (in import order) is held out when i % heldout_every == heldout_offset
    heldout_keys: frozenset[str] | None = None  # instead: exactly these frame keys are held out (--heldout-list)
    distortion_model: str = "Brown Conrady"  # librealsense's name of the model of ``dist``
    envelope: Path | None = None  # manip_envelope.json in the world frame of the poses (copied into the survey)
    # a posed folder's own pairing (darp.formats.trajectories.PosedFrames); else find_frames(sequence)
    colour_files: dict[str, Path] | None = None
    depth_files: dict[str, Path] | None = None
    intrinsics_by_key: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # per frame (K, dist)
    stamps: dict[str, float] = field(default_factory=dict)  # seconds per frame key, where the format has them


def find_frames(folder: Path) -> tuple[dict[str, Path], dict[str, Path]]:
    """(colour, depth) image files by frame key: ``*color*``/``*rgb*`` and ``*depth*`` names, or sub-folders."""
    files = [f for f in sorted(folder.rglob("*")) if f.is_file() and f.suffix.lower() in (".png", ".jpg", ".jpeg",
                                                                                            ".tif", ".tiff")]
    colour: dict[str, Path] = {}
    depth: dict[str, Path] = {}
    for f in files:
        rel = str(f.relative_to(folder)).lower()
        target = depth if any(w in rel for w in DEPTH_WORDS) else (
            colour if any(w in rel for w in COLOUR_WORDS) else None)
        if target is None:
            continue
        key = frame_key(f.name)
        if key in target:
            raise FormatError(f"two images for frame {key} ({target[key].name}, {f.name}): duplicated frame", folder)
        target[key] = f
    if not depth:
        raise FormatError("no depth images (names or folders containing 'depth')", folder)
    return colour, depth


def _read_depth(path: Path) -> np.ndarray:
    d: np.ndarray | None = decode_image(path, cv2.IMREAD_UNCHANGED, "a depth image")
    if d is None:
        raise FormatError("cannot read the depth image", path)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise FormatError(f"depth must be a 16-bit single-channel image, got {d.dtype} with shape {d.shape}", path)
    return d


def check_depth_scale(depth: np.ndarray, scale: float, path: Path) -> float:
    """Median depth (m) of a frame; raise when the declared scale puts it at an impossible distance."""
    valid = depth[depth > 0]
    if valid.size == 0:
        raise FormatError("depth image has no valid pixel", path)
    med = float(np.median(valid)) * scale
    if not MIN_DEPTH_M <= med <= MAX_DEPTH_M:
        for s in (1e-3, 1e-4, 2.5e-4, 1e-5, 1.0 / 5000.0):
            if MIN_DEPTH_M <= float(np.median(valid)) * s <= MAX_DEPTH_M:
                raise FormatError(f"depth scale {scale:g} m/unit puts the scene at {med:.3g} m (median); a scale of "
                                  f"{s:g} would put it at {float(np.median(valid)) * s:.2f} m: check --depth-scale-m",
                                  path)
        raise FormatError(f"depth scale {scale:g} m/unit puts the scene at {med:.3g} m (median): check "
                          "--depth-scale-m", path)
    return med


def check_translation_scale(T_world_cam: np.ndarray, median_depth_m: float, source: str,
                            factor: float = 50.0) -> None:
    """Raise when the cameras span far more than the scene's depth allows: millimetres given as metres."""
    t = T_world_cam[:, :3, 3]
    extent = float(np.max(np.ptp(t, axis=0))) if len(t) > 1 else 0.0
    if extent > factor * median_depth_m:
        raise FormatError(f"the cameras span {extent:.3g} m in a scene {median_depth_m:.2f} m deep (median depth): "
                          "the translations look like millimetres given as metres (divide them by 1000, or "
                          "--unit mm for flange poses)", source)


def _points(depth: np.ndarray, scale: float, K: np.ndarray, T: np.ndarray, step: int = 4) -> np.ndarray:
    d = depth[::step, ::step].astype(np.float64) * scale
    v, u = np.nonzero(d)
    z = d[v, u]
    x = (u * step - K[0, 2]) / K[0, 0] * z
    y = (v * step - K[1, 2]) / K[1, 1] * z
    P = np.stack([x, y, z], 1)
    return np.asarray(P @ T[:3, :3].T + T[:3, 3])


def pose_direction_check(frames: list[tuple[Path, np.ndarray, np.ndarray]], scale: float, K: np.ndarray,
                         source: str, ratio: float = 0.5) -> dict[str, float]:
    """Median nearest-neighbour distance (mm) between neighbouring frames' points, poses as given and inverted.

    Raises when the inverted poses agree much better (camera-from-world given as world-from-camera).
    """
    from scipy.spatial import cKDTree

    def nn(invert: bool) -> float:
        meds = []
        for (_, d0, T0), (_, d1, T1) in zip(frames[:-1], frames[1:], strict=True):
            A = _points(d0, scale, K, invert_transform(T0) if invert else T0)
            B = _points(d1, scale, K, invert_transform(T1) if invert else T1)
            if len(A) and len(B):
                meds.append(float(np.median(cKDTree(A).query(B)[0])))
        return 1e3 * float(np.median(meds)) if meds else float("nan")

    given, inverted = nn(False), nn(True)
    if np.isfinite(given) and np.isfinite(inverted) and inverted < ratio * given and given > 5.0:
        raise FormatError(f"the poses look camera-from-world, not world-from-camera: neighbouring frames' points lie "
                          f"{given:.1f} mm apart (median) as given, {inverted:.1f} mm with the poses inverted; "
                          "invert them (or, for flange poses, check the hand-eye direction)", source)
    return {"neighbour_median_mm": given, "neighbour_median_mm_inverted": inverted}


def import_sequence(spec: ImportSpec) -> dict[str, Any]:
    """Write the imported survey (keyframes folder and import.json); returns the import record."""
    if spec.depth_files is not None:
        colour, depth = dict(spec.colour_files or {}), dict(spec.depth_files)
        for f in depth.values():
            if not f.is_file():
                raise FormatError("depth image not found (listed by the sequence's index)", f)
    else:
        colour, depth = find_frames(spec.sequence)
    record: dict[str, Any] = {"sequence": str(spec.sequence), "pose_source": spec.pose_source,
                              "depth_scale_m": spec.depth_scale_m, "K": spec.K.tolist(), "warnings": []}

    def warn(msg: str) -> None:
        record["warnings"].append(msg)
        warnings.warn(msg, ImportWarning, stacklevel=2)

    no_colour = sorted(set(depth) - set(colour), key=_num)
    if colour and no_colour:
        warn(f"{spec.sequence}: {len(no_colour)} depth image(s) without a colour image (e.g. frame {no_colour[0]}); "
             "missing frames are imported without colour")
    no_pose = sorted(set(depth) - set(spec.poses), key=_num)
    if no_pose:
        warn(f"{spec.pose_source}: no pose for {len(no_pose)} of {len(depth)} depth frames (e.g. frame "
             f"{no_pose[0]}); those frames are skipped")
    unused = sorted(set(spec.poses) - set(depth), key=_num)
    if unused:
        warn(f"{spec.pose_source}: {len(unused)} pose(s) without a depth image (e.g. frame {unused[0]}): missing "
             "frames?")
    keys = [k for k in sorted(depth, key=_num) if k in spec.poses][::max(spec.every, 1)]
    if len(keys) < 2:
        raise FormatError(f"{len(keys)} frame(s) with both depth and a pose; need at least 2", spec.sequence)
    first = _read_depth(depth[keys[0]])
    h, w = first.shape
    if keys[0] in colour:
        c = decode_image(colour[keys[0]], cv2.IMREAD_COLOR, "a colour image")
        if c is None:
            raise FormatError("cannot read the colour image", colour[keys[0]])
        if c.shape[:2] != (h, w):
            raise FormatError(f"colour is {c.shape[1]} x {c.shape[0]} but depth {w} x {h}: the depth is not "
                              "registered to colour; register it (e.g. librealsense align-to-colour) and give the "
                              "colour intrinsics", colour[keys[0]])
    if abs(spec.K[0, 2] * 2 - w) > 0.25 * w or abs(spec.K[1, 2] * 2 - h) > 0.25 * h:
        raise FormatError(f"the principal point ({spec.K[0, 2]:.0f}, {spec.K[1, 2]:.0f}) is far from the centre of "
                          f"the {w} x {h} depth image: intrinsics for another resolution or stream?", spec.sequence)
    record["median_depth_m"] = check_depth_scale(first, spec.depth_scale_m, depth[keys[0]])
    check_translation_scale(np.array([spec.poses[k] for k in keys]), record["median_depth_m"], spec.pose_source)
    sample = [(depth[k], _read_depth(depth[k]), spec.poses[k]) for k in keys[:6]]
    record["pose_check"] = pose_direction_check(sample, spec.depth_scale_m, spec.K, spec.pose_source)

    def intrinsics_of(key: str) -> Intrinsics:
        K, dist = spec.intrinsics_by_key.get(key, (spec.K, spec.dist))
        return Intrinsics(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                          spec.distortion_model, tuple(float(v) for v in (list(dist) + [0.0] * 5)[:5]))  # type: ignore[arg-type]

    folder = spec.out / "keyframes"
    if spec.heldout_keys is not None:
        unknown = sorted(spec.heldout_keys - set(keys))
        if unknown:
            raise FormatError(f"{len(unknown)} held-out frame(s) are not imported frames (e.g. {unknown[0]!r})",
                              spec.sequence)
        held = np.array([k in spec.heldout_keys for k in keys])
    else:
        held = heldout_mask(len(keys), spec.heldout_every, spec.heldout_offset)
    entries, files = [], []
    for i, k in enumerate(keys):
        d = _read_depth(depth[k])
        if d.shape != (h, w):
            raise FormatError(f"depth is {d.shape[1]} x {d.shape[0]}, the first frame {w} x {h}", depth[k])
        rgb: np.ndarray = np.zeros((h, w, 3), np.uint8)
        if k in colour:
            c = decode_image(colour[k], cv2.IMREAD_COLOR, "a colour image")
            if c is None or c.shape[:2] != (h, w):  # never a black image in place of a frame's colour
                got = "not a readable image" if c is None else f"{c.shape[1]} x {c.shape[0]}, the depth {w} x {h}"
                raise FormatError(f"colour image: {got}", colour[k])
            rgb = np.ascontiguousarray(c[:, :, ::-1])
        t_s = spec.stamps.get(k, float(i))
        kf = Keyframe(arm=spec.arm, serial="imported", frame_number=int(_num(k)), timestamp_ms=t_s * 1e3,
                      t_s=t_s, split=HELDOUT if held[i] else FUSE, view=i, T_world_cam=spec.poses[k],
                      rgb=rgb, depth=d, ir_left=np.zeros((h, w), np.uint8), ir_right=np.zeros((h, w), np.uint8),
                      support_mask=d > 0, intrinsics=intrinsics_of(k), depth_scale=spec.depth_scale_m,
                      streams=("depth", "color") if k in colour else ("depth",))
        rel = f"{spec.arm}/{int(_num(k)):06d}.npz"
        write_keyframe(folder / rel, kf)
        entries.append(kf.index_entry(rel))
        files.append({"key": k, "frame_number": kf.frame_number, "keyframe": rel, "depth": str(depth[k]),
                      "colour": str(colour[k]) if k in colour else None})
    index = KeyframeIndex(folder=folder, survey=spec.sequence.name, object_name=spec.sequence.name,
                          pose_source=POSE_SOURCE, settings={"every": spec.every, "heldout_every": spec.heldout_every,
                                    "heldout_offset": spec.heldout_offset,
                                    "heldout": "list" if spec.heldout_keys is not None else "every"},
                          arms={spec.arm: {"serial": "imported", "keyframes": len(keys), "heldout": int(held.sum())}},
                          keyframes=entries, extra={"import": str(spec.out / IMPORT_FILE)})
    write_keyframe_index(index)
    record.update({"frames": len(keys), "heldout": int(held.sum()), "image_size": [w, h], "files": files})
    if spec.envelope is not None:
        from darp.formats.envelope import ENVELOPE_FILE, read_envelope, write_envelope

        env = read_envelope(spec.envelope)
        if not env.has_geometry:
            raise FormatError("the envelope has no centre/radius/height to crop to", spec.envelope)
        write_envelope(spec.out / ENVELOPE_FILE, env)
        record["envelope"] = str(spec.envelope)
    write_json_atomic(spec.out / IMPORT_FILE, record)
    return record


def _num(key: str) -> int:
    try:
        return int(key)
    except ValueError:
        return 0


def is_imported(folder: Path) -> bool:
    """True for a folder written by ``darp import``."""
    return (folder / IMPORT_FILE).is_file() and (folder / "keyframes" / "keyframes.json").is_file()


def process_imported(folder: Path, out: Path | None = None, fusion: FusionSettings | None = None,
                     mesh_settings: MeshSettings | None = None,
                     surface: SurfaceSettings | None = None) -> dict[str, Any]:
    """Fusion of the ``fuse`` keyframes, a mesh, held-out point-to-mesh; writes results.json.

    The surface is ``surface.method``'s (``auto``: the measured surface, :mod:`darp.processing.imported_surface`;
    ``paper``: voxel-support fusion and ball pivoting). The results document follows ``darp-results/1``
    (:mod:`darp.processing.results`) with pose_source "imported", no cross-arm section, no truth and no
    composition row, so ``darp report`` takes it.
    """
    out = out or folder
    out.mkdir(parents=True, exist_ok=True)
    kdir = folder / "keyframes"
    index = read_keyframe_index(kdir)
    settings = fusion or FusionSettings()
    surface = surface or SurfaceSettings()
    from darp.formats.envelope import ENVELOPE_FILE, read_envelope

    measured = resolve_method(surface, imported=True) == "measured"
    envelope_info: dict[str, Any]
    fuse_frames: list[PosedDepth] | None = None
    if (folder / ENVELOPE_FILE).is_file():
        crop = settings.crop(read_envelope(folder / ENVELOPE_FILE))
        envelope_info = {"source": "manip_envelope.json", "center_m": list(crop.center_m), "radius_m": crop.radius_m,
                         "height_m": crop.height_m}
    else:  # the fuse frames are read once: for the estimate, then for fusion (the measured surface: depth only)
        fuse_frames = [kf.posed_depth(colour=not measured)
                       for kf in iter_keyframes(kdir, FUSE, skip=DEPTH_ONLY if measured else ())]
        crop, envelope_info = _estimated_crop(fuse_frames, kdir, settings)
    if measured:
        return process_imported_measured(folder, out, index, surface, crop, envelope_info, fuse_frames)
    fz = VoxelFusion(settings, crop)
    for frame in fuse_frames if fuse_frames is not None else (kf.posed_depth() for kf in iter_keyframes(kdir, FUSE)):
        fz.add(frame)
    result = fz.result()
    if len(result.fused) < 10:
        raise ReconstructionError("fusion kept fewer than 10 points: do the frames overlap (poses, depth scale)?",
                                  folder)
    write_voxel_cloud(out / "fused.ply", result.fused)
    cloud = result.fused
    normals = cloud.normals / np.linalg.norm(cloud.normals, axis=1, keepdims=True)
    mesh = ball_pivoting_mesh(cloud.points, normals, cloud.colours, mesh_settings)
    write_mesh(out / "mesh.ply", mesh)
    md = MeshDistance(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    frames: list[PosedDepth] = [kf.posed_depth() for kf in iter_keyframes(kdir, HELDOUT)]
    held = evaluate_heldout(frames, md, object_name=index.object_name or index.survey, settings=settings,
                            region=crop)
    (out / EVALUATION_DIR).mkdir(exist_ok=True)
    _save_arrays(out / EVALUATION_DIR / HELDOUT_DISTANCES, held.distances)
    for arm, c in result.per_arm.items():
        write_voxel_cloud(out / f"{arm}.ply", c)
    figures = draw_figures(out, {a: c.points for a, c in result.per_arm.items()}, cloud.points, cloud.colours,
                           held.distances, title=index.survey)
    fig = out / FIGURES_DIR / "imported_mesh.png"
    pooled = np.concatenate(list(held.distances.values())) if held.distances else np.empty(0)
    _figure(mesh, [backproject(f, settings.depth, crop).points for f in frames], fig, index.survey,
            float(np.median(pooled)) * 1e3 if pooled.size else float("nan"))
    figures["mesh"] = f"{FIGURES_DIR}/imported_mesh.png"
    res = {
        "schema": SCHEMA, "survey": folder.name, "survey_path": str(folder),
        "object": index.object_name or index.survey, "pose_source": POSE_SOURCE,
        "calibration": {"epoch": None, "path": None}, "composition": None,
        "envelope": envelope_info,
        "keyframes": {"total": len(index.keyframes), "fuse": len(index.select(FUSE)), "heldout": len(frames),
                      "arms": index.arms},
        "clouds": {**{a: len(c) for a, c in result.per_arm.items()}, "fused": len(cloud)},
        "mesh": {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles), "area_m2": mesh_area(mesh)},
        "heldout": held.to_dict(), "cross_arm": None, "truth": None, "figures": figures, "stages": {},
        "paper": paper.HELDOUT,
    }
    write_json_atomic(out / RESULTS_FILE, to_jsonable(res))
    return res


def process_imported_measured(folder: Path, out: Path, index: KeyframeIndex, surface: SurfaceSettings, crop: Any,
                              envelope_info: dict[str, Any], fuse_frames: list[PosedDepth] | None) -> dict[str, Any]:
    """:func:`process_imported` with the measured surface (depth statistics, cleaned TSDF, supported mesh)."""
    from darp.processing.imported_surface import (
        build_measured_surface,
        depth_stats_of,
        envelope_open_pct,
        evaluate_heldout_measured,
        mesh_raster_figure,
        write_mesh_cloud,
    )

    kdir = folder / "keyframes"
    cpu: dict[str, float] = {}
    t = time.process_time()
    stats = depth_stats_of(fuse_frames if fuse_frames is not None else
                           (kf.posed_depth(colour=False) for kf in iter_keyframes(kdir, FUSE, skip=DEPTH_ONLY)),
                           surface)
    del fuse_frames
    cpu["depth_stats"] = time.process_time() - t
    frames_in = (kf.posed_depth() for kf in iter_keyframes(kdir, FUSE, skip=("ir_left", "ir_right", "support_mask")))
    mesh, info = build_measured_surface(stats, frames_in, surface, crop)
    cpu["surface"] = time.process_time() - t - cpu["depth_stats"]
    t = time.process_time()
    arm = next(iter(index.arms), "arm")
    write_mesh_cloud(out / "fused.ply", mesh, arm)
    write_mesh(out / "mesh.ply", mesh)
    md = MeshDistance(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    shown: list[np.ndarray] = []

    def keep(_: PosedDepth, points: np.ndarray) -> None:
        if len(shown) < 2:
            shown.append(points[::50])

    held = evaluate_heldout_measured((kf.posed_depth(colour=False) for kf in iter_keyframes(kdir, HELDOUT,
                                                                                          skip=DEPTH_ONLY)),
                                     md, stats, info, surface, crop, index.object_name or index.survey, keep)
    (out / EVALUATION_DIR).mkdir(exist_ok=True)
    _save_arrays(out / EVALUATION_DIR / HELDOUT_DISTANCES, held.distances)
    cpu["evaluation"] = time.process_time() - t
    t = time.process_time()
    vertices = np.asarray(mesh.vertices, np.float32)
    figures = draw_figures(out, {}, np.empty((0, 3)), None, held.distances, title=index.survey)
    pooled = np.concatenate(list(held.distances.values())) if held.distances else np.empty(0)
    mesh_raster_figure(mesh, shown, out / FIGURES_DIR / "imported_mesh.png", index.survey,
                       float(np.median(pooled)) * 1e3 if pooled.size else float("nan"))
    figures["mesh"] = f"{FIGURES_DIR}/imported_mesh.png"
    cpu["figures"] = time.process_time() - t
    info["open_pct"] = envelope_open_pct(mesh, envelope_info, info["voxel_size_m"])
    info["cpu_s"].update(cpu)
    res = {
        "schema": SCHEMA, "survey": folder.name, "survey_path": str(folder),
        "object": index.object_name or index.survey, "pose_source": POSE_SOURCE,
        "calibration": {"epoch": None, "path": None}, "composition": None,
        "envelope": envelope_info,
        "keyframes": {"total": len(index.keyframes), "fuse": len(index.select(FUSE)), "heldout": held.n_frames,
                      "arms": index.arms},
        "clouds": {arm: len(vertices), "fused": len(vertices)},
        "mesh": {"vertices": len(vertices), "triangles": len(mesh.triangles), "area_m2": mesh_area(mesh)},
        "surface": info,
        "heldout": held.to_dict(), "cross_arm": None, "truth": None, "figures": figures, "stages": {},
        "paper": paper.HELDOUT,
    }
    write_json_atomic(out / RESULTS_FILE, to_jsonable(res))
    return res


def _estimated_crop(frames: list[PosedDepth], kdir: Path, settings: FusionSettings) -> tuple[Any, dict[str, Any]]:
    """The object cylinder estimated from the fuse keyframes (as for a DARP survey without an envelope), or
    no crop with a warning when no object stands on a table at z = 0 where the cameras look."""
    from darp.reconstruction.envelope_estimate import envelope_from_frames, robust_look_at, search_region

    try:
        look_at, _ = robust_look_at(np.stack([f.T_world_cam for f in frames]))
        estimate = envelope_from_frames(frames, look_at, search_region(look_at, []), depth_settings=settings.depth,
                                        path=kdir)
    except ReconstructionError as err:
        warnings.warn(f"{kdir}: no envelope given and none could be estimated ({err.message}); fusing without a "
                      "crop (give --envelope to darp import to crop to the object)", ImportWarning, stacklevel=3)
        return None, {"source": "none (no --envelope and no object found to estimate one: no crop)"}
    return settings.crop(estimate.envelope()), estimate.to_dict()


def _figure(mesh: Any, held_points: list[np.ndarray], path: Path, title: str, median_mm: float,
            max_triangles: int | None = None) -> None:
    """The mesh from above and the side with held-out points; ``max_triangles``: draw an even sample of the
    triangles (None: the first 300,000, as before)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from darp.formats.atomic import atomic_path

    V = np.asarray(mesh.vertices)
    F = np.asarray(mesh.triangles)
    if max_triangles is not None:
        F = F[::max(len(F) // max_triangles, 1)]
    fig = Figure(figsize=(12, 5))
    for n, (a, b, name) in enumerate(((0, 1, "top (x, y)"), (0, 2, "side (x, z)"))):
        ax = fig.add_subplot(1, 2, n + 1)
        if len(F):
            ax.tripcolor(V[:, a], V[:, b], F[: min(len(F), 300000)], facecolors=V[F[:300000], 2 - n].mean(axis=1),
                         cmap="viridis", shading="flat")
        for P in held_points[:2]:
            if len(P):
                ax.scatter(P[::50, a], P[::50, b], s=0.2, c="red", alpha=0.3)
        ax.set_aspect("equal")
        ax.set_title(f"{title}: mesh {name}" + (f"; held-out median {median_mm:.2f} mm" if n == 0 else ""))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)


__all__ = ["IMPORT_FILE", "ImportSpec", "ImportWarning", "check_depth_scale", "check_translation_scale",
           "find_frames", "import_sequence", "is_imported", "pose_direction_check", "process_imported"]
