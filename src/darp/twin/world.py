"""The twin's MuJoCo scene: table, floor, both Z1 arms on their true bases with wrist cameras, the object.

Built with MuJoCo's model-editing API (``MjSpec``; :meth:`TwinWorld.mjcf` gives the equivalent MJCF
text). Only kinematics and collision detection are used: joint angles are *set* (the true angles of
:mod:`darp.twin.arm_sim`), never simulated with dynamics.

Scene (world frame of the rig file: z up, table top at ``rig.table.height_m``):

- table: a box with a faintly mottled top (seeded texture), a grey floor 0.75 m below;
- each arm: bodies ``<arm>_link00 .. <arm>_link06`` with hinge joints ``<arm>_joint1..6`` built from
  :data:`darp.kinematics.z1.Z1_JOINTS` (body frames are the URDF link frames), geoms are the facts'
  link cylinders (:data:`darp.kinematics.collision.LINK_CYLINDERS`, rendered and collided as cylinders);
  body ``<arm>_camera`` on link06 whose frame is the camera's depth optical frame at the TRUE mount,
  carrying the camera housing box and its bracket post;
- the object: one mesh geom per part in body ``object`` at ``T_world_object``, with colours, textures
  and per-part material flags (``dark``, ``specular``, ``transparent``) exposed per geom id for the
  camera's dropout model;
- optionally a ChArUco board lying face-up on the table (:func:`darp.twin.objects.board.add_charuco_board`).

Contacts: collision bits make every arm geom collide with the table, the object and the other arm,
and nothing else (no self-contacts within an arm, no table-object contact; each base stands on the
table and is excluded). :meth:`TwinWorld.contacts` lists the current contacts; the collision monitor
of :mod:`darp.twin.rig_backend` calls it during motion.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from darp.errors import TwinError
from darp.formats.calibration import CharucoBoardSpec
from darp.kinematics import z1
from darp.kinematics.collision import LINK_CYLINDERS
from darp.kinematics.transforms import compose, make_transform, matvec
from darp.twin.camera.render import mujoco  # render sets MUJOCO_GL before importing mujoco

TABLE_THICKNESS_M = 0.03
FLOOR_DROP_M = 0.75
TABLE_BIT, OBJECT_BIT = 1, 2
ARM_BITS = (4, 8)
ARM_COLLIDES_WITH = TABLE_BIT | OBJECT_BIT  # plus the other arm's bit
LINK_RGBA = {"link00": (0.12, 0.12, 0.13, 1), "link02": (0.72, 0.73, 0.75, 1), "link03": (0.72, 0.73, 0.75, 1),
             "link04": (0.12, 0.12, 0.13, 1), "link06": (0.12, 0.12, 0.13, 1)}
MOTOR_RGBA = (0.10, 0.10, 0.11, 1.0)
CAMERA_RGBA = (0.55, 0.56, 0.58, 1.0)
BRACKET_RGBA = (0.2, 0.2, 0.22, 1.0)
BRACKET_RADIUS_M = 0.01
ROD_SECTIONS = 48  # mesh cylinders: at most 0.07 mm inside the true 32.5 mm radius
COLLISION_GROUP = 3  # exact primitives used for contacts; not rendered (MuJoCo shows groups 0-2)


@dataclass(frozen=True)
class Contact:
    """One contact between an arm geom and the table, the object or the other arm."""

    arm_id: str
    arm_geom: str
    other: str  # "table", "object", or the other arm's id
    other_geom: str
    distance_m: float  # negative: penetration depth
    position_m: tuple[float, float, float]


@dataclass
class WorldGeoms:
    """Geom bookkeeping: owner of every geom id and the material flags of the object's parts."""

    owner: dict[int, str] = field(default_factory=dict)  # geom id -> "table", "object", arm id, ...
    dark: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    specular: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    transparent: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


def _quat(R: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=float).reshape(-1))
    return q


def _set_pose(element: Any, T: np.ndarray) -> None:
    element.pos = np.asarray(T[:3, 3], dtype=float)
    element.quat = _quat(T[:3, :3])


