"""Survey-level pose refinement (issue 16 item 4, ``--corrections refine``).

The algorithm is checked on exact depth images of a synthetic scene (a box and a sphere on a table, Open3D
ray casting: tests/helpers/synthetic_depth.py) seen by two 'arms' from opposite sides: it recovers a known
perturbation of one arm's poses and of one keyframe's pose, refuses a correction beyond its bound, gives
held-out keyframes their arm's correction only; the pipeline runs it only when the switch is on.

The two-arm views are rendered at the D435's 640x480. At 320x240 (1.8 mm pixels at 0.35 m, about two pixels per
2.5 mm registration voxel) the arm-to-arm fit along the arms' common axis and the per-view fits in their weak
directions were noise-dominated: over eight noise seeds a 4 mm arm offset was seen as 0.9-7.1 mm, and a change of
the rendered depth by 1e-7 of itself (35 nm) moved the results across these tests' thresholds, so they passed or
failed with the library and CPU bits (the numbers are in the commit that made this change).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from darp.formats.realsense.types import Intrinsics
from darp.reconstruction.backproject import PosedDepth
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.refine import RefineSettings, RefineView, refine_poses
from darp.reconstruction.registration import (
    displacement_m,
    information_ratios,
    mean_transform,
    rigid_power,
    rotation_angle_deg,
    transform_twist,
    twist_transform,
)
from helpers.synthetic_depth import Scene, add_depth_noise, box, orbit_poses, small_intrinsics, sphere, table, to_z16

CENTRE = np.array([0.0, 0.01, 0.04])
CROP = EnvelopeCrop((0.0, 0.01, 0.04), 0.07, 0.08, 0.0, 0.01, 0.003)
SCALE = 0.0001  # depth units of 0.1 mm: the test is about poses, not quantisation
HELD = 2  # each arm's third view is held out
SINGLED = "arm111/1"  # the keyframe given an offset of its own (elevation 35 deg, azimuth 0: it sees the box's +x
# face, the sphere and the table, so its data constrain every direction of that offset; arm111/0 at azimuth -40
# sees the offset's main part, 2 mm along y, only on the box's -y face at 60 deg incidence, with the sphere hidden
# behind the box: there the prior holds about half of it, which made "halves its error" a coin toss)


def _intrinsics(depth: np.ndarray) -> Intrinsics:
    """The camera a view was rendered with: :func:`small_intrinsics` of the D435's field of view at its size."""
    return small_intrinsics(depth.shape[1], depth.shape[0], 0.6 * depth.shape[1])


def _rigid(rotvec_deg: tuple[float, float, float], t_mm: tuple[float, float, float]) -> np.ndarray:
    """A rotation by ``rotvec_deg`` about :data:`CENTRE`, then a shift of ``t_mm``."""
    return twist_transform(np.concatenate([np.radians(rotvec_deg), np.asarray(t_mm) / 1000.0]), CENTRE)


def _two_arm_views(scene: Scene, held: int | None,
                   size: tuple[int, int] = (640, 480)) -> list[tuple[str, str, int, str, np.ndarray, np.ndarray]]:
    """(key, arm, frame, split, true pose, raw depth) of six noisy views per arm from opposite sides (D435 field of
    view, ``size`` pixels); each arm's view ``held`` is held out."""
    intr = small_intrinsics(size[0], size[1], 0.6 * size[0])
    rng = np.random.default_rng(0)
    views = []
    for arm, azimuths in (("arm110", (140, 180, 220)), ("arm111", (-40, 0, 40))):
        for k, T in enumerate(orbit_poses(CENTRE, 0.35, (35, 60), azimuths)):
            depth, _ = scene.render(T, intr)
            views.append((f"{arm}/{k}", arm, k, "heldout" if k == held else "fuse", T,
                          to_z16(add_depth_noise(depth, rng), SCALE)))
    return views


def _box_scene() -> Scene:
    return Scene([table(), box((0.06, 0.04, 0.08), (-0.03, -0.02, 0.0)), sphere(0.025, (0.0, 0.05, 0.025))])


@pytest.fixture(scope="module")
def scene_views() -> list[tuple[str, str, int, str, np.ndarray, np.ndarray]]:
    """A box and a sphere on the table (:func:`_two_arm_views`, the third view of each arm held out)."""
    return _two_arm_views(_box_scene(), HELD)


def _run(views: list, poses: dict[str, np.ndarray], uncertainty_m: float,
         settings: RefineSettings | None = None) -> tuple[dict[str, np.ndarray], dict]:
    result = refine_poses([RefineView(key, arm, k, split, poses[key]) for key, arm, k, split, _, _ in views],
                          [None if split != "fuse" else PosedDepth(arm, k, depth, SCALE, _intrinsics(depth), poses[key])
                           for key, arm, k, split, _, depth in views], CROP, uncertainty_m, settings)
    return result.poses, result.record


