"""Collision geometry of the Z1 and its wrist camera, and the distance queries planning needs.

Model (exact shapes, no inflation): every link cylinder of the facts' table is a solid cylinder;
the wrist camera body is a box (default 90 x 25 x 25 mm, as the default rig) at ``T_wrist_cam``;
its bracket is a capsule post from the tool axis to the body centre. Distances are signed (negative:
penetration depth) and exact to ~0.1 um for shapes that are apart (see
:mod:`darp.kinematics.collision_shapes`); they are never over-reported.

Self-collision skips pairs on the same link and on *adjacent* links, those joined by one joint or
by a link without geometry: (link00, link02), (link02, link03), (link03, link04), (link04, link06).
The camera and bracket belong to link06. One more pair is skipped by default
(:data:`ALLOWED_PAIRS`): the shoulder motor (link02) and the flange motor (link06) interpenetrate by
8 mm per the table's cylinders in the folded rest pose q = 0, which the real arm reaches without
contact (its housings are not full cylinders). The camera, the bracket and every other link stay
checked against the shoulder.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from darp.errors import KinematicsError
from darp.kinematics import z1
from darp.kinematics.collision_shapes import (
    Primitive,
    PrimitiveSet,
    _bounding_segment,
    as_set,
    concatenate,
    pair_distances,
    plane_distances,
    project,
    segment_distances,
)
from darp.kinematics.transforms import make_transform, rpy_to_rotation

Array = NDArray[np.float64]
IndexArray = NDArray[np.intp]

__all__ = [
    "ADJACENT_LINKS",
    "ALLOWED_PAIRS",
    "LINK_CYLINDERS",
    "NOMINAL_CAMERA_MOUNT",
    "NOMINAL_T_WRIST_CAM",
    "CameraMount",
    "DistanceResult",
    "LinkCylinder",
    "Primitive",
    "PrimitiveSet",
    "arm_arm_distance",
    "arm_envelope_distance",
    "arm_geometry",
    "arm_primitives",
    "arm_table_distance",
    "envelope_primitive",
    "min_distance",
    "segment_distances",
    "self_collision",
    "self_collision_distance",
]


@dataclass(frozen=True)
class LinkCylinder:
    """A collision cylinder of the facts' table, in its link's frame."""

    name: str
    link: str
    centre_m: tuple[float, float, float]
    axis: str
    length_m: float
    radius_m: float

    def primitive(self) -> Primitive:
        half = 0.5 * self.length_m * np.eye(3)["xyz".index(self.axis)]
        c = np.asarray(self.centre_m)
        return Primitive.cylinder(c - half, c + half, self.radius_m, self.name, self.link)


LINK_CYLINDERS: tuple[LinkCylinder, ...] = (
    LinkCylinder("base", "link00", (0.0, 0.0, 0.0255), "z", 0.051, 0.0325),
    LinkCylinder("shoulder_motor", "link02", (0.0, 0.0, 0.0), "y", 0.102, 0.0325),
    LinkCylinder("upper_arm", "link02", (-0.1625, 0.0, 0.0), "x", 0.235, 0.0225),
    LinkCylinder("elbow_motor", "link02", (-0.35, 0.0, 0.0), "y", 0.051, 0.0325),
    LinkCylinder("forearm", "link03", (0.128, 0.0, 0.055), "x", 0.116, 0.02),
    LinkCylinder("wrist_motor", "link03", (0.2205, 0.0, 0.055), "y", 0.059, 0.0325),
    LinkCylinder("wrist_pitch_motor", "link04", (0.072, 0.0, 0.0), "z", 0.067, 0.0325),
    LinkCylinder("flange_motor", "link06", (0.0255, 0.0, 0.0), "x", 0.051, 0.0325),
)
ADJACENT_LINKS: frozenset[frozenset[str]] = frozenset(
    frozenset(p) for p in (("link00", "link02"), ("link02", "link03"), ("link03", "link04"),
                           ("link04", "link06")))
ALLOWED_PAIRS: tuple[tuple[str, str], ...] = (("shoulder_motor", "flange_motor"),)

# Same extrinsic as the default rig: optical +z = flange +x, image right = flange -y, 55 mm above.
NOMINAL_T_WRIST_CAM: Array = make_transform(rpy_to_rotation(*np.radians([-90.0, 0.0, -90.0])),
                                             [0.0, 0.0, 0.055])
NOMINAL_T_WRIST_CAM.setflags(write=False)
_T_LINK06_FLANGE = make_transform(t=[z1.WRIST_FRAMES["flange"], 0.0, 0.0])


@dataclass(frozen=True, eq=False)
class CameraMount:
    """Wrist camera at ``T_wrist_cam``: a box body (size along camera x, y, z; centre in the optical
    frame) on a capsule bracket from ``bracket_anchor_flange_m`` (default: the point of the tool axis
    under the body centre, clamped to link06) to the body centre."""

    T_wrist_cam: Array = field(default_factory=lambda: NOMINAL_T_WRIST_CAM.copy())
    body_size_m: tuple[float, float, float] = (0.090, 0.025, 0.025)
    body_center_cam_m: tuple[float, float, float] = (0.0175, 0.0, -0.0083)
    bracket_radius_m: float = 0.01
    bracket_anchor_flange_m: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "_link06", self._build())  # validated and built once

    def primitives_link06(self) -> PrimitiveSet:
        """Body box and bracket capsule in the link06 frame."""
        return self._link06  # type: ignore[attr-defined, no-any-return]

    def _build(self) -> PrimitiveSet:
        T = np.asarray(self.T_wrist_cam, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise KinematicsError("camera mount T_wrist_cam must be a finite 4x4 transform")
        T_flange_body = T @ make_transform(t=self.body_center_cam_m)
        centre = T_flange_body[:3, 3]
        if self.bracket_anchor_flange_m is None:
            anchor = np.array([np.clip(centre[0], -z1.WRIST_FRAMES["flange"], 0.0), 0.0, 0.0])
        else:
            anchor = np.asarray(self.bracket_anchor_flange_m, dtype=np.float64)
        body = Primitive.box(T_flange_body, self.body_size_m, "camera_body", "link06")
        bracket = Primitive.capsule(anchor, centre, self.bracket_radius_m, "camera_bracket", "link06")
        return PrimitiveSet.from_list([body, bracket]).transformed(_T_LINK06_FLANGE)


NOMINAL_CAMERA_MOUNT = CameraMount()

_LOCAL = PrimitiveSet.from_list([c.primitive() for c in LINK_CYLINDERS])
_LINK_INDEX = np.array([z1.LINK_NAMES.index(c.link) for c in LINK_CYLINDERS])


def _attach(local: PrimitiveSet, link_index: Array, T_world_links: Array) -> PrimitiveSet:
    R, t = T_world_links[link_index, :3, :3], T_world_links[link_index, :3, 3]
    return PrimitiveSet(local.kinds, R @ local.R, np.einsum("nij,nj->ni", R, local.centre) + t,
                        local.half, local.names, local.links)


def arm_primitives(q: ArrayLike, T_world_base: ArrayLike | None = None,
                   camera_mount: CameraMount | None = NOMINAL_CAMERA_MOUNT) -> PrimitiveSet:
    """World-frame primitives (arrays) of one arm and its camera (None: no camera) at joints q."""
    T_wb = np.eye(4) if T_world_base is None else np.asarray(T_world_base, dtype=np.float64)
    if T_wb.shape != (4, 4) or not np.all(np.isfinite(T_wb)):
        raise KinematicsError(f"T_world_base must be a finite 4x4 transform, got shape {T_wb.shape}")
    T_wl = T_wb @ z1.link_transforms(q)
    arm = _attach(_LOCAL, _LINK_INDEX, T_wl)
    if camera_mount is None:
        return arm
    cam = camera_mount.primitives_link06()
    return concatenate([arm, _attach(cam, np.full(len(cam), 6), T_wl)])


def arm_geometry(q: ArrayLike, T_world_base: ArrayLike | None = None,
                 camera_mount: CameraMount | None = NOMINAL_CAMERA_MOUNT) -> list[Primitive]:
    """World-frame collision primitives of one arm and its wrist camera at joints q."""
    return arm_primitives(q, T_world_base, camera_mount).to_list()


@dataclass(frozen=True)
class DistanceResult:
    """Signed distance (m; negative = penetration) and the closest pair: names and points."""

    distance_m: float
    name_a: str
    name_b: str
    point_a: Array
    point_b: Array


def _closest_pair(A: PrimitiveSet, B: PrimitiveSet, ia: IndexArray, ib: IndexArray) -> DistanceResult:
    """Minimum over the listed pairs (A[ia[k]], B[ib[k]]), refining only pairs that can be closest."""
    if len(ia) == 0:
        return DistanceResult(float("inf"), "", "", np.full(3, np.nan), np.full(3, np.nan))
    Ap, Bp = A.subset(ia), B.subset(ib)
    (a1, b1), ra = _bounding_segment(Ap.R, Ap.centre, Ap.half, Ap.kinds)
    (a2, b2), rb = _bounding_segment(Bp.R, Bp.centre, Bp.half, Bp.kinds)
    d, _, pb = segment_distances(a1, b1, a2, b2)
    lower = d - ra - rb
    x = project(Ap, pb)
    upper = np.linalg.norm(project(Bp, x) - x, axis=1)  # a pair of points on the shapes: an upper bound
    cand = np.flatnonzero(lower <= np.min(np.maximum(upper, lower)) + 1e-12)
    if len(cand) > 1:  # a coarse pass first, then only the pairs that can still be the closest
        dist, xa, xb = pair_distances(Ap.subset(cand), Bp.subset(cand), tol_m=1e-4, max_iters=40)
        upper = np.maximum(np.linalg.norm(xb - xa, axis=1), dist)
        cand = cand[dist <= np.min(upper) + 1e-12]
    dist, xa, xb = pair_distances(Ap.subset(cand), Bp.subset(cand))
    k = int(np.argmin(dist))
    i, j = ia[cand[k]], ib[cand[k]]
    return DistanceResult(float(dist[k]), A.names[i], B.names[j], xa[k], xb[k])


def min_distance(prims_a: PrimitiveSet | Sequence[Primitive],
                 prims_b: PrimitiveSet | Sequence[Primitive]) -> DistanceResult:
    """Smallest signed distance between any primitive of ``prims_a`` and any of ``prims_b``."""
    A, B = as_set(prims_a), as_set(prims_b)
    ia, ib = np.meshgrid(np.arange(len(A)), np.arange(len(B)), indexing="ij")
    return _closest_pair(A, B, ia.ravel(), ib.ravel())


def _checked_pairs(names: tuple[str, ...], links: tuple[str, ...],
                   allowed: Sequence[tuple[str, str]]) -> tuple[IndexArray, IndexArray]:
    skip = {frozenset(p) for p in allowed}
    pairs = [(i, j) for i in range(len(names)) for j in range(i + 1, len(names))
             if links[i] != links[j] and frozenset((links[i], links[j])) not in ADJACENT_LINKS
             and frozenset((names[i], names[j])) not in skip and frozenset((links[i], links[j])) not in skip]
    arr = np.array(pairs, dtype=int).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


def self_collision_distance(q: ArrayLike, camera_mount: CameraMount | None = NOMINAL_CAMERA_MOUNT,
                            allowed_pairs: Sequence[tuple[str, str]] = ALLOWED_PAIRS) -> DistanceResult:
    """Smallest signed distance between non-adjacent parts of one arm (camera on link06 included).

    ``allowed_pairs``: pairs of primitive or link names not to check (default :data:`ALLOWED_PAIRS`).
    """
    prims = arm_primitives(q, None, camera_mount)
    ia, ib = _checked_pairs(prims.names, prims.links, allowed_pairs)
    return _closest_pair(prims, prims, ia, ib)


def self_collision(q: ArrayLike, margin_m: float = 0.0,
                   camera_mount: CameraMount | None = NOMINAL_CAMERA_MOUNT,
                   allowed_pairs: Sequence[tuple[str, str]] = ALLOWED_PAIRS) -> bool:
    """True when two non-adjacent parts of the arm come closer than ``margin_m``."""
    return self_collision_distance(q, camera_mount, allowed_pairs).distance_m < margin_m


def arm_arm_distance(qA: ArrayLike, T_world_baseA: ArrayLike, qB: ArrayLike, T_world_baseB: ArrayLike,
                     camera_mount_a: CameraMount | None = NOMINAL_CAMERA_MOUNT,
                     camera_mount_b: CameraMount | None = NOMINAL_CAMERA_MOUNT) -> DistanceResult:
    """Smallest signed distance between two arms (with their cameras) in a common world frame."""
    return min_distance(arm_primitives(qA, T_world_baseA, camera_mount_a),
                        arm_primitives(qB, T_world_baseB, camera_mount_b))


def arm_table_distance(q: ArrayLike, T_world_base: ArrayLike, table_height_z: float,
                       camera_mount: CameraMount | None = NOMINAL_CAMERA_MOUNT,
                       exclude_links: Sequence[str] = ("link00",)) -> DistanceResult:
    """Signed height of the arm's lowest point above the plane z = ``table_height_z`` (world frame).

    The base (link00) stands on the table and is excluded by default.
    """
    prims = arm_primitives(q, T_world_base, camera_mount)
    prims = prims.subset(np.array([link not in exclude_links for link in prims.links]))
    heights, lowest = plane_distances(prims, float(table_height_z))
    i = int(np.argmin(heights))
    p = lowest[i]
    return DistanceResult(float(heights[i]), prims.names[i], "table", p, np.array([p[0], p[1], table_height_z]))


def envelope_primitive(centre: ArrayLike, radius_m: float, height_m: float,
                       table_height_z: float | None = None) -> Primitive:
    """The object envelope: a vertical solid cylinder about ``centre`` (world x, y, z of the object).

    It spans ``centre_z +- height/2``, or ``[table_height_z, table_height_z + height]`` when the table
    height is given (the object stands on the table).
    """
    c = np.asarray(centre, dtype=np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)) or not (radius_m > 0 and height_m > 0):
        raise KinematicsError("envelope needs a finite 3-vector centre and positive radius and height")
    z_lo = c[2] - 0.5 * height_m if table_height_z is None else float(table_height_z)
    return Primitive.cylinder([c[0], c[1], z_lo], [c[0], c[1], z_lo + height_m], radius_m, "envelope", "object")


def arm_envelope_distance(q: ArrayLike, T_world_base: ArrayLike, centre: ArrayLike, radius_m: float,
                          height_m: float, *, table_height_z: float | None = None,
                          camera_mount: CameraMount | None = NOMINAL_CAMERA_MOUNT) -> DistanceResult:
    """Signed distance between the arm (with camera) and the object envelope (see
    :func:`envelope_primitive`)."""
    env = envelope_primitive(centre, radius_m, height_m, table_height_z)
    return min_distance(arm_primitives(q, T_world_base, camera_mount), [env])