def table_texture(seed: int, size: int = 256) -> np.ndarray:
    """A faint mottled light-grey table top (RGB uint8, tileable), deterministic for ``seed``.

    Band-limited noise made in the Fourier domain is periodic, so repeated tiles show no seams.
    """
    rng = np.random.default_rng([seed, 7])
    freq = np.fft.fftfreq(size)
    radius = np.hypot(freq[:, None], freq[None, :])
    blobs = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(size, size))) * np.exp(-(radius / 0.02) ** 2)))
    blobs /= max(float(blobs.std()), 1e-12)
    grain = rng.normal(0.0, 1.0, (size, size))
    grey = np.clip(178.0 + 5.0 * blobs + 3.0 * grain, 0, 255)
    rgb = np.stack([grey, grey, grey * 0.97], axis=2).astype(np.uint8)
    return np.ascontiguousarray(rgb)


def _add_texture(spec: mujoco.MjSpec, name: str, rgb: np.ndarray) -> None:
    tex = spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, width=rgb.shape[1],
                           height=rgb.shape[0], nchannel=3)
    tex.data = np.ascontiguousarray(rgb, dtype=np.uint8).tobytes()


def _add_environment(spec: mujoco.MjSpec, rig: Any, seed: int, lighting: Any = None) -> None:
    """Table, floor and lights (``lighting``: a :class:`darp.twin.settings.LightingSettings`; None: defaults)."""
    ambient, key, fill, key_yaw = ((0.35, 0.45, 0.25, 0.0) if lighting is None else
                                   (lighting.ambient, lighting.key, lighting.fill, lighting.key_yaw_deg))
    table = rig.table
    (x0, x1), (y0, y1), top = table.x_range_m, table.y_range_m, table.height_m
    _add_texture(spec, "table_tex", table_texture(seed))
    mat = spec.add_material(name="table_mat", rgba=[1, 1, 1, 1], specular=0.1, shininess=0.1, texuniform=True)
    mat.texrepeat = [4.0, 4.0]
    mat.textures[int(mujoco.mjtTextureRole.mjTEXROLE_RGB)] = "table_tex"
    spec.worldbody.add_geom(
        name="table", type=mujoco.mjtGeom.mjGEOM_BOX, material="table_mat",
        size=[0.5 * (x1 - x0), 0.5 * (y1 - y0), 0.5 * TABLE_THICKNESS_M],
        pos=[0.5 * (x0 + x1), 0.5 * (y0 + y1), top - 0.5 * TABLE_THICKNESS_M],
        contype=TABLE_BIT, conaffinity=0)
    # A box, not a plane: MuJoCo draws planes as a fine grid, which costs a software renderer several ms.
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_BOX, size=[4.0, 4.0, 0.01],
                            pos=[0, 0, top - FLOOR_DROP_M - 0.01], rgba=[0.42, 0.41, 0.40, 1], contype=0,
                            conaffinity=0)
    spec.visual.headlight.ambient = [ambient] * 3
    spec.visual.headlight.diffuse = [ambient] * 3
    spec.visual.headlight.specular = [0.05, 0.05, 0.05]
    key_dir = [-0.15, 0.45, -1.0]
    if key_yaw:  # turned about the vertical (exactly the default direction when not turned)
        c, s = np.cos(np.radians(key_yaw)), np.sin(np.radians(key_yaw))
        key_dir = [c * key_dir[0] - s * key_dir[1], s * key_dir[0] + c * key_dir[1], key_dir[2]]
    for name, pos, direction, level in (("key", [0.4, -1.2, 2.2], key_dir, key),
                                        ("fill", [-0.6, 1.0, 2.0], [0.25, -0.4, -1.0], fill)):
        light = spec.worldbody.add_light(name=name, pos=pos, dir=direction, castshadow=False)
        light.type = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
        light.diffuse = [level] * 3
        light.specular = [0.2, 0.2, 0.2]


