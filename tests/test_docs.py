"""The docs name what exists: every dotted ``pipeline.``/``mscal_core.``/``flows.`` name in
README.md and docs/*.md imports (a module, or an attribute of one; ``apply.executor.Plan`` is
read inside ``pipeline``), every source path they name is a file or folder of the repository,
and every relative link reaches its file and anchor."""

from __future__ import annotations

import importlib
import re
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: ``pipeline.apply.flight.apply_flight`` or ``apply.flight.apply_flight`` (inside ``pipeline``),
#: not ``tests/pipeline.x``, ``mscal.flows.x`` nor a file name (``run.json``, ``flows.md``).
SUBPACKAGES = ("storage", "ingest", "calibrate", "apply", "products", "run", "sim")
DOTTED = re.compile(r"(?<![\w./-])((?:pipeline|mscal_core|flows|%s)(?:\.[A-Za-z_]\w*)+)" % "|".join(SUBPACKAGES))
FILE_SUFFIX = re.compile(r"\.(json|zarr|py|md|yaml|html|csv|tif|tiff|npz|parquet|log|lock|png|jpg)$")
#: ``pipeline/apply/flight.py``, ``mscal_core/response/``, ``bench/bench_light.py``.
PATH = re.compile(r"(?<![\w./-])((?:pipeline|mscal_core|flows|bench|tests|catalogs)/[\w./-]*\w/?)")
LINK = re.compile(r"\]\(([^)\s]+)\)")
#: Placeholders in paths: ``catalogs/targets/NAME.yaml``.
PLACEHOLDER = re.compile(r"(^|/)[A-Z_]+(\.\w+)?(/|$)")
#: Linked before they exist: written on another branch, checked once they are here.
PENDING = {"docs/products.md"}


def _mentions(pattern: re.Pattern[str]) -> list[tuple[str, str]]:
    return sorted({(p.relative_to(ROOT).as_posix(), m) for p in DOCS
                   for m in pattern.findall(p.read_text(encoding="utf-8"))})


def _dotted() -> list[tuple[str, str]]:
    return [(doc, name if name.split(".")[0] not in SUBPACKAGES else f"pipeline.{name}")
            for doc, name in _mentions(DOTTED) if not FILE_SUFFIX.search(name)]


@cache
def resolves(name: str) -> bool:
    """True when ``name`` is an importable module or an attribute (at any depth) of one."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError as exc:
            if exc.name is not None and not ".".join(parts[:i]).startswith(exc.name):
                raise  # the module exists but imports something missing: a real error
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def anchors(path: Path) -> set[str]:
    """``<a id=...>`` anchors and GitHub's heading slugs of a markdown file."""
    text = path.read_text(encoding="utf-8")
    ids = set(re.findall(r'<a id="([^"]+)"></a>', text))
    for heading in re.findall(r"^#+ (.+)$", text, flags=re.M):
        ids.add(re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-"))
    return ids


def test_the_resolver_refuses_made_up_names() -> None:
    assert resolves("pipeline.apply.executor.process_frames")
    assert resolves("mscal_core.reflectance")
    assert not resolves("pipeline.apply.executor.process_frame")
    assert not resolves("mscal_core.no_such_module")
    assert not resolves("pipeline.apply.executor.FieldChain.no_such_field")


@pytest.mark.parametrize(("doc", "name"), _dotted())
def test_every_dotted_name_exists(doc: str, name: str) -> None:
    assert resolves(name.rstrip(".")), f"{doc} names {name}, which does not exist"


@pytest.mark.parametrize(("doc", "path"), [(d, p) for d, p in _mentions(PATH) if not PLACEHOLDER.search(p)])
def test_every_source_path_exists(doc: str, path: str) -> None:
    assert (ROOT / path).exists(), f"{doc} names {path}, which is not in the repository"


def test_every_relative_link_reaches_its_file_and_anchor() -> None:
    missing = []
    for doc in DOCS:
        for target in LINK.findall(doc.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target):
                continue  # https:, mailto:
            file, _, anchor = target.partition("#")
            dest = (doc.parent / file).resolve() if file else doc
            rel = dest.relative_to(ROOT).as_posix() if dest.is_relative_to(ROOT) else str(dest)
            if not dest.exists():
                if rel not in PENDING:
                    missing.append(f"{doc.name}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                missing.append(f"{doc.name}: {target} (no such anchor)")
    assert not missing, "\n".join(missing)
