"""Shape-completion export of twin surveys in PCN's layout, as PoinTr's ``PCN`` dataset class reads it.

Layout (PoinTr's ``cfgs/dataset_configs/PCN.yaml`` and ``datasets/PCNDataset.py``)::

    PCN.json                                    [{taxonomy_id, taxonomy_name, train: [...], val: [...], test: [...]}]
    PCN.yaml                                    PoinTr's dataset config for this folder (paths, N_POINTS, N_RENDERINGS)
    <subset>/complete/<taxonomy_id>/<model_id>.pcd       16384 points sampled on the true surface
    <subset>/partial/<taxonomy_id>/<model_id>/NN.pcd     single-view partials: one keyframe's object points
    multiview/<taxonomy_id>/<model_id>/<cloud>.pcd       darp's multi-view clouds (arm110, arm111, fused)
    pairs.json                                  every partial: files, kind, keyframe, points, T_world_model

A taxonomy is one object (``taxonomy_id`` its 8-digit index, as ShapeNet's synset ids are 8 digits), a
model one survey. All clouds are in the model frame of the BOP export: the twin's object frame moved to
its bounding-box centre (``T_world_model`` maps it to the world), metres, binary float32 PCD.

Subsets: each object's surveys in order, ``i % 10`` < 8 train, 8 val, 9 test. PoinTr reads partials
``00`` .. ``07`` of a training model (it draws one of 8 at random) and ``00`` of a val/test model, so a
training model with fewer than 8 partials repeats them (``repeat_of`` in ``pairs.json``). Partials are
ordered round-robin over the survey's views, so the first eight see the object from different sides.
Keyframe partials with fewer than ``MIN_PARTIAL_POINTS`` points are left out (PoinTr samples 2048 points
per partial and pads with zeros: a partial of a few points is mostly padding).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from darp.dataset import ProcessedSurvey, completion_pairs, read_object_truth
from darp.export._io import write_lines, write_pcd
from darp.formats.atomic import write_json_atomic
from darp.geometry import transform_points
from darp.reconstruction.keyframe_io import read_keyframe_index

MIN_PARTIAL_POINTS = 256  # 1/8 of the 2048 points PoinTr samples from a partial
N_RENDERINGS = 8  # PoinTr's PCN: partials read per training model
COMPLETE_POINTS = 16384  # PCN's complete-cloud size (PoinTr asserts it)
SUBSETS = ("train", "val", "test")


def subset_of(i: int) -> str:
    """The subset of an object's ``i``-th survey: 8 in 10 train, then one val, one test."""
    return "train" if i % 10 < 8 else "val" if i % 10 == 8 else "test"


def _round_robin(names: list[str], views: dict[str, tuple[str, int]]) -> list[str]:
    """``names`` interleaved across their (arm, view) groups: one of each group, then the next of each."""
    groups: dict[tuple[str, int], list[str]] = {}
    for name in names:
        groups.setdefault(views[name], []).append(name)
    ordered: list[str] = []
    depth = 0
    while len(ordered) < len(names):
        ordered += [g[depth] for g in groups.values() if depth < len(g)]
        depth += 1
    return ordered


