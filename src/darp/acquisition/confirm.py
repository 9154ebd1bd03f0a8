"""Cross-arm confirmation: combine the two arms' object estimates, or fall back, or terminate.

The searching arm's estimate A is an initial hypothesis; the other arm, looking straight at A while
the first is parked, gives B. :func:`decide` applies these rules, in order, and records every step:

1. **Consistent** (:func:`consistent`): the centres lie within ``max(centre_tolerance_m,
   centre_tolerance_rel * larger radius)`` of each other, or the smaller footprint lies inside the larger
   one up to ``centre_tolerance_m`` (a partial view of a non-convex object), and the heights within
   ``max(height_tolerance_m, height_tolerance_rel * larger height)``. They are **combined**
   (:func:`combine`): centres averaged, the larger radius kept and grown by half the centre distance (so
   the combined cylinder still contains both arms' cylinders' axes), the larger height kept: a
   conservative envelope. A partial view keeps the larger footprint, grown only to hold the smaller one.
2. **One valid estimate** (the other arm saw nothing usable even when looking straight at it): the
   valid one is the reference if its depth support is at least ``fallback_min_points``; otherwise
   the survey terminates (``unconfirmed``).
3. **Conflicting** (both valid, not consistent): never averaged. With ``conflict_policy="reobserve"``
   each arm looks again, straight at the *other* arm's estimate (C: the searching arm at B; D: the
   other arm at A). An estimate that both arms now support is the reference (**fallback**: A when
   C and D agree with A, B when both agree with B), combined with the re-observation that
   re-confirmed it. When each arm re-confirms its own estimate the disagreement is systematic (a
   calibration or encoder fault that two arms cannot resolve) and the survey terminates
   (``conflict``); so it does when the re-observations are invalid or agree with neither.
   ``conflict_policy="terminate"`` terminates at once.
4. **Neither valid**: terminate with the searching arm's reason (``no_object``, ``outside_workspace``...).

**Thresholds from the calibration** (:func:`settings_from_calibration`). A calibration that states its
uncertainty (``residuals``: the hand-eye and base standard deviations, held-out errors in mm) gives a
per-arm position uncertainty u at the viewing distance; the two arms' estimates may then differ by
about ``3 * sqrt(u1^2 + u2^2)`` plus the estimators' own spread (``estimate_spread_m``), so the centre
tolerance becomes ``max(that, centre_floor_rel * radius)``, never more than the configured one. A
calibration without stated uncertainty (the nominal one) keeps the configured thresholds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from darp.acquisition.localise import LocalisationResult, ObjectEstimate
from darp.errors import AcquisitionError

CONFLICT_POLICIES = ("reobserve", "terminate")

Reobserve = Callable[[str, ObjectEstimate], "ObjectEstimate | None"]
"""``reobserve(arm_id, hint)``: the arm looks straight at ``hint`` and returns its estimate (or None)."""


@dataclass(frozen=True)
class ConfirmSettings:
    """Thresholds of cross-arm confirmation."""

    centre_tolerance_m: float = 0.04
    centre_tolerance_rel: float = 0.5  # times the larger radius
    height_tolerance_m: float = 0.03
    height_tolerance_rel: float = 0.3  # times the larger height
    fallback_min_points: int = 300
    conflict_policy: str = "reobserve"

    def __post_init__(self) -> None:
        if self.conflict_policy not in CONFLICT_POLICIES:
            raise AcquisitionError(f"conflict_policy must be one of {', '.join(CONFLICT_POLICIES)}, "
                                   f"got {self.conflict_policy!r}")
        if not (self.centre_tolerance_m > 0 and self.height_tolerance_m > 0):
            raise AcquisitionError("confirmation tolerances must be positive")


def _norm(values: Any) -> float:
    try:
        arr = np.asarray(values, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        return 0.0
    return float(np.linalg.norm(arr[np.isfinite(arr)])) if arr.size else 0.0


def arm_uncertainty_m(residuals: dict[str, Any], distance_m: float = 0.4) -> float | None:
    """A calibration's stated position uncertainty (m) of one arm at ``distance_m`` from its camera: the
    hand-eye and base standard deviations (translation, and rotation times the distance) and the held-out
    errors in mm (their p90), added in quadrature; None when the residuals state none."""
    terms: list[float] = []
    for key in ("hand_eye_std", "base_std"):
        std = residuals.get(key)
        if isinstance(std, dict):
            terms.append(_norm(std.get("translation_mm", [])) / 1e3)
            terms.append(np.radians(_norm(std.get("rotation_deg", []))) * distance_m)
    heldout = residuals.get("heldout")
    if isinstance(heldout, dict):
        for name, stats in heldout.items():
            if "mm" in str(name) and isinstance(stats, dict) and stats.get("n", 1):
                value = stats.get("p90", stats.get("rms"))
                terms.append(float(value) / 1e3 if isinstance(value, (int, float)) else 0.0)
    terms = [t for t in terms if np.isfinite(t) and t > 0]
    return float(np.sqrt(np.sum(np.square(terms)))) if terms else None


def settings_from_calibration(base: ConfirmSettings, residuals_by_arm: dict[str, dict[str, Any]],
                              estimate_spread_m: float = 0.02,
                              centre_floor_rel: float = 0.2) -> tuple[ConfirmSettings, dict[str, Any]]:
    """Confirmation thresholds from the calibration's stated uncertainty (see the module docstring); returns
    the settings and a record of how they were derived."""
    u = {arm: arm_uncertainty_m(res) for arm, res in residuals_by_arm.items()}
    if not u or any(v is None for v in u.values()):
        return base, {"source": "configured", "uncertainty_m": u}
    combined = float(np.sqrt(sum(v * v for v in u.values() if v is not None)))
    tol = min(base.centre_tolerance_m, 3.0 * combined + estimate_spread_m)
    derived = ConfirmSettings(centre_tolerance_m=tol, centre_tolerance_rel=min(base.centre_tolerance_rel,
                                                                               centre_floor_rel),
                              height_tolerance_m=base.height_tolerance_m,
                              height_tolerance_rel=base.height_tolerance_rel,
                              fallback_min_points=base.fallback_min_points, conflict_policy=base.conflict_policy)
    return derived, {"source": "calibration", "uncertainty_m": {a: round(v or 0.0, 5) for a, v in u.items()},
                     "combined_m": round(combined, 5), "centre_tolerance_m": round(tol, 5),
                     "centre_tolerance_rel": derived.centre_tolerance_rel}


@dataclass
class Decision:
    """The confirmed envelope (None when terminated), the rule that decided, and the record."""

    status: str  # consistent | fallback | terminated
    estimate: ObjectEstimate | None
    reason: str  # a code: combined, single_estimate, reconfirmed_primary, conflict, no_object, ...
    message: str
    steps: list[dict[str, Any]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.estimate is not None

    def to_record(self) -> dict[str, Any]:
        return {"status": self.status, "reason": self.reason, "message": self.message,
                "estimate": None if self.estimate is None else self.estimate.to_record(), "steps": self.steps}


def consistency(a: ObjectEstimate, b: ObjectEstimate, settings: ConfirmSettings) -> dict[str, Any]:
    """Centre distance and height difference against their tolerances (a record; ``consistent`` key).

    The centres agree when they lie within the centre tolerance, or when the smaller estimate's footprint
    lies inside the larger one's, up to the absolute tolerance (``contained``): an arm that sees only part of
    a non-convex object (one leg of an L, the other hidden behind it) estimates a smaller cylinder off the
    whole object's centre. Two estimates of about the same size are held to the centre rule either way."""
    d = float(np.linalg.norm(np.asarray(a.centre_m)[:2] - np.asarray(b.centre_m)[:2]))
    dh = abs(a.height_m - b.height_m)
    tol_c = max(settings.centre_tolerance_m, settings.centre_tolerance_rel * max(a.radius_m, b.radius_m))
    tol_h = max(settings.height_tolerance_m, settings.height_tolerance_rel * max(a.height_m, b.height_m))
    small, large = sorted((a.radius_m, b.radius_m))
    contained = d > tol_c and d + small <= large + settings.centre_tolerance_m
    return {"centre_distance_m": round(d, 5), "centre_tolerance_m": round(tol_c, 5),
            "height_difference_m": round(dh, 5), "height_tolerance_m": round(tol_h, 5),
            "contained": bool(contained), "consistent": bool((d <= tol_c or contained) and dh <= tol_h)}


