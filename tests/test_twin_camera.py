"""The twin camera end to end on small MuJoCo scenes: rendering geometry, profiles, IR, SGBM, IMU, spec.

Oracles: MuJoCo's own ray caster (mj_multiRay), analytic surfaces, and OpenCV's ChArUco detector
(corners found in the rendered image against their true projections: the pixel-centre convention).
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from darp.calibration.board import corners_board_m, cv_board
from darp.errors import ConfigError, TwinError
from darp.formats.calibration import CharucoBoardSpec
from darp.formats.realsense.types import Intrinsics
from darp.twin.camera.imu import ImuSettings, ImuSimulator, pose_function_from_samples
from darp.twin.camera.render import SceneRenderer, mujoco
from darp.twin.camera.sensor import TwinCamera, TwinCameraSettings, dark_geom_dropouts
from darp.twin.camera.spec import draw_unit, make_camera_spec, with_resolution
from darp.twin.objects.board import add_charuco_board

SUBPIXEL = 0.08


# -- helpers -------------------------------------------------------------------------------------------
def rot_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def looking_down(
    height_m: float, R_extra: np.ndarray | None = None, xy: tuple[float, float] = (0, 0)
) -> np.ndarray:
    """Camera above the floor (world z up) looking straight down (+z_cam = -z_world), optionally tilted."""
    T = np.eye(4)
    T[:3, :3] = rot_x(180.0) @ (R_extra if R_extra is not None else np.eye(3))
    T[:3, 3] = [xy[0], xy[1], height_m]
    return T


def compile_spec(spec: mujoco.MjSpec) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def new_spec() -> mujoco.MjSpec:
    spec = mujoco.MjSpec()
    spec.worldbody.add_light(pos=[0.2, 0.1, 2.0], dir=[0, 0, -1], diffuse=[0.6, 0.6, 0.6], castshadow=False)
    return spec


def add_floor(spec: mujoco.MjSpec, rgba: tuple[float, ...] = (0.7, 0.7, 0.7, 1.0)) -> None:
    """A 3 m x 3 m slab whose top face is the plane z = 0."""
    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[1.5, 1.5, 0.01],
        pos=[0, 0, -0.01],
        rgba=list(rgba),
    )


def world_points(
    depth_m: np.ndarray, intr: Intrinsics, T_world_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project valid depth pixels to world points; also return their flat pixel indices."""
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u].astype(np.float64)
    p_cam = np.column_stack([(u - intr.ppx) / intr.fx * z, (v - intr.ppy) / intr.fy * z, z])
    return p_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3], v * depth_m.shape[1] + u


def plane_rms_m(depth_m: np.ndarray, roi: tuple[slice, slice]) -> float:
    z = depth_m[roi].astype(np.float64)
    v, u = np.mgrid[roi[0], roi[1]]
    ok = z > 0
    A = np.column_stack([u[ok], v[ok], np.ones(ok.sum())])
    coef, *_ = np.linalg.lstsq(A, z[ok], rcond=None)
    return float(np.std(z[ok] - A @ coef))


# -- scenes (module scope: one GL context each) --------------------------------------------------------
@pytest.fixture(scope="module")
def shapes_scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    spec = new_spec()
    add_floor(spec)
    spec.worldbody.add_geom(
        name="ball",
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[0.05, 0, 0],
        pos=[0.06, 0.03, 0.05],
        rgba=[0.9, 0.2, 0.2, 1],
    )
    spec.worldbody.add_geom(
        name="cube",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.03, 0.04, 0.05],
        pos=[-0.09, -0.04, 0.06],
        euler=[0, 0, 30],
        rgba=[0.2, 0.5, 0.9, 1],
    )
    return compile_spec(spec)


@pytest.fixture(scope="module")
def floor_scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    spec = new_spec()
    add_floor(spec)
    return compile_spec(spec)


