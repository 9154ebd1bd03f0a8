"""The measured surface of real depth (issue 28): depth statistics, depth cleaning, the support-trimmed TSDF,
``surface.method`` and benchmarks/real_fusion.py on the real 3DMatch frames."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from darp.errors import ConfigError
from darp.formats.realsense.types import Intrinsics
from darp.processing.settings import ProcessSettings, settings_from_dict
from darp.reconstruction.backproject import PosedDepth
from darp.reconstruction.depth_stats import depth_range, noise_model, survey_depth_stats
from darp.reconstruction.tsdf_surface import MeasuredSurface, SurfaceSettings, clean_depth, open_share
from helpers.realdata import needs, realdata
from helpers.script_modules import load_benchmark

REAL = realdata("3dmatch-frames")
W, H, F = 160, 120, 140.0


def plane_depth(z0: float, a: float, seed: int, tilt: float = 0.0) -> np.ndarray:
    """A fronto-parallel (or tilted along x) plane at ``z0`` with depth noise ``a z^2``, in millimetre units."""
    rng = np.random.default_rng(seed)
    u = np.arange(W)[None, :].repeat(H, 0)
    z = z0 + tilt * (u - W / 2) / F * z0
    return np.rint(1000 * (z + rng.normal(0, a * z**2, z.shape))).astype(np.uint16)


def test_noise_model_recovers_the_square_law() -> None:
    a = 0.002  # 2 mm at 1 m, 8 mm at 2 m
    frames = [(plane_depth(z0, a, s).astype(np.float32) * 1e-3, math.tan(math.radians(75)) / F)
              for s, z0 in enumerate((0.8, 1.2, 1.6, 2.0, 2.4))]
    fitted, bins = noise_model(frames, 3.0)
    assert fitted == pytest.approx(a, rel=0.1)
    assert bins[-1][1] > 3 * bins[0][1]  # noise grows with distance


def test_depth_range_cuts_a_far_minority_behind_a_gap_and_keeps_a_continuous_room() -> None:
    rng = np.random.default_rng(0)
    table = rng.uniform(0.35, 0.6, 80_000)
    floor = rng.uniform(1.3, 1.5, 20_000)  # seen through a glass table
    lo, hi, cut = depth_range(np.concatenate([table, floor]))
    assert cut and 0.6 <= hi < 1.3 and lo < 0.36
    room = rng.uniform(0.8, 3.5, 100_000)
    lo, hi, cut = depth_range(room)
    assert not cut and hi > 3.45
    lo, hi, cut = depth_range(np.concatenate([table, rng.uniform(1.3, 1.5, 60_000)]))  # far majority: kept
    assert not cut and hi > 1.45


def test_clean_depth_drops_the_near_side_of_a_step_and_keeps_the_surfaces() -> None:
    raw = np.full((H, W), 2000, np.uint16)
    raw[:, W // 2:] = 1000  # a box 1 m in front of a wall
    raw[:, W // 2] = 1500  # a flying pixel column between them
    frames = [(plane_depth(1.5, 0.001, s), 0.001, F) for s in range(3)]
    stats = survey_depth_stats(frames)
    z = clean_depth(raw, 0.001, F, stats, 0.5, 3.0, 0)
    assert np.all(z[:, W // 2] == 0)  # the flying pixel
    assert np.all(z[:, W // 2 + 1] == 0)  # the foreground edge pixel (nearer than its neighbour)
    assert np.all(z[:, W // 2 - 1] > 0)  # the background beside it stays
    assert np.count_nonzero(z) >= H * (W - 3)
    tilted = plane_depth(1.0, 0.0005, 1, tilt=1.0)  # a plane sloping 1:1 across the image: smooth, kept
    assert np.count_nonzero(clean_depth(tilted, 0.001, F, stats, 0.3, 3.0, 0)) > 0.95 * H * W


def _frame(i: int, raw: np.ndarray, T: np.ndarray) -> PosedDepth:
    return PosedDepth("arm", i, raw, 0.001, Intrinsics(W, H, F, F, W / 2, H / 2, "none", (0.0,) * 5), T)


def test_measured_surface_keeps_what_two_frames_saw_and_nothing_one_frame_saw() -> None:
    """A wall seen by three frames, a box seen by one: the wall is meshed where measured, the box is not."""
    wall = [plane_depth(1.5, 0.001, s) for s in range(3)]
    stats = survey_depth_stats([(w, 0.001, F) for w in wall])
    surface = MeasuredSurface(stats, SurfaceSettings(method="measured"))
    for i, w in enumerate(wall):
        T = np.eye(4)
        T[0, 3] = 0.02 * i
        if i == 0:
            w = w.copy()
            w[40:80, 60:100] = 1000  # a box only frame 0 measured
        surface.add(_frame(i, w, T))
    mesh, info = surface.mesh()
    V = np.asarray(mesh.vertices)
    assert info["min_frames"] == 2 and len(mesh.triangles) > 1000
    assert np.all(np.abs(V[:, 2] - 1.5) < 0.02)  # the wall only, to its noise; no box at 1 m
    # nothing beyond what the cameras saw: the wall's measured extent (x within the frames' union)
    half = 1.5 * (W / 2) / F
    assert V[:, 0].min() > -half - 0.02 and V[:, 0].max() < half + 0.06


def test_open_share_of_an_envelope() -> None:
    ang = np.linspace(-np.pi, np.pi, 4000, endpoint=False)
    zs = np.linspace(-0.049, 0.049, 50)
    side = np.array([[0.1 * np.cos(a), 0.1 * np.sin(a), z] for a in ang[ang < 0] for z in zs])  # half the side
    side_area, top_area = 2 * math.pi * 0.1 * 0.1, math.pi * 0.1**2
    expected = 100 * (0.5 * side_area + top_area) / (side_area + top_area)  # half the side and all the top open
    assert open_share(side, np.zeros(3), 0.1, 0.1, 0.005) == pytest.approx(expected, abs=3)


def test_surface_settings_are_left_out_of_records_while_default_and_checked() -> None:
    assert "surface" not in ProcessSettings().to_dict()
    assert ProcessSettings().fingerprint("fusion") == settings_from_dict({"surface": {"method": "auto"}}).fingerprint(
        "fusion")
    assert settings_from_dict({"surface": {"method": "paper"}}).to_dict()["surface"]["method"] == "paper"
    with pytest.raises(ConfigError, match="surface.*method"):
        settings_from_dict({"surface": {"method": "poisson"}})
    with pytest.raises(ConfigError, match="surface"):
        settings_from_dict({"surface": {"voxel_size_m": -1}})


def test_benchmark_scoring_is_point_to_mesh(tmp_path: Path) -> None:
    bench = load_benchmark("real_fusion")
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 0.001)
    o3d.io.write_triangle_mesh(str(tmp_path / "box.ply"), mesh)
    pts = np.column_stack([np.full(100, 0.5), np.full(100, 0.5), 0.001 + np.linspace(0.001, 0.1, 100)])
    s = bench.score(tmp_path / "box.ply", [pts])
    assert s["median_mm"] == pytest.approx(50.5, abs=0.01) and s["within_10mm_pct"] == pytest.approx(10.0)
    assert s["p90_mm"] == pytest.approx(np.percentile(np.linspace(1, 100, 100), 90), abs=0.01)


@needs(REAL)
@pytest.mark.slow
def test_real_fusion_benchmark_on_the_3dmatch_frames(tmp_path: Path) -> None:
    """darp import + darp process (default: the measured surface) and Open3D's TSDF on the same frames."""
    bench = load_benchmark("real_fusion")
    survey = bench.import_3dmatch(tmp_path / "3dmatch")
    m = bench.measure(survey, tmp_path, stride=4, peers=("vbg2",))
    assert m["surface"] == "measured" and m["heldout_frames"] == 1
    assert 0.005 < m["voxel_m"] < 0.02 and 1.0 < m["depth_range_m"][0] < m["depth_range_m"][1] < 10
    d, peer = m["darp"], m["vbg2"]
    # a room at 3 m from four frames: the held-out frame's raw points lie within about 1-2 cm of either mesh
    assert d["points"] == peer["points"] > 10_000 and d["median_mm"] < 20 and peer["median_mm"] < 20
    assert d["peak_rss_mb"] < peer["peak_rss_mb"]  # the TSDF without colour, 8^3 blocks
    rows = bench.table_rows(m, "3dmatch")
    assert {r.case.split(": ")[1] for r in rows} >= {"median_mm", "rmse_mm", "p90_mm", "cpu_s", "peak_rss_mb"}
    r = json.loads((tmp_path / "darp" / "3dmatch" / "results.json").read_text())
    assert r["surface"]["method"] == "measured" and r["surface"]["min_frames"] == 2
    assert r["surface"]["depth_stats"]["noise_sigma_at_1m_mm"] > 0
    # the vertex pass used every fuse frame of so short a survey and measured most of the vertices
    assert r["surface"]["snap"]["frames"] == 4 and r["surface"]["snap"]["vertices_measured_pct"] > 50


