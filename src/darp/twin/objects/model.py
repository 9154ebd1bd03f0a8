"""The digital twin's tabletop objects: the paper's ten, built parametrically, or any user mesh.

An object lives in its own frame: z up, resting on the table plane z=0, origin at the centre of its
footprint (the centre of the axis-aligned rectangle its shadow covers seen from above). Placing it
on the table is therefore a pure (x, y, yaw) transform, :class:`ObjectPlacement`. Its envelope
(``radius_m``: largest horizontal distance from the vertical axis through the origin; ``height_m``:
the top's height) is measured from the mesh and compared with the paper's release table
(``tab:release_composition``), which the acquisition's conservative envelope estimates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from darp.errors import TwinError
from darp.formats.atomic import atomic_path
from darp.kinematics.transforms import matvec
from darp.twin.objects.geometry import Piece
from darp.twin.objects.shapes import BUILDERS, ObjectPart, make_part

OBJECT_NAMES: tuple[str, ...] = ("red_bull", "dumbbell", "controller", "cube", "ketchup", "picture_frame",
                                 "mug", "paperweight", "clock", "cup")

# The paper's table: radius and height in cm (Red Bull has none). Kept in cm as printed.
PAPER_ENVELOPE_CM: dict[str, tuple[float, float] | None] = {
    "red_bull": None, "dumbbell": (6.90, 3.66), "controller": (5.78, 2.64), "cube": (4.31, 1.60),
    "ketchup": (4.41, 14.93), "picture_frame": (11.60, 19.07), "mug": (7.22, 6.30),
    "paperweight": (4.85, 7.44), "clock": (5.83, 9.95), "cup": (4.11, 10.16),
}

_ALIASES = {
    "redbull": "red_bull", "red_bull_can": "red_bull", "can": "red_bull",
    "game": "controller", "game_controller": "controller", "gamepad": "controller",
    "frame": "picture_frame", "photo_frame": "picture_frame",
    "weight": "paperweight", "paper_weight": "paperweight", "dumbell": "dumbbell",
    "ketchup_bottle": "ketchup", "desk_clock": "clock",
}


@dataclass
class TwinObject:
    """An object ready for the twin: its true mesh, its coloured parts and its measured envelope."""

    name: str
    mesh: trimesh.Trimesh
    parts: list[ObjectPart]
    radius_m: float
    height_m: float
    paper_radius_m: float | None = None
    paper_height_m: float | None = None
    source: str = "parametric"  # or the path of the mesh file it was loaded from

    def part(self, name: str) -> ObjectPart:
        """The part called ``name`` (TwinError listing the available parts otherwise)."""
        for p in self.parts:
            if p.name == name:
                return p
        raise TwinError(f"object {self.name!r} has no part {name!r}; parts: {[p.name for p in self.parts]}")


def canonical_name(name: str) -> str:
    """The canonical object name for ``name`` (case, spaces and hyphens ignored; aliases accepted)."""
    key = "_".join(str(name).strip().lower().replace("-", " ").split())
    key = _ALIASES.get(key, key)
    if key not in BUILDERS:
        raise TwinError(f"unknown object {name!r}; known objects: {', '.join(OBJECT_NAMES)}")
    return key


def make_object(name: str, *, scale: float = 1.0, seed: int | None = None) -> TwinObject:
    """Build one of the paper's objects. ``seed`` varies only its textures (clock time, photo, glaze);
    ``seed=None`` gives the canonical look. ``scale`` multiplies every dimension."""
    key = canonical_name(name)
    _check_scale(scale)
    rng = None if seed is None else np.random.default_rng(seed)
    obj = _finish(key, BUILDERS[key](rng), scale)
    paper = PAPER_ENVELOPE_CM[key]
    if paper is not None:
        obj.paper_radius_m, obj.paper_height_m = paper[0] / 100.0, paper[1] / 100.0
    return obj


def load_mesh_object(path: str | Path, *, scale: float = 1.0, name: str | None = None,
                     up: str = "z") -> TwinObject:
    """Load any mesh file trimesh reads (OBJ, PLY, STL, GLB, ...) as a twin object.

    Coordinates are taken as metres times ``scale`` (0.001 for a file in millimetres); ``up`` names
    the file's up axis ("z", "y", "x", or negated). The mesh is moved so that its lowest point is on
    z=0 and its footprint centre at the origin.
    """
    path = Path(path)
    _check_scale(scale, path)
    if not path.is_file():
        raise TwinError("no such mesh file" if not path.exists() else "not a file", path)
    try:
        loaded = trimesh.load(path, force="mesh")
    except Exception as err:  # trimesh raises many unrelated types for bad files
        raise TwinError(f"cannot read mesh: {type(err).__name__}: {err}", path) from err
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise TwinError("no triangles in the file", path)
    vertices = np.asarray(loaded.vertices, dtype=float)
    if not np.all(np.isfinite(vertices)):
        raise TwinError("vertices contain NaN or infinity", path)
    mesh = loaded.copy()
    mesh.apply_transform(_up_to_z(up, path) @ np.diag([scale, scale, scale, 1.0]))
    extents = mesh.extents
    if float(mesh.area) <= 1e-12 or float(np.min(extents)) < 1e-5:
        raise TwinError(f"degenerate mesh: extents {np.round(extents, 6).tolist()} m, area {mesh.area:.3g} m^2",
                        path)
    if float(np.max(extents)) > 1.5:
        raise TwinError(f"mesh is {np.max(extents):.3g} m across, too big for a tabletop object; "
                        "pass scale (0.001 for a mesh in millimetres)", path)
    part = _part_from_loaded(mesh)
    obj = _finish(name or path.stem, [part], 1.0)
    obj.source = str(path)
    return obj


def measure_envelope(mesh: trimesh.Trimesh) -> tuple[float, float]:
    """(radius_m, height_m) of a mesh in its object frame: max horizontal distance from the z axis,
    and max z."""
    v = np.asarray(mesh.vertices)
    return float(np.hypot(v[:, 0], v[:, 1]).max()), float(v[:, 2].max())


@dataclass(frozen=True)
class ObjectPlacement:
    """Where an object stands: position and yaw on the table, whose plane is at ``table_z_m``."""

    x_m: float
    y_m: float
    yaw_rad: float
    table_z_m: float = 0.0

    @property
    def T_world_object(self) -> np.ndarray:
        """4x4 pose of the object frame in the world frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0, self.x_m], [s, c, 0.0, self.y_m],
                         [0.0, 0.0, 1.0, self.table_z_m], [0.0, 0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RectRegion:
    """An axis-aligned rectangle of the table (world frame) where objects may be placed."""

    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float
    table_z_m: float = 0.0

    def sample_xy(self, rng: np.random.Generator, clearance_m: float) -> tuple[float, float]:
        """A uniform point at least ``clearance_m`` inside the rectangle's edges."""
        lo = np.array([self.x_min_m, self.y_min_m]) + clearance_m
        hi = np.array([self.x_max_m, self.y_max_m]) - clearance_m
        if np.any(hi < lo):
            raise TwinError(f"workspace rectangle {self} is too small for a clearance of {clearance_m:.3f} m")
        x, y = rng.uniform(lo, hi)
        return float(x), float(y)


@dataclass(frozen=True)
class DiscRegion:
    """A disc of the table (world frame) where objects may be placed."""

    centre_x_m: float
    centre_y_m: float
    radius_m: float
    table_z_m: float = 0.0

    def sample_xy(self, rng: np.random.Generator, clearance_m: float) -> tuple[float, float]:
        """A point uniform over the disc shrunk by ``clearance_m``."""
        r_max = self.radius_m - clearance_m
        if r_max < 0:
            raise TwinError(f"workspace disc {self} is too small for a clearance of {clearance_m:.3f} m")
        r, a = r_max * math.sqrt(rng.uniform()), rng.uniform(-math.pi, math.pi)
        return self.centre_x_m + r * math.cos(a), self.centre_y_m + r * math.sin(a)


WorkspaceRegion = RectRegion | DiscRegion


def random_placement(rng: np.random.Generator | int, workspace: WorkspaceRegion,
                     clearance_m: float = 0.0) -> ObjectPlacement:
    """Draw a placement: centre uniform in ``workspace`` kept ``clearance_m`` from its edge (pass the
    object's radius plus a margin to keep the whole object inside), yaw uniform in [-pi, pi)."""
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    if clearance_m < 0 or not math.isfinite(clearance_m):
        raise TwinError(f"clearance must be a finite distance >= 0 m, got {clearance_m}")
    x, y = workspace.sample_xy(gen, clearance_m)
    yaw = float(gen.uniform(-math.pi, math.pi))
    return ObjectPlacement(x, y, yaw, workspace.table_z_m)


def to_world(obj: TwinObject, placement: ObjectPlacement) -> trimesh.Trimesh:
    """The object's true mesh in the world frame (face colours kept), for ground truth.

    The vertices are mapped with ``matvec`` rather than trimesh's ``apply_transform`` (BLAS): the truth
    files must not depend on the BLAS kernel (:func:`darp.kinematics.transforms.compose`).
    """
    mesh = obj.mesh.copy()
    T = placement.T_world_object
    mesh.vertices = matvec(T[:3, :3], mesh.vertices) + T[:3, 3]  # a turn about z: the winding stays
    return mesh


def save_truth_mesh(obj: TwinObject, placement: ObjectPlacement, path: str | Path) -> Path:
    """Write the placed object's true mesh as binary PLY (with face colours), atomically."""
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise TwinError("the truth mesh is written as PLY; give a path ending in .ply", path)
    with atomic_path(path) as tmp:
        to_world(obj, placement).export(tmp, file_type="ply")
    return path


def sample_surface(obj: TwinObject, n_points: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points (and outward normals) uniform over the object's visible outer surface, object frame.

    Parts that meet overlap instead of being joined (a handle's ends sit inside the mug wall), so a
    sample of the raw mesh would put some points inside the object; those are dropped and redrawn.
    Use this, not ``mesh.sample``, for ground-truth completeness.
    """
    import open3d as o3d

    if n_points < 1:
        raise TwinError(f"n_points must be >= 1, got {n_points}")
    mesh = obj.mesh
    # trimesh.graph has no annotations
    labels = trimesh.graph.connected_component_labels(  # type: ignore[no-untyped-call]
        mesh.face_adjacency, node_count=len(mesh.faces))
    scenes = []
    for k in range(int(labels.max()) + 1):
        body = mesh.submesh([np.flatnonzero(labels == k)], append=True)
        assert isinstance(body, trimesh.Trimesh)  # append=True: one mesh
        scene = o3d.t.geometry.RaycastingScene()
        # open3d's stubs make Tensor's dtype and device required; they default to the array's and the CPU
        scene.add_triangles(o3d.core.Tensor(np.asarray(body.vertices, np.float32)),  # type: ignore[call-overload]
                            o3d.core.Tensor(np.asarray(body.faces, np.uint32)))  # type: ignore[call-overload]
        scenes.append(scene)
    points: list[np.ndarray] = []
    normals: list[np.ndarray] = []
    draw = 0
    while sum(len(p) for p in points) < n_points:
        pts, face = trimesh.sample.sample_surface(mesh, 2 * n_points, seed=seed + draw)
        draw += 1
        hidden = np.zeros(len(pts), bool)
        if len(scenes) > 1:
            query = o3d.core.Tensor(np.asarray(pts, np.float32))  # type: ignore[call-overload]  # (as above)
            for k, scene in enumerate(scenes):
                hidden |= (scene.compute_occupancy(query).numpy() > 0) & (labels[face] != k)
        points.append(pts[~hidden])
        normals.append(mesh.face_normals[face[~hidden]])
    return np.vstack(points)[:n_points], np.vstack(normals)[:n_points]


def plot_objects(path: str | Path, names: tuple[str, ...] | list[str] = OBJECT_NAMES, *,
                 panel_px: int = 360, seed: int | None = None) -> Path:
    """Render a contact sheet of objects (orthographic, textured, shaded) to a PNG."""
    from darp.twin.objects.plot import contact_sheet

    return contact_sheet(Path(path), [make_object(n, seed=seed) for n in names], panel_px=panel_px)


def _finish(name: str, parts: list[ObjectPart], scale: float) -> TwinObject:
    """Recentre parts on the footprint, scale them, and build the combined, merged true mesh."""
    all_v = np.vstack([p.mesh.vertices for p in parts])
    lo, hi = all_v.min(axis=0), all_v.max(axis=0)
    T = np.diag([scale, scale, scale, 1.0])
    T[:3, 3] = -scale * np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    for p in parts:
        p.mesh.apply_transform(T)
    offsets = np.cumsum([0] + [len(p.mesh.vertices) for p in parts[:-1]])
    faces = np.vstack([np.asarray(p.mesh.faces) + o for p, o in zip(parts, offsets, strict=True)])
    colours = np.vstack([np.tile(np.round(np.asarray(p.rgba) * 255), (len(p.mesh.faces), 1)) for p in parts])
    mesh = trimesh.Trimesh(all_v @ T[:3, :3].T + T[:3, 3], faces, face_colors=colours.astype(np.uint8),
                           process=False)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    radius, height = measure_envelope(mesh)
    return TwinObject(name, mesh, parts, radius, height)


def _check_scale(scale: float, path: Path | None = None) -> None:
    if not (math.isfinite(scale) and scale > 0):
        raise TwinError(f"scale must be a finite number > 0, got {scale}", path)


def _up_to_z(up: str, path: Path) -> np.ndarray:
    """Rotation taking the file's up axis to +z."""
    axes = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1)}
    key = up.strip().lower()
    sign = -1.0 if key.startswith("-") else 1.0
    if key.lstrip("+-") not in axes:
        raise TwinError(f"up must be one of x, y, z (optionally negated), got {up!r}", path)
    a = sign * np.array(axes[key.lstrip("+-")], dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    T = np.eye(4)
    if np.allclose(a, z):
        return T
    if np.allclose(a, -z):
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])
        return T
    axis = np.cross(a, z)
    # trimesh.transformations has no annotations
    T[:3, :3] = trimesh.transformations.rotation_matrix(math.pi / 2, axis)[:3, :3]  # type: ignore[no-untyped-call]
    return T


