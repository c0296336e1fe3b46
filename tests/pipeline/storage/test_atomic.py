"""pipeline.storage.atomic: files and folders appear whole or not at all; temporaries carry
TMP_MARK and are removed on failure and on restart."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from pipeline.storage.atomic import (
    TMP_MARK,
    atomic_folder,
    atomic_path,
    install_folder,
    outputs_manifest,
    remove_temporaries,
    write_json_atomic,
    write_text_atomic,
)


def test_atomic_path_replaces_and_cleans(tmp_path) -> None:
    target = tmp_path / "sub" / "x.tif"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp.name.startswith(".x.") and not tmp.exists()
        assert TMP_MARK in tmp.name
        tmp.write_bytes(b"new")
        tmp.with_name(tmp.name + ".aux.xml").write_text("<PAMDataset/>")
    assert target.read_bytes() == b"new"
    assert sorted(os.listdir(target.parent)) == ["x.tif"]
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("boom")
    assert target.read_bytes() == b"new" and sorted(os.listdir(target.parent)) == ["x.tif"]


def test_atomic_path_without_parent_creation(tmp_path) -> None:
    target = tmp_path / "missing" / "c.0"
    with pytest.raises(FileNotFoundError):
        with atomic_path(target, make_parent=False) as tmp:
            tmp.write_bytes(b"x")
    assert not (tmp_path / "missing").exists()


def test_json_is_indented_sorted_and_without_newline(tmp_path) -> None:
    p = write_json_atomic(tmp_path / "run.json", {"b": 1, "a": [1, 2]})
    assert p.read_text() == '{\n  "a": [\n    1,\n    2\n  ],\n  "b": 1\n}'
    write_json_atomic(p, {"b": 1, "a": 2}, sort_keys=False)
    assert list(json.loads(p.read_text())) == ["b", "a"]
    write_text_atomic(p, "é")
    assert p.read_bytes() == "é".encode() and os.listdir(tmp_path) == ["run.json"]


def test_atomic_folder_replaces_the_old_folder(tmp_path) -> None:
    final = tmp_path / "s.zarr"
    final.mkdir()
    (final / "old").write_text("old")
    with atomic_folder(final) as tmp:
        assert TMP_MARK in tmp.name and not tmp.exists()
        tmp.mkdir()
        (tmp / "new").write_text("new")
    assert sorted(os.listdir(final)) == ["new"] and os.listdir(tmp_path) == ["s.zarr"]
    with pytest.raises(RuntimeError):
        with atomic_folder(final) as tmp:
            tmp.mkdir()
            raise RuntimeError("boom")
    assert sorted(os.listdir(final)) == ["new"] and os.listdir(tmp_path) == ["s.zarr"]
    other = tmp_path / "other"
    other.mkdir()
    install_folder(other, tmp_path / "fresh")
    assert sorted(os.listdir(tmp_path)) == ["fresh", "s.zarr"]


def test_remove_temporaries_removes_only_marked_names(tmp_path) -> None:
    (tmp_path / f".a.zarr{TMP_MARK}1234").mkdir()
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / f".x{TMP_MARK}5.tif").write_text("x")
    (tmp_path / "keep" / "y.tif").write_text("y")
    remove_temporaries(tmp_path)
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == ["keep", "keep/y.tif"]
    remove_temporaries(tmp_path / "absent")  # no folder: nothing to do


def test_install_folder_when_another_process_installs_the_same_name_at_once(tmp_path, monkeypatch) -> None:
    """Two runs filling one calibration cache: the other's folder appears between the check
    and the rename (os.replace then fails with ENOTEMPTY); it is moved aside and ours stays."""
    from pipeline.storage import atomic

    final, tmp = tmp_path / "stage.zarr", tmp_path / ".stage.zarr.tmp-mine"
    tmp.mkdir()
    (tmp / "zarr.json").write_text("mine")
    real_replace, raced = os.replace, []

    def replace(src, dst):
        if str(dst) == str(final) and not raced:
            raced.append(1)
            final.mkdir()
            (final / "zarr.json").write_text("theirs")
        return real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", replace)
    install_folder(tmp, final, durable=True)
    assert raced and (final / "zarr.json").read_text() == "mine" and not tmp.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["stage.zarr"]


def _manifest_by_pathlib(root: Path, names: list[str]) -> dict:
    """outputs_manifest as first written (Path.rglob, sorted Paths, Path.stat): run.json files
    written by it must still match (a mismatch redoes the flight)."""
    import hashlib

    lines, total = [], 0
    for name in sorted(set(names)):
        top = root / name.rstrip("/")
        paths = [top] if top.is_file() else sorted(p for p in top.rglob("*") if p.is_file()) if top.is_dir() else []
        if not top.exists():
            lines.append(f"{name.rstrip('/')}\tmissing")
        for p in paths:
            if TMP_MARK in p.name or p.name.endswith(".lock"):
                continue
            total += p.stat().st_size
            lines.append(f"{p.relative_to(root).as_posix()}\t{p.stat().st_size}")
    digest = hashlib.sha256("\n".join(lines).encode()).hexdigest()
    return {"files": sum(1 for ln in lines if not ln.endswith("\tmissing")), "bytes": total, "sha256": digest}


def test_outputs_manifest_is_the_pathlib_walk_it_replaced(tmp_path) -> None:
    """Same files, sizes, order and digest as the pathlib walk: names whose order differs as
    strings and as path components ("a/b" before "a.b/c" by components, after as strings),
    nested folders, temporaries and locks left out, a link to a file counted, a link to a
    folder not followed, a name that is missing."""
    out = tmp_path / "out"
    for rel, size in [("s.zarr/a/b", 3), ("s.zarr/a.b/c", 5), ("s.zarr/a-b", 7), ("s.zarr/a/z/y/x", 11),
                      ("s.zarr/c.0.0.0", 13), (f"s.zarr/a/tmp{TMP_MARK}x", 17), ("s.zarr/zarr.json.lock", 19),
                      ("tiffs/IMG_1_Red.tif", 23), ("run.json", 29)]:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(b"x" * size)
    os.symlink(out / "tiffs" / "IMG_1_Red.tif", out / "tiffs" / "link.tif")
    os.symlink(out / "s.zarr" / "a", out / "tiffs" / "folder_link")
    names = ["s.zarr", "tiffs/", "run.json", "absent.zarr"]
    got = outputs_manifest(out, names)
    assert got == _manifest_by_pathlib(out, names)
    assert got["files"] == 8 and got["bytes"] == 3 + 5 + 7 + 11 + 13 + 23 + 23 + 29
