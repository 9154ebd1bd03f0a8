#!/usr/bin/env python3
"""The safety campaign: random twin surveys must touch nothing, invalid placements must be refused first.

**Valid surveys.** Survey ``i`` draws everything from ``numpy.random.default_rng([seed, i])``:

- the object: one of the paper's ten objects or a user mesh (a torus, a mushroom-like shape and an
  L-shape, written as PLY files and loaded like any user mesh, ``load_mesh_object``);
- its placement: centre uniform over the rig's whole placement workspace (edges included, no margin),
  yaw uniform; redrawn until :func:`darp.twin.placement.validate_placement` accepts it (the draws
  it refused are counted);
- the twin's seed (its true rig: joint-zero biases, hand-eye and base errors, noise), the viewpoint
  strategy (orbit or coverage, the latter with next best views) and the calibration the survey decides
  with (the twin's true one, or the rig's nominal one: the twin's true rig then differs from what the
  motion checks model by the profile's errors);
- drawn after those (so ``--profiles realistic --solved-share 0`` draws exactly what the campaigns before
  these two draws drew): the twin profile (``realistic`` or ``paper``, whose real-rig error levels put the
  live envelope mm to cm off) and, with probability ``--solved-share``, a third calibration kind,
  ``solved``: a calibration solved from simulated board images of the same twin (same profile and twin
  seed) by darp's own capture and solve code (``capture_twin``, ``solve_captures``; ``--calib-captures``
  per arm at the survey's resolution). A ``solved`` draw takes its twin seed from a pool of
  ``--solved-pool`` seeds per profile, so the campaign solves at most pool x profiles calibrations; each is
  solved once and cached in ``--out/calibrations/<profile>_seed<twin seed>/``.

Each survey runs the whole acquisition (localise, confirm, plan, record both cameras, verify; no
processing) on the cheapest camera the twin offers (424x240 depth and colour at 6 fps, no IMU). The
contacts are the twin's collision monitor's (:attr:`TwinRig.contact_events`: whenever an arm moves,
the moving arms' true geometry against the table, the object and the other arm, at
``collision_check_hz``, 60 Hz; the first one stops both arms and latches a fault) and, independently, a
dense check at ``--dense-hz`` (1 kHz simulated, while any arm moves; it only records) that a shallow
contact entered and left between two of the monitor's ticks cannot slip through. ``--self-check``
first drives arm110 through a cup outside any check and refuses to run unless both count it.

**Invalid placements.** ``--invalid`` draws per kind (non-finite, off the table, inside a robot base,
against a robot (closer than the clearance), outside the workspace, too tall) go through the real
command line (``darp collect NAME --twin --placement=X,Y,YAW``): each must exit 2 with a one-line
``darp: error:`` message, leave no episode folder and send no joint command (every ``SimArm.move_to``
and ``TwinRig`` construction in the process is counted).

Prints one line per survey and a summary; ``--json`` writes every row.

    MUJOCO_GL=egl .venv/bin/python studies/safety.py [--surveys 100] [--invalid 3] [--seed 0]
        [--start 0] [--fps 6] [--resolution 424x240] [--profiles realistic,paper] [--solved-share 0.333]
        [--solved-pool 4] [--calib-captures 12] [--json safety.json] [--out DIR] [--self-check]
        [--dense-hz 1000] [--resume]

``--resume`` keeps the rows already in ``--json`` and goes on with the next survey (a campaign cut
short, or split over sessions, adds up to the same draws).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np

USER_MESHES = ("torus", "mushroom", "l_shape")
INVALID_KINDS = ("non_finite", "off_table", "inside_base", "against_robot", "outside_workspace", "too_tall")


# -- objects ------------------------------------------------------------------------------------------------
def write_user_meshes(folder: Path) -> dict[str, Path]:
    """A torus, a mushroom-like shape and an L-shape (metres, z up) as PLY files in ``folder``."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    torus = trimesh.creation.torus(major_radius=0.055, minor_radius=0.02, major_sections=48, minor_sections=24)
    stem = trimesh.creation.cylinder(radius=0.018, height=0.06, sections=32)
    stem.apply_translation([0.0, 0.0, 0.03])
    cap = trimesh.creation.icosphere(subdivisions=3, radius=0.055)
    cap.vertices[:, 2] = np.maximum(cap.vertices[:, 2], 0.0) * 0.6  # a flattened dome
    cap.apply_translation([0.0, 0.0, 0.055])
    mushroom = trimesh.util.concatenate([stem, cap])
    foot = trimesh.creation.box([0.14, 0.05, 0.03])
    foot.apply_translation([0.0, 0.0, 0.015])
    upright = trimesh.creation.box([0.04, 0.05, 0.12])
    upright.apply_translation([-0.05, 0.0, 0.06])
    l_shape = trimesh.util.concatenate([foot, upright])
    out = {}
    for name, mesh in (("torus", torus), ("mushroom", mushroom), ("l_shape", l_shape)):
        out[name] = folder / f"{name}.ply"
        mesh.export(out[name])
    return out


