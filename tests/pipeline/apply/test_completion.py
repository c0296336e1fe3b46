"""A flight's outputs count as up to date only through its completion marker:
``run.json``, written last after the outputs are flushed, notes every output file's name and
size. A half-written or damaged store, a missing TIFF or a missing marker is redone, never
trusted; the redone outputs equal an uninterrupted run's."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipeline.storage.atomic import outputs_manifest
from tests.pipeline.apply.test_apply import _apply, _assert_same_outputs, _outputs


def _largest_chunk(store: Path) -> Path:
    return max((p for p in (store / "reflectance").rglob("*") if p.is_file() and p.name != "zarr.json"),
               key=lambda p: p.stat().st_size)


def _truncate_chunk(out: Path) -> None:
    chunk = _largest_chunk(out / "reflectance.zarr")
    with chunk.open("r+b") as f:
        f.truncate(chunk.stat().st_size // 2)


def _empty_store(out: Path) -> None:  # what two unlocked runs left behind (a store with no arrays)
    shutil.rmtree(out / "reflectance.zarr")
    (out / "reflectance.zarr").mkdir()


def _remove_chunk(out: Path) -> None:
    _largest_chunk(out / "reflectance.zarr").unlink()


def _remove_tiff(out: Path) -> None:
    next((out / "photogrammetry").glob("*.tif")).unlink()


def _remove_marker(out: Path) -> None:
    (out / "run.json").unlink()


def _marker_of_before(out: Path) -> None:  # a run.json written before completion markers had a manifest
    run = json.loads((out / "run.json").read_text())
    del run["outputs_manifest"]
    (out / "run.json").write_text(json.dumps(run))


DAMAGE = {"nothing": None, "chunk_truncated": _truncate_chunk, "chunk_removed": _remove_chunk,
          "store_emptied": _empty_store, "tiff_removed": _remove_tiff, "marker_removed": _remove_marker,
          "marker_without_manifest": _marker_of_before}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_or_unmarked_output_is_redone(applied, tmp_path: Path, damage: str, capsys) -> None:
    session, calib, clean = applied
    reference = _outputs(clean)
    out = tmp_path / "out"
    shutil.copytree(clean, out)
    if DAMAGE[damage] is not None:
        DAMAGE[damage](out)
    capsys.readouterr()
    assert _apply(session / "flights" / "field", calib, out) == 0
    said = capsys.readouterr().out
    assert ("up to date" in said) == (damage == "nothing"), said
    _assert_same_outputs(reference, _outputs(out))
    run = json.loads((out / "run.json").read_text())
    assert run["outputs_manifest"] == outputs_manifest(out, run["outputs"].values())
    assert run["outputs_manifest"]["files"] > 3 and run["outputs_manifest"]["bytes"] > 0


def test_the_manifest_sees_a_changed_size_and_a_missing_output(tmp_path: Path) -> None:
    (tmp_path / "a.zarr" / "c").mkdir(parents=True)
    (tmp_path / "a.zarr" / "c" / "0").write_bytes(b"x" * 10)
    (tmp_path / "a.zarr" / ".c.tmp-1234").write_bytes(b"left by a killed run")
    m = outputs_manifest(tmp_path, ["a.zarr", "t/"])
    assert m["files"] == 1 and m["bytes"] == 10
    (tmp_path / "a.zarr" / "c" / "0").write_bytes(b"x" * 9)
    assert outputs_manifest(tmp_path, ["a.zarr", "t/"])["sha256"] != m["sha256"]
    (tmp_path / "a.zarr" / "c" / "0").write_bytes(b"y" * 10)  # same size: a name and size note, not a hash
    assert outputs_manifest(tmp_path, ["a.zarr", "t/"]) == m
    (tmp_path / "t").mkdir()
    assert outputs_manifest(tmp_path, ["a.zarr", "t/"])["sha256"] != m["sha256"]  # an empty folder is not a missing one


def test_run_json_is_written_only_after_the_outputs_are_flushed(tmp_path: Path, monkeypatch) -> None:
    """The manifest is taken while ``syncfs`` runs, but run.json waits for both: a flush that
    fails leaves no completion marker, and one that succeeds writes the manifest of the files."""
    from pipeline.apply import record as record_mod

    (tmp_path / "a.zarr").mkdir()
    (tmp_path / "a.zarr" / "c.0").write_bytes(b"x" * 10)
    record = {"outputs": {"reflectance": "a.zarr"}}

    def failing(path: Path) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(record_mod, "sync_file_system", failing)
    with pytest.raises(OSError, match="Input/output"):
        record_mod.write_run_record(tmp_path, dict(record))
    assert not (tmp_path / "run.json").exists()
    order = []
    monkeypatch.setattr(record_mod, "sync_file_system", lambda path: order.append(("sync", path)))
    record_mod.write_run_record(tmp_path, dict(record))
    assert order == [("sync", tmp_path)]
    written = json.loads((tmp_path / "run.json").read_text())
    assert written["outputs_manifest"] == outputs_manifest(tmp_path, ["a.zarr"]) and written["outputs_manifest"]["files"] == 1
