"""Parametric builders for the paper's ten tabletop objects, sized to its release table.

Each builder returns named :class:`ObjectPart` s in the object frame (metres, z up, resting on z=0;
:mod:`darp.twin.objects.model` recentres them on the footprint). Dimensions are written in centimetres
next to the paper's envelope they were chosen to match; ``docs/twin-objects.md`` lists the results.
Vessels are revolved closed profiles with a wall thickness, so they are open at the top and still
watertight; parts that meet (a mug handle, controller buttons) overlap slightly instead of being
joined by booleans, which keeps every component closed and outward-facing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import ArrayLike
from PIL import Image

from darp.errors import TwinError
from darp.kinematics.transforms import compose, matvec
from darp.twin.objects import textures as tex
from darp.twin.objects.geometry import (
    CM,
    Piece,
    arc,
    arc_tube,
    concat,
    hull,
    planar_uv,
    profile,
    quads,
    revolve,
    rotation,
    rounded_block,
    scaling,
    translation,
)

RGBA = tuple[float, float, float, float]


@dataclass
class ObjectPart:
    """A named sub-mesh with its look: colour, optional texture + UV, and camera-relevant flags.

    ``texture`` is RGB uint8 (row 0 = v 1); ``uv`` has one row per ``mesh`` vertex. ``dark`` marks
    low-reflectance surfaces (weak IR return), ``specular`` mirror-like ones (highlights, dropouts),
    ``transparent`` see-through ones; the camera model decides what to do with them.
    """

    name: str
    mesh: trimesh.Trimesh
    rgba: RGBA
    texture: np.ndarray | None = None
    uv: np.ndarray | None = None
    dark: bool = False
    specular: bool = False
    transparent: bool = False


def make_part(name: str, piece: Piece, rgba: RGBA | None = None, texture: np.ndarray | None = None,
              **flags: bool) -> ObjectPart:
    """Wrap a piece as a part; textured parts keep their UV (seams stay split), others are merged."""
    if texture is not None:
        if piece.uv is None:
            raise TwinError(f"part {name!r} has a texture but no UV")
        # trimesh's TextureVisuals has no annotations
        visual = trimesh.visual.TextureVisuals(uv=piece.uv, image=Image.fromarray(texture))  # type: ignore[no-untyped-call]
        mesh = trimesh.Trimesh(piece.vertices, piece.faces, visual=visual, process=False)
        mesh.merge_vertices()  # merges only vertices whose UV also match
        mesh.remove_unreferenced_vertices()
        assert isinstance(mesh.visual, trimesh.visual.TextureVisuals)
        uv = np.asarray(mesh.visual.uv, dtype=np.float64)
        colour = rgba if rgba is not None else tex.mean_rgba(texture)
    else:
        mesh = trimesh.Trimesh(piece.vertices, piece.faces, process=True)
        mesh.remove_unreferenced_vertices()
        uv, colour = None, rgba if rgba is not None else (0.6, 0.6, 0.6, 1.0)
    return ObjectPart(name, mesh, colour, texture, uv, **flags)


RNG = np.random.Generator | None
SILVER: RGBA = (0.78, 0.79, 0.81, 1.0)
CHROME: RGBA = (0.85, 0.86, 0.88, 1.0)


def red_bull(rng: RNG) -> list[ObjectPart]:
    """250 ml slim can, 5.3 cm x 13.4 cm: domed bottom on a foot ring, printed wall, necked lid."""
    pts, labels = profile([
        ("bottom", [(0, 0.9), (0.9, 0.8), (1.5, 0.55), (1.9, 0.22), (2.05, 0.0), (2.25, 0.0),
                    (2.5, 0.2), (2.62, 0.55), (2.65, 0.9)]),
        ("wall", [(2.65, 11.7)]),
        ("top", [(2.6, 12.2), (2.45, 12.7), (2.32, 13.0), (2.32, 13.3), (2.27, 13.4), (2.17, 13.4),
                 (2.12, 13.3), (2.1, 12.95), (2.0, 12.85), (0, 12.85)]),
    ])
    p = revolve(pts, labels)
    return [make_part("wall", p["wall"], texture=tex.can_label(rng)),
            make_part("top", p["top"], SILVER, specular=True),
            make_part("bottom", p["bottom"], SILVER, specular=True)]


def dumbbell(rng: RNG) -> list[ObjectPart]:
    """Hex dumbbell lying on a flat: heads 3.66 cm across flats, 13.3 cm long, chrome grip."""
    half, head = 6.65, 3.0
    head_rz = [(0, -half), (1.8, -half), (2.113, -half + 0.3), (2.113, -half + head - 0.3),
               (1.8, -half + head), (0, -half + head)]
    grip_rz = [(0, -half + head - 0.2), (1.05, -half + head - 0.2), (1.05, half - head + 0.2),
               (0, half - head + 0.2)]
    lay = compose(translation(z=1.83 * CM), rotation("y", 90))  # axis along x; a hex flat on the table
    parts = []
    pts, labels = profile([("head", head_rz)])
    head_piece = revolve(pts, labels, sections=6, theta0_rad=np.pi / 6)["head"]  # flats at +-x
    for side, turn in (("left", np.eye(4)), ("right", rotation("x", 180))):
        piece = head_piece.transformed(compose(lay, turn))
        parts.append(make_part(f"head_{side}", piece, (0.07, 0.07, 0.08, 1.0), dark=True))
    pts, labels = profile([("grip", grip_rz)])
    grip = revolve(pts, labels, sections=48)["grip"].transformed(lay)
    parts.append(make_part("grip", grip, CHROME, texture=tex.knurl(), specular=True))
    return parts


def controller(rng: RNG) -> list[ObjectPart]:
    """Gamepad lying flat: a flattened body, two angled grips, a top bump, buttons, d-pad, sticks."""
    body = _capsule(4.4, 2.2).transformed(
        compose(translation(0, 0.3 * CM, 1.1 * CM), scaling(1, 1, 0.5), rotation("y", 90)))
    shell = [body]
    for sx in (1.0, -1.0):
        p0, p1 = np.array([2.9 * sx, 0.0]), np.array([4.0 * sx, -2.5])
        mid, d = (p0 + p1) / 2, p1 - p0
        grip = _capsule(float(np.hypot(*d)), 1.35).transformed(
            compose(translation(mid[0] * CM, mid[1] * CM, 1.2 * CM), scaling(1, 1, 1.2 / 1.35),
                    rotation("z", np.degrees(np.arctan2(d[1], d[0]))), rotation("y", 90)))
        shell.append(grip)
    shell.append(_ellipsoid(2.0, 1.3, 0.5).transformed(translation(0, 0.9 * CM, 2.0 * CM)))
    shell_piece = concat(shell)
    shell_mesh = trimesh.Trimesh(shell_piece.vertices, shell_piece.faces, process=False)
    top = _top_surface(shell_mesh)
    dark_grey: RGBA = (0.13, 0.13, 0.15, 1.0)
    parts = [make_part("shell", shell_piece, dark_grey, dark=True)]
    bx, by = 3.0, 0.35
    for name, (dx, dy), colour in (("button_a", (0, -0.55), (0.2, 0.7, 0.3, 1.0)),
                                   ("button_b", (0.55, 0), (0.85, 0.15, 0.15, 1.0)),
                                   ("button_x", (-0.55, 0), (0.15, 0.35, 0.85, 1.0)),
                                   ("button_y", (0, 0.55), (0.95, 0.8, 0.1, 1.0))):
        x, y = bx + dx, by + dy
        parts.append(make_part(name, _cylinder(0.28, top(x, y) - 0.3, top(x, y) + 0.15, x, y), colour))
    z = top(-bx, by)
    dpad = concat([hull(np.array([[sx * a, sy * b, zz] for sx in (-1, 1) for sy in (-1, 1)
                                  for zz in (z - 0.3, z + 0.15)]) * CM
                        + np.array([-bx, by, 0]) * CM) for a, b in ((0.65, 0.21), (0.21, 0.65))])
    parts.append(make_part("dpad", dpad, (0.2, 0.2, 0.22, 1.0), dark=True))
    sticks = []
    for x in (-1.4, 1.4):
        z = top(x, -0.8)
        pts, labels = profile([("s", [(0, z - 0.3), (0.42, z - 0.3), (0.42, z + 0.45), (0.6, z + 0.45),
                                      (0.6, z + 0.6), (0, z + 0.6)])])  # stem and thumb cap, one body
        sticks.append(revolve(pts, labels, sections=32)["s"].transformed(translation(x * CM, -0.8 * CM)))
    parts.append(make_part("sticks", concat(sticks), (0.25, 0.25, 0.27, 1.0), dark=True))
    return parts


def cube(rng: RNG) -> list[ObjectPart]:
    """The table's 'cube' envelope is a flat block: 6.25 x 6.25 x 1.6 cm with 3 mm rounded edges."""
    return [make_part("block", rounded_block((6.25, 6.25, 1.6), 0.3), (0.92, 0.5, 0.12, 1.0))]


