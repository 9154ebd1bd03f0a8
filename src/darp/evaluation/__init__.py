"""darp.evaluation: the paper's measures of a processed survey.

Held-out point-to-mesh error (:mod:`.heldout`, distances in :mod:`.point_to_mesh`), cross-arm consistency
(:mod:`.cross_arm`), metrics against the twin's truth (:mod:`.truth_metrics`), the composition table
(:mod:`.composition`), the figures (:mod:`.figures`, observation maps in :mod:`.observations`) and the trust flags that
say when a survey's figures should not be believed (:mod:`.trust`). Inputs are reconstruction's outputs and files;
Open3D and matplotlib load only when a measure or figure is computed.
"""

from __future__ import annotations

from darp.lazy import LazyExports

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing

_lazy = LazyExports(__name__, {
    ".heldout": ("HeldoutResult", "HeldoutSummary", "evaluate_heldout", "heldout_mask", "heldout_points"),
    ".point_to_mesh": ("DistanceStats", "MeshDistance", "distance_stats", "point_to_mesh_distances"),
    ".cross_arm": ("CrossArmResult", "cross_arm_consistency"),
    ".truth_metrics": ("TruthMetrics",),
    ".composition": ("SurveyComposition", "survey_composition", "format_composition"),
    ".figures": ("cross_arm_figure", "heldout_histogram", "partial_fused_figure"),
    ".observations": ("survey_observations", "observations_figure"),
})
__getattr__ = _lazy.attribute
__dir__ = _lazy.names

if TYPE_CHECKING:
    from darp.evaluation.composition import SurveyComposition, format_composition, survey_composition
    from darp.evaluation.cross_arm import CrossArmResult, cross_arm_consistency
    from darp.evaluation.figures import cross_arm_figure, heldout_histogram, partial_fused_figure
    from darp.evaluation.heldout import HeldoutResult, HeldoutSummary, evaluate_heldout, heldout_mask, heldout_points
    from darp.evaluation.observations import observations_figure, survey_observations
    from darp.evaluation.point_to_mesh import DistanceStats, MeshDistance, distance_stats, point_to_mesh_distances
    from darp.evaluation.truth_metrics import TruthMetrics

__all__ = [
    "CrossArmResult",
    "DistanceStats",
    "HeldoutResult",
    "HeldoutSummary",
    "MeshDistance",
    "SurveyComposition",
    "TruthMetrics",
    "cross_arm_consistency",
    "cross_arm_figure",
    "distance_stats",
    "evaluate_heldout",
    "format_composition",
    "heldout_histogram",
    "heldout_mask",
    "heldout_points",
    "observations_figure",
    "partial_fused_figure",
    "point_to_mesh_distances",
    "survey_composition",
    "survey_observations",
]