@pytest.fixture(scope="module")
def box_scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    """A 10 cm tall box on the floor (its top is the foreground)."""
    spec = new_spec()
    add_floor(spec)
    spec.worldbody.add_geom(
        name="block",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.05, 0.05, 0.05],
        pos=[0.0, 0.0, 0.05],
        rgba=[0.8, 0.8, 0.3, 1],
    )
    spec.worldbody.add_geom(
        name="dark",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.05, 0.05, 0.001],
        pos=[0.0, 0.15, 0.001],
        rgba=[0.03, 0.03, 0.03, 1],
    )
    spec.add_material(name="chrome", rgba=[0.8, 0.8, 0.8, 1], reflectance=0.9)
    spec.worldbody.add_geom(
        name="mirror",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[0.03, 0.03, 0.001],
        pos=[0.2, -0.15, 0.001],
        material="chrome",
    )
    return compile_spec(spec)


BOARD = CharucoBoardSpec(squares_x=7, squares_y=5, square_length_m=0.03, marker_length_m=0.022,
                         dictionary="DICT_5X5_100")
T_WORLD_BOARD = np.eye(4)
T_WORLD_BOARD[:3, :3] = rot_x(180.0)  # printed side (-z of the board) faces world +z
T_WORLD_BOARD[:3, 3] = [-0.105, 0.075, 0.002]  # board centre at the world origin


@pytest.fixture(scope="module")
def board_scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    spec = new_spec()
    add_floor(spec, rgba=(0.3, 0.3, 0.3, 1))
    add_charuco_board(spec, BOARD, T_parent_board=T_WORLD_BOARD)
    return compile_spec(spec)


# -- rendering geometry --------------------------------------------------------------------------------
def test_rendered_depth_and_segmentation_match_ray_casting(shapes_scene) -> None:
    model, data = shapes_scene
    intr = Intrinsics(640, 480, 383.2, 386.1, 326.3, 233.7)  # fx != fy, off-centre principal point
    T = looking_down(0.42, rot_x(12) @ rot_y(-8) @ rot_z(25), xy=(0.02, -0.03))
    with SceneRenderer(model, 640, 480) as renderer:
        out = renderer.render(data, T, intr)
        seg = renderer.render_segmentation(T, intr)
        seg_again, depth_flat = renderer.render_segmentation_and_depth(T, intr)
    assert np.array_equal(seg_again, seg)
    assert np.array_equal(depth_flat, out.depth_m)  # the flat id pass rasterises the same geometry
    v, u = np.mgrid[0:480, 0:640]
    rays_cam = np.stack([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, np.ones(u.shape)], -1).reshape(
        -1, 3
    )
    rays_world = rays_cam @ T[:3, :3].T  # z component 1 in the camera: ray parameter = depth z
    n = rays_world.shape[0]
    dist, geom = np.zeros(n), np.zeros(n, np.int32)
    mujoco.mj_multiRay(
        model, data, T[:3, 3].copy(), rays_world.reshape(-1).copy(), None, 1, -1, geom, dist, None, n, 100.0
    )
    z_ray, geom = dist.reshape(480, 640), geom.reshape(480, 640)
    assert out.depth_m is not None and out.rgb is not None
    assert np.mean(seg == geom) > 0.999
    same = (seg == geom) & (z_ray > 0)
    err = np.abs(out.depth_m[same] - z_ray[same])
    assert np.median(err) < 1e-5
    assert np.percentile(err, 99) < 2e-4  # tessellated sphere: chord error below 0.1 mm
    ball = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "ball")
    assert np.all(out.rgb[seg == ball][:, 0] > out.rgb[seg == ball][:, 2])  # red where the ball is


def test_renderer_rejects_bad_pose_and_size(floor_scene) -> None:
    model, data = floor_scene
    with SceneRenderer(model, 320, 240) as renderer:
        with pytest.raises(TwinError, match="4x4"):
            renderer.render(data, np.eye(3), Intrinsics(320, 240, 200, 200, 160, 120))
        with pytest.raises(TwinError, match="exceeds"):
            renderer.render(data, looking_down(0.5), Intrinsics(640, 480, 383, 383, 320, 240))


