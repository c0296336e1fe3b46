"""mscal_core is pure maths: importing it (all of it) loads no I/O or orchestration stack."""

import pathlib
import subprocess
import sys

FORBIDDEN = ["dask", "xarray", "zarr", "rasterio", "prefect", "tifffile", "pandas", "yaml", "exifread", "click"]


def test_core_imports_no_io_or_orchestration_packages() -> None:
    code = (
        "import importlib, pkgutil, sys, json\n"
        "import mscal_core\n"
        "for m in pkgutil.walk_packages(mscal_core.__path__, 'mscal_core.'):\n"
        "    importlib.import_module(m.name)\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    import json

    loaded = set(json.loads(out.stdout.strip().splitlines()[-1]))
    assert "mscal_core.mosaic" in loaded  # the walk really imported the modules
    bad = sorted(m for m in loaded if m.split(".")[0] in FORBIDDEN)
    assert bad == [], f"mscal_core pulled in {bad}"


def test_core_does_no_file_io() -> None:
    """No open()/Path reads or writes and no image decoding in mscal_core's source."""
    import pathlib

    import mscal_core

    root = pathlib.Path(mscal_core.__file__).parent
    offenders = []
    for p in root.rglob("*.py"):
        text = p.read_text()
        for token in ("open(", "imread", "imwrite", "read_text", "write_text", "np.save", "np.load"):
            if token in text:
                offenders.append(f"{p.name}: {token}")
    assert offenders == []


def _imports(path) -> set[str]:
    """Top-level names of the modules a source file imports (absolute imports only)."""
    import ast

    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_flows_import_prefect_and_pipeline_only() -> None:
    """flows/ is wiring: Prefect, the pipeline, the standard library; nothing else."""
    import pathlib

    import flows

    allowed = {"prefect", "pipeline"} | set(sys.stdlib_module_names)
    files = sorted(pathlib.Path(flows.__file__).parent.glob("*.py"))
    assert any(p.name == "post_flight.py" for p in files)
    bad = {p.name: sorted(_imports(p) - allowed) for p in files if _imports(p) - allowed}
    assert bad == {}


def test_pipeline_does_not_import_prefect_or_flows() -> None:
    """pipeline never imports Prefect or flows: the command line finds the flows through the
    ``mscal.flows`` entry-point group."""
    import pathlib

    import pipeline

    files = sorted(pathlib.Path(pipeline.__file__).parent.rglob("*.py"))
    assert len(files) > 25  # the walk really reached the subpackages
    bad = sorted(str(p) for p in files if _imports(p) & {"prefect", "flows"})
    assert bad == []


# --------------------------------------------------------------------------- pipeline layers

# The order of pipeline/__init__.py's docstring: a subpackage may import itself and those listed
# for it. ``apply`` may also import ``products.writers`` (it writes the per-frame TIFFs while
# it applies), ``sim`` may import storage, ingest and calibrate.
LAYERS = ("storage", "ingest", "calibrate", "apply", "products", "run")
ALLOWED = {pkg: set(LAYERS[:i + 1]) for i, pkg in enumerate(LAYERS)}
ALLOWED["run"] |= {"sim"}
ALLOWED["sim"] = {"sim", "storage", "ingest", "calibrate"}
ALLOWED_MODULES = {"apply": {"pipeline.products.writers"}}


def _sources() -> dict[str, "pathlib.Path"]:
    """``{dotted module name: file}`` of every module in pipeline/ and flows/."""
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1]
    out = {}
    for top in ("pipeline", "flows"):
        for p in sorted((root / top).rglob("*.py")):
            parts = list(p.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


def _type_checking_nodes(tree) -> set[int]:
    """ids of the nodes inside ``if TYPE_CHECKING:`` blocks (imports for annotations only)."""
    import ast

    inside: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING"):
            for child in node.body:
                inside.update(id(n) for n in ast.walk(child))
    return inside


def _module_imports(name: str, path) -> list[tuple[str, list[str], int, bool]]:
    """``(module, imported names, line, for annotations only)`` of every absolute import of
    ``name`` (relative imports resolved against it)."""
    import ast

    tree = ast.parse(path.read_text())
    typing_only = _type_checking_nodes(tree)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([module] if module else []))
            out.append((module, [a.name for a in node.names], node.lineno, id(node) in typing_only))
        elif isinstance(node, ast.Import):
            for a in node.names:
                out.append((a.name, [], node.lineno, id(node) in typing_only))
    return out


