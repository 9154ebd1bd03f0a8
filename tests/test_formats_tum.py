"""TUM trajectories (darp.formats.trajectories), darp's one reader and one writer: the writer's files read by an
independent reader (evo's), the reader against hand-written lines whose rotations are known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from evo.tools import file_interface
from scipy.spatial.transform import Rotation

from darp.errors import FormatError
from darp.formats.trajectories import exact, read_tum, read_tum_trajectory, write_tum


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[0, :3, :3] = np.eye(3)  # identity and a half turn: the quaternion's sign and w = 0 cases
    T[1, :3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:, :3, 3] = rng.normal(0.0, 2.0, (n, 3))
    return T


@pytest.mark.parametrize(("number", "atol"), [(exact, 1e-14), ("{:.9f}".format, 3e-9)])
def test_written_tum_is_what_evo_reads(tmp_path: Path, number, atol: float) -> None:  # type: ignore[no-untyped-def]
    T = _poses(40, 3)
    stamps = [f"{1_700_000_000.0 + k / 30.0:.6f}" for k in range(len(T))]
    path = tmp_path / "traj.tum"
    write_tum(path, stamps, T, ("# timestamp tx ty tz qx qy qz qw", "# a second comment"), number)
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(traj.timestamps, [float(s) for s in stamps])
    np.testing.assert_allclose(np.array(traj.poses_se3), T, rtol=0, atol=atol)
    assert np.all(traj.orientations_quat_wxyz[:, 0] >= 0)  # darp writes the representative with w >= 0
    assert path.read_text().splitlines()[2].split()[0] == stamps[0]  # timestamps exactly as given


def test_reader_gives_the_known_rotations_of_hand_written_lines(tmp_path: Path) -> None:
    path = tmp_path / "groundtruth.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n\n"
                    "1.5 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n"  # 90 deg about z
                    "   2.25  -1 0 0.5   1 0 0 0\n"  # 180 deg about x (w = 0)
                    "3 0 0 0 0 0 0 2\n"  # identity, not normalised
                    "# 4 a comment\n"
                    "4.0 0 0 0 0 -0.25881904510252074 0 0.9659258262890683\n")  # -30 deg about y
    stamps, T = read_tum_trajectory(path)
    assert stamps == ["1.5", "2.25", "3", "4.0"]
    c, s = np.cos(np.radians(-30)), np.sin(np.radians(-30))
    expected_R = [[[0, -1, 0], [1, 0, 0], [0, 0, 1]], np.diag([1, -1, -1]), np.eye(3),
                  [[c, 0, s], [0, 1, 0], [-s, 0, c]]]
    np.testing.assert_allclose(T[:, :3, :3], expected_R, atol=1e-15)
    np.testing.assert_array_equal(T[:, :3, 3], [[1, 2, 3], [-1, 0, 0.5], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(T[:, 3], np.tile([0.0, 0, 0, 1], (4, 1)))
    assert list(read_tum(path)) == stamps


@pytest.mark.parametrize(("text", "message"), [
    ("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n", "line 3: expected 8 values"),
    ("1.0 0 0 x 0 0 0 1\n", "line 1: not numbers"),
    ("\n1.0 0 0 0 0 0 0 0\n", "line 2: not a pose"),
    ("1.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n", "timestamp 1.0 appears twice"),
])
def test_reader_names_the_file_and_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(FormatError, match=f"bad.txt: {message}"):
        read_tum(path)
