"""Pinhole rendering of a MuJoCo scene: colour, exact metric depth and geom segmentation.

A thin wrapper that owns one offscreen OpenGL context, an ``MjrContext`` and an ``MjvScene``. It renders
from any camera pose ``T_world_cam`` (OpenCV frame: x right, y down, z forward) with any pinhole
intrinsics, honoured exactly: instead of a model camera (vertical fovy, centred principal point) it
writes an asymmetric OpenGL frustum into the scene's GL cameras, so ``fx != fy`` and an off-centre
principal point need no warping or cropping. Pixel centres are at integer coordinates (OpenCV and
librealsense): the frustum's left edge is at ``u = -0.5`` and its right edge at ``u = W - 0.5``.

Why not ``mujoco.Renderer``: it converts depth with the model's near/far planes and reads colour and
depth in separate renders; here one ``mjr_render`` gives both buffers and the depth conversion uses
the frustum this module sets. MuJoCo renders with reversed Z into a float depth buffer, so metric
depth is exact to float32 precision (checked against ``mj_multiRay`` in the tests).

Multisampling is switched off for this renderer's context: with MSAA, depth and segmentation ids at
edges are resolved from sub-pixel samples (mixed ids, off-centre depths). Shadows are off by default:
the shadow map pass costs about 25 ms per image on a 2-core llvmpipe CPU and the twin's lights are
ambient-like.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

import cv2
import numpy as np

from darp.errors import TwinError
from darp.formats.limits import IMAGE_SIDE_MAX_PX
from darp.formats.realsense.types import Intrinsics

os.environ.setdefault("MUJOCO_GL", "egl")
import mujoco as mujoco  # MUJOCO_GL must be set before the first import; re-exported for that reason

NO_GEOM = -1  # segmentation value of pixels that see no geom
Region = tuple[int, int, int, int]  # image rectangle (u0, v0, u1, v1): columns u0..u1-1, rows v0..v1-1


def _gl_context_class() -> Any:
    """The GL context class for the backend named by MUJOCO_GL (egl unless set otherwise)."""
    backend = os.environ.get("MUJOCO_GL", "egl").lower().strip()
    try:
        if backend == "osmesa":
            from mujoco.osmesa import GLContext
        elif backend == "egl":
            from mujoco.egl import GLContext
        else:
            from mujoco.glfw import GLContext
    except (ImportError, OSError, AttributeError) as err:
        raise TwinError(f"MuJoCo rendering backend {backend!r} is unavailable: {err}") from err
    return GLContext


@dataclass
class RenderOutput:
    """One rendered view: ``rgb`` in RGB order; ``depth_m`` is z along the optical axis (0 = no surface)."""

    rgb: np.ndarray | None  # (H, W, 3) uint8
    depth_m: np.ndarray | None  # (H, W) float32


def gl_camera_from_pose(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, forward and up vectors of the OpenGL camera for an OpenCV camera pose.

    OpenGL cameras look along their -z with y up; OpenCV cameras look along +z with y down, so
    forward is the OpenCV z axis and up is minus the OpenCV y axis.
    """
    T = np.asarray(T_world_cam, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise TwinError(f"T_world_cam must be a finite 4x4 matrix, got shape {T.shape}")
    return T[:3, 3].copy(), T[:3, 2].copy(), -T[:3, 1]


def frustum_from_intrinsics(intr: Intrinsics, near_m: float) -> tuple[float, float, float, float]:
    """(left, right, bottom, top) of the near-plane window for pinhole intrinsics (integer pixel centres)."""
    left = near_m * (-0.5 - intr.ppx) / intr.fx
    right = near_m * (intr.width - 0.5 - intr.ppx) / intr.fx
    top = near_m * (intr.ppy + 0.5) / intr.fy
    bottom = -near_m * (intr.height - 0.5 - intr.ppy) / intr.fy
    return left, right, bottom, top


def geom_image_region(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    geom_ids: np.ndarray,
    T_world_cam: np.ndarray,
    intr: Intrinsics,
    *,
    near_m: float = 0.01,
    margin_px: int = 2,
) -> Region | None:
    """Image rectangle ``(u0, v0, u1, v1)`` (exclusive ends) that holds every pixel of the given geoms.

    Projects the corners of each geom's bounding box (``model.geom_aabb`` at the pose in ``data``);
    None when no box reaches into the image; the whole image when a box crosses the near plane.
    Conservative: ``margin_px`` pixels are added around the projected corners.
    """
    ids = np.asarray(geom_ids, dtype=int).reshape(-1)
    if ids.size == 0:
        return None
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    aabb = model.geom_aabb[ids]  # (n, 6): centre and half-size in the geom frame
    local = aabb[:, None, :3] + signs[None] * aabb[:, None, 3:]  # (n, 8, 3)
    R = data.geom_xmat[ids].reshape(-1, 3, 3)
    world = np.einsum("nij,nkj->nki", R, local) + data.geom_xpos[ids][:, None, :]
    T = np.asarray(T_world_cam, dtype=float)
    cam = (world - T[:3, 3]) @ T[:3, :3]  # (n, 8, 3) in the camera frame
    z = cam[..., 2]
    whole = (0, 0, intr.width, intr.height)
    in_front = np.all(z > near_m, axis=1)
    if np.any(~in_front & np.any(z > near_m, axis=1)):
        return whole  # a box crosses the camera plane: its projection is unbounded
    if not np.any(in_front):
        return None
    cam = cam[in_front]
    u = intr.fx * cam[..., 0] / cam[..., 2] + intr.ppx
    v = intr.fy * cam[..., 1] / cam[..., 2] + intr.ppy
    u0 = max(0, int(np.floor(u.min())) - margin_px)
    v0 = max(0, int(np.floor(v.min())) - margin_px)
    u1 = min(intr.width, int(np.ceil(u.max())) + 1 + margin_px)
    v1 = min(intr.height, int(np.ceil(v.max())) + 1 + margin_px)
    if u0 >= u1 or v0 >= v1:
        return None
    return (u0, v0, u1, v1)


class SceneRenderer:
    """Renders a MuJoCo model from arbitrary OpenCV camera poses and intrinsics; reuse it across frames.

    Call :meth:`update_scene` once per simulation state, then :meth:`render_view`,
    :meth:`render_segmentation` or :meth:`render_segmentation_and_depth` for as many cameras as
    needed (:meth:`render` does an update and one view).
    One renderer can serve several twin cameras of the same model.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        max_width: int = 1280,
        max_height: int = 800,
        *,
        near_m: float = 0.01,
        far_m: float = 20.0,
        shadows: bool = False,
        scene_option: mujoco.MjvOption | None = None,
        max_geom: int = 10000,
        min_slices: int = 96,
    ) -> None:
        if not 0.0 < near_m < far_m:
            raise TwinError(f"renderer clip planes must satisfy 0 < near < far, got {near_m}, {far_m}")
        self.model = model
        self.near_m = float(near_m)
        self.far_m = float(far_m)
        self.max_width = int(max_width)
        self.max_height = int(max_height)
        self._gl: Any = None
        self._con: mujoco.MjrContext | None = None
        # The offscreen buffer is sized from the model; grow it (a visual-only setting) if too small.
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.max_width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, self.max_height)
        if max(self.max_width, self.max_height) > IMAGE_SIDE_MAX_PX:
            raise TwinError(f"{self.max_width}x{self.max_height} images are too large to render (at most "
                            f"{IMAGE_SIDE_MAX_PX} px a side)")
        context_made = False
        try:
            self._gl = _gl_context_class()(self.max_width, self.max_height)
            self._gl.make_current()
            context_made = True
            quality = model.vis.quality
            saved = (quality.offsamples, quality.numslices, quality.numstacks)
            quality.offsamples = 0  # no MSAA in this context (see module docstring)
            # Finer built-in sphere/cylinder meshes: chord error on a 5 cm sphere 0.3 mm -> 0.03 mm.
            quality.numslices = max(quality.numslices, min_slices)
            quality.numstacks = max(quality.numstacks, min_slices // 2)
            try:
                self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
            finally:
                quality.offsamples, quality.numslices, quality.numstacks = saved
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
            self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR  # raw reversed-Z values
        except TwinError:
            raise
        except Exception as err:  # EGL/OSMesa failures surface as assorted exception types
            self.close()
            if context_made:  # OpenGL works; its buffers for this image size could not be made
                raise TwinError(f"cannot allocate offscreen buffers for {self.max_width}x{self.max_height} images "
                                f"({type(err).__name__}: {err})") from err
            raise TwinError(
                f"cannot create an offscreen OpenGL context ({type(err).__name__}: {err}); "
                "install libegl1/libosmesa6 or set MUJOCO_GL"
            ) from err
        self._scene = mujoco.MjvScene(model, maxgeom=max_geom)
        self._option = scene_option if scene_option is not None else mujoco.MjvOption()
        self._free_camera = mujoco.MjvCamera()
        mujoco.mjv_defaultFreeCamera(model, self._free_camera)
        self.shadows = shadows
        self._buffers: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    # -- scene state ----------------------------------------------------------------------------------
    def update_scene(self, data: mujoco.MjData) -> None:
        """Copy the geometry of ``data`` (after mj_forward/mj_kinematics) into the render scene."""
        mujoco.mjv_updateScene(
            self.model, data, self._option, None, self._free_camera, mujoco.mjtCatBit.mjCAT_ALL, self._scene
        )
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(self.shadows)

    def _set_camera(self, T_world_cam: np.ndarray, intr: Intrinsics) -> mujoco.MjrRect:
        if intr.width > self.max_width or intr.height > self.max_height:
            raise TwinError(
                f"image {intr.width}x{intr.height} exceeds this renderer's "
                f"{self.max_width}x{self.max_height} buffer"
            )
        pos, forward, up = gl_camera_from_pose(T_world_cam)
        left, right, bottom, top = frustum_from_intrinsics(intr, self.near_m)
        for gl_cam in (self._scene.camera[0], self._scene.camera[1]):  # mono rendering averages both
            gl_cam.pos[:] = pos
            gl_cam.forward[:] = forward
            gl_cam.up[:] = up
            gl_cam.orthographic = 0
            gl_cam.frustum_near = self.near_m
            gl_cam.frustum_far = self.far_m
            gl_cam.frustum_bottom = bottom
            gl_cam.frustum_top = top
            gl_cam.frustum_center = 0.5 * (left + right)
            gl_cam.frustum_width = 0.5 * (right - left)
        self._scene.enabletransform = 0
        return mujoco.MjrRect(0, 0, intr.width, intr.height)

    def _linear_depth(self, raw: np.ndarray) -> np.ndarray:
        """Reversed-Z window depth (1 at near, 0 at far) -> z in metres; 0 where nothing was drawn.

        Window depth is ``n (f / z - 1) / (f - n)``; its inverse in float32 keeps a relative error
        near 1e-7 (0.1 um at 1 m), as good as the float32 depth buffer itself. ``raw`` is overwritten.
        """
        n, f = np.float32(self.near_m), np.float32(self.far_m)
        empty = raw <= 0.0  # cleared to the far plane: no surface
        np.multiply(raw, f - n, out=raw)
        raw += n
        np.divide(f * n, raw, out=raw)
        raw[empty] = 0.0
        return raw

    # -- rendering ------------------------------------------------------------------------------------
    def render_view(
        self, T_world_cam: np.ndarray, intrinsics: Intrinsics, *, rgb: bool = True, depth: bool = True
    ) -> RenderOutput:
        """Render the current scene: colour (RGB order) and/or metric depth from one render pass."""
        rgb_out, depth_out = self._render(T_world_cam, intrinsics, rgb, depth)
        return RenderOutput(rgb=rgb_out, depth_m=depth_out)

    def render_segmentation(
        self, T_world_cam: np.ndarray, intrinsics: Intrinsics, *, region: Region | None = None
    ) -> np.ndarray:
        """Geom id seen by each pixel (int32, ``NO_GEOM`` where none) for the current scene.

        ``region`` ``(u0, v0, u1, v1)``: render only the pixels ``[v0:v1, u0:u1]`` (the others get
        ``NO_GEOM``); the ids there are the same as in a full render (same projection, the viewport is
        shifted by whole pixels) and the cost follows the region's area.
        """
        return self._segmentation(T_world_cam, intrinsics, depth=False, region=region)[0]

    def render_segmentation_and_depth(
        self, T_world_cam: np.ndarray, intrinsics: Intrinsics, *, depth: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Geom ids and metric depth from one flat (unlit, untextured, so cheaper) id-colour pass."""
        return self._segmentation(T_world_cam, intrinsics, depth=depth, region=None)

    def _segmentation(
        self, T_world_cam: np.ndarray, intrinsics: Intrinsics, *, depth: bool, region: Region | None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        flags = self._scene.flags
        saved = (flags[mujoco.mjtRndFlag.mjRND_SEGMENT], flags[mujoco.mjtRndFlag.mjRND_IDCOLOR])
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 1
        flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 1
        try:
            colour, depth_m = self._render(T_world_cam, intrinsics, True, depth, region)
        finally:
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT], flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = saved
        assert colour is not None
        code = (
            colour[..., 0].astype(np.int32)
            | (colour[..., 1].astype(np.int32) << 8)
            | (colour[..., 2].astype(np.int32) << 16)
        )
        # Colour code k is scene geom k-1; map scene geoms to model geom ids (other objects -> NO_GEOM).
        ngeom = self._scene.ngeom
        lookup = np.full(ngeom + 1, NO_GEOM, np.int32)
        geom_type = int(mujoco.mjtObj.mjOBJ_GEOM)
        for k in range(ngeom):
            g = self._scene.geoms[k]
            if g.objtype == geom_type and 0 <= g.segid < ngeom:
                lookup[g.segid + 1] = g.objid
        code[code > ngeom] = 0
        ids = lookup[code]
        if region is None:
            return ids, depth_m
        u0, v0, u1, v1 = region
        full = np.full((intrinsics.height, intrinsics.width), NO_GEOM, np.int32)
        full[v0:v1, u0:u1] = ids
        return full, None

    def _render(
        self,
        T_world_cam: np.ndarray,
        intrinsics: Intrinsics,
        rgb: bool,
        depth: bool,
        region: Region | None = None,
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        if self._con is None:
            raise TwinError("renderer used after close()")
        self._gl.make_current()
        rect = self._set_camera(T_world_cam, intrinsics)
        h, w = intrinsics.height, intrinsics.width
        if region is not None:  # shift the viewport so that the region's corner lands on pixel (0, 0)
            u0, v0, u1, v1 = region
            if not (0 <= u0 < u1 <= w and 0 <= v0 < v1 <= h):
                raise TwinError(f"render region {region} is not inside the {w}x{h} image")
            rect = mujoco.MjrRect(-u0, v1 - h, w, h)  # GL rows run bottom-up
            h, w = v1 - v0, u1 - u0
        mujoco.mjr_render(rect, self._scene, self._con)
        rgb_buf, depth_buf = self._read_buffers(h, w)
        mujoco.mjr_readPixels(
            rgb_buf if rgb else None, depth_buf if depth else None, mujoco.MjrRect(0, 0, w, h), self._con
        )
        # OpenGL rows run bottom-up; images run top-down (cv2.flip makes a new top-down array).
        rgb_out = cv2.flip(rgb_buf, 0) if rgb else None
        depth_out = self._linear_depth(cv2.flip(depth_buf, 0)) if depth else None
        return rgb_out, depth_out

    def render(
        self,
        data: mujoco.MjData,
        T_world_cam: np.ndarray,
        intrinsics: Intrinsics,
        *,
        rgb: bool = True,
        depth: bool = True,
    ) -> RenderOutput:
        """Convenience: :meth:`update_scene` then :meth:`render_view`."""
        self.update_scene(data)
        return self.render_view(T_world_cam, intrinsics, rgb=rgb, depth=depth)

    def _read_buffers(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """Read-back buffers for an ``h x w`` view, kept between renders (outputs are copies)."""
        buffers = self._buffers.get((h, w))
        if buffers is None:
            buffers = self._buffers[(h, w)] = (np.empty((h, w, 3), np.uint8), np.empty((h, w), np.float32))
        return buffers

    # -- lifetime -------------------------------------------------------------------------------------
    def close(self) -> None:
        """Free the GL resources (idempotent)."""
        if self._con is not None:
            if self._gl is not None:
                self._gl.make_current()
            self._con.free()
            self._con = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at interpreter shutdown the GL libraries may be gone
            self.close()
