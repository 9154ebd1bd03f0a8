"""``darp recording info`` and ``darp recording export``: outputs, read-back pixels, selection, errors."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import darp.cli.recording as cli_recording
from darp.cli._app import run
from darp.errors import RecordingError
from darp.formats.realsense.recording import open_recording
from darp.formats.realsense.types import DeviceInfo, Intrinsics, StreamProfile

FIXTURES = Path(__file__).parent / "fixtures" / "recordings"
DB3 = FIXTURES / "rs259_png.db3"
BAG = FIXTURES / "rs257_lz4.bag"


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.mark.parametrize("path", [DB3, BAG], ids=["db3", "bag"])
def test_info_table(path, capsys):
    assert run(["recording", "info", str(path)]) == 0
    out = capsys.readouterr().out
    for text in ("348522076490", "Intel RealSense D435I", "5.13.0.50", "depth", "ir2", "gyro", "Brown Conrady",
                 "Inverse Brown Conrady", "Global Time", "Hardware Clock", "extrinsics depth -> stream", "-50.123"):
        assert text in out, text
    assert ("png" if path.suffix == ".db3" else "lz4") in out


@pytest.mark.parametrize("path", [DB3, BAG], ids=["db3", "bag"])
def test_info_json_agrees_with_the_reader(path, capsys):
    assert run(["recording", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["device"] == {"name": "Intel RealSense D435I", "serial": "348522076490", "firmware": "5.13.0.50",
                              "product_id": "0B3A"}
    assert info["file_version"] == 4 and info["size_bytes"] == path.stat().st_size
    with open_recording(path) as recording:
        assert info["depth_scale_m"] == recording.depth_scale
        depth = info["streams"]["depth"]
        infos = recording.frame_infos("depth")
        assert (depth["format"], depth["width"], depth["height"], depth["fps"], depth["frames"]) == \
            ("z16", 64, 48, 30, 4)
        assert depth["first_timestamp_ms"] == infos[0].timestamp_ms
        assert depth["last_timestamp_ms"] == infos[-1].timestamp_ms
        assert depth["measured_rate_hz"] == pytest.approx(3000.0 / (infos[-1].timestamp_ms - infos[0].timestamp_ms))
        assert info["streams"]["color"]["intrinsics"]["fx"] == recording.streams["color"].intrinsics.fx
        color = info["extrinsics_from_depth"]["color"]
        T = recording.extrinsics("depth", "color")
        assert color["translation_mm"] == pytest.approx(T[:3, 3] * 1000.0)
        # an independent angle; Rodrigues first projects the (6-decimal, in .db3) matrix onto a rotation
        angle = np.linalg.norm(cv2.Rodrigues(T[:3, :3])[0])
        assert color["rotation_deg"] == pytest.approx(math.degrees(angle), abs=1e-3)
        assert color["rotation_deg"] == pytest.approx(1.2939, abs=1e-3)  # the fixture's (0.01, -0.02, 0.003) rad
        assert "accel" not in info["extrinsics_from_depth"]  # the recorder stores none for the IMU
        span = [f.recording_time_ns for k in recording.streams for f in recording.frame_infos(k)]
        assert info["duration_s"] == pytest.approx((max(span) - min(span)) / 1e9)


@pytest.mark.parametrize("path", [DB3, BAG], ids=["db3", "bag"])
def test_export_png_reads_back_identical(tmp_path, path, capsys):
    out = tmp_path / "export"
    assert run(["recording", "export", str(path), "--out", str(out)]) == 0
    assert "exported 4 depth, 4 color, 4 ir1, 4 ir2, 8 accel, 8 gyro" in capsys.readouterr().out
    rows = _rows(out / "frames.csv")
    assert len(rows) == 16 and not list(out.glob("*.partial"))
    with open_recording(path) as recording:
        for row in rows:
            frame = recording.read_frame(row["stream"], int(row["index"]))
            assert row["file"] == f"{row['stream']}_{frame.info.frame_number:06d}.png"
            assert float(row["timestamp_ms"]) == frame.info.timestamp_ms
            assert row["timestamp_domain"] == frame.info.timestamp_domain
            image = cv2.imread(str(out / row["file"]), cv2.IMREAD_UNCHANGED)
            assert image.dtype == frame.data.dtype and np.array_equal(image, frame.data), row["file"]
        assert cv2.imread(str(out / "depth_001000.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
        # the top-left colour pixel is pure blue; a PNG viewer (and OpenCV) must see blue
        assert cv2.imread(str(out / "color_000500.png"))[0, 0].tolist() == [255, 0, 0]
        imu = _rows(out / "imu.csv")
        assert [r["stream"] for r in imu].count("gyro") == 8
        for r in imu:
            sample = recording.read_frame(r["stream"], int(r["index"])).data
            assert [float(r[a]) for a in "xyz"] == sample.tolist()
        meta = json.loads((out / "intrinsics.json").read_text())
        assert meta["depth_scale_m"] == recording.depth_scale
        assert meta["streams"]["color"]["K"] == recording.streams["color"].intrinsics.K.tolist()
        assert meta["streams"]["gyro"]["motion_intrinsics"]["data_3x4"][0][0] == pytest.approx(1.01)
        np.testing.assert_array_equal(meta["extrinsics"]["T_color_depth"], recording.extrinsics("depth", "color"))


def test_export_npy_selection_and_every(tmp_path):
    out = tmp_path / "npy"
    args = ["recording", "export", str(DB3), "--out", str(out), "--format", "npy", "--stream", "depth",
            "--stream", "ir1", "--every", "2"]
    assert run(args) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "depth_001000.npy", "depth_001002.npy", "frames.csv", "intrinsics.json", "ir1_001000.npy", "ir1_001002.npy"]
    with open_recording(DB3) as recording:
        assert np.array_equal(np.load(out / "depth_001002.npy"), recording.read_frame("depth", 2).data)
        infos = recording.frame_infos("depth")
        t1_ms, t3_ms = infos[1].recording_time_ns / 1e6, infos[3].recording_time_ns / 1e6
    window = tmp_path / "window"
    assert run(["recording", "export", str(DB3), "--out", str(window), "--stream", "depth", "--stream", "imu",
                "--start-ms", str(t1_ms), "--stop-ms", str(t3_ms)]) == 0
    rows = _rows(window / "frames.csv")
    assert [(r["stream"], r["index"]) for r in rows] == [("depth", "1"), ("depth", "2")]
    assert (window / "imu.csv").exists() and not (window / "color_000501.png").exists()


def test_export_rgb8_bag_writes_true_colours_and_names_repeated_counters_by_index(tmp_path):
    from darp.formats.realsense.bag.writer import BagWriter

    intr = Intrinsics(width=8, height=6, fx=5.0, fy=5.0, ppx=3.5, ppy=2.5)
    streams = [StreamProfile(key="depth", stream_type="Depth", index=0, sensor_index=0, format="z16", fps=30,
                             width=8, height=6, intrinsics=intr),
               StreamProfile(key="color", stream_type="Color", index=0, sensor_index=1, format="rgb8", fps=30,
                             width=8, height=6, intrinsics=intr)]
    path = tmp_path / "rgb.bag"
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red in RGB order
    with BagWriter(path, DeviceInfo(name="Intel RealSense D435", serial="1"), streams) as writer:
        for n in range(3):
            writer.write_image("depth", np.full((6, 8), 100 + n, np.uint16), 1000.0 + 33 * n, 0)  # counter stuck at 0
            writer.write_image("color", rgb, 1000.0 + 33 * n, 7 + n)
    out = tmp_path / "out"
    assert run(["recording", "export", str(path), "--out", str(out)]) == 0
    assert cv2.imread(str(out / "color_000007.png"))[0, 0].tolist() == [0, 0, 200]  # BGR on disk: red
    assert [r["file"] for r in _rows(out / "frames.csv") if r["stream"] == "depth"] == [
        "depth_000000.png", "depth_000001.png", "depth_000002.png"]
    assert cv2.imread(str(out / "depth_000002.png"), cv2.IMREAD_UNCHANGED)[0, 0] == 102


def test_export_refuses_a_non_empty_folder_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert run(["recording", "export", str(DB3), "--out", str(out), "--stream", "ir2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"darp: error: {out}: output folder is not empty (use --overwrite to write into it)"
    assert run(["recording", "export", str(DB3), "--out", str(out), "--stream", "ir2", "--overwrite"]) == 0
    assert (out / "ir2_001003.png").exists() and (out / "keep.txt").read_text() == "mine"


def test_interrupted_export_leaves_no_partial_files(tmp_path, monkeypatch, capsys):
    real_encode = cli_recording._encode
    calls = []

    def failing(frame, fmt, stream_format):
        calls.append(frame.info)
        if len(calls) == 3:
            raise RecordingError("simulated failure")
        return real_encode(frame, fmt, stream_format)

    monkeypatch.setattr(cli_recording, "_encode", failing)
    out = tmp_path / "out"
    assert run(["recording", "export", str(DB3), "--out", str(out)]) == 2
    assert "simulated failure" in capsys.readouterr().err
    names = sorted(p.name for p in out.iterdir())
    assert "UNFINISHED.txt" in names  # the half folder is marked (issue 32)
    names.remove("UNFINISHED.txt")
    assert len(names) == 2 and all(n.endswith(".png") for n in names)  # two whole images, no csv, no .partial


@pytest.mark.parametrize("args,message", [
    (["info", "{missing}"], "Invalid value for "),  # click: the path does not exist
    (["export", "{db3}", "--out", "{tmp}/x", "--stream", "lidar"], "Invalid value for '--stream'"),
    (["info", "{garbage}"], "{garbage}: corrupt ROS2 .db3 recording: file is not a database"),
    (["export", "{garbage}", "--out", "{tmp}/y"], "{garbage}: corrupt ROS2 .db3 recording"),
])
def test_errors_are_one_line_exit_2(tmp_path, capsys, args, message):
    garbage = tmp_path / "garbage.db3"
    garbage.write_bytes(b"SQLite format 3\x00" + b"\xff" * 3000)
    names = {"missing": tmp_path / "nope.db3", "db3": DB3, "garbage": garbage, "tmp": tmp_path}
    argv = ["recording"] + [a.format(**names) for a in args]
    assert run(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"darp: error: {message.format(**names)}"), err


def test_console_entry_point_has_no_traceback(tmp_path):
    bad = tmp_path / "bad.db3"
    bad.write_bytes(b"SQLite format 3\x00" + b"\x00" * 100)
    result = subprocess.run([sys.executable, "-c", "from darp.cli import main; main()", "recording", "info", str(bad)],
                            capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 2
    assert result.stderr.startswith(f"darp: error: {bad}: ") and "Traceback" not in result.stderr


# -- damaged recordings: read as far as they go, and said so ----------------------------------------------
@pytest.fixture(scope="module")
def damaged(tmp_path_factory):
    """A complete bag (small chunks), its interrupted form (no index) and a copy cut in half, with the frames
    each should yield: those in complete chunks, from the complete bag's own index."""
    from darp.formats.realsense.bag.reader import BagRecording
    from helpers.bag_samples import write_sample
    from helpers.damaged_recordings import cut_copy, unindexed_copy

    root = tmp_path_factory.mktemp("damaged")
    sample = write_sample(root / "whole.bag", chunk_threshold=20_000)
    half = sample.path.stat().st_size // 2
    with BagRecording(sample.path) as whole:
        chunks = whole._index.chunks
        complete = sum(c.data_start + c.data_len <= half for c in chunks)
        chunk_of = {key: whole._data[key]["chunk"] for key in whole.streams}
    return {
        "sample": sample,
        "interrupted": (unindexed_copy(sample.path, root / "interrupted.bag"), len(chunks),
                        {key: len(frames) for key, frames in sample.frames.items()}),
        "cut": (cut_copy(sample.path, root / "cut.bag", half), complete,
                {key: int((chunk_of[key] < complete).sum()) for key in chunk_of}),
    }


