"""How captures and frames are paired with their poses: one documented rule, printed and checkable.

**The rule** (docs/any-arm.md, "Pairing"): every file, CSV row or table entry has an **id**:

1. the file name without its extension, and without a role suffix after a dot (``frame-000012.color.png``
   -> ``frame-000012``);
2. without role words at its start or end (``color``, ``rgb``, ``image``, ``img``, ``depth``, ``pose``,
   ``frame``, ``calib``, ``capture``, ``board``, ``boardpose``, ``flange``, ...: :data:`ROLE_WORDS`), each
   with its separator (``calib_003`` -> ``003``, ``img_2024-05-01_14-05-41`` -> ``2024-05-01_14-05-41``);
3. a remainder of digits only is a number (``003`` and ``3`` are the same id); anything else is kept whole,
   so names ending in a time (``..._14-05-41``) never collide on their last number.

A CSV's id column (``--id-column NAME``; default its first column when that is not a number) goes through the
same rule, so ``calib_003.png``, ``003`` and ``3`` all name capture ``3``. When the two sides share no id by
this rule, the **last number** of each name is tried and used when it is unique on both sides (the rule used
is printed). An **order file** (``--order FILE``: one image or frame name per line, in the order of the pose
rows) pairs by position instead, and a pose table without ids pairs with the images in natural order.

:func:`describe_pairs` prints the first and last pairs; the pairing is then *checked* by the caller
(hand-eye: boards placed in the base; RGB-D: neighbouring frames' back-projections) against the likely
mistakes: poses shifted by one, the hand-eye or the poses inverted, the other quaternion order
(:func:`judge_alternatives`). ``--pair-shift N`` pairs image ``i`` with the pose ``N`` places later on purpose
(:func:`shift_poses`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np

from darp.errors import FormatError

V = TypeVar("V")

ROLE_WORDS = ("color", "colour", "rgb", "image", "images", "img", "depth", "pose", "poses", "frame", "calib",
              "calibration", "capture", "cap", "shot", "board", "boardpose", "board_pose", "flange", "tool", "tcp",
              "ee", "transform", "matrix", "aligned", "registered", "raw")
_SEP = r"[-_. ]"
_WORDS = "|".join(sorted((re.escape(w) for w in ROLE_WORDS), key=len, reverse=True))
_LEAD = re.compile(rf"^(?:{_WORDS})(?:{_SEP}+|(?=\d))", re.IGNORECASE)
_TRAIL = re.compile(rf"(?:{_SEP}+|(?<=\d))(?:{_WORDS})$", re.IGNORECASE)


def file_stem(name: str) -> str:
    """The name without its extension and without a role suffix after a dot (``a.color.png`` -> ``a``)."""
    base = Path(name).name
    head, dot, ext = base.rpartition(".")
    stem = head if dot and head and ext.isalpha() and len(ext) <= 5 else base  # a time stamp's decimals stay
    parts = stem.split(".")
    while len(parts) > 1 and parts[-1].lower() in ROLE_WORDS:
        parts.pop()
    return ".".join(parts)


def frame_id(name: str) -> str:
    """The id of a file name or CSV id (the module's rule): stem, role words dropped, digits as a number."""
    s = file_stem(str(name).strip())
    for _ in range(3):
        t = _TRAIL.sub("", _LEAD.sub("", s))
        if t == s or not t:
            break
        s = t
    s = s.strip("-_. ")
    if s.isdigit():
        return s.lstrip("0") or "0"
    return s.lower() if s else file_stem(str(name)).lower()


def last_number(name: str) -> str | None:
    """The last number of a file stem (the fallback rule), or None."""
    runs = re.findall(r"\d+", file_stem(name))
    return (runs[-1].lstrip("0") or "0") if runs else None


def natural_key(key: str) -> tuple[tuple[int, int | str], ...]:
    """Sort key that orders embedded numbers numerically (``2`` before ``10``; times chronologically)."""
    return tuple((0, int(p)) if p.isdigit() else (1, p) for p in re.split(r"(\d+)", key) if p)


def keyed(items: Iterable[tuple[str, V]], source: Path | str, what: str = "file") -> dict[str, V]:
    """``{frame_id(name): value}``, or a FormatError naming both names when two share an id."""
    out: dict[str, V] = {}
    names: dict[str, str] = {}
    for name, value in items:
        k = frame_id(name)
        if k in out:
            kinds = {Path(names[k]).stem.rstrip("0123456789_-").lower(), Path(name).stem.rstrip("0123456789_-").lower()}
            hint = (f"; these look like two kinds of file ({', '.join(sorted(kinds))}) in one folder: keep one "
                    "kind per folder (board poses in board_poses/, flange poses in poses/)") if len(kinds) > 1 else ""
            raise FormatError(f"two {what}s have the id {k!r} ({names[k]}, {name}){hint}; rename one, or pair "
                              "with --order FILE (see docs/any-arm.md, Pairing)", source)
        out[k], names[k] = value, name
    return out


@dataclass
class Pairing:
    """Which observation (image, board pose, depth frame) goes with which pose, and by which rule."""

    rule: str
    pairs: list[tuple[str, str, str]]  # (id, observation name, pose name) in natural order
    no_pose: list[str] = field(default_factory=list)  # observation names without a pose
    no_observation: list[str] = field(default_factory=list)  # pose names without an observation

    @property
    def ids(self) -> list[str]:
        return [k for k, _, _ in self.pairs]


def pair_names(observations: Sequence[str], poses: Sequence[str], source: Path | str, *,
               order: Sequence[str] | None = None, poses_have_ids: bool = True) -> tuple[Pairing, dict[str, str],
                                                                                           dict[str, str]]:
    """Pair observation names with pose names by the module's rule.

    Returns (pairing, observation name -> id, pose name -> id); the ids are what both sides are keyed by.
    ``order``: names in the order of the poses (an order file); ``poses_have_ids=False``: the poses are rows
    in order, paired with the observations in natural order.
    """
    if order is not None or not poses_have_ids:
        obs_sorted = list(order) if order is not None else sorted(observations, key=lambda n: natural_key(frame_id(n)))
        known = {Path(n).name: n for n in observations} | {frame_id(n): n for n in observations}
        omap, pmap, pairs = {}, {}, []
        for i, name in enumerate(obs_sorted):
            if i >= len(poses):
                break
            real = known.get(Path(name).name, known.get(frame_id(name)))
            if real is None:
                raise FormatError(f"line {i + 1}: {name!r} is not one of the images/frames", source)
            k = str(i)
            omap[real], pmap[poses[i]] = k, k
            pairs.append((k, real, poses[i]))
        rule = "order file" if order is not None else "position (natural order of the names; the poses have no ids)"
        return (Pairing(rule, pairs, [n for n in observations if n not in omap], [p for p in poses if p not in pmap]),
                omap, pmap)
    o = {n: frame_id(n) for n in observations}
    p = {n: frame_id(n) for n in poses}
    rule = "file stem (role words dropped, numbers without leading zeros)"
    if not set(o.values()) & set(p.values()):
        lo = {n: last_number(n) for n in observations}
        lp = {n: last_number(n) for n in poses}
        unique = (None not in lo.values() and None not in lp.values() and len(set(lo.values())) == len(lo)
                  and len(set(lp.values())) == len(lp))
        if unique and set(lo.values()) & set(lp.values()):
            o, p = {n: str(v) for n, v in lo.items()}, {n: str(v) for n, v in lp.items()}
            rule = "last number in the name (the stems share no id)"
    by_pose = {v: n for n, v in p.items()}
    pairs = sorted(((k, n, by_pose[k]) for n, k in o.items() if k in by_pose), key=lambda t: natural_key(t[0]))
    paired = {k for k, _, _ in pairs}
    return (Pairing(rule, pairs, sorted((n for n, k in o.items() if k not in paired), key=natural_key),
                    sorted((n for n, k in p.items() if k not in paired), key=natural_key)), o, p)


def describe_pairs(pairing: Pairing, head: int = 3) -> str:
    """One printable line: the rule, how many pairs, and the first and last few."""
    shown = pairing.pairs if len(pairing.pairs) <= 2 * head else pairing.pairs[:head] + pairing.pairs[-head:]
    text = ", ".join(f"{Path(a).name} <-> {Path(b).name}" for _, a, b in shown)
    if len(pairing.pairs) > 2 * head:
        cut = text.split(", ")
        text = ", ".join(cut[:head]) + ", ..., " + ", ".join(cut[head:])
    extra = ""
    if pairing.no_pose:
        extra += f"; {len(pairing.no_pose)} without a pose"
    if pairing.no_observation:
        extra += f"; {len(pairing.no_observation)} poses unused"
    return f"paired {len(pairing.pairs)} by {pairing.rule}: {text}{extra}"


def read_order_file(path: str | Path) -> list[str]:
    """An order file: one image/frame name per line (``#`` comments, blank lines skipped)."""
    p = Path(path)
    from darp.formats.text import read_utf8_text

    lines = read_utf8_text(p, "an order file").splitlines()
    names = [s.split(",")[0].strip() for s in (line.strip() for line in lines) if s and not s.startswith("#")]
    if not names:
        raise FormatError("the order file names no image", p)
    return names


def shift_poses(poses: Mapping[str, V], ids: Sequence[str], shift: int) -> dict[str, V]:
    """Pair the observation at position ``i`` of ``ids`` (natural order) with the pose at ``i + shift``."""
    order = sorted(ids, key=natural_key)
    out: dict[str, V] = {}
    for i, k in enumerate(order):
        j = i + shift
        if 0 <= j < len(order) and order[j] in poses:
            out[k] = poses[order[j]]
    return out


ALTERNATIVE_FIX = {
    "shift+1": "each image is paired with the pose one row too early: the poses are shifted by one (pair with "
               "--pair-shift 1, or fix the names/--order)",
    "shift-1": "each image is paired with the pose one row too late: the poses are shifted by one (pair with "
               "--pair-shift -1, or fix the names/--order)",
    "inverted hand-eye": "the hand-eye looks inverted (camera-from-flange given as flange-from-camera): invert it",
    "inverted poses": "the poses look inverted (camera-from-world or flange-from-base given as world-from-camera / "
                      "base-from-flange): invert them",
    "quaternion order": "the quaternions look like the other order (wxyz vs xyzw): declare it (handeye.yaml's "
                        "quaternion:, or darp import --quaternion)",
    "ROS body camera frame": "the hand-eye's camera frame looks like a ROS body frame (x forward), not the optical "
                             "frame (x right, y down, z forward): give the optical frame's transform",
}


def judge_alternatives(scores: Mapping[str, float], source: Path | str, what: str, *, ratio: float = 0.5,
                       min_value: float = 3.0, force: bool = False) -> str | None:
    """The pairing check's verdict: ``scores`` are disagreements (mm, lower is better) of the data as given
    (``"as given"``) and of each alternative reading (keys of :data:`ALTERNATIVE_FIX`).

    Raise a one-line FormatError naming ``source``, the better reading and the fix when an alternative
    disagrees less than ``ratio`` times as much (and the given reading more than ``min_value``); with
    ``force`` return that line as a warning text instead. None when the data as given is the best reading.
    """
    given = scores["as given"]
    alts = {k: v for k, v in scores.items() if k != "as given" and not np.isnan(v)}
    if not alts or np.isnan(given):
        return None
    best = min(alts, key=lambda k: alts[k])
    if given > min_value and alts[best] < ratio * given:
        others = ", ".join(f"{k} {v:.1f}" for k, v in alts.items() if k != best)
        line = (f"{ALTERNATIVE_FIX.get(best, best)} ({what} disagree by {given:.1f} mm median as given, "
                f"{alts[best]:.1f} mm {best}; {others})")
        if force:
            return f"kept as given (--force): {line}"
        raise FormatError(line + "; --force keeps the data as given", source)
    return None


COLOUR_WORDS = ("color", "colour", "rgb", "image", "img")
DEPTH_WORDS = ("depth",)
RGBD_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def rgbd_frames(folder: Path) -> tuple[dict[str, Path], dict[str, Path]]:
    """(colour, depth) image files by frame id in an RGB-D folder.

    A file whose path (name or sub-folder) contains ``depth`` is a depth image, one with ``color``/``colour``/
    ``rgb``/``image``/``img`` a colour image; files with neither, side by side in one folder, pair by id:
    the ``.jpg``/``.jpeg`` is the colour, the ``.png``/``.tif`` the depth (``12.jpg`` + ``12.png``).
    """
    files = [f for f in sorted(folder.rglob("*")) if f.is_file() and f.suffix.lower() in RGBD_SUFFIXES]
    colour: list[tuple[str, Path]] = []
    depth: list[tuple[str, Path]] = []
    plain: dict[str, list[Path]] = {}
    for f in files:
        rel = str(f.relative_to(folder)).lower()
        if any(w in rel for w in DEPTH_WORDS):
            depth.append((str(f.relative_to(folder)), f))
        elif any(w in rel for w in COLOUR_WORDS):
            colour.append((str(f.relative_to(folder)), f))
        else:
            plain.setdefault(frame_id(f.name), []).append(f)
    for group in plain.values():
        for f in group:
            jpeg = f.suffix.lower() in (".jpg", ".jpeg")
            if jpeg or any(g.suffix.lower() in (".jpg", ".jpeg") for g in group):
                (colour if jpeg else depth).append((str(f.relative_to(folder)), f))
    if not depth:
        raise FormatError("no depth images (names or folders containing 'depth', or a .png beside each .jpg)",
                          folder)
    return keyed(colour, folder, "colour image"), keyed(depth, folder, "depth image")


def backprojected(depth: np.ndarray, scale: float, K: np.ndarray, T: np.ndarray, max_points: int = 20000
                  ) -> np.ndarray:
    """World points (N, 3) of a depth image's valid pixels (every ``step``-th, at most about ``max_points``)."""
    step = max(1, int(np.ceil(np.sqrt(depth.size / max_points))))
    d = depth[::step, ::step].astype(np.float64) * scale
    v, u = np.nonzero(d)
    z = d[v, u]
    P = np.stack([(u * step - K[0, 2]) / K[0, 0] * z, (v * step - K[1, 2]) / K[1, 1] * z, z], 1)
    return np.asarray(P @ T[:3, :3].T + T[:3, 3])


def neighbour_agreement(depths: Sequence[np.ndarray], K: np.ndarray, scale: float,
                        poses: Sequence[np.ndarray | None]) -> list[float]:
    """Per consecutive pair of frames: the median distance (mm) from the second's back-projected points to the
    first's nearest (NaN where a pose is missing)."""
    from scipy.spatial import cKDTree

    out = []
    for i in range(0, len(depths) - 1, 2):
        T0, T1 = poses[i], poses[i + 1]
        if T0 is None or T1 is None:
            out.append(float("nan"))
            continue
        A = backprojected(depths[i], scale, K, T0)
        B = backprojected(depths[i + 1], scale, K, T1)
        out.append(1e3 * float(np.median(cKDTree(A).query(B)[0])) if len(A) and len(B) else float("nan"))
    return out


__all__ = ["ALTERNATIVE_FIX", "ROLE_WORDS", "Pairing", "describe_pairs", "file_stem", "frame_id", "judge_alternatives",
           "backprojected", "keyed", "last_number", "natural_key", "neighbour_agreement", "pair_names",
           "read_order_file", "rgbd_frames", "shift_poses"]
