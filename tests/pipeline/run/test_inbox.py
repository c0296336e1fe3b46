"""serve's inbox: which waiting folders its summary names."""

from __future__ import annotations

from pipeline.run.inbox import newly_waiting, reason_kind

COPYING_40 = "still being copied: a file was modified 40 s ago and there is no READY file"
COPYING_95 = "still being copied: a file was modified 95 s ago and there is no READY file"
EMPTY = "empty folder: nothing to process"


def test_reason_kind_drops_the_figures() -> None:
    assert reason_kind(COPYING_40) == reason_kind(COPYING_95) == "still being copied"
    assert reason_kind(EMPTY) == "empty folder"
    assert reason_kind("") == ""


def test_a_folder_is_named_when_it_starts_waiting_or_its_reason_changes_kind() -> None:
    before = {"tuesday": {"reason": COPYING_40, "utc": "2026-12-06T00:00:00+00:00"},
              "empty": {"reason": EMPTY, "utc": "2026-12-06T00:00:00+00:00"}}
    now = {"tuesday": COPYING_95, "empty": COPYING_40, "wednesday": EMPTY}
    assert newly_waiting(before, now) == {"empty": COPYING_40, "wednesday": EMPTY}
    assert newly_waiting({}, now) == now
    assert newly_waiting(before, {}) == {}
