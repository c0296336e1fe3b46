"""Every public function of mscal_core has a numpydoc docstring a newcomer can use: a
Parameters section naming each parameter (when it takes any) and a Returns section (when it
returns something other than None).

Public: the names of a module's ``__all__`` (every name without a leading underscore when it
has none) and the names that ``pipeline/`` imports from it; for a package (``response``) the
functions its ``__all__`` re-exports from its private modules. Parsed with numpydoc's parser
(``numpydoc.docscrape``) where it is installed, else by the section headers.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
from pathlib import Path
from typing import Callable

import pytest

import mscal_core

ROOT = Path(__file__).resolve().parents[2]
#: Modules left out, each with the reason.
EXCLUDED = {
}


def _excluded(name: str) -> bool:
    return any(name == e or name.startswith(e + ".") for e in EXCLUDED)


def _pipeline_imports() -> dict[str, set[str]]:
    """Names that pipeline/ imports from each mscal_core module (``from mscal_core.X import a``)."""
    out: dict[str, set[str]] = {}
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("mscal_core."):
                out.setdefault(node.module, set()).update(a.name for a in node.names)
    return out


def public_functions() -> list[tuple[str, Callable]]:
    """``(qualified name, function)`` of every public function of mscal_core's modules."""
    imported = _pipeline_imports()
    found: dict[str, Callable] = {}
    for info in pkgutil.walk_packages(mscal_core.__path__, "mscal_core."):
        name = info.name
        if _excluded(name) or name.rsplit(".", 1)[1].startswith("_"):
            continue
        module = importlib.import_module(name)
        names = set(getattr(module, "__all__", None) or (n for n in vars(module) if not n.startswith("_")))
        names |= imported.get(name, set())
        for attr in sorted(names):
            obj = getattr(module, attr, None)
            if not inspect.isfunction(obj):
                continue
            home = obj.__module__
            if home != name and not (info.ispkg and home.startswith(name + ".")):
                continue  # imported from elsewhere: checked in its own module
            found[f"{home}.{obj.__name__}"] = obj
    return sorted(found.items())


SECTION = re.compile(r"^(\w[\w ]*)\n-{3,}$", re.M)


def _sections_by_headers(doc: str) -> dict[str, list[str]]:
    """Section name -> parameter-like entry names (``name : type`` lines), without numpydoc."""
    out: dict[str, list[str]] = {}
    heads = list(SECTION.finditer(doc))
    for i, m in enumerate(heads):
        body = doc[m.end():heads[i + 1].start() if i + 1 < len(heads) else len(doc)]
        entries = [line.split(" : ")[0].strip() for line in body.splitlines() if line and not line[0].isspace()]
        out[m.group(1)] = entries
    return out


def sections(func: Callable) -> dict[str, list[str]]:
    """Section name -> entry names of a function's docstring (numpydoc's parser where installed)."""
    doc = inspect.getdoc(func) or ""
    try:
        from numpydoc.docscrape import FunctionDoc
    except ImportError:
        return _sections_by_headers(doc)
    parsed = FunctionDoc(func, doc=doc, config={})
    out = {}
    for key in ("Parameters", "Other Parameters", "Returns", "Yields", "Raises"):
        if parsed[key]:
            out[key] = [p.name if key != "Returns" else (p.name or p.type) for p in parsed[key]]
    return out


def documented_parameters(entries: list[str]) -> set[str]:
    """``a, b`` documents both; ``*args`` documents ``args``."""
    return {n.strip().lstrip("*") for entry in entries for n in entry.split(",") if n.strip()}


FUNCTIONS = public_functions()


def test_the_walk_finds_the_public_functions() -> None:
    names = {n for n, _ in FUNCTIONS}
    assert {"mscal_core.reflectance.eq15", "mscal_core.registration.register_stack",
            "mscal_core.response._fit.fit_response"} <= names
    assert not any(_excluded(n.rsplit(".", 1)[0]) for n in names)


@pytest.mark.parametrize(("name", "func"), FUNCTIONS, ids=[n for n, _ in FUNCTIONS])
def test_public_function_has_parameters_and_returns(name: str, func: Callable) -> None:
    found = sections(func)
    params = [p for p in inspect.signature(func).parameters.values()]
    if params:
        assert "Parameters" in found, f"{name}: no Parameters section"
        documented = documented_parameters(found["Parameters"] + found.get("Other Parameters", []))
        missing = [p.name for p in params if p.name not in documented]
        assert not missing, f"{name}: parameters not documented: {missing}"
        unknown = sorted(documented - {p.name for p in params})
        assert not unknown, f"{name}: documents parameters it does not take: {unknown}"
    returns = inspect.signature(func).return_annotation
    if returns not in (None, "None", inspect.Signature.empty):
        assert "Returns" in found or "Yields" in found, f"{name}: no Returns section"
