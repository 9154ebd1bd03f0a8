"""darp.dataset: keyframes and completion pairs as numpy, and the optional PyTorch wrapper."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from darp.dataset import KeyframeDataset, completion_pairs, sample_surface, torch_dataset
from darp.errors import DarpError, FormatError
from darp.evaluation.point_to_mesh import point_to_mesh_distances

pytestmark = pytest.mark.slow  # needs the processed twin survey


def test_keyframes_are_numpy_with_pose_intrinsics_and_split(processed_path: Path) -> None:
    ds = KeyframeDataset(processed_path.parent)  # the output folder of darp process: every survey in it
    index = json.loads((processed_path / "keyframes" / "keyframes.json").read_text())
    assert len(ds) == len(index["keyframes"]) > 0
    heldout = KeyframeDataset(processed_path, split="heldout")
    assert 0 < len(heldout) < len(ds) and all(s["split"] == "heldout" for s in heldout)
    s = ds[0]
    h, w = s["depth_m"].shape
    assert s["rgb"].shape == (h, w, 3) and s["rgb"].dtype == np.uint8 and s["mask"].dtype == bool
    assert s["depth_m"].dtype == np.float32 and 0.1 < np.median(s["depth_m"][s["mask"]]) < 1.0  # metres
    assert s["K"].shape == (3, 3) and s["T_world_cam"].shape == (4, 4) and s["arm"] in ("arm110", "arm111")
    # the mask's pixels, back-projected with K and the pose, lie on the true object (truth poses: mm)
    v, u = np.nonzero(s["mask"] & (s["depth_m"] > 0))
    z = s["depth_m"][v, u].astype(np.float64)
    K = s["K"]
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    world = cam @ s["T_world_cam"][:3, :3].T + s["T_world_cam"][:3, 3]
    survey = Path(json.loads((processed_path / "results.json").read_text())["survey_path"])
    import trimesh

    mesh = trimesh.load(survey / "truth" / "object.ply", process=False, force="mesh")
    d = point_to_mesh_distances(world, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    assert np.median(d) < 0.004


def test_completion_pairs_per_keyframe_arm_and_fused(processed_path: Path) -> None:
    pairs = list(completion_pairs(processed_path, complete_points=2048))
    assert {p.kind for p in pairs} == {"keyframe", "arm", "fused"}
    assert all(p.complete.shape == (2048, 3) and p.partial.dtype == np.float32 for p in pairs)
    fused = next(p for p in pairs if p.kind == "fused")
    # canonical frame: the object sits at the origin, whatever its placement in the world
    assert np.linalg.norm(fused.complete.mean(axis=0)[:2]) < 0.01
    assert np.linalg.norm(fused.partial.mean(axis=0)[:2]) < 0.02


def test_surface_samples_are_seeded_and_on_the_mesh() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    t = np.array([[0, 1, 2], [0, 1, 3]])
    a, b = sample_surface(v, t, 500, seed=3), sample_surface(v, t, 500, seed=3)
    np.testing.assert_array_equal(a, b)
    assert point_to_mesh_distances(a, v, t).max() < 1e-6


def test_a_folder_without_keyframes_is_a_format_error(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="no processed survey"):
        KeyframeDataset(tmp_path)


def test_the_torch_wrapper_says_torch_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "torch", None)  # what an environment without torch sees: ImportError
    with pytest.raises(DarpError, match="needs torch"):
        torch_dataset([])


@pytest.mark.skipif(importlib.util.find_spec("torch") is None, reason="torch is not installed (the test extra has it)")
def test_torch_dataloader_batches_keyframes_and_completion_pairs(processed_path: Path) -> None:
    """torch's own DataLoader and default collate over the wrapper: batched tensors equal to the numpy items."""
    import torch
    from torch.utils.data import DataLoader

    ds = KeyframeDataset(processed_path, split="fuse")
    batch = next(iter(DataLoader(torch_dataset(ds), batch_size=3, shuffle=False)))
    h, w = ds[0]["depth_m"].shape
    assert batch["rgb"].shape == (3, h, w, 3) and batch["rgb"].dtype == torch.uint8
    assert batch["colour_valid"].dtype == torch.bool and batch["depth_valid"].shape == (3, h, w)
    for k in range(3):
        item = ds[k]
        np.testing.assert_array_equal(batch["T_world_cam"][k].numpy(), item["T_world_cam"])
        np.testing.assert_array_equal(batch["depth_m"][k].numpy(), item["depth_m"])
        np.testing.assert_array_equal(batch["mask"][k].numpy(), item["mask"])
        assert batch["arm"][k] == item["arm"] and float(batch["t_s"][k]) == item["t_s"]
        assert not (item["colour_valid"] & ~item["depth_valid"]).any()  # colour only where depth was aligned
    pairs = [p for p in completion_pairs(processed_path, complete_points=512) if p.kind != "keyframe"]
    loaded = list(DataLoader(torch_dataset(pairs), batch_size=1))
    assert len(loaded) == len(pairs) == 3 and loaded[0]["complete"].shape == (1, 512, 3)


def test_unfinished_processed_folders_are_refused_or_skipped(tmp_path: Path) -> None:
    """A folder marked UNFINISHED.txt by an interrupted or failed darp process is never read as a result."""
    from darp.dataset import find_processed
    from darp.errors import DarpWarning, FormatError
    from darp.formats.atomic import UNFINISHED_FILE
    from darp.reconstruction.keyframe_io import INDEX_FILE

    for name in ("done", "broken"):
        (tmp_path / name / "keyframes").mkdir(parents=True)
        (tmp_path / name / "keyframes" / INDEX_FILE).write_text("{}", encoding="utf-8")
    (tmp_path / "broken" / UNFINISHED_FILE).write_text("fuse failed: no point\n", encoding="utf-8")
    with pytest.raises(FormatError, match="did not finish .fuse failed: no point."):
        find_processed(tmp_path / "broken")
    with pytest.warns(DarpWarning, match="broken: skipped"):
        found = find_processed(tmp_path)
    assert [s.name for s in found] == ["done"]
