"""``darp inspect`` and the release-composition table: values from synthetic surveys, the four formats,
the paper's own numbers, and exit code 2 on bad input."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from darp.cli._app import run
from darp.errors import EvaluationError
from darp.evaluation.composition import SurveyComposition, format_composition, survey_composition
from darp.formats.arm_poses import ArmPoseWriter
from darp.formats.envelope import Envelope, write_envelope
from darp.formats.survey import open_survey

# -- the paper's table (Release composition and recording statistics) -----------------------------
# object, radius cm, height cm, standoff cm, rows/arm, duration s, rate Hz, depth110, depth111, size GB
PAPER = [
    ("Red Bull", None, None, None, 1150, 118.6, 9.7, 3412, 3436, 14.85),
    ("Dumbbell", 6.90, 3.66, 36.9, 3297, 110.6, 29.8, 3160, 3194, 13.78),
    ("Controller", 5.78, 2.64, 35.8, 3093, 103.6, 29.9, 2950, 2986, 12.87),
    ("Cube", 4.31, 1.60, 34.3, 2534, 88.4, 28.6, 2522, 2535, 10.96),
    ("Ketchup", 4.41, 14.93, 34.4, 4119, 135.4, 30.4, 3921, 3944, 17.05),
    ("Picture Frame", 11.60, 19.07, 52.2, 2923, 99.4, 29.4, 2843, 2867, 12.37),
    ("Mug", 7.22, 6.30, 37.2, 2954, 99.4, 29.7, 2830, 2865, 12.35),
    ("Paperweight", 4.85, 7.44, 34.8, 3465, 115.4, 30.0, 3315, 3314, 14.40),
    ("Clock", 5.83, 9.95, 35.8, 3820, 126.6, 30.2, 3656, 3677, 15.90),
    ("Cup", 4.11, 10.16, 34.1, 3151, 107.6, 29.3, 3088, 3107, 13.43),
]


def _paper_items() -> list[SurveyComposition]:
    def m(cm: float | None) -> float | None:
        return None if cm is None else cm / 100.0

    return [
        SurveyComposition(
            name=name, radius_m=m(r), height_m=m(h), standoff_m=m(s),
            rows_by_arm={"arm110": rows, "arm111": rows}, duration_s=dur,
            depth_frames={"arm110": d110, "arm111": d111}, size_bytes=round(gb * 1e9),
        )
        for name, r, h, s, rows, dur, _, d110, d111, gb in PAPER
    ]


def test_definitions_reproduce_the_papers_rate_column() -> None:
    for item, row in zip(_paper_items(), PAPER):
        rate_paper = row[6]
        # the paper's Duration is rounded to 0.1 s: Rate = Rows/Arm / Duration must hold within that
        low = item.rows_per_arm / (item.duration_s + 0.05)
        high = item.rows_per_arm / (item.duration_s - 0.05)
        assert low - 0.05 <= rate_paper <= high + 0.05, row[0]


def test_total_row_reproduces_the_papers_totals() -> None:
    text = format_composition(_paper_items(), "latex")
    total = next(line for line in text.splitlines() if "Total / Range" in line)
    cells = [c.strip().removesuffix(r"\\").strip() for c in total.split("&")]
    assert cells[4:] == [r"\textbf{30,506}", r"\textbf{1105.0}", "--", r"\textbf{31,697}", r"\textbf{31,925}",
                         r"\textbf{137.96}"]  # the paper prints 1105.1 and 137.94: sums of its unrounded values
    assert cells[2:4] == [r"\textbf{1.6--19.1}", r"\textbf{34.1--52.2}"]  # as in the paper
    assert cells[1] == r"\textbf{4.1--11.6}"  # the paper prints 3.5--11.6, below every radius it lists
    assert r"Red Bull & -- & -- & -- & 1150 & 118.6 & 9.7 & 3412 & 3436 & 14.85 \\" in text
    assert r"Picture Frame & 11.60 & 19.07 & 52.2 & 2923 & 99.4 & 29.4 & 2843 & 2867 & 12.37 \\" in text


def test_format_errors() -> None:
    with pytest.raises(EvaluationError, match="unknown table format 'html'"):
        format_composition(_paper_items(), "html")
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


def _survey(root: Path, *, rows: dict[str, int], depth: dict[str, int], t0_s: float = 1718000000.0,
            envelope: Envelope | None = Envelope(object_name="Cube", radius_m=0.0431, height_m=0.016,
                                                 standoff_m=0.343)) -> tuple[Path, float]:
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
    from damaged_recordings import salvage_warning, unindexed_copy

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
