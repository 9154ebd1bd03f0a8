"""Convex collision primitives (capsule, cylinder, box) and their exact signed distances, in numpy.

Every primitive has a pose (its local z is the axis of a capsule or cylinder) and half extents
(box: half sizes; capsule and cylinder: ``(radius, radius, half length)``), so one set of arrays
holds any mix of kinds and every query is vectorised over pairs.

Signed distance between two convex shapes A and B (negative = penetration depth) equals
``max over unit n of L(n)``, ``L(n) = -h_A(n) - h_B(-n)`` with ``h`` the support function (closed
form for all three kinds); any single ``n`` gives a lower bound. The search for ``n``:

1. Capsule-capsule pairs are solved exactly from their segments' closest points.
2. Other pairs start from their *bounding capsules* (containing capsules, an exact lower bound) and
   run alternating projections (``x <- P_A(y)``, ``y <- P_B(x)``, closed-form projections), which
   converge to a closest pair when the shapes are apart. ``|x - y|`` is an upper bound and
   ``L((y - x) / |x - y|)`` a lower bound; iteration stops when they agree to ``tol_m``.
3. Overlapping pairs take the best ``L`` over the capsules' direction and the shapes' axes and
   their cross products (a separating-axis style estimate of the penetration depth).

The value returned is the best lower bound found, so a distance is never over-reported, and it is
exact (to ``tol_m``) for shapes that are apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from darp.errors import KinematicsError

Array = NDArray[np.float64]
IndexArray = NDArray[np.intp]  # primitive kinds, indices

KINDS = ("capsule", "cylinder", "box")
CAPSULE, CYLINDER, BOX = 0, 1, 2


def _frame_with_z(axis: Array) -> Array:
    """A rotation whose third column is ``axis`` (unit); the other two are any orthonormal pair."""
    z = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


@dataclass(frozen=True)
class Primitive:
    """One convex shape in some frame: kind, ``T_frame_shape`` (4, 4), half extents (3,), name, link."""

    kind: str
    T_frame_shape: Array
    half_extents_m: Array
    name: str = ""
    link: str = ""

    @staticmethod
    def _round(kind: str, a: ArrayLike, b: ArrayLike, radius_m: float, name: str, link: str) -> Primitive:
        pa, pb = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        if pa.shape != (3,) or pb.shape != (3,) or not radius_m > 0:
            raise KinematicsError(f"{kind} {name!r}: needs two 3-vector end points and a positive radius")
        length = float(np.linalg.norm(pb - pa))
        T = np.eye(4)
        T[:3, :3] = _frame_with_z(pb - pa) if length > 0 else np.eye(3)
        T[:3, 3] = 0.5 * (pa + pb)
        return Primitive(kind, T, np.array([radius_m, radius_m, 0.5 * length]), name, link)

    @staticmethod
    def capsule(a: ArrayLike, b: ArrayLike, radius_m: float, name: str = "", link: str = "") -> Primitive:
        """Segment a-b swept by a ball of ``radius_m``."""
        return Primitive._round("capsule", a, b, radius_m, name, link)

    @staticmethod
    def cylinder(a: ArrayLike, b: ArrayLike, radius_m: float, name: str = "", link: str = "") -> Primitive:
        """Solid cylinder whose axis runs from face centre a to face centre b."""
        return Primitive._round("cylinder", a, b, radius_m, name, link)

    @staticmethod
    def box(T_frame_box: ArrayLike, size_m: ArrayLike, name: str = "", link: str = "") -> Primitive:
        """Box of full ``size_m`` (3,) along the axes of ``T_frame_box``, centred at its origin."""
        size = np.asarray(size_m, dtype=np.float64)
        if size.shape != (3,) or np.any(size <= 0):
            raise KinematicsError(f"box {name!r}: size must be three positive extents, got {size_m!s}")
        return Primitive("box", np.asarray(T_frame_box, dtype=np.float64), 0.5 * size, name, link)

    @property
    def radius_m(self) -> float:
        return float(self.half_extents_m[0])

    @property
    def end_points(self) -> tuple[Array, Array]:
        """Axis end points of a capsule or cylinder (for a box: its longest centre line)."""
        (a, b), _ = _bounding_segment(self.T_frame_shape[None, :3, :3], self.T_frame_shape[None, :3, 3],
                                      self.half_extents_m[None], np.array([KINDS.index(self.kind)]))
        return a[0], b[0]


@dataclass(frozen=True)
class PrimitiveSet:
    """Primitives as arrays: kinds (N,), R (N, 3, 3), centre (N, 3), half (N, 3), names, links."""

    kinds: IndexArray
    R: Array
    centre: Array
    half: Array
    names: tuple[str, ...]
    links: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.names)

    @staticmethod
    def from_list(prims: Sequence[Primitive]) -> PrimitiveSet:
        if len(prims) == 0:
            raise KinematicsError("a distance query needs at least one primitive on each side")
        for p in prims:
            if p.kind not in KINDS:
                raise KinematicsError(f"unknown primitive kind {p.kind!r}; available: {', '.join(KINDS)}")
        T = np.array([p.T_frame_shape for p in prims], dtype=np.float64)
        return PrimitiveSet(np.array([KINDS.index(p.kind) for p in prims]), T[:, :3, :3], T[:, :3, 3],
                            np.array([p.half_extents_m for p in prims], dtype=np.float64),
                            tuple(p.name for p in prims), tuple(p.link for p in prims))

    def to_list(self) -> list[Primitive]:
        out = []
        for i in range(len(self)):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = self.R[i], self.centre[i]
            out.append(Primitive(KINDS[self.kinds[i]], T, self.half[i].copy(), self.names[i], self.links[i]))
        return out

    def subset(self, index: ArrayLike) -> PrimitiveSet:
        idx = np.asarray(index)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx
        return PrimitiveSet(self.kinds[idx], self.R[idx], self.centre[idx], self.half[idx],
                            tuple(self.names[i] for i in idx), tuple(self.links[i] for i in idx))

    def transformed(self, T_a_frame: ArrayLike) -> PrimitiveSet:
        """The same primitives expressed in frame a."""
        T = np.asarray(T_a_frame, dtype=np.float64)
        return PrimitiveSet(self.kinds, T[:3, :3] @ self.R, self.centre @ T[:3, :3].T + T[:3, 3],
                            self.half, self.names, self.links)

    def lowest_z(self) -> Array:
        """Lowest z of each primitive (exact: minus the support value in direction -z)."""
        return -support(self, np.tile([0.0, 0.0, -1.0], (len(self), 1)))


def as_set(prims: PrimitiveSet | Sequence[Primitive]) -> PrimitiveSet:
    return prims if isinstance(prims, PrimitiveSet) else PrimitiveSet.from_list(prims)


def concatenate(sets: Sequence[PrimitiveSet]) -> PrimitiveSet:
    return PrimitiveSet(np.concatenate([s.kinds for s in sets]), np.concatenate([s.R for s in sets]),
                        np.concatenate([s.centre for s in sets]), np.concatenate([s.half for s in sets]),
                        sum((s.names for s in sets), ()), sum((s.links for s in sets), ()))


def _bounding_segment(R: Array, c: Array, half: Array, kinds: IndexArray) -> tuple[tuple[Array, Array], Array]:
    """Segments and radii of capsules containing each shape (a box: along its longest side)."""
    n = len(kinds)
    long_axis = np.where(kinds == BOX, np.argmax(half, axis=1), 2)
    axis = R[np.arange(n), :, long_axis]
    h = half[np.arange(n), long_axis]
    others = np.sort(np.where(np.eye(3, dtype=bool)[long_axis], 0.0, half), axis=1)[:, 1:]
    radius = np.where(kinds == BOX, np.hypot(others[:, 0], others[:, 1]), half[:, 0])
    return (c - h[:, None] * axis, c + h[:, None] * axis), radius


def project(s: PrimitiveSet, p: Array) -> Array:
    """Closest point of each shape s[i] to the point p[i] (the point itself when inside)."""
    local = np.einsum("nji,nj->ni", s.R, p - s.centre)
    r, h = s.half[:, 0], s.half[:, 2]
    z = np.clip(local[:, 2], -h, h)
    out = np.clip(local, -s.half, s.half)  # box
    round_rows = s.kinds != BOX
    if np.any(round_rows):
        cap = s.kinds == CAPSULE
        v = local.copy()
        v[:, 2] = np.where(cap, local[:, 2] - z, 0.0)  # capsule: from the axis point; cylinder: radial
        nv = np.linalg.norm(v, axis=1)
        scale = np.minimum(1.0, r / np.where(nv > 0, nv, 1.0))
        rounded = v * scale[:, None]
        rounded[:, 2] += z
        out = np.where(round_rows[:, None], rounded, out)
    return cast(Array, s.centre + np.einsum("nij,nj->ni", s.R, out))


def support(s: PrimitiveSet, n: Array) -> Array:
    """Support function h_i(n_i) = max over shape i of n_i . x (n need not be unit)."""
    m = np.abs(np.einsum("nji,nj->ni", s.R, n))
    r, h = s.half[:, 0], s.half[:, 2]
    box = np.einsum("ni,ni->n", m, s.half)
    capsule = h * m[:, 2] + r * np.linalg.norm(m, axis=1)
    cylinder = h * m[:, 2] + r * np.hypot(m[:, 0], m[:, 1])
    return cast(Array, np.einsum("ni,ni->n", s.centre, n) + np.choose(s.kinds, [capsule, cylinder, box]))


def segment_distances(a1: Array, b1: Array, a2: Array, b2: Array) -> tuple[Array, Array, Array]:
    """Closest points between segments a1-b1 and a2-b2 (broadcast (..., 3)): (distance, p1, p2).

    Minimises |(a1 + s d1) - (a2 + t d2)| over s, t in [0, 1]: the unconstrained optimum's s is
    clamped, t follows from s and is clamped, and s is recomputed from a clamped t. Point segments
    and parallel segments are handled by the same clamping.
    """
    d1, d2, r = b1 - a1, b2 - a2, a1 - a2
    aa = np.einsum("...i,...i->...", d1, d1)
    ee = np.einsum("...i,...i->...", d2, d2)
    bb = np.einsum("...i,...i->...", d1, d2)
    cc = np.einsum("...i,...i->...", d1, r)
    ff = np.einsum("...i,...i->...", d2, r)
    tiny = 1e-18
    denom = aa * ee - bb * bb
    general = denom > 1e-12 * np.maximum(aa * ee, tiny)
    safe_aa, safe_ee = np.where(aa > tiny, aa, 1.0), np.where(ee > tiny, ee, 1.0)
    s = np.where(general, (bb * ff - cc * ee) / np.where(general, denom, 1.0), 0.0)
    s = np.where(aa > tiny, np.clip(s, 0.0, 1.0), 0.0)
    t = np.where(ee > tiny, (bb * s + ff) / safe_ee, 0.0)
    t_clamped = np.clip(t, 0.0, 1.0)
    s = np.where((t != t_clamped) & (aa > tiny), np.clip((bb * t_clamped - cc) / safe_aa, 0.0, 1.0), s)
    p1 = a1 + s[..., None] * d1
    p2 = a2 + t_clamped[..., None] * d2
    return np.linalg.norm(p1 - p2, axis=-1), p1, p2


def _lower_bound(A: PrimitiveSet, B: PrimitiveSet, n: Array) -> Array:
    return -support(A, n) - support(B, -n)


def _unit(v: Array, fallback: Array) -> Array:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(norm > 1e-12, v / np.where(norm > 1e-12, norm, 1.0), fallback)


def _axis_directions(A: PrimitiveSet, B: PrimitiveSet) -> list[Array]:
    """Separating-axis style candidates: both shapes' axes and their cross products, both signs."""
    axes = [A.R[:, :, k] for k in range(3)] + [B.R[:, :, k] for k in range(3)]
    dirs = axes + [np.cross(axes[i], axes[j]) for i in range(3) for j in range(3, 6)]
    up = np.array([0.0, 0.0, 1.0])
    units = [_unit(d, up) for d in dirs]
    return units + [-u for u in units]


