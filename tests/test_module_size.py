"""House rules that a reviewer would otherwise check by hand: no module of pipeline/, mscal_core/ or
flows/ over 800 lines, and no issue-tracker numbers in their code or in catalogs/."""

from __future__ import annotations

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "mscal_core", "flows")
MAX_LINES = 800
#: "issue 22", "Issue #7", "issue-31": a tracker reference, which belongs in git history.
ISSUE_REFERENCE = re.compile(r"\bissues?[ #-]*#?\d+", re.IGNORECASE)


def _sources(*roots: str, pattern: str = "*.py") -> list[pathlib.Path]:
    return sorted(p for r in roots for p in (ROOT / r).rglob(pattern))


def test_no_module_over_the_line_limit() -> None:
    sources = _sources(*PACKAGES)
    assert len(sources) > 100  # the walk found the packages
    long = {str(p.relative_to(ROOT)): n for p in sources
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}, f"split these along what their parts do (limit {MAX_LINES} lines): {long}"


def test_no_issue_numbers_in_code_or_catalogs() -> None:
    files = _sources(*PACKAGES) + _sources("catalogs", pattern="*.yaml")
    found = [f"{p.relative_to(ROOT)}:{i}" for p in files
             for i, line in enumerate(p.read_text().splitlines(), 1) if ISSUE_REFERENCE.search(line)]
    assert found == []


def test_issue_pattern_matches_what_it_should() -> None:
    assert ISSUE_REFERENCE.search("fixed in issue 22") and ISSUE_REFERENCE.search("see Issue #7")
    assert not ISSUE_REFERENCE.search("an issue with 3 bands") and not ISSUE_REFERENCE.search("tissue 4")
