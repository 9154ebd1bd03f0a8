"""Per-keyframe fitted table plane (issue 16; ``corrections.table``; docs/accuracy.md "Table plane crop").

The envelope crop (:mod:`darp.reconstruction.crop`) cuts the world at a horizontal plane: the table height
the acquisition assumed, raised by a margin that grows with the calibration's stated uncertainty. A view
whose pose is off by a few millimetres sees the real table that much above or below that plane: the table
points above it enter the fused cloud (and the held-out evaluation), those of a low view leave a gap.

With ``corrections.table`` each keyframe's table is fitted in that keyframe's own world points: a RANSAC
plane through the points of a ring around the envelope (outside the object's cylinder) within ``band_m`` of
the crop's table height, refined by least squares on its inliers. The keyframe then keeps only points at
least ``margin_m`` above its own plane (and inside the cylinder, below its top). Because the plane and the
object's points come from the same depth image and the same pose, a pose error moves both alike: the margin
only has to cover depth noise and the plane fit, not the calibration's uncertainty, which sets the band the
plane is searched in instead. A keyframe whose ring has too few points, or whose plane is tilted more than
``max_tilt_deg``, keeps the envelope crop unchanged (recorded).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from darp.reconstruction.backproject import DepthFilterSettings, PosedDepth, backproject
from darp.reconstruction.crop import EnvelopeCrop


@dataclass(frozen=True)
class TableSettings:
    """Parameters of the fitted table plane (fixed: the switch is ``corrections.table``)."""

    ring_m: float = 0.06  # the ring: from the crop's radius (with its margin) outward by this
    band_m: float = 0.015  # table points searched within this of the crop's table height (at least) ...
    band_calibration_factor: float = 3.0  # ... or this times the calibration's stated p90 error
    inlier_m: float = 0.002  # RANSAC inlier distance
    iterations: int = 200
    min_points: int = 300  # ring points needed to fit a plane
    max_tilt_deg: float = 5.0  # a plane tilted more than this from the world's z is not the table
    margin_m: float = 0.003  # points kept only this far above the keyframe's own plane (depth noise, fit)
    max_points: int = 4000  # RANSAC on an even subsample of this many ring points
    seed: int = 0


@dataclass(frozen=True)
class TablePlane:
    """``normal . p + offset`` = height of ``p`` above the plane (metres; ``normal`` unit, pointing up)."""

    normal: np.ndarray
    offset: float
    inliers: int
    rms_m: float

    def height(self, points: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.asarray(points, np.float64) @ self.normal + self.offset
        return out

    @property
    def tilt_deg(self) -> float:
        return math.degrees(math.acos(min(1.0, abs(float(self.normal[2])))))


@dataclass(frozen=True)
class _Ring:
    """The region a keyframe's table points are taken from (world frame)."""

    crop: EnvelopeCrop
    outer_m: float
    band_m: float

    @property
    def bounds_m(self) -> tuple[np.ndarray, np.ndarray]:
        cx, cy, _ = self.crop.center_m
        z = self.crop.table_z_m
        return (np.array([cx - self.outer_m, cy - self.outer_m, z - self.band_m]),
                np.array([cx + self.outer_m, cy + self.outer_m, z + self.band_m]))

    def contains(self, points_world: np.ndarray) -> np.ndarray:
        p = np.asarray(points_world)
        r2 = (p[:, 0] - self.crop.center_m[0]) ** 2 + (p[:, 1] - self.crop.center_m[1]) ** 2
        inner = self.crop.radius_m + self.crop.margin_m
        out: np.ndarray = ((r2 >= inner ** 2) & (r2 <= self.outer_m ** 2)
                           & (np.abs(p[:, 2] - self.crop.table_z_m) <= self.band_m))
        return out