@pytest.mark.parametrize("kind,missing", [("interrupted", "no index (interrupted recording?)"),
                                          ("cut", "truncated at byte ")])
def test_info_on_a_salvaged_bag_warns_and_shows_what_was_recovered(damaged, capsys, kind, missing):
    from helpers.damaged_recordings import salvage_warning

    path, chunks, frames = damaged[kind]
    recovered = f"recovered {frames['depth']} depth, {frames['color']} color"
    assert run(["recording", "info", str(path)]) == 0
    out, err = capsys.readouterr()
    salvage_warning(err, path, missing, recovered, f"from {chunks} complete chunks")
    assert "salvaged:" in out and missing in out and recovered in out

    assert run(["recording", "info", str(path), "--json"]) == 0
    out, err = capsys.readouterr()
    salvage_warning(err, path, missing)
    info = json.loads(out)
    salvaged = info["salvaged"]
    assert salvaged["frames"] == frames and {k: s["frames"] for k, s in info["streams"].items()} == frames
    assert salvaged["chunks"] == chunks and salvaged["duration_s"] == pytest.approx(info["duration_s"])
    assert any(missing in m for m in salvaged["missing"]) and salvaged["missing"][0].startswith("no index")
    if kind == "cut":
        size = path.stat().st_size
        assert 0 < salvaged["truncated_at_byte"] < size and f"({size - salvaged['truncated_at_byte']} bytes ignored)" \
            in salvaged["summary"]
    else:
        assert salvaged["truncated_at_byte"] is None


