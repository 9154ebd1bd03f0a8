"""Keyframe selection (settled, in view, diverse, held-out split), colour-to-depth alignment and the
keyframe file format. Trajectories are constructed with known joint speeds; alignment is checked
against pyrealsense2's own projection functions."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from darp.errors import FormatError, ReconstructionError
from darp.formats.realsense.types import Intrinsics
from darp.kinematics.camera_poses import POSED, CameraPoses
from darp.processing.settings import ProcessSettings
from darp.reconstruction.align import align_colour_to_depth, colour_to_rgb, project_points
from darp.reconstruction.keyframe_io import (
    DEPTH_ONLY,
    FOR_FUSION,
    Keyframe,
    KeyframeIndex,
    KeyframeInfo,
    iter_keyframes,
    load_keyframes,
    read_keyframe,
    read_keyframe_index,
    write_keyframe,
    write_keyframe_index,
)
from darp.reconstruction.keyframes import (
    KeyframeSettings,
    look_at_point,
    select_arm_keyframes,
    select_survey_keyframes,
    settled_mask,
)
from darp.reconstruction.poses import CameraTrajectory
from helpers.synthetic_depth import look_at, small_intrinsics

CENTRE = np.array([0.02, -0.01, 0.05])
FPS = 30.0
STILL, MOVING = 0.004, 0.4  # rad/s: encoder noise of a still arm, a move


def eye(az_deg: float, el_deg: float, dist_m: float) -> np.ndarray:
    a, e = np.radians(az_deg), np.radians(el_deg)
    return CENTRE + dist_m * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])


def build(schedule: list[tuple]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Frames at 30 fps of a schedule of ``("dwell", az, el, dist, seconds[, look_away])`` and
    ``("move", seconds)`` (linear in az/el/dist between the dwells around it).

    Returns times, poses (N, 4, 4), joint speeds and the dwell index of each frame (-1 while moving).
    """
    times, poses, speeds, dwell_of = [], [], [], []
    t = 0.0
    dwells = [s for s in schedule if s[0] == "dwell"]
    k = -1
    for step in schedule:
        n = int(round(step[-1] if step[0] == "move" else step[4]) * FPS)
        if step[0] == "dwell":
            k += 1
            _, az, el, dist, _seconds, *away = step
            target = CENTRE + (eye(az, el, dist) - CENTRE) * 3.0 if away else CENTRE
            for _ in range(n):
                times.append(t), poses.append(look_at(eye(az, el, dist), target)), speeds.append(STILL)
                dwell_of.append(k)
                t += 1 / FPS
        else:
            a, b = dwells[k], dwells[k + 1]
            for i in range(n):
                f = (i + 0.5) / n
                p = [a[j] + f * (b[j] - a[j]) for j in (1, 2, 3)]
                times.append(t), poses.append(look_at(eye(*p), CENTRE)), speeds.append(MOVING), dwell_of.append(-1)
                t += 1 / FPS
    return np.array(times), np.array(poses), np.array(speeds), np.array(dwell_of)


SCHEDULE = [("dwell", 180.0, 30.0, 0.80, 1.0),  # park: far, the same direction as the next view
            ("move", 0.8), ("dwell", 182.0, 32.0, 0.35, 1.0),
            ("move", 0.8), ("dwell", 160.0, 30.0, 0.35, 1.0),
            ("move", 0.8), ("dwell", 140.0, 45.0, 0.35, 0.2),  # too short to settle
            ("move", 0.8), ("dwell", 200.0, 30.0, 0.35, 1.0),
            ("move", 0.8), ("dwell", 220.0, 30.0, 0.35, 1.0, "away"),  # the object is not in the image
            ("move", 0.8), ("dwell", 203.0, 60.0, 0.35, 1.0),
            ("move", 0.8), ("dwell", 160.5, 30.5, 0.35, 1.0),  # a revisit of dwell 2, 0.7 deg away
            ("move", 0.8), ("dwell", 180.0, 30.0, 0.80, 1.0)]  # park again
INTR = small_intrinsics(160, 120, 96.0)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


@pytest.fixture(scope="module")
def survey_arrays():
    return build(SCHEDULE)


