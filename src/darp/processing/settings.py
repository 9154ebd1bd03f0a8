"""Settings of ``darp process``: keyframes, fusion (with its depth filters), meshing and evaluation.

A settings file (YAML or JSON) gives any subset; everything not given keeps its default::

    keyframes: {per_view: 3, min_separation_deg: 6, heldout_every: 5}
    fusion: {voxel_size_m: 0.0015, min_frames: 3, depth: {max_depth_m: 1.0}}
    mesh: {radius_factors: [2, 4, 8]}
    surface: {method: auto}    # auto | paper | measured (auto: measured for imported surveys, paper for DARP ones)
    evaluation: {truth_sample_spacing_m: 0.001, figures: true}
    corrections: {kinematics: true, depth: true, time: true, refine: true, table: true, fusion: true, mesh: true}
    refinement: {max_sigma: 2.0, per_view: true}   # parameters of corrections.refine

``corrections`` switches darp's improvements over the paper's method (docs/accuracy.md); all off is
"paper mode": camera poses from the calibration and the kinematics alone, as the paper computed them.

Unknown keys are errors naming the file and the key (a typo must not silently keep a default).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from darp.errors import ConfigError
from darp.formats.schema import dataclass_from_mapping, refuse_unknown_keys
from darp.formats.text import read_yaml_mapping
from darp.reconstruction.backproject import DepthFilterSettings
from darp.reconstruction.fusion import FusionSettings
from darp.reconstruction.keyframes import KeyframeSettings
from darp.reconstruction.mesh import MeshSettings
from darp.reconstruction.refine import RefineSettings
from darp.reconstruction.tsdf_surface import SurfaceSettings


@dataclass(frozen=True)
class EvaluationSettings:
    """What the evaluation stage measures and draws."""

    truth_sample_spacing_m: float = 0.001  # area-uniform samples of the true surface (twin only)
    visibility_tolerance_m: float = 0.005  # a true sample is 'seen' when a keyframe's depth is this close
    figures: bool = True  # cross-arm, partial/fused and held-out histogram figures
    seed: int = 0  # random sampling of surfaces (truth metrics)
    max_heldout_median_mm: float = 10.0  # a held-out median above this is flagged implausible (paper: 2.13)
    # twin surveys: a fused cloud whose median distance to the true mesh is above this is flagged implausible
    # (the held-out median measures self-consistency and cannot see whole views moved together)
    max_truth_accuracy_mm: float = 10.0
    # a fused cloud whose voxels cover less than this share of the envelope's top and side is flagged implausible
    # (an almost empty reconstruction: the held-out figures are then measured against almost no surface)
    min_surface_pct: float = 2.0
    # twin surveys with recorded feasible poses: truth.seeable.missing_by_cause, why each seeable sample farther
    # than missing_threshold_m from the fused cloud is missing (fuses the keyframes a second time: off by default,
    # it made the evaluation stage about 5x slower on a 640x480 survey)
    missing_by_cause: bool = False
    missing_threshold_m: float = 0.005

    def __post_init__(self) -> None:
        if not (self.truth_sample_spacing_m > 0 and self.visibility_tolerance_m > 0):
            raise ConfigError("evaluation: truth_sample_spacing_m and visibility_tolerance_m must be > 0")
        if not self.missing_threshold_m > 0:
            raise ConfigError("evaluation: missing_threshold_m must be > 0")
        if not (self.max_heldout_median_mm > 0 and self.max_truth_accuracy_mm > 0):
            raise ConfigError("evaluation: max_heldout_median_mm and max_truth_accuracy_mm must be > 0")
        if not 0 <= self.min_surface_pct <= 100:
            raise ConfigError(f"evaluation: min_surface_pct must be within 0 .. 100, got {self.min_surface_pct}")


CORRECTIONS = ("kinematics", "time", "depth", "refine", "table", "fusion", "mesh")

# corrections.fusion: darp's fusion rules (docs/processing.md, "darp's fusion rules"), each applied where the
# setting still holds its default, so a value given in the settings file wins. They keep surface that the
# paper's per-arm support and outlier rules drop (thin rims, the sides between the arms, sparse true surface).
FUSION_RULES: dict[str, Any] = {"arm_support_from_fused": 1, "sor_local_ratio": 2.0, "support_neighbourhood": 1,
                                "neighbourhood_plane_voxels": 0.5, "neighbourhood_holes_only": 2,
                                "support_cell_voxels": 2}
DEPTH_FILTER_RULES: dict[str, Any] = {"edge_margin_px": 0}
# corrections.mesh: ball pivoting per normal side (MeshSettings.split_sides), where the file kept the default
MESH_RULES: dict[str, Any] = {"split_sides": True}
_Group = TypeVar("_Group", FusionSettings, DepthFilterSettings, MeshSettings)


def _with_rules(given: _Group, rules: dict[str, Any]) -> _Group:
    """``given`` with each of ``rules`` applied where ``given`` still holds its class's default."""
    default = type(given)()
    return dataclasses.replace(given, **{k: v for k, v in rules.items() if getattr(given, k) == getattr(default, k)})


