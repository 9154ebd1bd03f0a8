"""The layer table of docs/architecture.md is the rule: this test reads it from the doc and checks every import
in src/darp (module level and lazy, inside functions) against it."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

import darp

SRC = Path(darp.__file__).resolve().parent
DOC = SRC.parents[1] / "docs" / "architecture.md"
ANY = "*"


def read_layer_table(text: str) -> list[tuple[str, set[str]]]:
    """The rows of the "## Layers" table, top first: (layer, the layers its row names under "may import")."""
    section = text.split("\n## Layers", 1)[1].split("\n## ", 1)[0]
    rows: list[tuple[str, set[str]]] = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("| `darp.") or len(cells) != 3:
            continue
        layer = cells[0].strip("`").removeprefix("darp.")
        rows.append((layer, {ANY} if cells[2] == "any layer" else set(re.findall(r"`([a-z_.]+)`", cells[2]))))
    return rows


def allowed_imports(rows: list[tuple[str, set[str]]]) -> dict[str, set[str]]:
    """Each layer's allowed imports: the layers its row names and, transitively, everything they may import.
    Refuses a row naming an unknown layer or one that is not below it in the table (that would be a cycle)."""
    order = [layer for layer, _ in rows]
    named = dict(rows)
    allowed: dict[str, set[str]] = {}
    for layer in reversed(order):
        if named[layer] == {ANY}:
            allowed[layer] = set(order) - {layer}
            continue
        below = set(order[order.index(layer) + 1:])
        wrong = named[layer] - below
        assert not wrong, f"docs/architecture.md: {layer} may import {sorted(wrong)}, not layers below it"
        allowed[layer] = set().union(*([{n} | allowed[n] for n in named[layer]] or [set()]))
    return allowed


ROWS = read_layer_table(DOC.read_text(encoding="utf-8"))
ALLOWED = allowed_imports(ROWS)


def layer_of(module: str) -> str | None:
    """The longest layer name that is ``module`` (without ``darp.``) or a prefix of it."""
    name = module.removeprefix("darp.")
    matches = [layer for layer in ALLOWED if name == layer or name.startswith(layer + ".")]
    return max(matches, key=len) if matches else None


def darp_imports(path: Path) -> list[tuple[int, str]]:
    """Every darp module ``path`` imports, with its line (``from darp.x import y`` counts as ``darp.x.y`` when y
    is a module)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and (
                node.module == "darp" or node.module.startswith("darp.")):
            package = SRC.joinpath(*node.module.split(".")[1:])
            for alias in node.names:
                sub = package / alias.name
                is_module = sub.with_suffix(".py").is_file() or (sub / "__init__.py").is_file()
                found.append((node.lineno, f"{node.module}.{alias.name}" if is_module else node.module))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.startswith("darp.")]
    return sorted(set(found))


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(("darp", *(parts[:-1] if parts[-1] == "__init__" else parts)))


def breaches(path: Path, module: str) -> list[str]:
    """The imports of ``path`` (module ``module``) the layer table does not allow."""
    layer = layer_of(module)
    assert layer is not None, f"{module} is in no layer of docs/architecture.md"
    out = []
    for line, name in darp_imports(path):
        target = layer_of(name)
        if target is None and name == "darp":
            continue  # the package itself: its __init__ holds only the version and DarpError
        if target != layer and target not in ALLOWED[layer]:
            out.append(f"line {line}: {name} ({layer} may import {sorted(ALLOWED[layer])})")
    return out


def modules() -> list[Path]:
    return sorted(p for p in SRC.rglob("*.py") if p != SRC / "__init__.py")


def test_every_module_has_a_layer_and_every_layer_a_module() -> None:
    names = [module_name(p) for p in modules()]
    assert not [n for n in names if layer_of(n) is None], "modules in no layer of docs/architecture.md"
    assert {layer_of(n) for n in names} == set(ALLOWED), "layers of docs/architecture.md with no module"


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(SRC)))
def test_imports_follow_the_layer_table(path: Path) -> None:
    found = breaches(path, module_name(path))
    assert not found, f"{path.relative_to(SRC)}: " + "; ".join(found)


def test_the_table_is_read_from_the_doc() -> None:
    layers = [layer for layer, _ in ROWS]
    assert layers[0] == "__main__" and layers[-1] == "errors" and "formats.realsense" in layers
    assert ALLOWED["formats.realsense"] == {"geometry", "formats.text", "formats.io_input", "errors", "lazy"}
    assert "formats" not in ALLOWED["formats.realsense"] and "formats.realsense" in ALLOWED["formats"]
    assert "twin" not in ALLOWED["hardware"] and "hardware" not in ALLOWED["twin"]
    assert "acquisition" not in ALLOWED["twin"] | ALLOWED["hardware"] | ALLOWED["calibration"]


def test_the_checker_refuses_an_edge_the_doc_does_not_allow(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("from darp.formats.text import read_utf8_text\n\n\ndef f():\n"
                   "    from darp.processing.job import open_job\n    from darp import paper\n"
                   "    import darp.formats.survey\n")
    assert darp_imports(bad) == [(1, "darp.formats.text"), (5, "darp.processing.job"), (6, "darp.paper"),
                                 (7, "darp.formats.survey")]
    found = breaches(bad, "darp.reconstruction.bad")
    assert [b.split(" (")[0] for b in found] == ["line 5: darp.processing.job", "line 6: darp.paper"]
    assert [b.split(" (")[0] for b in breaches(bad, "darp.formats.realsense.bad")] == [
        "line 5: darp.processing.job", "line 6: darp.paper", "line 7: darp.formats.survey"]
    assert breaches(bad, "darp.cli.bad") == []


def test_the_doc_table_refuses_a_cycle() -> None:
    rows = [("a", {"b"}), ("b", {"a"})]
    with pytest.raises(AssertionError, match="not layers below it"):
        allowed_imports(rows)
    assert allowed_imports([("a", {"b"}), ("b", {"c"}), ("c", set())]) == {"a": {"b", "c"}, "b": {"c"}, "c": set()}


MAX_LINES = 500


def documented_long_modules(text: str) -> set[str]:
    """The modules docs/architecture.md's "Module size" section allows over MAX_LINES (each listed with a reason)."""
    section = text.split("\n## Module size", 1)[1].split("\n## ", 1)[0]
    return set(re.findall(r"^- `([a-z_/]+\.py)`: \S", section, flags=re.M))


def test_every_module_is_under_500_lines_unless_the_doc_says_why() -> None:
    allowed = documented_long_modules(DOC.read_text(encoding="utf-8"))
    sizes = {p.relative_to(SRC).as_posix(): len(p.read_text(encoding="utf-8").splitlines()) for p in modules()}
    long = {name for name, n in sizes.items() if n >= MAX_LINES}
    assert long <= allowed, f"modules of {MAX_LINES}+ lines not in docs/architecture.md: {sorted(long - allowed)}"
    assert allowed <= set(sizes), f"docs/architecture.md lists missing modules: {sorted(allowed - set(sizes))}"


def test_the_size_rule_is_read_from_the_doc() -> None:
    text = "intro\n## Module size\n\n- `a/b.py`: because\n- `c.py` no reason\n\n## Next\n- `d.py`: elsewhere\n"
    assert documented_long_modules(text) == {"a/b.py"}
