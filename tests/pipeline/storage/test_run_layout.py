"""run.json's layout (:mod:`pipeline.storage.run_layout`): a source's keys nested under their
kind of input, and read back from that layout and from the flat one of earlier runs."""

from __future__ import annotations

from pipeline.storage.run_layout import CAPTURES, FACTORY, GROUPS, group_parts, run_value


def test_a_sources_keys_go_under_their_group_and_the_shared_ones_stay_at_the_top() -> None:
    parts = {"illumination": {"varies_in_time": False}, "skipped": [{"file": "a.txt", "reason": "not a capture"}],
             "reference": {"route": "dls"}, "panels": [], "light": {"warnings": []}, "snapshot": {"single_pass": True}}
    grouped = group_parts(parts)
    assert grouped == {"illumination": {"varies_in_time": False}, "snapshot": {"single_pass": True},
                       CAPTURES: {"skipped": [{"file": "a.txt", "reason": "not a capture"}], "panels": []},
                       FACTORY: {"reference": {"route": "dls"}, "light": {"warnings": []}}}
    assert group_parts({"illumination": {}}) == {"illumination": {}}  # no empty groups


def test_a_key_reads_the_same_from_the_nested_and_the_flat_layout() -> None:
    nested = group_parts({"reference": {"route": "panel"}, "skipped": [1], "coregistration": None})
    flat = {"reference": {"route": "panel"}, "skipped": [1], "coregistration": None}
    for run in (nested, flat):
        assert run_value(run, "reference") == {"route": "panel"} and run_value(run, "skipped") == [1]
        assert run_value(run, "coregistration", "absent") is None  # a key written as null stays null
        assert run_value(run, "thermal", []) == [] and run_value(run, "light") is None
    assert run_value({"frames_out": 3}, "frames_out") == 3  # the common keys are read at the top


def test_no_key_is_in_two_groups() -> None:
    keys = [k for ks in GROUPS.values() for k in ks]
    assert len(keys) == len(set(keys)) == 18 and not set(GROUPS) & set(keys)
