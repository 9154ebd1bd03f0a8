"""Why seeable true surface is missing from the fused cloud (results.json ``truth.seeable.missing_by_cause``):
the classification on synthetic stage clouds, the fusion's kept stages, and the whole helper on the processed
tiny twin survey."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from darp.evaluation.truth_metrics import MISSING_CAUSES, missing_by_cause, sample_surface


def test_each_missing_sample_gets_the_last_stage_that_had_it() -> None:
    # eight samples 10 cm apart; sample k is lost at cause k
    samples = np.column_stack([np.arange(8) * 0.1, np.zeros(8), np.zeros(8)])
    stages = {"in_envelope": samples[5:] + [0, 0, 0.004], "supported": samples[6:] + [0, 0.003, 0],
              "after_sor": samples[7:] - [0.004, 0, 0], "fused": np.empty((0, 3))}
    k = np.arange(8)
    in_view, in_view_well, raw, measured = k >= 1, k >= 2, k >= 3, k >= 4
    out = missing_by_cause(samples, np.ones(8, bool), in_view=in_view, in_view_well=in_view_well,
                           measured=measured, measured_raw=raw, stages=stages, threshold_m=0.005)
    assert out["missing"] == 8
    assert out["count"] == dict.fromkeys(MISSING_CAUSES, 1)
    # a sample that is not missing is not counted; a 6 mm offset is beyond a 5 mm threshold
    far = {name: v + [0, 0, 0.006] for name, v in stages.items()}
    out = missing_by_cause(samples, np.arange(8) >= 4, in_view=in_view, in_view_well=in_view_well,
                           measured=measured, measured_raw=raw, stages=far, threshold_m=0.005)
    assert out["missing"] == 4 and out["count"]["crop"] == 4 and out["share_pct"]["crop"] == 100.0


def test_fusion_keeps_its_stages_on_request() -> None:
    from darp.reconstruction.backproject import FrameCloud
    from darp.reconstruction.fusion import FusionSettings, VoxelFusion

    rng = np.random.default_rng(0)
    plane = np.column_stack([rng.uniform(0, 0.05, 4000), rng.uniform(0, 0.05, 4000), np.zeros(4000)])
    ghost = np.array([[0.5, 0.5, 0.5]])
    fusion = VoxelFusion(FusionSettings(adaptive_support=False))
    for k in range(4):
        centre = np.array([0.1 * k, 0.0, 0.4])
        pts = np.vstack([plane, ghost]) if k == 0 else plane
        normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
        fusion.add_cloud("arm110", k, FrameCloud(pts.astype(np.float32), normals.astype(np.float32), None,
                                                      np.arange(len(pts)), centre))
    plain = fusion.result()
    assert plain.stages is None
    staged = fusion.result(keep_stages=True)
    assert staged.stages is not None
    s = staged.stages
    assert len(s["in_envelope"]) > len(s["supported"]) >= len(s["after_sor"])
    assert np.min(np.linalg.norm(s["in_envelope"] - ghost, axis=1)) < 1e-6  # the ghost reached the voxels
    assert np.min(np.linalg.norm(s["supported"] - ghost, axis=1)) > 0.1  # and was not supported
    np.testing.assert_array_equal(s["fused"], staged.fused.points)
    np.testing.assert_array_equal(staged.fused.points, plain.fused.points)


@pytest.mark.slow
def test_missing_causes_on_the_tiny_survey(processed_path: Path, survey_path: Path) -> None:
    from scipy.spatial import cKDTree

    from darp.processing.evaluate import missing_causes, read_truth_mesh
    from darp.processing.job import open_job, survey_calibration
    from darp.processing.settings import ProcessSettings
    from darp.reconstruction.cloud_io import read_ply

    job = open_job(survey_path, processed_path, survey_calibration(survey_path, None), settings=ProcessSettings(),
                   truth_poses=True)
    tv, tt = read_truth_mesh(survey_path / "truth" / "object.ply")
    samples, normals = sample_surface(tv, tt, np.random.default_rng(0), spacing_m=0.002)
    # declare missing the top face where the fused cloud has it (the re-fused stages must end in it) and the
    # underside away from the sides (which no camera sees: only the table was measured there, and cut)
    fused = read_ply(processed_path / "fused.ply").points
    top = (normals[:, 2] > 0.9) & (cKDTree(fused).query(samples)[0] <= 0.001)
    side = np.abs(normals[:, 2]) < 0.5
    underside = (normals[:, 2] < -0.9) & (cKDTree(samples[side]).query(samples)[0] > 0.008)
    missing = top | underside
    out = missing_causes(job, samples, normals, tv, tt, missing, 0.005)
    assert top.sum() > 100 and underside.sum() > 100
    assert out["missing"] == int(missing.sum()) and sum(out["count"].values()) == out["missing"]
    c = out["count"]
    assert c["surface_fit"] >= 0.9 * top.sum()  # the fused cloud's own surface is found in the last stage
    unseen = c["not_in_view"] + c["grazing_or_range"] + c["no_depth"] + c["depth_filter"] + c["crop"]
    assert unseen >= 0.9 * underside.sum()
    assert c["support"] + c["outlier_removal"] <= 0.05 * out["missing"]


def test_the_benchmark_row_reads_results_json() -> None:
    from helpers.script_modules import load_study

    bench = load_study("missing_by_cause")
    results = {"object": "mug", "clouds": {"fused": 1234},
               "heldout": {"aggregate": {"median_mm": 0.5, "rmse_mm": 1.0, "within_10mm_pct": 99.5}},
               "cross_arm": {"directions": [{"co_observed_pct": 12.0}, {"co_observed_pct": 9.5}]},
               "truth": {"cloud": {"accuracy": {"median_mm": 0.2, "p90_mm": 0.4}},
                         "seeable": {"completeness_pct": {"5mm": 90.0},
                                     "missing_by_cause": {"share_pct": {"support": 60.0, "outlier_removal": 40.0,
                                                                        "crop": 0.5}}}}}
    line = bench.row(results, "default")
    assert line is not None and line.startswith("| mug | default | 1,234 | 90.0 % | support 6.0, SOR 4.0 |")
    assert "12.0 / 9.5 %" in line and "crop" not in line  # 0.05 point is below the printed 0.1
    assert bench.row({"truth": None}, "x") is None