def ketchup(rng: RNG) -> list[ObjectPart]:
    """Squeeze bottle, oval body (8.8 x 5.5 cm) rounding into a round neck, white flip cap, 14.9 cm."""
    pts, labels = profile([
        ("bottom", [(0, 0.3), (3.4, 0.08), (3.9, 0.0), (4.2, 0.2), (4.37, 0.7), (4.41, 1.6)]),
        ("label", [(4.41, 7.5), (4.36, 9.0)]),
        ("shoulder", [(4.2, 10.0), (3.9, 10.7), (3.4, 11.4), (2.6, 12.1), (1.8, 12.5)]),
        ("cap", [(1.95, 12.5), (1.95, 14.2), (1.8, 14.55), (1.25, 14.7), (0.55, 14.7), (0.45, 14.93),
                 (0, 14.93)]),
    ])
    # oval body (y squeezed to 62 %); up the shoulder the flat faces keep their depth until round
    half_depth = 0.62 * 4.41 * CM
    y_scale = np.where(pts[:, 1] < 9.0 * CM, 0.62, np.minimum(1.0, half_depth / np.maximum(pts[:, 0], 1e-9)))
    p = revolve(pts, labels, y_scale=y_scale)
    red: RGBA = (0.69, 0.07, 0.09, 1.0)
    return [make_part("label", p["label"], texture=tex.ketchup_label(rng)),
            make_part("body", concat([p["bottom"], p["shoulder"]]), red),
            make_part("cap", p["cap"], (0.95, 0.94, 0.9, 1.0))]