def _part_from_loaded(mesh: trimesh.Trimesh) -> ObjectPart:
    """One part holding the loaded mesh, keeping a texture or its mean colour when the file had one."""
    piece = Piece(np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces))
    visual = mesh.visual
    if isinstance(visual, trimesh.visual.TextureVisuals) and visual.uv is not None:
        material = visual.material
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if image is not None and len(visual.uv) == len(piece.vertices):
            piece.uv = np.asarray(visual.uv, dtype=np.float64)
            return make_part("body", piece, texture=np.asarray(image.convert("RGB")))
    rgba = (0.6, 0.6, 0.6, 1.0)
    if isinstance(visual, trimesh.visual.ColorVisuals) and visual.kind in ("face", "vertex"):
        mean = np.asarray(visual.face_colors, dtype=float).mean(axis=0) / 255.0
        rgba = (float(mean[0]), float(mean[1]), float(mean[2]), float(mean[3]))
    return make_part("body", piece, rgba)


__all__ = [
    "OBJECT_NAMES", "PAPER_ENVELOPE_CM", "DiscRegion", "ObjectPart", "ObjectPlacement", "RectRegion",
    "TwinObject", "WorkspaceRegion", "canonical_name", "load_mesh_object", "make_object",
    "measure_envelope", "plot_objects", "random_placement", "sample_surface", "save_truth_mesh",
    "to_world",
]
