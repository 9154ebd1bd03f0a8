"""``darp inspect`` and the release-composition table: the printed numbers against counts taken from the
survey files by other means (csv, json, pyrealsense2's playback, the file system), the four formats, the
total row, and exit code 2 on bad input."""

from __future__ import annotations

import csv
import io
import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from darp.cli._app import run
from darp.errors import EvaluationError
from darp.evaluation.composition import SurveyComposition, format_composition, survey_composition
from darp.formats.arm_poses import ArmPoseWriter
from darp.formats.envelope import Envelope, write_envelope
from darp.formats.survey import open_survey
from helpers.realsense_playback import play_back


def _item(name: str, rows: tuple[int, int], duration_s: float, depth: tuple[int, int], size_bytes: int,
          radius_m: float | None = None, height_m: float | None = None,
          standoff_m: float | None = None) -> SurveyComposition:
    return SurveyComposition(name=name, radius_m=radius_m, height_m=height_m, standoff_m=standoff_m,
                             rows_by_arm={"arm110": rows[0], "arm111": rows[1]}, duration_s=duration_s,
                             depth_frames={"arm110": depth[0], "arm111": depth[1]}, size_bytes=size_bytes)


def test_total_row_sums_unrounded_values_with_thousands_separators() -> None:
    items = [_item("Ketchup", (4119, 4120), 135.44, (3921, 3944), 17_054_000_000, 0.0441, 0.1493, 0.344),
             _item("Dumbbell", (3297, 3297), 110.64, (3160, 3194), 13_784_000_000, 0.069, 0.0366, 0.369),
             _item("Red Bull", (1150, 1150), 118.63, (3412, 3436), 14_854_000_000)]
    text = format_composition(items, "latex")
    total = next(line for line in text.splitlines() if "Total / Range" in line)
    cells = [c.strip().removesuffix(r"\\").strip() for c in total.split("&")]
    assert cells[1:4] == [r"\textbf{4.4--6.9}", r"\textbf{3.7--14.9}", r"\textbf{34.4--36.9}"]  # ranges of the known
    assert cells[4:] == [r"\textbf{8,566.5}", r"\textbf{364.7}", "--", r"\textbf{10,493}", r"\textbf{10,574}",
                         r"\textbf{45.69}"]  # rounded cells would add up to 364.6 s and 45.68 GB
    assert r"Ketchup & 4.41 & 14.93 & 34.4 & 4119.5 & 135.4 & 30.4 & 3921 & 3944 & 17.05 \\" in text
    assert r"Red Bull & -- & -- & -- & 1150 & 118.6 & 9.7 & 3412 & 3436 & 14.85 \\" in text


def test_format_errors() -> None:
    with pytest.raises(EvaluationError, match="unknown table format 'html'"):
        format_composition([_item("x", (1, 1), 1.0, (1, 1), 1)], "html")
    with pytest.raises(EvaluationError, match="no surveys"):
        format_composition([], "table")


def test_uneven_rows_and_missing_depth_stream() -> None:
    item = SurveyComposition(name="odd", radius_m=0.05, height_m=None, standoff_m=0.35,
                             rows_by_arm={"arm110": 10, "arm111": 11}, duration_s=0.0,
                             depth_frames={"arm110": 4, "arm111": None}, size_bytes=123)
    rows = list(csv.reader(io.StringIO(format_composition([item], "csv"))))
    assert rows[0] == ["Object", "Radius [cm]", "Height [cm]", "Standoff [cm]", "Rows/Arm", "Duration [s]",
                       "Rate [Hz]", "Depth_110", "Depth_111", "Size [GB]"]
    assert rows[1] == ["odd", "5.00", "", "35.0", "10.5", "0.0", "", "4", "", "0.00"]
    assert rows[2] == ["Total / Range", "5.0-5.0", "", "35.0-35.0", "10.5", "0.0", "", "4", "", "0.00"]


# -- synthetic surveys written with darp's own BagWriter ---------------------------------------------
SERIALS = {"arm110": "348522076490", "arm111": "405622074504"}
W, H = 32, 24


def _profiles() -> list:
    from darp.formats.realsense.types import Intrinsics, StreamProfile

    intr = Intrinsics(W, H, 30.0, 30.0, (W - 1) / 2, (H - 1) / 2)
    return [
        StreamProfile("depth", "Depth", 0, 0, "z16", 30, W, H, intr),
        StreamProfile("ir1", "Infrared", 1, 0, "y8", 30, W, H, intr),
        StreamProfile("color", "Color", 0, 1, "bgr8", 30, W, H, intr),
    ]