def picture_frame(rng: RNG) -> list[ObjectPart]:
    """21 x 19.2 cm wooden frame leaning back 12 deg on a strut; the photo sits in a 5 mm pocket."""
    w, h, d, b, pocket, lean = 21.0, 19.16, 1.6, 2.0, 0.5, 12.0
    outer = [(-w / 2, 0), (w / 2, 0), (w / 2, h), (-w / 2, h)]
    inner = [(-w / 2 + b, b), (w / 2 - b, b), (w / 2 - b, h - b), (-w / 2 + b, h - b)]
    ring = [(x, 0.0, z) for x, z in outer] + [(x, d, z) for x, z in outer] \
        + [(x, 0.0, z) for x, z in inner] + [(x, pocket, z) for x, z in inner]
    sides = [(0, 0, -1), (1, 0, 0), (0, 0, 1), (-1, 0, 0)]  # outward normals of edges 0-1, 1-2, 2-3, 3-0
    qs: list[tuple[int, int, int, int]] = []
    outs: list[ArrayLike] = []
    for i in range(4):
        j = (i + 1) % 4
        qs += [(i, j, 4 + j, 4 + i), (i, j, 8 + j, 8 + i), (8 + i, 8 + j, 12 + j, 12 + i)]
        edge_out = np.array(sides[i], dtype=float)
        outs += [edge_out, (0, -1, 0), -edge_out]
    frame = quads(np.asarray(ring) * CM, qs, outs)
    back = quads(np.asarray([(x, d, z) for x, z in outer]) * CM, [(0, 1, 2, 3)], [(0, 1, 0)])
    photo = quads(np.asarray([(x, pocket, z) for x, z in inner]) * CM, [(0, 1, 2, 3)], [(0, -1, 0)])
    photo.uv = planar_uv(photo.vertices, np.array([0, 0, h / 2]) * CM, np.array([1.0, 0, 0]),
                         np.array([0, 0, 1.0]), ((w / 2 - b) * CM, (h / 2 - b) * CM))
    tilt = compose(translation(y=d * CM), rotation("x", -lean), translation(y=-d * CM))  # pivot: back-bottom edge
    frame, back, photo = (p.transformed(tilt) for p in (frame, back, photo))
    strut = _strut(tilt, d, attach_z_cm=10.5, angle_deg=60.0, half_width_cm=1.4, thickness_cm=0.5)
    wood: RGBA = (0.5, 0.33, 0.18, 1.0)
    backing: RGBA = (0.3, 0.22, 0.15, 1.0)
    return [make_part("frame", frame, wood), make_part("backing", back, backing),
            make_part("photo", photo, texture=tex.frame_photo(rng)), make_part("strut", strut, backing)]


