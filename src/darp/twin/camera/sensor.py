"""The twin's D435-class camera: renders a MuJoCo scene into a RealSense-like frame set plus ground truth.

``TwinCamera.capture(data, T_world_cam, timestamp_s)`` renders, for the depth (left IR) frame pose
``T_world_cam`` (OpenCV axes):

- colour from the colour imager's pose ``T_world_cam @ T_depth_color`` with the colour intrinsics;
- exact depth (and the view's light) from the left imager, geom segmentation from the same view
  (with segmentation off, only the image rectangle of the dropout geoms' bounding boxes, if any);
- exact depth and light from the right imager (``baseline_m`` along +x), for occlusion and IR2;

then applies the depth model (or SGBM on the IR pair) and the IR model. One render pass per view;
``SceneRenderer.update_scene`` runs once per capture. Pass one ``SceneRenderer`` to several cameras of
the same model to share the GL context. ``TwinCamera.stage_cpu_s`` accumulates the CPU time of each
stage (``CAPTURE_STAGES``).

Frame set keys (what the recorder writes, in librealsense formats):
``color`` (H, W, 3) uint8 BGR8; ``depth`` (H, W) uint16 Z16 in ``spec.depth_unit_m``; ``ir1``,
``ir2`` (H, W) uint8 Y8; ``timestamp_s``; ``depth_m`` float32 metres before the depth unit (0 =
invalid); ``truth``: ``depth_m`` exact z of the left imager (0 = no surface), ``geom_id`` int32 per
depth pixel (-1 = none; None when segmentation is off), ``T_world_depth``, ``T_world_color``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Self

import cv2
import numpy as np

from darp.errors import ConfigError, TwinError
from darp.kinematics.transforms import compose
from darp.twin.camera.depth_model import DepthModel, DepthNoiseSettings, depth_to_z16
from darp.twin.camera.imu import ImuSettings, ImuSimulator, PoseFunction
from darp.twin.camera.ir import IrModel, IrSettings
from darp.twin.camera.noise import NoiseBank
from darp.twin.camera.render import RenderOutput, SceneRenderer, geom_image_region, mujoco
from darp.twin.camera.spec import CameraSpec
from darp.twin.camera.stereo import StereoMatcher, StereoSettings

PROFILES = ("ideal", "realistic")
FIELD_GRID = (3, 4)
"""Rows x columns of the per-frame disparity error field's nodes: it varies over about a third of the image."""
STATIC_FIELD_GRID = (6, 8)
"""Rows x columns of the sensor-fixed disparity error field's nodes: it varies over about an eighth of the image."""
FIELD_STREAM = 0xF1E1D
"""Third seed word of the per-frame disparity field's generator (``(seed, frame, FIELD_STREAM)``)."""
CAPTURE_STAGES = ("render", "ir", "depth_noise", "colour", "z16")
DEPTH_MODES = ("model", "sgbm")


def sensor_field_nodes(rng: np.random.Generator, std_px: float) -> tuple[tuple[float, ...], ...]:
    """One unit's sensor-fixed disparity field: :data:`STATIC_FIELD_GRID` node values, scaled so that their
    RMS is exactly ``std_px`` (a unit's non-flatness is one draw of the stated size)."""
    nodes = rng.normal(0.0, 1.0, STATIC_FIELD_GRID)
    nodes *= std_px / max(float(np.sqrt(np.mean(nodes * nodes))), 1e-12)
    return tuple(tuple(float(v) for v in row) for row in nodes)


