"""``darp view``: a survey or a processed survey in rerun (rerun-sdk).

Entities (world frame, metres, z up; one timeline ``time``, the host clock):

=============================== ===================================================================================
``world/<arm>/links``           the arm's collision geometry (darp.kinematics: link cylinders, camera body and
                                bracket) at each logged joint state, with the calibration's base pose and joint
                                zeros; ``world/<arm>/skeleton`` the chain of link origins
``world/<arm>/camera``          the camera pose (``T_world_cam``) as a transform and a pinhole (its frustum)
``world/<arm>/camera/rgb``      colour aligned to depth; ``.../depth`` metric depth; ``.../ir`` left infrared
``world/clouds/<name>``         per-arm and fused clouds (``arm110``, ``arm111``, ``fused``), processed only
``world/mesh``                  the ball-pivoting mesh, processed only
``world/heldout``               held-out keyframes' object points coloured by distance to the mesh (0-10 mm,
                                turbo), processed only; their distances in millimetres as ``world/heldout_mm``
=============================== ===================================================================================

A processed survey's images are its keyframes; a raw survey's are frame sets a ``every_s`` apart,
with eq. 1 poses (the calibration given, the twin's true one, or the rig's nominal one).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from darp.dataset import ProcessedSurvey, find_processed, keyframe_object_points
from darp.errors import ConfigError, DarpError, FormatError
from darp.formats.calibration import Calibration, read_calibration
from darp.formats.survey import Survey, open_survey
from darp.kinematics import z1
from darp.kinematics.collision import arm_primitives
from darp.kinematics.collision_shapes import KINDS
from darp.kinematics.rig import load_rig
from darp.kinematics.transforms import rotation_to_quaternion
from darp.reconstruction.cloud_io import read_ply
from darp.reconstruction.keyframe_io import read_keyframe, read_keyframe_index

ARM_RATE_HZ = 10.0  # joint states logged per second of the timeline
HELDOUT_RANGE_M = 0.010  # the colour map's top (10 mm: the paper's coarser threshold)
ENTITY = {"cylinder": "cylinders", "capsule": "capsules", "box": "boxes"}
ARM_COLOURS = {"arm110": (230, 120, 40), "arm111": (40, 140, 230)}


@dataclass
class ViewStats:
    """What a view logged: counts per entity kind."""

    arm_states: int = 0
    images: int = 0
    clouds: int = 0
    heldout_points: int = 0
    mesh_triangles: int = 0


def _rerun() -> Any:
    # rerun's own log lines (gRPC retries ...) would repeat darp's one-line errors; RUST_LOG set by the user wins
    os.environ.setdefault("RUST_LOG", "off")
    try:
        import rerun as rr
    except ImportError:
        raise DarpError("darp view needs rerun-sdk (pip install rerun-sdk, or make setup)") from None
    return rr



def arm_columns(arm: str, q_states: np.ndarray, calibration: Calibration) -> dict[str, Any]:
    """Collision primitives and link origins of ``arm`` at every joint state (N, 6), as flat arrays:
    per kind its rows' ``R``, ``centre``, ``half`` (N * k) and ``k``; ``origins`` (N, 7, 3)."""
    cal = calibration.arms[arm]
    q_true = np.asarray(q_states, np.float64) + cal.joint_offsets_rad
    sets = [arm_primitives(q, cal.T_world_base) for q in q_true]
    out: dict[str, Any] = {"origins": (cal.T_world_base @ z1.link_transforms_batch(q_true))[:, :, :3, 3]}
    for kind in KINDS:
        sel = sets[0].kinds == KINDS.index(kind)
        out[kind] = {"k": int(sel.sum()), "R": np.concatenate([p.R[sel] for p in sets]),
                     "centre": np.concatenate([p.centre[sel] for p in sets]),
                     "half": np.concatenate([p.half[sel] for p in sets])}
    return out