def mug(rng: RNG) -> list[ObjectPart]:
    """Wide mug: 10.6 cm across, 6.3 cm tall, 4.4 mm wall, foot ring, C handle reaching 3.8 cm out."""
    pts, labels = profile([
        ("foot", [(0, 0.25), (4.2, 0.25), (4.45, 0.0), (4.9, 0.0), (5.2, 0.2), (5.3, 0.6)]),
        ("outer", [(5.3, 5.9), (5.3, 6.08)]),
        ("inside", arc(5.08, 6.08, 0.22, 0, 180, 9)[1:] + [(4.86, 1.2), (4.7, 0.85), (4.4, 0.75),
                                                         (0, 0.75)]),
    ])
    p = revolve(pts, labels)
    glaze = tex.mug_glaze(rng)
    handle = arc_tube((6.366 * CM, 3.4 * CM), 2.284 * CM, -123.7, 123.7, 0.4 * CM, 0.8 * CM)
    white: RGBA = (0.95, 0.95, 0.93, 1.0)
    return [make_part("outer", p["outer"], texture=glaze), make_part("inside", p["inside"], white),
            make_part("foot", p["foot"], (0.86, 0.82, 0.74, 1.0)),
            make_part("handle", handle, tex.mean_rgba(glaze[:100]))]


def paperweight(rng: RNG) -> list[ObjectPart]:
    """Swirled resin dome: 9.7 cm across, 7.4 cm tall (half-ellipse over a short rounded foot)."""
    dome = [(4.85 * np.cos(a), 0.9 + 6.54 * np.sin(a)) for a in np.radians(np.linspace(0, 90, 19))]
    pts, labels = profile([("base", [(0, 0), (4.3, 0), (4.62, 0.12), (4.8, 0.45)]), ("dome", dome)])
    p = revolve(pts, labels)
    swirl = tex.marble(rng)
    return [make_part("dome", p["dome"], texture=swirl, specular=True),
            make_part("base", p["base"], (0.25, 0.27, 0.3, 1.0))]


def clock(rng: RNG) -> list[ObjectPart]:
    """Desk clock: a 9.3 cm round case on its edge with a chrome bezel, on a 10.2 x 6 x 1 cm base."""
    pts, labels = profile([
        ("face", [(0, -1.9), (3.8, -1.9)]),
        ("bezel", [(3.85, -2.4), (4.2, -2.4), (4.65, -2.2), (4.65, -2.0), (4.6, -1.9)]),
        ("case", [(4.6, 1.7)] + arc(4.2, 1.7, 0.4, 0, 90, 5)[1:] + [(0, 2.1)]),
    ])
    centre_z = 1.0 + 4.65 - 0.35  # sits 3.5 mm into the base
    stand = compose(translation(z=centre_z * CM), rotation("x", -90))  # revolve axis -> y, face towards -y
    p = {k: v.transformed(stand) for k, v in revolve(pts, labels).items()}
    p["face"].uv = planar_uv(p["face"].vertices, np.array([0, -1.9, centre_z]) * CM, np.array([1.0, 0, 0]),
                             np.array([0, 0, 1.0]), (3.8 * CM, 3.8 * CM))
    return [make_part("face", p["face"], texture=tex.clock_face(rng)),
            make_part("bezel", p["bezel"], CHROME, specular=True),
            make_part("case", p["case"], (0.86, 0.83, 0.76, 1.0)),
            make_part("base", rounded_block((10.2, 6.0, 1.0), 0.2), (0.55, 0.36, 0.2, 1.0))]


