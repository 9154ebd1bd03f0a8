"""Pre-flight check of the real rig (``darp hardware check``): reads, never moves.

From a rig YAML file it checks, in order: the file (geometry and ``hardware:`` section); the RealSense
devices pyrealsense2 sees (name, serial, firmware, USB type); per arm, that its camera is connected, is
the camera the packaged rig gives that arm (a crossed pair is flagged), sits on USB 3, and offers every
stream profile darp will ask for (depth Z16, IR1/IR2 Y8, colour BGR8 at the configured size and rate;
accel and gyro when ``cameras.imu`` is ``on``); then it reads each Z1's joint state once through
:func:`darp.hardware.z1_arm.probe_arm` (SDK loop on, read, loop off: no FSM request, no command) and
checks the joints against the Z1 limits and the rig's park pose.

Cameras are only enumerated (no pipeline is started), so a camera streaming elsewhere is still seen.
Each check has a verdict: ``ok``, ``warning`` (worth knowing, not blocking) or ``FAIL`` (darp cannot run
a survey like this). :func:`check_rig` never raises for hardware problems: they become checks.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from darp.errors import DarpError
from darp.hardware import sdk as sdk_loader
from darp.hardware.realsense_camera import CameraSettings, VideoStream, device_info, find_device, video_streams
from darp.hardware.settings import HardwareSettings, load_hardware_settings
from darp.hardware.z1_arm import ArmProbe, probe_arm
from darp.kinematics.rig import Rig, default_rig_path, load_rig

OK, WARNING, FAIL = "ok", "warning", "FAIL"
PARK_TOLERANCE_RAD = 0.05
USB2_BUDGET_MB_S = 35.0  # what a USB 2 link sustains in practice (480 Mbit/s raw, less after protocol)
# bytes per pixel on the wire: depth Z16, IR Y8, colour (the camera sends YUYV; the SDK converts to BGR8)
WIRE_BYTES = {"depth": 2, "ir1": 1, "ir2": 1, "color": 2}
INFO_KEYS = {"name": "name", "serial": "serial_number", "firmware": "firmware_version",  # field -> camera_info
             "usb": "usb_type_descriptor"}


@dataclass(frozen=True)
class Check:
    """One line of the pre-flight table."""

    name: str
    verdict: str  # ok, warning, FAIL
    detail: str


@dataclass(frozen=True)
class CameraDevice:
    """A RealSense device as pyrealsense2 lists it ('' where the device does not say)."""

    name: str
    serial: str
    firmware: str
    usb: str

    @property
    def on_usb2(self) -> bool:
        return self.usb.startswith("2")


@dataclass
class CheckReport:
    """Everything the check found: the table, the cameras listed, the arms read."""

    rig_path: Path
    checks: list[Check] = field(default_factory=list)
    cameras: list[CameraDevice] = field(default_factory=list)
    arms: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def failures(self) -> list[Check]:
        return [c for c in self.checks if c.verdict == FAIL]

    @property
    def ok(self) -> bool:
        return not self.failures

    def add(self, name: str, verdict: str, detail: str) -> None:
        self.checks.append(Check(name, verdict, detail))

    def to_dict(self) -> dict[str, Any]:
        return {"rig": str(self.rig_path), "ok": self.ok, "checks": [asdict(c) for c in self.checks],
                "cameras": [asdict(c) for c in self.cameras], "arms": self.arms}


def _fmt_q(q: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:+.3f}" for v in q) + "]"


# -- cameras ------------------------------------------------------------------------------------------
def list_cameras(rs: ModuleType) -> list[CameraDevice]:
    """The RealSense devices connected now, as pyrealsense2's context lists them (nothing is started)."""
    out = []
    for dev in rs.context().query_devices():
        info = device_info(rs, dev)
        out.append(CameraDevice(**{field: str(info.get(key, "")) for field, key in INFO_KEYS.items()}))
    return out


def required_profiles(rs: ModuleType, s: CameraSettings) -> dict[str, VideoStream]:
    """What ``RealSenseCamera`` will request, as the device lists its profiles: label -> (stream, index,
    format, width, height, fps), index 0 for the single-stream sensors (depth, colour)."""
    return {label: (stream, max(index, 0), *rest) for label, (stream, index, *rest) in video_streams(rs, s).items()}


def _offered(rs: ModuleType, dev: Any) -> tuple[set[VideoStream], dict[str, list[int]]]:
    """Every video profile the device offers (stream, index, format, w, h, fps) and its IMU rates."""
    video: set[VideoStream] = set()
    imu: dict[str, list[int]] = {"accel": [], "gyro": []}
    for sensor in dev.query_sensors():
        for p in sensor.get_stream_profiles():
            if p.is_video_stream_profile():
                v = p.as_video_stream_profile()
                video.add((p.stream_type(), p.stream_index() if p.stream_type() == rs.stream.infrared else 0,
                           p.format(), int(v.width()), int(v.height()), int(p.fps())))
            elif p.format() == rs.format.motion_xyz32f:
                kind = str(p.stream_type()).split(".")[-1]
                if kind in imu:
                    imu[kind].append(int(p.fps()))
    return video, imu


