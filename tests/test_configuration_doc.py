"""docs/configuration.md lists every environment variable the code of pipeline/, mscal_core/ and
flows/ reads or sets: found in the source (ast), not in a list kept by hand."""

from __future__ import annotations

import ast
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "mscal_core", "flows")
#: Functions of pipeline.storage.process that set variables for a block (their dict's keys).
SETTERS = {"environment"}


def _constants(tree: ast.Module) -> dict[str, object]:
    """Module-level ``NAME = "text"`` and ``NAME = {"KEY": ...}`` of one file."""
    out: dict[str, object] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            value = node.value
            if isinstance(value, ast.Constant) and isinstance(value.value, str):
                out[node.targets[0].id] = value.value
            elif isinstance(value, ast.Dict):
                out[node.targets[0].id] = [k.value for k in value.keys
                                           if isinstance(k, ast.Constant) and isinstance(k.value, str)]
    return out


def _is_environ(node: ast.AST) -> bool:
    return isinstance(node, ast.Attribute) and node.attr == "environ" and isinstance(node.value, ast.Name) \
        and node.value.id == "os"


def _names(node: ast.AST | None, consts: dict[str, object]) -> list[str]:
    """The variable names an expression stands for (a text, a module constant, a dict's keys)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, ast.Name) and node.id in consts:
        value = consts[node.id]
        return [value] if isinstance(value, str) else list(value)  # type: ignore[arg-type]
    if isinstance(node, ast.Dict):
        return [n for k in node.keys for n in _names(k, consts)]
    if isinstance(node, ast.DictComp) and isinstance(node.generators[0].iter, ast.Call):
        call = node.generators[0].iter  # {k: v for k, v in CONST.items() if ...}
        return _names(call.func.value, consts) if isinstance(call.func, ast.Attribute) else []
    return []


def variables_in(path: pathlib.Path) -> set[str]:
    """Environment variables one source file reads or sets: ``os.environ.get/setdefault/pop(X)``,
    ``os.environ[X]``, ``X in os.environ``, ``os.getenv(X)``, click's ``envvar=X`` and the keys
    given to :func:`pipeline.storage.process.environment`."""
    tree = ast.parse(path.read_text())
    consts = _constants(tree)
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            if isinstance(func, ast.Attribute) and _is_environ(func.value) and func.attr in ("get", "setdefault", "pop"):
                found.update(_names(node.args[0], consts))
            elif isinstance(func, ast.Attribute) and func.attr == "getenv":
                found.update(_names(node.args[0], consts))
            elif isinstance(func, ast.Name) and func.id in SETTERS and node.args:
                found.update(_names(node.args[0], consts))
            for kw in node.keywords:
                if kw.arg == "envvar":
                    found.update(_names(kw.value, consts))
        elif isinstance(node, ast.Subscript) and _is_environ(node.value):
            found.update(_names(node.slice, consts))
        elif isinstance(node, ast.Compare) and any(_is_environ(c) for c in node.comparators):
            found.update(_names(node.left, consts))
    return {n for n in found if re.fullmatch(r"[A-Z][A-Z0-9_]+", n)}


def code_variables() -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for name in variables_in(path):
                out.setdefault(name, set()).add(str(path.relative_to(ROOT)))
    return out


def test_every_variable_the_code_reads_is_documented() -> None:
    found = code_variables()
    # the walk really reaches the variables (a read, a click default, a block's setting)
    assert {"MSCAL_CALIBRATE_WORKERS", "MSCAL_CATALOG_PATH", "MSCAL_CACHE_DIR", "MSCAL_APPLY_WORKERS",
            "OPENBLAS_NUM_THREADS", "PREFECT_HOME"} <= set(found)
    doc = (ROOT / "docs" / "configuration.md").read_text()
    listed = set(re.findall(r"^\| `([A-Z][A-Z0-9_]+)`", doc, flags=re.M))
    missing = {name: sorted(where) for name, where in found.items() if name not in listed}
    assert missing == {}, f"not in docs/configuration.md: {missing}"
    stale = sorted(listed - set(found))
    assert stale == [], f"docs/configuration.md lists variables the code no longer uses: {stale}"
