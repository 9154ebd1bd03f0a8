"""Figures of the rig and of camera trajectories (matplotlib, imported lazily, Agg backend).

- :func:`plot_rig`: both arms at given joints (links, collision capsules), camera bodies and frustums,
  table and workspace, in a perspective and a top view.
- :func:`plot_trajectories`: both camera trajectories of a survey with optical axes, the object
  envelope, the bases and the table, in a top view (x-y) and a side view (x-z).

Colours: arm110 red, arm111 blue, everywhere.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from darp.colours import arm_colour
from darp.formats.atomic import atomic_path
from darp.kinematics import z1
from darp.kinematics.rig import Rig

if TYPE_CHECKING:
    from darp.reconstruction.poses import SurveyPoses

FRUSTUM_FOV_DEG = (69.0, 42.0)  # D435-class colour camera, horizontal x vertical
FRUSTUM_DEPTH_M = 0.10
AXIS_ARROW_M = 0.08


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, out: str | Path) -> Path:
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format=out.suffix.lstrip(".") or "png", dpi=130)
    _pyplot().close(fig)
    return out


def frustum_lines(T_world_cam: np.ndarray, depth_m: float = FRUSTUM_DEPTH_M) -> list[np.ndarray]:
    """Line segments (each (2, 3)) of a camera frustum: apex to 4 corners and the far rectangle."""
    hx = np.tan(np.radians(FRUSTUM_FOV_DEG[0] / 2)) * depth_m
    hy = np.tan(np.radians(FRUSTUM_FOV_DEG[1] / 2)) * depth_m
    corners_cam = np.array([[-hx, -hy, depth_m], [hx, -hy, depth_m], [hx, hy, depth_m], [-hx, hy, depth_m]])
    corners = corners_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    apex = T_world_cam[:3, 3]
    lines = [np.stack([apex, c]) for c in corners]
    lines += [np.stack([corners[i], corners[(i + 1) % 4]]) for i in range(4)]
    # a short tick marks the image's top edge (camera -y), so that a flipped mount is visible
    top_mid = (corners[0] + corners[1]) / 2
    lines.append(np.stack([top_mid, top_mid - T_world_cam[:3, 1] * 0.3 * hy]))
    return lines


def box_lines(T_world_box: np.ndarray, size_m: np.ndarray) -> list[np.ndarray]:
    """The 12 edges (each (2, 3)) of a box of ``size_m`` centred at ``T_world_box``."""
    h = np.asarray(size_m) / 2
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    corners = (signs * h) @ T_world_box[:3, :3].T + T_world_box[:3, 3]
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.sum(signs[a] != signs[b]) == 1]
    return [np.stack([corners[a], corners[b]]) for a, b in edges]


def primitive_lines(prim: Any) -> list[np.ndarray]:
    """Wireframe of a collision primitive (``darp.kinematics.collision``): box, cylinder or capsule."""
    if prim.kind == "box":
        return box_lines(prim.T_frame_shape, 2.0 * prim.half_extents_m)
    p0, p1 = prim.end_points
    return capsule_lines(p0, p1, prim.radius_m, rounded=prim.kind == "capsule")


def capsule_lines(p0: np.ndarray, p1: np.ndarray, radius: float, n: int = 16,
                  rounded: bool = True) -> list[np.ndarray]:
    """Wireframe of a capsule or cylinder (axis p0-p1, radius): two end rings and four side lines
    (reaching past the rings by the radius for a capsule's rounded ends)."""
    axis = np.asarray(p1, float) - np.asarray(p0, float)
    length = np.linalg.norm(axis)
    u = axis / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(u, helper)
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    angles = np.linspace(0, 2 * np.pi, n + 1)
    ring = radius * (np.outer(np.cos(angles), a) + np.outer(np.sin(angles), b))
    lines = [p0 + ring, p1 + ring]
    cap = radius if rounded else 0.0
    for k in range(0, n, n // 4):
        lines.append(np.stack([p0 + ring[k] - cap * u, p1 + ring[k] + cap * u]))
    return lines


def _draw_lines3d(ax: Any, lines: list[np.ndarray], **kwargs: Any) -> None:
    for seg in lines:
        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], **kwargs)


