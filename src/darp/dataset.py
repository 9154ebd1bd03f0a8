"""darp's processed surveys as a learning-ready dataset: keyframes and completion pairs as numpy arrays.

::

    from darp.dataset import KeyframeDataset, completion_pairs
    ds = KeyframeDataset("processed/")            # every survey under processed/ (or one survey folder)
    sample = ds[0]                                # dict of numpy arrays and metadata (see KeyframeDataset)
    pairs = completion_pairs("processed/cube")    # twin surveys: partial / complete clouds, object frame

With torch installed, ``torch_dataset(ds)`` wraps either in a ``torch.utils.data.Dataset`` (torch is
not a dependency of darp; without it the call raises a ``DarpError`` saying so).

Conventions (the same as darp's files): metres; ``T_world_cam`` maps OpenCV camera coordinates
(x right, y down, z forward) to the world frame (the rig's base-to-base frame, z up); ``K`` is the
3x3 pinhole matrix of the depth (left IR) stream with pixel centres at integer coordinates; RGB is
aligned to the depth image, so one ``K`` serves RGB, depth, IR and the mask.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import DarpError, DarpWarning, DecodeError, FormatError
from darp.formats.atomic import UNFINISHED_FILE
from darp.formats.io_input import LIMITS, marker_text
from darp.formats.text import read_utf8_text
from darp.formats.truth import OBJECT_JSON_FILE, OBJECT_MESH_FILE, TRUTH_DIR
from darp.geometry.transforms import transform_points
from darp.reconstruction.backproject import backproject
from darp.reconstruction.cloud_io import read_ply
from darp.reconstruction.keyframe_io import INDEX_FILE, Keyframe, KeyframeInfo, read_keyframe, read_keyframe_index

KEYFRAMES_DIR = "keyframes"
RESULTS_FILE = "results.json"
CLOUD_FILES = {"arm110": "arm110.ply", "arm111": "arm111.ply", "fused": "fused.ply"}
MESH_FILE = "mesh.ply"
COMPLETE_POINTS = 16384  # PCN's complete-cloud size


@dataclass(frozen=True)
class ProcessedSurvey:
    """One survey's output folder of ``darp process`` (``<out>/<survey>/``) and what it points at."""

    folder: Path
    name: str
    survey_path: Path | None  # the raw survey (from results.json), None if unknown or gone
    calibration_path: Path | None = None  # the calibration it was processed with (None: truth or unknown)

    @property
    def keyframes_dir(self) -> Path:
        return self.folder / KEYFRAMES_DIR

    @property
    def truth_dir(self) -> Path | None:
        """The twin's ``truth/`` folder of the raw survey, if this is a twin survey still on disk."""
        if self.survey_path is None or not (self.survey_path / TRUTH_DIR / OBJECT_JSON_FILE).is_file():
            return None
        return self.survey_path / TRUTH_DIR

    def require_truth(self, what: str) -> Path:
        truth = self.truth_dir
        if truth is None:
            raise FormatError(f"{what} needs a twin survey's truth/ folder; results.json's survey_path "
                              f"({self.survey_path}) has none", self.folder)
        return truth

    def cloud(self, name: str) -> np.ndarray:
        """Points (N, 3) float64 of ``arm110``, ``arm111`` or ``fused`` (world frame, metres)."""
        return read_ply(self.folder / CLOUD_FILES[name]).points


def find_processed(path: str | Path) -> list[ProcessedSurvey]:
    """The processed survey folders at ``path``: the folder itself if it holds ``keyframes/``, else its
    subfolders that do (the output folder of a multi-survey ``darp process``)."""
    path = Path(path)
    if not path.is_dir():
        raise FormatError("not a folder", path)
    if (path / UNFINISHED_FILE).is_file():
        raise FormatError(f"its processing did not finish ({_first_line(path / UNFINISHED_FILE)}): run darp "
                          "process again", path)
    candidates = [path] if (path / KEYFRAMES_DIR / INDEX_FILE).is_file() else sorted(
        p for p in path.iterdir() if (p / KEYFRAMES_DIR / INDEX_FILE).is_file())
    unfinished = [p for p in candidates if (p / UNFINISHED_FILE).is_file()]
    for p in unfinished:
        warnings.warn(f"{p}: skipped, its processing did not finish ({_first_line(p / UNFINISHED_FILE)})",
                      DarpWarning, stacklevel=2)
    candidates = [p for p in candidates if p not in unfinished]
    if not candidates:
        raise FormatError(f"no processed survey here (no finished {KEYFRAMES_DIR}/{INDEX_FILE}; run darp process "
                          "first)", path)
    return [_processed(p) for p in candidates]