def _rod_mesh(spec: mujoco.MjSpec, kind: str, radius_m: float, length_m: float) -> str:
    """Name of a triangle-mesh cylinder or capsule along z, centred at the origin (added once per size)."""
    name = f"rod_{kind}_{radius_m * 1e4:.0f}_{length_m * 1e4:.0f}"
    if spec.mesh(name) is None:
        if kind == "cylinder":
            mesh = trimesh.creation.cylinder(radius=radius_m, height=length_m, sections=ROD_SECTIONS)
        else:
            mesh = trimesh.creation.capsule(height=length_m, radius=radius_m, count=[ROD_SECTIONS, ROD_SECTIONS // 2])
            mesh.apply_translation(-0.5 * (mesh.bounds[0] + mesh.bounds[1]))
        asset = spec.add_mesh(name=name, inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL)
        asset.uservert = np.asarray(mesh.vertices, dtype=float).reshape(-1).tolist()
        asset.userface = np.asarray(mesh.faces, dtype=np.int64).reshape(-1).tolist()
    return name


def _add_rod(spec: mujoco.MjSpec, body: Any, name: str, a: np.ndarray, b: np.ndarray, radius_m: float, kind: str,
             rgba: tuple[float, ...], contype: int, conaffinity: int) -> None:
    """A cylinder or capsule from a to b: an exact primitive for contacts (hidden) plus a mesh to render.

    MuJoCo's built-in cylinders and capsules cost about 1.5 ms each per image on a software (llvmpipe)
    renderer, 15 times a triangle mesh of the same shape, so the arms are drawn as meshes.
    """
    prim = mujoco.mjtGeom.mjGEOM_CYLINDER if kind == "cylinder" else mujoco.mjtGeom.mjGEOM_CAPSULE
    body.add_geom(name=name, type=prim, fromto=[*a, *b], size=[radius_m, 0, 0], rgba=list(rgba),
                  contype=contype, conaffinity=conaffinity, mass=0.0, group=COLLISION_GROUP)
    d = np.asarray(b, float) - np.asarray(a, float)
    length = float(np.linalg.norm(d, axis=-1))  # axis=-1: no BLAS, the scene must not depend on its kernel
    z = d / length
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=-1)
    R = np.stack([x, np.cross(z, x), z], axis=1)
    geom = body.add_geom(name=f"{name}_visual", type=mujoco.mjtGeom.mjGEOM_MESH,
                         meshname=_rod_mesh(spec, kind, radius_m, length), rgba=list(rgba), contype=0, conaffinity=0,
                         mass=0.0)
    _set_pose(geom, make_transform(R, 0.5 * (np.asarray(a, float) + np.asarray(b, float))))


def _add_arm(spec: mujoco.MjSpec, arm_id: str, index: int, T_world_base: np.ndarray,
             T_wrist_cam: np.ndarray, camera_body: Any, kinematic_errors: Any | None = None) -> None:
    own = ARM_BITS[index]
    other = ARM_BITS[1 - index]
    affinity = ARM_COLLIDES_WITH | other
    parent = spec.worldbody.add_body(name=f"{arm_id}_link00")
    _set_pose(parent, T_world_base)
    bodies = {"link00": parent}
    origins = axes = None
    if kinematic_errors is not None:  # the true chain (darp.twin.arm_errors): perturbed origins and axes
        origins, axes = kinematic_errors.origins(), kinematic_errors.axes()
    for i, joint in enumerate(z1.Z1_JOINTS):
        pos = list(joint.origin_xyz_m) if origins is None else [float(v) for v in origins[i]]
        axis = list(np.eye(3)["xyz".index(joint.axis)]) if axes is None else [float(v) for v in axes[i]]
        body = bodies[joint.parent].add_body(name=f"{arm_id}_{joint.child}", pos=pos)
        body.add_joint(name=f"{arm_id}_{joint.name}", type=mujoco.mjtJoint.mjJNT_HINGE,
                       axis=axis, range=[joint.lower_rad, joint.upper_rad])
        bodies[joint.child] = body
    for cyl in LINK_CYLINDERS:
        axis = np.eye(3)["xyz".index(cyl.axis)]
        a = np.asarray(cyl.centre_m) - 0.5 * cyl.length_m * axis
        b = np.asarray(cyl.centre_m) + 0.5 * cyl.length_m * axis
        rgba = MOTOR_RGBA if "motor" in cyl.name else LINK_RGBA.get(cyl.link, MOTOR_RGBA)
        _add_rod(spec, bodies[cyl.link], f"{arm_id}_{cyl.name}", a, b, cyl.radius_m, "cylinder", rgba, own, affinity)
    flange = z1.WRIST_FRAMES["flange"]
    T_link6_cam = compose(make_transform(t=[flange, 0.0, 0.0]), T_wrist_cam)
    cam = bodies["link06"].add_body(name=f"{arm_id}_camera")
    _set_pose(cam, T_link6_cam)
    size = np.asarray(camera_body.size_m, dtype=float)
    cam.add_geom(name=f"{arm_id}_camera_body", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(0.5 * size),
                 pos=list(np.asarray(camera_body.center_cam_m, dtype=float)), rgba=list(CAMERA_RGBA),
                 contype=own, conaffinity=affinity, mass=0.0)
    # Bracket post as in darp.kinematics.collision.CameraMount: a capsule from the tool axis under the
    # housing centre (clamped to link06) up to the housing, radius 1 cm.
    centre = matvec(T_wrist_cam, np.append(np.asarray(camera_body.center_cam_m, dtype=float), 1.0))[:3]
    anchor = np.array([np.clip(centre[0], -flange, 0.0), 0.0, 0.0])
    offset = np.array([flange, 0.0, 0.0])
    _add_rod(spec, bodies["link06"], f"{arm_id}_camera_bracket", anchor + offset, centre + offset, BRACKET_RADIUS_M,
             "capsule", BRACKET_RGBA, own, affinity)
    spec.add_exclude(bodyname1="world", bodyname2=f"{arm_id}_link00")


def _add_object(spec: mujoco.MjSpec, parts: Sequence[Any], T_world_object: np.ndarray) -> list[tuple[str, Any]]:
    body = spec.worldbody.add_body(name="object")
    _set_pose(body, T_world_object)
    added = []
    for k, part in enumerate(parts):
        name = f"object_{k}_{part.name}"
        mesh = spec.add_mesh(name=f"{name}_mesh", inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL)
        vertices = np.asarray(part.mesh.vertices, dtype=float)
        faces = np.asarray(part.mesh.faces, dtype=np.int64)
        if len(faces) == 0:
            raise TwinError(f"object part {part.name!r} has no triangles")
        uv = None if getattr(part, "uv", None) is None else np.asarray(part.uv, dtype=float)
        if len(vertices) < 4:  # MuJoCo wants at least 4 vertices: add an unused centroid
            vertices = np.vstack([vertices, vertices.mean(axis=0)])
            uv = None if uv is None else np.vstack([uv, uv.mean(axis=0)])
        mesh.uservert = vertices.reshape(-1).tolist()
        mesh.userface = faces.reshape(-1).tolist()
        material = ""
        if getattr(part, "texture", None) is not None and uv is not None:
            mesh.usertexcoord = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1).reshape(-1).tolist()
            _add_texture(spec, f"{name}_tex", np.asarray(part.texture)[..., :3])
            mat = spec.add_material(name=f"{name}_mat", rgba=[1, 1, 1, float(part.rgba[3])])
            mat.textures[int(mujoco.mjtTextureRole.mjTEXROLE_RGB)] = f"{name}_tex"
            material = f"{name}_mat"
        if getattr(part, "specular", False):
            if not material:
                spec.add_material(name=f"{name}_mat", rgba=list(part.rgba), specular=0.9, shininess=0.9,
                                  reflectance=0.0)
                material = f"{name}_mat"
            else:
                spec.material(material).specular = 0.9
                spec.material(material).shininess = 0.9
        # MuJoCo collides meshes through their convex hull, which a flat part does not have: such
        # parts are visual only (a flat part lies on another one or on the table anyway).
        centred = vertices - vertices.mean(axis=0)
        solid = len(vertices) >= 4 and np.linalg.svd(centred, compute_uv=False)[-1] > 1e-6
        geom = body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}_mesh",
                             rgba=list(part.rgba), contype=OBJECT_BIT if solid else 0, conaffinity=0, mass=0.0)
        if material:
            geom.material = material
        added.append((name, part))
    return added


