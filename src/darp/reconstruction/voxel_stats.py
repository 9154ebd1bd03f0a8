"""Per-voxel statistics of back-projected points, kept as sorted numpy arrays and merged by sorting.

A :class:`VoxelStats` holds, per occupied voxel (a packed int64 key), the number of points, the sums
of their positions, normals and colours, the number of distinct frames that saw it and a 64-bit mask
of the viewing-direction bins it was seen from. Statistics of one frame are reduced first
(:func:`frame_stats`: one frame counts once per voxel), then any number of them are merged
(:func:`merge_stats`): counts and sums add, masks OR. No Python objects per voxel or per point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from darp.errors import ReconstructionError

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_KEY_MASK = (1 << _KEY_BITS) - 1
N_VIEW_BINS = 64


def fibonacci_directions(n: int = N_VIEW_BINS) -> np.ndarray:
    """``n`` nearly uniform unit vectors on the sphere (golden-angle spiral), float32 (n, 3)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z]).astype(np.float32)


VIEW_DIRECTIONS = fibonacci_directions()
"""Centres of the 64 viewing-direction bins (neighbouring centres are about 25 deg apart)."""


_LUT_POLAR, _LUT_AZIMUTH = 128, 256  # 1.4 deg cells


def _view_bin_table() -> np.ndarray:
    """Nearest bin of every (polar, azimuth) cell centre: a lookup instead of 64 dot products per voxel."""
    polar = (np.arange(_LUT_POLAR) + 0.5) * np.pi / _LUT_POLAR
    azimuth = (np.arange(_LUT_AZIMUTH) + 0.5) * 2 * np.pi / _LUT_AZIMUTH - np.pi
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    d = np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), np.cos(p)], axis=-1).reshape(-1, 3)
    table: np.ndarray = np.argmax(d @ VIEW_DIRECTIONS.T.astype(np.float64), axis=1).astype(np.uint8).reshape(p.shape)
    return table


_VIEW_BIN_TABLE = _view_bin_table()


def view_bins(directions: np.ndarray) -> np.ndarray:
    """Index (N,) of the bin of :data:`VIEW_DIRECTIONS` nearest each direction (any length > 0).

    Looked up in a 1.4 deg (polar x azimuth) table, so a direction within about a degree of the border
    between two bins may get the other one; the bins only measure view diversity.
    """
    d = np.asarray(directions, np.float32)
    length = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    polar = np.arccos(np.clip(d[:, 2] / np.maximum(length, 1e-30), -1.0, 1.0))
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    i = np.minimum((polar * (_LUT_POLAR / np.pi)).astype(np.int64), _LUT_POLAR - 1)
    j = np.minimum(((azimuth + np.pi) * (_LUT_AZIMUTH / (2 * np.pi))).astype(np.int64), _LUT_AZIMUTH - 1)
    bins: np.ndarray = _VIEW_BIN_TABLE[i, j]
    return bins


def voxel_indices(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(N, 3) int64 integer voxel coordinates ``floor(p / voxel)``."""
    return np.floor(np.asarray(points, np.float64) / voxel_size_m).astype(np.int64)


def pack_keys(ijk: np.ndarray) -> np.ndarray:
    """Pack integer voxel coordinates (21 bits each, about +-1 km at 1 mm) into int64 keys."""
    if ijk.size and (ijk.min() < -_KEY_OFFSET or ijk.max() >= _KEY_OFFSET):
        raise ReconstructionError("points lie too far from the world origin for the voxel grid")
    shifted = ijk + _KEY_OFFSET
    keys: np.ndarray = (shifted[:, 0] << (2 * _KEY_BITS)) | (shifted[:, 1] << _KEY_BITS) | shifted[:, 2]
    return keys


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_keys`: (N, 3) int64 voxel coordinates."""
    keys = np.asarray(keys, np.int64)
    return np.column_stack([(keys >> (2 * _KEY_BITS)) & _KEY_MASK, (keys >> _KEY_BITS) & _KEY_MASK,
                            keys & _KEY_MASK]) - _KEY_OFFSET


def popcount64(masks: np.ndarray) -> np.ndarray:
    """Number of set bits of each uint64, as int32."""
    masks = np.ascontiguousarray(masks, dtype=np.uint64)
    if hasattr(np, "bitwise_count"):
        counts: np.ndarray = np.bitwise_count(masks).astype(np.int32)
        return counts
    table = np.array([i.bit_count() for i in range(256)], np.int32)  # numpy < 2.0
    counts = table[masks.view(np.uint8).reshape(-1, 8)].sum(axis=1).astype(np.int32)
    return counts


@dataclass
class VoxelStats:
    """Sorted, unique voxel keys with their accumulated statistics."""

    keys: np.ndarray  # (M,) int64, strictly increasing
    n_points: np.ndarray  # (M,) int64
    sum_xyz: np.ndarray  # (M, 3) float64
    sum_normal: np.ndarray  # (M, 3) float64
    sum_rgb: np.ndarray | None  # (M, 3) float64 or None
    n_frames: np.ndarray  # (M,) int32: frames that saw the voxel (each frame once)
    view_mask: np.ndarray  # (M,) uint64: viewing-direction bins that saw it
    arm_mask: np.ndarray  # (M,) uint8: bit i set when arm i saw it

    def __len__(self) -> int:
        return int(self.keys.size)

    @property
    def nbytes(self) -> int:
        arrays = [self.keys, self.n_points, self.sum_xyz, self.sum_normal, self.n_frames, self.view_mask,
                  self.arm_mask] + ([self.sum_rgb] if self.sum_rgb is not None else [])
        return int(sum(a.nbytes for a in arrays))

    @classmethod
    def empty(cls, with_colour: bool) -> VoxelStats:
        return cls(np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3)),
                   np.empty((0, 3)) if with_colour else None, np.empty(0, np.int32), np.empty(0, np.uint64),
                   np.empty(0, np.uint8))

    def select(self, keep: np.ndarray) -> VoxelStats:
        """The voxels where ``keep`` is True (order kept)."""
        return VoxelStats(self.keys[keep], self.n_points[keep], self.sum_xyz[keep], self.sum_normal[keep],
                          None if self.sum_rgb is None else self.sum_rgb[keep], self.n_frames[keep],
                          self.view_mask[keep], self.arm_mask[keep])