def test_ideal_depth_lies_on_true_surfaces(shapes_scene) -> None:
    model, data = shapes_scene
    spec = make_camera_spec(draw_unit(3))
    T = looking_down(0.40, rot_x(10) @ rot_y(6))
    with TwinCamera(model, spec, TwinCameraSettings.from_profile("ideal"), seed=1) as cam:
        frames = cam.capture(data, T, timestamp_s=0.0)
    geom_id = frames["truth"]["geom_id"]
    ids = {
        name: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) for name in ("floor", "ball", "cube")
    }
    cube_T = np.eye(4)
    cube_T[:3, :3] = data.geom_xmat[ids["cube"]].reshape(3, 3)
    cube_T[:3, 3] = data.geom_xpos[ids["cube"]]
    half = model.geom_size[ids["cube"]]

    def surface_distance(p: np.ndarray, name: str) -> np.ndarray:
        if name == "floor":
            return np.abs(p[:, 2])
        if name == "ball":
            return np.abs(
                np.linalg.norm(p - data.geom_xpos[ids["ball"]], axis=1) - model.geom_size[ids["ball"]][0]
            )
        q = np.abs((p - cube_T[:3, 3]) @ cube_T[:3, :3]) - half  # box signed distance, in the cube frame
        return np.abs(np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0))

    for key, limit in (("depth_m", 0.05e-3), ("depth", 0.3e-3)):  # exact metres, then Z16 (1 mm unit)
        depth = frames[key] * 0.001 if key == "depth" else frames[key]
        points, flat = world_points(depth, spec.depth, T)
        for name, gid in ids.items():
            mine = geom_id.reshape(-1)[flat] == gid
            assert mine.sum() > 500, name
            assert np.median(surface_distance(points[mine], name)) < limit, (key, name)
    assert frames["depth"].dtype == np.uint16 and frames["color"].dtype == np.uint8
    assert frames["color"].shape == (480, 640, 3) and frames["ir1"].shape == (480, 640)


@pytest.mark.parametrize("distance_m", [0.30, 0.45, 0.60])
def test_charuco_corners_land_on_true_projections(board_scene, distance_m: float) -> None:
    model, data = board_scene
    spec = make_camera_spec(draw_unit(11))  # off-centre principal points, fx != fy
    tilt = {0.30: rot_x(8), 0.45: rot_x(-15) @ rot_y(10), 0.60: rot_y(-20) @ rot_z(30)}[distance_m]
    T_world_depth = looking_down(distance_m, tilt)
    T_world_depth[:3, 3] = -T_world_depth[:3, 2] * distance_m  # optical axis through the board centre
    with TwinCamera(model, spec, TwinCameraSettings.from_profile("ideal"), seed=0) as cam:
        frames = cam.capture(data, T_world_depth)
    T_world_color = frames["truth"]["T_world_color"]
    detector = cv2.aruco.CharucoDetector(cv_board(BOARD))
    corners, ids, _, _ = detector.detectBoard(cv2.cvtColor(frames["color"], cv2.COLOR_BGR2GRAY))
    assert ids is not None and len(ids) >= 20
    P_world = corners_board_m(BOARD) @ T_WORLD_BOARD[:3, :3].T + T_WORLD_BOARD[:3, 3]
    T_color_world = np.linalg.inv(T_world_color)
    P_cam = P_world @ T_color_world[:3, :3].T + T_color_world[:3, 3]
    K = spec.color.K
    uv = (P_cam @ K.T)[:, :2] / P_cam[:, 2:3]
    err = np.linalg.norm(corners.reshape(-1, 2) - uv[ids.ravel()], axis=1)
    assert np.median(err) < 0.2


# -- realistic profile through the whole camera ---------------------------------------------------------
@pytest.mark.parametrize("distance_m", [0.30, 0.45, 0.60])
def test_realistic_noise_rms_matches_intel_formula(floor_scene, distance_m: float) -> None:
    model, data = floor_scene
    spec = make_camera_spec()
    settings = TwinCameraSettings.from_profile("realistic", render_ir=False, segmentation=False)
    roi = (slice(140, 340), slice(260, 460))
    with TwinCamera(model, spec, settings, seed=5) as cam:
        rms = [
            plane_rms_m(cam.capture(data, looking_down(distance_m))["depth"] * 0.001, roi) for _ in range(3)
        ]
    formula = distance_m**2 * SUBPIXEL / (spec.depth.fx * spec.baseline_m)
    assert np.mean(rms) == pytest.approx(np.hypot(formula, 0.001 / np.sqrt(12)), rel=0.30)