def usb_load_mb_s(s: CameraSettings) -> float:
    """Megabytes per second the configured video streams put on the USB link."""
    keys = ["depth"] + (["ir1", "ir2"] if s.infrared else []) + (["color"] if s.color else [])
    return sum(WIRE_BYTES[k] for k in keys) * s.width * s.height * s.fps / 1e6


def _check_mapping(report: CheckReport, arm_id: str, serial: str, default_owner: dict[str, str]) -> None:
    owner = default_owner.get(serial)
    if owner is not None and owner != arm_id:
        report.add(f"{arm_id} camera mapping", WARNING, f"{serial} is {owner}'s camera in the packaged rig "
                   f"(serials swapped?); darp will treat it as {arm_id}'s")
    elif owner == arm_id:
        report.add(f"{arm_id} camera mapping", OK, f"{serial} -> {arm_id}, as in the packaged rig")
    else:
        report.add(f"{arm_id} camera mapping", OK, f"{serial} -> {arm_id} (not a camera of the packaged rig)")


def _check_camera(report: CheckReport, rs: ModuleType, arm_id: str, serial: str, s: CameraSettings,
                  found: dict[str, CameraDevice]) -> None:
    name = f"{arm_id} camera"
    cam = found.get(serial)
    dev = find_device(rs, rs.context(), serial)[0] if cam is not None else None
    if cam is None or dev is None:
        others = ", ".join(sorted(found)) or "none"
        report.add(name, FAIL, f"{serial} is not connected (cameras found: {others}); check the USB 3 cable and "
                   f"the udev rules")
        return
    report.add(name, OK, f"{serial} connected: {cam.name}, firmware {cam.firmware or '?'}")
    load = usb_load_mb_s(s)
    if not cam.usb:
        report.add(f"{arm_id} USB", WARNING, "the device does not report its USB type")
    elif cam.on_usb2:
        verdict = FAIL if load > USB2_BUDGET_MB_S else WARNING
        report.add(f"{arm_id} USB", verdict, f"USB {cam.usb}: the configured streams need {load:.0f} MB/s, USB 2 "
                   f"carries about {USB2_BUDGET_MB_S:.0f} (plug it into a USB 3 port with a USB 3 cable)")
    else:
        report.add(f"{arm_id} USB", OK, f"USB {cam.usb} ({load:.0f} MB/s configured)")
    video, imu = _offered(rs, dev)
    del dev
    wanted = required_profiles(rs, s)
    missing = [label for label, key in wanted.items() if key not in video]
    mode = f"{s.width}x{s.height}@{s.fps}"
    if missing:
        report.add(f"{arm_id} streams", FAIL, f"{serial} offers no {', '.join(missing)} profile at {mode}")
    else:
        report.add(f"{arm_id} streams", OK, f"{', '.join(wanted)} at {mode}")
    has_imu = bool(imu["accel"] and imu["gyro"])
    rates = f"accel {min(imu['accel'])} Hz, gyro {min(imu['gyro'])} Hz" if has_imu else ""
    if s.imu == "off":
        report.add(f"{arm_id} IMU", OK, "off in the rig file (not recorded)")
    elif has_imu:
        report.add(f"{arm_id} IMU", OK, rates)
    elif s.imu == "on":
        report.add(f"{arm_id} IMU", FAIL, f"{cam.name} offers no accel+gyro profiles, but cameras.imu is 'on'")
    else:
        report.add(f"{arm_id} IMU", WARNING, f"{cam.name} has no IMU: surveys will have none (cameras.imu: auto)")


def check_cameras(report: CheckReport, rig: Rig, settings: HardwareSettings, rs: ModuleType | None = None) -> None:
    """Add the camera checks for every arm of ``rig`` to ``report``."""
    try:
        rs = rs if rs is not None else sdk_loader.load_realsense()
        version = ".".join(map(str, sdk_loader.realsense_version(rs)))
        report.cameras = list_cameras(rs)
    except (DarpError, RuntimeError) as err:
        report.add("pyrealsense2", FAIL, str(err))
        return
    report.add("pyrealsense2", OK, f"version {version}, {len(report.cameras)} camera(s) connected")
    found = {c.serial: c for c in report.cameras}
    default_owner = {arm.camera_serial: arm.arm_id for arm in load_rig(default_rig_path()).arms.values()}
    for arm_id in rig.arm_ids:
        serial = rig.arm(arm_id).camera_serial
        try:
            _check_camera(report, rs, arm_id, serial, settings.cameras, found)
        except RuntimeError as err:  # the SDK lost the device while we looked
            report.add(f"{arm_id} camera", FAIL, f"pyrealsense2: {err}")
        _check_mapping(report, arm_id, serial, default_owner)
    expected = {rig.arm(a).camera_serial for a in rig.arm_ids}
    extra = [f"{c.serial} ({c.name})" for c in report.cameras if c.serial not in expected]
    if extra:
        report.add("other cameras", WARNING, f"not in the rig file: {', '.join(extra)}")


