"""Reading a user's text file (UTF-8, optional BOM) and YAML mappings, with every failure mapped to
one darp error that names the file: a missing file, a folder, a file that is not a regular file,
bytes that are not UTF-8."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from darp.errors import ConfigError, DarpError, FormatError
from darp.formats.io_input import LIMITS, read_input_bytes


def read_utf8_text(path: str | Path, what: str, error: type[DarpError] = FormatError, *,
                   limit: int = LIMITS["text"]) -> str:
    """The text of ``path`` (a leading BOM dropped); ``what`` names the expected kind in the folder
    error ("is a folder, not a JSON file"). Read through :func:`darp.formats.io_input.read_input_bytes`:
    a regular file of at most ``limit`` bytes."""
    path = Path(path)
    data = read_input_bytes(path, what, error, limit=limit)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise error(f"not UTF-8 text (byte {err.start})", path) from err


class YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2 floats: ``1.0e6`` and ``1e6`` are numbers, as in JSON, not the
    strings YAML 1.1 makes of them (``1.0e+6`` was a number, ``1.0e6`` a string)."""


YamlLoader.yaml_implicit_resolvers = {k: [r for r in v if r[0] != "tag:yaml.org,2002:float"]
                                      for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def load_yaml(text: str) -> Any:
    """Parse YAML text with :class:`YamlLoader` (safe, YAML 1.2 floats)."""
    return yaml.load(text, Loader=YamlLoader)


def read_yaml_mapping(path: str | Path, *, empty_ok: bool = False) -> dict[str, Any]:
    """Parse a YAML (or JSON) file whose top level is a mapping; every failure is a ConfigError naming
    ``path``. ``empty_ok``: an empty file is an empty mapping (a settings file that changes nothing)."""
    path = Path(path)
    text = read_utf8_text(path, "a YAML file", ConfigError, limit=LIMITS["yaml"])
    try:
        data = load_yaml(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"invalid YAML{where}: {problem}", path) from None
    except RecursionError:
        raise ConfigError("nested too deeply", path) from None
    if data is None and empty_ok:
        return {}
    if not isinstance(data, dict):
        kind = "empty" if data is None else type(data).__name__
        raise ConfigError(f"top level must be a mapping, got {kind}", path)
    return data


__all__ = ["YamlLoader", "load_yaml", "read_utf8_text", "read_yaml_mapping"]
