"""Scripted twin survey: move the arms through waypoints while both cameras record, write the folder.

The sequence mirrors the paper's acquisition (Sec. III): the joint log starts first, then both
cameras record continuously; each arm in turn visits its waypoints (pausing ``dwell_s`` at each) and
returns to park while the other arm stays parked; then the cameras stop and, a little later, the log.
So the usable camera interval lies inside the joint log's interval and no pose needs extrapolation.

Output (built in ``<out>.partial/``, renamed to ``<out>`` only when complete; ``PARTIAL.txt`` is its first file
and is removed last, so a folder holding it is unfinished however the run ended, SIGKILL included; the finished
folder holds ``.darp-written``, without which ``--overwrite`` refuses to delete a folder)::

    cam<serial>.bag x2, arm_poses.csv, manip_envelope.json   the DARP survey folder
    truth/                                                  ground truth (darp.twin.truth)

``manip_envelope.json`` holds the object's TRUE envelope here (centre, radius, height), the park and
view configurations; the autonomous survey estimates it instead.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import TwinError
from darp.formats.arm_poses import read_arm_poses
from darp.formats.atomic import write_json_atomic
from darp.formats.envelope import ENVELOPE_FILE, Envelope, write_envelope
from darp.formats.survey import PARTIAL_FILE, WRITTEN_BY_FILE
from darp.kinematics.rig import Rig
from darp.twin.arm_sim import QuinticMove
from darp.twin.rig_backend import ContactEvent, TwinRig
from darp.twin.settings import TwinSettings
from darp.twin.truth import TRUTH_DIR, write_truth
from darp.twin.waypoints import WaypointPlan

LOG_LEAD_S = 0.5  # joint log runs this long before the cameras start
CAMERA_LEAD_S = 0.3  # cameras record this long before the first move
CAMERA_TAIL_S = 0.3  # ... and after the last arm is parked again
LOG_TAIL_S = 0.5  # joint log runs this long after the cameras stop
MOVE_TIMEOUT_S = 60.0
DEFAULT_STANDOFF_M = 0.35

ProgressFn = Callable[[float, float], None]  # (simulated seconds done, expected total)


@dataclass
class RecordResult:
    """What a recording produced."""

    folder: Path
    duration_s: float  # simulated seconds from the first log row to the last
    frames: dict[str, int]  # recorded depth frames per arm
    log_rows: dict[str, int]
    contact_events: list[ContactEvent] = field(default_factory=list)
    timings_s: dict[str, dict[str, float]] = field(default_factory=dict)


def expected_duration_s(plan: WaypointPlan, park: dict[str, np.ndarray], settings: TwinSettings) -> float:
    """Simulated length of a recording (for progress bars): moves, dwells, settling, leads and tails."""
    m = settings.motion
    total = LOG_LEAD_S + CAMERA_LEAD_S + CAMERA_TAIL_S + LOG_TAIL_S
    for arm_id in plan.order:
        q = park[arm_id]
        targets = [(w.q_rad, w.speed_rad_s, w.dwell_s) for w in plan.arms[arm_id]] + [(park[arm_id], None, 0.0)]
        for target, speed, dwell in targets:
            zero = np.zeros(6)
            move = QuinticMove.plan(0, q, zero, zero, target, speed or m.max_speed_rad_s, m.max_accel_rad_s2)
            total += move.duration_s + (m.settle_s if move.duration_s > 0 else 0.0) + dwell
            q = target
    return total


BYTES_PER_PIXEL = 7.3  # uncompressed bag bytes per pixel per frame: depth 2 + colour 3 + IR 2 (+ records)
SPACE_MARGIN_BYTES = 32 * 1024**2  # joint log, truth/, indexes


def estimated_bytes(plan: WaypointPlan, park: dict[str, np.ndarray], settings: TwinSettings) -> int:
    """About how many bytes a recording writes (both bags uncompressed: 0.74 MB per 424x240 frame set)."""
    c = settings.camera
    per_camera = expected_duration_s(plan, park, settings) * c.fps * c.width * c.height * BYTES_PER_PIXEL
    factor = 0.5 if c.compression == "lz4" else 1.0  # lz4 shrinks the twin's images about two- to threefold
    return int(factor * len(park) * per_camera) + SPACE_MARGIN_BYTES


def check_free_space(folder: Path, needed: int) -> None:
    """Refuse to start a recording that clearly cannot fit on the file system holding ``folder``."""
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if free < needed:
        raise TwinError(f"needs about {needed / 1e6:,.0f} MB, but {probe} has {free / 1e6:,.0f} MB free "
                        "(lower --fps, --resolution or the dwell times, or free some space)", folder)


def _check_overwritable(out: Path) -> None:
    """``--overwrite`` replaces only a folder darp wrote (it holds WRITTEN_BY_FILE)."""
    if not out.is_dir():
        raise TwinError("exists and is not a folder (refusing to replace it)", out)
    if any(out.iterdir()) and not (out / WRITTEN_BY_FILE).is_file():
        raise TwinError(f"is not a survey darp recorded (no {WRITTEN_BY_FILE} marker): refusing to delete it with "
                        "--overwrite; remove it yourself or choose another --out", out)


def _object_info(obj: Any, placement: Any, scale: float) -> dict[str, Any]:
    return {
        "name": obj.name,
        "source": getattr(obj, "source", "parametric"),
        "scale": scale,
        "T_world_object": np.asarray(placement.T_world_object).tolist(),
        "placement": {"x_m": placement.x_m, "y_m": placement.y_m, "yaw_rad": placement.yaw_rad,
                      "table_z_m": placement.table_z_m},
        "center_m": [placement.x_m, placement.y_m, placement.table_z_m + 0.5 * obj.height_m],
        "radius_m": obj.radius_m,
        "height_m": obj.height_m,
        "paper_radius_m": getattr(obj, "paper_radius_m", None),
        "paper_height_m": getattr(obj, "paper_height_m", None),
    }


def write_twin_truth(folder: str | Path, twin: TwinRig, obj: Any = None, placement: Any = None,
                     scale: float = 1.0) -> list[ContactEvent]:
    """Write ``folder/truth/`` of a twin run: true calibration, settings, camera poses, the object (object.json,
    object.ply; none for an empty table) and contacts.json. Returns the contact events."""
    object_info = mesh = None
    if obj is not None and placement is not None:
        from darp.twin.objects.model import to_world

        object_info, mesh = _object_info(obj, placement, scale), to_world(obj, placement)
    write_truth(folder, true_rig=twin.true_rig, settings=twin.settings,
                camera_poses={a: c.truth for a, c in twin.cameras.items()}, object_info=object_info,
                object_mesh_world=mesh)
    events = list(twin.contact_events)
    write_json_atomic(Path(folder) / TRUTH_DIR / "contacts.json", [
        {"time_s": e.time_s, "arm": e.contact.arm_id, "arm_geom": e.contact.arm_geom,
         "other": e.contact.other, "other_geom": e.contact.other_geom, "distance_m": e.contact.distance_m}
        for e in events])
    return events


def _run(twin: TwinRig, plan: WaypointPlan, folder: Path, progress: ProgressFn | None, total_s: float) -> None:
    clock = twin.clock

    def sleep(duration_s: float) -> None:
        clock.sleep(duration_s)
        if progress is not None:
            progress(clock.elapsed_ns / 1e9, total_s)

    def wait(arm_id: str) -> None:
        while twin.arms[arm_id].is_moving():
            if clock.elapsed_ns / 1e9 > MOVE_TIMEOUT_S + total_s:
                raise TwinError(f"{arm_id} did not stop moving")
            sleep(0.1)

    twin.start_joint_log(folder / "arm_poses.csv")
    sleep(LOG_LEAD_S)
    for camera in twin.cameras.values():
        camera.start_recording(folder / f"cam{camera.serial}.bag")
    sleep(CAMERA_LEAD_S)
    for arm_id in plan.order:
        arm = twin.arms[arm_id]
        for waypoint in plan.arms[arm_id]:
            arm.move_to(waypoint.q_rad, waypoint.speed_rad_s)
            wait(arm_id)
            if waypoint.dwell_s > 0:
                sleep(waypoint.dwell_s)
        arm.move_to(twin.park_q(arm_id))
        wait(arm_id)
    sleep(CAMERA_TAIL_S)
    for camera in twin.cameras.values():
        camera.stop_recording()
    sleep(LOG_TAIL_S)
    twin.stop_joint_log()


def record_survey(
    out: str | Path,
    plan: WaypointPlan,
    obj: Any,
    placement: Any,
    *,
    settings: TwinSettings | None = None,
    rig: Rig | None = None,
    scale: float = 1.0,
    standoff_m: float = DEFAULT_STANDOFF_M,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
    camera_workers: bool = False,
) -> RecordResult:
    """Record one twin survey of ``obj`` (a ``TwinObject``) at ``placement`` into folder ``out``.

    ``camera_workers`` renders each camera in its own subprocess: identical files, faster on 2+ cores.
    """
    out = Path(out)
    settings = settings if settings is not None else TwinSettings.from_profile("realistic")
    if out.exists() and not overwrite:
        raise TwinError("already exists (choose another --out or remove it)", out)
    if out.exists():
        _check_overwritable(out)
    partial = out.with_name(out.name + ".partial")
    if partial.exists():
        if not overwrite:  # whatever it holds (a user's files too), it is not this run's to delete
            raise TwinError("an unfinished recording is there (remove it, or give --overwrite to replace it)",
                            partial)
        if not (partial / PARTIAL_FILE).is_file():
            raise TwinError(f"exists but holds no {PARTIAL_FILE}: not an interrupted recording of darp's, refusing "
                            "to delete it", partial)
        shutil.rmtree(partial)
    partial.mkdir(parents=True)
    try:
        # The marker is the first file and the last removed: a folder holding it is unfinished, however the run
        # ended.
        (partial / PARTIAL_FILE).write_text("partial: darp twin record did not finish this survey (interrupted, "
                                            "killed or failed); delete the folder\n", encoding="utf-8")
        with TwinRig(settings, rig=rig, obj=obj, placement=placement, camera_workers=camera_workers) as twin:
            unknown = [a for a in plan.arms if a not in twin.arms]
            if unknown:
                raise TwinError(f"waypoints name unknown arm(s) {', '.join(unknown)} (rig: {', '.join(twin.arms)})")
            park = {a: twin.park_q(a) for a in twin.arms}
            check_free_space(partial, estimated_bytes(plan, park, settings))
            total = expected_duration_s(plan, park, settings)
            _run(twin, plan, partial, progress, total)
            envelope = Envelope(
                object_name=obj.name,
                center_m=(placement.x_m, placement.y_m, placement.table_z_m + 0.5 * obj.height_m),
                radius_m=obj.radius_m, height_m=obj.height_m, standoff_m=standoff_m,
                park_q_rad={a: tuple(float(v) for v in q) for a, q in park.items()},
                view_q_rad={a: [tuple(float(v) for v in w.q_rad) for w in wps] for a, wps in plan.arms.items()},
                extra={"source": "darp twin record: the object's true envelope"},
            )
            write_envelope(partial / ENVELOPE_FILE, envelope)
            events = write_twin_truth(partial, twin, obj, placement, scale)
            frames = {a: c.frames_recorded for a, c in twin.cameras.items()}
            timings = {a: dict(c.timings_s) for a, c in twin.cameras.items()}
        log = read_arm_poses(partial / "arm_poses.csv", known_arms=tuple(park))
        first, last = log.span()
        (partial / WRITTEN_BY_FILE).write_text("darp twin record\n", encoding="utf-8")
        if out.exists():
            shutil.rmtree(out)
        partial.rename(out)
        (out / PARTIAL_FILE).unlink()  # last: killed before this line, the survey still says it is partial
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return RecordResult(out, last - first, frames, {a: log.rows(a) for a in log.arms}, events, timings)


__all__ = ["RecordResult", "check_free_space", "estimated_bytes", "expected_duration_s", "record_survey",
           "write_twin_truth"]