def test_info_on_an_intact_bag_says_nothing_of_salvage(damaged, capsys):
    path = damaged["sample"].path
    assert run(["recording", "info", str(path), "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["salvaged"] is None and err == ""


def test_export_of_a_cut_bag_warns_once_and_writes_the_recovered_frames(damaged, tmp_path, capsys):
    from helpers.damaged_recordings import salvage_warning

    path, _, frames = damaged["cut"]
    out = tmp_path / "export"
    assert run(["recording", "export", str(path), "--out", str(out), "--format", "npy"]) == 0
    stdout, err = capsys.readouterr()
    salvage_warning(err, path, "truncated at byte ", f"recovered {frames['depth']} depth")
    assert f"exported {frames['depth']} depth, {frames['color']} color" in stdout
    rows = _rows(out / "frames.csv")
    sample = damaged["sample"].frames
    for key in ("depth", "color", "ir1", "ir2"):
        mine = [row for row in rows if row["stream"] == key]
        assert len(mine) == frames[key] > 0
        for row, expected in zip(mine, sample[key], strict=False):
            assert np.array_equal(np.load(out / row["file"]), expected["data"])
    assert len(_rows(out / "imu.csv")) == frames["accel"] + frames["gyro"]


@pytest.mark.parametrize("name", ["x.bag", "x.db3"])
def test_a_fifo_named_like_a_recording_is_refused_before_it_is_opened(tmp_path, name):
    fifo = tmp_path / name
    os.mkfifo(fifo)
    result = subprocess.run([sys.executable, "-c", "from darp.cli import main; main()", "recording", "info", str(fifo)],
                            capture_output=True, text=True, timeout=60, check=False)  # it used to block forever
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr == f"darp: error: {fifo}: is a named pipe (FIFO), not a regular file: not a recording\n"


def test_a_device_or_folder_named_like_a_recording_is_refused(tmp_path, capsys):
    folder = tmp_path / "x.bag"
    folder.mkdir()
    assert run(["recording", "info", str(folder)]) == 2
    assert capsys.readouterr().err == f"darp: error: {folder}: is a folder, not a recording\n"
    if Path("/dev/null").exists():
        assert run(["recording", "export", "/dev/null", "--out", str(tmp_path / "out")]) == 2
        expected = "darp: error: /dev/null: is a character device, not a regular file: not a recording\n"
        assert capsys.readouterr().err == expected
        with pytest.raises(RecordingError, match="character device"):
            from darp.formats.realsense.bag.reader import BagRecording

            BagRecording("/dev/null")
