"""``darp rig show`` and ``darp rig plot``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from darp.cli._app import run
from darp.kinematics.rig import default_rig_path, load_rig


def test_rig_show_prints_the_rig(capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["rig", "show"]) == 0
    out = capsys.readouterr().out
    assert "1.3986 m" in out and "178.40 deg" in out
    assert "arm110" in out and "arm111" in out


def test_rig_show_yaml_reloads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["rig", "show", "--yaml", "--rig", str(default_rig_path())]) == 0
    path = tmp_path / "printed.yaml"
    path.write_text(capsys.readouterr().out)
    again, default = load_rig(path), load_rig()
    np.testing.assert_allclose(again.arm("arm111").T_world_base, default.arm("arm111").T_world_base, atol=1e-10)


def test_rig_show_bad_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = yaml.safe_load(default_rig_path().read_text())
    del data["margins"]
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    assert run(["rig", "show", "--rig", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"darp: error: {path}: margins: missing field"


def test_rig_plot_writes_an_image(tmp_path: Path) -> None:
    out = tmp_path / "rig.png"
    assert run(["rig", "plot", "--out", str(out), "--q110-rad", "0.3,1.2,-1.0,-0.3,0,0", "--config", "forward"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob("*.partial"))


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--config", "dance"], "Invalid value for '--config'"),
     (["--q111-rad", "1,2,3"], "'--q111-rad': expected 6 finite numbers")],
)
def test_rig_plot_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str],
                                message: str) -> None:
    assert run(["rig", "plot", "--out", str(tmp_path / "x.png"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "x.png").exists()
