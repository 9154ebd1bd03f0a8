"""A contact sheet of twin objects: a small orthographic z-buffer renderer plus a matplotlib grid.

matplotlib's own 3-D axes sort whole polygons and get overlapping parts (a handle in a mug wall)
wrong, and cannot show textures; a per-pixel depth test with UV lookup shows each object as the
twin's cameras will see it: its parts' colours, its textures, and its shape.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from darp.formats.atomic import atomic_path
from darp.twin.objects.shapes import ObjectPart

if TYPE_CHECKING:
    from darp.twin.objects.model import TwinObject

BACKGROUND = np.array([0.97, 0.97, 0.96])


def view_axes(azimuth_deg: float, elevation_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, towards_camera) unit vectors of an orthographic view looking at the object."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    towards = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(-towards, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return right, np.cross(right, -towards), towards


def render(parts: Sequence[ObjectPart], *, size_px: int = 360, azimuth_deg: float = -65.0,
           elevation_deg: float = 25.0, supersample: int = 2) -> tuple[np.ndarray, float]:
    """Render parts to an RGB uint8 image; also return the scale in pixels per metre."""
    right, up, towards = view_axes(azimuth_deg, elevation_deg)
    light = 0.45 * right + 0.7 * up + towards
    light /= np.linalg.norm(light)
    half_vec = (light + towards) / np.linalg.norm(light + towards)
    n = size_px * supersample
    all_v = np.vstack([p.mesh.vertices for p in parts])
    sx, sy = all_v @ right, all_v @ up
    scale = 0.86 * n / max(np.ptp(sx), np.ptp(sy))
    mid = np.array([(sx.max() + sx.min()) / 2, (sy.max() + sy.min()) / 2])
    image = np.tile(BACKGROUND, (n, n, 1))
    depth = np.full((n, n), -np.inf)
    for part in parts:
        v = np.asarray(part.mesh.vertices)
        px = np.column_stack([n / 2 + scale * (v @ right - mid[0]), n / 2 - scale * (v @ up - mid[1])])
        pz = v @ towards
        normals = np.asarray(part.mesh.face_normals)
        facing = normals @ towards > 0
        shade = 0.38 + 0.62 * np.clip(normals @ light, 0, None)
        gloss = 0.5 * np.clip(normals @ half_vec, 0, None) ** 40 if part.specular else np.zeros(len(normals))
        for f in np.flatnonzero(facing):
            _fill_triangle(part, np.asarray(part.mesh.faces[f]), px, pz, image, depth, shade[f], gloss[f])
    small = cv2.resize((np.clip(image, 0, 1) * 255).astype(np.uint8), (size_px, size_px),
                       interpolation=cv2.INTER_AREA)
    return small, scale / supersample


def _fill_triangle(part: ObjectPart, tri: np.ndarray, px: np.ndarray, pz: np.ndarray, image: np.ndarray,
                   depth: np.ndarray, shade: float, gloss: float) -> None:
    (x0, y0), (x1, y1), (x2, y2) = px[tri]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    if abs(area) < 1e-12:
        return
    n = image.shape[0]
    cx = np.arange(max(int(np.floor(min(x0, x1, x2))), 0), min(int(np.ceil(max(x0, x1, x2))), n - 1) + 1)
    cy = np.arange(max(int(np.floor(min(y0, y1, y2))), 0), min(int(np.ceil(max(y0, y1, y2))), n - 1) + 1)
    if len(cx) == 0 or len(cy) == 0:
        return
    gx, gy = np.meshgrid(cx, cy)
    w0 = ((x1 - gx) * (y2 - gy) - (x2 - gx) * (y1 - gy)) / area
    w1 = ((x2 - gx) * (y0 - gy) - (x0 - gx) * (y2 - gy)) / area
    w2 = 1.0 - w0 - w1
    inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
    z = w0 * pz[tri[0]] + w1 * pz[tri[1]] + w2 * pz[tri[2]]
    rows, cols = gy[inside], gx[inside]
    closer = z[inside] > depth[rows, cols]
    if not closer.any():
        return
    rows, cols = rows[closer], cols[closer]
    depth[rows, cols] = z[inside][closer]
    if part.texture is not None and part.uv is not None:
        uv = (w0[inside][closer, None] * part.uv[tri[0]] + w1[inside][closer, None] * part.uv[tri[1]]
              + w2[inside][closer, None] * part.uv[tri[2]])
        h, w = part.texture.shape[:2]
        tc = np.clip((uv[:, 0] % 1.0) * w, 0, w - 1).astype(int)
        tr = np.clip((1.0 - uv[:, 1]) * h, 0, h - 1).astype(int)
        colour = part.texture[tr, tc].astype(float) / 255.0
    else:
        colour = np.asarray(part.rgba[:3], dtype=float)[None, :]
    image[rows, cols] = np.clip(colour * shade + gloss, 0, 1)


def contact_sheet(path: Path, objects: Sequence[TwinObject], *, panel_px: int = 360, columns: int = 5) -> Path:
    """Render each object in a grid with its measured and paper envelope; PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = -(-len(objects) // columns)
    cols = min(columns, len(objects))
    fig = Figure(figsize=(2.6 * cols, 2.9 * rows), dpi=panel_px / 2.6)
    FigureCanvasAgg(fig)
    for k, obj in enumerate(objects):
        ax = fig.add_subplot(rows, cols, k + 1)
        picture, px_per_m = render(obj.parts, size_px=panel_px)
        ax.imshow(picture)
        bar = 0.05 * px_per_m
        y = panel_px * 0.95
        ax.plot([panel_px * 0.05, panel_px * 0.05 + bar], [y, y], color="k", lw=2)
        ax.text(panel_px * 0.05, y - panel_px * 0.02, "5 cm", fontsize=7)
        paper = ("paper: n/a" if obj.paper_radius_m is None or obj.paper_height_m is None else
                 f"paper {obj.paper_radius_m * 100:.2f} / {obj.paper_height_m * 100:.2f}")
        ax.set_title(f"{obj.name}\nr {obj.radius_m * 100:.2f} / h {obj.height_m * 100:.2f} cm ({paper})",
                     fontsize=7)
        ax.set_axis_off()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