def _bag(path: Path, serial: str, start_ms: float, n_depth: int) -> None:
    from darp.formats.realsense.bag.writer import BagWriter
    from darp.formats.realsense.types import DeviceInfo

    device = DeviceInfo(name="Intel RealSense D435", serial=serial)
    with BagWriter(path, device, _profiles()) as writer:
        for k in range(n_depth):
            t_ms = start_ms + k * 1000.0 / 30.0
            writer.write_image("depth", np.full((H, W), 500 + k, np.uint16), t_ms, k + 1)
            writer.write_image("ir1", np.full((H, W), k, np.uint8), t_ms, k + 1)
            writer.write_image("color", np.full((H, W, 3), k, np.uint8), t_ms + 3.0, k + 1)


CUBE = Envelope(object_name="Cube", radius_m=0.0431, height_m=0.016, standoff_m=0.343)


def _survey(root: Path, *, rows: dict[str, int], depth: dict[str, int], t0_s: float = 1718000000.0,
            envelope: Envelope | None = CUBE) -> tuple[Path, float]:
    """A survey with ``rows`` joint-log rows and ``depth`` depth frames per arm; returns its log span."""
    root.mkdir(parents=True)
    times = {arm: t0_s + np.arange(n) / 29.5 + (0.004 if arm == "arm111" else 0.0) for arm, n in rows.items()}
    with ArmPoseWriter(root / "arm_poses.csv") as writer:
        events = sorted((t, arm) for arm, ts in times.items() for t in ts)
        for t, arm in events:
            writer.write(t, arm, np.zeros(6))
    for arm, n in depth.items():
        _bag(root / f"cam{SERIALS[arm]}.bag", SERIALS[arm], (t0_s + 0.2) * 1000.0, n)
    if envelope is not None:
        write_envelope(root / "manip_envelope.json", envelope)
    span = max(t[-1] for t in times.values()) - min(t[0] for t in times.values())
    return root, span


def test_values_match_the_constructed_survey(tmp_path: Path) -> None:
    root, span = _survey(tmp_path / "Cube", rows={"arm110": 40, "arm111": 38},
                         depth={"arm110": 5, "arm111": 7})
    item = survey_composition(open_survey(root))
    assert item.rows_by_arm == {"arm110": 40, "arm111": 38} and item.rows_per_arm == 39.0
    assert item.duration_s == pytest.approx(span, abs=2e-6)  # log written with 1 µs resolution
    assert item.rate_hz == pytest.approx(39.0 / span, rel=1e-5)
    assert item.depth_frames == {"arm110": 5, "arm111": 7}
    files = ["cam348522076490.bag", "cam405622074504.bag", "arm_poses.csv", "manip_envelope.json"]
    assert item.size_bytes == sum((root / f).stat().st_size for f in files)
    assert (item.radius_m, item.height_m, item.standoff_m) == (0.0431, 0.016, 0.343)
    assert item.notes == ()


@dataclass
class Counted:
    """One survey's statistics taken from its files without darp's readers."""

    rows: Counter[str]  # joint-log rows per arm
    duration_s: float  # first to last joint-log time
    depth: dict[str, int]  # depth frames pyrealsense2 plays back, per arm
    envelope: dict  # manip_envelope.json as JSON
    size_bytes: int  # the folder's files

    @property
    def rows_per_arm(self) -> float:
        return sum(self.rows[arm] for arm in SERIALS) / len(SERIALS)


def _count_files(root: Path) -> Counted:
    with open(root / "arm_poses.csv", newline="", encoding="utf-8") as handle:
        log = list(csv.DictReader(handle))
    times = [float(row["time_s"]) for row in log]
    depth = {arm: len(play_back(root / f"cam{serial}.bag").frames.get("depth", [])) for arm, serial in SERIALS.items()}
    return Counted(rows=Counter(row["arm"] for row in log), duration_s=max(times) - min(times), depth=depth,
                   envelope=json.loads((root / "manip_envelope.json").read_text(encoding="utf-8")),
                   size_bytes=sum(f.stat().st_size for f in root.iterdir() if f.is_file()))


def _cm(envelope: dict, key: str) -> float | None:
    return None if envelope.get(key) is None else envelope[key] * 100.0


def _cell(text: str) -> float | None:
    return None if text == "" else float(text)


def _range(text: str) -> tuple[float, float]:
    low, high = text.split("-")
    return float(low), float(high)