# -- arms ---------------------------------------------------------------------------------------------
def _check_arm(report: CheckReport, arm_id: str, probe: ArmProbe, park_q: np.ndarray, park_tol_rad: float) -> None:
    q, lower, upper = probe.q_rad, probe.lower_rad, probe.upper_rad
    outside = np.flatnonzero((q < lower) | (q > upper))
    off_park = np.abs(q - park_q)
    report.arms[arm_id] = {"state": probe.state, "q_rad": q.tolist(), "qd_rad_s": probe.qd_rad_s.tolist(),
                           "lower_rad": lower.tolist(), "upper_rad": upper.tolist(),
                           "within_limits": not outside.size, "max_from_park_rad": float(off_park.max()),
                           "at_park": bool(off_park.max() <= park_tol_rad)}
    if outside.size:
        parts = [f"joint{j + 1} {q[j]:+.3f} rad outside [{lower[j]:+.3f}, {upper[j]:+.3f}]" for j in outside]
        report.add(f"{arm_id} joints", FAIL, "; ".join(parts) + " (bring it back with Unitree's tools first)")
    else:
        report.add(f"{arm_id} joints", OK, f"q = {_fmt_q(q)} rad, within the Z1 limits")
    j = int(np.argmax(off_park))
    if off_park[j] <= park_tol_rad:
        report.add(f"{arm_id} park", OK, f"at the park pose (at most {off_park[j]:.3f} rad off)")
    else:
        report.add(f"{arm_id} park", WARNING, f"not at the park pose: joint{j + 1} is {off_park[j]:.3f} rad off "
                   f"(park {_fmt_q(park_q)}); make sure the way there is clear")


def check_arms(report: CheckReport, rig: Rig, settings: HardwareSettings, *, timeout_s: float = 3.0,
               park_tol_rad: float = PARK_TOLERANCE_RAD, sdk: ModuleType | None = None) -> None:
    """Read every arm once through :func:`probe_arm` (no motion) and add its checks to ``report``."""
    try:
        sdk = sdk if sdk is not None else sdk_loader.load_unitree_sdk()
    except DarpError as err:
        report.add("unitree_arm_interface", FAIL, str(err))
        return
    multi = all(hasattr(sdk, n) for n in sdk_loader.MULTI_ARM_NAMES)
    report.add("unitree_arm_interface", OK, "multi-arm binding" if multi else "stock binding (one arm on 8071/8072)")
    for arm_id in rig.arm_ids:
        connection = settings.arms[arm_id]
        try:
            probe = probe_arm(arm_id, connection, timeout_s=timeout_s, sdk=sdk)
        except DarpError as err:
            report.add(f"{arm_id} controller", FAIL, str(err).removeprefix(f"{arm_id}: "))
            continue
        except Exception as err:  # an SDK failure of any kind: reported as the arm's verdict
            report.add(f"{arm_id} controller", FAIL, f"{connection.describe()}: {type(err).__name__}: {err}")
            continue
        busy = probe.state not in ("PASSIVE", "JOINTCTRL")
        report.add(f"{arm_id} controller", WARNING if busy else OK,
                   f"{connection.describe()} answered, state {probe.state}"
                   + (" (another program is driving the arm?)" if busy else ""))
        _check_arm(report, arm_id, probe, np.asarray(rig.arm(arm_id).park_q_rad, dtype=np.float64), park_tol_rad)


# -- everything ---------------------------------------------------------------------------------------
def check_rig(rig_path: str | Path, *, arm_timeout_s: float = 3.0, park_tol_rad: float = PARK_TOLERANCE_RAD,
              rs: ModuleType | None = None, sdk: ModuleType | None = None, twin_cameras: bool = False) -> CheckReport:
    """Run every pre-flight check on the rig of ``rig_path``; nothing moves, nothing is raised for
    hardware problems (a bad rig file is one FAIL check and the rest is skipped).

    ``rs``/``sdk`` replace the pyrealsense2 and unitree_arm_interface modules (tests); ``twin_cameras``: the
    cameras will be the twin's (``--twin-cameras``), so no RealSense device is looked for.
    """
    report = CheckReport(Path(rig_path))
    try:
        rig = load_rig(rig_path)
        settings = load_hardware_settings(rig_path, rig.arm_ids)
    except DarpError as err:
        report.add("rig file", FAIL, str(err))
        return report
    c = settings.cameras
    report.add("rig file", OK, f"{len(rig.arm_ids)} arms ({', '.join(rig.arm_ids)}); cameras {c.width}x{c.height}"
               f"@{c.fps}, imu {c.imu}")
    if twin_cameras:
        report.add("cameras", OK, "twin cameras, rendered from the arms' reported joints (no RealSense checked)")
    else:
        check_cameras(report, rig, settings, rs)
    check_arms(report, rig, settings, timeout_s=arm_timeout_s, park_tol_rad=park_tol_rad, sdk=sdk)
    return report


__all__ = ["FAIL", "OK", "WARNING", "CameraDevice", "Check", "CheckReport", "check_arms", "check_cameras",
           "check_rig", "list_cameras", "required_profiles", "usb_load_mb_s"]