def test_snap_moves_vertices_to_the_noise_weighted_mean_of_the_frames() -> None:
    """A plane at z = 2 m seen from 1 m (exact) and from 2 m (4 mm too far): the near frame's measurement
    weighs (2 / 1)^4 = 16 times the far one's (sigma = a z^2), so a vertex lands 4 / 17 mm behind the plane."""
    near = np.full((H, W), 1000, np.uint16)
    far = np.full((H, W), 2004, np.uint16)
    stats = survey_depth_stats([(near, 0.001, F), (far, 0.001, F)])
    surface = MeasuredSurface(stats, SurfaceSettings(method="measured"))
    T_near, T_far = np.eye(4), np.eye(4)
    T_near[2, 3] = 1.0
    surface.add(_frame(0, near, T_near))
    surface.add(_frame(1, far, T_far))
    V = np.array([[0.0, 0.0, 2.003], [0.1, -0.05, 1.998], [5.0, 0.0, 2.0]])  # the last: outside both views
    N = np.tile([0.0, 0.0, -1.0], (3, 1))
    moved, pct = surface.snap(V, N)
    assert moved[:2, 2] == pytest.approx(2.0 + 0.004 / 17, abs=2e-5)
    assert moved[:2, :2] == pytest.approx(V[:2, :2]) and moved[2] == pytest.approx(V[2])
    assert pct == pytest.approx(100 * 2 / 3)