def load(name: str, meshes: dict[str, Path], scale: float = 1.0) -> Any:
    from darp.twin.objects.model import load_mesh_object, make_object

    if name in meshes:
        return load_mesh_object(meshes[name], scale=scale)
    return make_object(name, scale=scale)


# -- valid surveys ------------------------------------------------------------------------------------------
def solved_pool_seed(seed: int, profile: str, k: int) -> int:
    """The ``k``-th twin seed of the ``solved`` draws' pool for ``profile`` in campaign ``seed``."""
    from darp.twin.settings import PROFILES

    return int(np.random.default_rng([seed, 0xCA1B, PROFILES.index(profile), k]).integers(2**31))


def draw_valid(i: int, seed: int, objects: list[str], meshes: dict[str, Path], rig: Any, *,
               profiles: tuple[str, ...] = ("realistic",), solved_share: float = 0.0, solved_pool: int = 4
               ) -> dict[str, Any]:
    """Survey ``i``'s draws (see the module docstring); the defaults draw what campaigns before the profile and
    ``solved`` draws drew."""
    from darp.errors import TwinError
    from darp.twin.objects.model import ObjectPlacement
    from darp.twin.placement import validate_placement

    rng = np.random.default_rng([seed, i])
    name = str(objects[int(rng.integers(len(objects)))])
    obj = load(name, meshes)
    ws, refused = rig.workspace, 0
    for _ in range(10_000):
        x = float(rng.uniform(*ws.x_range_m))
        y = float(rng.uniform(*ws.y_range_m))
        yaw = float(rng.uniform(-math.pi, math.pi))
        try:
            validate_placement(rig, obj.radius_m, obj.height_m, ObjectPlacement(x, y, yaw, rig.table.height_m))
            break
        except TwinError:
            refused += 1
    else:
        raise SystemExit(f"survey {i}: no valid placement of {name} in 10000 draws")
    row = {"index": i, "object": name, "x_m": round(x, 4), "y_m": round(y, 4), "yaw_deg": round(math.degrees(yaw), 2),
           "refused_draws": refused, "twin_seed": int(rng.integers(2**31)),
           "viewpoints": ("orbit", "coverage")[int(rng.integers(2))],
           "calibration": ("truth", "nominal")[int(rng.integers(2))]}
    # drawn after the draws above, always, so that those stay what they were
    profile = profiles[int(rng.integers(len(profiles)))]
    k, solved = int(rng.integers(max(1, solved_pool))), bool(rng.random() < solved_share)
    row["profile"] = profile
    if solved:
        row.update(calibration="solved", twin_seed=solved_pool_seed(seed, profile, k))
    return row


def contacts_of(twin: Any) -> dict[str, Any]:
    """What the twin's collision monitor recorded: samples (recorded and dropped), the arms and what they hit."""
    events = list(twin.contact_events)
    first = events[0] if events else None
    fault = twin.fault()
    return {"contacts": len(events) + int(twin.contacts_dropped),
            "contact_pairs": sorted({f"{e.contact.arm_id}:{e.contact.arm_geom}->{e.contact.other}:"
                                     f"{e.contact.other_geom}" for e in events}),
            "first_contact": None if first is None else {
                "time_s": first.time_s, "arm": first.contact.arm_id, "arm_geom": first.contact.arm_geom,
                "other": first.contact.other, "other_geom": first.contact.other_geom,
                "depth_mm": round(-first.contact.distance_m * 1000, 2)},
            "fault": None if fault is None else fault.message}


