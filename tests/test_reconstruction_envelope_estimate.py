"""The object envelope estimated from a survey whose manip_envelope.json has no geometry: the pieces on
exact synthetic depth (Open3D ray casting as the oracle), then ``darp process`` on twin surveys with the
geometry stripped (the DARP release's Red Bull case) and on a survey with nothing above the table."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import open3d as o3d
import pytest

from darp.cli._app import run
from darp.errors import ReconstructionError
from darp.formats.envelope import Envelope
from darp.formats.survey import open_survey
from darp.processing.job import SurveyJob
from darp.reconstruction.backproject import PosedDepth
from darp.reconstruction.envelope_estimate import (
    EnvelopeEstimate,
    EnvelopeEstimateSettings,
    envelope_from_frames,
    object_cluster,
    robust_look_at,
    search_region,
    still_view_poses,
)
from darp.reconstruction.keyframes import look_at_point
from darp.reconstruction.voxel_stats import frame_stats, merge_stats
from darp.twin.truth import read_truth
from helpers.synthetic_depth import Scene, add_depth_noise, box, look_at, orbit_poses, small_intrinsics, table, to_z16
from helpers.twin_surveys import record_tiny_survey

INTR = small_intrinsics(320, 240, 380.0)  # the D435's pixel footprint, a smaller field of view
BASES_XY = [np.array([-0.6993, 0.0]), np.array([0.6993, 0.0])]
TABLE_Z = 0.002  # the table 2 mm above the world's z = 0: a calibration slightly off in z


# -- synthetic scenes ------------------------------------------------------------------------------------
def mug_like(centre_xy=(0.02, -0.01)) -> o3d.geometry.TriangleMesh:
    """A cylinder (r 35 mm, h 80 mm) with a thin handle sticking out to 55 mm along +y, on the table."""
    body = o3d.geometry.TriangleMesh.create_cylinder(0.035, 0.08, 120, 8)
    body.translate((centre_xy[0], centre_xy[1], TABLE_Z + 0.04))
    handle = box((0.012, 0.022, 0.05), (centre_xy[0] - 0.006, centre_xy[1] + 0.033, TABLE_Z + 0.015))
    return body + handle


def render_frames(meshes, centre, seed: int = 3) -> list[PosedDepth]:
    """Noisy depth of two arms orbiting ``centre`` from opposite sides (five views each, two frames a view)."""
    scene = Scene([*meshes, table(1.2, TABLE_Z)])
    rng = np.random.default_rng(seed)
    frames = []
    for arm, start in (("arm110", 110.0), ("arm111", -70.0)):
        for k, T in enumerate(orbit_poses(centre, 0.35, (35.0, 60.0), np.linspace(start, start + 140.0, 3))):
            exact = scene.render(T, INTR)[0]
            for draw in range(2):
                depth = to_z16(add_depth_noise(exact, rng, fx=INTR.fx))
                frames.append(PosedDepth(arm, 2 * k + draw, depth, 0.001, INTR, T))
    return frames


def true_cylinder(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, float, float]:
    """Smallest enclosing circle of the mesh seen from above, and its top above the table."""
    v = np.asarray(mesh.vertices)
    (cx, cy), r = cv2.minEnclosingCircle(v[:, :2].astype(np.float32))
    return np.array([cx, cy]), float(r), float(v[:, 2].max()) - TABLE_Z


# -- the pieces ----------------------------------------------------------------------------------------------
def test_look_at_ignores_axes_that_look_elsewhere() -> None:
    centre = np.array([0.03, -0.02, 0.05])
    views = orbit_poses(centre, 0.35, (30.0, 55.0), np.linspace(0.0, 300.0, 6))
    parks = [look_at((-0.7, 0.0, 0.41), (-0.09, 0.0, 0.0)), look_at((0.7, 0.0, 0.41), (0.09, 0.0, 0.0))]
    away = [look_at((0.0, 0.3, 0.3), (0.0, 0.8, 0.3))]  # the object behind the camera
    T = np.array([*views, *parks, *away])
    point, inliers = robust_look_at(T)
    assert np.linalg.norm(point - centre) < 1e-6
    assert inliers.tolist() == [True] * len(views) + [False] * 3
    assert np.linalg.norm(look_at_point(T) - centre) > 0.005  # plain least squares is pulled away


def test_still_views_are_one_pose_per_still_run_and_repeats_count_once() -> None:
    a, b = look_at((0.3, 0.0, 0.2), (0, 0, 0)), look_at((0.0, 0.3, 0.2), (0, 0, 0))
    t = np.arange(40) * 0.1
    # still at a (1 s), moving, still at b, moving, still at a again (the same pose: counts once)
    runs = [(0, 10, a), (15, 25, b), (30, 40, a)]
    T = np.repeat(look_at((0.2, 0.2, 0.3), (0, 0, 0))[None], 40, axis=0)
    speed = np.full(40, 0.5)
    for start, stop, pose in runs:
        T[start:stop], speed[start:stop] = pose, 0.0
    poses = SimpleNamespace(t_s=t, T_world_cam=T, joint_speed_rad_s=speed)
    views = still_view_poses({"arm110": SimpleNamespace(timestamps_ms=t * 1000, poses=poses)})
    assert len(views) == 2
    np.testing.assert_allclose(views[0], a)
    np.testing.assert_allclose(views[1], b)


def test_search_region_keeps_clear_of_the_bases() -> None:
    region = search_region(np.array([0.0, 0.0, 0.05]), BASES_XY)
    assert region.radius_m == pytest.approx(0.25) and region.table_z_m < 0 < region.z_range_m[1]
    near_base = search_region(np.array([-0.4, 0.0, 0.05]), BASES_XY)
    assert near_base.radius_m == pytest.approx(0.6993 - 0.4 - 0.15)


@pytest.fixture(scope="module")
def mug_estimate() -> tuple[EnvelopeEstimate, o3d.geometry.TriangleMesh]:
    mug = mug_like()
    centre = np.array([0.02, -0.01, TABLE_Z + 0.04])
    far_block = box((0.04, 0.04, 0.06), (0.17, 0.12, TABLE_Z))  # inside the search region, 16 cm away
    frames = render_frames([mug, far_block], centre)
    region = search_region(centre, BASES_XY)
    return envelope_from_frames(frames, centre, region), mug


def test_a_mug_like_object_is_found_with_its_handle(mug_estimate) -> None:
    estimate, mug = mug_estimate
    centre_xy, radius, height = true_cylinder(mug)
    assert np.linalg.norm(np.array(estimate.center_m[:2]) - centre_xy) < 0.003
    assert abs(estimate.radius_m - radius) < 0.003 and estimate.radius_m > 0.035 + 0.01  # the handle counts
    assert abs(estimate.height_m - height) < 0.003
    assert estimate.table_measured and abs(estimate.table_z_m - TABLE_Z) < 0.0005
    assert estimate.center_m[2] == pytest.approx(estimate.table_z_m + 0.5 * estimate.height_m)
    assert estimate.frames == {"arm110": 12, "arm111": 12}


def test_the_estimate_fills_only_the_geometry_of_the_envelope(mug_estimate) -> None:
    estimate, _ = mug_estimate
    base = Envelope(object_name="Red Bull", standoff_m=0.4, park_q_rad={"arm110": (0.0,) * 6}, extra={"x": 1},
                    schema_version=None)
    env = estimate.envelope(base)
    assert env.has_geometry and env.center_m == estimate.center_m and env.radius_m == estimate.radius_m
    assert (env.object_name, env.standoff_m, env.park_q_rad, env.extra) == ("Red Bull", 0.4, base.park_q_rad, {"x": 1})
    record = estimate.to_dict()
    assert record["source"] == "estimated" and json.loads(json.dumps(record)) == record


def test_the_same_frames_give_the_same_estimate() -> None:
    centre = np.array([0.0, 0.0, 0.05])
    frames = render_frames([mug_like((0.0, 0.0))], centre, seed=9)
    region = search_region(centre, BASES_XY)
    assert envelope_from_frames(frames, centre, region) == envelope_from_frames(frames, centre, region)


def patch_stats(corner, size_m, arm_bit: int, frame_copies: int = 2):
    """Voxel statistics of a dense vertical patch of points (seen ``frame_copies`` times by one arm)."""
    u, w = np.meshgrid(np.arange(0.0, size_m[0], 0.001), np.arange(0.0, size_m[1], 0.001))
    points = np.column_stack([corner[0] + u.ravel(), np.full(u.size, corner[1]), corner[2] + w.ravel()])
    normals = np.tile([0.0, -1.0, 0.0], (len(points), 1))
    return [frame_stats(points, normals, None, np.array([0.0, -0.4, 0.2]), 0.004, arm_bit)
            for _ in range(frame_copies)]


def test_the_cluster_seen_by_every_arm_wins_over_a_larger_one_seen_by_one() -> None:
    look = np.array([0.0, 0.0, 0.05])
    wrist = patch_stats((-0.06, -0.05, 0.10), (0.12, 0.08), arm_bit=0)  # large, near, one camera only
    front = patch_stats((-0.03, 0.0, 0.01), (0.06, 0.06), arm_bit=0)  # the object: both arms see it
    back = patch_stats((-0.03, 0.004, 0.01), (0.06, 0.06), arm_bit=1)
    stats = merge_stats(wrist + front + back)
    cluster = object_cluster(stats, 0.0, look, n_arms=2)
    assert cluster is not None and cluster[:, 2].max() < 0.08 and cluster[:, 1].min() > -0.01
    alone = object_cluster(merge_stats(wrist), 0.0, look, n_arms=2)  # no better candidate: the largest
    assert alone is not None and alone[:, 2].min() > 0.09
    assert object_cluster(merge_stats(patch_stats((-0.03, 0.0, 0.01), (0.06, 0.06), 0, frame_copies=1)),
                          0.0, look, n_arms=1) is None  # one frame: no support


def test_nothing_above_the_table_is_a_one_line_error(tmp_path: Path) -> None:
    centre = np.array([0.0, 0.0, 0.02])
    frames = render_frames([], centre)
    with pytest.raises(ReconstructionError) as err:
        envelope_from_frames(frames, centre, search_region(centre, BASES_XY), path=tmp_path / "redbull")
    message = str(err.value)
    assert "redbull" in message and "no object could be found" in message and "\n" not in message
    arms = sorted({f.arm for f in frames})
    counts = ", ".join(f"{a}: {sum(f.arm == a for f in frames)}" for a in arms)
    assert message.endswith(f"in {len(frames)} depth frames ({counts})") if len(arms) > 1 else message.endswith(
        f"in {len(frames)} depth frames")


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ReconstructionError, match="voxel_size_m"):
        EnvelopeEstimateSettings(voxel_size_m=0.0)
    with pytest.raises(ReconstructionError, match="views_per_arm"):
        EnvelopeEstimateSettings(views_per_arm=0)


# -- twin surveys through darp process -------------------------------------------------------------------------
def strip_geometry(survey: Path, folder: Path) -> Path:
    """A copy of ``survey`` (recordings linked, not copied) whose manip_envelope.json has no geometry."""
    folder.mkdir(parents=True)
    for item in survey.iterdir():
        if item.name == "manip_envelope.json":
            payload = json.loads(item.read_text())
            for key in ("center_m", "radius_m", "height_m"):
                payload.pop(key)
            (folder / item.name).write_text(json.dumps(payload))
        elif item.is_dir():
            shutil.copytree(item, folder / item.name)
        else:
            os.symlink(item, folder / item.name)
    return folder


def survey_state(folder: Path) -> dict[str, tuple[int, int]]:
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.iterdir()}


def record_empty_survey(folder: Path) -> Path:
    """One view per arm of a table with nothing above it (a 1.6 mm thin square: the cube at scale 0.1)."""
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import ObjectPlacement, make_object
    from darp.twin.record import record_survey
    from darp.twin.settings import TwinSettings
    from darp.twin.waypoints import WaypointPlan, orbit_waypoints

    rig = load_rig()
    plan = WaypointPlan({arm: tuple(orbit_waypoints(rig, arm, (0.0, 0.0, 0.0), 0.33, azimuths_deg=(0.0,),
                                                    elevation_deg=40.0, dwell_s=0.8))
                         for arm in ("arm110", "arm111")}, ("arm110", "arm111"))
    settings = TwinSettings.from_profile("realistic", seed=11).with_camera(fps=6, width=424, height=240)
    record_survey(folder, plan, make_object("cube", scale=0.1), ObjectPlacement(0.0, 0.0, 0.4), settings=settings)
    return folder


@pytest.fixture(scope="module")
def red_bull(tmp_path_factory) -> tuple[Path, Path]:
    """The tiny twin survey of the process tests, of a Red Bull can, and its copy without envelope geometry."""
    root = tmp_path_factory.mktemp("twin")
    survey = record_tiny_survey(root / "red_bull", "red_bull")
    return survey, strip_geometry(survey, root / "stripped" / "red_bull")


@pytest.mark.slow
def test_the_estimate_matches_the_true_object(red_bull, tmp_path: Path) -> None:
    survey, stripped = red_bull
    assert not open_survey(stripped).envelope().has_geometry
    truth = read_truth(survey)
    job = SurveyJob(open_survey(stripped), tmp_path / "red_bull", truth.calibration, None)
    try:
        envelope = job.envelope()
        record = job.envelope_record()
    finally:
        job.close()
    true_object = json.loads((survey / "truth" / "object.json").read_text())
    assert record["source"] == "estimated"
    assert np.linalg.norm(np.subtract(envelope.center_m, true_object["center_m"])) < 0.01
    assert abs(envelope.radius_m - true_object["radius_m"]) < 0.015
    assert abs(envelope.height_m - true_object["height_m"]) < 0.015
    assert envelope.object_name == "red_bull" and envelope.standoff_m is not None  # the rest of the file is kept


@pytest.mark.slow
def test_darp_process_estimates_the_envelope_and_matches_the_real_one(red_bull, tmp_path: Path, capsys) -> None:
    survey, stripped = red_bull
    calibration = str(survey / "truth" / "calibration.json")
    before = survey_state(stripped)
    envelope_bytes = (stripped / "manip_envelope.json").read_bytes()
    assert run(["process", str(survey), "-c", calibration, "--out", str(tmp_path / "real")]) == 0
    assert "estimated" not in capsys.readouterr().err
    assert run(["process", str(stripped), "-c", calibration, "--out", str(tmp_path / "estimated")]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "estimated" in line]
    assert len(warnings) == 1 and warnings[0].startswith("darp: warning: red_bull:"), warnings

    real = json.loads((tmp_path / "real" / "red_bull" / "results.json").read_text())
    est = json.loads((tmp_path / "estimated" / "red_bull" / "results.json").read_text())
    assert real["envelope"]["source"] == "manip_envelope.json" and est["envelope"]["source"] == "estimated"
    assert est["composition"]["radius_m"] is None  # the release table still shows the file's "--"
    index = json.loads((tmp_path / "estimated" / "red_bull" / "keyframes" / "keyframes.json").read_text())
    assert index["support_mask"]["source"] == "estimated"
    assert index["support_mask"]["radius_m"] == pytest.approx(est["envelope"]["radius_m"], abs=1e-6)
    accuracy = {name: r["truth"]["cloud"]["accuracy"]["median_mm"] for name, r in (("real", real), ("est", est))}
    completeness = {name: r["truth"]["cloud"]["completeness"]["within_5mm_pct"] for name, r in (("real", real),
                                                                                               ("est", est))}
    assert accuracy["est"] < 1.0 and abs(accuracy["est"] - accuracy["real"]) < 0.1, accuracy
    assert abs(completeness["est"] - completeness["real"]) < 5.0, completeness
    assert est["clouds"]["fused"] > 0.9 * real["clouds"]["fused"]
    assert survey_state(stripped) == before and (stripped / "manip_envelope.json").read_bytes() == envelope_bytes


@pytest.mark.slow
def test_a_survey_with_nothing_above_the_table_is_a_one_line_error(tmp_path: Path, capsys) -> None:
    survey = record_empty_survey(tmp_path / "twin" / "flat")
    stripped = strip_geometry(survey, tmp_path / "stripped" / "flat")
    code = run(["process", str(stripped), "-c", str(survey / "truth" / "calibration.json"), "--out",
                str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("darp: error:"), err
    assert "flat" in err[0] and "no object could be found" in err[0]