def _private_uses(name: str, path, modules: set[str]) -> list[str]:
    """``module._x`` and ``from module import _x`` of another project module's private names."""
    import ast

    tree = ast.parse(path.read_text())
    bad = []
    aliases: dict[str, str] = {}  # local name -> project module it is bound to
    for module, names, line, _ in _module_imports(name, path):
        if module.split(".")[0] not in ("pipeline", "flows", "mscal_core") or module == name:
            continue
        for n in names:
            if n.startswith("_") and not n.startswith("__"):
                bad.append(f"{name}:{line} from {module} import {n}")
            elif f"{module}.{n}" in modules:
                aliases[n] = f"{module}.{n}"
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                aliases[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                and isinstance(node.value, (ast.Name, ast.Attribute))):
            target = ast.unparse(node.value)
            head = target.split(".")[0]
            if head in aliases and aliases[head].split(".")[0] in ("pipeline", "flows", "mscal_core"):
                dotted = aliases[head] + target[len(head):]
                if dotted != name:
                    bad.append(f"{name}:{node.lineno} {target}.{node.attr}")
    return bad


def test_no_module_imports_another_modules_private_names() -> None:
    sources = _sources()
    assert {"pipeline.apply.flight", "pipeline.storage.atomic", "flows.post_flight"} <= set(sources)
    bad = [b for name, path in sources.items() for b in _private_uses(name, path, set(sources))]
    assert bad == []


def test_private_name_check_catches_both_forms(tmp_path) -> None:
    p = tmp_path / "m.py"
    p.write_text("from pipeline.apply.flight import _x, ok\nimport pipeline.ingest.raw as raw\nraw._y\nself._z\n")
    bad = _private_uses("pipeline.run.m", p, {"pipeline.ingest.raw"})
    assert bad == ["pipeline.run.m:1 from pipeline.apply.flight import _x", "pipeline.run.m:3 raw._y"]


def _upward_imports(name: str, path) -> list[str]:
    pkg = name.split(".")[1] if name.count(".") >= 1 else None
    if pkg is None or pkg not in ALLOWED:
        return []
    bad = []
    for module, _, line, typing_only in _module_imports(name, path):
        parts = module.split(".")
        if parts[0] != "pipeline" or len(parts) < 2 or typing_only:
            continue
        if parts[1] not in ALLOWED[pkg] and not any(module == m or module.startswith(m + ".")
                                                    for m in ALLOWED_MODULES.get(pkg, ())):
            bad.append(f"{name}:{line} imports {module}")
    return bad


def test_pipeline_subpackages_import_only_earlier_ones() -> None:
    sources = _sources()
    pkgs = {n.split(".")[1] for n in sources if n.startswith("pipeline.") and n.count(".") >= 1}
    assert pkgs == set(ALLOWED), "a new subpackage needs its place in pipeline/__init__.py and ALLOWED"
    bad = [b for name, path in sources.items() if name.startswith("pipeline.") for b in _upward_imports(name, path)]
    assert bad == []


def test_upward_import_check_catches_one(tmp_path) -> None:
    p = tmp_path / "m.py"
    p.write_text("from typing import TYPE_CHECKING\nfrom pipeline.products.report import x\n"
                 "from pipeline.apply.flight import y\nif TYPE_CHECKING:\n    from pipeline.run.cli import z\n")
    assert _upward_imports("pipeline.calibrate.m", p) == ["pipeline.calibrate.m:2 imports pipeline.products.report",
                                                          "pipeline.calibrate.m:3 imports pipeline.apply.flight"]
    assert _upward_imports("pipeline.apply.m", p) == ["pipeline.apply.m:2 imports pipeline.products.report"]


def test_layer_order_is_the_documented_one() -> None:
    import pipeline

    doc = pipeline.__doc__ or ""
    positions = [doc.index(f"``{pkg}``") for pkg in LAYERS]
    assert positions == sorted(positions)