def _consistency_mm(errors: dict[str, np.ndarray]) -> dict[str, float]:
    """Per view: RMS displacement (mm) of points around the object by the view's pose error, once the
    errors' common part (the gauge, which no overlap can see) is removed."""
    points = CENTRE + np.random.default_rng(1).uniform(-0.04, 0.04, (200, 3))
    gauge = np.linalg.inv(mean_transform(list(errors.values()), CENTRE))
    out = {}
    for key, E in errors.items():
        G = gauge @ E
        out[key] = float(np.sqrt(np.mean(np.sum((points @ G[:3, :3].T + G[:3, 3] - points) ** 2, axis=1)))) * 1000
    return out


def _own_error_mm(errors: dict[str, np.ndarray], key: str) -> float:
    """RMS displacement (mm) of points around the object by view ``key``'s pose error relative to its arm mates'
    mean error (its other fuse views): the part of its error that is its own, which the per-view level corrects."""
    arm = key.split("/")[0]
    mates = [E for k, E in errors.items() if k.startswith(arm) and k not in (key, f"{arm}/{HELD}")]
    G = errors[key] @ np.linalg.inv(mean_transform(mates, CENTRE))
    points = CENTRE + np.random.default_rng(1).uniform(-0.04, 0.04, (200, 3))
    return float(np.sqrt(np.mean(np.sum((points @ G[:3, :3].T + G[:3, 3] - points) ** 2, axis=1)))) * 1000


def test_rigid_helpers() -> None:
    T = _rigid((3.0, -2.0, 5.0), (10.0, -4.0, 2.0))
    half = rigid_power(T, 0.5)
    np.testing.assert_allclose(half @ half, T, atol=1e-12)
    np.testing.assert_allclose(mean_transform([T, T, T], np.array([0.0, 0.1, 0.0])), T, atol=1e-12)
    np.testing.assert_allclose(twist_transform(transform_twist(T, CENTRE), CENTRE), T, atol=1e-12)
    assert rotation_angle_deg(T) == pytest.approx(np.linalg.norm([3.0, -2.0, 5.0]), rel=1e-9)
    assert displacement_m(T, CENTRE) == pytest.approx(np.linalg.norm([10, -4, 2]) / 1000)


def test_recovers_one_arms_offset_and_one_keyframes(scene_views: list) -> None:
    truth = {v[0]: v[4] for v in scene_views}
    arm_offset = _rigid((0.0, 0.3, 0.2), (2.5, -1.5, 1.0))  # every pose of arm111
    view_offset = _rigid((0.2, 0.0, 0.0), (0.0, 2.0, -1.0))  # and keyframe SINGLED more
    perturbed = {key: (arm_offset @ T if key.startswith("arm111") else T) for key, T in truth.items()}
    perturbed[SINGLED] = view_offset @ perturbed[SINGLED]
    errors_before = {k: perturbed[k] @ np.linalg.inv(T) for k, T in truth.items()}
    before = _consistency_mm(errors_before)

    poses, record = _run(scene_views, perturbed, 0.004)
    errors_after = {k: poses[k] @ np.linalg.inv(T) for k, T in truth.items()}
    after = _consistency_mm(errors_after)
    assert record["arms"]["arm110"]["accepted"] and record["arms"]["arm111"]["accepted"]
    # the arms agree again (before: ~1.5 mm each way; after: 0.13-0.21 of that over noise seeds 0-11), held out or
    # not (0.17-0.26)
    assert np.median(list(after.values())) < 0.5 * np.median(list(before.values())), (before, after)
    assert after[f"arm111/{HELD}"] < 0.6 * before[f"arm111/{HELD}"]
    # the singled-out view agrees with its arm mates again (its own 2.2 mm; after: 0.12-0.40 of it over seeds 0-11)
    own_before, own_after = _own_error_mm(errors_before, SINGLED), _own_error_mm(errors_after, SINGLED)
    assert own_after < 0.5 * own_before, (own_before, own_after)
    # held-out keyframes get their arm's correction only, and every view is recorded
    rows = {row["key"]: row for row in record["views"]}
    assert len(rows) == len(scene_views)
    assert rows[f"arm111/{HELD}"]["applied"] == "arm" and rows[SINGLED]["applied"] == "view"
    np.testing.assert_allclose(rows[f"arm111/{HELD}"]["translation_mm"], record["arms"]["arm111"]["translation_mm"],
                               atol=1e-3)