def plot_rig(
    rig: Rig,
    q_by_arm: Mapping[str, np.ndarray],
    out: str | Path,
    *,
    calibration: Any = None,
    title: str | None = None,
) -> Path:
    """Draw both arms at ``q_by_arm`` (perspective + top view) and save to ``out`` (PNG/SVG/PDF)."""
    plt = _pyplot()
    fig = plt.figure(figsize=(13, 6.2))
    views = [("perspective", 22, -62), ("top (x right, y up)", 90, -90)]
    table = rig.table.corners()
    ws = rig.workspace
    for col, (name, elev, azim) in enumerate(views):
        ax = fig.add_subplot(1, 2, col + 1, projection="3d")
        ring = np.vstack([table, table[:1]])
        ax.plot(ring[:, 0], ring[:, 1], ring[:, 2], color="0.35", lw=1.2)
        ax.plot_trisurf(table[:, 0], table[:, 1], table[:, 2], color="0.85", alpha=0.35, linewidth=0)
        ws_box = np.eye(4)
        ws_box[:3, 3] = ws.center_m
        ws_size = np.array([np.ptp(ws.x_range_m), np.ptp(ws.y_range_m), np.ptp(ws.z_range_m)])
        _draw_lines3d(ax, box_lines(ws_box, ws_size), color="tab:green", lw=0.6, ls="--")
        for index, (arm, q) in enumerate(q_by_arm.items()):
            colour = arm_colour(arm, index)
            T_world_base = rig.extrinsics(arm, calibration)[0]
            dq = rig.extrinsics(arm, calibration)[2]
            links = T_world_base @ z1.link_transforms(np.asarray(q) + dq)
            chain = np.vstack([links[:, :3, 3], rig.T_world_wrist(arm, q, calibration=calibration)[:3, 3]])
            ax.plot(chain[:, 0], chain[:, 1], chain[:, 2], "-o", color=colour, lw=2.5, ms=3,
                    label=f"{arm} ({rig.arm(arm).side})")
            for prim in rig.arm_primitives(arm, q, calibration=calibration).to_list():
                _draw_lines3d(ax, primitive_lines(prim), color=colour, lw=0.4, alpha=0.45)
            T_cam = rig.T_world_cam(arm, q, calibration=calibration)
            _draw_lines3d(ax, frustum_lines(T_cam), color="k", lw=0.8)
            T_body = rig.T_world_camera_body(arm, q, calibration=calibration)
            _draw_lines3d(ax, box_lines(T_body, rig.camera_body.size_m), color=colour, lw=1.0)
            base = T_world_base[:3, 3]
            facing = T_world_base[:3, 0] * 0.15
            ax.quiver(*base, *facing, color=colour, lw=1.0, arrow_length_ratio=0.25)
        _equal_axes_3d(ax, np.vstack([table, table + [0, 0, 0.75]]))
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_zlabel("z (m)")
        if elev == 90:  # looking straight down: z ticks would pile up on one point
            ax.set_zticks([])
            ax.set_zlabel("")
            ax.set_proj_type("ortho")
        ax.set_title(name, fontsize=10)
        if col == 0:
            ax.legend(loc="upper left", fontsize=8)
    fig.suptitle(title or f"rig {rig.name}: arms, cameras (frustum = optical axis), table, workspace (green)")
    fig.tight_layout()
    return _save(fig, out)


def _equal_axes_3d(ax: Any, points: np.ndarray) -> None:
    lo, hi = points.min(axis=0), points.max(axis=0)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-3)))


def _cylinder_outline(envelope: Any) -> tuple[np.ndarray, np.ndarray] | None:
    if envelope is None or not getattr(envelope, "has_geometry", False):
        return None
    c, r, h = np.asarray(envelope.center_m, float), float(envelope.radius_m), float(envelope.height_m)
    angles = np.linspace(0, 2 * np.pi, 73)
    top = np.stack([c[0] + r * np.cos(angles), c[1] + r * np.sin(angles)], axis=1)
    side = np.array([[c[0] - r, c[2] - h / 2], [c[0] + r, c[2] - h / 2], [c[0] + r, c[2] + h / 2],
                     [c[0] - r, c[2] + h / 2], [c[0] - r, c[2] - h / 2]])
    return top, side


