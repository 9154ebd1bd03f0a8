"""Small validation helpers shared by the JSON formats (envelope, calibration) and every settings reader.

Each helper checks one value and raises :class:`darp.errors.FormatError` (or the subclass given) with
the file path and the dotted name of the field, so that a bad file is reported in one line:
``calibration.json: arms.arm110.T_world_base: not a rigid transform: rotation is not orthonormal (error 3.2e-02,
...)``. Settings files (rig, twin, processing, hardware, waypoints) are read into dataclasses by the one
:func:`dataclass_from_mapping`, which refuses unknown keys with :func:`refuse_unknown_keys`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from darp.errors import DarpError, FormatError
from darp.formats.atomic import write_text_atomic
from darp.formats.limits import MAX_JSON_BYTES
from darp.formats.text import read_utf8_text
from darp.geometry.rigid import check_rigid


def load_json_object(path: str | Path, error: type[FormatError] = FormatError) -> dict[str, Any]:
    """Read a JSON file whose top level is an object; syntax errors name the line and column. A file over
    ``MAX_JSON_BYTES`` is refused before it is read (none of darp's JSON files comes near it)."""
    path = Path(path)
    text = read_utf8_text(path, "a JSON file", error, limit=MAX_JSON_BYTES)
    if not text.strip():
        raise error("empty file: expected a JSON object", path)
    try:
        payload = json.loads(text)
    except json.JSONDecodeError as err:
        raise error(f"invalid JSON at line {err.lineno} column {err.colno}: {err.msg}", path) from err
    except RecursionError:
        raise error(f"nested too deeply (more than about {sys.getrecursionlimit()} levels)", path) from None
    except ValueError as err:  # an integer longer than Python's int-parsing limit (4300 digits)
        raise error(f"invalid JSON: {str(err).splitlines()[0]}", path) from None
    if not isinstance(payload, dict):
        raise error(f"top level must be a JSON object, not {_type_name(payload)}", path)
    return payload


def write_json_checked(path: str | Path, payload: Any) -> None:
    """Write ``payload`` atomically as indented JSON; NaN/inf are refused (JSON has no such numbers)."""
    try:
        text = json.dumps(to_jsonable(payload), indent=2, allow_nan=False)
    except ValueError as err:
        raise FormatError(f"cannot write: {err}", path) from err
    write_text_atomic(path, text + "\n")


def to_jsonable(value: Any) -> Any:
    """numpy arrays/scalars and tuples to plain lists and numbers, recursively."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    return value


def _type_name(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def as_float(
    value: Any,
    field: str,
    path: str | Path | None,
    *,
    positive: bool = False,
    error: type[FormatError] = FormatError,
) -> float:
    """A finite JSON number (booleans are not numbers); optionally > 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(f"{field}: expected a number, got {_type_name(value)}", path)
    number = float(value)
    if not math.isfinite(number):
        raise error(f"{field}: must be finite, got {number}", path)
    if positive and number <= 0.0:
        raise error(f"{field}: must be positive, got {number}", path)
    return number


def as_optional_float(
    value: Any, field: str, path: str | Path | None, *, positive: bool = False,
    error: type[FormatError] = FormatError,
) -> float | None:
    """Like :func:`as_float`, but ``None`` (JSON null or an absent key) stays ``None``."""
    return None if value is None else as_float(value, field, path, positive=positive, error=error)


def as_int(
    value: Any, field: str, path: str | Path | None, *, minimum: int | None = None,
    error: type[FormatError] = FormatError,
) -> int:
    """A JSON integer (``3.0`` is refused: counts are written as integers)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise error(f"{field}: expected an integer, got {_type_name(value)}", path)
    if minimum is not None and value < minimum:
        raise error(f"{field}: must be >= {minimum}, got {value}", path)
    return int(value)


def as_str(value: Any, field: str, path: str | Path | None, error: type[FormatError] = FormatError) -> str:
    if not isinstance(value, str):
        raise error(f"{field}: expected a string, got {_type_name(value)}", path)
    return value


def as_dict(
    value: Any, field: str, path: str | Path | None, error: type[FormatError] = FormatError
) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise error(f"{field}: expected an object, got {_type_name(value)}", path)
    return value


def as_array(
    value: Any,
    field: str,
    path: str | Path | None,
    shape: tuple[int, ...],
    error: type[FormatError] = FormatError,
) -> np.ndarray:
    """A nested list of finite numbers with exactly ``shape``, as a float64 array."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, Sequence) or isinstance(value, str):
        raise error(f"{field}: expected a list of shape {shape}, got {_type_name(value)}", path)
    _check_numbers(value, field, path, error)
    try:
        array = np.asarray(value, dtype=np.float64)
    except ValueError as err:  # ragged nesting
        raise error(f"{field}: expected a list of shape {shape} (ragged rows)", path) from err
    if array.shape != shape:
        raise error(f"{field}: expected shape {shape}, got {array.shape}", path)
    if not np.all(np.isfinite(array)):
        raise error(f"{field}: all values must be finite", path)
    return array


def _check_numbers(value: Any, field: str, path: str | Path | None, error: type[FormatError]) -> None:
    if isinstance(value, (list, tuple)):
        for item in value:
            _check_numbers(item, field, path, error)
    elif isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(f"{field}: expected numbers, found {_type_name(value)}", path)


def as_rigid_transform(
    value: Any,
    field: str,
    path: str | Path | None,
    *,
    error: type[FormatError] = FormatError,
) -> np.ndarray:
    """A 4x4 rigid transform by :func:`darp.geometry.rigid.check_rigid`'s rule: finite, orthonormal right-handed
    rotation, last row ``0 0 0 1``."""
    return check_rigid(as_array(value, field, path, (4, 4), error), field, path, error=error)


_Settings = TypeVar("_Settings")


def dotted(where: str, key: object) -> str:
    """The dotted path of ``key`` inside ``where`` (``fusion`` + ``depth`` -> ``fusion.depth``)."""
    return f"{where}.{key}" if where else str(key)


def refuse_unknown_keys(values: Iterable[Any], known: Iterable[str], where: str = "", path: str | Path | None = None,
                        error: type[DarpError] = FormatError) -> None:
    """The one unknown-key rule of darp's files: a key not in ``known`` (a misspelt key would otherwise keep its
    default silently) is refused in one line naming its dotted path, the known keys and the file."""
    known = tuple(known)
    unknown = [dotted(where, k) for k in values if k not in known]
    if unknown:
        raise error(f"unknown key(s) {', '.join(unknown)} (known: {', '.join(known)})", path)


def dataclass_from_mapping(
    cls: type[_Settings],
    values: Any,
    where: str = "",
    *,
    base: _Settings | None = None,
    nested: Mapping[str, type] | None = None,
    convert: Mapping[str, Callable[[Any], Any]] | None = None,
    path: str | Path | None = None,
    error: type[DarpError] = FormatError,
) -> _Settings:
    """The dataclass ``cls`` from a (partial) mapping of its field names: the settings readers' one reader.

    Fields not given keep ``base``'s values (``cls``'s defaults without one); ``None`` gives ``base`` or the
    defaults. ``nested`` fields are dataclasses read the same way; ``convert`` turns a value into the field's
    type (a YAML list into a tuple). Unknown keys, a non-mapping, a value the class refuses (its own
    ``__post_init__`` check raising a :class:`~darp.errors.DarpError`) or a missing argument are ``error`` with
    the dotted path of ``where`` and the file ``path``."""
    if values is None:
        return base if base is not None else cls()
    if not isinstance(values, Mapping):
        raise error(f"{where or 'settings'}: expected a mapping, got {type(values).__name__}", path)
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]  # cls is a dataclass type
    refuse_unknown_keys(values, names, where, path, error)
    kwargs = dict(values)
    for name, sub in (nested or {}).items():
        if name in kwargs:
            current = getattr(base, name) if base is not None else None
            kwargs[name] = dataclass_from_mapping(sub, kwargs[name], dotted(where, name), base=current, path=path,
                                                  error=error)
    for name, change in (convert or {}).items():
        if name in kwargs:
            kwargs[name] = change(kwargs[name])
    try:
        return dataclasses.replace(base, **kwargs) if base is not None else cls(**kwargs)  # type: ignore[type-var]
    except DarpError as err:  # the class's own check; its message may already name the dotted path
        named = not where or err.message.startswith((f"{where}.", f"{where}:"))
        raise error(err.message if named else f"{where}: {err.message}", path) from None
    except TypeError as err:
        raise error(f"{where}: {err}" if where else str(err), path) from None
