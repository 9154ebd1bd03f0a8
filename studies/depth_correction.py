#!/usr/bin/env python3
"""Per-camera depth correction (issue 16 item 3) against the twin's true depth errors.

Reads a twin capture folder WITH depth images (``darp calib capture --twin``), detects the board, fits
each camera's correction (:mod:`darp.calibration.depth_fit`) and compares it with the truth the twin
drew from its settings (``truth/settings.yaml``: scale, offset, distance bias, thermal drift and the
written intrinsics' focal error; used here only for evaluation). Printed per camera: the estimate with
its standard errors, and the error of the corrected depth at 0.3 .. 0.7 m, with and without the
colour focal error that PnP's range inherits.

    .venv/bin/python studies/depth_correction.py [CAPTURES] [--json out.json]

Without CAPTURES it first captures 20 per arm on the twin's paper profile, seed 0
(about two minutes), into a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np


def true_unit_errors(captures_dir: Path) -> dict[str, dict[str, Any]]:
    """Per arm: the twin's drawn depth errors and the written colour/depth focal scale (evaluation only)."""
    from darp.kinematics.rig import load_rig
    from darp.twin.camera.sensor import TwinCameraSettings
    from darp.twin.camera.spec import UnitCalibration, draw_unit, make_camera_spec
    from darp.twin.rig_backend import camera_unit_errors
    from darp.twin.settings import TwinSettings

    settings = TwinSettings.load(captures_dir / "truth" / "settings.yaml")
    c = settings.camera
    out = {}
    for arm_id, arm in load_rig().arms.items():
        unit = draw_unit(settings.rng(f"unit:{arm.camera_serial}")) if c.unit_variation else UnitCalibration()
        spec = make_camera_spec(unit, serial=arm.camera_serial, depth_resolution=(c.width, c.height),
                                colour_resolution=(c.width, c.height), fps=c.fps, colour_fps=c.fps)
        cam, factory = camera_unit_errors(settings, arm.camera_serial, spec,
                                          TwinCameraSettings.from_profile(c.depth_noise))
        e = cam.errors
        out[arm_id] = {"scale": e.depth_scale, "offset_m": e.depth_offset_m, "bias_per_m": e.depth_bias_per_m,
                       "thermal_drift": e.thermal_drift, "thermal_tau_s": e.thermal_tau_s,
                       "session_start_s": e.session_start_s,
                       "color_focal_ratio": 1.0 if factory is None else factory.color.fx / spec.color.fx,
                       "depth_focal_ratio": 1.0 if factory is None else factory.depth.fx / spec.depth.fx}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("captures", type=Path, nargs="?")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from darp.calibration.captures import read_captures
    from darp.calibration.depth_fit import DepthFitSettings, capture_depth_samples, fit_depth_correction
    from darp.calibration.detect import detect_captures

    if args.captures is None:
        import tempfile

        from darp.twin.calib_capture import capture_twin

        args.captures = Path(tempfile.mkdtemp(prefix="darp-depthcorr-")) / "captures"
        print(f"capturing 20 per arm on the twin (paper profile, seed 0) into {args.captures}")
        capture_twin(args.captures, seed=0, profile="paper", n_per_arm=20)
    cs = read_captures(args.captures)
    t0 = time.perf_counter()
    dets = detect_captures(cs)
    t1 = time.perf_counter()
    samples = capture_depth_samples(cs, dets)
    truth = true_unit_errors(args.captures)
    report: dict[str, Any] = {}
    zs = np.linspace(0.3, 0.7, 5)
    for arm, smp in sorted(samples.items()):
        corr = fit_depth_correction(smp, DepthFitSettings())
        t = truth[arm]
        times = np.array([r.time_s for r in cs.for_arm(arm)])
        elapsed = float(np.mean(times)) - t["session_start_s"]
        drift = t["thermal_drift"] * (1 - np.exp(-elapsed / t["thermal_tau_s"]))
        s_eff = t["scale"] + drift
        # measured = z (1 + s_eff) + o + b z^2 ; corrected = corr(measured); error vs true z
        meas = zs * (1 + s_eff) + t["offset_m"] + t["bias_per_m"] * zs * zs
        err_true = corr.apply(meas) - zs
        # what PnP sees: the board at z * colour focal ratio
        err_pnp = corr.apply(meas) - zs * t["color_focal_ratio"]
        raw_err = meas - zs
        report[arm] = {"estimate": corr.to_dict(), "truth": t, "mean_capture_elapsed_s": elapsed,
                       "thermal_drift_at_captures": drift,
                       "z_m": zs.tolist(), "uncorrected_error_mm": (1e3 * raw_err).tolist(),
                       "corrected_error_vs_truth_mm": (1e3 * err_true).tolist(),
                       "corrected_error_vs_pnp_range_mm": (1e3 * err_pnp).tolist()}
        print(f"{arm}: scale {corr.scale:.5f} +- {corr.scale_std:.5f}, offset {1e3 * corr.offset_m:+.2f} +- "
              f"{1e3 * (corr.offset_std_m or 0):.2f} mm, quad {1e3 * corr.quad_per_m:+.2f} mm/m^2 "
              f"({corr.n_captures} captures, {corr.n_pixels} px, MAD {1e3 * (corr.residual_mad_m or 0):.2f} mm)")
        print(f"   notes: {corr.notes}")
        print(f"   truth: scale {t['scale']:+.5f} (+drift {drift:+.5f} at captures), offset {1e3 * t['offset_m']:+.2f} "
              f"mm, bias {1e3 * t['bias_per_m']:+.2f} mm/m^2, colour focal x{t['color_focal_ratio']:.5f}")
        for z, a, b, c in zip(zs, raw_err, err_true, err_pnp, strict=True):
            print(f"   z {z:.2f} m: raw error {1e3 * a:+6.2f} mm -> corrected {1e3 * b:+6.2f} mm vs truth, "
                  f"{1e3 * c:+6.2f} mm vs the PnP range")
    print(f"detect {t1 - t0:.1f} s, samples+fit {time.perf_counter() - t1:.1f} s")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main()