def log_arm_states(rec: Any, rr: Any, arm: str, times_s: np.ndarray, q_states: np.ndarray,
                   calibration: Calibration) -> None:
    """Every joint state of one arm in one call per entity (rerun's columnar API): its collision
    primitives and the chain of link origins on the ``time`` timeline."""
    cols = arm_columns(arm, q_states, calibration)
    n = len(times_s)
    index = [rr.TimeColumn("time", timestamp=np.asarray(times_s, np.float64))]
    colour = np.array(ARM_COLOURS.get(arm, (200, 200, 200)), np.uint8)
    for kind in KINDS:
        c = cols[kind]
        if c["k"] == 0:
            continue
        half, quats = c["half"], rotation_to_quaternion(c["R"]).reshape(-1, 4)
        colours = np.tile(colour, (len(half), 1))
        if kind == "cylinder":
            data = rr.Cylinders3D.columns(lengths=2 * half[:, 2], radii=half[:, 0], centers=c["centre"],
                                          quaternions=quats, colors=colours)
        elif kind == "capsule":  # rerun's capsule starts at its translation and runs along +z
            start = c["centre"] - c["R"][:, :, 2] * half[:, 2:3]
            data = rr.Capsules3D.columns(lengths=2 * half[:, 2], radii=half[:, 0], translations=start,
                                         quaternions=quats, colors=colours)
        else:
            data = rr.Boxes3D.columns(half_sizes=half, centers=c["centre"], quaternions=quats, colors=colours)
        rec.send_columns(f"world/{arm}/links/{ENTITY[kind]}", indexes=index, columns=data.partition([c["k"]] * n))
    rec.send_columns(f"world/{arm}/skeleton", indexes=index,
                     columns=rr.LineStrips3D.columns(strips=list(cols["origins"]), colors=np.tile(colour, (n, 1))))


