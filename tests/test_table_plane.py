"""Per-keyframe fitted table plane crop (issue 16, ``--corrections table``).

Exact depth of a box on a table (Open3D ray casting, tests/helpers/synthetic_depth.py): the crop's floor is
put 4 mm too low (as a calibration off by that much does), so the table passes it; the fitted plane of the
view's own points removes the table and keeps the box, also when the view's pose is off by a few millimetres.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from darp.processing.settings import CorrectionSettings, ProcessSettings
from darp.reconstruction.backproject import PosedDepth, backproject
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.table_plane import TableCrop, TableSettings, fit_plane_ransac, table_region
from helpers.synthetic_depth import Scene, add_depth_noise, box, orbit_poses, small_intrinsics, table, to_z16

CENTRE = (0.0, 0.0, 0.04)
SCALE = 0.0001


@pytest.fixture(scope="module")
def view() -> tuple[np.ndarray, np.ndarray]:
    """(true pose, raw depth) of one noisy 320x240 view of a 6 x 4 x 8 cm box on a table."""
    scene = Scene([table(), box((0.06, 0.04, 0.08), (-0.03, -0.02, 0.0))])
    intr = small_intrinsics(320, 240, 192.0)
    T = orbit_poses(CENTRE, 0.35, (45,), (30,))[0]
    depth, _ = scene.render(T, intr)
    return T, to_z16(add_depth_noise(depth, np.random.default_rng(0)), SCALE)


def _frame(T: np.ndarray, depth: np.ndarray) -> PosedDepth:
    return PosedDepth("arm110", 1, depth, SCALE, small_intrinsics(320, 240, 192.0), T)


def test_plane_fit_recovers_a_tilted_plane_with_outliers() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.1, 0.1, (2000, 2))
    n = np.array([0.02, -0.03, 1.0]) / np.linalg.norm([0.02, -0.03, 1.0])
    z = (0.005 - n[0] * xy[:, 0] - n[1] * xy[:, 1]) / n[2] + rng.normal(0, 0.0005, 2000)
    pts = np.column_stack([xy, z])
    pts[:300, 2] += rng.uniform(0.01, 0.05, 300)  # an object's points in the ring
    plane = fit_plane_ransac(pts, TableSettings())
    assert plane is not None and np.degrees(np.arccos(plane.normal @ n)) < 0.2
    assert abs(plane.offset + 0.005) < 3e-4
    assert fit_plane_ransac(pts[:100], TableSettings()) is None  # too few points


@pytest.mark.parametrize("shift_mm", [0.0, 3.0])
def test_table_points_removed_box_kept(view: tuple[np.ndarray, np.ndarray], shift_mm: float) -> None:
    T_true, depth = view
    T = T_true.copy()
    T[2, 3] += shift_mm / 1000  # a pose error: the whole view (table and box) 3 mm higher
    crop = EnvelopeCrop(CENTRE, 0.05, 0.08, -0.004, 0.005, 0.003)  # floor at -1 mm: the table passes it
    frame = _frame(T, depth)
    plain = backproject(frame, None, crop).points
    region, record = table_region(frame, crop)
    assert isinstance(region, TableCrop) and record["fitted"]
    assert record["table_z_mm"] == pytest.approx(shift_mm, abs=0.5)
    kept = backproject(frame, None, region).points
    table_pts = plain[:, 2] < shift_mm / 1000 + 0.0015
    assert table_pts.sum() > 500  # the crop alone lets the table in
    assert np.sum(kept[:, 2] < shift_mm / 1000 + 0.0015) == 0  # the fitted plane keeps none of it
    box_pts = plain[:, 2] > shift_mm / 1000 + 0.006
    assert len(kept) >= 0.98 * box_pts.sum()  # and (nearly) all of the box above 6 mm


def test_no_table_in_view_keeps_the_crop(view: tuple[np.ndarray, np.ndarray]) -> None:
    T, depth = view
    crop = EnvelopeCrop(CENTRE, 0.05, 0.08, 0.3, 0.005, 0.003)  # a table height where there is nothing
    region, record = table_region(_frame(T, depth), crop)
    assert region is crop and not record["fitted"]


def test_switch_parses_and_paper_records_stay() -> None:
    assert CorrectionSettings.parse("table").applied == ("table",)
    assert "table" in CorrectionSettings.parse("all").applied
    assert "table" not in ProcessSettings().to_dict()["corrections"]  # off: absent (older fingerprints stay)
    assert ProcessSettings(corrections=CorrectionSettings(table=True)).to_dict()["corrections"]["table"] is True


@pytest.mark.slow
def test_the_switch_cuts_the_pipelines_keyframes_at_their_planes(survey_path: Path, tmp_path: Path) -> None:
    """``--corrections table`` on the tiny twin survey: most fuse keyframes get a plane, the fusion records it,
    and no fused point lies below the lowest plane plus the margin."""
    from darp.cli._app import run
    from darp.reconstruction.cloud_io import read_ply

    out = tmp_path / "p"
    assert run(["process", str(survey_path), "--truth-poses", "--corrections", "table", "-o", str(out)]) == 0
    results = json.loads((out / survey_path.name / "results.json").read_text())
    record = results["corrections"]["table"]
    assert results["corrections"]["applied"] == ["table"]
    assert record["keyframes"] > 0 and record["fitted"] >= record["keyframes"] // 2  # the rest keep the crop
    assert record["tilt_deg_median"] < 1.0 and record["rms_mm_median"] < 1.5
    cloud = read_ply(out / survey_path.name / "fused.ply")
    z = np.asarray(cloud.points if hasattr(cloud, "points") else cloud[0])[:, 2]
    assert z.min() * 1000 >= record["table_z_mm"]["min"] + record["margin_mm"] - 1.0