def frame_stats(points: np.ndarray, normals: np.ndarray, colours: np.ndarray | None,
                camera_centre: np.ndarray, voxel_size_m: float, arm_bit: int) -> VoxelStats:
    """Reduce one frame's points to per-voxel statistics; the frame counts once per voxel it hits."""
    if points.shape[0] == 0:
        return VoxelStats.empty(colours is not None)
    keys = pack_keys(voxel_indices(points, voxel_size_m))
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    m = uniq.size

    def sums(values: np.ndarray) -> np.ndarray:
        return np.column_stack([np.bincount(inverse, weights=values[:, j], minlength=m) for j in range(3)])

    sum_xyz = sums(points)
    to_camera = (np.asarray(camera_centre, np.float64) - sum_xyz / counts[:, None]).astype(np.float32)
    view_bin = view_bins(to_camera)
    return VoxelStats(
        keys=uniq, n_points=counts.astype(np.int64), sum_xyz=sum_xyz, sum_normal=sums(normals),
        sum_rgb=None if colours is None else sums(colours.astype(np.float64)),
        n_frames=np.ones(m, np.int32), view_mask=np.left_shift(np.uint64(1), view_bin.astype(np.uint64)),
        arm_mask=np.full(m, np.uint8(1 << arm_bit), np.uint8),
    )


def _runs(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stable order that sorts ``keys`` and the start of each run of equal keys in that order."""
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    return order, np.flatnonzero(np.concatenate(([True], ordered[1:] != ordered[:-1])))


def merge_stats(parts: list[VoxelStats]) -> VoxelStats:
    """Merge any number of statistics (sorted by key, one row per voxel)."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return VoxelStats.empty(False)
    if len(parts) == 1:
        return parts[0]
    with_colour = all(p.sum_rgb is not None for p in parts)
    keys = np.concatenate([p.keys for p in parts])
    order, starts = _runs(keys)

    def reduce(values: list[np.ndarray], op: np.ufunc = np.add) -> np.ndarray:
        return op.reduceat(np.concatenate(values)[order], starts, axis=0)

    return VoxelStats(
        keys=keys[order][starts],
        n_points=reduce([p.n_points for p in parts]),
        sum_xyz=reduce([p.sum_xyz for p in parts]),
        sum_normal=reduce([p.sum_normal for p in parts]),
        sum_rgb=reduce([p.sum_rgb for p in parts if p.sum_rgb is not None]) if with_colour else None,
        n_frames=reduce([p.n_frames for p in parts]),
        view_mask=reduce([p.view_mask for p in parts], np.bitwise_or),
        arm_mask=reduce([p.arm_mask for p in parts], np.bitwise_or),
    )


def cell_keys(keys: np.ndarray, factor: int) -> np.ndarray:
    """Keys of the ``factor``^3-voxel cells that hold voxels ``keys`` (floor division of their coordinates)."""
    return pack_keys(np.floor_divide(unpack_keys(keys), int(factor)))


def cell_stats(frame: VoxelStats, factor: int) -> VoxelStats:
    """One frame's statistics per ``factor``^3-voxel cell: the frame counts once per cell it hits, its view
    and arm bits are the union of its voxels' there. Merged over frames (:func:`merge_stats`), ``n_frames``
    is the number of distinct frames that hit each cell."""
    if len(frame) == 0:
        return frame
    keys = cell_keys(frame.keys, factor)
    order, starts = _runs(keys)

    def reduce(values: np.ndarray, op: np.ufunc = np.add) -> np.ndarray:
        return op.reduceat(values[order], starts, axis=0)

    m = starts.size
    return VoxelStats(keys=keys[order][starts], n_points=reduce(frame.n_points), sum_xyz=reduce(frame.sum_xyz),
                      sum_normal=reduce(frame.sum_normal), sum_rgb=None, n_frames=np.ones(m, np.int32),
                      view_mask=reduce(frame.view_mask, np.bitwise_or), arm_mask=reduce(frame.arm_mask, np.bitwise_or))


__all__ = [
    "N_VIEW_BINS",
    "VIEW_DIRECTIONS",
    "VoxelStats",
    "cell_keys",
    "cell_stats",
    "fibonacci_directions",
    "frame_stats",
    "merge_stats",
    "pack_keys",
    "popcount64",
    "unpack_keys",
    "view_bins",
    "voxel_indices",
]