def test_settled_mask_follows_speed_and_settle_window() -> None:
    t = np.arange(12) * 0.1
    speed = np.array([0.001, 0.001, 0.5, 0.5, 0.001, 0.001, 0.001, 0.001, np.nan, 0.001, 0.001, 0.001])
    mask = settled_mask(t, speed, KeyframeSettings(max_joint_speed_rad_s=0.02, settle_s=0.2))
    # runs start at 0.0 (frame 0), 0.4 (frame 4) and 0.9 (frame 9, after an unposed frame)
    assert mask.tolist() == [False, False, False, False, False, False, True, True, False, False, False, True]
    with pytest.raises(ReconstructionError, match="time order"):
        settled_mask(t[::-1], speed, KeyframeSettings())


def test_keyframes_are_settled_in_view_and_from_distinct_views(survey_arrays) -> None:
    t, T, speed, dwell = survey_arrays
    settings = KeyframeSettings(settle_s=0.3, per_view=3, min_separation_deg=6.0)
    sel = select_arm_keyframes("arm110", t, T, speed, CENTRE, settings, INTR)
    assert len(sel) > 0 and np.all(np.diff(sel.indices) > 0)
    for i in sel.indices:
        assert speed[i] <= settings.max_joint_speed_rad_s
        start = i
        while start > 0 and speed[start - 1] <= settings.max_joint_speed_rad_s:
            start -= 1
        assert t[i] - t[start] >= settings.settle_s - 1e-9  # inside a settled window after a move
    picked_dwells = sorted(set(dwell[sel.indices].tolist()))
    # near view 1 beats the far park views 0 and 8; 3 never settles; 5 looks away; 7 revisits 2
    assert picked_dwells == [1, 2, 4, 6]
    for d in picked_dwells:
        assert np.count_nonzero(dwell[sel.indices] == d) == settings.per_view
    dirs = (T[sel.indices, :3, 3] - CENTRE) / np.linalg.norm(T[sel.indices, :3, 3] - CENTRE, axis=1)[:, None]
    for a in range(len(sel)):
        for b in range(a + 1, len(sel)):
            if sel.view_ids[a] != sel.view_ids[b]:
                assert angle_deg(dirs[a], dirs[b]) >= settings.min_separation_deg
    assert sel.counts["views"] == 4 and sel.counts["keyframes"] == 12


FAR_SCHEDULE = [("dwell", 120.0, 60.0, 0.80, 1.0),  # park: far, from a direction no near view has
                ("move", 0.8), ("dwell", 180.0, 30.0, 0.35, 1.0),
                ("move", 0.8), ("dwell", 160.0, 30.0, 0.50, 1.0),  # farther, but within 2x the nearest
                ("move", 0.8), ("dwell", 200.0, 30.0, 0.35, 1.0)]


def test_a_view_more_than_twice_as_far_as_the_nearest_is_dropped() -> None:
    t, T, speed, dwell = build(FAR_SCHEDULE)
    settings = KeyframeSettings(settle_s=0.3)
    sel = select_arm_keyframes("arm110", t, T, speed, CENTRE, settings, INTR)
    assert sorted(set(dwell[sel.indices].tolist())) == [1, 2, 3]
    assert sel.counts["far_views"] == 1 and sel.counts["views_found"] == 4
    off = select_arm_keyframes("arm110", t, T, speed, CENTRE,
                               dataclasses.replace(settings, max_view_distance_ratio=None), INTR)
    assert 0 in dwell[off.indices]  # the old rule: the far view is distinct in direction, so it was taken
    with pytest.raises(ReconstructionError, match="max_view_distance_ratio"):
        KeyframeSettings(max_view_distance_ratio=0.5)


def test_frames_at_the_park_pose_are_never_keyframes() -> None:
    t, T, speed, dwell = build(FAR_SCHEDULE)
    park = np.array([0.0, 1.5, -1.0, -0.5, 0.0, 0.0])
    q = np.where((dwell == 0)[:, None], park + 0.01, park + 0.3)  # the park dwell within 0.01 rad of park
    settings = KeyframeSettings(settle_s=0.3, max_view_distance_ratio=None)
    sel = select_arm_keyframes("arm110", t, T, speed, CENTRE, settings, INTR, q_rad=q, park_q_rad=park)
    assert 0 not in dwell[sel.indices] and sorted(set(dwell[sel.indices].tolist())) == [1, 2, 3]
    assert sel.counts["at_park"] == int(np.count_nonzero((dwell == 0) & settled_mask(t, speed, settings)))
    strict = dataclasses.replace(settings, park_tolerance_rad=0.005)  # 0.01 rad off park is then not "at park"
    assert 0 in dwell[select_arm_keyframes("arm110", t, T, speed, CENTRE, strict, INTR, q_rad=q,
                                           park_q_rad=park).indices]


