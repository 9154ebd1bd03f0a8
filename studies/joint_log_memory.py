"""Is the joint log streamed? Peak memory of reading a long ``arm_poses.csv`` and interpolating it (issue 32).

Writes a valid ``arm_poses.csv`` of ``--rows`` rows (two arms interleaved at 33 Hz each, the writer's number
format: about 98 bytes a row, 0.98 GB for 10 million) into a temporary folder, then, in a fresh child process
(so that the generator's memory is not counted), reads it with :func:`darp.formats.arm_poses.read_arm_poses` and
interpolates each arm's joints at 10,000 frame times with :func:`darp.kinematics.camera_poses.interpolate_joints`
(the pose recovery's step over the whole log). Reports the child's peak RSS (``ru_maxrss``), its wall time, and
the bytes the parsed rows need (64 a row: time, six joints, line number). The file is removed afterwards.

    .venv/bin/python studies/joint_log_memory.py --rows 10000000
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = r"""
import json, resource, sys, time
import numpy as np
from darp.formats.arm_poses import read_arm_poses
from darp.kinematics.camera_poses import interpolate_joints
start = time.perf_counter()
log = read_arm_poses(sys.argv[1])
read_s = time.perf_counter() - start
posed = 0
for arm in log.arms:
    t = log.times(arm)
    query = np.linspace(t[0], t[-1], 10_000)
    posed += int(interpolate_joints(t, log.joints(arm), query, max_gap_s=1.0).posed.sum())
print(json.dumps({"rows": log.n_rows, "read_s": round(read_s, 2), "total_s": round(time.perf_counter() - start, 2),
                  "posed_frames": posed,
                  "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}))
"""


def write_log(path: Path, rows: int, block: int = 200_000) -> int:
    """A valid two-arm log of ``rows`` rows, written in blocks with numpy (fast, bounded memory)."""
    import numpy as np

    rng = np.random.default_rng(0)
    with path.open("w", encoding="utf-8", newline="\n") as f:
        f.write("time_s,arm,q1,q2,q3,q4,q5,q6\n")
        done = 0
        while done < rows:
            n = min(block, rows - done)
            k = np.arange(done, done + n)
            t = 1.7e9 + (k // 2) / 33.0 + (k % 2) * 1e-4
            q = np.clip(np.cumsum(rng.normal(0, 1e-3, (n, 6)), axis=0), -2.5, 2.5)
            arms = np.where(k % 2 == 0, "arm110", "arm111")
            lines = [f"{ti:.6f},{a}," + ",".join(f"{v:.9f}" for v in qi) for ti, a, qi in zip(t, arms, q, strict=True)]
            f.write("\n".join(lines) + "\n")
            done += n
    return path.stat().st_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=10_000_000, help="rows of the generated log")
    parser.add_argument("--work", type=Path, default=None, help="folder for the file (default: a temporary one)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(dir=args.work) as tmp:
        path = Path(tmp) / "arm_poses.csv"
        start = time.perf_counter()
        size = write_log(path, args.rows)
        print(f"wrote {args.rows} rows, {size / 1e9:.2f} GB in {time.perf_counter() - start:.0f} s", flush=True)
        src = str(Path(__file__).resolve().parents[1] / "src")
        env = {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}
        out = subprocess.run([sys.executable, "-c", CHILD, str(path)], capture_output=True, text=True, env=env,
                             check=True)
        result = json.loads(out.stdout.strip().splitlines()[-1])
    result.update(file_gb=round(size / 1e9, 3), parsed_rows_mb=round(args.rows * 64 / 2**20, 1))
    child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(json.dumps(result))
    print(f"peak RSS {result['peak_rss_mb']:.0f} MB (children max {child:.0f} MB) for {result['rows']} rows; "
          f"the rows themselves {result['parsed_rows_mb']:.0f} MB; limit 1024 MB: "
          f"{'PASS' if result['peak_rss_mb'] < 1024 else 'FAIL'}")


if __name__ == "__main__":
    main()
