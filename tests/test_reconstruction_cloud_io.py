"""PLY reading and writing: round trips, other writers' files (Open3D, trimesh, ascii), bad files."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from darp.errors import FormatError
from darp.reconstruction.cloud_io import read_mesh_ply, read_ply, write_cloud_ply, write_mesh_ply


@pytest.fixture()
def cloud() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3)).astype(np.float32)
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    rgb = rng.integers(0, 256, size=(500, 3)).astype(np.uint8)
    return pts, nrm, rgb


def test_cloud_round_trip_with_fields(tmp_path, cloud) -> None:
    pts, nrm, rgb = cloud
    frames = np.arange(500, dtype=np.int32)
    path = write_cloud_ply(tmp_path / "c.ply", pts, normals=nrm, colours=rgb, fields={"n_frames": frames},
                           comments=["hello"])
    ply = read_ply(path)
    np.testing.assert_array_equal(ply.points, pts)
    np.testing.assert_allclose(ply.normals, nrm, atol=1e-7)
    np.testing.assert_array_equal(ply.colours, rgb)
    np.testing.assert_array_equal(ply.vertex["n_frames"], frames)
    assert ply.triangles is None and "hello" in ply.comments
    # Open3D reads it too (the oracle for the header and byte layout)
    theirs = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(theirs.points), pts, atol=1e-7)
    np.testing.assert_allclose(np.asarray(theirs.colors), rgb / 255.0, atol=1e-6)
    assert not list(tmp_path.glob("*.partial"))


def test_reads_open3d_trimesh_and_ascii_files(tmp_path, cloud) -> None:
    pts, nrm, _ = cloud
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    pc.normals = o3d.utility.Vector3dVector(nrm.astype(np.float64))
    o3d.io.write_point_cloud(str(tmp_path / "o3d.ply"), pc)
    ply = read_ply(tmp_path / "o3d.ply")
    np.testing.assert_allclose(ply.points, pts, atol=1e-6)
    np.testing.assert_allclose(ply.normals, nrm, atol=1e-6)

    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    (tmp_path / "tm.ply").write_bytes(box.export(file_type="ply", encoding="binary"))
    v, t = read_mesh_ply(tmp_path / "tm.ply")
    np.testing.assert_allclose(v, box.vertices, atol=1e-6)
    np.testing.assert_array_equal(t, box.faces)

    (tmp_path / "a.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    v, t = read_mesh_ply(tmp_path / "a.ply")
    np.testing.assert_array_equal(v, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(t, [[0, 1, 2]])


def test_bad_files_name_the_problem(tmp_path, cloud) -> None:
    pts, _, _ = cloud
    path = write_mesh_ply(tmp_path / "m.ply", pts[:3], np.array([[0, 1, 2]]))
    data = path.read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-5])
    with pytest.raises(FormatError, match="file ends inside element 'face'"):
        read_ply(tmp_path / "cut.ply")
    (tmp_path / "no.ply").write_text("hello\n")
    with pytest.raises(FormatError, match="not a PLY file"):
        read_ply(tmp_path / "no.ply")
    with pytest.raises(FormatError, match="no faces"):
        read_mesh_ply(write_cloud_ply(tmp_path / "c.ply", pts))
    with pytest.raises(FormatError, match="indices below 3"):
        write_mesh_ply(tmp_path / "bad.ply", pts[:3], np.array([[0, 1, 5]]))
    with pytest.raises(FormatError, match="normals must be"):
        write_cloud_ply(tmp_path / "bad2.ply", pts, normals=pts[:4])
    with pytest.raises(FormatError, match="no such file"):
        read_ply(tmp_path / "missing.ply")
    assert not (tmp_path / "bad.ply").exists()