@pytest.mark.parametrize("distance_m", [0.32, 0.55])
def test_realistic_left_band_width(floor_scene, distance_m: float) -> None:
    model, data = floor_scene
    spec = make_camera_spec()
    with TwinCamera(model, spec, TwinCameraSettings(render_ir=False), seed=2) as cam:
        depth = cam.capture(data, looking_down(distance_m))["depth"]
    first_valid = np.argmax(depth[60:420] > 0, axis=1)
    assert np.median(first_valid) == pytest.approx(spec.depth.fx * spec.baseline_m / distance_m, abs=1.0)


def test_realistic_occlusion_hole_left_of_box(box_scene) -> None:
    model, data = box_scene
    spec = make_camera_spec()
    height = 0.50
    settings = TwinCameraSettings(render_ir=False)
    with TwinCamera(model, spec, settings, seed=3) as cam:
        frames = cam.capture(data, looking_down(height))
    depth, truth = frames["depth"], frames["truth"]["depth_m"]
    z_fg, z_bg = height - 0.10, height
    rows = range(200, 280)
    widths = []
    for row in rows:
        box_cols = np.flatnonzero(np.abs(truth[row] - z_fg) < 1e-4)
        left_edge = box_cols[0]
        widths.append(np.sum(depth[row, left_edge - 25 : left_edge] == 0))  # the hole, whatever fattening did
        assert depth[row, left_edge - 25] > 0
        assert np.all(depth[row, box_cols[-1] + 3 : box_cols[-1] + 40] > 0)  # no hole on the right
    predicted = spec.depth.fx * spec.baseline_m * (1 / z_fg - 1 / z_bg)
    assert np.median(widths) == pytest.approx(predicted, abs=1.5)  # edge fattening may fill a pixel


def test_realistic_min_depth(floor_scene) -> None:
    model, data = floor_scene
    spec = make_camera_spec()
    assert spec.min_depth_m == pytest.approx(0.152, abs=0.003)
    with TwinCamera(model, spec, TwinCameraSettings(render_ir=False), seed=1) as cam:
        too_close = cam.capture(data, looking_down(0.9 * spec.min_depth_m))
        just_far = cam.capture(data, looking_down(1.1 * spec.min_depth_m))
    assert np.all(too_close["depth"] == 0) and np.all(too_close["truth"]["depth_m"] > 0)
    assert np.mean(just_far["depth"][:, 400:] > 0) > 0.99


def test_realistic_noise_is_spatially_correlated(floor_scene) -> None:
    model, data = floor_scene
    with TwinCamera(model, make_camera_spec(), TwinCameraSettings(render_ir=False), seed=4) as cam:
        frames = cam.capture(data, looking_down(0.6))
    err = (frames["depth_m"] - frames["truth"]["depth_m"])[140:340, 260:460]
    assert np.corrcoef(err[:, :-1].ravel(), err[:, 1:].ravel())[0, 1] > 0.5


def test_dark_material_drops_out(box_scene) -> None:
    model, data = box_scene
    dropouts = dark_geom_dropouts(model)
    dark = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "dark")
    assert set(dropouts) == {dark, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "mirror")}
    with TwinCamera(
        model, make_camera_spec(), TwinCameraSettings(render_ir=False), seed=6, dropout_geoms=dropouts
    ) as cam:
        frames = cam.capture(data, looking_down(0.5))
    on_dark = frames["truth"]["geom_id"] == dark
    floor = frames["truth"]["geom_id"] == mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    floor[:, :100] = False  # beyond the left band
    assert on_dark.sum() > 2000
    assert np.mean(frames["depth"][on_dark] == 0) == pytest.approx(0.7, abs=0.2)
    assert np.mean(frames["depth"][floor] == 0) < 0.05  # occlusion holes beside the block only
    with pytest.raises(ConfigError, match="not a geom"):
        TwinCamera(model, make_camera_spec(), dropout_geoms={"nope": 0.5})