def _first_line(path: Path) -> str:
    lines = marker_text(path).strip().splitlines()
    return lines[0] if lines else "no reason recorded"


def _resolve(recorded: Any, folder: Path) -> Path | None:
    """A path results.json recorded: as is, or (relative to where darp process ran) against the current
    folder or one of the processed folder's ancestors; None if it is nowhere."""
    if not recorded:
        return None
    path = Path(str(recorded))
    if path.is_absolute():
        return path if path.exists() else None
    for base in (Path.cwd(), *folder.resolve().parents):
        if (base / path).exists():
            return base / path
    return None


def _processed(folder: Path) -> ProcessedSurvey:
    payload: Any = {}
    results = folder / RESULTS_FILE
    if results.is_file():
        try:
            payload = json.loads(read_utf8_text(results, "a JSON file", limit=LIMITS["json"]))
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise FormatError(f"invalid JSON: {err}", results) from err
    if not isinstance(payload, dict):
        payload = {}
    calibration = payload.get("calibration")
    return ProcessedSurvey(folder, folder.name, _resolve(payload.get("survey_path"), folder),
                           _resolve(calibration.get("path") if isinstance(calibration, dict) else None, folder))


def read_object_truth(truth_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """The twin object's true mesh in its canonical (object) frame and its pose: (vertices, triangles,
    T_world_object, object.json)."""
    meta_path = truth_dir / OBJECT_JSON_FILE
    try:
        meta = json.loads(read_utf8_text(meta_path, "a JSON file", limit=LIMITS["json"]))
        T_world_object = np.array(meta["T_world_object"], np.float64)
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise FormatError(f"cannot read the object's pose: {err}", meta_path) from err
    mesh_path = truth_dir / OBJECT_MESH_FILE
    try:  # trimesh: the truth mesh carries face colours, which darp's own PLY reader does not take
        import trimesh

        mesh = trimesh.load(mesh_path, process=False, force="mesh")
        if not isinstance(mesh, trimesh.Trimesh):
            raise DecodeError(f"not a triangle mesh (trimesh read a {type(mesh).__name__})")
        points, triangles = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    except (OSError, ValueError) as err:
        raise FormatError(f"cannot read the object mesh: {err}", mesh_path) from err
    if not len(triangles):
        raise FormatError("the object mesh has no faces", mesh_path)
    return transform_points(np.linalg.inv(T_world_object), points), triangles, T_world_object, meta


# -- keyframes ------------------------------------------------------------------------------------------
def keyframe_sample(kf: Keyframe, survey: str = "") -> dict[str, Any]:
    """One keyframe as a dict of numpy arrays (and a few strings/ints) - what ``KeyframeDataset`` yields."""
    return {
        "rgb": kf.rgb,  # (H, W, 3) uint8, aligned to depth
        "depth_m": kf.depth_m,  # (H, W) float32 metres, 0 = no depth
        "ir_left": kf.ir_left, "ir_right": kf.ir_right,  # (H, W) uint8
        "mask": kf.support_mask,  # (H, W) bool: object support
        "colour_valid": np.asarray(kf.rgb).any(axis=2),  # (H, W) bool: the colour camera saw the pixel
        "depth_valid": kf.depth > 0,  # (H, W) bool: a depth measurement
        "K": kf.intrinsics.K,  # (3, 3) float64
        "distortion_coeffs": np.array(kf.intrinsics.coeffs, np.float64),
        "T_world_cam": np.asarray(kf.T_world_cam, np.float64),  # (4, 4) world-from-camera (OpenCV axes)
        "arm": kf.arm, "split": kf.split, "frame_number": kf.frame_number, "survey": survey,
        "timestamp_ms": kf.timestamp_ms,  # camera clock
        "t_s": kf.t_s,  # host clock: the time of the pose
    }


class KeyframeDataset:
    """Keyframes of one or more processed surveys, read lazily one ``.npz`` at a time.

    ``split`` (``fuse`` or ``heldout``) and ``arm`` filter; items are dicts (:func:`keyframe_sample`):
    ``rgb``, ``depth_m``, ``ir_left``, ``ir_right``, ``mask`` (object support), ``colour_valid``,
    ``depth_valid``, ``K``, ``T_world_cam``, ``arm``, ``split``, ``frame_number``, ``survey``,
    ``timestamp_ms`` (camera clock), ``t_s`` (host clock).
    """

    def __init__(self, path: str | Path, split: str | None = None, arm: str | None = None) -> None:
        self.surveys = find_processed(path)
        self.entries: list[tuple[ProcessedSurvey, KeyframeInfo]] = []
        for survey in self.surveys:
            index = read_keyframe_index(survey.keyframes_dir)
            self.entries += [(survey, info) for info in index.select(split, arm)]

    def __len__(self) -> int:
        return len(self.entries)

    def keyframe(self, i: int) -> Keyframe:
        survey, info = self.entries[i]
        return read_keyframe(survey.keyframes_dir / info.file)

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        survey, _ = self.entries[i]
        return keyframe_sample(self.keyframe(i), survey.name)

    def __iter__(self) -> Iterator[dict[str, Any]]:
        for i in range(len(self)):
            yield self[i]


# -- completion pairs ----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class CompletionPair:
    """A partial observation and the complete shape, both (N, 3) float32 in the object's canonical frame
    (metres; ``T_world_object`` of the twin's truth maps it to the world)."""

    name: str  # e.g. "cube/arm110_000033", "cube/arm110", "cube/fused"
    kind: str  # "keyframe", "arm" or "fused"
    partial: np.ndarray
    complete: np.ndarray
    T_world_object: np.ndarray


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points uniformly on a triangle mesh (area-weighted, seeded): PCN's complete cloud."""
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, np.float64)[np.asarray(triangles)]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    tri = rng.choice(len(v), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = 1 - s, s * (1 - r2), s * r2
    return np.asarray(a[:, None] * v[tri, 0] + b[:, None] * v[tri, 1] + c[:, None] * v[tri, 2], np.float32)


def keyframe_object_points(kf: Keyframe) -> np.ndarray:
    """World points (N, 3) of one keyframe on the object's support (depth filters of fusion, mask)."""
    cloud = backproject(kf.posed_depth(colour=False))
    keep = kf.support_mask.reshape(-1)[cloud.pixels]
    return np.asarray(cloud.points[keep], np.float64)


def completion_pairs(path: str | Path, complete_points: int = COMPLETE_POINTS, seed: int = 0,
                     keyframe_partials: bool = True) -> Iterator[CompletionPair]:
    """Partial / complete pairs of twin surveys: one per keyframe (its object points), one per arm's
    cloud and one for the fused cloud; the complete cloud is sampled from the true mesh."""
    for survey in find_processed(path):
        vertices, triangles, T_wo, _ = read_object_truth(survey.require_truth("completion pairs"))
        T_ow = np.linalg.inv(T_wo)
        complete = sample_surface(vertices, triangles, complete_points, seed)
        if keyframe_partials:
            index = read_keyframe_index(survey.keyframes_dir)
            for info in index.keyframes:
                kf = read_keyframe(index.folder / info.file)
                partial = transform_points(T_ow, keyframe_object_points(kf)).astype(np.float32)
                yield CompletionPair(f"{survey.name}/{kf.arm}_{kf.frame_number:06d}", "keyframe", partial,
                                     complete, T_wo)
        for name in CLOUD_FILES:
            if (survey.folder / CLOUD_FILES[name]).is_file():
                partial = transform_points(T_ow, survey.cloud(name)).astype(np.float32)
                yield CompletionPair(f"{survey.name}/{name}", "fused" if name == "fused" else "arm", partial,
                                     complete, T_wo)


def torch_dataset(items: KeyframeDataset | Sequence[Any]) -> Any:
    """A ``torch.utils.data.Dataset`` over ``items`` (arrays become tensors); needs torch installed."""
    try:
        import torch
        from torch.utils.data import Dataset
    except ImportError:
        raise DarpError("the PyTorch wrapper needs torch (pip install torch); the numpy API works without it") \
            from None

    def tensors(item: Any) -> Any:
        if isinstance(item, CompletionPair):
            item = {"partial": item.partial, "complete": item.complete, "name": item.name}
        return {k: torch.from_numpy(np.ascontiguousarray(v)) if isinstance(v, np.ndarray) else v
                for k, v in item.items()}

    class _Wrapped(Dataset[Any]):  # type: ignore[misc, unused-ignore]  # Any where torch is not installed
        def __len__(self) -> int:
            return len(items)

        def __getitem__(self, i: int) -> Any:
            return tensors(items[i])

    return _Wrapped()


__all__ = [
    "COMPLETE_POINTS",
    "CompletionPair",
    "KeyframeDataset",
    "ProcessedSurvey",
    "completion_pairs",
    "find_processed",
    "keyframe_object_points",
    "keyframe_sample",
    "read_object_truth",
    "sample_surface",
    "torch_dataset",
]