def export_completion(surveys: list[ProcessedSurvey], out: Path, complete_points: int = COMPLETE_POINTS,
                      seed: int = 0, min_points: int = MIN_PARTIAL_POINTS) -> dict[str, Any]:
    """PCN-layout partial/complete pairs of twin surveys (see the module docstring)."""
    by_object: dict[str, list[ProcessedSurvey]] = {}
    for survey in surveys:
        _, _, _, meta = read_object_truth(survey.require_truth("the completion export"))
        by_object.setdefault(str(meta.get("name", survey.name)), []).append(survey)
    categories, pairs, dropped = [], [], []
    for t, obj in enumerate(sorted(by_object), start=1):
        taxonomy = f"{t:08d}"
        category: dict[str, Any] = {"taxonomy_id": taxonomy, "taxonomy_name": obj, **{s: [] for s in SUBSETS}}
        for i, survey in enumerate(by_object[obj]):
            subset = subset_of(i)
            vertices, _, T_world_object, _ = read_object_truth(survey.require_truth("the completion export"))
            T_object_model = np.eye(4)
            T_object_model[:3, 3] = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
            T_model_object = np.linalg.inv(T_object_model)
            index = read_keyframe_index(survey.keyframes_dir)
            views = {f"{survey.name}/{k.arm}_{k.frame_number:06d}": (k.arm, k.view) for k in index.keyframes}
            singles: dict[str, np.ndarray] = {}
            wrote_complete = False
            complete_rel = f"{subset}/complete/{taxonomy}/{survey.name}.pcd"
            for pair in completion_pairs(survey.folder, complete_points=complete_points, seed=seed):
                if not wrote_complete:
                    write_pcd(out / complete_rel, transform_points(T_model_object, pair.complete).astype(np.float32))
                    wrote_complete = True
                partial = transform_points(T_model_object, pair.partial).astype(np.float32)
                if pair.name not in views:  # a multi-view cloud (arm110, arm111, fused)
                    write_pcd(out / "multiview" / taxonomy / survey.name / f"{pair.name.split('/', 1)[1]}.pcd",
                              partial)
                    pairs.append(_pair(f"multiview/{taxonomy}/{survey.name}/{pair.name.split('/', 1)[1]}.pcd",
                                       complete_rel, pair.kind, obj, survey.name, partial, T_world_object,
                                       T_object_model, subset=None))
                    continue
                if len(partial) < min_points:
                    dropped.append({"keyframe": pair.name, "points": len(partial)})
                    continue
                singles[pair.name] = partial
            if not singles:
                continue
            ordered = _round_robin(list(singles), views)
            count = max(len(ordered), N_RENDERINGS if subset == "train" else 1)
            for n in range(count):
                name = ordered[n % len(ordered)]
                rel = f"{subset}/partial/{taxonomy}/{survey.name}/{n:02d}.pcd"
                write_pcd(out / rel, singles[name])
                pairs.append(_pair(rel, complete_rel, "keyframe", obj, survey.name, singles[name], T_world_object,
                                   T_object_model, subset=subset, keyframe=name.split("/", 1)[1],
                                   repeat_of=None if n < len(ordered) else f"{ordered.index(name):02d}"))
            category[subset].append(survey.name)
        categories.append(category)
    write_json_atomic(out / "PCN.json", categories)
    root = out.resolve()
    write_lines(out / "PCN.yaml", [
        "NAME: PCN", f"CATEGORY_FILE_PATH: {root / 'PCN.json'}", f"N_POINTS: {complete_points}",
        f"N_RENDERINGS: {N_RENDERINGS}", f"PARTIAL_POINTS_PATH: {root}/%s/partial/%s/%s/%02d.pcd",
        f"COMPLETE_POINTS_PATH: {root}/%s/complete/%s/%s.pcd", "CARS: False"])
    write_json_atomic(out / "pairs.json", {
        "frame": "model: the object frame moved to its bounding-box centre, metres",
        "min_partial_points": min_points, "dropped": dropped, "pairs": pairs})
    return {"pairs": len(pairs), "dropped": len(dropped), "objects": len(categories)}


def _pair(partial: str, complete: str, kind: str, obj: str, survey: str, points: np.ndarray,
          T_world_object: np.ndarray, T_object_model: np.ndarray, **extra: Any) -> dict[str, Any]:
    return {"partial": partial, "complete": complete, "kind": kind, "object": obj, "survey": survey,
            "points": len(points), **extra, "T_world_model": (T_world_object @ T_object_model).tolist()}


__all__ = ["MIN_PARTIAL_POINTS", "N_RENDERINGS", "export_completion", "subset_of"]