# -- IR, determinism, SGBM ------------------------------------------------------------------------------
def test_ir_dots_are_projected_through_the_geometry(floor_scene) -> None:
    model, data = floor_scene
    spec = make_camera_spec()
    z = 0.45
    settings = TwinCameraSettings.from_profile("ideal")
    with TwinCamera(model, spec, settings, seed=9) as cam:
        frames = cam.capture(data, looking_down(z))
        moved = cam.capture(data, looking_down(z, xy=(0.01, 0.0)))  # 1 cm along camera +x
    ir1, ir2 = frames["ir1"].astype(float), frames["ir2"].astype(float)
    d = round(spec.depth.fx * spec.baseline_m / z)
    rows, cols = slice(100, 380), slice(200, 560)
    shifted = (slice(100, 380), slice(200 - d, 560 - d))
    corr_matched = np.corrcoef(ir1[rows, cols].ravel(), ir2[shifted].ravel())[0, 1]
    corr_unshifted = np.corrcoef(ir1[rows, cols].ravel(), ir2[rows, cols].ravel())[0, 1]
    assert corr_matched > 0.9 and corr_unshifted < 0.3
    # Moving the camera does not drag the pattern along: the projector moves too, so on a plane the
    # dots stay in place in the image (the defining property of a projector fixed to the camera).
    assert (
        np.corrcoef(
            frames["ir1"][rows, cols].ravel().astype(float), moved["ir1"][rows, cols].ravel().astype(float)
        )[0, 1]
        > 0.9
    )
    assert frames["ir1"][rows, cols].std() > 10  # dots give texture


def test_same_seed_same_frames_different_seed_different_noise(box_scene) -> None:
    model, data = box_scene
    spec = make_camera_spec()
    renderer = SceneRenderer(model, 640, 480)
    try:
        runs = []
        for seed in (1, 1, 2):
            cam = TwinCamera(model, spec, TwinCameraSettings(), seed=seed, renderer=renderer)
            runs.append([cam.capture(data, looking_down(0.5, rot_x(5))) for _ in range(2)])
    finally:
        renderer.close()
    for a, b in zip(runs[0], runs[1], strict=True):
        for key in ("color", "depth", "ir1", "ir2"):
            assert np.array_equal(a[key], b[key]), key
    for a, c in zip(runs[0], runs[2], strict=True):
        for key in ("color", "depth", "ir1", "ir2"):
            assert not np.array_equal(a[key], c[key]), key
        assert np.array_equal(a["truth"]["depth_m"], c["truth"]["depth_m"])
    assert not np.array_equal(runs[0][0]["depth"], runs[0][1]["depth"])  # frames differ over time


def test_sgbm_mode_measures_a_textured_plane(floor_scene) -> None:
    model, data = floor_scene
    spec = make_camera_spec()
    z = 0.45
    settings = TwinCameraSettings(depth_mode="sgbm", segmentation=False)
    with TwinCamera(model, spec, settings, seed=2) as cam:
        frames = cam.capture(data, looking_down(z))
    depth = frames["depth_m"]
    roi = (slice(60, 420), slice(140, 600))  # right of the left band (about 43 px)
    valid = depth[roi] > 0
    assert valid.mean() > 0.95
    fb = spec.depth.fx * spec.baseline_m
    disparity_error = fb / depth[roi][valid] - fb / z
    assert np.median(np.abs(disparity_error)) < 0.5  # SGBM locks to whole pixels, never further
    effective_subpixel = plane_rms_m(depth, roi) * fb / z**2
    # Facts: SGBM on a rendered dot pair has about twice a D4's noise (0.16-0.20 px) and strong
    # pixel-locking, which at this distance (disparity 42.6 px) spreads values between 42.5 and 43.
    assert 0.1 < effective_subpixel < 0.4
    assert np.all(depth[100:380, :30] == 0)  # no match left of the right image's field of view