def _pattern_search(A: PrimitiveSet, B: PrimitiveSet, n: Array, value: Array, min_step: Array,
                    steps: int = 120) -> tuple[Array, Array]:
    """Raise L(n) by searching around n on the unit sphere (8 trial directions, shrinking step)."""
    step = np.full(len(n), 0.3)
    k = 8
    for it in range(steps):
        helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        u = _unit(np.cross(n, helper), helper)
        v = np.cross(n, u)
        phi = (np.arange(k) + 0.5 * (it % 2)) * (2.0 * np.pi / k)
        c, s = np.cos(step), np.sin(step)
        trial = (c[None, :, None] * n[None] + s[None, :, None] * (
            np.cos(phi)[:, None, None] * u[None] + np.sin(phi)[:, None, None] * v[None]))
        flat = trial.reshape(-1, 3)
        vals = _lower_bound(_tile(A, k), _tile(B, k), flat).reshape(k, -1)
        best = np.argmax(vals, axis=0)
        top = vals[best, np.arange(len(n))]
        better = top > value
        n = np.where(better[:, None], trial[best, np.arange(len(n))], n)
        value = np.where(better, top, value)
        step = np.where(better, np.minimum(step * 1.5, 0.5), step * 0.5)
        if np.all(step < min_step):
            break
    return n, value


