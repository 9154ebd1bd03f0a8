"""Calibration end to end on the digital twin (MuJoCo renders, realistic error profile): the acceptance tests.

The twin draws a true rig for the seed (joint-zero biases up to 1 deg per joint, hand-eye mounts 3 mm /
1 deg off nominal, the second base 4 mm / 0.3 deg off, encoder noise); darp plans and takes 2 x 30
captures of a board lying on the table, solves, and is compared with the twin's truth. A few more
captures of the same rig must pass ``calib check``; captures after knocking arm110's camera mount by
2 mm / 0.5 deg must not.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from darp.calibration.captures import read_captures
from darp.calibration.check import check_calibration
from darp.calibration.solve import SolveSettings, solve_captures
from darp.formats.calibration import read_calibration, write_calibration
from darp.kinematics.transforms import axis_angle_to_rotation, make_transform
from darp.twin.calib_capture import capture_twin
from helpers.calibration_synthetic import shared_once

pytestmark = pytest.mark.slow
SEED = 7


@pytest.fixture(scope="module")
def twin_solve(tmp_path_factory: pytest.TempPathFactory):
    def build(root: Path) -> None:
        caps = capture_twin(root / "caps", seed=SEED, n_per_arm=30)
        truth = read_calibration(caps.truth_calibration_path())
        write_calibration(root / "cal.json", solve_captures(caps, SolveSettings(folds=3), truth=truth).calibration)

    root = shared_once(tmp_path_factory, "calib-twin", build)
    return root, read_captures(root / "caps"), read_calibration(root / "cal.json")


def test_twin_captures_are_complete_and_detected(twin_solve) -> None:
    _, caps, cal = twin_solve
    assert len(caps.for_arm("arm110")) == len(caps.for_arm("arm111")) == 30
    rec = caps.captures[0]
    assert rec.stream == "color" and rec.image_size == (640, 480) and rec.q_std_rad is not None
    assert not np.allclose(rec.T_depth_stream, np.eye(4))  # the factory depth-to-colour extrinsic
    assert cal.report["n_used"] >= 56, cal.report["rejected"]
    assert cal.report["sigma_px"] < 0.2


def test_twin_calibration_meets_the_acceptance_targets(twin_solve) -> None:
    _, _, cal = twin_solve
    truth = cal.report["truth"]
    assert truth is not None
    darp = truth["darp"]
    for arm, a in darp["arms"].items():
        assert a["hand_eye"]["translation_mm"] < 1.0 and a["hand_eye"]["rotation_deg"] < 0.1, arm
        assert a["max_identifiable_joint_offset_error_deg"] < 0.05, arm
        held = cal.arms[arm].residuals["heldout"]["corner_3d_mm"]
        assert held["median"] <= 1.0, arm  # the paper: 3.58 and 3.93 mm
    assert darp["base_to_base"]["translation_mm"] < 1.0 and darp["base_to_base"]["rotation_deg"] < 0.05
    # side by side on the same captures: OpenCV alone is far worse (the refinement's gain is a ratio)
    for base in ("opencv_hand_eye", "opencv_robot_world"):
        b = truth[base]
        assert b["base_to_base"]["translation_mm"] > 10 * darp["base_to_base"]["translation_mm"]
        for arm in darp["arms"]:
            assert (b["arms"][arm]["camera_pose"]["translation_mm_median"]
                    > 10 * darp["arms"][arm]["camera_pose"]["translation_mm_median"])
            held_b = cal.report["heldout"][base][arm]["corner_3d_mm"]["median"]
            assert held_b > 5 * cal.arms[arm].residuals["heldout"]["corner_3d_mm"]["median"]


def test_twin_check_passes_unchanged_and_flags_a_knocked_mount(twin_solve, tmp_path: Path) -> None:
    _, _, cal = twin_solve
    same = capture_twin(tmp_path / "same", seed=SEED, n_per_arm=6, plan_seed=SEED + 100)
    result = check_calibration(cal, same)
    assert result.ok, {a: r.reasons for a, r in result.arms.items()}
    knock = make_transform(axis_angle_to_rotation([0.3, 1.0, 0.2], np.radians(0.5)), [0.0, 0.002, 0.0])
    knocked = capture_twin(tmp_path / "knocked", seed=SEED, n_per_arm=6, plan_seed=SEED + 100,
                           mount_offsets={"arm110": knock})
    result = check_calibration(cal, read_captures(Path(knocked.folder)))
    assert not result.ok and not result.arms["arm110"].ok
    assert result.arms["arm110"].self_consistency_mm > result.arms["arm110"].limit_mm