def _spread_along_path(centres: np.ndarray, posed: np.ndarray, count: int) -> np.ndarray:
    """Indices of up to ``count`` posed frames evenly spaced by path length (first and last included)."""
    idx = np.flatnonzero(posed)
    if idx.size <= 1:
        return idx
    steps = np.linalg.norm(np.diff(centres[idx], axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    if travelled[-1] < 1e-6:  # a camera that never moved: one axis is enough
        return idx[:1]
    marks = np.linspace(0.0, travelled[-1], count)
    spread: np.ndarray = idx[np.unique(np.searchsorted(travelled, marks).clip(0, idx.size - 1))]
    return spread


def plot_trajectories(
    result: SurveyPoses,
    out: str | Path,
    *,
    rig: Rig | None = None,
    max_arrows: int = 40,
) -> Path:
    """Top (x-y) and side (x-z) views of every camera trajectory of ``result``; saved to ``out``."""
    plt = _pyplot()
    from matplotlib.collections import LineCollection

    fig, axes = plt.subplots(1, 2, figsize=(14, 6.0))
    planes = [("top view", (0, 1), "y (m)"), ("side view (from -y)", (0, 2), "z (m)")]
    envelope = _cylinder_outline(result.envelope)
    for ax, (name, (i, j), ylabel) in zip(axes, planes, strict=True):
        if rig is not None:
            corners = rig.table.corners()
            if j == 1:
                ring = np.vstack([corners, corners[:1]])
                ax.plot(ring[:, i], ring[:, j], color="0.4", lw=1.0, label="table")
            else:
                ax.plot(rig.table.x_range_m, [rig.table.height_m] * 2, color="0.4", lw=1.5, label="table")
        if envelope is not None:
            outline = envelope[0] if j == 1 else envelope[1]
            ax.plot(outline[:, 0], outline[:, 1], color="tab:green", lw=1.2, label="object envelope")
        for index, (arm, traj) in enumerate(result.trajectories.items()):
            colour = arm_colour(arm, index)
            T_world_base = result.calibration.arms[arm].T_world_base
            base = T_world_base[:3, 3]
            ax.plot(base[i], base[j], "s", color=colour, ms=9, mec="k")
            ax.annotate(f"{arm} base", (base[i], base[j]), textcoords="offset points", xytext=(4, -12), fontsize=8)
            posed = traj.poses.posed
            centres = traj.poses.T_world_cam[:, :3, 3]  # NaN rows break the line at unposed frames
            n_posed = int(np.count_nonzero(posed))
            ax.plot(centres[:, i], centres[:, j], "-", color=colour, lw=1.0,
                    label=f"{arm} camera {traj.serial} ({n_posed}/{traj.poses.status.size} posed)")
            pick = _spread_along_path(centres, posed, max_arrows)
            if pick.size:
                tips = centres[pick] + traj.poses.T_world_cam[pick, :3, 2] * AXIS_ARROW_M
                segments = np.stack([centres[pick][:, [i, j]], tips[:, [i, j]]], axis=1)
                # matplotlib's stubs want a Sequence of segments; it takes an (N, 2, 2) array as well
                ax.add_collection(LineCollection(segments, colors=colour, linewidths=0.9,  # type: ignore[arg-type]
                                                 alpha=0.8))
                ax.plot(centres[pick, i], centres[pick, j], ".", color=colour, ms=3)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, lw=0.3)
        ax.set_xlabel("x (m)")
        ax.set_ylabel(ylabel)
        ax.set_title(name, fontsize=10)
    axes[0].legend(loc="best", fontsize=8)
    kind = "nominal rig" if result.calibration_path is None else f"calibration {result.calibration.epoch}"
    fig.suptitle(f"{result.survey_path.name}: camera trajectories ({kind}); arrows = optical axes")
    fig.tight_layout()
    return _save(fig, out)


__all__ = ["box_lines", "capsule_lines", "frustum_lines", "plot_rig", "plot_trajectories",
           "primitive_lines"]