@dataclass(frozen=True)
class TableCrop:
    """The envelope cylinder above a keyframe's own table plane (a :class:`backproject.Region`)."""

    crop: EnvelopeCrop
    plane: TablePlane
    margin_m: float
    band_m: float

    @property
    def bounds_m(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.crop.bounds_m
        lo = lo.copy()
        lo[2] = self.crop.table_z_m - self.band_m
        return lo, hi

    def contains(self, points_world: np.ndarray) -> np.ndarray:
        p = np.asarray(points_world)
        r = self.crop.radius_m + self.crop.margin_m
        r2 = (p[:, 0] - self.crop.center_m[0]) ** 2 + (p[:, 1] - self.crop.center_m[1]) ** 2
        top = self.crop.z_range_m[1]
        out: np.ndarray = ((r2 <= r * r) & (p[:, 2] <= top) & (p[:, 2] >= self.crop.table_z_m - self.band_m)
                           & (self.plane.height(p) >= self.margin_m))
        return out


def band_m(settings: TableSettings, calibration_uncertainty_m: float | None) -> float:
    """How far from the crop's table height the table is searched."""
    if calibration_uncertainty_m is None or not math.isfinite(calibration_uncertainty_m):
        return settings.band_m
    return max(settings.band_m, settings.band_calibration_factor * float(calibration_uncertainty_m))


def fit_plane_ransac(points: np.ndarray, settings: TableSettings) -> TablePlane | None:
    """A near-horizontal plane through ``points`` (N, 3): RANSAC (seeded), then least squares on the inliers."""
    P = np.asarray(points, np.float64)
    if len(P) < settings.min_points:
        return None
    if len(P) > settings.max_points:
        P = P[np.linspace(0, len(P) - 1, settings.max_points).astype(int)]
    rng = np.random.default_rng(settings.seed)
    best, best_count = None, 0
    cos_max = math.cos(math.radians(settings.max_tilt_deg))
    for _ in range(settings.iterations):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = float(np.linalg.norm(n))
        if norm < 1e-12:
            continue
        n /= norm
        if abs(n[2]) < cos_max:
            continue
        count = int(np.sum(np.abs((P - a) @ n) <= settings.inlier_m))
        if count > best_count:
            best, best_count = (n, a), count
    if best is None or best_count < settings.min_points // 2:
        return None
    n, a = best
    inl = P[np.abs((P - a) @ n) <= settings.inlier_m]
    centroid = inl.mean(axis=0)
    _, _, vt = np.linalg.svd(inl - centroid, full_matrices=False)
    normal = vt[2] if vt[2][2] > 0 else -vt[2]
    if abs(normal[2]) < cos_max:
        return None
    resid = (inl - centroid) @ normal
    return TablePlane(normal, -float(normal @ centroid), len(inl), float(np.sqrt(np.mean(resid ** 2))))


def table_region(frame: PosedDepth, crop: EnvelopeCrop, settings: TableSettings | None = None,
                 depth: DepthFilterSettings | None = None,
                 calibration_uncertainty_m: float | None = None) -> tuple[EnvelopeCrop | TableCrop, dict[str, Any]]:
    """The region a keyframe's points are kept in: the crop above its own fitted table plane, or the crop
    itself when no plane is found; and a record (plane height at the envelope axis vs the crop's floor)."""
    s = settings or TableSettings()
    band = band_m(s, calibration_uncertainty_m)
    ring = _Ring(crop, crop.radius_m + crop.margin_m + s.ring_m, band)
    bare = PosedDepth(frame.arm, frame.frame_id, frame.depth, frame.depth_scale, frame.intrinsics,
                      frame.T_world_cam, None)
    points = backproject(bare, depth, ring).points
    plane = fit_plane_ransac(points, s)
    if plane is None:
        return crop, {"fitted": False, "ring_points": len(points)}
    axis = np.array([crop.center_m[0], crop.center_m[1], 0.0])
    z_axis = float(-(plane.offset + plane.normal[:2] @ axis[:2]) / plane.normal[2])  # plane z on the axis
    return TableCrop(crop, plane, s.margin_m, band), {
        "fitted": True, "ring_points": len(points), "inliers": plane.inliers, "rms_mm": round(plane.rms_m * 1e3, 3),
        "tilt_deg": round(plane.tilt_deg, 3), "table_z_mm": round(z_axis * 1e3, 3),
        "crop_floor_mm": round(crop.z_range_m[0] * 1e3, 3)}


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The table crop's record for results.json: how many keyframes got a plane and where it was."""
    fitted = [r for r in records if r.get("fitted")]
    out: dict[str, Any] = {"keyframes": len(records), "fitted": len(fitted),
                           "margin_mm": TableSettings().margin_m * 1e3}
    if fitted:
        z = np.array([r["table_z_mm"] for r in fitted])
        out.update({"table_z_mm": {"median": round(float(np.median(z)), 3), "min": round(float(z.min()), 3),
                                   "max": round(float(z.max()), 3)},
                    "crop_floor_mm": fitted[0]["crop_floor_mm"],
                    "tilt_deg_median": round(float(np.median([r["tilt_deg"] for r in fitted])), 3),
                    "rms_mm_median": round(float(np.median([r["rms_mm"] for r in fitted])), 3)})
    return out


__all__ = ["TableCrop", "TablePlane", "TableSettings", "band_m", "fit_plane_ransac", "summarise", "table_region"]
