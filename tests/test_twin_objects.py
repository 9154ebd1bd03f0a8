"""The twin's objects: sizes against the paper's table, mesh validity, placement, loading, export.

Open3D (manifoldness, ray casting, occupancy, PLY reading) and MuJoCo (mesh volume) are the oracles.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import mujoco
import numpy as np
import open3d as o3d
import pytest
import trimesh
from scipy.spatial import Delaunay

from darp.errors import DarpError, TwinError
from darp.twin.objects.model import (
    OBJECT_NAMES,
    PAPER_ENVELOPE_CM,
    DiscRegion,
    ObjectPlacement,
    RectRegion,
    canonical_name,
    load_mesh_object,
    make_object,
    plot_objects,
    random_placement,
    sample_surface,
    save_truth_mesh,
    to_world,
)
from darp.twin.objects.plot import render

PAPER_NAMES = [n for n in OBJECT_NAMES if PAPER_ENVELOPE_CM[n] is not None]
_CACHE: dict[str, object] = {}


def obj(name: str):
    """Objects are rebuilt only once per session (each build takes tens of milliseconds)."""
    if name not in _CACHE:
        _CACHE[name] = make_object(name)
    return _CACHE[name]


def o3d_mesh(mesh: trimesh.Trimesh) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices)),
                                     o3d.utility.Vector3iVector(np.asarray(mesh.faces)))


def raycast_scene(mesh: trimesh.Trimesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(o3d_mesh(mesh)))
    return scene


def first_hit_down(mesh: trimesh.Trimesh, x: float, y: float) -> float:
    """z of the first surface a ray going straight down from 1 m above (x, y) meets (-inf: none)."""
    rays = o3d.core.Tensor(np.array([[x, y, 1.0, 0.0, 0.0, -1.0]], np.float32))
    t = float(raycast_scene(mesh).cast_rays(rays)["t_hit"].numpy()[0])
    return 1.0 - t if math.isfinite(t) else -math.inf


# --- names -------------------------------------------------------------------------------------------

def test_ten_names_and_aliases() -> None:
    assert len(set(OBJECT_NAMES)) == 10
    for alias, name in (("Red Bull", "red_bull"), ("REDBULL", "red_bull"), ("game", "controller"),
                        ("Frame", "picture_frame"), ("weight", "paperweight"), ("picture-frame", "picture_frame"),
                        ("Mug", "mug")):
        assert canonical_name(alias) == name
    with pytest.raises(TwinError, match="unknown object 'teapot'.*red_bull"):
        make_object("teapot")


# --- sizes -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", PAPER_NAMES)
def test_envelope_within_15_percent_of_paper(name: str) -> None:
    o = obj(name)
    radius_cm, height_cm = PAPER_ENVELOPE_CM[name]
    assert o.paper_radius_m == pytest.approx(radius_cm / 100) and o.paper_height_m == pytest.approx(height_cm / 100)
    assert o.radius_m == pytest.approx(radius_cm / 100, rel=0.15)
    assert o.height_m == pytest.approx(height_cm / 100, rel=0.15)


def test_red_bull_is_a_250ml_slim_can() -> None:
    o = obj("red_bull")
    assert o.paper_radius_m is None and o.paper_height_m is None
    assert 2 * o.radius_m == pytest.approx(0.053, abs=0.001)
    assert o.height_m == pytest.approx(0.134, abs=0.002)
    assert o.mesh.volume == pytest.approx(250e-6 * 1.1, rel=0.1)  # liquid plus headspace and walls


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_envelope_matches_mesh_and_footprint_is_centred(name: str) -> None:
    o = obj(name)
    v = np.asarray(o.mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    assert np.allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)  # footprint centre at the origin
    assert lo[2] == pytest.approx(0.0, abs=1e-12) and hi[2] == pytest.approx(o.height_m)
    # the radius is the farthest point from the vertical axis: check against a dense surface sample
    pts, _ = trimesh.sample.sample_surface(o.mesh, 20000, seed=1)
    sampled = np.hypot(pts[:, 0], pts[:, 1]).max()
    assert sampled <= o.radius_m + 1e-9 and sampled >= 0.97 * o.radius_m


# --- mesh validity -----------------------------------------------------------------------------------

@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_mesh_is_closed_manifold_and_faces_point_outward(name: str) -> None:
    mesh = obj(name).mesh
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.area_faces.min() > 1e-9  # no slivers: smallest face above 0.001 mm^2
    legacy = o3d_mesh(mesh)
    assert legacy.is_edge_manifold(allow_boundary_edges=False) and legacy.is_vertex_manifold()
    for body in mesh.split(only_watertight=False):  # parts may overlap each other, a body never itself
        assert body.volume > 0 and not o3d_mesh(body).is_self_intersecting()
        # a point just outside each face is outside its body, a point just inside is inside
        scene = raycast_scene(body)
        c, n = body.triangles_center, body.face_normals
        out = scene.compute_occupancy(o3d.core.Tensor((c + 2e-4 * n).astype(np.float32))).numpy()
        inn = scene.compute_occupancy(o3d.core.Tensor((c - 2e-4 * n).astype(np.float32))).numpy()
        assert out.sum() == 0 and inn.all()


@pytest.mark.parametrize("name", ["red_bull", "cup", "ketchup", "mug"])
def test_mujoco_measures_the_same_volume(name: str) -> None:
    mesh = obj(name).mesh
    vertex = " ".join(f"{x:.9f}" for x in np.asarray(mesh.vertices).ravel())
    face = " ".join(map(str, np.asarray(mesh.faces).ravel()))
    xml = (f'<mujoco><asset><mesh name="m" inertia="exact" vertex="{vertex}" face="{face}"/></asset>'
           '<worldbody><body><freejoint/><geom type="mesh" mesh="m" density="1000"/></body></worldbody></mujoco>')
    model = mujoco.MjModel.from_xml_string(xml)
    assert model.body_mass[1] / 1000.0 == pytest.approx(mesh.volume, rel=1e-4)


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_rests_stably_on_the_table(name: str) -> None:
    mesh = obj(name).mesh
    v = np.asarray(mesh.vertices)
    contact = v[v[:, 2] < 5e-4, :2]
    assert len(contact) >= 3
    support = Delaunay(contact, qhull_options="QJ")
    assert support.find_simplex(mesh.center_mass[:2]) >= 0  # centre of mass above the support polygon


@pytest.mark.parametrize("name", ["mug", "cup"])
def test_vessels_are_open_with_walls(name: str) -> None:
    o = obj(name)
    axis_xy = o.part("inside").mesh.vertices[:, :2].mean(axis=0)
    floor = first_hit_down(o.mesh, *axis_xy)
    assert 0.0 < floor < 0.2 * o.height_m  # the ray falls to the inner bottom: open top
    assert o.mesh.volume < 0.35 * math.pi * o.radius_m**2 * o.height_m  # hollow, not a solid


@pytest.mark.parametrize("name", ["red_bull", "ketchup", "paperweight"])
def test_closed_objects_stop_a_ray_at_their_top(name: str) -> None:
    o = obj(name)
    assert first_hit_down(o.mesh, 0.0, 0.0) > 0.9 * o.height_m


def test_picture_frame_stands_upright_on_a_strut() -> None:
    o = obj("picture_frame")
    strut = o.part("strut").mesh
    assert strut.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-9)  # its foot is on the table
    photo = o.part("photo").mesh
    assert photo.face_normals[:, 1].max() < -0.9  # the photo faces -y, tilted back a little
    assert np.ptp(photo.vertices[:, 2]) > 0.12  # and it is upright: 15 cm tall


def test_surface_samples_skip_what_is_buried_inside_another_part() -> None:
    o = obj("dumbbell")
    pts, normals = sample_surface(o, 20000, seed=2)
    assert pts.shape == (20000, 3) and np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    distance = raycast_scene(o.mesh).compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    assert distance.max() < 1e-5  # on the surface (float32 ray casting: micrometres)
    # the grip runs 2 mm into each head (heads' inner faces at |x| = 3.65 cm): none of that is sampled
    def buried(p: np.ndarray) -> np.ndarray:  # grip surface between |x| = 3.65 and 3.85 cm
        radial = np.hypot(p[:, 1], p[:, 2] - 0.0183)
        return (np.abs(p[:, 0]) > 0.03651) & (np.abs(p[:, 0]) < 0.0386) & (radial < 0.0105 + 1e-6)

    assert not buried(pts).any()
    raw, _ = trimesh.sample.sample_surface(o.mesh, 20000, seed=2)
    assert buried(raw).sum() > 50  # a plain sample of the mesh does land there
    again, _ = sample_surface(o, 20000, seed=2)
    assert np.array_equal(pts, again)


# --- looks -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_parts_cover_the_mesh_with_valid_looks(name: str) -> None:
    o = obj(name)
    assert sum(p.mesh.area for p in o.parts) == pytest.approx(o.mesh.area, rel=1e-6)
    for p in o.parts:
        assert len(p.rgba) == 4 and all(0.0 <= c <= 1.0 for c in p.rgba)
        if p.texture is not None:
            assert p.texture.dtype == np.uint8 and p.texture.ndim == 3 and p.texture.shape[2] == 3
            assert p.uv is not None and p.uv.shape == (len(p.mesh.vertices), 2)
            assert np.all(p.uv >= -1e-9) and np.all(p.uv <= 1 + 1e-9)


def test_material_flags() -> None:
    assert obj("dumbbell").part("head_left").dark and obj("dumbbell").part("grip").specular
    assert obj("red_bull").part("top").specular and not obj("red_bull").part("wall").specular
    assert obj("clock").part("bezel").specular and obj("controller").part("shell").dark
    assert not any(p.transparent for name in OBJECT_NAMES for p in obj(name).parts)


def test_clock_face_texture_is_placed_upright_on_the_dial() -> None:
    face = obj("clock").part("face")
    v, uv = np.asarray(face.mesh.vertices), face.uv
    top = np.argmax(v[:, 2])  # the dial's top point maps to the image's top centre (the 12)
    assert uv[top] == pytest.approx([0.5, 1.0], abs=0.02)
    right = np.argmax(v[:, 0])
    assert uv[right] == pytest.approx([1.0, 0.5], abs=0.02)


# --- determinism and scale ---------------------------------------------------------------------------

def test_deterministic_for_a_seed_and_geometry_independent_of_it() -> None:
    a, b, c = make_object("clock", seed=5), make_object("clock", seed=5), make_object("clock", seed=6)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert np.array_equal(a.part("face").texture, b.part("face").texture)
    assert not np.array_equal(a.part("face").texture, c.part("face").texture)
    assert np.array_equal(a.mesh.vertices, obj("clock").mesh.vertices)


def test_scale() -> None:
    big = make_object("mug", scale=2.0)
    assert big.radius_m == pytest.approx(2 * obj("mug").radius_m)
    assert big.height_m == pytest.approx(2 * obj("mug").height_m)
    assert big.mesh.volume == pytest.approx(8 * obj("mug").mesh.volume)
    with pytest.raises(TwinError, match="scale"):
        make_object("mug", scale=0.0)


# --- user meshes -------------------------------------------------------------------------------------

def test_load_obj_stl_ply_recentred(tmp_path: Path) -> None:
    box = trimesh.creation.box((0.08, 0.04, 0.12))
    box.apply_translation((0.5, -0.3, 0.7))
    box.export(tmp_path / "box.obj")
    o = load_mesh_object(tmp_path / "box.obj")
    assert o.name == "box" and o.source.endswith("box.obj")
    assert o.height_m == pytest.approx(0.12) and o.radius_m == pytest.approx(math.hypot(0.04, 0.02))
    assert o.mesh.bounds[0] == pytest.approx([-0.04, -0.02, 0.0])

    y_up = trimesh.creation.cylinder(radius=0.03, height=0.1)
    y_up.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 2, [1, 0, 0]))  # axis to +y
    y_up.export(tmp_path / "can.stl")
    o = load_mesh_object(tmp_path / "can.stl", up="y", name="tin")
    assert o.name == "tin" and o.height_m == pytest.approx(0.1) and o.radius_m == pytest.approx(0.03, rel=0.01)

    millimetres = trimesh.creation.icosphere(radius=40.0)
    millimetres.export(tmp_path / "ball_mm.ply")
    o = load_mesh_object(tmp_path / "ball_mm.ply", scale=0.001)
    assert o.height_m == pytest.approx(0.08, rel=0.01) and o.mesh.is_watertight
    with pytest.raises(TwinError, match="ball_mm.ply.*millimetres"):
        load_mesh_object(tmp_path / "ball_mm.ply")


def test_load_keeps_a_texture(tmp_path: Path) -> None:
    wall = obj("red_bull").part("wall")
    wall.mesh.export(tmp_path / "wall.obj")  # writes the .mtl and the texture .png beside it
    loaded = load_mesh_object(tmp_path / "wall.obj").parts[0]
    assert loaded.texture is not None and np.array_equal(loaded.texture, wall.texture)
    assert loaded.uv is not None and loaded.uv.shape == (len(loaded.mesh.vertices), 2)


def test_load_bad_files_name_the_file(tmp_path: Path) -> None:
    (tmp_path / "garbage.obj").write_text("this is not a mesh\n")
    (tmp_path / "empty.ply").write_bytes(b"")
    (tmp_path / "cut.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\n")
    trimesh.creation.box((0.1, 0.1, 0.0)).export(tmp_path / "flat.stl")
    cases = [("garbage.obj", "no triangles"), ("empty.ply", "cannot read"), ("cut.ply", "cannot read"),
             ("flat.stl", "degenerate"), ("missing.obj", "no such mesh file")]
    for filename, problem in cases:
        with pytest.raises(TwinError, match=problem) as info:
            load_mesh_object(tmp_path / filename)
        assert filename in str(info.value) and isinstance(info.value, DarpError)
    with pytest.raises(TwinError, match="up must be"):
        load_mesh_object(tmp_path / "flat.stl", up="w")


# --- placement and export ----------------------------------------------------------------------------

def test_placement_transform_and_to_world() -> None:
    p = ObjectPlacement(0.4, -0.1, math.radians(30), table_z_m=0.02)
    T = p.T_world_object
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.linalg.det(T[:3, :3]) == pytest.approx(1)
    assert T @ np.array([0, 0, 0, 1.0]) == pytest.approx([0.4, -0.1, 0.02, 1.0])
    o = obj("mug")
    world = to_world(o, p)
    assert world.vertices[:, 2].min() == pytest.approx(0.02)
    d = np.hypot(world.vertices[:, 0] - 0.4, world.vertices[:, 1] + 0.1)
    assert d.max() == pytest.approx(o.radius_m)
    assert np.array_equal(o.mesh.vertices, obj("mug").mesh.vertices)  # the object frame is untouched


@pytest.mark.parametrize("region", [RectRegion(0.2, 0.6, -0.3, 0.1, table_z_m=0.01), DiscRegion(0.4, 0.0, 0.2)])
def test_random_placements_keep_the_object_inside(region) -> None:
    o = obj("picture_frame")
    rng = np.random.default_rng(3)
    yaws = []
    for _ in range(100):
        p = random_placement(rng, region, o.radius_m + 0.01)
        xy = to_world(o, p).vertices[:, :2]
        if isinstance(region, RectRegion):
            assert xy[:, 0].min() >= 0.2 and xy[:, 0].max() <= 0.6 and xy[:, 1].min() >= -0.3
            assert xy[:, 1].max() <= 0.1
        else:
            assert np.hypot(xy[:, 0] - 0.4, xy[:, 1]).max() <= 0.2
        assert p.table_z_m == region.table_z_m
        yaws.append(p.yaw_rad)
    assert min(yaws) < -2.5 and max(yaws) > 2.5  # yaw covers the circle
    assert random_placement(7, region, 0.05) == random_placement(7, region, 0.05)
    with pytest.raises(TwinError, match="too small"):
        random_placement(rng, region, 0.3)


def test_save_truth_mesh_reads_back_in_open3d(tmp_path: Path) -> None:
    o, p = obj("ketchup"), ObjectPlacement(0.35, 0.05, 1.0)
    path = save_truth_mesh(o, p, tmp_path / "truth" / "object.ply")
    back = o3d.io.read_triangle_mesh(str(path))
    expected = to_world(o, p)
    assert len(back.triangles) == len(expected.faces)
    assert np.allclose(np.asarray(back.vertices), expected.vertices, atol=1e-6)
    assert [f.name for f in path.parent.iterdir()] == ["object.ply"]  # no temporary left behind
    with pytest.raises(TwinError, match=r"\.ply"):
        save_truth_mesh(o, p, tmp_path / "object.stl")


def test_render_and_contact_sheet(tmp_path: Path) -> None:
    picture, px_per_m = render(obj("red_bull").parts, size_px=96)
    background = np.all(picture > 240, axis=2)
    assert 0.1 < 1 - background.mean() < 0.6 and px_per_m > 0
    blue = (picture[..., 2].astype(int) - picture[..., 0] > 40)  # the can's blue checks show
    assert blue.sum() > 20
    path = plot_objects(tmp_path / "sheet.png", ["cup", "frame"], panel_px=96)
    image = cv2.imread(str(path))
    assert image is not None and image.shape[1] > image.shape[0] and image.std() > 10