def _tile(s: PrimitiveSet, k: int) -> PrimitiveSet:
    return PrimitiveSet(np.tile(s.kinds, k), np.tile(s.R, (k, 1, 1)), np.tile(s.centre, (k, 1)),
                        np.tile(s.half, (k, 1)), s.names * k, s.links * k)


def pair_distances(A: PrimitiveSet, B: PrimitiveSet, tol_m: float = 1e-6,
                   max_iters: int = 400) -> tuple[Array, Array, Array]:
    """Signed distances between A[i] and B[i] (same length): (distance (P,), x_A (P, 3), x_B (P, 3)).

    The points are the closest pair found (for overlapping shapes: a point in both).
    """
    (a1, b1), ra = _bounding_segment(A.R, A.centre, A.half, A.kinds)
    (a2, b2), rb = _bounding_segment(B.R, B.centre, B.half, B.kinds)
    d, pa, pb = segment_distances(a1, b1, a2, b2)
    best = d - ra - rb  # bounding capsules contain the shapes: a lower bound (exact for capsules)
    exact = (A.kinds == CAPSULE) & (B.kinds == CAPSULE)
    unit = _unit(pb - pa, np.array([0.0, 0.0, 1.0]))
    xa, xb = pa + ra[:, None] * unit, pb - rb[:, None] * unit
    todo = np.flatnonzero(~exact)
    if len(todo) == 0:
        return best, xa, xb
    As, Bs = A.subset(todo), B.subset(todo)
    n_best = unit[todo]
    lower = np.maximum(best[todo], _lower_bound(As, Bs, n_best))
    x = project(As, pb[todo])
    y = project(Bs, x)
    upper = np.linalg.norm(y - x, axis=1)
    act = np.arange(len(todo))
    Aa, Ba = As, Bs
    for _ in range(max_iters):
        open_ = (upper[act] - lower[act] > tol_m) & (upper[act] > 1e-12)
        if not np.all(open_):  # shrink the working set to the pairs not yet certified
            act = act[open_]
            if len(act) == 0:
                break
            Aa, Ba = As.subset(act), Bs.subset(act)
        xa_ = project(Aa, y[act])
        ya_ = project(Ba, xa_)
        x[act], y[act] = xa_, ya_
        upper[act] = np.linalg.norm(ya_ - xa_, axis=1)
        n = _unit(ya_ - xa_, n_best[act])
        value = _lower_bound(Aa, Ba, n)
        improved = (upper[act] > 1e-12) & (value > lower[act])
        n_best[act] = np.where(improved[:, None], n, n_best[act])
        lower[act] = np.where(improved, value, lower[act])
    touching = upper <= 1e-12
    if np.any(touching):  # overlapping: start from the best separating-axis candidate
        idx = np.flatnonzero(touching)
        At, Bt = As.subset(idx), Bs.subset(idx)
        cands = [n_best[idx]] + _axis_directions(At, Bt)
        vals = np.array([_lower_bound(At, Bt, c) for c in cands])
        pick = np.argmax(vals, axis=0)
        n_best[idx] = np.array(cands)[pick, np.arange(len(idx))]
        lower[idx] = vals[pick, np.arange(len(idx))]
    loose = np.flatnonzero(upper - lower > tol_m)
    if len(loose):  # alternating projections were slow (edges, corners) or shapes overlap
        # Apart: polish to the tolerance; overlapping: a coarser depth estimate is enough.
        min_step = np.where(touching[loose], 1e-3, 1e-10)
        _, lower[loose] = _pattern_search(As.subset(loose), Bs.subset(loose), n_best[loose], lower[loose],
                                          min_step)
    lower = np.where(touching, np.minimum(lower, 0.0), np.minimum(lower, upper))
    best[todo], xa[todo], xb[todo] = lower, x, y
    return best, xa, xb


def plane_distances(s: PrimitiveSet, height_z: float) -> tuple[Array, Array]:
    """Signed heights of each shape above the plane z = height_z and each shape's lowest point."""
    low = s.lowest_z()
    point = project(s, s.centre - np.array([0.0, 0.0, 1e3]))  # lowest point (one of them)
    return low - height_z, point
