"""Ground-truth metrics on constructed cases with known answers: a box and offset/partial reconstructions."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from darp.errors import EvaluationError
from darp.evaluation.point_to_mesh import MeshDistance
from darp.evaluation.truth_metrics import sample_surface, truth_metrics, visible_in_frames
from darp.reconstruction.backproject import PosedDepth
from helpers.synthetic_depth import Scene, box, look_at, small_intrinsics, table

EXTENTS = np.array([0.06, 0.04, 0.08])  # box centred at the origin: faces 24, 48, 32 cm^2 (x2)


@pytest.fixture(scope="module")
def truth() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=EXTENTS)


def test_samples_lie_on_the_surface_uniformly_by_area(truth: trimesh.Trimesh) -> None:
    pts, normals = sample_surface(truth.vertices, truth.faces, np.random.default_rng(0), spacing_m=0.0005)
    area = 2 * (EXTENTS[0] * EXTENTS[1] + EXTENTS[0] * EXTENTS[2] + EXTENTS[1] * EXTENTS[2])
    assert len(pts) == int(np.ceil(area / 0.0005**2))
    assert MeshDistance(truth.vertices, truth.faces).distances(pts).max() < 1e-7
    on_top = np.abs(pts[:, 2] - EXTENTS[2] / 2) < 1e-9
    assert np.mean(on_top) == pytest.approx(EXTENTS[0] * EXTENTS[1] / area, abs=0.01)
    np.testing.assert_allclose(normals[on_top], np.tile([0.0, 0.0, 1.0], (on_top.sum(), 1)), atol=1e-9)
    again, _ = sample_surface(truth.vertices, truth.faces, np.random.default_rng(0), spacing_m=0.0005)
    np.testing.assert_array_equal(again, pts)
    with pytest.raises(EvaluationError, match="count or a positive"):
        sample_surface(truth.vertices, truth.faces, np.random.default_rng(0))


def test_offset_reconstruction_has_known_accuracy_and_fscore(truth: trimesh.Trimesh) -> None:
    rng = np.random.default_rng(1)
    samples, _ = sample_surface(truth.vertices, truth.faces, rng, spacing_m=0.0007)
    recon, recon_normals = sample_surface(truth.vertices, truth.faces, rng, spacing_m=0.0007)
    top = recon_normals[:, 2] > 0.5
    moved = recon.copy()
    moved[top] += 0.003 * recon_normals[top]  # the top face measured 3 mm too high, the rest exact
    m = truth_metrics(moved, truth.vertices, truth.faces, samples, thresholds_m=(0.001, 0.005))
    share_top = EXTENTS[0] * EXTENTS[1] / (truth.area)
    # accuracy: exact points at 0, lifted ones at exactly 3 mm
    assert m.cloud.accuracy.max_m == pytest.approx(0.003, abs=1e-7)
    assert m.cloud.precision_pct(0.001) == pytest.approx(100 * (1 - share_top), abs=1.0)
    assert m.cloud.precision_pct(0.005) == pytest.approx(100.0)
    # completeness: the top face is 3 mm from the nearest reconstructed point, the rest within 1 mm
    assert m.cloud.completeness_pct(0.001) == pytest.approx(100 * (1 - share_top), abs=1.5)
    assert m.cloud.completeness_pct(0.005) == pytest.approx(100.0)
    p, r = m.cloud.precision_pct(0.001), m.cloud.completeness_pct(0.001)
    assert m.cloud.fscore_pct(0.001) == pytest.approx(2 * p * r / (p + r))
    assert m.n_samples == len(samples) and m.n_seen == len(samples)


def test_completeness_counts_only_the_seen_surface(truth: trimesh.Trimesh) -> None:
    rng = np.random.default_rng(2)
    samples, normals = sample_surface(truth.vertices, truth.faces, rng, spacing_m=0.0007)
    recon, recon_normals = sample_surface(truth.vertices, truth.faces, rng, spacing_m=0.0007)
    recon = recon[recon_normals[:, 0] > 0.5]  # only the +x face was reconstructed
    everything = truth_metrics(recon, truth.vertices, truth.faces, samples, thresholds_m=(0.002,))
    # the +x face plus a 2 mm band of the four faces around it
    reached = EXTENTS[1] * EXTENTS[2] + 2 * (EXTENTS[1] + EXTENTS[2]) * 0.002
    assert everything.cloud.completeness_pct(0.002) == pytest.approx(100 * reached / truth.area, abs=1.0)
    seen = normals[:, 0] > 0.5
    only_seen = truth_metrics(recon, truth.vertices, truth.faces, samples, seen, thresholds_m=(0.002,),
                              mesh=(truth.vertices, truth.faces))
    assert only_seen.cloud.completeness_pct(0.002) == pytest.approx(100.0)
    assert only_seen.n_seen == seen.sum()
    # a perfect mesh: zero accuracy error, every seen sample on it
    assert only_seen.mesh.accuracy.max_m < 1e-6
    assert only_seen.mesh.completeness_pct(0.002) == pytest.approx(100.0)
    with pytest.raises(EvaluationError, match="one entry per"):
        truth_metrics(recon, truth.vertices, truth.faces, samples, seen[:5])


def test_visibility_from_depth_frames() -> None:
    intr = small_intrinsics(160, 120, 190.0)
    block = box((0.06, 0.04, 0.08), (-0.03, -0.02, 0.0))
    scene = Scene([block, table()])
    T = look_at((0.0, 0.0, 0.5), (0.0, 0.0, 0.08), up=(0.0, 1.0, 0.0))  # straight down
    depth, _ = scene.render(T, intr)
    frame = PosedDepth("arm110", 0, depth, 1.0, intr, T)
    v, t = np.asarray(block.vertices), np.asarray(block.triangles)
    samples, normals = sample_surface(v, t, np.random.default_rng(0), spacing_m=0.001)
    seen = visible_in_frames(samples, [frame], normals=normals, tolerance_m=0.002)
    top = normals[:, 2] > 0.5
    assert seen[top].mean() > 0.98
    assert not seen[~top].any()  # sides are edge-on, the bottom is on the table
    # from the side, the +x face becomes visible too
    T_side = look_at((0.4, 0.0, 0.3), (0.0, 0.0, 0.04))
    side = PosedDepth("arm111", 0, scene.render(T_side, intr)[0], 1.0, intr, T_side)
    both = visible_in_frames(samples, [frame, side], normals=normals, tolerance_m=0.002)
    plus_x = normals[:, 0] > 0.5
    assert both[plus_x].mean() > 0.95 and not both[normals[:, 0] < -0.5].any()


def test_seeable_surface_is_what_some_pose_sees_first_facing_and_in_range() -> None:
    """The surface any feasible camera pose can see, on a box standing on the table: a camera on +x sees
    the +x face only (the others are at 90 deg or face away), one above sees the top, the union both; a
    second box in front hides what it covers, and a pose beyond the depth range sees nothing."""
    from darp.evaluation.truth_metrics import seeable_from_poses

    obj = trimesh.creation.box(extents=EXTENTS)
    obj.apply_translation([0.0, 0.0, EXTENTS[2] / 2])  # standing on the table (z = 0)
    pts, normals = sample_surface(obj.vertices, obj.faces, np.random.default_rng(3), spacing_m=0.002)
    centre = [0.0, 0.0, EXTENTS[2] / 2]
    side, above = look_at([0.40, 0.0, EXTENTS[2] / 2], centre), look_at([0.0, 0.0, 0.45], centre, up=(1.0, 0.0, 0.0))
    plus_x = normals[:, 0] > 0.99
    top = normals[:, 2] > 0.99

    def seeable(mesh: trimesh.Trimesh, poses: list[np.ndarray]) -> np.ndarray:
        return seeable_from_poses(pts, normals, mesh.vertices, mesh.faces, poses, table_z_m=0.0)

    np.testing.assert_array_equal(seeable(obj, [side]), plus_x)
    np.testing.assert_array_equal(seeable(obj, [above[:3]]), top)  # a 3x4 pose is enough
    np.testing.assert_array_equal(seeable(obj, [side, above]), plus_x | top)
    # a thin box between the camera and the lower half of the +x face hides that half
    wall = trimesh.creation.box(extents=[0.005, 0.2, EXTENTS[2] / 2])
    wall.apply_translation([0.2, 0.0, EXTENTS[2] / 4])
    both = trimesh.util.concatenate([obj, wall])
    hidden = seeable(both, [side])
    assert hidden[plus_x & (pts[:, 2] > 0.7 * EXTENTS[2])].all()
    assert not hidden[plus_x & (pts[:, 2] < 0.25 * EXTENTS[2])].any()
    # beyond the depth range (1.2 m) nothing counts
    assert not seeable(obj, [look_at([1.5, 0.0, EXTENTS[2] / 2], centre)]).any()