def test_cli_numbers_equal_counts_taken_from_the_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parent = tmp_path / "darp"
    _survey(parent / "Cube", rows={"arm110": 40, "arm111": 38}, depth={"arm110": 5, "arm111": 7})
    _survey(parent / "Mug", rows={"arm110": 25, "arm111": 28}, depth={"arm110": 9, "arm111": 4},
            t0_s=1718003600.0, envelope=Envelope(object_name="Mug", radius_m=0.0722, height_m=0.063,
                                                 standoff_m=0.372))
    _survey(parent / "RedBull", rows={"arm110": 12, "arm111": 13}, depth={"arm110": 3, "arm111": 2},
            envelope=Envelope(object_name="Red Bull"))
    assert run(["inspect", str(parent), "--format", "csv"]) == 0
    printed = list(csv.reader(io.StringIO(capsys.readouterr().out)))
    assert printed[0][7:9] == ["Depth_110", "Depth_111"]
    assert [row[0] for row in printed] == ["Object", "Cube", "Mug", "RedBull", "Total / Range"]
    counted = {name: _count_files(parent / name) for name in ("Cube", "Mug", "RedBull")}
    assert counted["Cube"].depth == {"arm110": 5, "arm111": 7}  # the oracle sees what was written
    for row in printed[1:4]:
        c = counted[row[0]]
        for cell, key, digits in ((row[1], "radius_m", 2), (row[2], "height_m", 2), (row[3], "standoff_m", 1)):
            expected = _cm(c.envelope, key)
            assert _cell(cell) == (None if expected is None else pytest.approx(expected, abs=0.51 * 10**-digits))
        assert float(row[4]) == c.rows_per_arm
        assert float(row[5]) == pytest.approx(c.duration_s, abs=0.051)
        assert float(row[6]) == pytest.approx(c.rows_per_arm / c.duration_s, abs=0.051)
        assert [int(row[7]), int(row[8])] == [c.depth["arm110"], c.depth["arm111"]]
        assert float(row[9]) == pytest.approx(c.size_bytes / 1e9, abs=0.0051)
    total, known = printed[4], [c for c in counted.values() if c.envelope.get("radius_m") is not None]
    for cell, key in ((total[1], "radius_m"), (total[2], "height_m"), (total[3], "standoff_m")):
        values = [_cm(c.envelope, key) for c in known]
        assert _range(cell) == pytest.approx((min(values), max(values)), abs=0.051)
    assert float(total[4]) == sum(c.rows_per_arm for c in counted.values())
    assert float(total[5]) == pytest.approx(sum(c.duration_s for c in counted.values()), abs=0.051)
    assert total[6] == ""  # no total rate
    assert [int(total[7]), int(total[8])] == [sum(c.depth[arm] for c in counted.values()) for arm in SERIALS]
    assert float(total[9]) == pytest.approx(sum(c.size_bytes for c in counted.values()) / 1e9, abs=0.0051)