def test_profiles_and_settings_are_validated(floor_scene) -> None:
    with pytest.raises(ConfigError, match="profiles: ideal, realistic"):
        TwinCameraSettings.from_profile("noisy")
    with pytest.raises(ConfigError, match="needs the IR"):
        TwinCameraSettings(depth_mode="sgbm", render_ir=False)
    with pytest.raises(ConfigError, match="depth mode"):
        TwinCameraSettings(depth_mode="tof")
    model, data = floor_scene
    with TwinCamera(
        model,
        make_camera_spec(),
        TwinCameraSettings(render_ir=False),
        seed=0,
        dropout_geoms={np.int64(0): 0.5},
    ) as cam:
        with pytest.raises(TwinError, match="4x4"):
            cam.capture(data, np.eye(4)[:3])
        with pytest.raises(TwinError, match="finite"):
            cam.capture(data, np.full((4, 4), np.nan))
        assert cam.capture(data, looking_down(0.5))["truth"]["geom_id"] is not None
    with pytest.raises(ConfigError, match=r"must be in \[0, 1\]"):
        TwinCamera(model, make_camera_spec(), dropout_geoms={"floor": 1.5})


# -- camera spec -----------------------------------------------------------------------------------------
def test_camera_spec_scales_intrinsics_and_composes_extrinsics() -> None:
    unit = draw_unit(5)
    base = make_camera_spec(unit)
    assert 382 <= base.depth.fx <= 385 and 319 <= base.depth.ppx <= 322 and 236 <= base.depth.ppy <= 246
    assert 606 <= base.color.fx <= 615 and 314 <= base.color.ppx <= 323
    hd = make_camera_spec(unit, depth_resolution=(1280, 720), colour_resolution=(1280, 720))
    assert hd.depth.fx == pytest.approx(base.depth.fx / 0.6)  # 640x480 is the full sensor scaled by 0.6
    assert hd.color.fx == pytest.approx(base.color.fx * 1.5)  # colour 640x480 is 1920x1080 scaled by 4/9
    assert (hd.depth.ppx - 639.5) == pytest.approx((base.depth.ppx - 319.5) / 0.6)
    small = make_camera_spec(unit, depth_resolution=(424, 240))
    assert small.depth.fx == pytest.approx(base.depth.fx * (424 / 1280) / 0.6)
    assert hd.min_depth_m == pytest.approx(base.min_depth_m / 0.6)
    back = with_resolution(with_resolution(base, (848, 480), (1280, 720)), (640, 480), (640, 480))
    assert back.depth.fx == pytest.approx(base.depth.fx) and back.depth.fy == pytest.approx(base.depth.fy)
    assert back.depth.ppy == pytest.approx(base.depth.ppy) and back.color.ppx == pytest.approx(base.color.ppx)
    # Same unit twice -> identical; other seed -> different.
    assert draw_unit(5) == unit and draw_unit(6) != unit
    # Extrinsics: librealsense direction and composition.
    assert np.allclose(base.extrinsics("depth", "color"), base.T_color_depth)
    assert np.allclose(base.extrinsics("depth", "ir2")[:3, 3], [-unit.baseline_m, 0, 0])
    T_ir2_color = base.extrinsics("color", "ir2")
    assert np.allclose(T_ir2_color, base.extrinsics("depth", "ir2") @ base.extrinsics("color", "depth"))
    angle = np.degrees(np.arccos((np.trace(base.T_color_depth[:3, :3]) - 1) / 2))
    assert angle < 0.4
    assert base.T_depth_stream("color")[0, 3] == pytest.approx(-unit.t_color_depth_m[0], abs=1e-4)
    profiles = base.stream_profiles()
    assert set(profiles) == {"depth", "color", "ir1", "ir2", "accel", "gyro"}
    assert profiles["depth"].format == "z16" and profiles["color"].format == "bgr8"
    assert profiles["ir2"].rs_name == "Infrared_2" and profiles["ir2"].intrinsics == base.depth
    assert profiles["color"].intrinsics.model == "Inverse Brown Conrady"
    with pytest.raises(ConfigError, match="not a D435 mode"):
        make_camera_spec(depth_resolution=(1000, 500))
    with pytest.raises(ConfigError, match="frame rates"):
        make_camera_spec(fps=25)