class TwinWorld:
    """The compiled scene plus its state: set true joint angles, query contacts and poses."""

    def __init__(self, rig: Any, true_arms: dict[str, Any], *, parts: Sequence[Any] = (),
                 T_world_object: np.ndarray | None = None, board: CharucoBoardSpec | None = None,
                 T_world_board: np.ndarray | None = None, seed: int = 0, lighting: Any = None) -> None:
        """``true_arms``: arm id -> object with ``T_world_base`` and ``T_wrist_cam`` (a :class:`TrueArm`).

        ``board``: the calibration board record, drawn at ``T_world_board`` with the twin's default
        texture (:data:`darp.twin.objects.board.DEFAULT_TEXTURE`).
        """
        self.rig = rig
        self.arm_ids = tuple(true_arms)
        if len(self.arm_ids) > len(ARM_BITS):
            raise TwinError(f"the twin world holds at most {len(ARM_BITS)} arms, got {len(self.arm_ids)}")
        spec = mujoco.MjSpec()
        spec.modelname = "darp_twin"
        spec.compiler.degree = False
        # Kinematics only: lower bounds on mass and inertia keep the compiler happy (geoms are massless).
        spec.compiler.boundmass = 1e-3
        spec.compiler.boundinertia = 1e-6
        spec.option.gravity = [0.0, 0.0, -9.81]
        _add_environment(spec, rig, seed, lighting)
        for index, arm_id in enumerate(self.arm_ids):
            arm = true_arms[arm_id]
            _add_arm(spec, arm_id, index, np.asarray(arm.T_world_base, float), np.asarray(arm.T_wrist_cam, float),
                     rig.camera_body, getattr(arm, "kinematic_errors", None))
        object_parts = []
        if parts:
            T_wo = np.eye(4) if T_world_object is None else np.asarray(T_world_object, dtype=float)
            object_parts = _add_object(spec, parts, T_wo)
        self.board_geom: str | None = None
        self.T_world_board = None if board is None else np.asarray(T_world_board, dtype=float)
        if board is not None:
            from darp.twin.objects.board import add_charuco_board

            if T_world_board is None:
                raise TwinError("a board needs its pose T_world_board")
            self.board_geom = add_charuco_board(spec, board, name="charuco", T_parent_board=self.T_world_board)
        self.spec = spec
        try:
            self.model = spec.compile()
        except Exception as err:  # MuJoCo compile errors come as ValueError or mujoco.FatalError
            raise TwinError(f"cannot build the twin scene: {err}") from err
        self.data = mujoco.MjData(self.model)
        self._index(object_parts)
        self.forward()

    # -- bookkeeping ----------------------------------------------------------------------------
    def _index(self, object_parts: list[tuple[str, Any]]) -> None:
        m = self.model
        self.qpos_adr = {arm_id: np.array([m.jnt_qposadr[m.joint(f"{arm_id}_joint{k}").id] for k in range(1, 7)])
                         for arm_id in self.arm_ids}
        self.camera_body_id = {arm_id: m.body(f"{arm_id}_camera").id for arm_id in self.arm_ids}
        geoms = WorldGeoms(dark=np.zeros(m.ngeom, bool), specular=np.zeros(m.ngeom, bool),
                           transparent=np.zeros(m.ngeom, bool))
        for g in range(m.ngeom):
            name = m.geom(g).name
            owner = next((a for a in self.arm_ids if name.startswith(f"{a}_")), None)
            if owner is None:
                owner = "object" if name.startswith("object_") else ("board" if name.startswith("charuco") else name)
            geoms.owner[g] = owner
        for name, part in object_parts:
            g = m.geom(name).id
            geoms.dark[g] = bool(getattr(part, "dark", False))
            geoms.specular[g] = bool(getattr(part, "specular", False))
            geoms.transparent[g] = bool(getattr(part, "transparent", False))
        self.geoms = geoms
        self.object_geom_ids = np.array([m.geom(name).id for name, _ in object_parts], dtype=int)

    def mjcf(self, texture_dir: str | Path | None = None) -> str:
        """The scene as MJCF text (for inspection; MuJoCo writes about 6 significant digits).

        MJCF cannot hold texture pixels: with ``texture_dir`` they are written there as PNG files that
        the text references; without it textured materials are left out.
        """
        import cv2

        spec = self.spec.copy()
        for tex in list(spec.textures):
            if texture_dir is None:
                spec.delete(tex)
                continue
            folder = Path(texture_dir)
            folder.mkdir(parents=True, exist_ok=True)
            image = np.frombuffer(bytes(tex.data), np.uint8).reshape(tex.height, tex.width, tex.nchannel)
            target = folder / f"{tex.name}.png"
            cv2.imwrite(str(target), image[..., ::-1] if tex.nchannel == 3 else image)
            tex.data = b""
            tex.file = str(target)
        if texture_dir is None:
            for mat in spec.materials:
                mat.textures[int(mujoco.mjtTextureRole.mjTEXROLE_RGB)] = ""
        xml: str = spec.to_xml()
        return xml

    # -- state ------------------------------------------------------------------------------------
    def set_arm_q(self, arm_id: str, q_true_rad: np.ndarray) -> None:
        """Set one arm's true joint angles (call :meth:`forward` before reading poses or contacts)."""
        self.data.qpos[self.qpos_adr[arm_id]] = np.asarray(q_true_rad, dtype=float)

    def forward(self) -> None:
        """Recompute body and geom poses from the joint angles (kinematics only, no dynamics)."""
        mujoco.mj_kinematics(self.model, self.data)

    def T_world_camera(self, arm_id: str) -> np.ndarray:
        """Pose of the arm's camera (depth optical frame) from MuJoCo's kinematics."""
        b = self.camera_body_id[arm_id]
        return make_transform(self.data.xmat[b].reshape(3, 3), self.data.xpos[b])

    def T_world_body(self, name: str) -> np.ndarray:
        b = self.model.body(name).id
        return make_transform(self.data.xmat[b].reshape(3, 3), self.data.xpos[b])

    # -- contacts ---------------------------------------------------------------------------------
    def contacts(self) -> list[Contact]:
        """Contacts of any arm with the table, the object or the other arm at the current state."""
        mujoco.mj_collision(self.model, self.data)
        found = []
        owner = self.geoms.owner
        for k in range(self.data.ncon):
            c = self.data.contact[k]
            g1, g2 = int(c.geom1), int(c.geom2)
            o1, o2 = owner[g1], owner[g2]
            if o1 not in self.arm_ids:
                g1, g2, o1, o2 = g2, g1, o2, o1
            if o1 not in self.arm_ids:
                continue
            x, y, z = (float(v) for v in c.pos)
            found.append(Contact(o1, self.model.geom(g1).name, o2, self.model.geom(g2).name, float(c.dist), (x, y, z)))
        return found

    def clearance(self, arm_id: str, distmax_m: float = 0.5) -> tuple[float, str, str]:
        """Smallest signed distance (m) from ``arm_id`` to the table, the object or the other arm."""
        best = (float(distmax_m), "", "")
        m = self.model
        moving = m.body_weldid[m.geom_bodyid] != 0  # the base stands on the table
        solid = (m.geom_contype | m.geom_conaffinity) != 0  # contact primitives, not the rendered meshes
        mine = [g for g, o in self.geoms.owner.items() if o == arm_id and moving[g] and solid[g]]
        others = [g for g, o in self.geoms.owner.items()
                  if solid[g] and (o in ("table", "object") or (o in self.arm_ids and o != arm_id))]
        for g1 in mine:
            for g2 in others:
                d = mujoco.mj_geomDistance(self.model, self.data, g1, g2, distmax_m, None)
                if d < best[0]:
                    best = (float(d), self.model.geom(g1).name, self.model.geom(g2).name)
        return best


__all__ = ["Contact", "TwinWorld", "WorldGeoms", "table_texture"]