def test_cli_all_formats(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parent = tmp_path / "darp"
    _, span_a = _survey(parent / "Cube", rows={"arm110": 30, "arm111": 30}, depth={"arm110": 4, "arm111": 6})
    _, span_b = _survey(parent / "RedBull", rows={"arm110": 12, "arm111": 12},
                        depth={"arm110": 3, "arm111": 2},
                        envelope=Envelope(object_name="Red Bull"))
    (parent / "README.md").write_text("not a survey")
    outputs = {}
    for fmt in ("table", "csv", "markdown", "latex"):
        assert run(["inspect", str(parent), "--format", fmt]) == 0
        captured = capsys.readouterr()
        assert captured.err == ""
        outputs[fmt] = captured.out
    rows = list(csv.reader(io.StringIO(outputs["csv"])))
    assert [r[0] for r in rows] == ["Object", "Cube", "RedBull", "Total / Range"]
    cube, red, total = rows[1], rows[2], rows[3]
    assert cube[1:5] == ["4.31", "1.60", "34.3", "30"] and cube[7:9] == ["4", "6"]
    assert cube[5] == f"{span_a:.1f}" and cube[6] == f"{30 / span_a:.1f}"
    assert red[1:4] == ["", "", ""] and red[4] == "12" and red[7:9] == ["3", "2"]
    assert total[1:5] == ["4.3-4.3", "1.6-1.6", "34.3-34.3", "42"]
    assert total[5] == f"{span_a + span_b:.1f}" and total[6] == "" and total[7:9] == ["7", "8"]
    assert "| Cube | 4.31 | 1.60 | 34.3 | 30 |" in outputs["markdown"]
    assert "| RedBull | -- | -- | -- | 12 |" in outputs["markdown"]
    assert "| **Total / Range** | **4.3-4.3** |" in outputs["markdown"]
    assert r"\textbf{Depth$_{110}$}" in outputs["latex"] and r"RedBull & -- & -- & --" in outputs["latex"]
    table = outputs["table"].splitlines()
    assert table[0].split()[:3] == ["Object", "Radius", "[cm]"]
    assert table[2].split()[:5] == ["Cube", "4.31", "1.60", "34.3", "30"]
    assert table[-1].split()[:3] == ["Total", "/", "Range"]
    # the same surveys named one by one give the same table
    assert run(["inspect", str(parent / "Cube"), str(parent / "RedBull")]) == 0
    assert capsys.readouterr().out == outputs["table"]


def test_cli_notes_go_to_stderr(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root, _ = _survey(tmp_path / "Mug", rows={"arm110": 5, "arm111": 5}, depth={"arm110": 2, "arm111": 2},
                      envelope=None)
    with open(root / "arm_poses.csv", "a", encoding="utf-8") as handle:
        handle.write("1718000009.0,arm110,0.1,0.2")  # a crash mid-row
    assert run(["inspect", str(root), "-f", "csv"]) == 0
    captured = capsys.readouterr()
    assert "no manip_envelope.json" in captured.err and "cut-short last line 12 ignored" in captured.err
    assert list(csv.reader(io.StringIO(captured.out)))[1][1:5] == ["", "", "", "5"]


def test_cli_warns_once_about_an_interrupted_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from helpers.damaged_recordings import salvage_warning, unindexed_copy

    root, _ = _survey(tmp_path / "Cube", rows={"arm110": 5, "arm111": 5}, depth={"arm110": 4, "arm111": 3})
    bag = root / "cam348522076490.bag"
    unindexed_copy(bag, tmp_path / "interrupted.bag").replace(bag)
    assert run(["inspect", str(root), "-f", "csv"]) == 0
    captured = capsys.readouterr()
    salvage_warning(captured.err, bag, "no index (interrupted recording?)", "recovered 4 depth, 4 color, 4 ir1 frames")
    assert len(captured.err.splitlines()) == 1  # the warning, and no separate note about the same file
    assert list(csv.reader(io.StringIO(captured.out)))[1][7:9] == ["4", "3"]


def test_cli_camera_mapping_override(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root, _ = _survey(tmp_path / "Cube", rows={"arm110": 5, "arm111": 5}, depth={"arm110": 2, "arm111": 3})
    swapped = ["--camera", "348522076490=arm111", "--camera", "405622074504=arm110"]
    assert run(["inspect", str(root), "-f", "csv", *swapped]) == 0
    rows = list(csv.reader(io.StringIO(capsys.readouterr().out)))
    assert rows[0][7:9] == ["Depth_111", "Depth_110"]  # arms in the order of the given mapping
    assert rows[1][7:9] == ["2", "3"]  # camera 348522076490 (2 frames) now counts as arm111
    assert run(["inspect", str(root), "--camera", "348522076490=arm110"]) == 2  # 405622074504 unmapped
    err = capsys.readouterr().err
    assert "camera serial 405622074504 is not mapped to an arm" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("setup", "expected"),
    [
        (lambda root: None, "does not exist"),
        (lambda root: root.mkdir(), "not a survey folder and holds no survey folders"),
        (lambda root: root.write_text("x"), "not a folder"),
    ],
)
def test_cli_exit_code_2_on_bad_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], setup, expected: str  # type: ignore[no-untyped-def]
) -> None:
    root = tmp_path / "bad"
    setup(root)
    assert run(["inspect", str(root)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("darp: error: ") and expected in lines[0]


def test_cli_exit_code_2_on_incomplete_or_corrupt_survey(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root, _ = _survey(tmp_path / "Cube", rows={"arm110": 5, "arm111": 5}, depth={"arm110": 2, "arm111": 2})
    (root / "cam405622074504.bag").rename(root / "cam405622074504.bag.partial")
    assert run(["inspect", str(root)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no recording for arm111" in err and "cam405622074504.bag.partial: an interrupted recording" in err
    (root / "cam405622074504.bag.partial").rename(root / "cam405622074504.bag")
    (root / "cam348522076490.bag").write_bytes(b"not a bag at all")
    assert run(["inspect", str(root)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cam348522076490.bag" in err
    assert run(["inspect", str(root), "--camera", "nonsense"]) == 2
    assert "'--camera': expected SERIAL=ARM" in capsys.readouterr().err
