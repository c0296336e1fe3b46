"""What every calibration stage shares: the :class:`StageReport` it returns (inputs with
content hashes, frames skipped and why, residuals, timings; the store's provenance) and the
files of its frames whose hashes are its inputs."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from pipeline.ingest.session import FrameRecord


@dataclass
class StageReport:
    """What a stage read and found: ``inputs`` (file -> content hash), ``skipped`` frames
    (file and reason), ``residuals`` (the fit's numbers) and its wall time in ``seconds``;
    :meth:`as_attrs` is its entry in the store's attributes. ``arrays``: per-band arrays the
    stage found besides its fits, for its part of the store (not attributes; e.g. the
    vignetting stage's ``coverage``)."""

    stage: str
    inputs: dict[str, str] = field(default_factory=dict)
    skipped: list[dict[str, str]] = field(default_factory=list)
    residuals: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    arrays: dict[str, Any] = field(default_factory=dict)

    def as_attrs(self) -> dict[str, Any]:
        return {
            "inputs": self.inputs,
            "skipped": self.skipped,
            "residuals": self.residuals,
            "seconds": round(self.seconds, 3),
        }


def record_files(records: Sequence[FrameRecord]) -> list[Path]:
    """Every file of the frames (a multi-lens capture has one per band)."""
    return [f for r in records for f in r.files]