def test_refuses_a_correction_beyond_its_bound(scene_views: list) -> None:
    truth = {v[0]: v[4] for v in scene_views}
    offset = _rigid((0.0, 0.0, 0.0), (4.0, 0.0, 0.0))
    perturbed = {key: (offset @ T if key.startswith("arm111") else T) for key, T in truth.items()}
    # a stated uncertainty of 0.5 mm bounds a correction to 1 mm at the envelope centre: 2 mm per arm is refused
    poses, record = _run(scene_views, perturbed, 0.0005, RefineSettings(per_view=False, prior_sigma=20.0))
    assert record["bound"]["translation_mm"] == pytest.approx(1.0)
    assert record["arm_pair"]["translation_mm"] > 3.0  # it saw the offset (3.8-4.8 mm over noise seeds 0-11) ...
    assert not record["arms"]["arm111"]["accepted"] and "bound" in record["arms"]["arm111"]["refused"]
    for key, T in perturbed.items():  # ... and applied nothing
        np.testing.assert_array_equal(poses[key], T)


def test_paper_mode_records_and_changes_nothing(processed_path: Path) -> None:
    results = json.loads((processed_path / "results.json").read_text())
    assert results["corrections"] == {"mode": "paper", "applied": []}
    index = json.loads((processed_path / "keyframes" / "keyframes.json").read_text())
    assert "refinement" not in index


@pytest.mark.slow
def test_the_switch_refines_the_pipelines_keyframes(survey_path: Path, tmp_path: Path) -> None:
    from darp.cli._app import run

    out = tmp_path / "kf"
    assert run(["keyframes", str(survey_path), "--truth-poses", "--corrections", "refine", "-o", str(out)]) == 0
    index = json.loads((out / "keyframes.json").read_text())
    record = index["refinement"]
    assert record["bound"]["source"].startswith("default")  # true poses: the calibration states no error
    assert len(record["views"]) == len(index["keyframes"])
    applied = {row["key"]: row for row in record["views"]}
    for entry in index["keyframes"]:  # the index's poses are the refined ones, and within the bound
        assert applied[entry["file"]]["translation_mm"] <= record["bound"]["translation_mm"]


def test_heldout_register_aligns_heldout_views_to_the_fuse_ones(scene_views: list) -> None:
    truth = {v[0]: v[4] for v in scene_views}
    offset = _rigid((0.0, 0.2, 0.0), (0.0, 2.5, 1.0))  # one held-out view only: no fuse view can see it
    perturbed = dict(truth)
    perturbed[f"arm111/{HELD}"] = offset @ truth[f"arm111/{HELD}"]
    frames = [PosedDepth(arm, k, depth, SCALE, _intrinsics(depth), perturbed[key])
              for key, arm, k, _, _, depth in scene_views]
    views = [RefineView(key, arm, k, split, perturbed[key]) for key, arm, k, split, _, _ in scene_views]
    settings = RefineSettings(per_arm=False, per_view=False, heldout="register")
    result = refine_poses(views, frames, CROP, 0.004, settings)
    rows = {row["key"]: row for row in result.record["views"]}
    assert rows[f"arm111/{HELD}"]["applied"] == "registered" and result.record["heldout"] == "register"
    error = result.poses[f"arm111/{HELD}"] @ np.linalg.inv(truth[f"arm111/{HELD}"])
    assert displacement_m(error, CENTRE) < 0.3 * displacement_m(offset, CENTRE)
    arm_only = refine_poses(views, frames, CROP, 0.004, RefineSettings(per_arm=False, per_view=False))
    np.testing.assert_array_equal(arm_only.poses[f"arm111/{HELD}"], perturbed[f"arm111/{HELD}"])


@pytest.fixture(scope="module")
def many_views() -> list[tuple[str, str, int, str, np.ndarray, np.ndarray]]:
    """Eight noisy views per arm (the sixth held out), enough for the gate's validation views."""
    scene = Scene([table(), box((0.06, 0.04, 0.08), (-0.03, -0.02, 0.0)), sphere(0.025, (0.0, 0.05, 0.025))])
    intr = small_intrinsics(320, 240, 192.0)
    rng = np.random.default_rng(2)
    views = []
    for arm, azimuths in (("arm110", (110, 130, 150, 170, 190, 210, 230, 250)),
                          ("arm111", (-70, -50, -30, -10, 10, 30, 50, 70))):
        for k, T in enumerate(orbit_poses(CENTRE, 0.35, (45,), azimuths)):
            depth, _ = scene.render(T, intr)
            views.append((f"{arm}/{k}", arm, k, "heldout" if k == 5 else "fuse", T,
                          to_z16(add_depth_noise(depth, rng), SCALE)))
    return views