@dataclass(frozen=True)
class UnitErrors:
    """One camera unit's depth errors and its colour images' photographic errors (drawn by the rig).

    Valid depth becomes ``z * (1 + scale + drift(t)) + offset_m + bias_per_m * z^2`` with ``drift(t) =
    thermal_drift * (1 - exp(-(t - session_start_s) / thermal_tau_s))`` for the frame's timestamp ``t``;
    with ``field_disparity_px`` > 0 each frame also gets its own smooth disparity error field ``e(u, v)``
    (node values ``N(0, field_disparity_px)`` on a coarse :data:`FIELD_GRID` grid, bicubically
    interpolated), applied in the disparity domain: ``z -> z / (1 + z e / focal_baseline_px_m)``, so its
    depth effect grows as ``z^2``, as a stereo matcher's error does; ``static_field_px`` (nodes of a finer
    :data:`STATIC_FIELD_GRID`, drawn once per unit) is a disparity error fixed to the sensor, added to ``e``
    in every frame; the colour image is blurred
    (``blur_sigma_px``), lit unevenly (a gradient in a random direction per frame plus vignetting, each up
    to ``shading`` of the brightness) and gets ``noise_dn`` more noise.
    """

    depth_scale: float = 0.0
    depth_offset_m: float = 0.0
    depth_bias_per_m: float = 0.0
    thermal_drift: float = 0.0
    thermal_tau_s: float = 600.0
    session_start_s: float = 0.0
    blur_sigma_px: float = 0.0
    shading: float = 0.0
    noise_dn: float = 0.0
    field_disparity_px: float = 0.0
    focal_baseline_px_m: float = 0.0  # the unit's fx * baseline (px m): disparity = focal_baseline / z
    static_field_px: tuple[tuple[float, ...], ...] = ()  # sensor-fixed field nodes (px), () = none

    def sensor_field(self, shape: tuple[int, int]) -> np.ndarray:
        """The unit's sensor-fixed disparity error field (px, float64, ``shape``; bicubic between the nodes)."""
        nodes = np.asarray(self.static_field_px, dtype=np.float32)
        h, w = shape
        return cv2.resize(nodes, (w, h), interpolation=cv2.INTER_CUBIC).astype(np.float64)

    def disparity_field(self, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
        """One frame's smooth disparity error field (px, float64, ``shape``) drawn from ``rng``."""
        nodes = rng.normal(0.0, self.field_disparity_px, FIELD_GRID).astype(np.float32)
        h, w = shape
        return cv2.resize(nodes, (w, h), interpolation=cv2.INTER_CUBIC).astype(np.float64)

    def depth(self, depth_m: np.ndarray, timestamp_s: float | None,
              rng: np.random.Generator | None = None) -> np.ndarray:
        """The measured depth (float32 metres, 0 stays invalid) for the model's output ``depth_m``.

        ``rng`` (the frame's generator) draws the per-frame disparity field; without it, or with
        ``field_disparity_px`` = 0, nothing is drawn.
        """
        t = 0.0 if timestamp_s is None else max(0.0, timestamp_s - self.session_start_s)
        scale = 1.0 + self.depth_scale + self.thermal_drift * (1.0 - np.exp(-t / self.thermal_tau_s))
        field = self.field_disparity_px > 0 and self.focal_baseline_px_m > 0 and rng is not None
        static = len(self.static_field_px) > 0 and self.focal_baseline_px_m > 0
        if (scale == 1.0 and self.depth_offset_m == 0.0 and self.depth_bias_per_m == 0.0 and not field
                and not static):
            return depth_m
        z = np.asarray(depth_m, dtype=np.float64)
        if field or static:
            e = self.disparity_field(z.shape, rng) if field and rng is not None else np.zeros(z.shape)
            if static:
                e = e + self.sensor_field(z.shape)
            z = z / np.maximum(1.0 + z * e / self.focal_baseline_px_m, 0.5)
        out = z * scale + self.depth_offset_m + self.depth_bias_per_m * z * z
        return np.where(z > 0, np.maximum(out, 0.0), 0.0).astype(np.float32)

    def photograph(self, bgr: np.ndarray, rng: np.random.Generator, motion_px: np.ndarray | None) -> np.ndarray:
        """The colour image with motion blur, optical blur, uneven light and sensor noise."""
        img = bgr
        if motion_px is not None and float(np.hypot(*motion_px)) >= 0.5:
            length = int(np.ceil(np.hypot(*motion_px)))
            size = 2 * length + 1
            kernel = np.zeros((size, size), np.float32)
            for u in np.linspace(-0.5, 0.5, 4 * length + 1):
                kernel[int(round(length + u * motion_px[1])), int(round(length + u * motion_px[0]))] += 1.0
            img = cv2.filter2D(img, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REPLICATE)
        if self.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma_px)
        if self.shading > 0 or self.noise_dn > 0:
            h, w = img.shape[:2]
            out = img.astype(np.float32)
            if self.shading > 0:
                angle = rng.uniform(0.0, 2 * np.pi)
                y, x = np.mgrid[0:h, 0:w].astype(np.float32)
                u = ((x - 0.5 * w) * np.cos(angle) + (y - 0.5 * h) * np.sin(angle)) / (0.5 * max(w, h))
                r2 = ((x - 0.5 * w) ** 2 + (y - 0.5 * h) ** 2) / (0.25 * (w * w + h * h))
                gain = 1.0 + 0.5 * self.shading * rng.uniform(0.5, 1.0) * u - 0.5 * self.shading * r2
                out *= gain[:, :, None]
            if self.noise_dn > 0:
                out += rng.normal(0.0, self.noise_dn, out.shape).astype(np.float32)
            img = np.clip(np.rint(out), 0, 255).astype(np.uint8)
        return img