def test_one_frame_per_view_gives_pairwise_minimum_angle(survey_arrays) -> None:
    t, T, speed, _ = survey_arrays
    for min_sep in (6.0, 25.0):
        settings = KeyframeSettings(settle_s=0.3, per_view=1, min_separation_deg=min_sep)
        sel = select_arm_keyframes("arm110", t, T, speed, CENTRE, settings, INTR)
        dirs = sel.directions
        pairs = [angle_deg(dirs[a], dirs[b]) for a in range(len(sel)) for b in range(a + 1, len(sel))]
        assert len(sel) >= 2 and min(pairs) >= min_sep
    assert len(select_arm_keyframes("arm110", t, T, speed, CENTRE, KeyframeSettings(
        settle_s=0.3, per_view=1, max_views=2), INTR)) == 2


def test_unposed_frames_and_missing_centre(survey_arrays) -> None:
    t, T, speed, _ = survey_arrays
    T = T.copy()
    speed = speed.copy()
    T[::7] = np.nan  # unposed frames: never keyframes, and they break the still runs
    speed[::7] = np.nan
    settings = KeyframeSettings(settle_s=0.1)
    sel = select_arm_keyframes("arm110", t, T, speed, None, settings, INTR)  # centre from the optical axes
    assert len(sel) > 0 and not np.any(sel.indices % 7 == 0)
    assert np.linalg.norm(look_at_point(T[speed <= 0.02]) - CENTRE) < 1e-6


def test_heldout_split_is_deterministic_with_the_expected_fraction(survey_arrays) -> None:
    t, T, speed, _ = survey_arrays
    settings = KeyframeSettings(settle_s=0.3, per_view=5, heldout_every=4, heldout_offset=1)
    first = select_arm_keyframes("arm111", t, T, speed, CENTRE, settings, INTR)
    second = select_arm_keyframes("arm111", t, T, speed, CENTRE, settings, INTR)
    assert np.array_equal(first.indices, second.indices) and np.array_equal(first.heldout, second.heldout)
    k = len(first)
    assert np.flatnonzero(first.heldout).tolist() == list(range(1, k, 4))
    assert first.counts["heldout"] == len(range(1, k, 4)) and abs(first.heldout.mean() - 0.25) < 1.0 / k
    assert first.splits.count("heldout") == first.counts["heldout"]
    default = KeyframeSettings()
    assert 1.0 / default.heldout_every == pytest.approx(0.2)  # ~22 of ~110 keyframes per object, like the paper
    with pytest.raises(ReconstructionError, match="held-out split"):
        KeyframeSettings(heldout_every=1)


def test_heldout_views_are_held_out_whole_so_no_fused_keyframe_shares_their_pose(survey_arrays) -> None:
    t, T, speed, _ = survey_arrays
    by_frame = KeyframeSettings(settle_s=0.3, per_view=5, heldout_every=4, heldout_offset=1)
    by_view = KeyframeSettings(settle_s=0.3, per_view=5, heldout_every=4, heldout_offset=1, heldout_unit="view")
    frames = select_arm_keyframes("arm111", t, T, speed, CENTRE, by_frame, INTR)
    views = select_arm_keyframes("arm111", t, T, speed, CENTRE, by_view, INTR)
    assert np.array_equal(frames.indices, views.indices)  # the same keyframes, another split
    held, fused = set(views.view_ids[views.heldout].tolist()), set(views.view_ids[~views.heldout].tolist())
    assert held and not held & fused  # whole views: every keyframe of a held-out view is held out
    in_time_order = list(dict.fromkeys(views.view_ids.tolist()))  # the views by first appearance
    assert sorted(held) == sorted(in_time_order[1::4])
    assert set(frames.view_ids[frames.heldout].tolist()) & set(frames.view_ids[~frames.heldout].tolist())
    recorded = ProcessSettings(keyframes=by_frame).to_dict()["keyframes"]  # what keyframes.json records
    assert "heldout_unit" not in recorded
    assert ProcessSettings(keyframes=by_view).to_dict()["keyframes"]["heldout_unit"] == "view"
    with pytest.raises(ReconstructionError, match="heldout_unit must be one of keyframe, view"):
        KeyframeSettings(heldout_unit="arm")