def consistent(a: ObjectEstimate, b: ObjectEstimate, settings: ConfirmSettings) -> bool:
    """True when two estimates agree within the tolerances."""
    return bool(consistency(a, b, settings)["consistent"])


def combine(a: ObjectEstimate, b: ObjectEstimate, stage: str = "confirmed", contained: bool = False) -> ObjectEstimate:
    """The conservative envelope of two consistent estimates (centres averaged, larger extents). With
    ``contained`` (the smaller footprint inside the larger one: a partial view) it is the larger footprint,
    grown only as far as it must to hold the smaller one: averaging there would move the centre towards the
    part one arm saw and grow the radius for nothing, and a wider envelope sends the views further away."""
    ca, cb = np.asarray(a.centre_m, float), np.asarray(b.centre_m, float)
    d = float(np.linalg.norm(ca[:2] - cb[:2]))
    height = max(a.height_m, b.height_m)
    table_z = float(ca[2] - 0.5 * a.height_m)
    if contained:
        large, small = (a, b) if a.radius_m >= b.radius_m else (b, a)
        cl = np.asarray(large.centre_m, float)
        centre = np.array([cl[0], cl[1], table_z + 0.5 * height])
        radius = max(large.radius_m, d + small.radius_m)
    else:
        centre = np.array([0.5 * (ca[0] + cb[0]), 0.5 * (ca[1] + cb[1]), table_z + 0.5 * height])
        radius = max(a.radius_m, b.radius_m) + 0.5 * d
    arms = a.arm_id if a.arm_id == b.arm_id else f"{a.arm_id}+{b.arm_id}"
    return ObjectEstimate(arms, centre, radius, height, a.n_points + b.n_points,
                          min(a.valid_fraction, b.valid_fraction), stage=stage)


