"""``darp view``: a survey or a processed survey in rerun (rerun-sdk).

Entities (world frame, metres, z up; one timeline ``time``, the host clock):

=============================== ===================================================================================
``world/<arm>/links``           the arm's collision geometry (darp.kinematics: link cylinders, camera body and
                                bracket) at each logged joint state, with the calibration's base pose and joint
                                zeros; ``world/<arm>/skeleton`` the chain of link origins
``world/<arm>/camera``          the wrist camera's pose (eq. 1, ``T_world_cam``) at every logged arm state and
                                at every image's time, and its pinhole (the frustum): it never leaves the wrist
``world/<arm>/camera/rgb``      colour aligned to depth; ``.../depth`` metric depth; ``.../ir`` left infrared
``world/clouds/<name>``         per-arm and fused clouds (``arm110``, ``arm111``, ``fused``), processed only
``world/mesh``                  the ball-pivoting mesh, processed only
``world/heldout``               held-out keyframes' object points coloured by distance to the mesh (0-10 mm,
                                turbo), processed only; their distances in millimetres as ``world/heldout_mm``
=============================== ===================================================================================

A processed survey's images are its keyframes; a raw survey's are frame sets a ``every_s`` apart,
with eq. 1 poses (the calibration given, the twin's true one, or the rig's nominal one).

The recording carries a default layout (:func:`default_blueprint`): a 3-D view centred on the object's
envelope, looking at it from the cameras' side, with the arms, frustums, clouds, mesh and held-out errors
but without the back-projected depth and IR (the room: table, walls), and per arm the colour, depth and
IR images beside it.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from darp.colours import arm_rgb
from darp.dataset import ProcessedSurvey, find_processed, keyframe_object_points
from darp.errors import ConfigError, DarpError, DarpWarning, FormatError
from darp.formats.atomic import atomic_path
from darp.formats.calibration import Calibration, read_calibration
from darp.formats.io_input import LIMITS
from darp.formats.survey import Survey, open_survey
from darp.formats.text import read_utf8_text
from darp.kinematics import z1
from darp.kinematics.camera_poses import interpolate_joints
from darp.kinematics.collision import arm_primitives
from darp.kinematics.collision_shapes import KINDS
from darp.kinematics.rig import Rig, load_rig
from darp.kinematics.transforms import rotation_to_quaternion
from darp.reconstruction.cloud_io import read_ply
from darp.reconstruction.keyframe_io import read_keyframe, read_keyframe_index

ARM_RATE_HZ = 10.0  # joint states logged per second of the timeline (plus one at every image's time)
HELDOUT_RANGE_M = 0.010  # the colour map's top (10 mm: the paper's coarser threshold)
ENTITY = {"cylinder": "cylinders", "capsule": "capsules", "box": "boxes"}
ARM_COLOURS = {arm: arm_rgb(arm) for arm in ("arm110", "arm111")}


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



def arm_columns(arm: str, q_states: np.ndarray, calibration: Calibration, rig: Rig | None = None) -> dict[str, Any]:
    """Collision primitives and link origins of ``arm`` at every joint state (N, 6), as flat arrays:
    per kind its rows' ``R``, ``centre``, ``half`` (N * k) and ``k``; ``origins`` (N, 7, 3); and the wrist
    camera's ``T_world_cam`` (N, 4, 4) by eq. 1 with the calibration (the camera body box sits on it)."""
    rig = rig or load_rig()
    cal = calibration.arms[arm]
    q_true = np.asarray(q_states, np.float64) + cal.joint_offsets_rad
    mount = rig.camera_mount(arm, calibration) if arm in rig.arms else None
    sets = [arm_primitives(q, cal.T_world_base, mount) if mount else arm_primitives(q, cal.T_world_base)
            for q in q_true]
    out: dict[str, Any] = {"origins": (cal.T_world_base @ z1.link_transforms_batch(q_true))[:, :, :3, 3]}
    wrist = rig.wrist_frame if arm in rig.arms else "flange"
    out["T_world_cam"] = cal.T_world_base @ z1.fk_batch(q_true, frame=wrist) @ cal.T_wrist_cam
    for kind in KINDS:
        sel = sets[0].kinds == KINDS.index(kind)
        out[kind] = {"k": int(sel.sum()), "R": np.concatenate([p.R[sel] for p in sets]),
                     "centre": np.concatenate([p.centre[sel] for p in sets]),
                     "half": np.concatenate([p.half[sel] for p in sets])}
    return out


