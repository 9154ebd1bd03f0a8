"""An oracle for the Z1 model, written independently of :mod:`darp.kinematics.z1`.

The joint table is typed here from facts/z1-kinematics.md (not read from ``z1.Z1_JOINTS``), so a wrong number
in darp's table shows as a disagreement. Two forward kinematics use it: a plain chain of scipy rotations
(darp's FK is a closed form and a column-mixing recursion) and a URDF for Pinocchio or MuJoCo to load.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# joint name, origin in the parent link (m, zero rotation), axis, lower and upper limit (rad): facts table
FACTS_JOINTS: tuple[tuple[str, tuple[float, float, float], str, float, float], ...] = (
    ("joint1", (0.0, 0.0, 0.0585), "z", -2.6179939, 2.6179939),
    ("joint2", (0.0, 0.0, 0.045), "y", 0.0, 2.9670597),
    ("joint3", (-0.35, 0.0, 0.0), "y", -2.8797933, 0.0),
    ("joint4", (0.218, 0.0, 0.057), "y", -1.5184364, 1.5184364),
    ("joint5", (0.07, 0.0, 0.0), "z", -1.3439035, 1.3439035),
    ("joint6", (0.0492, 0.0, 0.0), "x", -2.7925268, 2.7925268),
)
# tool frames: offset along link06 x (m), orientation link06's
FACTS_TOOL_X_M = {"link06": 0.0, "flange": 0.0618, "gripper": 0.1}


def reference_links(q: np.ndarray) -> list[np.ndarray]:
    """``T_base_link`` (4, 4) for link00..link06 at joints q (6,): one scipy rotation per joint."""
    R, p = Rotation.identity(), np.zeros(3)
    out = [np.eye(4)]
    for (_, origin, axis, _, _), angle in zip(FACTS_JOINTS, q, strict=True):
        p = p + R.apply(origin)
        R = R * Rotation.from_euler(axis, float(angle))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R.as_matrix(), p
        out.append(T)
    return out


def reference_fk(q: np.ndarray, frame: str = "flange") -> np.ndarray:
    """``T_base_frame`` (4, 4) of a tool frame at joints q (6,)."""
    T = reference_links(q)[-1].copy()
    T[:3, 3] += T[:3, 0] * FACTS_TOOL_X_M[frame]
    return T


def reference_urdf() -> str:
    """The facts table as a URDF: links link00..link06, one fixed child link per tool frame."""
    axes = {"x": "1 0 0", "y": "0 1 0", "z": "0 0 1"}
    links = [f'<link name="link0{i}"/>' for i in range(7)] + [f'<link name="{t}"/>' for t in ("flange", "gripper")]
    joints = [f'<joint name="{name}" type="revolute"><parent link="link0{i}"/><child link="link0{i + 1}"/>'
              f'<origin xyz="{x} {y} {z}" rpy="0 0 0"/><axis xyz="{axes[axis]}"/>'
              f'<limit lower="{lo}" upper="{hi}" effort="30" velocity="3.1416"/></joint>'
              for i, (name, (x, y, z), axis, lo, hi) in enumerate(FACTS_JOINTS)]
    joints += [f'<joint name="{t}_joint" type="fixed"><parent link="link06"/><child link="{t}"/>'
               f'<origin xyz="{FACTS_TOOL_X_M[t]} 0 0" rpy="0 0 0"/></joint>' for t in ("flange", "gripper")]
    return f'<robot name="z1_facts">{"".join(links)}{"".join(joints)}</robot>'
