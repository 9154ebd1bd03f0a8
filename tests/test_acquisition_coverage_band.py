"""The coverage planner's co-observed band: side samples both arms see closely (the top of an open container
is its opening, where the arms see opposite faces of its wall, so the band lies on the sides)."""

from __future__ import annotations

import numpy as np

from darp.acquisition.coverage import CoverageSettings
from darp.acquisition.coverage_plan import _greedy


def pools() -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Two arms, each with a view of the top (30 samples) and a view of the side band (10 samples)."""
    n_top, n_band = 30, 10
    top = np.r_[np.ones(n_top, bool), np.zeros(n_band, bool)]
    band = ~top
    vis = {a: np.stack([top, band]) for a in ("arm110", "arm111")}
    return vis, band


def pick(settings: CoverageSettings) -> dict[str, list[int]]:
    vis, band = pools()
    reachable = np.ones(band.size, bool)
    return _greedy(vis, vis, vis, reachable, settings, {a: set() for a in vis}, dict.fromkeys(vis, 0),
                   co_vis=vis, sides=band)


def test_the_second_arm_adds_a_view_of_the_band_the_first_one_sees() -> None:
    base = CoverageSettings(support_views=1, min_views=0, target_co_observed=0.25, min_gain=0.0, target_co_sides=0.25)
    without = pick(CoverageSettings(**{**base.__dict__, "target_co_sides": 0.0}))
    with_band = pick(base)
    # without the band the co-observed target is met on the top (both arms see it) and the band stays one arm's
    seen_band_by = [a for a, views in without.items() if 1 in views]
    assert len(seen_band_by) == 1
    # with it, both arms look at the band
    assert all(1 in views for views in with_band.values())
    assert sum(len(v) for v in with_band.values()) == sum(len(v) for v in without.values()) + 1


def test_no_band_is_asked_where_the_other_arm_cannot_see_the_sides() -> None:
    vis, band = pools()
    vis["arm111"] = vis["arm111"][:1]  # arm111 has only the top view
    picked = _greedy(vis, vis, vis, np.ones(band.size, bool),
                     CoverageSettings(support_views=1, min_views=0, min_gain=0.0, target_co_sides=0.25),
                     {a: set() for a in vis}, dict.fromkeys(vis, 0), co_vis=vis, sides=band)
    assert picked["arm110"] and 1 in picked["arm110"]  # the band is still covered, by the arm that can
    assert len(picked["arm111"]) <= 1
