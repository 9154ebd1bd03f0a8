"""Cross-arm confirmation: combining consistent estimates, falling back, terminating."""

from __future__ import annotations

import numpy as np
import pytest

from darp.acquisition.confirm import ConfirmSettings, combine, consistency, decide
from darp.acquisition.localise import LocalisationResult, ObjectEstimate
from darp.errors import AcquisitionError


def est(arm: str, x: float, y: float, r: float = 0.05, h: float = 0.10, n: int = 800) -> ObjectEstimate:
    return ObjectEstimate(arm, np.array([x, y, h / 2]), r, h, n, 0.8)


def result(arm: str, e: ObjectEstimate | None, reason: str = "", detail: str = "") -> LocalisationResult:
    return LocalisationResult(arm, e, reason, detail)


class Reobserver:
    """Scripted re-observations: each arm returns a fixed estimate; records who looked where."""

    def __init__(self, answers: dict[str, ObjectEstimate | None]) -> None:
        self.answers = answers
        self.calls: list[tuple[str, tuple[float, float]]] = []

    def __call__(self, arm: str, hint: ObjectEstimate) -> ObjectEstimate | None:
        self.calls.append((arm, (float(hint.centre_m[0]), float(hint.centre_m[1]))))
        return self.answers[arm]


def test_consistent_estimates_are_combined_conservatively() -> None:
    a, b = est("arm110", 0.10, 0.00, r=0.05, h=0.10), est("arm111", 0.12, 0.00, r=0.06, h=0.09)
    d = decide(result("arm110", a), result("arm111", b))
    assert d.status == "consistent" and d.reason == "combined"
    np.testing.assert_allclose(d.estimate.centre_m[:2], [0.11, 0.0])
    assert d.estimate.radius_m == pytest.approx(0.06 + 0.01)  # larger radius, grown by half the gap
    assert d.estimate.height_m == pytest.approx(0.10)
    assert d.estimate.centre_m[2] == pytest.approx(0.05)
    assert d.steps[1]["consistent"] and d.steps[1]["centre_distance_m"] == pytest.approx(0.02)
    # the combined cylinder contains both arms' cylinders
    for e in (a, b):
        gap = np.linalg.norm(d.estimate.centre_m[:2] - e.centre_m[:2])
        assert gap + e.radius_m <= d.estimate.radius_m + 1e-12


def test_tolerance_grows_with_size() -> None:
    s = ConfirmSettings(centre_tolerance_m=0.04, centre_tolerance_rel=0.5)
    small = consistency(est("arm110", 0.0, 0.0, r=0.04), est("arm111", 0.05, 0.0, r=0.04), s)
    large = consistency(est("arm110", 0.0, 0.0, r=0.12), est("arm111", 0.05, 0.0, r=0.12), s)
    assert not small["consistent"] and small["centre_tolerance_m"] == pytest.approx(0.04)
    assert large["consistent"] and large["centre_tolerance_m"] == pytest.approx(0.06)
    tall = consistency(est("arm110", 0.0, 0.0, h=0.10), est("arm111", 0.0, 0.0, h=0.15), s)
    assert not tall["consistent"]  # heights differ by 5 cm > max(3 cm, 30 % of 15 cm)


def test_conflict_terminates_without_averaging_under_the_terminate_policy() -> None:
    a, b = est("arm110", 0.0, 0.0), est("arm111", 0.12, 0.0)
    spy = Reobserver({"arm110": a, "arm111": b})
    d = decide(result("arm110", a), result("arm111", b), ConfirmSettings(conflict_policy="terminate"), spy)
    assert d.status == "terminated" and d.reason == "conflict" and d.estimate is None
    assert "not averaged" in d.message and "12.0 cm" in d.message
    assert spy.calls == []


