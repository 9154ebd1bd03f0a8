"""Direct tests of the twin's fast paths against slow, obvious references.

- ``occluded_from_right_scanline`` (windowed minimum, ``mirrored``) and ``_window_min`` against brute-force
  loops written here from the geometric rule;
- ``geom_image_region`` and region-limited segmentation renders against full MuJoCo segmentation renders
  (and OpenCV's ``projectPoints`` for the box corners);
- ``BagWriter(lz4_acceleration=...)`` played back by pyrealsense2 and darp's reader, chunks parsed here;
- ``TwinCamera(segmentation=False)`` with dropout geoms against ``segmentation=True`` (same seed).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import lz4.frame
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from darp.errors import RecordingError, TwinError
from darp.formats.realsense.bag.reader import BagRecording
from darp.formats.realsense.bag.writer import BagWriter
from darp.formats.realsense.types import DeviceInfo, Intrinsics, StreamProfile
from darp.twin.camera.depth_model import _window_min, occluded_from_right_scanline
from darp.twin.camera.render import NO_GEOM, SceneRenderer, geom_image_region, mujoco
from darp.twin.camera.sensor import TwinCamera, TwinCameraSettings
from darp.twin.camera.spec import make_camera_spec
from helpers.realsense_playback import play_back


# ======================================================================================================
# 1. occlusion scan and windowed minimum
# ======================================================================================================
def brute_force_occlusion(disparity_px: np.ndarray, mirrored: bool = False) -> np.ndarray:
    """Per row: left pixel u with d > 0 lands at u - d in the other image; it is hidden when any pixel
    right of it that has a surface lands at or left of it. ``mirrored``: the same on mirrored rows."""
    d = np.asarray(disparity_px, np.float32)
    if mirrored:
        return brute_force_occlusion(d[:, ::-1])[:, ::-1]
    h, w = d.shape
    hidden = np.zeros((h, w), bool)
    for row in range(h):
        for i in range(w):
            if not d[row, i] > 0:
                continue
            x_i = np.float32(i) - d[row, i]
            for j in range(i + 1, w):
                if d[row, j] > 0 and np.float32(j) - d[row, j] <= x_i:
                    hidden[row, i] = True
                    break
    return hidden


def disparity_cases() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    cases: dict[str, np.ndarray] = {}
    # Piecewise-constant rows (foreground/background steps) with holes; 1/32 px steps like the D4.
    h, w = 12, 90
    steps = np.zeros((h, w), np.float32)
    for row in range(h):
        cuts = np.sort(rng.choice(np.arange(1, w), 6, replace=False))
        level = rng.uniform(2, 25, 7)
        steps[row] = np.repeat(level, np.diff(np.r_[0, cuts, w]))
    steps = np.round(steps * 32) / 32
    steps[rng.random((h, w)) < 0.1] = 0.0
    cases["steps_and_holes"] = steps.astype(np.float32)
    # Integer disparities: many exact ties (a pixel landing exactly on another's column).
    cases["integer_ties"] = rng.integers(0, 9, (10, 60)).astype(np.float32)
    # Smooth slanted surfaces plus noise (what the depth model feeds it), a few NaN/negative/inf pixels.
    u = np.arange(120, dtype=np.float32)[None, :]
    smooth = 30 + 10 * np.sin(u / 9.0 + np.arange(8)[:, None]) + rng.normal(0, 0.3, (8, 120))
    smooth = smooth.astype(np.float32)
    smooth[2, 10:30] = 0.0
    smooth[3, 40] = np.nan
    smooth[4, 50:55] = -3.0
    smooth[5, 70] = np.inf  # surface at z ~ 0: hides every surface pixel left of it in its row
    cases["smooth_with_specials"] = smooth
    # Disparities far larger than the width (span clipped to the row) and tiny ones (span 3).
    cases["huge"] = rng.uniform(50, 400, (6, 40)).astype(np.float32)
    tiny = rng.uniform(0, 2e-3, (6, 40)).astype(np.float32)
    tiny[:, 20] = 1.5  # one nearer column among tiny disparities
    cases["tiny"] = tiny
    # Far-background pixels and sparse near spikes: hiders at every distance up to the largest disparity.
    spikes = rng.uniform(0.01, 0.5, (10, 80)).astype(np.float32)
    near = rng.random((10, 80)) < 0.05
    spikes[near] = rng.uniform(5, 20, near.sum())
    cases["sparse_spikes"] = spikes
    cases["width_1"] = rng.uniform(0, 5, (5, 1)).astype(np.float32)
    cases["width_2"] = np.array([[3, 4], [4, 3], [0, 9], [2, 0], [1, 2.5], [5, 6]], np.float32)
    cases["no_surface"] = np.where(rng.random((6, 30)) < 0.5, 0.0, -rng.uniform(0, 5, (6, 30))).astype(np.float32)
    return cases


CASES = disparity_cases()


@pytest.mark.parametrize("mirrored", [False, True])
@pytest.mark.parametrize("name", list(CASES))
def test_scanline_occlusion_equals_brute_force(name: str, mirrored: bool) -> None:
    d = CASES[name]
    got = occluded_from_right_scanline(d, mirrored=mirrored)
    expected = brute_force_occlusion(d, mirrored=mirrored)
    assert got.dtype == bool and got.shape == d.shape
    np.testing.assert_array_equal(got, expected)
    if name in ("steps_and_holes", "integer_ties", "smooth_with_specials", "huge", "sparse_spikes"):
        assert expected.any() and not expected.all()  # the case exercises both outcomes
    if name == "no_surface":
        assert not got.any()


def test_scanline_occlusion_rules_on_hand_made_rows() -> None:
    # A nearer pixel right of a farther one: hidden when it lands at or left of it (0 - 3 = 1 - 4).
    assert occluded_from_right_scanline(np.array([[3, 4, 0, 0]], np.float32)).tolist() == [[True, False, False, False]]
    assert occluded_from_right_scanline(np.array([[3, 3.9, 0, 0]], np.float32)).tolist() == [[False] * 4]
    # The farthest possible hider: 10 columns right with 10 px more disparity (the row's maximum).
    far = np.zeros((1, 14), np.float32)
    far[0, 2], far[0, 12] = 0.25, 10.25
    assert occluded_from_right_scanline(far)[0].tolist() == [False, False, True] + [False] * 11
    far[0, 12] = 10.2  # lands 0.05 px right of it: visible
    assert not occluded_from_right_scanline(far).any()
    # Mirrored: the other camera on the left, so the nearer pixel must be on the left.
    row = np.array([[0, 0, 4, 3]], np.float32)
    assert occluded_from_right_scanline(row, mirrored=True).tolist() == [[False, False, False, True]]
    assert not occluded_from_right_scanline(row).any()
    # Mirroring the rows by hand gives the mirrored answer on random data.
    d = CASES["steps_and_holes"]
    np.testing.assert_array_equal(occluded_from_right_scanline(d, mirrored=True),
                                  occluded_from_right_scanline(d[:, ::-1])[:, ::-1])


def naive_window_min(x: np.ndarray, span: int, leftward: bool) -> np.ndarray:
    """Per pixel, ``fmin`` over the ``span`` columns right (left) of it; columns beyond the image are inf."""
    h, w = x.shape
    out = np.empty((h, w), np.float32)
    for row in range(h):
        for i in range(w):
            lo, hi = (i - span, i) if leftward else (i + 1, i + 1 + span)
            cells = list(x[row, max(lo, 0) : min(hi, w)])
            if lo < 0 or hi > w:
                cells.append(np.float32(np.inf))
            out[row, i] = np.fmin.reduce(np.array(cells, np.float32))
    return out


@pytest.mark.parametrize("leftward", [False, True])
def test_window_min_equals_naive_loop(leftward: bool) -> None:
    rng = np.random.default_rng(3)
    h, w = 5, 37
    x = rng.normal(0, 10, (h, w)).astype(np.float32)
    x[rng.random((h, w)) < 0.1] = np.inf
    x[rng.random((h, w)) < 0.1] = np.nan
    x[1, 5:25] = np.nan  # a run of NaN longer than the small spans
    x[2, 3] = -np.inf
    x[3] = np.nan  # a whole row of NaN
    for span in (1, 2, 3, 5, 7, 8, 13, 16, 31, w - 1, w, w + 1, 3 * w):
        got = _window_min(x, span, leftward=leftward)
        assert got.shape == (h, w) and got.dtype == np.float32
        np.testing.assert_array_equal(got, naive_window_min(x, span, leftward), err_msg=f"span {span}")
    # x itself is left alone
    assert np.isnan(x[3]).all() and x[2, 3] == -np.inf


@pytest.mark.parametrize("leftward", [False, True])
def test_window_min_on_narrow_images(leftward: bool) -> None:
    for w in (1, 2, 3):
        x = np.arange(4 * w, dtype=np.float32).reshape(4, w)[:, ::-1].copy()
        for span in (1, 2, 5):
            np.testing.assert_array_equal(_window_min(x, span, leftward=leftward), naive_window_min(x, span, leftward))


# ======================================================================================================
# 2. image regions of geoms and region-limited segmentation renders
# ======================================================================================================
def pose(R: np.ndarray, t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


DOWN = Rotation.from_euler("x", 180, degrees=True).as_matrix()  # camera +z = world -z
UP = np.eye(3)  # camera +z = world +z


@pytest.fixture(scope="module")
def scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    spec = mujoco.MjSpec()
    spec.worldbody.add_light(pos=[0.2, 0.1, 2.0], dir=[0, 0, -1], diffuse=[0.6] * 3, castshadow=False)
    G = mujoco.mjtGeom
    spec.worldbody.add_geom(name="floor", type=G.mjGEOM_BOX, size=[1.5, 1.5, 0.01], pos=[0, 0, -0.01])
    spec.worldbody.add_geom(name="ball", type=G.mjGEOM_SPHERE, size=[0.05, 0, 0], pos=[0.06, 0.03, 0.05])
    spec.worldbody.add_geom(name="cube", type=G.mjGEOM_BOX, size=[0.03, 0.04, 0.05], pos=[-0.09, -0.04, 0.06],
                            euler=[0, 0, 30])
    spec.worldbody.add_geom(name="capsule", type=G.mjGEOM_CAPSULE, size=[0.02, 0.06, 0], pos=[0.1, -0.12, 0.03],
                            euler=[80, 10, 0])
    # An asymmetric mesh: MuJoCo recentres it, so its bounding box is off the geom origin.
    spec.add_mesh(name="wedge", uservert=[0, 0, 0, 0.1, 0, 0, 0, 0.05, 0, 0, 0, 0.03, 0.1, 0, 0.03, 0, 0.05, 0.03])
    spec.worldbody.add_geom(name="wedge", type=G.mjGEOM_MESH, meshname="wedge", pos=[-0.08, 0.12, 0.02],
                            euler=[20, -30, 50])
    spec.worldbody.add_geom(name="pillar", type=G.mjGEOM_BOX, size=[0.02, 0.02, 0.4], pos=[0.4, 0.4, 0.4])
    spec.worldbody.add_geom(name="lamp", type=G.mjGEOM_SPHERE, size=[0.02, 0, 0], pos=[0.0, 0.05, 0.7])
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


INTR = Intrinsics(320, 240, 250.3, 252.1, 161.2, 118.7)  # fx != fy, off-centre principal point


def gid(model: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)


def projected_box_corners(model, data, ids, T_world_cam, intr) -> np.ndarray:
    """Pixel coordinates of the geoms' bounding-box corners, by OpenCV's projectPoints."""
    corners = []
    for g in ids:
        centre, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        local = np.array([centre + half * s for s in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3)])
        corners.append(local @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g])
    T_cam_world = np.linalg.inv(T_world_cam)
    K = np.array([[intr.fx, 0, intr.ppx], [0, intr.fy, intr.ppy], [0, 0, 1]])
    uv, _ = cv2.projectPoints(np.concatenate(corners), cv2.Rodrigues(T_cam_world[:3, :3])[0], T_cam_world[:3, 3], K,
                              None)
    return uv.reshape(-1, 2)


def random_views(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(n):
        tilt = Rotation.from_euler("xyz", rng.uniform(-25, 25, 3), degrees=True).as_matrix()
        views.append(pose(DOWN @ tilt, (*rng.uniform(-0.12, 0.12, 2), rng.uniform(0.22, 0.5))))
    return views


def test_geom_region_holds_every_pixel_of_the_geom_and_region_render_matches(scene) -> None:
    model, data = scene
    names = ("ball", "cube", "capsule", "wedge")
    groups = [[gid(model, n)] for n in names] + [[gid(model, "ball"), gid(model, "wedge")]]
    seen_partial = seen_inside = 0
    with SceneRenderer(model, 400, 300) as renderer:  # buffer larger than the image
        renderer.update_scene(data)
        for T in random_views(14, seed=1):
            full = renderer.render_segmentation(T, INTR)
            full_again = full.copy()
            for ids in groups:
                region = geom_image_region(model, data, np.array(ids), T, INTR)
                pixels = np.isin(full, ids)
                if region is None:
                    assert not pixels.any(), (ids, T)
                    continue
                u0, v0, u1, v1 = region
                assert 0 <= u0 < u1 <= INTR.width and 0 <= v0 < v1 <= INTR.height
                inside = np.zeros(full.shape, bool)
                inside[v0:v1, u0:u1] = True
                assert inside[pixels].all(), (ids, region)
                # Tight: the box corners' pixel bounds plus at most the 2 px margin (OpenCV projects them).
                uv = projected_box_corners(model, data, ids, T, INTR)
                assert u0 >= max(0, np.floor(uv[:, 0].min()) - 2) and v0 >= max(0, np.floor(uv[:, 1].min()) - 2)
                assert u1 <= min(INTR.width, np.ceil(uv[:, 0].max()) + 3)
                assert v1 <= min(INTR.height, np.ceil(uv[:, 1].max()) + 3)
                assert u0 <= max(0, np.floor(uv[:, 0].min())) and v0 <= max(0, np.floor(uv[:, 1].min()))
                part = renderer.render_segmentation(T, INTR, region=region)
                assert part.shape == full.shape and part.dtype == np.int32
                np.testing.assert_array_equal(part[inside], full[inside])
                assert np.all(part[~inside] == NO_GEOM)
                seen_inside += int(pixels.sum() > 0)
                seen_partial += int((u1 - u0) * (v1 - v0) < INTR.width * INTR.height)
            # Renders reuse read-back buffers: an earlier result must not change under later renders.
            np.testing.assert_array_equal(full, full_again)
            np.testing.assert_array_equal(renderer.render_segmentation(T, INTR), full)
    assert seen_inside >= 30 and seen_partial >= 30  # the views really put geoms in view, in sub-images


def test_region_render_of_arbitrary_rectangles(scene) -> None:
    model, data = scene
    T = pose(DOWN, (0.0, 0.0, 0.35))
    w, h = INTR.width, INTR.height
    with SceneRenderer(model, w, h) as renderer:
        renderer.update_scene(data)
        full = renderer.render_segmentation(T, INTR)
        assert len(np.unique(full)) >= 4
        for region in [(0, 0, w, h), (0, 0, 1, 1), (w - 1, h - 1, w, h), (0, 100, w, 101), (150, 0, 151, h),
                       (37, 11, 203, 190), (200, 150, w, h)]:
            u0, v0, u1, v1 = region
            part = renderer.render_segmentation(T, INTR, region=region)
            np.testing.assert_array_equal(part[v0:v1, u0:u1], full[v0:v1, u0:u1], err_msg=str(region))
            outside = np.ones(full.shape, bool)
            outside[v0:v1, u0:u1] = False
            assert np.all(part[outside] == NO_GEOM)
        # Read-back buffers are kept between renders: outputs must be copies, and a region render in
        # between must not change the next full view (viewport back to the whole image).
        before = renderer.render_view(T, INTR)
        kept_rgb, kept_depth = before.rgb.copy(), before.depth_m.copy()
        renderer.render_segmentation(T, INTR, region=(37, 11, 203, 190))
        other = renderer.render_view(pose(DOWN, (0.05, -0.02, 0.5)), INTR)
        assert not np.array_equal(other.depth_m, kept_depth)
        np.testing.assert_array_equal(before.rgb, kept_rgb)
        np.testing.assert_array_equal(before.depth_m, kept_depth)
        after = renderer.render_view(T, INTR)
        np.testing.assert_array_equal(after.rgb, kept_rgb)
        np.testing.assert_array_equal(after.depth_m, kept_depth)
        for bad in [(-1, 0, 10, 10), (0, -1, 10, 10), (0, 0, w + 1, h), (0, 0, w, h + 1), (5, 5, 5, 10),
                    (5, 5, 10, 5), (10, 0, 5, 10), (w, 0, w + 5, 10)]:
            with pytest.raises(TwinError, match="not inside"):
                renderer.render_segmentation(T, INTR, region=bad)


def test_geom_region_none_behind_or_out_of_view_whole_when_straddling(scene) -> None:
    model, data = scene
    ball, cube, pillar = gid(model, "ball"), gid(model, "cube"), gid(model, "pillar")
    whole = (0, 0, INTR.width, INTR.height)
    with SceneRenderer(model, INTR.width, INTR.height) as renderer:
        renderer.update_scene(data)
        # Looking up from above the objects: everything is behind the camera.
        T_up = pose(UP, (0.0, 0.0, 0.3))
        assert geom_image_region(model, data, np.array([ball, cube]), T_up, INTR) is None
        assert not np.isin(renderer.render_segmentation(T_up, INTR), [ball, cube]).any()
        # Looking down far to the side: in front of the camera but outside the image.
        T_side = pose(DOWN, (0.7, -0.5, 0.35))
        assert geom_image_region(model, data, np.array([ball]), T_side, INTR) is None
        assert not np.any(renderer.render_segmentation(T_side, INTR) == ball)
        # Beside the 80 cm pillar at 30 cm height: its box crosses the camera plane -> the whole image,
        # and the pillar (below the camera) is indeed in the image.
        T_pillar = pose(DOWN, (0.3, 0.3, 0.3))
        assert geom_image_region(model, data, np.array([pillar]), T_pillar, INTR) == whole
        seen = renderer.render_segmentation(T_pillar, INTR) == pillar
        assert 100 < seen.sum() < seen.size
        # Mixed, looking up at the lamp: the ball behind is ignored, the lamp in front gets its region.
        lamp = gid(model, "lamp")
        front = geom_image_region(model, data, np.array([lamp]), T_up, INTR)
        assert front is not None and front != whole
        assert geom_image_region(model, data, np.array([ball, lamp, cube]), T_up, INTR) == front
        u0, v0, u1, v1 = front
        seen = renderer.render_segmentation(T_up, INTR) == lamp
        assert seen.sum() > 100 and seen[v0:v1, u0:u1].sum() == seen.sum()
        assert geom_image_region(model, data, np.array([ball, pillar]), T_up, INTR) == whole
        assert geom_image_region(model, data, np.array([], int), T_up, INTR) is None


# ======================================================================================================
# 3. LZ4 fast mode of the bag writer
# ======================================================================================================
DEVICE = DeviceInfo("Intel RealSense D435I", "348522076490", "5.13.0.50", "0B3A", {"Product Line": "D400"})
W, H = 160, 120


def image_profiles() -> list[StreamProfile]:
    intr = Intrinsics(W, H, 0.6 * W, 0.6 * W, W / 2 - 0.3, H / 2 + 0.2, "Brown Conrady", (0.0,) * 5)
    return [StreamProfile("depth", "Depth", 0, 0, "z16", 30, W, H, intr),
            StreamProfile("ir1", "Infrared", 1, 0, "y8", 30, W, H, intr),
            StreamProfile("ir2", "Infrared", 2, 0, "y8", 30, W, H, intr),
            StreamProfile("color", "Color", 0, 1, "rgb8", 30, W, H, intr)]


def frame_images(n: int = 8) -> list[dict[str, np.ndarray]]:
    """Images like the twin's: smooth content plus sensor noise (compressible, but not trivially)."""
    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:H, 0:W]
    out = []
    for i in range(n):
        ramp = 700 + 3 * u + 2 * v + 40 * np.sin((u + 4 * i) / 11.0)
        depth = np.where((u - 80) ** 2 + (v - 60) ** 2 < 900, 450, ramp) + rng.integers(0, 3, (H, W))
        ir = np.clip(90 + 60 * np.sin(u / 5.0 + i) * np.cos(v / 7.0) + rng.normal(0, 2, (H, W)), 0, 255)
        colour = np.stack([(u * 255 // W), (v * 255 // H), np.full((H, W), 40 + i)], -1)
        out.append({"depth": depth.astype(np.uint16), "ir1": ir.astype(np.uint8),
                    "ir2": np.roll(ir, -7, axis=1).astype(np.uint8),
                    "color": (colour + rng.integers(0, 2, (H, W, 3))).astype(np.uint8)})
    return out


IMAGES = frame_images()


def write_bag(path: Path, **kwargs) -> Path:
    with BagWriter(path, DEVICE, image_profiles(), chunk_threshold=60_000, **kwargs) as writer:
        for i, images in enumerate(IMAGES):
            for key in ("depth", "ir1", "ir2", "color"):
                writer.write_image(key, images[key], 1_700_000_000_000.0 + 33.3 * i, 100 + i)
    return path


def bag_chunks(path: Path) -> list[tuple[str, int, bytes]]:
    """(compression, uncompressed size, stored data) of each chunk record, by walking the file's records."""
    raw = path.read_bytes()
    assert raw.startswith(b"#ROSBAG V2.0\n")
    pos, chunks = 13, []
    while pos < len(raw):
        (header_len,) = struct.unpack_from("<I", raw, pos)
        header, pos = raw[pos + 4 : pos + 4 + header_len], pos + 4 + header_len
        fields, k = {}, 0
        while k < len(header):
            (field_len,) = struct.unpack_from("<I", header, k)
            name, _, value = header[k + 4 : k + 4 + field_len].partition(b"=")
            fields[name.decode()] = value
            k += 4 + field_len
        (data_len,) = struct.unpack_from("<I", raw, pos)
        data, pos = raw[pos + 4 : pos + 4 + data_len], pos + 4 + data_len
        if fields["op"] == b"\x05":
            chunks.append((fields["compression"].decode(), struct.unpack("<I", fields["size"])[0], data))
    return chunks


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("lz4")
    return {"default": write_bag(folder / "default.bag"), "one": write_bag(folder / "one.bag", lz4_acceleration=1),
            "fast": write_bag(folder / "fast.bag", lz4_acceleration=2),
            "fastest": write_bag(folder / "fastest.bag", lz4_acceleration=np.int64(65537))}


def test_lz4_fast_bag_plays_back_in_pyrealsense2_with_identical_pixels(bags) -> None:
    played = play_back(bags["fast"])
    for key in ("depth", "ir1", "ir2", "color"):
        frames = played.frames[key]
        assert [f.frame_number for f in frames] == [100 + i for i in range(len(IMAGES))], key
        for frame, images in zip(frames, IMAGES, strict=True):
            assert frame.data.dtype == images[key].dtype and np.array_equal(frame.data, images[key]), key


@pytest.mark.parametrize("which", ["fast", "fastest"])
def test_lz4_fast_bag_reads_identically_in_darp(bags, which: str) -> None:
    with BagRecording(bags[which]) as fast, BagRecording(bags["default"]) as default:
        assert fast.compressions == ["lz4"] and not fast.truncated
        for key in ("depth", "ir1", "ir2", "color"):
            assert fast.frame_count(key) == len(IMAGES)
            assert fast.frame_infos(key) == default.frame_infos(key)
            for i, images in enumerate(IMAGES):
                assert np.array_equal(fast.read_frame(key, i).data, images[key]), (key, i)


def test_lz4_fast_chunks_are_lz4_frames_librealsense_reads(bags) -> None:
    fast, default, fastest = (bag_chunks(bags[k]) for k in ("fast", "default", "fastest"))
    assert len(fast) >= 4 and len(fast) == len(default) == len(fastest)
    for (c_fast, size_fast, data_fast), (c_def, size_def, data_def) in zip(fast, default, strict=True):
        assert c_fast == c_def == "lz4" and size_fast == size_def
        # LZ4 frame: magic, version 01, independent blocks, no block checksum, no content size, content
        # checksum, no dictionary; the same block-size byte as darp's default chunks (LZ4 lowers the
        # requested 4 MiB maximum to the smallest that holds the chunk).
        assert data_fast[:4] == data_def[:4] == b"\x04\x22\x4d\x18"
        assert data_fast[4] == data_def[4] == 0b0110_0100 and data_fast[5] == data_def[5]
        assert lz4.frame.decompress(data_fast) == lz4.frame.decompress(data_def)
        assert len(lz4.frame.decompress(data_fast)) == size_fast
    # The acceleration is really used: different streams, larger files the faster the mode.
    assert any(a[2] != b[2] for a, b in zip(fast, default, strict=True))
    sizes = {k: p.stat().st_size for k, p in bags.items()}
    assert sizes["default"] < sizes["fastest"] and sizes["default"] <= sizes["fast"] <= sizes["fastest"]


def test_lz4_acceleration_one_is_the_default(bags) -> None:
    assert bags["one"].read_bytes() == bags["default"].read_bytes()


@pytest.mark.parametrize("bad", [0, -1, 1.5, 70000, 65538, "2", None])
def test_invalid_lz4_acceleration_is_rejected_and_writes_nothing(tmp_path: Path, bad) -> None:
    path = tmp_path / "new_folder" / "cam.bag"
    with pytest.raises(RecordingError, match="lz4_acceleration") as err:
        BagWriter(path, DEVICE, image_profiles(), lz4_acceleration=bad)
    assert str(path) in str(err.value) and err.value.path == path
    assert list(tmp_path.iterdir()) == []  # no bag, no .partial, not even the folder


# ======================================================================================================
# 4. TwinCamera: dropout ids from the region pass when segmentation is off
# ======================================================================================================
@pytest.fixture(scope="module")
def dropout_scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    spec = mujoco.MjSpec()
    spec.worldbody.add_light(pos=[0.2, 0.1, 2.0], dir=[0, 0, -1], diffuse=[0.6] * 3, castshadow=False)
    G = mujoco.mjtGeom
    spec.worldbody.add_geom(name="floor", type=G.mjGEOM_BOX, size=[1.5, 1.5, 0.01], pos=[0, 0, -0.01],
                            rgba=[0.7, 0.7, 0.7, 1])
    spec.worldbody.add_geom(name="block", type=G.mjGEOM_BOX, size=[0.05, 0.05, 0.05], pos=[0, 0, 0.05],
                            rgba=[0.8, 0.8, 0.3, 1])
    spec.worldbody.add_geom(name="dark", type=G.mjGEOM_BOX, size=[0.05, 0.05, 0.001], pos=[0.0, 0.12, 0.001],
                            euler=[0, 0, 25], rgba=[0.03, 0.03, 0.03, 1])
    spec.worldbody.add_geom(name="glass", type=G.mjGEOM_SPHERE, size=[0.03, 0, 0], pos=[0.12, -0.08, 0.03],
                            rgba=[0.5, 0.6, 0.9, 0.3])
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


VIEWS = {
    "both_in_view": pose(DOWN @ Rotation.from_euler("xy", [6, -4], degrees=True).as_matrix(), (0.01, 0.02, 0.45)),
    "dark_only": pose(DOWN, (-0.05, 0.2, 0.3)),
    "none_in_view": pose(DOWN, (-0.6, 0.5, 0.4)),
}


@pytest.mark.parametrize("render_ir", [True, False])
def test_dropouts_without_segmentation_match_full_segmentation(dropout_scene, monkeypatch, render_ir: bool) -> None:
    model, data = dropout_scene
    spec = make_camera_spec(depth_resolution=(424, 240), colour_resolution=(424, 240))
    dark, glass = gid(model, "dark"), gid(model, "glass")
    dropouts = {"dark": 0.8, glass: 0.6}
    w, h = spec.depth.width, spec.depth.height
    renderer = SceneRenderer(model, w, h)
    try:
        with_ids = TwinCamera(model, spec, TwinCameraSettings(render_ir=render_ir), seed=11, renderer=renderer,
                              dropout_geoms=dropouts)
        without = TwinCamera(model, spec, TwinCameraSettings(render_ir=render_ir, segmentation=False), seed=11,
                             renderer=renderer, dropout_geoms=dropouts)
        no_dropouts = TwinCamera(model, spec, TwinCameraSettings(render_ir=render_ir), seed=11, renderer=renderer)
        regions: list = []
        original = renderer.render_segmentation

        def spy(*args, **kwargs):
            regions.append(kwargs.get("region"))
            return original(*args, **kwargs)

        for name, T in VIEWS.items():
            a = with_ids.capture(data, T)
            regions.clear()
            monkeypatch.setattr(renderer, "render_segmentation", spy)
            b = without.capture(data, T)
            monkeypatch.setattr(renderer, "render_segmentation", original)
            c = no_dropouts.capture(data, T)
            keys = ("depth", "depth_m", "color") + (("ir1", "ir2") if render_ir else ())
            for key in keys:
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name}: {key}")
            assert b["truth"]["geom_id"] is None
            ids = a["truth"]["geom_id"]
            on_dropout = np.isin(ids, [dark, glass])
            if render_ir:  # the ids came from one region-limited pass, around the dropout geoms only
                if name == "none_in_view":
                    assert regions == [] and not on_dropout.any()
                else:
                    assert len(regions) == 1 and regions[0] is not None
                    u0, v0, u1, v1 = regions[0]
                    assert (u1 - u0) * (v1 - v0) < 0.6 * w * h
                    inside = np.zeros((h, w), bool)
                    inside[v0:v1, u0:u1] = True
                    assert on_dropout.any() and inside[on_dropout].all()
            else:  # no IR: one flat full-image pass gives ids and depth
                assert regions == []
            if on_dropout.any():  # the dropouts really happen, on the dropout geoms
                dropped = (a["depth"] == 0) & (c["depth"] > 0)
                assert dropped[on_dropout].mean() > 0.3
                assert dropped[~on_dropout].mean() < 0.01
            else:
                np.testing.assert_array_equal(a["depth"], c["depth"])
    finally:
        renderer.close()
