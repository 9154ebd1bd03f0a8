"""Are issue 32's kinds of case clean on other files and options? A sweep of the command line as a user runs it.

Each case runs ``python -m darp ...`` in a scratch folder holding a named pipe, an empty survey, a captures folder
and a copy of the packaged rig, and is clean when it ends in time with exit 2 and exactly one ``darp: error:``
line (warnings aside), no traceback, and no input changed (every file of the scratch folder that existed before
is byte-identical after; nothing but the named outputs appears). The cases are the issue's kinds (special files
as inputs, outputs over inputs, out-of-range and non-finite options) on files and options the tests do not use.

    .venv/bin/python studies/reliability_sweep.py [--timeout-s 40] [--only SUBSTRING]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BAG = ROOT / "tests" / "fixtures" / "recordings" / "rs257_uncompressed.bag"
CASES = [
    # special files as inputs
    "calib capture --twin -o caps2 --plan pipe", "calib capture --twin -o caps2 --plan /dev/zero",
    "process s -o out -c pipe", "poses s -o p -c /dev/zero", "poses s -o p --rig pipe", "view s --save x.rrd -c pipe",
    "twin record --object cube -w pipe -o rec", "twin record --object cube -w /dev/zero -o rec",
    "twin waypoints --object cube -o w.yaml --rig /dev/zero", "collect x --twin --object cube --rig pipe",
    "recording info pipe", "rig plot --rig pipe -o r.png", "hardware check --rig pipe", "calib check caps -c pipe",
    "rig show --rig /dev/zero", "import g -o imp --trajectory pipe --intrinsics pipe",
    # outputs over inputs
    "rig plot --rig rig.yaml -o rig.yaml", "twin waypoints --object cube --rig rig.yaml -o rig.yaml",
    "calib handeye g -o g/cal.json", "poses s -o s/poses", "export tum s -o s/x", "import g -o g/imp",
    f"recording export {BAG} -o .", "calib capture --twin -o s", "process s -o s/out", "keyframes s -o s/kf",
    # values
    "twin waypoints --object cube -o w.yaml --elevation-deg nan",
    "twin waypoints --object cube -o w.yaml --dwell-s 1e9",
    "twin waypoints --object cube -o w.yaml --azimuth-deg inf", "twin waypoints --object cube -o w.yaml --scale 1e30",
    "twin waypoints --object cube -o w.yaml --placement 1e9,0,0", "poses s -o p --max-gap-s nan",
    f"recording export {BAG} -o ex --start-ms 10 --stop-ms 5", f"recording export {BAG} -o ex --stop-ms nan",
    "twin generate -n 1 -o gen --fps 100000", "twin generate -n 1 -o gen --views 100000000",
    "twin generate -n 1 -o gen --resolution 100000x100000", "twin generate -n 1 -o gen --executor ray:127.0.0.1:1",
    "twin generate -n 1 -o gen --executor ray:nonsense", "calib handeye g -o c.json --folds 1",
    "calib handeye g -o c.json --seed -1", "calib solve caps -o c.json --folds -3", "import g -o imp --depth-scale-m 0",
    "collect x --twin --object cube --placement nan,0,0", "twin record --object cube -w rig.yaml -o rec --seed -5",
]


def scratch(folder: Path) -> None:
    """The inputs every case may name."""
    os.mkfifo(folder / "pipe")
    for name in ("caps", "g", "s"):
        (folder / name).mkdir()
    (folder / "s" / "arm_poses.csv").write_text("time_s,arm,q1,q2,q3,q4,q5,q6\n")
    (folder / "g" / "notes.txt").write_text("a user's file\n")
    shutil.copy(ROOT / "src" / "darp" / "data" / "rig_default.yaml", folder / "rig.yaml")


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def run_case(args: str, timeout_s: float) -> tuple[bool, str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        scratch(folder)
        before = snapshot(folder)
        env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
        start = time.monotonic()
        try:
            done = subprocess.run([sys.executable, "-m", "darp", *args.split()], cwd=folder, capture_output=True,
                                  text=True, timeout=timeout_s, env=env)
        except subprocess.TimeoutExpired:
            return False, "HANG", timeout_s
        seconds = time.monotonic() - start
        errors = [line for line in done.stderr.splitlines() if not line.startswith("darp: warning:")]
        after = snapshot(folder)
        changed = sorted(k for k, v in before.items() if after.get(k) != v)
        problems = []
        if done.returncode != 2:
            problems.append(f"exit {done.returncode}")
        if "Traceback" in done.stderr or len(errors) != 1 or not errors[0].startswith("darp: error:"):
            problems.append(f"{len(errors)} stderr lines")
        if changed:
            problems.append(f"inputs changed: {', '.join(changed)}")
        last = errors[-1] if errors else ""
        return not problems, "; ".join(problems) or last, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--timeout-s", type=float, default=40.0, help="a case running longer is a hang")
    parser.add_argument("--only", default="", help="run only the cases containing this text")
    args = parser.parse_args()
    cases = [c for c in CASES if args.only in c]
    clean = 0
    for case in cases:
        ok, what, seconds = run_case(case, args.timeout_s)
        clean += ok
        print(f"{'clean' if ok else 'NOT CLEAN':9} {seconds:5.1f} s  darp {case}\n          {what[:160]}", flush=True)
    print(f"{clean} of {len(cases)} cases clean ({100.0 * clean / max(len(cases), 1):.0f} %)")


if __name__ == "__main__":
    main()
