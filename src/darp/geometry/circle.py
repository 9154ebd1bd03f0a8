"""The smallest circle enclosing 2-D points (acquisition's localisation, reconstruction's envelope estimates)."""

from __future__ import annotations

import contextlib

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError

from darp.errors import DarpError

Array = NDArray[np.float64]


def min_enclosing_circle(points_xy: Array) -> tuple[Array, float]:
    """Smallest circle enclosing 2-D points: (centre (2,), radius). Welzl's incremental algorithm on
    the convex hull's vertices, in a fixed order (deterministic)."""
    P = np.asarray(points_xy, dtype=np.float64)
    if len(P) == 0:
        raise DarpError("no points to enclose")
    if len(P) > 3:
        with contextlib.suppress(QhullError):  # collinear or coincident: all points are on a line
            P = P[ConvexHull(P).vertices]
    P = P[np.random.default_rng(0).permutation(len(P))]

    def circle2(a: Array, b: Array) -> tuple[Array, float]:
        c = 0.5 * (a + b)
        return c, float(np.linalg.norm(a - c))

    def circle3(a: Array, b: Array, c: Array) -> tuple[Array, float]:
        d = 2.0 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]))
        if abs(d) < 1e-15:  # collinear: the widest pair
            pairs = [circle2(a, b), circle2(a, c), circle2(b, c)]
            return max(pairs, key=lambda p: p[1])
        sa, sb, sc = a @ a, b @ b, c @ c
        ux = (sa * (b[1] - c[1]) + sb * (c[1] - a[1]) + sc * (a[1] - b[1])) / d
        uy = (sa * (c[0] - b[0]) + sb * (a[0] - c[0]) + sc * (b[0] - a[0])) / d
        centre = np.array([ux, uy])
        return centre, float(np.linalg.norm(a - centre))

    def inside(c: Array, r: float, p: Array) -> bool:
        return float(np.linalg.norm(p - c)) <= r + 1e-12

    c, r = P[0].copy(), 0.0
    for i in range(1, len(P)):
        if inside(c, r, P[i]):
            continue
        c, r = P[i].copy(), 0.0
        for j in range(i):
            if inside(c, r, P[j]):
                continue
            c, r = circle2(P[i], P[j])
            for k in range(j):
                if not inside(c, r, P[k]):
                    c, r = circle3(P[i], P[j], P[k])
    return c, r


__all__ = ["min_enclosing_circle"]
