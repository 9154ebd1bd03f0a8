#!/usr/bin/env python3
"""Z1 kinematics speed: darp's batched FK next to Pinocchio, IK and look-at times, collision queries.

Pinocchio (the peer) gets the same arm, built joint by joint from darp's table; both must agree on
the flange poses to 1e-9 before anything is timed. Pinocchio is timed as a Python caller uses it per
configuration (``forwardKinematics`` + ``updateFramePlacements``); darp as ``fk_batch`` on the whole
array. Prints darp's number, the peer's number and the ratio; IK numbers are printed against the
2 ms per pose target.

    .venv/bin/python benchmarks/kinematics.py [--n 10000] [--poses 500]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from darp.kinematics import collision, ik, z1
from darp.kinematics import transforms as tf
from results import Row, Target, row

FK_TARGET = Target("ratio", ">=", 5.0, "issue 3")  # batched FK at least 5x Pinocchio's per-call loop
IK_TARGET = Target("darp", "<=", 2.0, "issue 3")  # IK median at most 2 ms per pose


def best_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def pinocchio_model() -> tuple[object, object, int]:
    import pinocchio as pin

    model = pin.Model()
    joint_models = {"x": pin.JointModelRX, "y": pin.JointModelRY, "z": pin.JointModelRZ}
    parent = 0
    for joint in z1.Z1_JOINTS:
        placement = pin.SE3(np.eye(3), np.array(joint.origin_xyz_m))
        parent = model.addJoint(parent, joint_models[joint.axis](), placement, joint.name)
    flange = pin.SE3(np.eye(3), np.array([z1.WRIST_FRAMES["flange"], 0.0, 0.0]))
    frame_id = model.addFrame(pin.Frame("flange", parent, flange, pin.FrameType.OP_FRAME))
    return model, model.createData(), frame_id


def bench_fk(n: int) -> dict[str, float]:
    """Flange poses of ``n`` random configurations: darp's ``fk_batch`` and Pinocchio's loop (configurations/s)."""
    import pinocchio as pin

    Q = z1.random_configurations(n, np.random.default_rng(0))
    model, data, fid = pinocchio_model()

    def pin_loop() -> None:
        for q in Q:
            pin.forwardKinematics(model, data, q)
            pin.updateFramePlacements(model, data)

    T_darp = z1.fk_batch(Q)
    T_pin = np.empty_like(T_darp)
    for i, q in enumerate(Q):
        pin.forwardKinematics(model, data, q)
        pin.updateFramePlacements(model, data)
        T_pin[i] = data.oMf[fid].homogeneous
    err = np.max(np.abs(T_darp - T_pin))
    assert err < 1e-9, f"darp and Pinocchio disagree on flange poses by {err:.3g}"
    # Interleaved rounds, best of each: the two see the same machine load.
    t_darp, t_pin = np.inf, np.inf
    for _ in range(5):
        t_darp = min(t_darp, best_time(lambda: z1.fk_batch(Q), 5))
        t_pin = min(t_pin, best_time(pin_loop, 1))
    print(f"FK, {n} random configurations (flange poses agree to {err:.1e}):")
    print(f"  darp fk_batch                 {n / t_darp:12,.0f} configurations/s  ({t_darp * 1e3:.2f} ms)")
    print(f"  Pinocchio per-call loop       {n / t_pin:12,.0f} configurations/s  ({t_pin * 1e3:.2f} ms)")
    print(f"  ratio darp / Pinocchio        {t_pin / t_darp:12.1f} x   (target >= 5)")
    t_single = best_time(lambda: [z1.fk(q) for q in Q[:2000]], 3) / 2000
    print(f"  darp fk, one call per pose    {1 / t_single:12,.0f} configurations/s")
    t_jac = best_time(lambda: z1.jacobian_batch(Q), 5)
    print(f"  darp jacobian_batch           {n / t_jac:12,.0f} configurations/s")
    return {"darp": n / t_darp, "pinocchio": n / t_pin}


def bench_ik(poses: int) -> dict[str, float]:
    """IK on random reachable poses: median ms per pose of each method."""
    medians = {}
    Q = z1.random_configurations(poses, np.random.default_rng(1))
    T = z1.fk_batch(Q)
    for label, kwargs in (("closed form (auto)", {}), ("damped least squares", {"method": "numeric"})):
        times, results = [], []
        count = poses if not kwargs else min(poses, 200)
        for i in range(count):
            t0 = time.perf_counter()
            results.append(ik.solve_ik(T[i], **kwargs))
            times.append(time.perf_counter() - t0)
        ok = [r for r in results if r.success]
        print(f"IK {label}, {count} random reachable poses:")
        print(f"  median {np.median(times) * 1e3:.3f} ms/pose (p95 {np.percentile(times, 95) * 1e3:.3f}; "
              f"target <= 2 ms), success {100 * len(ok) / count:.1f} %, max residual "
              f"{max(r.position_error_m for r in ok):.1e} m / {max(r.rotation_error_rad for r in ok):.1e} rad")
        medians[label] = float(np.median(times)) * 1e3
    t_batch = best_time(lambda: ik.solve_ik_batch(T), 3)
    print(f"  solve_ik_batch (closed form)  {poses / t_batch:,.0f} poses/s")
    far = tf.make_transform(t=[1.5, 0.0, 0.3])
    t_fail = best_time(lambda: ik.solve_ik(far), 20)
    print(f"  unreachable target rejected in {t_fail * 1e3:.3f} ms")
    return medians


def bench_look_at(n: int) -> None:
    rng = np.random.default_rng(2)
    targets = np.column_stack([rng.uniform(0.25, 0.5, n), rng.uniform(-0.25, 0.25, n), rng.uniform(0.0, 0.15, n)])
    T_fc = collision.NOMINAL_T_WRIST_CAM
    for label, given in (("given view direction", True), ("free view direction", False)):
        times, ok = [], 0
        for p in targets:
            view = p - np.array([0.0, 0.0, 0.45]) if given else None
            t0 = time.perf_counter()
            r = ik.solve_look_at(p, 0.32, T_frame_cam=T_fc, view_dir_base=view)
            times.append(time.perf_counter() - t0)
            ok += r.success
        print(f"look-at IK, {label}, {n} targets in front of the arm: median {np.median(times) * 1e3:.2f} ms, "
              f"success {100 * ok / n:.0f} %")


def bench_collision(n: int) -> None:
    Q = z1.random_configurations(n, np.random.default_rng(3))
    T_a = tf.make_transform(t=[-0.6993, 0, 0])
    T_b = tf.make_transform(tf.rot_z(np.radians(178.4)), [0.6993, 0, 0])
    t_self = best_time(lambda: [collision.self_collision_distance(q) for q in Q], 2) / n
    t_arms = best_time(lambda: [collision.arm_arm_distance(q, T_a, q, T_b) for q in Q], 2) / n
    t_table = best_time(lambda: [collision.arm_table_distance(q, T_a, 0.0) for q in Q], 2) / n
    hits = np.mean([collision.self_collision(q) for q in Q])
    print(f"collision, {n} random configurations (with camera): self {t_self * 1e3:.2f} ms, "
          f"arm-arm {t_arms * 1e3:.2f} ms, arm-table {t_table * 1e3:.3f} ms per query; "
          f"{100 * hits:.1f} % of random in-limit configurations self-collide")


def rows(n: int = 10_000, poses: int = 500) -> list[Row]:
    """The results table's rows: batched FK against Pinocchio, IK median time against its target."""
    fk, ik_ms = bench_fk(n), bench_ik(poses)
    return [row("kinematics", f"FK, {n:,} random configurations", "configurations/s", fk["darp"], fk["pinocchio"],
                "Pinocchio per-call loop", FK_TARGET),
            *(row("kinematics", f"IK {label}, median per pose", "ms", ms,  # the target is on darp's default IK
                  target=IK_TARGET if label.startswith("closed form") else None) for label, ms in ik_ms.items())]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10_000, help="configurations for the FK comparison")
    parser.add_argument("--poses", type=int, default=500, help="random reachable poses for IK")
    args = parser.parse_args()
    t0 = time.perf_counter()
    bench_fk(args.n)
    bench_ik(args.poses)
    bench_look_at(100)
    bench_collision(300)
    print(f"(total {time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
