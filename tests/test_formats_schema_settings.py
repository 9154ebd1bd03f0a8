"""The one settings reader (darp.formats.schema.dataclass_from_mapping) and the one unknown-key rule."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest

import darp
from darp.errors import ConfigError, DarpError, FormatError
from darp.formats.schema import dataclass_from_mapping, refuse_unknown_keys
from darp.processing.settings import load_settings

SRC = Path(darp.__file__).resolve().parent


@dataclass(frozen=True)
class Inner:
    gain: float = 1.0

    def __post_init__(self) -> None:
        if self.gain <= 0:
            raise ConfigError(f"gain: must be positive, got {self.gain}")


@dataclass(frozen=True)
class Outer:
    size: int = 3
    factors: tuple[float, ...] = (1.0,)
    inner: Inner = field(default_factory=Inner)


def test_fields_not_given_keep_the_base_or_the_defaults() -> None:
    assert dataclass_from_mapping(Outer, None) == Outer()
    assert dataclass_from_mapping(Outer, {"size": 5}) == Outer(size=5)
    base = Outer(size=7, inner=Inner(2.0))
    assert dataclass_from_mapping(Outer, {"inner": {}}, base=base, nested={"inner": Inner}) == base
    got = dataclass_from_mapping(Outer, {"factors": [1, 2], "inner": {"gain": 4}}, nested={"inner": Inner},
                                 convert={"factors": lambda v: tuple(float(x) for x in v)})
    assert got == Outer(factors=(1.0, 2.0), inner=Inner(4.0)) and isinstance(got.factors, tuple)


@pytest.mark.parametrize(("values", "message"), [
    ({"sise": 5}, "settings.yaml: unknown key(s) outer.sise (known: size, factors, inner)"),
    ({"inner": {"gian": 1}}, "settings.yaml: unknown key(s) outer.inner.gian (known: gain)"),
    ({"inner": {"gain": -1}}, "settings.yaml: outer.inner: gain: must be positive, got -1"),
    ({"inner": 3}, "settings.yaml: outer.inner: expected a mapping, got int"),
    ([1, 2], "settings.yaml: outer: expected a mapping, got list"),
])
def test_errors_name_the_dotted_key_and_the_file(values: object, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        dataclass_from_mapping(Outer, values, "outer", nested={"inner": Inner}, path="settings.yaml",
                               error=ConfigError)
    assert str(info.value) == message and "\n" not in str(info.value)


def test_unknown_keys_use_the_callers_error_class() -> None:
    with pytest.raises(FormatError, match=r"^f.json: unknown key\(s\) a.b, a.c \(known: x\)$"):
        refuse_unknown_keys({"x": 1, "b": 2, "c": 3}, ("x",), "a", "f.json")
    refuse_unknown_keys({"x": 1}, ("x",))


def test_a_settings_file_with_a_typo_names_the_file_and_key(tmp_path: Path) -> None:
    path = tmp_path / "process.yaml"
    path.write_text("fusion:\n  depth:\n    min_depth_mm: 0.2\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"process.yaml: unknown key\(s\) fusion.depth.min_depth_mm \(known: "):
        load_settings(path)


UNKNOWN_KEY_WORDS = re.compile(r"unknown (key|field|setting)")


@pytest.mark.parametrize("path", sorted(SRC.rglob("*.py")), ids=lambda p: str(p.relative_to(SRC)))
def test_no_settings_reader_writes_its_own_unknown_key_check(path: Path) -> None:
    if path == SRC / "formats" / "schema.py":
        return
    text = path.read_text(encoding="utf-8")
    assert not UNKNOWN_KEY_WORDS.search(text), f"{path.relative_to(SRC)}: use darp.formats.schema.refuse_unknown_keys"
    assert "__dataclass_fields__" not in text, f"{path.relative_to(SRC)}: use dataclass_from_mapping"


def test_the_checker_sees_a_copy() -> None:
    assert UNKNOWN_KEY_WORDS.search('raise ConfigError(f"{where}: unknown setting(s) {names}")')
    assert issubclass(ConfigError, DarpError)
