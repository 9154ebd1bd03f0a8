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

    from darp.cli.process import _job
    from darp.processing.evaluate import missing_causes, read_truth_mesh
    from darp.processing.settings import ProcessSettings
    from darp.reconstruction.cloud_io import read_ply

    job = _job(survey_path, processed_path, None, True, ProcessSettings())
    tv, tt = read_truth_mesh(survey_path / "truth" / "object.ply")
    samples, normals = sample_surface(tv, tt, np.random.default_rng(0), spacing_m=0.002)
    fused = read_ply(processed_path / "fused.ply").points
    missing = cKDTree(fused).query(samples)[0] > 0.005
    out = missing_causes(job, samples, normals, tv, tt, missing, 0.005)
    assert out["missing"] == int(missing.sum()) > 0
    assert sum(out["count"].values()) == out["missing"]
    # the cube's underside on the table is in no keyframe's view; nothing is lost to the surface fit
    # (the fused cloud is what the re-fused stages end in)
    bottom = samples[:, 2] < tv[:, 2].min() + 1e-4
    assert out["count"]["not_in_view"] >= int((bottom & missing).sum())
    assert out["count"]["surface_fit"] == 0


def test_local_outlier_rule_keeps_a_sparse_strip_and_drops_a_stray_point() -> None:
    from darp.reconstruction.fusion import FusionSettings, statistical_outliers

    # a dense 1.5 mm grid (6 x 6 cm), a strip beside it sampled at 4.5 mm (a side seen by few frames)
    # and a stray point 6 mm above the dense part
    g = np.arange(0, 0.06, 0.0015)
    dense = np.array([(x, y, 0.0) for x in g for y in g])
    s = np.arange(0, 0.06, 0.0045)
    strip = np.array([(x, y, 0.0) for x in 0.0615 + s[:6] for y in s])
    stray = np.array([[0.03, 0.03, 0.006]])
    pts = np.vstack([dense, strip, stray])
    strip_idx = np.arange(len(dense), len(dense) + len(strip))
    global_rule = statistical_outliers(pts, 20, 2.0)
    local_rule = statistical_outliers(pts, 20, 2.0, local_ratio=2.0)
    assert global_rule[strip_idx].mean() < 0.5  # the cloud-wide rule eats most of the sparse strip
    assert local_rule[strip_idx].mean() > 0.9  # the local one keeps it
    assert not global_rule[-1] and not local_rule[-1]  # both drop the stray point
    assert np.all(local_rule >= global_rule)  # the local rule only ever spares points
    with pytest.raises(Exception, match="sor_local_ratio"):
        FusionSettings(sor_local_ratio=0.5)