def add_dense_check(twin: Any, hz: float = 1000.0) -> dict[str, Any]:
    """A second, independent contact check at ``hz`` (simulated) while any arm moves: the twin's monitor samples
    at 60 Hz, so a shallow contact entered and left between two of its ticks would go unseen. Records
    only (it never stops an arm); returns the record it fills (samples checked, samples in contact, first)."""
    record: dict[str, Any] = {"dense_hz": hz, "dense_samples": 0, "dense_contacts": 0, "dense_first": None}
    period_ns = max(1, round(1e9 / hz))

    def tick(now_ns: int) -> int:
        moving = {a for a, arm in twin.arms.items() if arm.is_moving()}
        if moving:
            record["dense_samples"] += 1
            found = [c for c in twin.contacts() if c.arm_id in moving or c.other in moving]
            if found:
                record["dense_contacts"] += 1
                if record["dense_first"] is None:
                    c = found[0]
                    record["dense_first"] = {"time_s": twin.clock.host_time_s(now_ns), "arm": c.arm_id,
                                             "arm_geom": c.arm_geom, "other": c.other, "other_geom": c.other_geom,
                                             "depth_mm": round(-c.distance_m * 1000, 2)}
        return now_ns + period_ns

    twin.clock.add_process("dense-contact-check", tick, first_due_ns=twin.clock.elapsed_ns)
    return record


def calibration_gap(cal: Any, truth: Any) -> dict[str, float]:
    """How far a calibration is from the twin's true one: the largest base and hand-eye translation
    differences (mm) and joint-offset difference (deg) over the arms."""
    base = max(float(np.linalg.norm(cal.arms[a].T_world_base[:3, 3] - truth.arms[a].T_world_base[:3, 3]))
               for a in truth.arms)
    hand_eye = max(float(np.linalg.norm(cal.arms[a].T_wrist_cam[:3, 3] - truth.arms[a].T_wrist_cam[:3, 3]))
                   for a in truth.arms)
    dq = max(float(np.max(np.abs(np.asarray(cal.arms[a].joint_offsets_rad) - truth.arms[a].joint_offsets_rad)))
             for a in truth.arms)
    return {"base_mm": round(1e3 * base, 3), "hand_eye_mm": round(1e3 * hand_eye, 3),
            "joint_offset_deg": round(math.degrees(dq), 4)}


def solved_calibration(out: Path, profile: str, twin_seed: int, *, captures: int = 12,
                       size: tuple[int, int] = (424, 240)) -> tuple[Any, dict[str, Any]]:
    """The calibration solved from simulated board images of the twin (``profile``, ``twin_seed``) by darp's
    own capture and solve code, and what the solve reported; cached in ``out/calibrations/<profile>_seed<seed>/``
    (``calibration.json`` and ``solve.json``; the capture images are deleted once solved)."""
    from darp.calibration.captures import read_captures
    from darp.calibration.solve import SolveSettings, solve_captures
    from darp.formats.atomic import write_json_atomic
    from darp.formats.calibration import read_calibration, write_calibration
    from darp.twin.calib_capture import capture_twin

    folder = out / "calibrations" / f"{profile}_seed{twin_seed}"
    path, info_path = folder / "calibration.json", folder / "solve.json"
    if path.is_file() and info_path.is_file():
        return read_calibration(path), {**json.loads(info_path.read_text()), "cached": True}
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        capture_twin(folder / "captures", seed=twin_seed, profile=profile, n_per_arm=captures, resolution=size,
                     overwrite=True)
    caps = read_captures(folder / "captures")
    truth_path = caps.truth_calibration_path()
    assert truth_path is not None
    truth = read_calibration(truth_path)
    outcome = solve_captures(caps, SolveSettings(folds=0, compare=False, epoch=f"safety-{profile}-seed{twin_seed}"))
    cal = outcome.calibration
    info = {"profile": profile, "twin_seed": twin_seed, "captures_per_arm": captures, "resolution": list(size),
            "n_used": cal.report["n_used"], "n_captures": cal.report["n_captures"],
            "fit_px_median": {a: round(c.residuals["fit_reprojection_px"]["median"], 3) for a, c in cal.arms.items()},
            "gap_to_truth": calibration_gap(cal, truth), "wall_s": round(time.perf_counter() - t0, 1)}
    write_calibration(path, cal)
    write_json_atomic(info_path, info)
    shutil.rmtree(folder / "captures", ignore_errors=True)
    return cal, {**info, "cached": False}


