"""The order of an arm's views: a short joint-space tour from park through the views and back.

Views are ordered to shorten joint travel: greedy nearest neighbour from the park
configuration, then 2-opt, with the cost of a move being its largest joint change (a synchronised
joint move's duration grows with it); the tour starts and ends at park. Moves whose costs differ by
less than :data:`TIE_TOLERANCE_RAD` are ties, broken by the lower candidate index: the orbit is
symmetric about the arm's side, so mirror-image views are often equally far from park, and the last
bits of their costs (which change with the BLAS kernel) must not choose the tour's direction.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


TIE_TOLERANCE_RAD = 1e-9  # move costs closer than this are equal when ordering views (module docstring)


# -- ordering ------------------------------------------------------------------------------------
def move_cost(qa: Array, qb: Array) -> Array:
    """Cost of a joint move: its largest joint change (rad); broadcasts over leading dimensions."""
    return cast(Array, np.max(np.abs(np.asarray(qb, float) - np.asarray(qa, float)), axis=-1))


def tour_cost(q_start: Array, Q: Array, q_end: Array | None = None) -> float:
    """Joint travel of ``q_start`` -> rows of Q in order -> ``q_end`` (if given)."""
    pts = [np.asarray(q_start, float), *np.asarray(Q, float)]
    if q_end is not None:
        pts.append(np.asarray(q_end, float))
    P = np.array(pts)
    return float(np.sum(move_cost(P[:-1], P[1:]))) if len(P) > 1 else 0.0


def order_views(q_start: Array, Q: Array, q_end: Array | None = None, two_opt_rounds: int = 50) -> list[int]:
    """Order of the rows of Q (N, 6) for a short tour from ``q_start`` (to ``q_end``): greedy
    nearest neighbour, then 2-opt segment reversals while they shorten the tour."""
    Q = np.asarray(Q, dtype=float)
    n = len(Q)
    if n <= 1:
        return list(range(n))
    start = np.asarray(q_start, dtype=float)
    P = np.vstack([start, Q] + ([np.asarray(q_end, float)] if q_end is not None else []))
    D = move_cost(P[:, None, :], P[None, :, :])
    remaining = set(range(1, n + 1))
    path = [0]
    while remaining:
        last = path[-1]
        best = min(D[last, j] for j in remaining)
        nxt = min(j for j in remaining if D[last, j] <= best + TIE_TOLERANCE_RAD)  # ties: the lower index
        path.append(nxt)
        remaining.remove(nxt)
    if q_end is not None:
        path.append(n + 1)
    fixed_end = q_end is not None
    for _ in range(two_opt_rounds):
        improved = False
        last_view = len(path) - 2 if fixed_end else len(path) - 1
        for i in range(1, last_view):
            for k in range(i + 1, last_view + 1):
                a, b = path[i - 1], path[i]
                c = path[k]
                d = path[k + 1] if k + 1 < len(path) else None
                before = D[a, b] + (D[c, d] if d is not None else 0.0)
                after = D[a, c] + (D[b, d] if d is not None else 0.0)
                if after < before - TIE_TOLERANCE_RAD:
                    path[i:k + 1] = path[i:k + 1][::-1]
                    improved = True
        if not improved:
            break
    return [p - 1 for p in path if 1 <= p <= n]


__all__ = ["TIE_TOLERANCE_RAD", "move_cost", "order_views", "tour_cost"]
