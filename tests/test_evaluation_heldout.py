"""Held-out evaluation: frames back-projected with their own poses against a known mesh."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from darp.errors import EvaluationError
from darp.evaluation.heldout import HeldoutSummary, evaluate_heldout, heldout_mask
from darp.evaluation.point_to_mesh import MeshDistance
from darp.reconstruction.backproject import PosedDepth
from darp.reconstruction.crop import EnvelopeCrop
from helpers.synthetic_depth import Scene, box, look_at, small_intrinsics, table

INTR = small_intrinsics(160, 120, 190.0)
TOP = 0.05
CROP = EnvelopeCrop((0.0, 0.0, TOP / 2), 0.06, TOP, table_z_m=0.0, table_margin_m=0.01)  # pose errors lift the table


@pytest.fixture(scope="module")
def setup() -> tuple[Scene, MeshDistance]:
    scene = Scene([box((0.08, 0.08, TOP), (-0.04, -0.04, 0.0)), table()])
    truth = trimesh.creation.box(extents=(0.08, 0.08, TOP))
    truth.apply_translation((0.0, 0.0, TOP / 2))
    return scene, MeshDistance(truth.vertices, truth.faces)


def held_out_frame(scene: Scene, arm: str, index: int, eye: tuple[float, float, float],
                   pose_error_z_m: float = 0.0) -> PosedDepth:
    T_true = look_at(eye, (0.0, 0.0, TOP), up=(0.0, 1.0, 0.0))
    depth, _ = scene.render(T_true, INTR)
    T_recorded = T_true.copy()
    T_recorded[2, 3] += pose_error_z_m  # the pose the robot reported: off by a known amount
    return PosedDepth(arm, index, depth, 1.0, INTR, T_recorded)


def test_exact_poses_give_zero_and_a_known_pose_error_gives_its_size(setup) -> None:
    scene, mesh = setup
    exact = [held_out_frame(scene, "arm110", 0, (0.0, 0.0, 0.4))]
    result = evaluate_heldout(exact, mesh, object_name="box", region=CROP)
    assert result.stats().count > 1000
    assert result.stats().max_m < 1e-5
    # the top face seen from straight above, the recorded camera 3 mm too high: every point 3 mm off
    shifted = [held_out_frame(scene, "arm111", 0, (0.0, 0.0, 0.4), pose_error_z_m=0.003)]
    off = evaluate_heldout(shifted, mesh, object_name="box", region=CROP, thresholds_m=(0.0025, 0.005))
    assert off.stats().median_m == pytest.approx(0.003, abs=2e-5)
    assert off.stats().within_pct == pytest.approx({0.0025: 0.0, 0.005: 100.0})


def test_per_arm_per_object_and_pooled_statistics(setup) -> None:
    scene, mesh = setup
    frames = [held_out_frame(scene, "arm110", 0, (0.0, 0.0, 0.4), 0.001),
              held_out_frame(scene, "arm110", 1, (0.0, 0.0, 0.4), 0.002),
              held_out_frame(scene, "arm111", 0, (0.0, 0.0, 0.4), 0.006)]
    one = evaluate_heldout(frames, mesh, object_name="a", region=CROP)
    assert one.frames == {"arm110": 2, "arm111": 1}
    # the top face from straight above: each frame gives the same pixels, every point off by its pose error
    n = one.stats("arm111").count
    assert n > 1000 and one.stats("arm110").count == 2 * n and one.stats().count == 3 * n
    assert one.stats("arm111").median_m == pytest.approx(0.006, abs=1e-7)
    assert one.stats("arm110").median_m == pytest.approx(0.0015, abs=1e-7)  # n points at 1 mm, n at 2 mm
    # pooled by hand: thirds at 1, 2 and 6 mm
    pooled = one.stats()
    assert pooled.median_m == pytest.approx(0.002, abs=1e-7)
    assert pooled.p90_m == pytest.approx(0.006, abs=1e-7)
    assert pooled.rmse_m == pytest.approx(1e-3 * np.sqrt((1 + 4 + 36) / 3), abs=1e-7)
    assert pooled.within_pct == pytest.approx({0.005: 200 / 3, 0.01: 100.0})
    two = evaluate_heldout(frames[:1], mesh, object_name="b", region=CROP)
    summary = HeldoutSummary((one, two))
    assert summary.n_frames == 4
    # four frames' points: quarters at 1, 2, 6 and 1 mm
    assert summary.aggregate().count == 4 * n
    assert summary.aggregate().median_m == pytest.approx(0.0015, abs=1e-7)
    assert summary.aggregate().rmse_m == pytest.approx(1e-3 * np.sqrt((1 + 4 + 36 + 1) / 4), abs=1e-7)
    table = summary.markdown()
    assert "| a | 3 |" in table and "| b | 1 |" in table and "| **all** | 4 |" in table
    assert "2.13" in table  # the paper's row for comparison
    payload = summary.to_dict()
    assert payload["aggregate"]["keyframes"] == 4 and set(payload["arms"]) == {"arm110", "arm111"}


def test_heldout_split() -> None:
    mask = heldout_mask(12, every=5, offset=2)
    np.testing.assert_array_equal(np.flatnonzero(mask), [2, 7])
    with pytest.raises(EvaluationError, match="every >= 2"):
        heldout_mask(10, every=1)
