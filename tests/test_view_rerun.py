"""darp view --save: the .rrd read back with rerun's own reader holds every entity the viewer promises."""

from __future__ import annotations

from pathlib import Path

import pytest

from darp.cli._app import run

pytestmark = pytest.mark.slow  # needs the processed twin survey

ARM_ENTITIES = {"links/cylinders": "Cylinders3D", "links/capsules": "Capsules3D", "links/boxes": "Boxes3D",
                "skeleton": "LineStrips3D", "camera": "Pinhole", "camera/rgb": "Image", "camera/depth": "DepthImage",
                "camera/ir": "Image"}


def test_view_of_a_processed_survey_holds_every_entity(processed_path: Path, tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from darp.view import rrd_entities

    rrd = tmp_path / "cube.rrd"
    assert run(["view", str(processed_path), "--save", str(rrd)]) == 0
    entities = rrd_entities(rrd)
    for arm in ("arm110", "arm111"):
        for entity, archetype in ARM_ENTITIES.items():
            assert archetype in entities.get(f"/world/{arm}/{entity}", set()), (arm, entity, sorted(entities))
        assert "Transform3D" in entities[f"/world/{arm}/camera"]
    for entity in ("clouds/arm110", "clouds/arm111", "clouds/fused", "heldout"):
        assert "Points3D" in entities[f"/world/{entity}"], entity
    assert "Mesh3D" in entities["/world/mesh"]


def test_view_of_a_raw_survey_moves_the_arms_and_shows_the_streams(survey_path: Path, tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from darp.view import rrd_entities, view

    stats = view(survey_path, tmp_path / "raw.rrd", every_s=2.0)
    entities = rrd_entities(tmp_path / "raw.rrd")
    assert stats.arm_states > 100 and stats.images >= 4 and stats.clouds == 0
    for arm in ("arm110", "arm111"):
        assert "Cylinders3D" in entities[f"/world/{arm}/links/cylinders"]
        assert "DepthImage" in entities[f"/world/{arm}/camera/depth"]


def test_view_of_a_folder_without_a_survey_is_one_error_line(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["view", str(tmp_path), "--save", str(tmp_path / "x.rrd")]) == 2
    assert capsys.readouterr().err.startswith("darp: error:")