@dataclass(frozen=True)
class CorrectionSettings:
    """Which of darp's improvements over the paper's method to apply (all off: paper mode)."""

    kinematics: bool = False  # the calibration's richer kinematic model (link, axis and compliance terms)
    time: bool = False  # the calibration's camera-to-joint-log time offset
    depth: bool = False  # the calibration's per-camera depth scale and offset, at back-projection
    refine: bool = False  # survey-level pose refinement from overlapping depth, within the calibration's bounds
    table: bool = False  # each keyframe cut at its own fitted table plane instead of the crop's floor
    fusion: bool = False  # darp's fusion rules (FUSION_RULES, DEPTH_FILTER_RULES) instead of the paper's support
    mesh: bool = False  # darp's meshing rules (MESH_RULES): the two sides of thin walls pivoted apart

    @classmethod
    def parse(cls, spec: str) -> CorrectionSettings:
        """``paper`` (none), ``all``, or a comma-separated subset of kinematics, time, depth, refine, table,
        fusion, mesh."""
        words = [w.strip().lower() for w in spec.split(",") if w.strip()]
        if words == ["paper"] or words == ["none"]:
            return cls()
        if words == ["all"]:
            return cls(**dict.fromkeys(CORRECTIONS, True))
        unknown = sorted(set(words) - set(CORRECTIONS))
        if unknown or not words:
            raise ConfigError(f"corrections: unknown {', '.join(unknown) or 'empty list'} "
                              f"(use paper, all, or a list of {', '.join(CORRECTIONS)})")
        return cls(**{name: name in words for name in CORRECTIONS})

    @property
    def applied(self) -> tuple[str, ...]:
        """The names of the corrections switched on, in a fixed order."""
        return tuple(name for name in CORRECTIONS if getattr(self, name))

    @property
    def label(self) -> str:
        """``paper`` when none is on, ``all`` when all are, else the names joined by ``+``."""
        on = self.applied
        return "paper" if not on else "all" if len(on) == len(CORRECTIONS) else "+".join(on)


# Settings added after results.json records and stage fingerprints were first written. Each is left out of
# ``to_dict`` while it holds its default, so a record written before it existed reads the same and a processed
# folder's stages are not redone only because darp learnt a new option. Append new settings here.
ADDED_LATER: tuple[tuple[str, str], ...] = (
    ("corrections", "table"),
    ("corrections", "fusion"),
    ("corrections", "mesh"),
    ("fusion", "support_neighbourhood"),
    ("fusion", "arm_support_from_fused"),
    ("fusion", "sor_local_ratio"),
    ("fusion", "neighbourhood_own_frames"),
    ("fusion", "neighbourhood_plane_voxels"),
    ("fusion", "neighbourhood_holes_only"),
    ("fusion", "support_cell_voxels"),
    ("evaluation", "missing_by_cause"),
    ("evaluation", "missing_threshold_m"),
    ("mesh", "split_sides"),
    ("keyframes", "heldout_unit"),
)

# Whole groups added later: left out of ``to_dict`` while every setting in them holds its default.
ADDED_LATER_GROUPS: tuple[str, ...] = ("surface",)