def log_camera(rec: Any, rr: Any, arm: str, T_world_cam: np.ndarray, K: np.ndarray, size: tuple[int, int],
               rgb: np.ndarray | None, depth: np.ndarray | None, depth_units_per_m: float,
               ir: np.ndarray | None) -> None:
    """One posed camera frame: transform, pinhole (frustum) and its images."""
    T = np.asarray(T_world_cam, np.float64)
    path = f"world/{arm}/camera"
    rec.log(path, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    rec.log(path, rr.Pinhole(image_from_camera=K, resolution=list(size), camera_xyz=rr.ViewCoordinates.RDF,
                             image_plane_distance=0.05))
    if rgb is not None:
        rec.log(f"{path}/rgb", rr.Image(rgb))
    if depth is not None:
        rec.log(f"{path}/depth", rr.DepthImage(depth, meter=depth_units_per_m))
    if ir is not None:
        rec.log(f"{path}/ir", rr.Image(ir))


def _arm_rows(log_t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Rows of the joint log at about ``rate_hz`` (the nearest row to each tick)."""
    if not len(log_t):
        return np.empty(0, np.int64)
    times = np.arange(log_t[0], log_t[-1] + 1e-9, 1.0 / rate_hz)
    return np.unique(np.clip(np.searchsorted(log_t, times), 0, len(log_t) - 1))


def _calibration(survey_path: Path | None, calibration_path: Path | None) -> Calibration:
    if calibration_path is not None:
        return read_calibration(calibration_path)
    if survey_path is not None and (survey_path / "truth" / "calibration.json").is_file():
        return read_calibration(survey_path / "truth" / "calibration.json")
    return load_rig().nominal_calibration()


def _turbo(values: np.ndarray) -> np.ndarray:
    from matplotlib import colormaps

    return np.asarray(colormaps["turbo"](np.clip(values, 0.0, 1.0))[:, :3] * 255, np.uint8)


def viewer_url(value: str) -> str:
    """A rerun viewer's gRPC address: ``rerun+http://HOST:PORT/proxy`` (or ``rerun://``, ``rerun+https://``),
    ``HOST:PORT`` or a port on this machine, as the ``rerun`` command's ``--connect`` takes it."""
    value = value.strip()
    if value.isdigit():
        return f"rerun+http://127.0.0.1:{value}/proxy"
    if "://" not in value:
        host, _, port = value.rpartition(":")
        if host and port.isdigit():
            return f"rerun+http://{host}:{port}/proxy"
        raise ConfigError(f"viewer address {value!r}: expected rerun+http://HOST:PORT/proxy, HOST:PORT or a port")
    scheme, _, rest = value.partition("://")
    if scheme not in ("rerun", "rerun+http", "rerun+https") or not rest.split("/", 1)[0]:
        raise ConfigError(f"viewer address {value!r}: the scheme must be rerun://, rerun+http:// or rerun+https://")
    return value if rest.endswith("/proxy") else f"{value.rstrip('/')}/proxy"


def view(path: str | Path, save: str | Path | None = None, *, calibration_path: Path | None = None,
         every_s: float = 0.5, spawn: bool = True, connect: str | None = None) -> ViewStats:
    """Log a survey folder or a processed survey to rerun; ``save``: write an ``.rrd`` file and open no
    window; ``connect``: send to the viewer (or ``rerun --serve-grpc`` proxy) at that address
    (:func:`viewer_url`); otherwise spawn a viewer (``spawn`` False: the one listening on the default port)."""
    rr = _rerun()
    if save is not None and connect is not None:
        raise ConfigError("--save and --connect: give one (a file, or a viewer to send to)")
    url = None if connect is None else viewer_url(connect)
    path = Path(path)
    processed = _processed_or_none(path)
    survey_path = processed.survey_path if processed is not None else path
    if survey_path is not None and not survey_path.is_dir():
        survey_path = None
    calibration = _calibration(survey_path, calibration_path or (processed.calibration_path if processed else None))
    rec = rr.RecordingStream("darp", recording_id=f"darp-{path.resolve().name}")
    if save is not None:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(save))
    elif url is not None or not spawn:
        rec.connect_grpc(url)
    else:
        rec.spawn()
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    if url is not None:  # fail in seconds, before decoding anything, when no viewer listens there
        try:
            rec.flush(timeout_sec=15.0)
        except RuntimeError as err:
            rec.disconnect()
            raise DarpError(f"no rerun viewer reachable at {url} (start one there with 'rerun' or "
                            f"'rerun --serve-grpc'): {str(err).splitlines()[0]}") from None
    stats = ViewStats()
    survey = None
    if survey_path is not None:
        survey = open_survey(survey_path, serial_to_arm={a.serial: n for n, a in calibration.arms.items()})
        stats.arm_states = _log_arms(rec, rr, survey, calibration)
    if processed is not None:
        _log_processed(rec, rr, processed, stats)
    elif survey is not None:
        stats.images = _log_raw_frames(rec, rr, survey, calibration, every_s)
    rec.flush()
    if save is not None or url is not None:
        rec.disconnect()  # everything sent (or written) before darp exits
    return stats


def _processed_or_none(path: Path) -> ProcessedSurvey | None:
    if (path / "keyframes" / "keyframes.json").is_file():
        return find_processed(path)[0]
    if (path / "arm_poses.csv").is_file():
        return None
    found = find_processed(path)  # the output folder of several surveys: the first one
    if len(found) > 1:
        raise FormatError(f"{len(found)} processed surveys here: view one of them ({found[0].folder}, ...)", path)
    return found[0]


def _log_arms(rec: Any, rr: Any, survey: Survey, calibration: Calibration) -> int:
    log = survey.arm_poses()
    n = 0
    for arm in log.arms:
        if arm not in calibration.arms:
            continue
        rows = _arm_rows(log.times(arm), ARM_RATE_HZ)
        log_arm_states(rec, rr, arm, log.times(arm)[rows], log.joints(arm)[rows], calibration)
        n += len(rows)
    return n


def _log_processed(rec: Any, rr: Any, processed: ProcessedSurvey, stats: ViewStats) -> None:
    index = read_keyframe_index(processed.keyframes_dir)
    heldout = {info.file for info in index.select("heldout", None)}
    parts = []  # held-out keyframes' object points, from the one read of each keyframe
    for info in index.select(None, None):
        kf = read_keyframe(index.folder / info.file)
        rec.set_time("time", timestamp=kf.t_s)
        i = kf.intrinsics
        log_camera(rec, rr, kf.arm, kf.T_world_cam, i.K, (i.width, i.height), kf.rgb, kf.depth,
                   1.0 / kf.depth_scale, kf.ir_left)
        stats.images += 1
        if info.file in heldout:
            parts.append(keyframe_object_points(kf))
    for name, colour in (("arm110", ARM_COLOURS["arm110"]), ("arm111", ARM_COLOURS["arm111"]),
                         ("fused", None)):
        file = processed.folder / f"{name}.ply"
        if not file.is_file():
            continue
        ply = read_ply(file)
        colours = (np.column_stack([ply.vertex[c] for c in ("red", "green", "blue")]).astype(np.uint8)
                   if colour is None and "red" in ply.vertex else colour)
        rec.log(f"world/clouds/{name}", rr.Points3D(ply.points, colors=colours, radii=0.0008), static=True)
        stats.clouds += 1
    mesh_file = processed.folder / "mesh.ply"
    if mesh_file.is_file():
        from darp.evaluation.point_to_mesh import MeshDistance

        mesh = read_ply(mesh_file)
        assert mesh.triangles is not None
        rec.log("world/mesh", rr.Mesh3D(vertex_positions=mesh.points, triangle_indices=mesh.triangles,
                                        albedo_factor=[0.8, 0.8, 0.8, 0.6]), static=True)
        stats.mesh_triangles = len(mesh.triangles)
        points = np.concatenate(parts) if parts else np.empty((0, 3))
        if len(points):
            d = MeshDistance(mesh.points, mesh.triangles).distances(points)
            rec.log("world/heldout", rr.Points3D(points, colors=_turbo(d / HELDOUT_RANGE_M), radii=0.0008),
                    static=True)
            rec.log("world/heldout_mm", rr.AnyValues(distance_mm=np.asarray(d, np.float64) * 1000.0), static=True)
            stats.heldout_points = len(points)
    results = processed.folder / "results.json"
    if results.is_file():
        summary = json.loads(results.read_text(encoding="utf-8")).get("heldout", {}).get("aggregate", {})
        rec.log("summary", rr.TextDocument(json.dumps(summary, indent=1)), static=True)


def _log_raw_frames(rec: Any, rr: Any, survey: Survey, calibration: Calibration, every_s: float) -> int:
    from darp.reconstruction.align import align_colour_to_depth, colour_to_rgb
    from darp.reconstruction.poses import recover_survey_poses

    poses = recover_survey_poses(survey, calibration)
    n = 0
    for arm, traj in poses.trajectories.items():
        lookup = {int(f): k for k, f in enumerate(traj.frame_numbers)}
        recording = survey.open_recording(arm)
        try:
            d_intr = recording.stream("depth").intrinsics
            assert d_intr is not None
            last = -np.inf
            for fs in recording.framesets():
                if fs.depth is None or fs.timestamp_ms - last < 1000.0 * every_s:
                    continue
                k = lookup.get(fs.depth.info.frame_number)
                if k is None or not np.all(np.isfinite(traj.poses.T_world_cam[k])):
                    continue
                last = fs.timestamp_ms
                depth = np.asarray(fs.depth.data, np.uint16)
                rgb = None
                if fs.color is not None:
                    profile = recording.stream("color")
                    assert profile.intrinsics is not None
                    rgb = align_colour_to_depth(depth, recording.depth_scale, d_intr,
                                                colour_to_rgb(fs.color.data, profile.format), profile.intrinsics,
                                                recording.extrinsics("depth", "color"))
                ir = None if fs.ir1 is None else np.asarray(fs.ir1.data)
                rec.set_time("time", timestamp=float(traj.poses.t_s[k]))
                log_camera(rec, rr, arm, traj.poses.T_world_cam[k], d_intr.K, (d_intr.width, d_intr.height), rgb,
                           depth, 1.0 / recording.depth_scale, ir)
                n += 1
        finally:
            recording.close()
    return n


def rrd_entities(path: str | Path) -> dict[str, set[str]]:
    """Entity path -> archetype names (``Points3D``, ...) of an ``.rrd`` file, read with rerun's own reader."""
    _rerun()
    import warnings

    from rerun.chunk import RrdReader

    entities: dict[str, set[str]] = {}
    with warnings.catch_warnings():  # a streamed recording (``rerun --save`` of what a viewer received)
        warnings.filterwarnings("ignore", message="RRD file has no footer")  # has no footer: read it whole
        reader = RrdReader(str(path))
        try:
            store: Any = reader.store()
        except RuntimeError:
            store = reader.stream().collect()
    for column in store.schema():
        entity = getattr(column, "entity_path", None)
        archetype = getattr(column, "archetype", None)
        if entity is not None and archetype:
            entities.setdefault(str(entity), set()).add(str(archetype).rsplit(".", 1)[-1])
    return entities


__all__ = ["ViewStats", "arm_columns", "log_arm_states", "log_camera", "rrd_entities", "view", "viewer_url"]