def test_conflict_falls_back_to_the_estimate_both_arms_reconfirm() -> None:
    a, b = est("arm110", 0.0, 0.0), est("arm111", 0.12, 0.0)  # b was a fluke
    spy = Reobserver({"arm110": est("arm110", 0.005, 0.0), "arm111": est("arm111", -0.004, 0.002)})
    d = decide(result("arm110", a), result("arm111", b), reobserve=spy)
    assert d.status == "fallback" and d.reason == "reconfirmed_primary"
    assert np.linalg.norm(d.estimate.centre_m[:2]) < 0.005
    # each arm looked straight at the other's estimate
    assert spy.calls == [("arm110", (0.12, 0.0)), ("arm111", (0.0, 0.0))]
    assert d.steps[-1]["step"] == "reobserve" and d.steps[-1]["votes"]["d"]["vs_a"]["consistent"]


def test_conflict_can_fall_back_to_the_second_arm() -> None:
    a, b = est("arm110", 0.0, 0.0), est("arm111", 0.12, 0.0)  # a was the fluke
    spy = Reobserver({"arm110": est("arm110", 0.118, 0.0), "arm111": est("arm111", 0.121, 0.0)})
    d = decide(result("arm110", a), result("arm111", b), reobserve=spy)
    assert d.status == "fallback" and d.reason == "reconfirmed_secondary"
    assert d.estimate.centre_m[0] == pytest.approx(0.119, abs=1e-9)  # b combined with c


def test_each_arm_reconfirming_itself_is_a_systematic_conflict() -> None:
    a, b = est("arm110", 0.0, 0.0), est("arm111", 0.12, 0.0)
    spy = Reobserver({"arm110": est("arm110", 0.002, 0.0), "arm111": est("arm111", 0.119, 0.0)})
    d = decide(result("arm110", a), result("arm111", b), reobserve=spy)
    assert d.status == "terminated" and d.reason == "conflict"
    assert "each re-confirms its own" in d.message


def test_unhelpful_reobservation_terminates() -> None:
    a, b = est("arm110", 0.0, 0.0), est("arm111", 0.12, 0.0)
    d = decide(result("arm110", a), result("arm111", b), reobserve=Reobserver({"arm110": None, "arm111": None}))
    assert d.status == "terminated" and d.reason == "conflict" and "supports neither" in d.message


def test_single_valid_estimate_is_a_reference_only_with_enough_support() -> None:
    a = est("arm110", 0.02, 0.03, n=900)
    miss = result("arm111", None, "few_points", "only 40 depth points")
    d = decide(result("arm110", a), miss)
    assert d.status == "fallback" and d.reason == "single_estimate" and d.estimate is a
    assert "few_points" in d.message
    weak = decide(result("arm110", est("arm110", 0.02, 0.03, n=100)), miss)
    assert weak.status == "terminated" and weak.reason == "unconfirmed"
    # the other way round too
    d2 = decide(result("arm110", None, "truncated", "cut"), result("arm111", est("arm111", 0.0, 0.0, n=900)))
    assert d2.status == "fallback" and d2.estimate.arm_id == "arm111"


def test_no_estimate_terminates_with_the_searching_arms_reason() -> None:
    d = decide(result("arm110", None, "outside_workspace", "object at (0.0, 0.36) m is outside the workspace"),
               result("arm111", None, "skipped", "not tried"))
    assert d.status == "terminated" and d.reason == "outside_workspace"
    assert "outside the workspace" in d.message
    empty = decide(result("arm110", None, "no_object", "the search found no object"),
                   result("arm111", None, "no_object", "nothing"))
    assert empty.reason == "no_object" and empty.estimate is None


def test_record_is_json_ready_and_settings_are_validated() -> None:
    import json

    a, b = est("arm110", 0.0, 0.0), est("arm111", 0.01, 0.0)
    record = decide(result("arm110", a), result("arm111", b)).to_record()
    assert json.loads(json.dumps(record))["status"] == "consistent"
    with pytest.raises(AcquisitionError, match="conflict_policy"):
        ConfirmSettings(conflict_policy="average")
    assert combine(a, a).arm_id == "arm110"