def run_valid(draw: dict[str, Any], meshes: dict[str, Path], out: Path, *, fps: int, size: tuple[int, int],
              keep: bool, dense_hz: float = 1000.0, calib_captures: int = 12) -> dict[str, Any]:
    """One survey on a fresh twin (profile ``draw["profile"]``, realistic when absent); the row of the table."""
    from darp.acquisition.episode import read_events
    from darp.acquisition.survey import SurveySettings, run_survey
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import ObjectPlacement
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings

    rig = load_rig()
    obj = load(draw["object"], meshes)
    place = ObjectPlacement(draw["x_m"], draw["y_m"], math.radians(draw["yaw_deg"]), rig.table.height_m)
    profile = draw.get("profile", "realistic")
    settings = TwinSettings.from_profile(profile, seed=draw["twin_seed"]).with_camera(
        width=size[0], height=size[1], fps=fps, imu=False)
    name = f"s{draw['index']:04d}_{draw['object']}"
    row: dict[str, Any] = dict(draw)
    solved = None
    if draw["calibration"] == "solved":  # before the clock starts: solved once per (profile, seed), then cached
        from darp.errors import DarpError

        try:
            solved, row["solve"] = solved_calibration(out, profile, draw["twin_seed"], captures=calib_captures,
                                                      size=size)
        except DarpError as err:  # no survey without its calibration; a row that says why
            row.update(status="error", reason="calibration_failed", message=str(err)[:300], planned_views={},
                       executed_views={}, contacts=0, contact_pairs=[], first_contact=None, fault=None,
                       sim_s=0.0, wall_s=0.0, cpu_s=0.0)
            return row
    t0, cpu0 = time.perf_counter(), time.process_time()
    with TwinRig(settings, rig=rig, obj=obj, placement=place) as twin:
        dense = add_dense_check(twin, dense_hz) if dense_hz > 0 else {}
        truth = twin.true_rig.calibration(settings)
        cal = {"truth": truth, "nominal": None, "solved": solved}[draw["calibration"]]
        row["calibration_gap"] = calibration_gap(rig.nominal_calibration() if cal is None else cal, truth)
        try:
            outcome = run_survey(twin, rig, out, name, calibration=cal, overwrite=True, object_name=obj.name,
                                 settings=SurveySettings(viewpoint_strategy=draw["viewpoints"]))
            row.update(status=outcome.status, reason=outcome.reason, message=outcome.message[:300])
            row["planned_views"] = {a: len(p.views) for a, p in outcome.plans.items()}
            executed = dict.fromkeys(rig.arm_ids, 0)
            for e in read_events(outcome.folder):
                if e["kind"] in ("view_reached", "next_best_view"):
                    executed[e["arm"]] += 1
            row["executed_views"] = executed
            folder = outcome.folder
        except Exception as err:  # an error is a result here, not the end of the campaign
            row.update(status="error", reason=type(err).__name__, message=str(err)[:300], planned_views={},
                       executed_views={})
            folder = None
        row.update(contacts_of(twin))
        row.update(dense)
        row["sim_s"] = round(twin.clock.now() - settings.timing.start_time_s, 2)
    row["wall_s"] = round(time.perf_counter() - t0, 2)
    row["cpu_s"] = round(time.process_time() - cpu0, 2)  # this process's CPU: wall time on a shared machine is not
    if not keep and folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
    return row


