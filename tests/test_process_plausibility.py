"""The 'almost empty reconstruction' rule of results.json's warnings (processing.diagnostics.sparse_cloud_warning)
and its setting; the batch test in test_process_robust.py sees it fire through ``darp process``."""

from __future__ import annotations

import math

import pytest

from darp.errors import ConfigError
from darp.processing.diagnostics import sparse_cloud_warning
from darp.processing.settings import EvaluationSettings, settings_from_dict

ENVELOPE = {"radius_m": 0.059, "height_m": 0.030}  # the paper profile's controller at 424x240
AREA_M2 = math.pi * 0.059**2 + 2 * math.pi * 0.059 * 0.030


def test_a_cloud_covering_less_than_the_share_is_named_with_its_numbers() -> None:
    line = sparse_cloud_warning(71, ENVELOPE, 0.0015, 2.0)
    pct = 100 * 71 * 0.0015**2 / AREA_M2
    assert line.startswith("fused cloud almost empty: 71 points at 1.5 mm voxels cover about")
    assert f"{pct:.1f} %" in line and f"({AREA_M2 * 1e4:.0f} cm^2), below 2 %" in line


def test_clouds_at_or_above_the_share_pass() -> None:
    enough = math.ceil(0.02 * AREA_M2 / 0.0015**2)
    assert sparse_cloud_warning(enough, ENVELOPE, 0.0015, 2.0) == ""
    assert sparse_cloud_warning(enough - 1, ENVELOPE, 0.0015, 2.0) != ""
    assert sparse_cloud_warning(71, ENVELOPE, 0.0015, 0.0) == ""  # 0 turns the rule off


@pytest.mark.parametrize("envelope", [{}, {"radius_m": 0.05}, {"radius_m": 0.0, "height_m": 0.1},
                                      {"radius_m": "5 cm", "height_m": 0.1}])
def test_no_rule_without_an_envelope_geometry_or_for_an_empty_cloud(envelope: dict) -> None:
    assert sparse_cloud_warning(10, envelope, 0.0015, 2.0) == ""
    assert sparse_cloud_warning(0, ENVELOPE, 0.0015, 2.0) == ""  # an empty cloud is named per arm


def test_the_share_is_a_setting_within_0_and_100_percent() -> None:
    assert EvaluationSettings().min_surface_pct == 2.0
    assert settings_from_dict({"evaluation": {"min_surface_pct": 5}}).evaluation.min_surface_pct == 5
    with pytest.raises(ConfigError, match="min_surface_pct must be within 0 .. 100, got 150"):
        EvaluationSettings(min_surface_pct=150)