def cup(rng: RNG) -> list[ObjectPart]:
    """Paper cup: 5.7 cm base, 8.3 cm rolled rim, 10.16 cm tall, 1.2 mm wall, recessed bottom."""
    wall_in = 0.12
    pts, labels = profile([
        ("bottom", [(0, 0.8), (2.72, 0.8), (2.72, 0.0), (2.85, 0.0)]),
        ("outer", [(4.0, 9.86)]),
        ("inside", arc(4.0, 10.01, 0.15, -90, 200, 12)[1:] + [(4.0 - wall_in, 9.85),
                                                            (2.96 - wall_in, 0.95), (0, 0.95)]),
    ])
    p = revolve(pts, labels)
    white: RGBA = (0.96, 0.95, 0.93, 1.0)
    return [make_part("outer", p["outer"], texture=tex.cup_print(rng)),
            make_part("inside", p["inside"], white), make_part("bottom", p["bottom"], white)]


BUILDERS: dict[str, Callable[[RNG], list[ObjectPart]]] = {
    "red_bull": red_bull, "dumbbell": dumbbell, "controller": controller, "cube": cube,
    "ketchup": ketchup, "picture_frame": picture_frame, "mug": mug, "paperweight": paperweight,
    "clock": clock, "cup": cup,
}


def _capsule(length_cm: float, radius_cm: float) -> Piece:
    """Closed capsule along z centred on the origin (cylinder ``length_cm`` plus two hemispheres)."""
    lo = arc(0, -length_cm / 2, radius_cm, -90, 0, 9)
    hi = arc(0, length_cm / 2, radius_cm, 0, 90, 9)
    pts, labels = profile([("s", lo + hi)])
    return revolve(pts, labels, sections=48)["s"]


def _ellipsoid(ax_cm: float, ay_cm: float, az_cm: float) -> Piece:
    pts, labels = profile([("s", arc(0, 0, 1.0, -90, 90, 17))])
    return revolve(pts, labels, sections=48)["s"].transformed(scaling(ax_cm, ay_cm, az_cm))


def _cylinder(radius_cm: float, z0_cm: float, z1_cm: float, x_cm: float, y_cm: float) -> Piece:
    pts, labels = profile([("s", [(0, z0_cm), (radius_cm, z0_cm), (radius_cm, z1_cm), (0, z1_cm)])])
    return revolve(pts, labels, sections=32)["s"].transformed(translation(x_cm * CM, y_cm * CM))


def _top_surface(mesh: trimesh.Trimesh) -> Callable[[float, float], float]:
    """Height (cm) of a mesh's top surface above a table point (cm): highest triangle over it."""
    tri = np.asarray(mesh.triangles)

    def top(x_cm: float, y_cm: float) -> float:
        p = np.array([x_cm, y_cm]) * CM
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        e1, e2, q = (b - a)[:, :2], (c - a)[:, :2], p - a[:, :2]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        ok = np.abs(det) > 1e-16
        det = np.where(ok, det, 1.0)
        s = (q[:, 0] * e2[:, 1] - q[:, 1] * e2[:, 0]) / det
        t = (e1[:, 0] * q[:, 1] - e1[:, 1] * q[:, 0]) / det
        inside = ok & (s >= 0) & (t >= 0) & (s + t <= 1)
        if not inside.any():
            raise TwinError(f"no surface above ({x_cm}, {y_cm}) cm")
        z = a[:, 2] + s * (b - a)[:, 2] + t * (c - a)[:, 2]
        return float(z[inside].max()) / CM

    return top


def _strut(tilt: np.ndarray, depth_cm: float, *, attach_z_cm: float, angle_deg: float,
           half_width_cm: float, thickness_cm: float) -> Piece:
    """A plank from the frame's back (slightly embedded) down to a flat foot on the table."""
    attach = matvec(tilt, np.array([0.0, depth_cm * CM, attach_z_cm * CM, 1.0]))[:3]
    foot = np.array([0.0, attach[1] + attach[2] / np.tan(np.radians(angle_deg)), 0.0])
    u = (foot - attach) / np.linalg.norm(foot - attach, axis=-1)
    n = np.array([0.0, -u[2], u[1]])  # across the plank, pointing back and up
    t = thickness_cm * CM
    top_in, top_out = attach - 0.4 * CM * u, attach - 0.4 * CM * u + t * n
    foot_out = foot + t * n - (t * n[2] / u[2]) * u  # outer face meets the table
    x = np.array([half_width_cm * CM, 0.0, 0.0])
    return hull(np.array([p + s * x for p in (top_in, top_out, foot, foot_out) for s in (-1, 1)]))
