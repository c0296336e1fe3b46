"""A table of the QA report (a title, columns, rows and a note): the unit every section's
numbers are shown in, in HTML, markdown and the report's dict alike."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["Table"]


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[Any]]
    note: str = ""