def test_survey_selection_maps_back_to_trajectory_indices(survey_arrays) -> None:
    t, T, speed, _ = survey_arrays
    n = t.size
    velocity = np.zeros((n, 6))
    velocity[:, 2] = speed
    poses = CameraPoses(t, T, np.full(n, POSED, np.int8), np.zeros((n, 6)), velocity)
    traj = CameraTrajectory("arm110", "348522076490", "depth", np.arange(n) + 100, t * 1000.0, ("Global Time",),
                            poses, (t[0] - 1, t[-1] + 1), n)
    settings = KeyframeSettings(settle_s=0.3)
    out = select_survey_keyframes({"arm110": traj}, CENTRE, settings, {"arm110": INTR})["arm110"]
    direct = select_arm_keyframes("arm110", t, T, speed, CENTRE, settings, INTR)
    assert np.array_equal(out.indices, direct.indices)


# -- alignment ------------------------------------------------------------------------------------------
def rs_intrinsics(intr: Intrinsics):
    import pyrealsense2 as rs

    i = rs.intrinsics()
    i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy
    i.model = {"none": rs.distortion.none, "brown conrady": rs.distortion.brown_conrady,
               "inverse brown conrady": rs.distortion.inverse_brown_conrady,
               "modified brown conrady": rs.distortion.modified_brown_conrady}[intr.model.lower()]
    i.coeffs = list(intr.coeffs)
    return i


@pytest.mark.parametrize("model", ["None", "Brown Conrady", "Inverse Brown Conrady", "Modified Brown Conrady"])
def test_projection_matches_librealsense(model: str) -> None:
    import pyrealsense2 as rs

    coeffs = (0.0,) * 5 if model == "None" else (0.08, -0.04, 0.002, -0.001, 0.01)
    intr = Intrinsics(640, 480, 615.0, 612.0, 321.5, 238.7, model, coeffs)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.25, 0.25, 50), rng.uniform(-0.2, 0.2, 50), rng.uniform(0.3, 1.0, 50)])
    u, v, front = project_points(pts, intr)
    expected = np.array([rs.rs2_project_point_to_pixel(rs_intrinsics(intr), p.tolist()) for p in pts])
    assert front.all()
    np.testing.assert_allclose(np.column_stack([u, v]), expected, atol=2e-3)  # librealsense computes in float32


