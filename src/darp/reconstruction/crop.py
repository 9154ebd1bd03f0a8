"""The conservative geometric object-support region: the envelope cylinder above the table plane.

The survey's ``manip_envelope.json`` gives a vertical cylinder (centre, radius, height) around the
object. A point supports the object when it lies

- within ``radius + margin_m`` of the cylinder's vertical axis,
- below the cylinder's top plus ``margin_m`` (top = centre z + height / 2),
- above the table plane plus ``table_margin_m`` (the table is ``centre z - height / 2`` unless given).

The margin absorbs an envelope estimated from a few depth frames (the acquisition's localisation);
the table margin keeps the table's own noisy surface out while losing only a few millimetres of the
object's foot. :func:`support_mask` is the same test per pixel of a depth image (the keyframes'
object-support mask).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from darp.errors import ReconstructionError
from darp.formats.envelope import Envelope
from darp.formats.realsense.types import Intrinsics
from darp.reconstruction.backproject import check_pose, depth_to_metres, region_window, world_points

DEFAULT_MARGIN_M = 0.01
DEFAULT_TABLE_MARGIN_M = 0.003


@dataclass(frozen=True)
class EnvelopeCrop:
    """A vertical cylinder around the object, cut by the table plane (world frame, metres)."""

    center_m: tuple[float, float, float]
    radius_m: float
    height_m: float
    table_z_m: float
    margin_m: float = DEFAULT_MARGIN_M
    table_margin_m: float = DEFAULT_TABLE_MARGIN_M

    def __post_init__(self) -> None:
        values = (*self.center_m, self.radius_m, self.height_m, self.table_z_m, self.margin_m,
                  self.table_margin_m)
        if len(self.center_m) != 3 or not all(math.isfinite(v) for v in values):
            raise ReconstructionError("envelope crop: centre, radius, height and table height must be finite")
        if self.radius_m <= 0 or self.height_m <= 0 or self.margin_m < 0:
            raise ReconstructionError("envelope crop: radius and height must be > 0 and the margin >= 0")

    @classmethod
    def from_envelope(cls, envelope: Envelope, *, table_z_m: float | None = None,
                      margin_m: float = DEFAULT_MARGIN_M,
                      table_margin_m: float = DEFAULT_TABLE_MARGIN_M) -> EnvelopeCrop:
        """The crop of a survey envelope; the table defaults to the cylinder's bottom."""
        if not envelope.has_geometry:
            raise ReconstructionError(
                "the survey envelope has no centre/radius/height; cannot crop to the object")
        assert envelope.center_m is not None and envelope.radius_m is not None and envelope.height_m is not None
        cx, cy, cz = (float(c) for c in envelope.center_m)
        table = cz - 0.5 * envelope.height_m if table_z_m is None else float(table_z_m)
        return cls(center_m=(cx, cy, cz), radius_m=float(envelope.radius_m),
                   height_m=float(envelope.height_m), table_z_m=table, margin_m=margin_m,
                   table_margin_m=table_margin_m)

    @property
    def z_range_m(self) -> tuple[float, float]:
        """(lowest, highest) world z that is kept."""
        top = self.center_m[2] + 0.5 * self.height_m + self.margin_m
        return self.table_z_m + self.table_margin_m, top

    @property
    def bounds_m(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned (lower, upper) corners of the kept region."""
        r = self.radius_m + self.margin_m
        z0, z1 = self.z_range_m
        cx, cy = self.center_m[0], self.center_m[1]
        return np.array([cx - r, cy - r, z0]), np.array([cx + r, cy + r, z1])

    def contains(self, points_world: np.ndarray) -> np.ndarray:
        """Boolean (N,): which points lie inside the cylinder and above the table plane."""
        p = np.asarray(points_world)
        r = np.float32(self.radius_m + self.margin_m)
        dx = p[:, 0] - np.float32(self.center_m[0])
        dy = p[:, 1] - np.float32(self.center_m[1])
        z0, z1 = self.z_range_m
        return (dx * dx + dy * dy <= r * r) & (p[:, 2] >= np.float32(z0)) & (p[:, 2] <= np.float32(z1))


def support_mask(depth: np.ndarray, intrinsics: Intrinsics, T_world_cam: np.ndarray,
                 envelope: Envelope | EnvelopeCrop, table_z_m: float | None = None, *,
                 depth_scale: float | None = None, margin_m: float = DEFAULT_MARGIN_M,
                 table_margin_m: float = DEFAULT_TABLE_MARGIN_M) -> np.ndarray:
    """(H, W) bool: pixels whose back-projected point lies in the object-support region.

    ``depth`` is raw Z16 (pass ``depth_scale``) or metric float depth. Pixels without depth are False.
    An :class:`EnvelopeCrop` is used as is (``table_z_m`` and the margins are then ignored).
    """
    if np.issubdtype(np.asarray(depth).dtype, np.integer):
        if depth_scale is None:
            raise ReconstructionError("support_mask: raw integer depth needs depth_scale")
        depth_m = depth_to_metres(depth, depth_scale)
    else:
        depth_m = depth_to_metres(np.asarray(depth), 1.0 if depth_scale is None else depth_scale)
    crop = envelope if isinstance(envelope, EnvelopeCrop) else EnvelopeCrop.from_envelope(
        envelope, table_z_m=table_z_m, margin_m=margin_m, table_margin_m=table_margin_m)
    T = check_pose(T_world_cam)
    h, w = depth_m.shape
    mask = np.zeros((h, w), bool)
    window = region_window(crop, T, intrinsics)  # only pixels that can see the cylinder's box
    r0, r1, c0, c1 = (0, h, 0, w) if window is None else window
    rows, cols = np.nonzero(depth_m[r0:r1, c0:c1] > 0)
    pixels = (rows + r0) * w + (cols + c0)
    if pixels.size:
        inside = crop.contains(world_points(depth_m, intrinsics, T, pixels))
        mask.reshape(-1)[pixels[inside]] = True
    return mask


__all__ = ["DEFAULT_MARGIN_M", "DEFAULT_TABLE_MARGIN_M", "EnvelopeCrop", "support_mask"]