def test_gate_applies_a_correction_that_validates(many_views: list) -> None:
    """An arm offset: the validation views (fuse keyframes left out of the fit) agree better with the
    corrected fit views, so the correction is applied; the gate is recorded."""
    truth = {v[0]: v[4] for v in many_views}
    offset = _rigid((0.0, 0.3, 0.2), (2.5, -1.5, 1.0))
    perturbed = {key: (offset @ T if key.startswith("arm111") else T) for key, T in truth.items()}
    before = _consistency_mm({k: perturbed[k] @ np.linalg.inv(T) for k, T in truth.items()})
    poses, record = _run(many_views, perturbed, 0.004)
    gate = record["gate"]
    assert gate["used"] and gate["applied"] in ("arm", "view"), gate
    assert len(gate["validation_views"]) == 4 and not any(k.endswith("/5") for k in gate["validation_views"])
    assert gate["costs"][gate["applied"]]["cost_mm"] < 0.9 * gate["costs"]["none"]["cost_mm"]
    after = _consistency_mm({k: poses[k] @ np.linalg.inv(T) for k, T in truth.items()})
    assert np.median(list(after.values())) < 0.5 * np.median(list(before.values())), (before, after)
    rows = {row["key"]: row for row in record["views"]}
    assert all(rows[k]["applied"] == "arm" and "validation" in rows[k]["note"] for k in gate["validation_views"])


def test_gate_refuses_what_does_not_validate(many_views: list) -> None:
    """True poses: whatever the fit finds in the noise does not make the validation views agree better by the
    minimum gain, so nothing is applied and the refusal is recorded."""
    truth = {v[0]: v[4] for v in many_views}
    poses, record = _run(many_views, truth, 0.004, RefineSettings(gate_min_gain=0.05))
    gate = record["gate"]
    assert gate["used"] and gate["applied"] == "none", gate
    assert all(not arm["accepted"] and "validation" in arm["refused"] for arm in record["arms"].values())
    for key, T in truth.items():
        np.testing.assert_array_equal(poses[key], T)
    # and without the gate (validate_every 0) the same fit is applied
    _, plain = _run(many_views, truth, 0.004, RefineSettings(validate_every=0, per_view=False))
    assert plain["gate"] == {"used": False, "note": "off (validate_every 0)"}



def test_information_ratios_in_prior_units() -> None:
    prior = (0.002, 0.005)  # 2 mm, 5 mrad
    information = np.diag([1e3 / prior[1] ** 2, 1e3 / prior[1] ** 2, 0.1 / prior[1] ** 2] + [1e3 / prior[0] ** 2] * 3)
    np.testing.assert_allclose(information_ratios(information, prior), [0.1] + [1e3] * 5, rtol=1e-9)


@pytest.fixture(scope="module")
def round_scene_views() -> list[tuple[str, str, int, str, np.ndarray, np.ndarray]]:
    """The views of :func:`scene_views` on a cylinder on the table: a turn about its axis leaves both unchanged."""
    import open3d as o3d

    cylinder = o3d.geometry.TriangleMesh.create_cylinder(0.03, 0.08, 96)
    cylinder.translate(CENTRE)
    return _two_arm_views(Scene([table(), cylinder]), None, (320, 240))


@pytest.fixture(scope="module")
def scene_views_320() -> list[tuple[str, str, int, str, np.ndarray, np.ndarray]]:
    """:func:`scene_views` at 320x240, to compare with :func:`round_scene_views` (at 640x480 the 96-sided
    cylinder's facets show in the normals, and the turn about its axis is no longer unseen)."""
    return _two_arm_views(_box_scene(), HELD, (320, 240))


def test_arm_pair_records_what_its_overlap_constrains(round_scene_views: list, scene_views_320: list) -> None:
    """The arm-to-arm fit records its information per direction in prior units and its twist: on a cylinder
    the turn about its axis is the one direction the overlap does not see (ratio < 1), and the fit leaves it
    at zero; the box and sphere constrain that turn more."""
    offset = _rigid((0.0, 0.0, 1.5), (2.0, -1.0, 0.5))
    settings = RefineSettings(per_view=False, validate_every=0)
    pairs = {}
    for name, views in (("round", round_scene_views), ("box", scene_views_320)):
        truth = {v[0]: v[4] for v in views}
        perturbed = {key: (offset @ T if key.startswith("arm111") else T) for key, T in truth.items()}
        pairs[name] = _run(views, perturbed, 0.004, settings)[1]["arm_pair"]
    ratios = pairs["round"]["information_ratios"]
    assert len(ratios) == 6 and ratios[0] < 1.0 < ratios[1] and ratios == sorted(ratios)
    assert pairs["box"]["information_ratios"][0] > 2 * ratios[0]
    # the fit's twist: the round object's turn about z stays near zero (the true 1.5 deg is invisible to it)
    assert abs(pairs["round"]["rotvec_deg"][2]) < 0.3 and len(pairs["round"]["displacement_mm"]) == 3