def test_aligned_colour_lands_where_librealsense_projects_it() -> None:
    import pyrealsense2 as rs

    d_intr = Intrinsics(96, 72, 70.0, 70.0, 47.3, 35.6)
    c_intr = Intrinsics(128, 96, 110.0, 109.0, 63.2, 48.9, "Brown Conrady", (0.05, -0.02, 0.001, 0.0005, 0.0))
    angle = np.radians(2.0)
    T_colour_depth = np.eye(4)
    T_colour_depth[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    T_colour_depth[:3, 3] = [0.015, 0.0003, 0.0002]
    v, u = np.mgrid[0:72, 0:96]
    depth = (600 + 2 * u + v).astype(np.uint16)  # a slanted plane, 0.6-0.86 m at 1 mm units
    depth[10:14, 20:30] = 0  # a hole: no depth, no colour
    # every colour pixel gets a unique colour encoding its position
    cv, cu = np.mgrid[0:96, 0:128]
    colour = np.stack([cu, cv, np.full_like(cu, 200)], axis=-1).astype(np.uint8)
    aligned = align_colour_to_depth(depth, 0.001, d_intr, colour, c_intr, T_colour_depth, occlusion=False)
    assert np.all(aligned[10:14, 20:30] == 0)
    ext = rs.extrinsics()
    ext.rotation = T_colour_depth[:3, :3].T.reshape(-1).tolist()  # librealsense stores column-major
    ext.translation = T_colour_depth[:3, 3].tolist()
    rs_d, rs_c = rs_intrinsics(d_intr), rs_intrinsics(c_intr)
    inside = outside = 0
    for y, x in zip(*np.nonzero(depth), strict=True):
        p = rs.rs2_deproject_pixel_to_point(rs_d, [float(x), float(y)], float(depth[y, x] * 0.001))
        uc, vc = rs.rs2_project_point_to_pixel(rs_c, rs.rs2_transform_point_to_point(ext, p))
        iu, iv = round(uc), round(vc)
        if not (-0.5 < uc < 127.5 and -0.5 < vc < 95.5):
            assert aligned[y, x].tolist() == [0, 0, 0]
            outside += 1
        elif abs(uc - round(uc)) < 0.45 and abs(vc - round(vc)) < 0.45:  # clear of rounding ties (float32)
            assert aligned[y, x].tolist() == [iu, iv, 200], (y, x, uc, vc)
            inside += 1
    assert inside > 3000 and outside > 50


def test_occluded_background_gets_no_colour() -> None:
    intr = Intrinsics(80, 60, 60.0, 60.0, 39.5, 29.5)
    depth = np.full((60, 80), 1000, np.uint16)  # a wall at 1 m
    depth[:, 36:44] = 300  # a post at 0.3 m in front of it
    T_colour_depth = np.eye(4)
    T_colour_depth[0, 3] = -0.05  # the colour camera 5 cm to the right (+x) of the depth camera
    colour = np.full((60, 80, 3), 255, np.uint8)
    hidden = align_colour_to_depth(depth, 0.001, intr, colour, intr, T_colour_depth) == 0
    plain = align_colour_to_depth(depth, 0.001, intr, colour, intr, T_colour_depth, occlusion=False) == 0
    # in the colour image the post (0.3 m) moves f*b/z = 10 px left, the wall 3 px: the wall just left
    # of the post (depth columns 29..35, colour 26..32) lies behind the post for the colour camera
    cols = np.flatnonzero(hidden.all(axis=(0, 2)) & ~plain.all(axis=(0, 2)))
    assert cols.size >= 5 and cols.min() >= 27 and cols.max() <= 35
    assert not hidden[:, 36:44].any()  # the post itself is seen


def test_colour_to_rgb_orders_channels() -> None:
    bgr = np.zeros((2, 2, 3), np.uint8)
    bgr[..., 0] = 10
    assert colour_to_rgb(bgr, "bgr8")[0, 0].tolist() == [0, 0, 10]
    assert colour_to_rgb(bgr, "rgb8")[0, 0].tolist() == [10, 0, 0]
    with pytest.raises(ReconstructionError, match="yuyv"):
        colour_to_rgb(bgr, "yuyv")


# -- file format ------------------------------------------------------------------------------------------
def make_keyframe(rng: np.random.Generator, arm: str, frame: int, split: str) -> Keyframe:
    h, w = 12, 16
    intr = Intrinsics(w, h, 14.0, 14.5, 7.5, 5.5, "Brown Conrady", (0.01, 0.0, 0.0, 0.0, 0.0))
    return Keyframe(arm=arm, serial="348522076490", frame_number=frame, timestamp_ms=1.7e12 + frame * 33.3,
                    t_s=1.7e9 + frame / 30.0, split=split, view=frame // 3,
                    rgb=rng.integers(0, 256, (h, w, 3), np.uint8), depth=rng.integers(0, 65535, (h, w), np.uint16),
                    ir_left=rng.integers(0, 256, (h, w), np.uint8), ir_right=rng.integers(0, 256, (h, w), np.uint8),
                    support_mask=rng.random((h, w)) > 0.5, intrinsics=intr, depth_scale=0.001,
                    T_world_cam=look_at((0.3, 0.1, 0.4), CENTRE), streams=("depth", "color", "ir1", "ir2"))


def test_keyframe_round_trip_and_index(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    keyframes = [make_keyframe(rng, arm, n, split) for arm, n, split in
                 (("arm110", 7, "fuse"), ("arm110", 9, "heldout"), ("arm111", 4, "fuse"))]
    infos = []
    for kf in keyframes:
        rel = f"{kf.arm}/{kf.frame_number:06d}.npz"
        write_keyframe(tmp_path / rel, kf)
        infos.append(kf.index_entry(rel))
    write_keyframe_index(KeyframeIndex(tmp_path, "mug", "mug", "calibration", KeyframeSettings().to_dict(),
                                       {"arm110": {"keyframes": 2}}, infos, {"calibration_epoch": "e1"}))
    back = load_keyframes(tmp_path)
    assert len(back) == 3
    for a, b in zip(keyframes, back, strict=True):
        for name in ("arm", "serial", "frame_number", "timestamp_ms", "t_s", "split", "view", "depth_scale",
                     "intrinsics", "streams"):
            assert getattr(a, name) == getattr(b, name), name
        for name in ("rgb", "depth", "ir_left", "ir_right", "support_mask", "T_world_cam"):
            assert np.array_equal(getattr(a, name), getattr(b, name))
            assert getattr(a, name).dtype == getattr(b, name).dtype
    assert [k.frame_number for k in iter_keyframes(tmp_path, split="heldout")] == [9]
    assert [k.frame_number for k in load_keyframes(tmp_path, arm="arm111")] == [4]
    index = read_keyframe_index(tmp_path)
    assert all(isinstance(k, KeyframeInfo) and k.to_dict() == i.to_dict()
               for k, i in zip(index.keyframes, infos, strict=True))
    assert index.extra == {"calibration_epoch": "e1"} and index.settings["per_view"] == KeyframeSettings().per_view
    pd = back[0].posed_depth()
    assert pd.frame_id == 7 and pd.colour is back[0].rgb and pd.depth_scale == 0.001
    with np.load(tmp_path / infos[0].file) as data:  # plain numpy can read it
        assert data["depth"].shape == (12, 16) and str(data["split"]) == "fuse"


def test_keyframes_read_without_the_images_a_stage_does_not_use(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                                  ) -> None:
    """Fusion reads no IR nor mask, evaluation only depth: those members are not decompressed, come back empty,
    and what is read equals a full read."""
    import zipfile

    rng = np.random.default_rng(1)
    kf = make_keyframe(rng, "arm110", 7, "fuse")
    write_keyframe(tmp_path / "arm110/000007.npz", kf)
    write_keyframe_index(KeyframeIndex(tmp_path, "mug", "mug", "calibration", KeyframeSettings().to_dict(),
                                       {"arm110": {"keyframes": 1}}, [kf.index_entry("arm110/000007.npz")]))
    opened: list[str] = []
    original = zipfile.ZipFile.open

    def spy(self: zipfile.ZipFile, name: str | zipfile.ZipInfo, *args: object, **kwargs: object) -> object:
        opened.append(name if isinstance(name, str) else name.filename)
        return original(self, name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(zipfile.ZipFile, "open", spy)
    for skip in (FOR_FUSION, DEPTH_ONLY):
        opened.clear()
        (part,) = list(iter_keyframes(tmp_path, "fuse", skip=skip))
        assert not {f"{name}.npy" for name in skip} & set(opened) and "depth.npy" in opened
        for name in ("rgb", "depth", "ir_left", "ir_right", "support_mask"):
            got = getattr(part, name)
            if name in skip:
                assert got.shape == (0,) and got.dtype == getattr(kf, name).dtype, name
            else:
                assert np.array_equal(got, getattr(kf, name)), name
        assert np.array_equal(part.posed_depth(colour=False).depth, kf.depth)
    assert part.posed_depth(colour=False).colour is None
    with pytest.raises(ReconstructionError, match="cannot skip depth"):
        read_keyframe(tmp_path / "arm110/000007.npz", skip=("depth",))


def test_bad_keyframe_files_are_refused(tmp_path: Path) -> None:
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="junk.npz"):
        read_keyframe(tmp_path / "junk.npz")
    np.savez(tmp_path / "partial.npz", depth=np.zeros((2, 2), np.uint16))
    with pytest.raises(FormatError, match="missing array"):
        read_keyframe(tmp_path / "partial.npz")
    with pytest.raises(FormatError, match="not a keyframes folder"):
        read_keyframe_index(tmp_path)
    (tmp_path / "keyframes.json").write_text(json.dumps({"schema": "other/1"}))
    with pytest.raises(FormatError, match="schema"):
        read_keyframe_index(tmp_path)