def test_snap_brings_a_coarse_sphere_closer_to_the_measured_depth() -> None:
    """A sphere seen from four sides with coarse voxels: the snapped mesh lies closer to it than marching cubes'."""
    r, centre = 0.3, np.array([0.0, 0.0, 1.5])
    frames = []
    for i, ang in enumerate(np.radians([-20, -7, 7, 20])):
        T = np.eye(4)
        c, s = math.cos(ang), math.sin(ang)
        T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T[:3, 3] = centre - T[:3, :3] @ np.array([0, 0, 1.5])  # every camera 1.5 m from the centre, facing it
        o = T[:3, 3] - centre
        u, v = np.meshgrid(np.arange(W), np.arange(H))
        d = np.stack([(u - W / 2) / F, (v - H / 2) / F, np.ones_like(u, float)], -1) @ T[:3, :3].T
        b = np.einsum("ijk,k->ij", d, o)
        a = np.einsum("ijk,ijk->ij", d, d)
        disc = b * b - a * (o @ o - r * r)
        t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, 0)
        frames.append(_frame(i, np.rint(1000 * t).astype(np.uint16), T))
    stats = survey_depth_stats([(f.depth, 0.001, F) for f in frames])
    errors = []
    for snap in (False, True):
        surface = MeasuredSurface(stats, SurfaceSettings(method="measured", voxel_size_m=0.02, snap=snap))
        for f in frames:
            surface.add(f)
        mesh, info = surface.mesh()
        errors.append(np.median(np.abs(np.linalg.norm(np.asarray(mesh.vertices) - centre, axis=1) - r)))
        assert ("snap" in info) == snap
    assert errors[1] < 0.5 * errors[0]
