"""darp view --save: the .rrd read back with rerun's own reader holds every entity the viewer promises."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
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


def _rows(rrd: Path, entity: str, components: list[str]) -> dict[int, list[object]]:
    """Time (ns) -> the components' values of one entity's temporal rows, read with rerun's own reader."""
    from rerun.chunk import RrdReader

    rows: dict[int, list[object]] = {}
    for chunk in RrdReader(str(rrd)).store().stream():
        if str(chunk.entity_path) != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        times = batch.column("time").cast("int64").to_numpy()
        for i, t in enumerate(times):
            values = [batch.column(c)[i].as_py() if c in batch.schema.names else None for c in components]
            if all(v is not None for v in values):
                rows[int(t)] = values
    return rows


def test_view_frustums_sit_on_the_wrist_at_every_logged_frame(processed_path: Path, tmp_path: Path) -> None:
    """The camera's transform is logged with every arm state (and the arm at every image's time): its
    origin lies in the wrist camera's collision box at each of them, read back from the .rrd; the
    recording carries its default (object-centred) layout."""
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader
    from scipy.spatial.transform import Rotation

    rrd = tmp_path / "cube.rrd"
    assert run(["view", str(processed_path), "--save", str(rrd)]) == 0
    for arm in ("arm110", "arm111"):
        camera = _rows(rrd, f"/world/{arm}/camera", ["Transform3D:translation"])
        boxes = _rows(rrd, f"/world/{arm}/links/boxes",
                      ["Boxes3D:centers", "Boxes3D:half_sizes", "Boxes3D:quaternions"])
        images = _rows(rrd, f"/world/{arm}/camera/rgb", ["Image:buffer"])
        assert len(boxes) > 100 and set(camera) == set(boxes) and images and set(images) <= set(camera)
        for t, ((origin,), (centres, halves, quats)) in ((t, (camera[t], boxes[t])) for t in boxes):
            local = np.einsum("nji,nj->ni", Rotation.from_quat(quats).as_matrix(), np.subtract(origin, centres))
            gap = np.linalg.norm(np.maximum(np.abs(local) - np.asarray(halves), 0.0), axis=1).min()
            assert gap < 1e-6, (arm, t, gap)  # float32 in the recording
    assert [b.kind for b in RrdReader(str(rrd)).blueprints()] == ["blueprint"]


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


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rerun_command() -> list[str]:
    exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if exe is None:
        pytest.skip("the rerun command (rerun-sdk's viewer) is not installed")
    return [exe]


def _entities_so_far(received: Path) -> dict[str, set[str]]:
    """What the server has written so far; a read that lands mid-frame (the server still writing) is empty."""
    from darp.view import rrd_entities

    if not received.is_file():
        return {}
    try:
        return rrd_entities(received)
    except RuntimeError:  # "Message payload ... exceeds file size": caught the writer between two writes
        return {}


def _stop_group(server: subprocess.Popen[str], timeout_s: float = 20.0) -> None:
    """SIGINT to the server's whole process group, then wait until every process of it has ended.

    The ``rerun`` command is a Python wrapper that runs the real binary as its child: a signal to the wrapper
    alone ends the wrapper and leaves the binary running (and still writing the file) with no parent."""
    group = server.pid  # start_new_session: the group's id is the wrapper's pid
    with contextlib.suppress(ProcessLookupError):
        os.killpg(group, signal.SIGINT)
    deadline = time.monotonic() + timeout_s
    with contextlib.suppress(subprocess.TimeoutExpired):
        server.wait(timeout=timeout_s)
    while True:
        server.poll()  # reap the wrapper: a zombie still counts as a member of its group
        try:
            os.killpg(group, signal.SIGKILL if time.monotonic() > deadline else 0)  # 0: is any of it alive?
        except ProcessLookupError:
            break
        time.sleep(0.1)