def test_thresholds_follow_the_calibrations_stated_uncertainty() -> None:
    """The issue's case: estimates 42 mm apart on a large object were "consistent" under the configured
    tolerance (max(40 mm, 0.5 r)); a calibration stating sub-millimetre residuals makes them conflict."""
    from darp.acquisition.confirm import arm_uncertainty_m, consistent, settings_from_calibration

    residuals = {"hand_eye_std": {"rotation_deg": [0.02, 0.02, 0.01], "translation_mm": [0.3, 0.2, 0.4]},
                 "heldout": {"corner_3d_mm": {"n": 900, "p90": 0.6}, "reprojection_px": {"n": 900, "p90": 0.2}}}
    u = arm_uncertainty_m(residuals)
    assert u is not None and 0.0007 < u < 0.001  # 0.54 mm, 0.21 mm (0.03 deg at 0.4 m), 0.6 mm: quadrature
    base = ConfirmSettings()
    derived, how = settings_from_calibration(base, {"arm110": residuals, "arm111": residuals})
    assert how["source"] == "calibration" and derived.centre_tolerance_m < 0.025
    a = ObjectEstimate("arm110", np.array([0.0, 0.0, 0.05]), 0.09, 0.10, 2000, 0.9)
    b = ObjectEstimate("arm111", np.array([0.042, 0.0, 0.05]), 0.09, 0.10, 2000, 0.9)
    assert consistent(a, b, base) and not consistent(a, b, derived)
    near = ObjectEstimate("arm111", np.array([0.012, 0.0, 0.05]), 0.09, 0.10, 2000, 0.9)
    assert consistent(a, near, derived)  # the estimators' own spread still passes
    # no stated uncertainty (a nominal calibration): the configured thresholds
    same, how = settings_from_calibration(base, {"arm110": {}, "arm111": residuals})
    assert same is base and how["source"] == "configured"


def test_a_partial_view_inside_the_other_estimate_is_consistent_but_a_shift_of_the_same_size_is_not() -> None:
    """The twin's L-shape (campaign seed 1200): arm110 saw the whole L (r 7.8 cm), arm111 one leg (r 3.5 cm,
    centre 4.8 cm off): the leg lies inside the L's footprint, so the arms agree; two whole-object estimates
    as far apart (a calibration fault) still disagree, and so does a small estimate reaching outside."""
    whole, leg = est("arm110", -0.108, 0.025, r=0.078, h=0.12), est("arm111", -0.062, 0.041, r=0.035, h=0.12)
    check = consistency(whole, leg, ConfirmSettings())
    assert check["contained"] and check["consistent"] and check["centre_distance_m"] > check["centre_tolerance_m"]
    d = decide(result("arm110", whole), result("arm111", leg))
    assert d.status == "consistent" and "partial view" in d.message
    combined = d.estimate
    for e in (whole, leg):  # the combined envelope holds both footprints
        gap = np.linalg.norm(np.asarray(combined.centre_m)[:2] - np.asarray(e.centre_m)[:2])
        assert gap + e.radius_m <= combined.radius_m + 1e-9
    # ... and is the whole L's, not grown by half the gap (a wider envelope sends the views further away)
    np.testing.assert_allclose(combined.centre_m[:2], whole.centre_m[:2])
    gap = float(np.linalg.norm(np.asarray(whole.centre_m)[:2] - np.asarray(leg.centre_m)[:2]))
    assert combined.radius_m == pytest.approx(max(whole.radius_m, gap + leg.radius_m))  # 8.4 cm, not 10.2
    shifted = est("arm111", -0.108 + 0.048, 0.025, r=0.078, h=0.12)  # the whole L, 4.8 cm off
    assert not consistency(whole, shifted, ConfirmSettings())["consistent"]
    outside = est("arm111", -0.108 + 0.09, 0.025, r=0.035, h=0.12)  # a small estimate reaching 4.7 cm out
    assert not consistency(whole, outside, ConfirmSettings())["consistent"]
