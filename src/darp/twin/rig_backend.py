"""``TwinRig``: the digital twin as a :class:`RigBackend` (world, two arms, two cameras, clock, joint log).

Everything runs on one :class:`~darp.twin.clock.SimClock`. Scheduled processes, in insertion order
for equal times: the two cameras' frame ticks (30 fps, staggered), the joint logger once started
(about 33 Hz with Gaussian interval jitter; each row's time is the host-clock time of its sample) and
the collision monitor (while any arm moves, the moving arms' contacts with the table, the object and
the other arm are checked at ``collision_check_hz`` and recorded in :attr:`TwinRig.contact_events`).

A contact during motion stops both arms at once (decelerating at the acceleration limit, as the Z1's
controller does) and latches a :class:`~darp.backend.RigFault` that :meth:`TwinRig.fault` reports; the
survey then refuses further planned moves (``stop_on_contact=False`` keeps the old record-only monitor).

The true rig (joint-zero offsets, camera mounts, second base) is drawn from the nominal rig and the
settings' seed (:func:`darp.twin.truth.draw_true_rig`); arms report SDK angles, the world and the
cameras use the true ones.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from darp.backend import RigBackend, RigFault
from darp.errors import TwinError
from darp.formats.arm_poses import ArmPoseWriter
from darp.kinematics.rig import Rig, load_rig
from darp.twin.arm_errors import LinkDeflection
from darp.twin.arm_sim import SimArm
from darp.twin.camera.backend import TwinCameraBackend
from darp.twin.clock import NS_PER_S, SimClock, s_to_ns
from darp.twin.placement import validate_placement
from darp.twin.settings import TwinSettings
from darp.twin.truth import TrueRig, draw_true_rig
from darp.twin.world import Contact, TwinWorld

if TYPE_CHECKING:  # the renderer and the camera import MuJoCo's GL backend: only when the cameras are built
    from darp.twin.camera.render import SceneRenderer
    from darp.twin.camera.sensor import TwinCamera
    from darp.twin.camera.spec import CameraSpec

MAX_CONTACT_EVENTS = 10_000


@dataclass(frozen=True)
class ContactEvent:
    """A contact seen by the collision monitor at host time ``time_s``."""

    time_s: float
    contact: Contact


class TwinRig(RigBackend):
    """The simulated rig. Use as a context manager; the cameras render only while recording."""

    clock: SimClock
    arms: dict[str, SimArm]
    cameras: dict[str, TwinCameraBackend]

    def __init__(self, settings: TwinSettings | None = None, *, rig: Rig | None = None,
                 obj: Any | None = None, placement: Any | None = None, board: Any | None = None,
                 T_world_board: np.ndarray | None = None,
                 q_initial_rad: dict[str, np.ndarray] | None = None, camera_workers: bool = False,
                 check_placement: bool = True) -> None:
        """``obj``: a :class:`darp.twin.objects.model.TwinObject` placed by ``placement`` (an ``ObjectPlacement``),
        refused (:class:`TwinError`) before anything is built when it is not finite, not on the table, touches
        a parked arm or lies outside the workspace (:func:`darp.twin.placement.validate_placement`; skipped
        with ``check_placement=False``, for tests of what the survey does with such a placement);
        ``board``: a :class:`darp.formats.calibration.CharucoBoardSpec` lying on the table at ``T_world_board``;
        ``q_initial_rad``: starting SDK angles per arm (default: the rig's park configurations);
        ``camera_workers``: render and record each camera in its own subprocess (same files, faster on
        several cores; a few seconds to start)."""
        self.settings = settings if settings is not None else TwinSettings.from_profile("realistic")
        self.rig = rig if rig is not None else load_rig()
        self.true_rig: TrueRig = draw_true_rig(self.rig, self.settings)
        self.obj = obj
        self.placement = placement
        s = self.settings
        self.clock = SimClock(s.timing.start_time_s)
        T_world_object = None
        if obj is not None:
            if placement is None:
                raise TwinError("an object needs a placement")
            if check_placement:
                validate_placement(self.rig, obj.radius_m, obj.height_m, placement)
            T_world_object = placement.T_world_object
        self.world = TwinWorld(self.rig, self.true_rig.arms, parts=obj.parts if obj is not None else (),
                               T_world_object=T_world_object, board=board, T_world_board=T_world_board,
                               seed=s.seed, lighting=s.lighting)
        self.arms = {}
        for arm_id, true_arm in self.true_rig.arms.items():
            q0 = (q_initial_rad or {}).get(arm_id, self.rig.arms[arm_id].park_q_rad)
            self.arms[arm_id] = SimArm(
                arm_id, self.clock, np.asarray(q0, dtype=float),
                joint_offsets_rad=true_arm.joint_offsets_rad,
                encoder_noise_std_rad=np.deg2rad(s.joints.encoder_noise_std_deg),
                rng=s.rng(f"encoder:{arm_id}"),
                max_speed_rad_s=s.motion.max_speed_rad_s, max_accel_rad_s2=s.motion.max_accel_rad_s2,
                settle_s=s.motion.settle_s,
                deflection=LinkDeflection(s.arm_errors, s.rng(f"deflection:{arm_id}")))
        self._world_time_ns: int | None = None
        self._renderer: SceneRenderer | None = None
        self._log_writer: ArmPoseWriter | None = None
        self._log_handle: int | None = None
        self.cameras = {}
        self._build_cameras(camera_workers)
        self._log_rng = s.rng("joint_log")
        self.contact_events: list[ContactEvent] = []
        self.contacts_dropped = 0
        self.stop_on_contact = True
        self._fault: RigFault | None = None
        self._braking: dict[str, object] = {}  # arm id -> the stop move it is executing
        self._monitor_period_ns = max(1, round(NS_PER_S / s.motion.collision_check_hz))
        self.clock.add_process("collision-monitor", self._monitor_tick, first_due_ns=0)

    # -- cameras ----------------------------------------------------------------------------------
    def _build_cameras(self, workers: bool) -> None:
        from darp.twin.camera.imu import ImuSettings, ImuSimulator
        from darp.twin.camera.render import SceneRenderer
        from darp.twin.camera.sensor import TwinCamera, TwinCameraSettings
        from darp.twin.camera.spec import UnitCalibration, draw_unit, make_camera_spec
        from darp.twin.camera.worker import CameraWorker, available_cores

        c, s = self.settings.camera, self.settings
        size = (c.width, c.height)
        self._renderer = SceneRenderer(self.world.model, c.width, c.height)
        # Segmentation is rendered only when an object part can drop out (the camera forces it then).
        base_cam_settings = TwinCameraSettings.from_profile(c.depth_noise, segmentation=False)
        dropouts = self._dropout_map()
        model = self.world.model
        try:
            for index, (arm_id, true_arm) in enumerate(self.true_rig.arms.items()):
                unit = draw_unit(s.rng(f"unit:{true_arm.serial}")) if c.unit_variation else UnitCalibration()
                spec = make_camera_spec(unit, serial=true_arm.serial, depth_resolution=size, colour_resolution=size,
                                        fps=c.fps, colour_fps=c.fps, accel_hz=c.accel_hz, gyro_hz=c.gyro_hz)
                seed = int(s.rng(f"camera:{true_arm.serial}").integers(2**31))
                cam_settings, factory = camera_unit_errors(s, true_arm.serial, spec, base_cam_settings)
                threads = max(1, available_cores() // len(self.true_rig.arms))
                worker = CameraWorker(model, spec, cam_settings, seed, dropouts, threads=threads) if workers else None
                record_cam = None if workers else TwinCamera(model, spec, cam_settings, seed=seed,
                                                             renderer=self._renderer, dropout_geoms=dropouts)

                def live(spec: CameraSpec = spec, seed: int = seed, cam_settings: Any = cam_settings) -> TwinCamera:
                    return TwinCamera(model, spec, cam_settings, seed=seed + 1, renderer=self._renderer,
                                      dropout_geoms=dropouts)

                imu = None
                if c.imu:
                    imu_settings = ImuSettings() if c.imu_noise == "realistic" else ImuSettings.ideal()
                    imu = ImuSimulator(imu_settings, s.rng(f"imu:{true_arm.serial}"))
                self.cameras[arm_id] = TwinCameraBackend(
                    arm_id, spec, self.clock, self, camera=record_cam, live_camera=live, imu=imu,
                    phase_ns=s_to_ns(index * s.timing.camera_stagger_ms / 1e3),
                    clock_offset_ms=s.timing.camera_clock_offset_ms, compression=c.compression, worker=worker,
                    factory_spec=factory, latency_ms=s.sync.latency_ms, jitter_ms=s.sync.jitter_ms,
                    exposure_ms=s.sync.exposure_ms, jitter_seed=seed + 2)
        except BaseException:
            self.close()
            raise

    def _dropout_map(self) -> dict[int, float]:
        """Depth dropout probability per object geom from its part's material flags."""
        c, g = self.settings.camera, self.world.geoms
        out: dict[int, float] = {}
        for gid in self.world.object_geom_ids:
            prob = max(c.dropout_dark if g.dark[gid] else 0.0, c.dropout_specular if g.specular[gid] else 0.0,
                       c.dropout_transparent if g.transparent[gid] else 0.0)
            if prob > 0:
                out[int(gid)] = prob
        return out

    # -- CameraHost -------------------------------------------------------------------------------
    def prepare_world(self, t_ns: int) -> Any:
        """Set every arm to its true joint angles at ``t_ns`` and update the scene; returns MjData."""
        if self._world_time_ns != t_ns:
            for arm_id, arm in self.arms.items():
                self.world.set_arm_q(arm_id, arm.true_q(t_ns))
            self.world.forward()
            self._world_time_ns = t_ns
        return self.world.data

    def true_camera_poses(self, arm_id: str, t_ns: np.ndarray) -> np.ndarray:
        q = np.atleast_2d(self.arms[arm_id].true_state(np.asarray(t_ns, dtype=np.int64))[0])
        return self.true_rig.T_world_cam(arm_id, q)

    def true_q(self, arm_id: str, t_ns: int) -> np.ndarray:
        return self.arms[arm_id].true_q(int(t_ns))

    # -- joint log --------------------------------------------------------------------------------
    def start_joint_log(self, path: Path) -> None:
        """Log both arms to ``path`` from now on (first row now), about ``joint_log_rate_hz``."""
        if self._log_writer is not None:
            raise TwinError("the joint log is already running")
        self._log_writer = ArmPoseWriter(path, known_arms=tuple(self.arms))
        self._log_handle = self.clock.add_process("joint-log", self._log_tick)

    def _log_tick(self, now_ns: int) -> int | None:
        if self._log_writer is None:
            return None
        for arm_id, arm in self.arms.items():
            state = arm.read_state()
            self._log_writer.write(state.time_s, arm_id, state.q_rad)
        t = self.settings.timing
        period_s = 1.0 / t.joint_log_rate_hz
        jitter_s = t.joint_log_jitter_ms / 1e3
        interval = period_s
        if jitter_s > 0:
            interval = float(np.clip(period_s + self._log_rng.normal(0.0, jitter_s), 0.6 * period_s, 1.4 * period_s))
        return now_ns + max(1, s_to_ns(interval))

    def stop_joint_log(self) -> None:
        """Stop logging and close ``arm_poses.csv``."""
        if self._log_writer is None:
            return
        writer, self._log_writer = self._log_writer, None
        if self._log_handle is not None:
            self.clock.remove(self._log_handle)
            self._log_handle = None
        writer.close()

    # -- collisions -------------------------------------------------------------------------------
    def contacts(self) -> list[Contact]:
        """Contacts at the current instant (any arm against the table, the object or the other arm)."""
        self.prepare_world(self.clock.elapsed_ns)
        return self.world.contacts()

    def _monitor_tick(self, now_ns: int) -> int:
        moving = {arm_id for arm_id, arm in self.arms.items() if arm.is_moving()}
        if moving:
            found = [c for c in self.contacts() if c.arm_id in moving or c.other in moving]
            for contact in found:
                if len(self.contact_events) < MAX_CONTACT_EVENTS:
                    self.contact_events.append(ContactEvent(self.clock.host_time_s(now_ns), contact))
                else:
                    self.contacts_dropped += 1
            if found and self.stop_on_contact:
                self._on_contact(found, self.clock.host_time_s(now_ns))
        return now_ns + self._monitor_period_ns

    def _on_contact(self, found: list[Contact], time_s: float) -> None:
        """Stop both arms at once and latch the first contact as the rig's fault."""
        for arm_id, arm in self.arms.items():
            if arm.is_moving() and self._braking.get(arm_id) is not arm._move:  # not already braking
                arm.stop()
                self._braking[arm_id] = arm._move
        if self._fault is None:
            c = found[0]
            arms = tuple(sorted({c.arm_id} | ({c.other} if c.other in self.arms else set())))
            x, y, z = c.position_m
            self._fault = RigFault(f"contact during motion at t={time_s:.3f} s: {c.arm_geom} against "
                                   f"{c.other_geom or c.other} at ({x:.3f}, {y:.3f}, {z:.3f}) m", arms)

    def fault(self) -> RigFault | None:
        """The first contact during motion (both arms were stopped then), or None."""
        return self._fault

    # -- poses --------------------------------------------------------------------------------------
    def park_q(self, arm_id: str) -> np.ndarray:
        """The rig file's park configuration (SDK angles)."""
        return np.array(self.rig.arms[arm_id].park_q_rad, dtype=float)

    def close(self) -> None:
        """Abort unfinished recordings, close the log and free the renderer (idempotent)."""
        try:
            for camera in self.cameras.values():
                camera.close()
        finally:
            self.stop_joint_log()
            if self._renderer is not None:
                self._renderer.close()
                self._renderer = None


def camera_unit_errors(settings: TwinSettings, serial: str, spec: CameraSpec,
                       cam_settings: Any) -> tuple[Any, CameraSpec | None]:
    """One unit's depth and image errors and its factory (recorded) spec, drawn from the settings' seed.

    Returns ``cam_settings`` unchanged and None when the settings hold no such errors (the default profiles).
    """
    from darp.twin.camera.sensor import UnitErrors, sensor_field_nodes

    d, im = settings.depth_errors, settings.images
    if d == type(d)() and im == type(im)():
        return cam_settings, None
    g = settings.rng(f"unit_errors:{serial}")

    def sign() -> float:
        return float(g.choice([-1.0, 1.0]))

    # Each per-unit error has its stated size (the std) and a random sign: one unit is one draw of about the
    # spec size, so that no seed gets a nearly perfect camera or one at three sigma.
    errors = UnitErrors(
        depth_scale=d.scale_std_pct / 100.0 * sign(),
        depth_offset_m=d.offset_std_mm * 1e-3 * sign(),
        depth_bias_per_m=d.bias_std_mm_per_m2 * 1e-3 * sign(),
        thermal_drift=d.thermal_drift_pct / 100.0 * sign(),
        thermal_tau_s=d.thermal_tau_s,
        session_start_s=settings.timing.start_time_s,
        blur_sigma_px=im.blur_sigma_px,
        shading=im.shading_pct / 100.0,
        noise_dn=im.noise_dn,
        field_disparity_px=d.frame_field_px,
        focal_baseline_px_m=spec.depth.fx * spec.baseline_m,
        static_field_px=(sensor_field_nodes(settings.rng(f"static_field:{serial}"), d.static_field_px)
                         if d.static_field_px > 0 else ()),
    )
    factory = None
    if d.focal_std_pct > 0 or d.centre_std_px > 0:
        def off(i: Any) -> Any:
            scale = 1.0 + d.focal_std_pct / 100.0 * sign()
            angle = float(g.uniform(0.0, 2.0 * np.pi))  # principal point: sqrt(2) x the per-axis std
            shift = np.sqrt(2.0) * d.centre_std_px
            return dataclasses.replace(i, fx=i.fx * scale, fy=i.fy * scale,
                                       ppx=i.ppx + shift * float(np.cos(angle)),
                                       ppy=i.ppy + shift * float(np.sin(angle)))
        factory = dataclasses.replace(spec, depth=off(spec.depth), color=off(spec.color))
    return dataclasses.replace(cam_settings, errors=errors), factory


__all__ = ["ContactEvent", "TwinRig", "camera_unit_errors"]
