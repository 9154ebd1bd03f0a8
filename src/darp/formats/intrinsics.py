"""Camera intrinsics files: a 3x3 camera matrix and distortion coefficients, in the forms people have them.

:func:`load_intrinsics` reads a 3x3 text/.npy, an .npz (``cameraMatrix``/``K``, ``distCoeffs``/``dist``), JSON
(``{"K": 3x3}``, Open3D's ``camera_intrinsic.json``, ``{"fx", "fy", "cx"|"ppx", "cy"|"ppy"}``), or a RealSense
recording's colour stream. Open3D's ``PinholeCameraIntrinsic`` JSON is read and written here
(:func:`read_open3d_intrinsic`, :func:`open3d_intrinsic_json`): ``intrinsic_matrix`` is the 3x3 column-major,
pixel centres at integer coordinates like OpenCV's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError
from darp.formats.io_input import LIMITS, load_numpy
from darp.formats.text import read_utf8_text


@dataclass(frozen=True)
class CameraModel:
    """OpenCV pinhole + distortion (k1, k2, p1, p2[, k3 ...]) as read from a file."""

    K: np.ndarray
    dist: np.ndarray
    source: str = ""
    model: str = "Brown Conrady"  # librealsense's name; "Brown Conrady" is OpenCV's model
    size: tuple[int, int] | None = None  # (width, height) when the file gives it


def check_camera_matrix(K: np.ndarray, path: Path, where: str = "") -> np.ndarray:
    """``K`` as a float 3x3 ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` with fx, fy > 0, else a FormatError naming
    ``path`` (and ``where`` in it, e.g. a frame)."""
    K = np.asarray(K, np.float64).reshape(3, 3)
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and abs(K[2, 2] - 1) < 1e-9
            and K[2, 0] == 0 and K[2, 1] == 0):
        prefix = f"{where}: " if where else ""
        raise FormatError(f"{prefix}not a 3x3 camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0 "
                          "(check row/column order)", path)
    return K


def open3d_matrix(values: Any) -> np.ndarray:
    """The 3x3 of Open3D's ``intrinsic_matrix`` (9 values, column-major)."""
    return np.asarray(values, np.float64).reshape(3, 3).T


def read_open3d_intrinsic(path: str | Path) -> tuple[np.ndarray, int, int]:
    """Open3D's ``PinholeCameraIntrinsic`` JSON: (K, width, height); ``intrinsic_matrix`` is column-major."""
    p = Path(path)
    try:
        d = json.loads(read_utf8_text(p, "a JSON file", limit=LIMITS["json"]))
        K = open3d_matrix(d["intrinsic_matrix"])
        return K, int(d.get("width", 0)), int(d.get("height", 0))
    except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError) as err:
        raise FormatError(f"not an Open3D camera_intrinsic.json ({err})", p) from None


def open3d_intrinsic_json(width: int, height: int, fx: float, fy: float, ppx: float, ppy: float) -> dict[str, Any]:
    """Open3D's ``camera_intrinsic.json`` (PinholeCameraIntrinsic: the 3x3 column-major)."""
    return {"width": width, "height": height, "intrinsic_matrix": [fx, 0.0, 0.0, 0.0, fy, 0.0, ppx, ppy, 1.0]}


def load_intrinsics(path: str | Path) -> CameraModel:
    """Intrinsics from a 3x3 text/.npy, an .npz (``cameraMatrix``/``K``, ``distCoeffs``/``dist``), JSON, or a
    RealSense recording (``.bag``/``.db3``: its colour stream, to which aligned depth is registered).

    JSON: ``{"K": 3x3}``, Open3D's ``camera_intrinsic.json`` (``intrinsic_matrix``, column-major) or
    ``{"fx", "fy", "cx"|"ppx", "cy"|"ppy"}``, optional ``"dist"``/``"coeffs"``; a nerfstudio-style
    ``fl_x``/``fl_y`` works too (its cx/cy taken as given: see ``darp import`` for nerfstudio's +0.5).
    A text file may hold the 3x3 then one distortion line.
    """
    p = Path(path)
    if not p.exists():  # a folder or a pipe is refused by the reading below, in its own words
        raise FormatError("intrinsics file not found", p)
    if p.suffix in (".bag", ".db3"):
        return _recording_intrinsics(p)
    dist = np.zeros(5)
    try:
        if p.suffix == ".npz":
            z = load_numpy(p, "an intrinsics .npz")
            key = next((k for k in ("cameraMatrix", "camera_matrix", "K", "mtx") if k in z), None)
            if key is None:
                raise FormatError(f"no cameraMatrix/K array (has {', '.join(z)})", p)
            K = z[key]
            dk = next((k for k in ("distCoeffs", "dist_coeffs", "dist", "D") if k in z), None)
            if dk is not None:
                dist = np.asarray(z[dk], np.float64).reshape(-1)
        elif p.suffix == ".npy":
            K = load_numpy(p, "an intrinsics .npy")
        elif p.suffix in (".yaml", ".yml") or (p.suffix == ".json" and _is_named_form(
                d := json.loads(read_utf8_text(p, "a JSON file", limit=LIMITS["json"])))):
            return read_named_intrinsics(p)
        elif p.suffix == ".json":
            if "K" in d or "camera_matrix" in d:
                K = np.asarray(d.get("K", d.get("camera_matrix")), np.float64)
            elif "intrinsic_matrix" in d:  # Open3D's PinholeCameraIntrinsic: 9 values, column-major
                K = open3d_matrix(d["intrinsic_matrix"])
            else:
                fx = d.get("fx", d.get("fl_x"))
                fy = d.get("fy", d.get("fl_y", fx))
                cx = d.get("cx", d.get("ppx"))
                cy = d.get("cy", d.get("ppy"))
                if None in (fx, cx, cy):
                    raise FormatError("JSON intrinsics need K, or fx, fy, cx, cy", p)
                K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
            for k in ("dist", "coeffs", "distortion", "dist_coeffs"):
                if k in d:
                    dist = np.asarray(d[k], np.float64).reshape(-1)
                    break
            else:
                dist = np.array([d.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")], np.float64)
        else:
            rows = [r for r in (line.replace(",", " ").split() for line in read_utf8_text(p, "a text file")
                                .splitlines() if line.strip() and not line.lstrip().startswith("#")) if r]
            vals = [[float(v) for v in r] for r in rows]
            K = np.array(vals[:3], np.float64)
            if len(vals) > 3:
                dist = np.array(vals[3], np.float64)
    except (ValueError, OSError, KeyError, json.JSONDecodeError) as err:
        raise FormatError(f"cannot read intrinsics ({err})", p) from None
    return CameraModel(check_camera_matrix(K, p), np.asarray(dist, np.float64), str(p))


_NAMED_KEYS = ("focallength", "principalpoint", "width", "imagewidth", "imagesize", "distortionmodel",
               "distortioncoefficients")
_NESTS = ("color", "colour", "rgb", "intrinsics", "camera", "colorintrinsics", "camerainfo", "cameraintrinsics")


def _norm(key: object) -> str:
    return "".join(ch for ch in str(key).lower() if ch.isalnum())


def _flat(d: Any) -> dict[str, Any]:
    """A mapping with normalised keys (lower case, no spaces/underscores), one known nesting level opened."""
    if not isinstance(d, dict):
        return {}
    out = {_norm(k): v for k, v in d.items()}
    for k in _NESTS:
        if isinstance(out.get(k), dict) and not any(n in out for n in ("fx", "focallength", "k", "cameramatrix")):
            return _flat(out[k])
    return out


def _is_named_form(d: Any) -> bool:
    if isinstance(d, dict) and "intrinsic_matrix" in d:  # Open3D's PinholeCameraIntrinsic (column-major)
        return False
    f = _flat(d)
    return any(k in f for k in _NAMED_KEYS) or isinstance(f.get("cameramatrix"), dict) or (
        isinstance(d, dict) and "k" in d)


def _values(v: Any) -> list[float]:
    """Numbers of a list, a ``{rows, cols, data}`` matrix (OpenCV/ROS YAML) or a space/comma string."""
    if isinstance(v, dict):
        v = v.get("data", v.get("Data"))
    if isinstance(v, str):
        v = v.replace(",", " ").replace("[", " ").replace("]", " ").split()
    return [float(x) for x in np.asarray(v, dtype=object).reshape(-1)]


def read_named_intrinsics(path: str | Path) -> CameraModel:
    """Intrinsics written with names, JSON or YAML:

    - RealSense style (the viewer, ``rs-enumerate-devices``, many scripts): ``"Focal Length": [fx, fy]``,
      ``"Principal Point": [ppx, ppy]``, ``"Distortion Coefficients"``/``"Coeffs"``, ``"Distortion Model"``,
      ``"Width"``/``"Height"`` or ``"Image Size"``; also ``Fx``, ``Fy``, ``PPX``, ``PPY``; one nesting level
      (``{"color": {...}}``) is opened;
    - ROS ``sensor_msgs/CameraInfo`` (``K``/``k`` 9 values row-major, ``D``/``d``, ``width``, ``height``,
      ``distortion_model``) and the ``camera_calibration`` YAML (``camera_matrix: {rows, cols, data}``,
      ``distortion_coefficients``, ``image_width``, ``image_height``).
    """
    from darp.formats.text import read_yaml_mapping

    p = Path(path)
    try:
        raw = (json.loads(read_utf8_text(p, "a JSON file", limit=LIMITS["json"])) if p.suffix == ".json"
               else read_yaml_mapping(p))
        d = _flat(raw)
        if "focallength" in d:
            f = _values(d["focallength"])
            c = _values(d["principalpoint"])
            fx, fy = f[0], f[-1]
            K = np.array([[fx, 0, c[0]], [0, fy, c[1]], [0, 0, 1]], np.float64)
        elif "fx" in d and ("ppx" in d or "cx" in d):
            fx = float(d["fx"])
            K = np.array([[fx, 0, float(d.get("ppx", d.get("cx", 0.0)))], [0, float(d.get("fy", fx)),
                         float(d.get("ppy", d.get("cy", 0.0)))], [0, 0, 1]], np.float64)
        else:
            key = next(k for k in ("k", "cameramatrix") if k in d)
            K = np.asarray(_values(d[key]), np.float64).reshape(3, 3)
        dist = np.array([float(d.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")], np.float64)
        for k in ("distortioncoefficients", "coeffs", "d", "dist", "distcoeffs", "distortion"):
            if d.get(k) is not None and not isinstance(d[k], str):
                dist = np.asarray(_values(d[k]), np.float64)
                break
        model_name = str(d.get("distortionmodel", d.get("model", d["distortion"] if isinstance(
            d.get("distortion"), str) else "plumb_bob")))
        size = None
        if "width" in d or "imagewidth" in d:
            size = (int(d.get("width", d.get("imagewidth", 0))), int(d.get("height", d.get("imageheight", 0))))
        elif "imagesize" in d:
            w, h = _values(d["imagesize"])[:2]
            size = (int(w), int(h))
    except (OSError, ValueError, KeyError, TypeError, StopIteration, IndexError, json.JSONDecodeError) as err:
        raise FormatError(f"cannot read intrinsics (expected RealSense 'Focal Length'/'Principal Point', or a ROS "
                          f"CameraInfo K/D/width/height; {type(err).__name__}: {err})", p) from None
    model = _distortion_model(model_name, dist, p)
    return CameraModel(check_camera_matrix(K, p), dist, str(p), model, size)


def _distortion_model(name: str, dist: np.ndarray, path: Path) -> str:
    """librealsense's model name for a file's distortion model (OpenCV's plumb_bob is "Brown Conrady")."""
    n = _norm(name)
    if n in ("plumbbob", "browncondrady", "brownconrady", "radtan", "opencv", "rs2distortionbrownconrady", ""):
        return "Brown Conrady"
    if n in ("inversebrownconrady", "rs2distortioninversebrownconrady"):
        return "Inverse Brown Conrady"
    if n in ("modifiedbrownconrady", "rs2distortionmodifiedbrownconrady"):
        return "Modified Brown Conrady"
    if n in ("none", "rs2distortionnone") or not np.any(dist):
        return "Brown Conrady"
    raise FormatError(f"distortion model {name!r} is not supported (plumb_bob / Brown Conrady, Inverse or Modified "
                      "Brown Conrady); undistort the images first or give zero coefficients", path)


def _recording_intrinsics(p: Path) -> CameraModel:
    from darp.formats.realsense import open_recording

    with open_recording(p) as rec:
        key = "color" if "color" in rec.streams else "depth"
        i = rec.stream(key).intrinsics
    if i is None:
        raise FormatError(f"the recording's {key} stream has no intrinsics", p)
    return CameraModel(i.K, np.asarray(i.coeffs, np.float64), f"{p} ({key} stream)",
                       "Brown Conrady" if i.model == "None" else i.model)


__all__ = ["CameraModel", "check_camera_matrix", "load_intrinsics", "open3d_intrinsic_json", "open3d_matrix",
           "read_named_intrinsics", "read_open3d_intrinsic"]