# -- IMU -----------------------------------------------------------------------------------------------------
def still(T: np.ndarray):
    return lambda t: np.repeat(T[None], np.size(t), axis=0)


@pytest.mark.parametrize("R_world_cam", [rot_x(-90.0), rot_x(180.0), rot_x(-60) @ rot_y(35) @ rot_z(20)])
def test_imu_still_camera_measures_gravity(R_world_cam: np.ndarray) -> None:
    T = np.eye(4)
    T[:3, :3] = R_world_cam
    imu = ImuSimulator(ImuSettings(), seed=4)
    samples = imu.sample(0.0, 2.0, still(T), accel_hz=250, gyro_hz=200)
    accel = samples["accel"]
    assert accel.shape == (500, 3) and samples["gyro"].shape == (400, 3)
    assert np.linalg.norm(accel.mean(axis=0)) == pytest.approx(9.81, abs=0.5)
    expected = R_world_cam.T @ np.array([0.0, 0.0, 9.80665])  # specific force points up
    assert np.allclose(accel.mean(axis=0) - imu.accel_bias, expected, atol=0.01)
    assert np.allclose(samples["gyro"].mean(axis=0), imu.gyro_bias, atol=0.002)
    if np.allclose(R_world_cam, rot_x(-90.0)):  # level camera, y down: librealsense reads (0, -g, 0)
        assert np.allclose(
            ImuSimulator(ImuSettings.ideal()).accel(np.zeros(1), still(T), 250)[0],
            [0, -9.80665, 0],
            atol=1e-6,
        )


def test_twin_camera_imu_uses_the_spec_rates(floor_scene) -> None:
    model, _ = floor_scene
    spec = make_camera_spec(accel_hz=63, gyro_hz=400)
    with TwinCamera(model, spec, TwinCameraSettings.from_profile("ideal"), seed=0) as cam:
        samples = cam.imu_samples(0.0, 1.0, still(looking_down(0.5)))
    assert samples["accel"].shape == (63, 3) and samples["gyro"].shape == (400, 3)
    assert np.allclose(samples["accel"], [0.0, 0.0, -9.80665], atol=1e-6)  # looking down: z_cam = -z_world
    assert np.allclose(samples["gyro"], 0.0, atol=1e-9)