def _estimate_record(est: ObjectEstimate | None) -> dict[str, Any] | None:
    return None if est is None else est.to_record()


def decide(primary: LocalisationResult, secondary: LocalisationResult, settings: ConfirmSettings | None = None,
           reobserve: Reobserve | None = None) -> Decision:
    """Apply the confirmation rules (module docstring) to the two arms' localisation results."""
    s = settings if settings is not None else ConfirmSettings()
    a, b = primary.estimate, secondary.estimate
    steps: list[dict[str, Any]] = [{"step": "estimates", "primary": primary.arm_id, "secondary": secondary.arm_id,
                                    "a": _estimate_record(a), "b": _estimate_record(b),
                                    "primary_reason": primary.reason, "secondary_reason": secondary.reason}]
    if a is None and b is None:
        reason = primary.reason or secondary.reason or "no_object"
        detail = primary.detail or secondary.detail or "no arm found the object"
        return Decision("terminated", None, reason, f"localisation failed: {detail}", steps)
    if a is None or b is None:
        valid, failed = (a, secondary) if b is None else (b, primary)
        assert valid is not None
        ok = valid.n_points >= s.fallback_min_points
        steps.append({"step": "single_estimate", "arm": valid.arm_id, "n_points": valid.n_points,
                      "required_points": s.fallback_min_points, "other_reason": failed.reason, "accepted": ok})
        if ok:
            return Decision("fallback", valid, "single_estimate",
                            f"only {valid.arm_id} has a valid estimate ({failed.arm_id}: {failed.reason or 'none'}: "
                            f"{failed.detail}); it has {valid.n_points} depth points and is used as the reference",
                            steps)
        return Decision("terminated", None, "unconfirmed",
                        f"only {valid.arm_id} has a valid estimate, with too little depth support "
                        f"({valid.n_points} points, {s.fallback_min_points} needed); {failed.arm_id}: "
                        f"{failed.reason or 'none'}", steps)
    check = consistency(a, b, s)
    steps.append({"step": "consistency", **check})
    if check["consistent"]:
        how = (f"centres {check['centre_distance_m'] * 100:.1f} cm apart, tolerance "
               f"{check['centre_tolerance_m'] * 100:.1f} cm): centres averaged, larger extents kept"
               if not check["contained"] else
               f"the smaller estimate lies inside the larger one: a partial view; centres "
               f"{check['centre_distance_m'] * 100:.1f} cm apart): the larger footprint kept, grown to hold both")
        return Decision("consistent", combine(a, b, contained=check["contained"]), "combined",
                        f"{a.arm_id} and {b.arm_id} agree ({how}", steps)
    gap = (f"centres {check['centre_distance_m'] * 100:.1f} cm apart "
           f"(tolerance {check['centre_tolerance_m'] * 100:.1f} cm)")
    if s.conflict_policy == "terminate" or reobserve is None:
        return Decision("terminated", None, "conflict", f"{a.arm_id} and {b.arm_id} disagree: {gap}; "
                        "conflicting estimates are not averaged", steps)
    c = reobserve(a.arm_id, b)  # the searching arm, straight at the other's estimate
    d = reobserve(b.arm_id, a)  # the other arm, straight at the searching arm's estimate
    votes = {}
    for name, est in (("c", c), ("d", d)):
        votes[name] = None if est is None else {"vs_a": consistency(est, a, s), "vs_b": consistency(est, b, s)}
    steps.append({"step": "reobserve", "c": _estimate_record(c), "d": _estimate_record(d), "votes": votes})

    def agrees(est: ObjectEstimate | None, ref: ObjectEstimate) -> bool:
        return est is not None and consistent(est, ref, s)

    if agrees(c, a) and agrees(d, a):
        assert d is not None
        return Decision("fallback", combine(a, d, "reconfirmed"), "reconfirmed_primary",
                        f"{a.arm_id} and {b.arm_id} disagreed ({gap}); looking again, both arms support "
                        f"{a.arm_id}'s estimate, which is the reference", steps)
    if agrees(c, b) and agrees(d, b):
        assert c is not None
        return Decision("fallback", combine(b, c, "reconfirmed"), "reconfirmed_secondary",
                        f"{a.arm_id} and {b.arm_id} disagreed ({gap}); looking again, both arms support "
                        f"{b.arm_id}'s estimate, which is the reference", steps)
    if agrees(c, a) and agrees(d, b):
        return Decision("terminated", None, "conflict",
                        f"{a.arm_id} and {b.arm_id} disagree ({gap}) and each re-confirms its own estimate: a "
                        "systematic disagreement (calibration or encoder fault?) that two arms cannot resolve", steps)
    return Decision("terminated", None, "conflict",
                    f"{a.arm_id} and {b.arm_id} disagree ({gap}) and re-observation supports neither estimate", steps)


__all__ = ["CONFLICT_POLICIES", "ConfirmSettings", "Decision", "Reobserve", "combine", "consistency", "consistent",
           "decide"]