@dataclass(frozen=True)
class ProcessSettings:
    """Every setting of the processing pipeline."""

    keyframes: KeyframeSettings = field(default_factory=KeyframeSettings)
    fusion: FusionSettings = field(default_factory=FusionSettings)
    mesh: MeshSettings = field(default_factory=MeshSettings)
    evaluation: EvaluationSettings = field(default_factory=EvaluationSettings)
    corrections: CorrectionSettings = field(default_factory=CorrectionSettings)
    refinement: RefineSettings = field(default_factory=RefineSettings)  # parameters of corrections.refine
    surface: SurfaceSettings = field(default_factory=SurfaceSettings)  # which surface (auto: measured if imported)

    @property
    def mesh_used(self) -> MeshSettings:
        """The meshing settings the pipeline uses: ``mesh``, with darp's meshing rules where ``corrections.mesh``
        is on and the setting holds its default."""
        return _with_rules(self.mesh, MESH_RULES) if self.corrections.mesh else self.mesh

    @property
    def fusion_used(self) -> FusionSettings:
        """The fusion settings the pipeline uses: ``fusion``, with darp's fusion rules where ``corrections.fusion``
        is on and the setting holds its default (a value the user gave is kept)."""
        if not self.corrections.fusion:
            return self.fusion
        depth = _with_rules(self.fusion.depth, DEPTH_FILTER_RULES)
        return _with_rules(dataclasses.replace(self.fusion, depth=depth), FUSION_RULES)

    def to_dict(self) -> dict[str, Any]:
        """Plain values of every group, less the :data:`ADDED_LATER` settings that hold their defaults."""
        plain: dict[str, Any] = json.loads(json.dumps(dataclasses.asdict(self)))
        defaults: dict[str, Any] = json.loads(json.dumps(dataclasses.asdict(ProcessSettings())))
        for group, name in ADDED_LATER:
            if plain[group][name] == defaults[group][name]:
                del plain[group][name]
        for group in ADDED_LATER_GROUPS:
            if plain[group] == defaults[group]:
                del plain[group]
        return plain

    def fingerprint(self, *groups: str) -> str:
        """Short hash of the given groups' values (all when none): changes when any of them changes."""
        values = self.to_dict()
        chosen = {g: values[g] for g in (groups or tuple(values)) if g in values}
        return hashlib.sha256(json.dumps(chosen, sort_keys=True).encode()).hexdigest()[:16]


def _floats(values: Any) -> tuple[float, ...]:
    return tuple(float(f) for f in values)


def settings_from_dict(values: Mapping[str, Any]) -> ProcessSettings:
    """Build :class:`ProcessSettings` from a (partial) mapping; errors name the offending key."""
    refuse_unknown_keys(values, ("keyframes", "fusion", "mesh", "evaluation", "corrections", "refinement",
                                 "surface"), error=ConfigError)
    return ProcessSettings(
        keyframes=dataclass_from_mapping(KeyframeSettings, values.get("keyframes"), "keyframes", error=ConfigError),
        fusion=dataclass_from_mapping(FusionSettings, values.get("fusion"), "fusion", nested={
            "depth": DepthFilterSettings}, error=ConfigError),
        mesh=dataclass_from_mapping(MeshSettings, values.get("mesh"), "mesh", convert={"radius_factors": _floats},
                                    error=ConfigError),
        evaluation=dataclass_from_mapping(EvaluationSettings, values.get("evaluation"), "evaluation",
                                          error=ConfigError),
        corrections=dataclass_from_mapping(CorrectionSettings, values.get("corrections"), "corrections",
                                           error=ConfigError),
        refinement=dataclass_from_mapping(RefineSettings, values.get("refinement"), "refinement",
                                          convert={"max_correspondence_m": _floats}, error=ConfigError),
        surface=dataclass_from_mapping(SurfaceSettings, values.get("surface"), "surface", error=ConfigError),
    )


def load_settings(path: str | Path) -> ProcessSettings:
    """Read a settings file (YAML or JSON, any subset of the groups)."""
    path = Path(path)
    values = read_yaml_mapping(path, empty_ok=True)  # JSON is YAML too
    try:
        return settings_from_dict(values)
    except ConfigError as err:
        raise ConfigError(err.message, path) from None


__all__ = ["CORRECTIONS", "CorrectionSettings", "EvaluationSettings", "ProcessSettings", "load_settings",
           "settings_from_dict"]