def test_imu_rotating_camera_gyro_matches_angular_velocity() -> None:
    omega_body = np.array([0.3, -0.5, 0.8])  # rad/s in the camera frame

    def pose(t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(t)
        out = np.tile(np.eye(4), (t.size, 1, 1))
        for i, ti in enumerate(t):
            angle = np.linalg.norm(omega_body) * ti
            axis = omega_body / np.linalg.norm(omega_body)
            K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
            out[i, :3, :3] = rot_x(-70) @ (np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K)
            out[i, :3, 3] = [0.1 * ti, 0.0, 0.5]
        return out

    imu = ImuSimulator(ImuSettings(), seed=1)
    samples = imu.sample(0.0, 1.0, pose)
    assert np.allclose(samples["gyro"].mean(axis=0) - imu.gyro_bias, omega_body, atol=0.002)
    exact = ImuSimulator(ImuSettings.ideal()).gyro(np.linspace(0, 1, 7), pose, 200)
    assert np.allclose(exact, omega_body, atol=1e-6)
    # Constant velocity and a pure rotation about the IMU: the accelerometer sees gravity only.
    f = ImuSimulator(ImuSettings.ideal()).accel(np.linspace(0.1, 0.9, 5), pose, 250)
    assert np.allclose(np.linalg.norm(f, axis=1), 9.80665, atol=1e-4)
    # The same motion given as 30 Hz pose samples (spline fit) gives the same angular velocity.
    t = np.arange(0.0, 1.0 + 1e-9, 1 / 30)
    fitted = pose_function_from_samples(t, pose(t))
    assert np.allclose(
        ImuSimulator(ImuSettings.ideal()).gyro(np.linspace(0.2, 0.8, 5), fitted, 200), omega_body, atol=1e-3
    )


def test_imu_linear_acceleration_and_lever_arm() -> None:
    a_world = np.array([1.0, -2.0, 0.5])
    R = rot_x(-90.0)

    def pose(t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(t)
        out = np.tile(np.eye(4), (t.size, 1, 1))
        out[:, :3, :3] = R
        out[:, :3, 3] = 0.5 * t[:, None] ** 2 * a_world
        return out

    f = ImuSimulator(ImuSettings.ideal()).accel(np.array([0.3, 0.7]), pose, 250)
    assert np.allclose(f, R.T @ (a_world - np.array([0, 0, -9.80665])), atol=1e-5)
    w = 2.0  # spinning about the camera z axis with the IMU 5 cm off-axis: centripetal w^2 r inward

    def spin(t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(t)
        out = np.tile(np.eye(4), (t.size, 1, 1))
        for i, ti in enumerate(t):
            out[i, :3, :3] = rot_z(np.degrees(w * ti))
        return out

    lever = ImuSimulator(
        replace(ImuSettings.ideal(), t_depth_imu_m=(0.05, 0.0, 0.0), gravity_world=(0.0, 0.0, 0.0))
    )
    f = lever.accel(np.array([0.25]), spin, 250)[0]
    assert np.allclose(f, [-w * w * 0.05, 0.0, 0.0], atol=1e-4)


# -- the paper profile's per-frame disparity field ------------------------------------------------------
def test_frame_disparity_field_moves_depth_smoothly_per_frame_and_leaves_colour_alone(floor_scene) -> None:
    """The same seeded camera with and without the field (both with unit errors): colour is byte-identical and
    depth is the field-free depth moved by the frame's own field in the disparity domain, z / (1 + z e / (fx B)),
    with e regenerated from its documented stream (seed, frame, FIELD_STREAM)."""
    from darp.twin.camera.sensor import FIELD_STREAM, UnitErrors

    model, data = floor_scene
    spec = make_camera_spec()
    fb = spec.depth.fx * spec.baseline_m
    base = TwinCameraSettings.from_profile("realistic", render_ir=False, segmentation=False)
    plain = replace(base, errors=UnitErrors(noise_dn=1.0))
    errors = UnitErrors(noise_dn=1.0, field_disparity_px=0.2, focal_baseline_px_m=fb)
    fields, moved = [], {}
    field = replace(base, errors=errors)
    with TwinCamera(model, spec, plain, seed=4) as a, TwinCamera(model, spec, field, seed=4) as b:
        for k, distance_m in enumerate((0.30, 0.60)):
            fa, fb_ = a.capture(data, looking_down(distance_m)), b.capture(data, looking_down(distance_m))
            assert np.array_equal(fa["color"], fb_["color"])
            z = fa["depth_m"].astype(np.float64)
            e = errors.disparity_field(z.shape, np.random.default_rng([4, k, FIELD_STREAM]))
            expected = np.where(z > 0, z / (1.0 + z * e / fb), 0.0)
            assert np.allclose(fb_["depth_m"], expected, atol=2e-6)
            fields.append(e)
            valid = z > 0
            moved[distance_m] = float(np.std((fb_["depth_m"] - fa["depth_m"])[valid] / z[valid] ** 2))
    assert np.std(fields[0] - fields[1]) > 0.1  # a new field every frame (px)
    for e in fields:  # smooth: neighbouring pixels move together
        assert 0.08 < float(np.std(e)) < 0.3 and float(np.abs(np.diff(e, axis=1)).max()) < 0.01
    # depth error / z^2 is the same at both distances (disparity domain), about e / (fx B)
    for distance_m, e in zip((0.30, 0.60), fields, strict=True):
        assert moved[distance_m] == pytest.approx(float(np.std(e)) / fb, rel=0.15)