# -- invalid placements -------------------------------------------------------------------------------------
def classify(message: str) -> str:
    """The kind of a placement refusal from its message."""
    if "must be finite" in message or "expected finite" in message:
        return "non_finite"
    if "not on the table" in message:
        return "off_table"
    if "is inside" in message:
        return "inside_base" if "base" in message else "inside_robot"
    if "mm from" in message:
        return "against_robot"
    if "outside the reachable workspace" in message:
        return "outside_workspace"
    if "taller than" in message:
        return "too_tall"
    return "other"


def draw_invalid(kind: str, j: int, seed: int, objects: list[str], meshes: dict[str, Path], rig: Any
                 ) -> dict[str, Any]:
    """The ``j``-th random placement of ``kind`` (object, x, y, yaw in degrees, scale), checked to be refused as
    that kind by :func:`validate_placement` (so the draw is of the kind it claims)."""
    from darp.errors import TwinError
    from darp.twin.objects.model import ObjectPlacement
    from darp.twin.placement import validate_placement

    rng = np.random.default_rng([seed, 0x5AFE, INVALID_KINDS.index(kind), j])
    t, ws = rig.table, rig.workspace
    for _ in range(10_000):
        name = str(objects[int(rng.integers(len(objects)))])
        scale = 1.0
        yaw = float(rng.uniform(-180.0, 180.0))
        if kind == "too_tall":
            name, scale = "cup", round(float(rng.uniform(3.0, 3.5)), 3)  # 305-356 mm tall
        obj = load(name, meshes, scale)
        r = obj.radius_m
        base = rig.arms[rig.arm_ids[j % 2]].T_world_base[:3, 3]  # each robot in turn
        if kind == "non_finite":
            x, y = float(rng.uniform(*ws.x_range_m)), float(rng.uniform(*ws.y_range_m))
            values = [x, y, yaw]
            values[int(rng.integers(3))] = float(rng.choice([math.nan, math.inf, -math.inf]))
            x, y, yaw = values
        elif kind == "off_table":
            side = int(rng.integers(4))
            x, y = float(rng.uniform(*ws.x_range_m)), float(rng.uniform(*ws.y_range_m))
            if side < 2:
                y = float(rng.choice([-1, 1]) * rng.uniform(t.y_range_m[1] - r + 1e-3, t.y_range_m[1] + 0.3))
            else:
                x = float(rng.choice([-1, 1]) * rng.uniform(t.x_range_m[1] - r + 1e-3, t.x_range_m[1] + 0.3))
        elif kind == "inside_base":
            x, y = float(base[0] + rng.uniform(-0.05, 0.05)), float(base[1] + rng.uniform(-0.05, 0.05))
        elif kind == "against_robot":
            d = float(rng.uniform(0.05, 0.45))
            angle = float(rng.uniform(-math.pi, math.pi))
            x, y = float(base[0] + d * math.cos(angle)), float(base[1] + d * math.sin(angle))
        elif kind == "outside_workspace":
            x = float(rng.uniform(t.x_range_m[0] + r, t.x_range_m[1] - r))
            y = float(rng.uniform(t.y_range_m[0] + r, t.y_range_m[1] - r))
        else:  # too_tall
            x, y = float(rng.uniform(-0.1, 0.1)), float(rng.uniform(-0.1, 0.1))
        try:
            validate_placement(rig, r, obj.height_m, ObjectPlacement(x, y, math.radians(yaw), t.height_m))
        except TwinError as err:
            if classify(str(err)) == kind or (kind == "inside_base" and classify(str(err)) == "inside_robot"):
                return {"kind": kind, "index": j, "object": name, "scale": scale, "x_m": x, "y_m": y, "yaw_deg": yaw}
    raise SystemExit(f"no {kind} placement drawn in 10000 tries")


