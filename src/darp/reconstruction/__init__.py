"""darp.reconstruction: from a survey's recordings and joint log to posed keyframes, fused clouds and meshes.

Camera poses by eq. 1 (:mod:`.poses`), keyframe selection (:mod:`.keyframes`) and export (:mod:`.keyframe_io`),
back-projection (:mod:`.backproject`, depth edges in :mod:`.depth_edges`, colour alignment in :mod:`.align`), the
envelope crop and estimate (:mod:`.crop`, :mod:`.envelope_estimate`, the table plane in :mod:`.table_plane`), optional
pose refinement and time alignment (:mod:`.refine`, rigid registration in :mod:`.registration`, :mod:`.time_align`),
voxel fusion (:mod:`.fusion`, support in :mod:`.voxel_support`, point filters in :mod:`.cloud_filters`, statistics in
:mod:`.voxel_stats`), the measured surface of imported surveys (a supported TSDF, :mod:`.tsdf_surface`, with thresholds
from the survey's own depth, :mod:`.depth_stats`), meshing (:mod:`.mesh`), PLY files (:mod:`.cloud_io`) and rig figures
(:mod:`.rig_figures`). Open3D and OpenCV load only when a stage that needs them runs.
"""

from __future__ import annotations

from darp.lazy import LazyExports

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing

_lazy = LazyExports(__name__, {
    ".poses": ("CameraTrajectory", "SurveyPoses", "recover_survey_poses", "write_survey_poses"),
    ".keyframes": ("KeyframeSettings", "select_survey_keyframes"),
    ".keyframe_io": (
        "Keyframe", "KeyframeIndex", "export_arm_keyframes", "iter_keyframes", "load_keyframes", "read_keyframe"
    ),
    ".backproject": ("DepthFilterSettings", "FrameCloud", "world_points"),
    ".crop": ("EnvelopeCrop",),
    ".envelope_estimate": ("EnvelopeEstimateSettings", "estimate_survey_envelope"),
    ".fusion": ("FusionResult", "FusionSettings", "fuse"),
    ".mesh": ("MeshSettings", "ball_pivoting_mesh", "write_mesh"),
    ".cloud_io": ("read_ply", "write_cloud_ply"),
    ".refine": ("RefineSettings", "refine_poses"),
})
__getattr__ = _lazy.attribute
__dir__ = _lazy.names

if TYPE_CHECKING:
    from darp.reconstruction.backproject import DepthFilterSettings, FrameCloud, world_points
    from darp.reconstruction.cloud_io import read_ply, write_cloud_ply
    from darp.reconstruction.crop import EnvelopeCrop
    from darp.reconstruction.envelope_estimate import EnvelopeEstimateSettings, estimate_survey_envelope
    from darp.reconstruction.fusion import FusionResult, FusionSettings, fuse
    from darp.reconstruction.keyframe_io import (
        Keyframe,
        KeyframeIndex,
        export_arm_keyframes,
        iter_keyframes,
        load_keyframes,
        read_keyframe,
    )
    from darp.reconstruction.keyframes import KeyframeSettings, select_survey_keyframes
    from darp.reconstruction.mesh import MeshSettings, ball_pivoting_mesh, write_mesh
    from darp.reconstruction.poses import CameraTrajectory, SurveyPoses, recover_survey_poses, write_survey_poses
    from darp.reconstruction.refine import RefineSettings, refine_poses

__all__ = [
    "CameraTrajectory",
    "DepthFilterSettings",
    "EnvelopeCrop",
    "EnvelopeEstimateSettings",
    "FrameCloud",
    "FusionResult",
    "FusionSettings",
    "Keyframe",
    "KeyframeIndex",
    "KeyframeSettings",
    "MeshSettings",
    "RefineSettings",
    "SurveyPoses",
    "ball_pivoting_mesh",
    "estimate_survey_envelope",
    "export_arm_keyframes",
    "fuse",
    "iter_keyframes",
    "load_keyframes",
    "read_keyframe",
    "read_ply",
    "recover_survey_poses",
    "refine_poses",
    "select_survey_keyframes",
    "world_points",
    "write_cloud_ply",
    "write_mesh",
    "write_survey_poses",
]