@dataclass(frozen=True)
class TwinCameraSettings:
    """What the camera simulates: depth, IR and IMU error models, depth mode, optional outputs.

    Build it with :meth:`from_profile`; ``profile`` is the name of the profile it started from.
    """

    profile: str = "realistic"
    depth: DepthNoiseSettings = field(default_factory=DepthNoiseSettings.realistic)
    ir: IrSettings = field(default_factory=IrSettings)
    depth_mode: str = "model"  # "model": parametric D4 model; "sgbm": OpenCV SGBM on the IR pair
    stereo: StereoSettings = field(default_factory=StereoSettings)
    colour_noise_dn: float = 1.0  # Gaussian colour sensor noise, 8-bit digital numbers
    render_ir: bool = True  # False skips both IR images (and the right view unless occlusion needs it)
    segmentation: bool = True  # truth geom ids; when off, dropout geoms get ids only around their image
    imu: ImuSettings = field(default_factory=ImuSettings)
    errors: UnitErrors | None = None  # per-unit depth errors and photographic errors (None: none)

    def __post_init__(self) -> None:
        if self.profile not in PROFILES:
            raise ConfigError(f"unknown camera profile {self.profile!r} (profiles: {', '.join(PROFILES)})")
        if self.depth_mode not in DEPTH_MODES:
            raise ConfigError(f"unknown depth mode {self.depth_mode!r} (modes: {', '.join(DEPTH_MODES)})")
        if self.depth_mode == "sgbm" and not self.render_ir:
            raise ConfigError("depth mode 'sgbm' needs the IR images (render_ir=True)")
        if self.colour_noise_dn < 0:
            raise ConfigError(f"colour_noise_dn must be >= 0, got {self.colour_noise_dn}")

    @classmethod
    def from_profile(cls, profile: str, **overrides: Any) -> TwinCameraSettings:
        """The named profile: "ideal" (exact depth, noiseless images) or "realistic" (D4-class errors)."""
        if profile == "ideal":
            base: dict[str, Any] = {
                "profile": "ideal",
                "depth": DepthNoiseSettings.ideal(),
                "ir": IrSettings.ideal(),
                "colour_noise_dn": 0.0,
                "imu": ImuSettings.ideal(),
            }
        elif profile == "realistic":
            base = {"profile": "realistic"}
        else:
            raise ConfigError(f"unknown camera profile {profile!r} (profiles: {', '.join(PROFILES)})")
        base.update(overrides)
        return cls(**base)


GeomDropouts = Mapping[int, float] | Mapping[str, float] | Mapping[int | str, float]
"""Depth dropout probability per geom, by geom id or name."""


def dark_geom_dropouts(
    model: mujoco.MjModel,
    *,
    max_luminance: float = 0.08,
    min_reflectance: float = 0.5,
    probability: float = 0.7,
) -> dict[int, float]:
    """Dropout probabilities for dark, transparent (alpha < 0.5) or mirror-like geoms.

    Colour comes from the geom's material if it has one, else from the geom's rgba; "mirror-like" is a
    material reflectance of at least ``min_reflectance`` (MuJoCo's reflection strength).
    """
    out: dict[int, float] = {}
    for gid in range(model.ngeom):
        mat = model.geom_matid[gid]
        rgba = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[gid]
        lum = 0.299 * rgba[0] + 0.587 * rgba[1] + 0.114 * rgba[2]
        glossy = mat >= 0 and model.mat_reflectance[mat] >= min_reflectance
        if lum <= max_luminance or rgba[3] < 0.5 or glossy:
            out[gid] = probability
    return out


