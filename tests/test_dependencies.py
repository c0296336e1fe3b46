"""Every third-party package that pipeline/, mscal_core/ and flows/ import (at the top of a
module or inside a function) is declared in pyproject.toml's dependencies: an install from the
declared list alone imports every module."""

from __future__ import annotations

import ast
import importlib.metadata
import pathlib
import re
import sys
import tomllib

ROOT = pathlib.Path(__file__).resolve().parents[1]
FIRST_PARTY = {"pipeline", "mscal_core", "flows", "catalogs"}
#: Import names whose distribution is named otherwise (the rest: the same name).
DISTRIBUTION = {"cv2": "opencv-python-headless", "yaml": "pyyaml"}


def _normal(name: str) -> str:
    """A distribution name as PEP 503 compares it."""
    return re.sub(r"[-_.]+", "-", name).lower()


def imported_modules() -> dict[str, set[str]]:
    """Top-level third-party modules imported by the three packages, with the files importing each."""
    out: dict[str, set[str]] = {}
    for package in ("pipeline", "mscal_core", "flows"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.split(".")[0]
                    if top not in FIRST_PARTY and top not in sys.stdlib_module_names:
                        out.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return out


def declared() -> set[str]:
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    return {_normal(re.match(r"[A-Za-z0-9._-]+", d).group(0)) for d in deps}


def test_every_imported_package_is_declared() -> None:
    modules = imported_modules()
    assert {"numpy", "cv2", "yaml", "numcodecs", "xarray"} <= set(modules)  # the walk found them
    wanted = {m: _normal(DISTRIBUTION.get(m, m)) for m in modules}
    missing = {m: sorted(modules[m]) for m, dist in wanted.items() if dist not in declared()}
    assert missing == {}, f"imported but not in pyproject.toml's dependencies: {missing}"


def test_the_import_names_map_to_the_installed_distributions() -> None:
    """The distribution each import name is checked under is the one that provides it here."""
    provides = importlib.metadata.packages_distributions()
    wrong = {m: provides.get(m) for m in imported_modules()
             if _normal(DISTRIBUTION.get(m, m)) not in {_normal(d) for d in provides.get(m, [])}}
    assert wrong == {}