def log_arm_states(rec: Any, rr: Any, arm: str, times_s: np.ndarray, q_states: np.ndarray,
                   calibration: Calibration, rig: Rig | None = None) -> None:
    """Every joint state of one arm in one call per entity (rerun's columnar API): its collision
    primitives, the chain of link origins and the wrist camera's pose (the frustum) on the ``time`` timeline."""
    cols = arm_columns(arm, q_states, calibration, rig)
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
    T = cols["T_world_cam"]
    rec.send_columns(f"world/{arm}/camera", indexes=index,
                     columns=rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]))


def log_camera(rec: Any, rr: Any, arm: str, T_world_cam: np.ndarray | None, K: np.ndarray, size: tuple[int, int],
               rgb: np.ndarray | None, depth: np.ndarray | None, depth_units_per_m: float,
               ir: np.ndarray | None) -> None:
    """One camera frame: its pinhole (frustum) and images, and its transform unless ``T_world_cam`` is None
    (the arm states carry the camera's pose, :func:`log_arm_states`)."""
    path = f"world/{arm}/camera"
    if T_world_cam is not None:
        T = np.asarray(T_world_cam, np.float64)
        rec.log(path, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    rec.log(path, rr.Pinhole(image_from_camera=K, resolution=list(size), camera_xyz=rr.ViewCoordinates.RDF,
                             image_plane_distance=0.05), static=True)  # one camera per arm: a frustum at all times
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
    with contextlib.ExitStack() as stack:  # --save: a temporary name beside the file, renamed when complete
        target = stack.enter_context(atomic_path(save)) if save is not None else None
        return _send(rr, path, target, url, spawn, processed, survey_path, calibration, every_s)


def viewer_executable() -> str | None:
    """The rerun viewer to spawn: the one on PATH, else the one installed beside this Python (``make demo``'s
    ``.venv/bin/rerun`` when the venv is not activated); None lets rerun-sdk search and say what it lacks."""
    found = shutil.which("rerun")
    if found is not None:
        return found
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.is_file() and os.access(beside, os.X_OK) else None


def _send(rr: Any, path: Path, save: Path | None, url: str | None, spawn: bool, processed: ProcessedSurvey | None,
          survey_path: Path | None, calibration: Calibration, every_s: float) -> ViewStats:
    rec = rr.RecordingStream("darp", recording_id=f"darp-{path.resolve().name}")
    arms = sorted(calibration.arms)
    blueprint = default_blueprint(*_envelope(processed, survey_path), arms=arms)
    if save is not None:
        rec.save(str(save), default_blueprint=blueprint)
    elif url is not None or not spawn:
        rec.connect_grpc(url, default_blueprint=blueprint)
    else:
        try:
            rr.spawn(executable_path=viewer_executable(), default_blueprint=blueprint, recording=rec)
        except (OSError, RuntimeError) as err:  # rerun-sdk without its viewer executable
            raise DarpError("no rerun viewer to open (install the viewer: pip install rerun-sdk; or give --save "
                            f"FILE.rrd or --connect URL): {str(err).splitlines()[0] if str(err) else err}"
                            ) from None
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    if save is None:  # fail in seconds, before decoding anything, when no viewer listens (or the spawned one died)
        try:
            rec.flush(timeout_sec=15.0)
        except RuntimeError as err:
            rec.disconnect()
            if url is not None:
                raise DarpError(f"no rerun viewer reachable at {url} (start one there with 'rerun' or "
                                f"'rerun --serve-grpc'): {str(err).splitlines()[0]}") from None
            raise DarpError("the rerun viewer did not start (no display here? give --save FILE.rrd, or --connect "
                            f"URL to a viewer elsewhere): {str(err).splitlines()[0]}") from None
    stats = ViewStats()
    survey = None
    if survey_path is not None:
        survey = open_survey(survey_path, serial_to_arm={a.serial: n for n, a in calibration.arms.items()})
        if survey.partial is not None:  # PARTIAL.txt: shown, and said to be unfinished
            warnings.warn(DarpWarning(f"unfinished survey ({survey.partial}): what is shown is partial",
                                      survey.path), stacklevel=2)
    image_times: dict[str, list[float]] = {}
    if processed is not None:
        image_times = _log_processed(rec, rr, processed, stats, pose=survey is None)
    elif survey is not None:
        image_times = _log_raw_frames(rec, rr, survey, calibration, every_s, stats)
    if survey is not None:
        stats.arm_states = _log_arms(rec, rr, survey, calibration, image_times)
    rec.flush()
    if save is not None or url is not None:
        rec.disconnect()  # everything sent (or written) before darp exits
    return stats


def _envelope(processed: ProcessedSurvey | None, survey_path: Path | None) -> tuple[np.ndarray, float, float]:
    """The object's envelope cylinder (centre, radius, height; metres): processing's, else the survey's
    ``manip_envelope.json``, else a 5 cm one at the world origin."""
    sources: list[tuple[Path, str | None]] = [] if processed is None else [(processed.folder / "results.json",
                                                                           "envelope")]
    if survey_path is not None:
        sources.append((survey_path / "manip_envelope.json", None))
    for file, key in sources:
        try:
            record = json.loads(read_utf8_text(file, "a JSON file", limit=LIMITS["json"]))
            record = record[key] if key else record
            return (np.asarray(record["center_m"], np.float64).reshape(3), float(record["radius_m"]),
                    float(record["height_m"]))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return np.zeros(3), 0.05, 0.05


def default_blueprint(centre: np.ndarray, radius_m: float, height_m: float, arms: list[str]) -> Any:
    """The recording's default layout: an object-centred 3-D view (eye 0.8 m from the envelope's centre on
    -y, 30 degrees up: the object in the middle, the arms in the frame while they survey it) with the arms,
    frustums, clouds and mesh but without the back-projected depth and IR of the room (table, walls) or the
    held-out error points (their own tab), and the images per arm beside it; the timeline paused at its start."""
    import rerun.blueprint as rrb

    c = np.asarray(centre, np.float64)
    reach = max(0.8, 10.0 * max(radius_m, height_m))
    eye = c + reach * np.array([0.0, -np.cos(np.radians(30.0)), np.sin(np.radians(30.0))])
    room = [f"- /world/{arm}/camera/{image}" for arm in arms for image in ("depth", "ir")]

    def view3d(name: str, hidden: list[str]) -> Any:
        return rrb.Spatial3DView(
            name=name, origin="/world", contents=["+ /world/**", *room, *hidden],
            eye_controls=rrb.EyeControls3D(position=eye.tolist(), look_target=c.tolist(), eye_up=[0.0, 0.0, 1.0]),
            line_grid=rrb.LineGrid3D(visible=False))

    main = rrb.Tabs(view3d("object", ["- /world/heldout"]),
                    view3d("held-out error", ["- /world/clouds/**"]), active_tab=0)
    images = [rrb.Tabs(*(rrb.Spatial2DView(name=f"{arm} {image}", origin=f"/world/{arm}/camera",
                                           contents=[f"$origin/{image}"]) for image in ("rgb", "depth", "ir")))
              for arm in arms]
    return rrb.Blueprint(rrb.Horizontal(main, rrb.Vertical(*images), column_shares=[3, 1]),
                         rrb.SelectionPanel(state="collapsed"), rrb.BlueprintPanel(state="collapsed"),
                         rrb.TimePanel(timeline="time", play_state="paused"))


def _processed_or_none(path: Path) -> ProcessedSurvey | None:
    if (path / "keyframes" / "keyframes.json").is_file():
        return find_processed(path)[0]
    if (path / "arm_poses.csv").is_file():
        return None
    found = find_processed(path)  # the output folder of several surveys: the first one
    if len(found) > 1:
        raise FormatError(f"{len(found)} processed surveys here: view one of them ({found[0].folder}, ...)", path)
    return found[0]


def _log_arms(rec: Any, rr: Any, survey: Survey, calibration: Calibration,
              image_times: dict[str, list[float]]) -> int:
    """Each arm at about ``ARM_RATE_HZ`` of its joint log and at every image's time (the joints interpolated
    there), so the frustum is on the wrist whenever an image is shown."""
    log = survey.arm_poses()
    rig = load_rig()
    n = 0
    for arm in log.arms:
        if arm not in calibration.arms:
            continue
        log_t, log_q = log.times(arm), log.joints(arm)
        rows = _arm_rows(log_t, ARM_RATE_HZ)
        times = np.union1d(log_t[rows], np.asarray(image_times.get(arm, []), np.float64))
        interp = interpolate_joints(log_t, log_q, times)
        times, q = times[interp.posed], interp.q_rad[interp.posed]
        log_arm_states(rec, rr, arm, times, q, calibration, rig)
        n += len(times)
    return n


def _log_processed(rec: Any, rr: Any, processed: ProcessedSurvey, stats: ViewStats,
                   pose: bool) -> dict[str, list[float]]:
    """Keyframes (their images; their poses too when ``pose``: no raw survey to move the arms), clouds, mesh,
    held-out errors and the summary. Returns each arm's image times."""
    times: dict[str, list[float]] = {}
    index = read_keyframe_index(processed.keyframes_dir)
    heldout = {info.file for info in index.select("heldout", None)}
    parts = []  # held-out keyframes' object points, from the one read of each keyframe
    for info in index.select(None, None):
        kf = read_keyframe(index.folder / info.file)
        rec.set_time("time", timestamp=kf.t_s)
        i = kf.intrinsics
        log_camera(rec, rr, kf.arm, kf.T_world_cam if pose else None, i.K, (i.width, i.height), kf.rgb, kf.depth,
                   1.0 / kf.depth_scale, kf.ir_left)
        times.setdefault(kf.arm, []).append(kf.t_s)
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
        summary = json.loads(read_utf8_text(results, "a JSON file", limit=LIMITS["json"])).get("heldout", {}).get(
            "aggregate", {})
        rec.log("summary", rr.TextDocument(json.dumps(summary, indent=1)), static=True)
    return times


def _log_raw_frames(rec: Any, rr: Any, survey: Survey, calibration: Calibration, every_s: float,
                    stats: ViewStats) -> dict[str, list[float]]:
    """Frame sets ``every_s`` apart with their images (the arm states carry the pose); each arm's times."""
    from darp.reconstruction.align import align_colour_to_depth, colour_to_rgb
    from darp.reconstruction.poses import recover_survey_poses

    poses = recover_survey_poses(survey, calibration)
    times: dict[str, list[float]] = {}
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
                log_camera(rec, rr, arm, None, d_intr.K, (d_intr.width, d_intr.height), rgb,
                           depth, 1.0 / recording.depth_scale, ir)
                times.setdefault(arm, []).append(float(traj.poses.t_s[k]))
                stats.images += 1
        finally:
            recording.close()
    return times


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


__all__ = ["ViewStats", "arm_columns", "default_blueprint", "log_arm_states", "log_camera", "rrd_entities", "view",
           "viewer_executable", "viewer_url"]