class TwinCamera:
    """One simulated D435-class camera bound to a MuJoCo model."""

    def __init__(
        self,
        model: mujoco.MjModel,
        spec: CameraSpec,
        settings: TwinCameraSettings | None = None,
        *,
        seed: int = 0,
        renderer: SceneRenderer | None = None,
        dropout_geoms: GeomDropouts | None = None,
    ) -> None:
        self.model = model
        self.spec = spec
        self.settings = settings if settings is not None else TwinCameraSettings()
        self.seed = int(seed)
        self._dropout_lookup = self._build_dropout_lookup(dropout_geoms or {})  # validate before GL
        self._dropout_geom_ids = (
            np.flatnonzero(self._dropout_lookup[1:] > 0)
            if self._dropout_lookup is not None
            else np.zeros(0, int)
        )
        need_w = max(spec.depth.width, spec.color.width)
        need_h = max(spec.depth.height, spec.color.height)
        if renderer is None:
            renderer = SceneRenderer(model, need_w, need_h)
            self._owns_renderer = True
        else:
            if renderer.model is not model:
                raise TwinError("the shared SceneRenderer was built for another MuJoCo model")
            self._owns_renderer = False
        self.renderer = renderer
        self.depth_model = DepthModel(
            self.settings.depth, spec.depth.fx, spec.baseline_m, bank_seed=[self.seed, 1]
        )
        self.ir_model = IrModel(
            self.settings.ir, spec.depth, spec.baseline_m, spec.projector_x_m, seed=[self.seed, 2]
        )
        c = spec.color
        self._colour_noise = (
            NoiseBank(
                (c.height, c.width, 3),
                np.random.default_rng([self.seed, 3]),
                scale=self.settings.colour_noise_dn,
                dtype=np.int16,
            )
            if self.settings.colour_noise_dn > 0
            else None
        )
        self._stereo = (
            StereoMatcher(self.settings.stereo, spec.depth.fx, spec.baseline_m)
            if self.settings.depth_mode == "sgbm"
            else None
        )
        self.imu = ImuSimulator(self.settings.imu, seed=np.random.default_rng([self.seed, 4]))
        self.T_depth_color = spec.T_depth_stream("color")
        self.T_depth_ir2 = spec.T_depth_stream("ir2")
        self.frame_index = 0
        # CPU seconds (this process, all threads: llvmpipe's render threads included) per capture stage.
        self.stage_cpu_s = dict.fromkeys(CAPTURE_STAGES, 0.0)

    def _build_dropout_lookup(self, dropout_geoms: GeomDropouts) -> np.ndarray | None:
        """Per-geom dropout probability indexed by geom id + 1 (index 0: no geom)."""
        if not dropout_geoms:
            return None
        lookup = np.zeros(self.model.ngeom + 1, np.float32)
        for key, prob in dropout_geoms.items():
            gid = (
                int(key)
                if isinstance(key, int | np.integer)
                else mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, key)
            )
            if not 0 <= gid < self.model.ngeom:
                raise ConfigError(f"dropout geom {key!r} is not a geom of the model")
            if not 0.0 <= prob <= 1.0:
                raise ConfigError(f"dropout probability for geom {key!r} must be in [0, 1], got {prob}")
            lookup[gid + 1] = prob
        return lookup

    def capture(
        self, data: mujoco.MjData, T_world_cam: np.ndarray, timestamp_s: float | None = None,
        motion_px: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """Render one frame set for the depth-frame pose ``T_world_cam`` (see the module docstring for keys).

        ``motion_px``: image motion (dx, dy) in colour pixels during the exposure (blurs colour when the
        settings carry :class:`UnitErrors`).

        Deterministic for a given seed and capture order: frame k draws its noise from ``(seed, k)``.
        """
        s = self.settings
        T_world_depth = np.asarray(T_world_cam, dtype=float)
        if T_world_depth.shape != (4, 4) or not np.all(np.isfinite(T_world_depth)):
            raise TwinError(f"T_world_cam must be a finite 4x4 matrix, got shape {T_world_depth.shape}")
        T_world_color = compose(T_world_depth, self.T_depth_color)  # no BLAS: images independent of its kernel
        T_world_ir2 = compose(T_world_depth, self.T_depth_ir2)
        rng = np.random.default_rng([self.seed, self.frame_index])
        self.frame_index += 1

        cpu = time.process_time
        stage = self.stage_cpu_s
        t0 = cpu()
        r = self.renderer
        r.update_scene(data)
        colour_rgb = r.render_view(T_world_color, self.spec.color, depth=False).rgb
        need_seg = s.segmentation or self._dropout_lookup is not None
        geom_id = None  # full-image ids (segmentation on)
        dropout_ids = None  # ids around the dropout geoms only (segmentation off)
        if s.render_ir:  # the IR image needs the lit view; ids need their own flat pass
            left = r.render_view(T_world_depth, self.spec.depth)
            if s.segmentation:
                geom_id = r.render_segmentation(T_world_depth, self.spec.depth)
            elif need_seg:  # only where a dropout geom can be: its bounding box's image
                region = geom_image_region(
                    self.model, data, self._dropout_geom_ids, T_world_depth, self.spec.depth
                )
                if region is not None:
                    dropout_ids = r.render_segmentation(T_world_depth, self.spec.depth, region=region)
        elif need_seg:  # ids and depth from one flat pass
            ids, left_depth = r.render_segmentation_and_depth(T_world_depth, self.spec.depth)
            left = RenderOutput(rgb=None, depth_m=left_depth)
            geom_id, dropout_ids = (ids, None) if s.segmentation else (None, ids)
        else:
            left = r.render_view(T_world_depth, self.spec.depth, rgb=False)
        need_right = s.render_ir or (s.depth.occlusion and s.depth_mode == "model")
        right = r.render_view(T_world_ir2, self.spec.depth, rgb=s.render_ir) if need_right else None
        assert colour_rgb is not None and left.depth_m is not None
        t1 = cpu()
        stage["render"] += t1 - t0

        ir1 = ir2 = None
        if s.render_ir:
            assert (
                left.rgb is not None
                and right is not None
                and right.rgb is not None
                and right.depth_m is not None
            )
            ir1, ir2 = self.ir_model.pair(left.rgb, left.depth_m, right.rgb, right.depth_m, rng)
        t2 = cpu()
        stage["ir"] += t2 - t1

        if s.depth_mode == "sgbm":
            assert ir1 is not None and ir2 is not None and self._stereo is not None
            depth_m = self._stereo.depth(ir1, ir2)
        else:
            dropout = None
            seen_ids = geom_id if geom_id is not None else dropout_ids
            if self._dropout_lookup is not None and seen_ids is not None:
                dropout = self._dropout_lookup[seen_ids + 1]
            depth_m = self.depth_model.apply(
                left.depth_m,
                rng,
                depth_right_m=right.depth_m if right is not None else None,
                dropout_prob=dropout,
            )
        if s.errors is not None:
            # the field has its own stream: colour noise (and so board detection) stays as without it
            field_rng = (np.random.default_rng([self.seed, self.frame_index - 1, FIELD_STREAM])
                         if s.errors.field_disparity_px > 0 else None)
            depth_m = s.errors.depth(depth_m, timestamp_s, field_rng)
        t3 = cpu()
        stage["depth_noise"] += t3 - t2

        colour_bgr = cv2.cvtColor(colour_rgb, cv2.COLOR_RGB2BGR)
        if self._colour_noise is not None:  # integer noise, saturating add
            colour_bgr = cv2.add(colour_bgr, self._colour_noise.draw(rng), dtype=cv2.CV_8U)
        if s.errors is not None:
            colour_bgr = s.errors.photograph(colour_bgr, rng, motion_px)
        t4 = cpu()
        stage["colour"] += t4 - t3
        depth_z16 = depth_to_z16(depth_m, self.spec.depth_unit_m)
        stage["z16"] += cpu() - t4

        return {
            "color": colour_bgr,
            "depth": depth_z16,
            "ir1": ir1,
            "ir2": ir2,
            "timestamp_s": timestamp_s,
            "depth_m": depth_m,
            "truth": {
                "depth_m": left.depth_m,
                "geom_id": geom_id,
                "T_world_depth": T_world_depth,
                "T_world_color": T_world_color,
            },
        }

    def imu_samples(self, t_start_s: float, t_stop_s: float, pose: PoseFunction) -> dict[str, np.ndarray]:
        """Accelerometer and gyroscope samples at the spec's rates along ``pose`` (see ``darp.twin.camera.imu``)."""
        return self.imu.sample(
            t_start_s, t_stop_s, pose, accel_hz=self.spec.accel_hz, gyro_hz=self.spec.gyro_hz
        )

    def close(self) -> None:
        """Free the renderer if this camera created it."""
        if self._owns_renderer:
            self.renderer.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