@contextlib.contextmanager
def counting_motion() -> Iterator[dict[str, int]]:
    """Count every joint command (``SimArm.move_to``) and every twin built (a ``TwinRig.__init__`` that returned)."""
    from darp.twin.arm_sim import SimArm
    from darp.twin.rig_backend import TwinRig

    counts = {"move_to": 0, "twins": 0}
    move_to, init = SimArm.move_to, TwinRig.__init__

    def counted_move(self: Any, *args: Any, **kwargs: Any) -> Any:
        counts["move_to"] += 1
        return move_to(self, *args, **kwargs)

    def counted_init(self: Any, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        counts["twins"] += 1  # built (a placement refused in the constructor builds nothing)

    SimArm.move_to, TwinRig.__init__ = counted_move, counted_init  # type: ignore[method-assign]
    try:
        yield counts
    finally:
        SimArm.move_to, TwinRig.__init__ = move_to, init  # type: ignore[method-assign]


def run_invalid(draw: dict[str, Any], meshes: dict[str, Path], out: Path) -> dict[str, Any]:
    """``darp collect`` on the invalid placement, as a child process (this script's ``--counted-darp``, which
    counts every joint command and twin built in it): exit code, message, folders, joint commands."""
    obj = str(meshes[draw["object"]]) if draw["object"] in meshes else draw["object"]
    where = out / f"invalid_{draw['kind']}_{draw['index']}"
    where.mkdir(parents=True, exist_ok=True)
    counts_file = out / f"invalid_{draw['kind']}_{draw['index']}.counts.json"  # beside the folder it checks
    argv = ["collect", "s", "--twin", "--object", obj, "--scale", str(draw["scale"]),
            f"--placement={draw['x_m']!r},{draw['y_m']!r},{draw['yaw_deg']!r}", "--out", str(where),
            "--fps", "6", "--resolution", "424x240", "--quiet"]
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, __file__, "--counted-darp", str(counts_file), *argv],
                          capture_output=True, text=True, check=False)
    code, message = done.returncode, done.stderr.strip()
    counts = json.loads(counts_file.read_text())
    counts_file.unlink()
    folders = sorted(p.name for p in where.iterdir())
    shutil.rmtree(where, ignore_errors=True)
    refused = (code == 2 and message.startswith("darp: error:") and "\n" not in message and not folders
               and counts["move_to"] == 0 and counts["twins"] == 0)
    return {**draw, "exit": code, "message": message, "folders": folders, "joint_commands": counts["move_to"],
            "twins_built": counts["twins"], "refused_before_motion": refused,
            "wall_s": round(time.perf_counter() - t0, 2)}


def counted_darp(counts_file: Path, argv: list[str]) -> int:
    """Child entry: the ``darp`` command on ``argv`` with every joint command and twin built counted into
    ``counts_file`` (JSON), however the command ends."""
    from darp.__main__ import main as darp_main

    sys.argv = ["darp", *argv]
    code: int | str | None = 0
    with counting_motion() as counts:
        try:
            darp_main()
        except SystemExit as end:
            code = end.code
        finally:
            counts_file.write_text(json.dumps(counts))
    return code if isinstance(code, int) else 1


# -- the self-check -----------------------------------------------------------------------------------------
def self_check(fps: int, size: tuple[int, int]) -> dict[str, Any]:
    """Drive arm110 through a cup outside any motion check: the monitor must count it and latch a fault, and the
    dense check must count it too."""
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import ObjectPlacement, make_object
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings

    rig = load_rig()
    settings = TwinSettings.from_profile("ideal", seed=5).with_camera(width=size[0], height=size[1], fps=fps, imu=False)
    with TwinRig(settings, rig=rig, obj=make_object("cup"), placement=ObjectPlacement(-0.2, 0.0, 0.0)) as twin:
        dense = add_dense_check(twin)
        twin.arms["arm110"].move_to(np.array([0.0, 2.4, -1.5, 0.0, 0.0, 0.0]))
        twin.wait_until_still("arm110", timeout_s=20.0)
        return {**contacts_of(twin), **dense}


