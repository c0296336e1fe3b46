"""mscal_core is pure maths: importing it (all of it) loads no I/O or orchestration stack."""

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


def _imports(path) -> set[str]:  # noqa: ANN001
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
