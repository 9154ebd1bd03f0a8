"""darp.geometry: the plain geometry every layer shares, at the bottom of the layer order (numpy, scipy and
:mod:`darp.errors` only; no files, no robots).

- :mod:`~darp.geometry.transforms`: SE(3) / SO(3) arithmetic (point mapping, Rodrigues, quaternions, skew);
- :mod:`~darp.geometry.rigid`: the one rigidity rule (tolerance, check, re-orthonormalisation);
- :mod:`~darp.geometry.pinhole`: pixels to rays and points and back, lens distortion (librealsense's models);
- :mod:`~darp.geometry.circle`: the smallest enclosing circle.
"""

from darp.geometry.circle import min_enclosing_circle
from darp.geometry.pinhole import backproject_rays, normalised_pixels, project
from darp.geometry.rigid import RIGID_TOLERANCE, check_rigid, orthonormalised
from darp.geometry.transforms import rotvec_to_rotation, skew, transform_points

__all__ = ["RIGID_TOLERANCE", "backproject_rays", "check_rigid", "min_enclosing_circle", "normalised_pixels",
           "orthonormalised", "project", "rotvec_to_rotation", "skew", "transform_points"]