# -- report -------------------------------------------------------------------------------------------------
def summary(valid: list[dict[str, Any]], invalid: list[dict[str, Any]]) -> dict[str, Any]:
    n = len(valid)
    by_status: dict[str, int] = {}
    for r in valid:
        key = r["status"] if r["status"] == "accepted" else f"{r['status']}:{r['reason']}"
        by_status[key] = by_status.get(key, 0) + 1
    wall = [r["wall_s"] for r in valid]
    draws: dict[str, int] = {}
    for r in valid:
        key = f"{r.get('profile', 'realistic')}/{r['calibration']}"
        draws[key] = draws.get(key, 0) + 1
    return {"surveys": n, "outcomes": by_status, "draws": draws,
            "surveys_with_contacts": sum(1 for r in valid if r["contacts"]),
            "contact_samples": sum(r["contacts"] for r in valid),
            "dense_checked_surveys": sum(1 for r in valid if "dense_samples" in r),
            "dense_contact_samples": sum(r.get("dense_contacts", 0) for r in valid),
            "dense_samples": sum(r.get("dense_samples", 0) for r in valid),
            "views_executed": sum(sum(r["executed_views"].values()) for r in valid),
            "wall_s_mean": float(np.mean(wall)) if wall else math.nan,
            "wall_s_total": float(np.sum(wall)) if wall else 0.0,
            "invalid": len(invalid), "invalid_refused_before_motion": sum(r["refused_before_motion"] for r in invalid),
            "invalid_by_kind": {k: [sum(r["refused_before_motion"] for r in invalid if r["kind"] == k),
                                    sum(1 for r in invalid if r["kind"] == k)] for k in INVALID_KINDS}}


def valid_line(r: dict[str, Any]) -> str:
    views = "/".join(f"{r['executed_views'].get(a, 0)}of{n}" for a, n in r["planned_views"].items()) or "-"
    status = r["status"] if r["status"] == "accepted" else f"{r['status']}({r['reason']})"
    return (f"{r['index']:4d} {r['object']:14s} ({r['x_m']:+.3f},{r['y_m']:+.3f}) {r['yaw_deg']:+7.1f}deg "
            f"{r['viewpoints']:8s} {r.get('profile', 'realistic'):9s} {r['calibration']:7s} {status:28s} "
            f"views {views:12s} "
            f"contacts {r['contacts']:3d}/{r.get('dense_contacts', '-')} "
            f"{r['wall_s']:6.1f} s")


def write_json(path: Path | None, args: argparse.Namespace, valid: list[dict[str, Any]],
               invalid: list[dict[str, Any]], check: dict[str, Any] | None) -> None:
    if path is None:
        return
    from darp.formats.atomic import write_json_atomic

    write_json_atomic(path, {"settings": {k: str(v) for k, v in vars(args).items()}, "self_check": check,
                             "summary": summary(valid, invalid), "valid": valid, "invalid": invalid})


