"""studies/safety.py: its contact count is real (a deliberate collision is counted), its random valid
placements pass the placement check, and each kind of invalid placement it draws is refused by ``darp
collect`` with exit 2 before any joint command."""

from __future__ import annotations

import math
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from helpers.script_modules import load_study

pytest.importorskip("mujoco")

from darp.kinematics.rig import load_rig
from darp.twin.objects.model import ObjectPlacement, make_object
from darp.twin.placement import validate_placement

RIG = load_rig()


@pytest.fixture(scope="module")
def safety() -> ModuleType:
    return load_study("safety")


@pytest.fixture(scope="module")
def meshes(safety: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return safety.write_user_meshes(tmp_path_factory.mktemp("meshes"))  # type: ignore[no-any-return]


def test_a_deliberate_collision_is_counted_and_a_clear_move_is_not(safety: ModuleType) -> None:
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings

    settings = TwinSettings.from_profile("ideal", seed=5).with_camera(width=424, height=240, fps=6, imu=False)
    with safety.counting_motion() as counts, TwinRig(settings, rig=RIG, obj=make_object("cup"),
                                                     placement=ObjectPlacement(-0.2, 0.0, 0.0)) as twin:
        assert counts == {"move_to": 0, "twins": 1}
        dense = safety.add_dense_check(twin)
        clear = np.array(RIG.arms["arm111"].park_q_rad) + [0.3, 0.0, 0.0, 0.0, 0.0, 0.0]
        twin.arms["arm111"].move_to(clear)  # a small joint-1 turn in the air
        assert twin.wait_until_still("arm111", timeout_s=10.0)
        assert safety.contacts_of(twin)["contacts"] == 0 and twin.fault() is None
        assert dense["dense_samples"] > 100 and dense["dense_contacts"] == 0  # 1 kHz over a ~0.5 s move
        twin.arms["arm110"].move_to(np.array([0.0, 2.4, -1.5, 0.0, 0.0, 0.0]))  # the wrist through the cup, unchecked
        twin.wait_until_still("arm110", timeout_s=20.0)
        record = safety.contacts_of(twin)
        assert counts["move_to"] == 2
    assert record["contacts"] >= 1 and record["first_contact"]["arm"] == "arm110"
    assert record["first_contact"]["other"] == "object" and record["first_contact"]["depth_mm"] > 0
    assert "contact during motion" in record["fault"]
    assert dense["dense_contacts"] >= record["contacts"] and dense["dense_first"]["arm"] == "arm110"


def test_valid_draws_cover_the_workspace_and_pass_the_placement_check(safety: ModuleType,
                                                                       meshes: dict[str, Path]) -> None:
    objects = ["cup", "picture_frame", *safety.USER_MESHES]
    draws = [safety.draw_valid(i, 3, objects, meshes, RIG) for i in range(12)]
    assert draws == [safety.draw_valid(i, 3, objects, meshes, RIG) for i in range(12)]  # deterministic
    assert {d["viewpoints"] for d in draws} == {"orbit", "coverage"}
    assert {d["calibration"] for d in draws} == {"truth", "nominal"}
    for d in draws:
        obj = safety.load(d["object"], meshes)
        validate_placement(RIG, obj.radius_m, obj.height_m, ObjectPlacement(d["x_m"], d["y_m"],
                                                                            math.radians(d["yaw_deg"])))
    xs = [d["x_m"] for d in draws]
    assert max(xs) - min(xs) > 0.2  # spread over the workspace, not bunched at its centre


@pytest.mark.parametrize("kind", ["non_finite", "off_table", "inside_base", "against_robot", "outside_workspace",
                                  "too_tall"])
def test_each_kind_of_invalid_placement_is_refused_before_motion(safety: ModuleType, meshes: dict[str, Path],
                                                                 tmp_path: Path, kind: str) -> None:
    objects = ["cup", "mug", "picture_frame", *safety.USER_MESHES]
    draw = safety.draw_invalid(kind, 1, 7, objects, meshes, RIG)
    assert draw["kind"] == kind
    row = safety.run_invalid(draw, meshes, tmp_path)
    assert row["exit"] == 2 and row["message"].startswith("darp: error: ")
    assert safety.classify(row["message"]).startswith(kind.split("_")[0])
    assert row["joint_commands"] == 0 and row["twins_built"] == 0 and row["folders"] == []
    assert row["refused_before_motion"]


def test_the_profile_and_solved_draws_come_after_the_old_ones(safety: ModuleType, meshes: dict[str, Path]) -> None:
    objects = ["cup", "picture_frame", *safety.USER_MESHES]
    old = [safety.draw_valid(i, 3, objects, meshes, RIG) for i in range(12)]
    new = [safety.draw_valid(i, 3, objects, meshes, RIG, profiles=("realistic", "paper"), solved_share=0.5,
                             solved_pool=2) for i in range(12)]
    assert all(o["profile"] == "realistic" for o in old)
    assert {n["profile"] for n in new} == {"realistic", "paper"}
    solved = [n for n in new if n["calibration"] == "solved"]
    assert 0 < len(solved) < 12
    pools = {p: {safety.solved_pool_seed(3, p, k) for k in range(2)} for p in ("realistic", "paper")}
    assert all(n["twin_seed"] in pools[n["profile"]] for n in solved)
    for o, n in zip(old, new, strict=True):  # the old fields are drawn as before
        same = ("index", "object", "x_m", "y_m", "yaw_deg", "viewpoints")
        assert {k: o[k] for k in same} == {k: n[k] for k in same}
        if n["calibration"] != "solved":
            assert (n["twin_seed"], n["calibration"]) == (o["twin_seed"], o["calibration"])


@pytest.mark.slow
def test_a_solved_calibration_is_solved_from_the_twins_images_once(safety: ModuleType, tmp_path: Path) -> None:
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings

    cal, info = safety.solved_calibration(tmp_path, "realistic", 21, captures=8)
    assert not info["cached"] and info["n_used"] >= 12
    settings = TwinSettings.from_profile("realistic", seed=21).with_camera(width=424, height=240, fps=6, imu=False)
    with TwinRig(settings, rig=RIG) as twin:  # the survey's twin: same profile and seed, the survey's camera
        truth = twin.true_rig.calibration(settings)
    to_truth = safety.calibration_gap(cal, truth)
    nominal_to_truth = safety.calibration_gap(RIG.nominal_calibration(), truth)
    assert info["gap_to_truth"] == to_truth  # solved against the same true rig as the survey's twin
    assert 0.01 < to_truth["hand_eye_mm"] < 3.0 and to_truth["joint_offset_deg"] > 1e-4  # solved: not the truth
    for key in ("hand_eye_mm", "joint_offset_deg"):  # ... and closer to it than the nominal rig (3 mm, 0.97 deg)
        assert to_truth[key] < nominal_to_truth[key]
    assert safety.calibration_gap(cal, RIG.nominal_calibration())["hand_eye_mm"] > 0.01
    path = tmp_path / "calibrations" / "realistic_seed21" / "calibration.json"
    stamp = path.stat().st_mtime_ns
    again, info2 = safety.solved_calibration(tmp_path, "realistic", 21, captures=8)
    assert info2["cached"] and path.stat().st_mtime_ns == stamp
    assert np.allclose(again.arms["arm110"].T_wrist_cam, cal.arms["arm110"].T_wrist_cam)
    assert not (path.parent / "captures").exists()