def test_view_connect_delivers_the_entities_to_a_live_viewer(processed_path: Path, tmp_path: Path) -> None:
    """No --save: ``darp view --connect`` streams to a running rerun (headless here: the viewer's own gRPC
    server, which writes what it receives with ``rerun --save``), as a viewer on a desktop receives it."""
    pytest.importorskip("rerun")
    from darp.view import rrd_entities

    port, received = _free_port(), tmp_path / "received.rrd"
    server = subprocess.Popen([*_rerun_command(), "--port", str(port), "--save", str(received)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                              env={**os.environ, "RERUN_ANALYTICS": "0"}, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while True:  # the server is up when its port accepts connections
            assert server.poll() is None, server.stderr.read() if server.stderr else ""
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            assert time.monotonic() < deadline, "rerun's gRPC server did not start"
            time.sleep(0.2)
        assert run(["view", str(processed_path), "--connect", f"127.0.0.1:{port}"]) == 0
        deadline = time.monotonic() + 30
        while True:  # the server writes the stream as it arrives: wait for the last static entity
            entities = _entities_so_far(received)
            if "TextDocument" in entities.get("/summary", set()) or time.monotonic() > deadline:
                break
            time.sleep(0.5)
    finally:
        _stop_group(server)
    entities = rrd_entities(received)  # the server has stopped: the file is whole now
    for arm in ("arm110", "arm111"):
        for entity, archetype in ARM_ENTITIES.items():
            assert archetype in entities.get(f"/world/{arm}/{entity}", set()), (arm, entity, sorted(entities))
    for entity in ("clouds/fused", "heldout"):
        assert "Points3D" in entities[f"/world/{entity}"], entity
    assert "Mesh3D" in entities["/world/mesh"]


def test_viewer_addresses() -> None:
    from darp.errors import ConfigError
    from darp.view import viewer_url

    assert viewer_url("9876") == "rerun+http://127.0.0.1:9876/proxy"
    assert viewer_url("10.0.0.5:9000") == "rerun+http://10.0.0.5:9000/proxy"
    assert viewer_url("rerun+https://viewer.lab:443") == "rerun+https://viewer.lab:443/proxy"
    assert viewer_url("rerun+http://h:1/proxy") == "rerun+http://h:1/proxy"
    for bad in ("http://h:1/proxy", "viewer", "rerun+http://"):
        with pytest.raises(ConfigError, match="viewer address"):
            viewer_url(bad)


def test_view_connect_and_save_together_is_one_error_line(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "in").mkdir()
    assert run(["view", str(tmp_path / "in"), "--save", str(tmp_path / "x.rrd"), "--connect", "9876"]) == 2
    assert "--connect" in capsys.readouterr().err.splitlines()[0]


def test_view_connect_without_a_viewer_is_one_error_line(survey_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("rerun")
    assert run(["view", str(survey_path), "--connect", str(_free_port())]) == 2
    err = capsys.readouterr().err
    assert err.startswith("darp: error: no rerun viewer reachable at rerun+http://127.0.0.1:"), err


def test_the_viewer_beside_this_python_is_found_without_an_activated_venv(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`make demo`'s venv is not on PATH: its `.venv/bin/rerun` is still the viewer to spawn (was: 'install the
    viewer: pip install rerun-sdk', with rerun-sdk installed)."""
    from darp.view import viewer_executable

    bin_dir = tmp_path / "venv" / "bin"
    bin_dir.mkdir(parents=True)
    (bin_dir / "rerun").write_text("#!/bin/sh\n")
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    monkeypatch.setattr(sys, "executable", str(bin_dir / "python"))
    assert viewer_executable() is None  # not executable: not a viewer
    (bin_dir / "rerun").chmod(0o755)
    assert viewer_executable() == str(bin_dir / "rerun")
    on_path = tmp_path / "onpath"
    on_path.mkdir()
    (on_path / "rerun").write_text("#!/bin/sh\n")
    (on_path / "rerun").chmod(0o755)
    monkeypatch.setenv("PATH", str(on_path))
    assert viewer_executable() == str(on_path / "rerun")  # PATH first, as a shell would


def test_view_spawns_the_viewer_beside_this_python(survey_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    rr = pytest.importorskip("rerun")
    beside = Path(sys.executable).parent / "rerun"
    if not (beside.is_file() and os.access(beside, os.X_OK)):
        pytest.skip("no rerun viewer beside this Python")
    seen: dict[str, object] = {}

    def spawn(**kwargs: object) -> None:
        seen.update(kwargs)
        raise RuntimeError("stopped before a window opens")

    monkeypatch.setattr(rr, "spawn", spawn)
    monkeypatch.setenv("PATH", "/nonexistent")
    assert run(["view", str(survey_path)]) == 2
    assert seen["executable_path"] == str(beside)
    assert "stopped before a window opens" in capsys.readouterr().err


def test_a_spawned_viewer_that_dies_is_one_error_line(survey_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """A machine without a display: the viewer starts and exits at once; darp says so in one line, exit 2 (was a
    traceback from the last flush, exit 1, after decoding the whole survey)."""
    rr = pytest.importorskip("rerun")
    port = _free_port()

    def spawn(**kwargs: object) -> None:  # what rerun's spawn leaves behind when the viewer died: nobody listening
        kwargs["recording"].connect_grpc(f"rerun+http://127.0.0.1:{port}/proxy")  # type: ignore[attr-defined]

    monkeypatch.setattr(rr, "spawn", spawn)
    assert run(["view", str(survey_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("darp: error: the rerun viewer did not start"), err


def test_an_interrupted_save_leaves_no_recording_under_its_name(survey_path: Path, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """`--save` writes a temporary name beside the file and renames it when complete: a run that fails while
    logging leaves neither a partial .rrd under the final name nor its temporary file (issue 32)."""
    import darp.view as view_module

    def broken(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(view_module, "_log_arms", broken)
    save = tmp_path / "out" / "survey.rrd"
    with pytest.raises(KeyboardInterrupt):
        view_module.view(survey_path, save)
    assert not save.exists() and list(save.parent.iterdir()) == []
    monkeypatch.undo()
    view_module.view(survey_path, save)  # the same command, uninterrupted, writes it
    assert save.is_file() and save.stat().st_size > 0 and [p.name for p in save.parent.iterdir()] == ["survey.rrd"]