def main(argv: list[str] | None = None) -> int:
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import OBJECT_NAMES

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--surveys", type=int, default=100, help="valid random surveys")
    p.add_argument("--start", type=int, default=0, help="index of the first survey (to resume or split a campaign)")
    p.add_argument("--invalid", type=int, default=3, help="invalid placements per kind")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--objects", default="all", help="comma-separated paper objects and torus,mushroom,l_shape")
    p.add_argument("--fps", type=int, default=6)
    p.add_argument("--resolution", default="424x240")
    p.add_argument("--profiles", default="realistic,paper", help="twin profiles drawn from (comma-separated)")
    p.add_argument("--profile", default=None, help="one profile only (same as --profiles NAME)")
    p.add_argument("--solved-share", type=float, default=1 / 3,
                   help="share of surveys with a calibration solved from the twin's board images (0: none)")
    p.add_argument("--solved-pool", type=int, default=4, help="twin seeds per profile for the solved draws")
    p.add_argument("--calib-captures", type=int, default=12, help="board captures per arm for a solved calibration")
    p.add_argument("--out", type=Path, default=None, help="where surveys are written (default: a temp folder)")
    p.add_argument("--keep", action="store_true", help="keep the survey folders")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--dense-hz", type=float, default=1000.0, help="the independent contact check's rate (0: off)")
    p.add_argument("--resume", action="store_true", help="keep the rows already in --json and go on after them")
    p.add_argument("--self-check", action="store_true", help="first show that a colliding move is counted")
    args = p.parse_args(argv)
    size = tuple(int(v) for v in args.resolution.lower().split("x"))
    profiles = (args.profile,) if args.profile else tuple(args.profiles.split(","))
    objects = list(OBJECT_NAMES) + list(USER_MESHES) if args.objects == "all" else args.objects.split(",")
    out = args.out or Path(tempfile.mkdtemp(prefix="darp-safety-"))
    meshes = write_user_meshes(out / "meshes")
    rig = load_rig()
    check, valid, invalid = None, [], []
    if args.resume and args.json is not None and args.json.is_file():
        prior = json.loads(args.json.read_text())
        check, valid, invalid = prior["self_check"], prior["valid"], prior["invalid"]
        args.start = max((r["index"] for r in valid), default=args.start - 1) + 1
        print(f"resuming after {len(valid)} surveys and {len(invalid)} invalid placements, at survey {args.start}")
    if args.self_check and check is None:
        check = self_check(args.fps, size)  # type: ignore[arg-type]
        print(f"self-check (arm110 driven through a cup, no checks): {check['contacts']} contact samples, "
              f"dense check {check['dense_contacts']} samples, fault: {check['fault']}")
        if not check["contacts"] or not check["dense_contacts"] or check["fault"] is None:
            print("the collision monitor did not count a deliberate collision: refusing to run", file=sys.stderr)
            return 1
    per_kind = 0 if invalid else args.invalid  # resumed: the invalid placements were run already
    for kind in INVALID_KINDS:
        for j in range(per_kind):
            r = run_invalid(draw_invalid(kind, j, args.seed, objects, meshes, rig), meshes, out)
            invalid.append(r)
            print(f"invalid {kind:18s} {r['object']:14s} ({r['x_m']:+.3f},{r['y_m']:+.3f}) exit {r['exit']} "
                  f"commands {r['joint_commands']} {'REFUSED' if r['refused_before_motion'] else 'NOT REFUSED'}: "
                  f"{r['message'][:150]}", flush=True)
    t0, first = time.perf_counter(), len(valid)
    for i in range(args.start, args.start + args.surveys - first):
        draw = draw_valid(i, args.seed, objects, meshes, rig, profiles=profiles, solved_share=args.solved_share,
                          solved_pool=args.solved_pool)
        row = run_valid(draw, meshes, out, fps=args.fps, size=size, keep=args.keep,  # type: ignore[arg-type]
                        dense_hz=args.dense_hz, calib_captures=args.calib_captures)
        valid.append(row)
        print(f"[{len(valid)}/{args.surveys} {time.perf_counter() - t0:6.0f} s] {valid_line(row)}", flush=True)
        if row["contacts"] or row.get("dense_contacts"):
            print(f"      CONTACT: {row['first_contact']}; dense: {row.get('dense_first')}; fault: {row['fault']}",
                  flush=True)
        write_json(args.json, args, valid, invalid, check)  # after every survey: a cut-short campaign keeps its rows
    s = summary(valid, invalid)
    write_json(args.json, args, valid, invalid, check)
    print(f"\n== {s['surveys']} valid surveys ({','.join(profiles)}, {args.resolution} at {args.fps} fps, "
          f"seed {args.seed})")
    print(f"draws: {json.dumps(s['draws'])}")
    print(f"outcomes: {json.dumps(s['outcomes'])}")
    print(f"contacts during motion: {s['contact_samples']} samples in {s['surveys_with_contacts']} surveys "
          f"(target 0); views executed: {s['views_executed']}")
    print(f"dense check ({args.dense_hz:g} Hz while moving, {s['dense_checked_surveys']} surveys, "
          f"{s['dense_samples']} samples): "
          f"{s['dense_contact_samples']} samples in contact (target 0)")
    print(f"wall time per survey: mean {s['wall_s_mean']:.1f} s, total {s['wall_s_total']:.0f} s")
    print(f"invalid placements refused before motion with exit 2: {s['invalid_refused_before_motion']}/{s['invalid']} "
          + ", ".join(f"{k} {a}/{b}" for k, (a, b) in s["invalid_by_kind"].items()))
    ok = (s["contact_samples"] == 0 and s["dense_contact_samples"] == 0
          and s["invalid_refused_before_motion"] == s["invalid"])
    return 0 if ok else 1


if __name__ == "__main__":
    if sys.argv[1:2] == ["--counted-darp"]:
        raise SystemExit(counted_darp(Path(sys.argv[2]), sys.argv[3:]))
    raise SystemExit(main())
