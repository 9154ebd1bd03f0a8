"""The residual-vector figure's magnification follows the residuals (a fixed x200 drew the paper profile's
3-4 px residuals as a tangle of 600 px arrows)."""

from __future__ import annotations

import math

import pytest

from darp.calibration.report import arrow_scale


@pytest.mark.parametrize("rms_px", [0.01, 0.05, 0.3, 3.5, 40.0])
def test_an_rms_residual_is_drawn_between_4_and_10_px(rms_px: float) -> None:
    scale = arrow_scale(rms_px)
    assert 4.0 <= scale * rms_px <= 10.0 + 1e-9
    mantissa = scale / 10 ** math.floor(math.log10(scale))
    assert mantissa == pytest.approx(1.0) or mantissa == pytest.approx(2.0) or mantissa == pytest.approx(5.0)


def test_the_realistic_and_paper_profiles_sizes() -> None:
    assert arrow_scale(0.05) == 200.0 and arrow_scale(3.5) == 2.0


@pytest.mark.parametrize("rms_px", [0.0, float("nan"), float("inf")])
def test_no_residuals_draw_at_natural_size(rms_px: float) -> None:
    assert arrow_scale(rms_px) == 1.0
