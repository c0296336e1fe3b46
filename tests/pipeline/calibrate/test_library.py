"""The calibration library (pipeline.calibrate.library): calibrations recorded by camera and
serial number (read from the band files of synthetic RedEdge-style sessions), found again for
a later flight of the same camera body only, the newest fitted before the flight."""

from __future__ import annotations

import json
import shutil
import threading
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
import yaml

from mscal_core.errors import CalibrationStoreError, InputError, SessionError
from pipeline.calibrate import library
from pipeline.ingest.catalog import load_camera
from pipeline.sim.multilens import write_multilens_session
from pipeline.storage.store import new_dataset, open_calibration, write_store

CAMERA = "micasense-rededge"
SERIAL_A, SERIAL_B = "RE-A0001", "RE-B0002"
#: The synthetic session's newest response/vignetting/reflector capture: the reflector's last
#: (pipeline.sim.multilens: SESSION_START 09:30:00 UTC, reflector captures from +900 s).
T0 = datetime(2017, 6, 14, 9, 45, 6, tzinfo=timezone.utc)


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> dict[str, Path]:
    """Two small multi-lens sessions (no fit), of two camera bodies: serials A and B."""
    root = tmp_path_factory.mktemp("library-sessions")
    return {s: write_multilens_session(root / s, seed=0, size="small", shape=(120, 160), serial=s)
            for s in (SERIAL_A, SERIAL_B)}


def _store(path: Path, level: float, camera: str = CAMERA, created: str = "2017-06-15T08:00:00+00:00") -> Path:
    """A tiny calibration store of ``camera`` (S = ``level`` in every band): enough to record."""
    cam = load_camera(camera)
    ds = new_dataset(cam)
    ds["spectral_factor"] = (("band",), np.full(cam.n_bands, level))
    ds.attrs.update({"created_utc": created, "session": "elsewhere"})
    return write_store(ds, path)


def _index(root: Path) -> dict:
    return json.loads((root / "index.json").read_text())


def test_serial_and_session_time_come_from_the_band_files(sessions, tmp_path) -> None:
    a, b = sessions[SERIAL_A], sessions[SERIAL_B]
    assert library.camera_serial(a, CAMERA) == SERIAL_A
    assert library.camera_serial(b / "check", load_camera(CAMERA)) == SERIAL_B  # a flight-like folder
    assert library.camera_serial(sorted((b / "response").glob("*.tif"))[:5], CAMERA) == SERIAL_B
    assert library.file_serial(a / "response" / "IMG_0000_1.tif") == SERIAL_A
    card = tmp_path / "card"  # session.yaml beside the frames of a flight, no field data
    shutil.copytree(b / "check", card)
    (card / "session.yaml").write_text(f"camera: {CAMERA}\n")
    assert library.camera_serial(card, CAMERA) == SERIAL_B
    assert library.session_time(a) == T0
    assert max(library.frame_times(a / "response", CAMERA)) == datetime(2017, 6, 14, 9, 30, 14, tzinfo=timezone.utc)
    assert min(library.frame_times(a / "check", CAMERA)) == datetime(2017, 6, 14, 9, 50, 0, tzinfo=timezone.utc)
    # a band file of the other body among the frames: two cameras, named
    mixed = tmp_path / "mixed"
    shutil.copytree(a / "response", mixed)
    for f in (b / "vignetting").glob("IMG_1000_*.tif"):
        shutil.copy(f, mixed / f.name)
    with pytest.raises(InputError, match=f"two cameras.*serial number.*({SERIAL_A}|{SERIAL_B})") as info:
        library.camera_serial(mixed, CAMERA)
    assert str(mixed) in str(info.value)


def test_session_yaml_serial_for_frames_without_one(sessions, tmp_path) -> None:
    """A snapshot session's frames (PNG + frames.csv) carry no serial: session.yaml's
    ``serial`` is used; where the frames carry one, a different session.yaml serial is an error."""
    snap = tmp_path / "snap"
    (snap / "response").mkdir(parents=True)
    (snap / "response" / "f00.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    (snap / "session.yaml").write_text("camera: ximea-mq022hg-sm5x5-nir\nserial: \"XI-0042\"\n")
    assert library.camera_serial(snap, "ximea-mq022hg-sm5x5-nir") == "XI-0042"
    (snap / "session.yaml").write_text("camera: ximea-mq022hg-sm5x5-nir\n")
    assert library.camera_serial(snap, "ximea-mq022hg-sm5x5-nir") is None
    (snap / "session.yaml").write_text("camera: ximea-mq022hg-sm5x5-nir\nserial: [1, 2]\n")
    with pytest.raises(SessionError, match="serial must be"):
        library.camera_serial(snap, "ximea-mq022hg-sm5x5-nir")
    other = tmp_path / "other"
    shutil.copytree(sessions[SERIAL_A], other, ignore=shutil.ignore_patterns("vignetting", "check", "truth.npz"))
    data = yaml.safe_load((other / "session.yaml").read_text())
    (other / "session.yaml").write_text(yaml.safe_dump({**data, "serial": SERIAL_B}))
    with pytest.raises(SessionError, match=f"serial is {SERIAL_B} but the frames say {SERIAL_A}") as info:
        library.camera_serial(other, CAMERA)
    assert str(other / "session.yaml") in str(info.value)


def test_newest_calibration_of_the_same_serial_fitted_before_the_flight(sessions, tmp_path) -> None:
    root = tmp_path / "library"
    serial = library.camera_serial(sessions[SERIAL_A], CAMERA)
    t0 = library.session_time(sessions[SERIAL_A])
    t2 = t0 + timedelta(days=30)
    first = library.record(_store(tmp_path / "s1.zarr", 1.25), camera=CAMERA, serial=serial, session_time=t0,
                           library_root=root)
    second = library.record(_store(tmp_path / "s2.zarr", 2.5), camera=CAMERA, serial=serial, session_time=t2,
                            library_root=root)
    assert first.parent == root / CAMERA / SERIAL_A and first.name.startswith("20170614T094506Z-")
    assert second.name.startswith("20170714T094506Z-") and first != second
    assert open_calibration(first)["spectral_factor"].values.tolist() == [1.25] * 5  # a whole copy

    found = library.lookup(CAMERA, SERIAL_A, t0 + timedelta(days=10), root)  # between the two
    assert found is not None and found.store == first and found.session_time == t0
    assert found.fitted_utc == datetime(2017, 6, 15, 8, 0, tzinfo=timezone.utc) and found.serial == SERIAL_A
    assert library.lookup(CAMERA, SERIAL_A, t2 + timedelta(days=10), root).store == second
    assert library.lookup(CAMERA, SERIAL_A, t2, root).store == second  # at the session's time: fitted before
    assert library.lookup(CAMERA, SERIAL_A, None, root).store == second  # no flight time: the newest
    assert library.lookup(CAMERA, "re-a0001", t2 + timedelta(days=10), root).store == second  # any case
    assert library.lookup(CAMERA, SERIAL_A, t0 - timedelta(seconds=1), root) is None  # none yet then
    assert library.lookup(CAMERA, SERIAL_B, t2 + timedelta(days=10), root) is None  # another body
    assert library.lookup(CAMERA, None, t2 + timedelta(days=10), root) is None  # unknown serial
    assert library.lookup("micasense-rededge-mx", SERIAL_A, t2 + timedelta(days=10), root) is None
    naive = (t0 + timedelta(days=10)).replace(tzinfo=None)  # a time without a zone is UTC
    assert library.lookup(CAMERA, SERIAL_A, naive, root).store == first
    # flights: the serial and the first capture time from their band files
    assert library.find_for_flight(sessions[SERIAL_A] / "check", CAMERA, root).store == first
    assert library.find_for_flight(sessions[SERIAL_B] / "check", CAMERA, root) is None

    # the same calibration again: no second entry, the same copy
    again = library.record(tmp_path / "s1.zarr", camera=CAMERA, serial=SERIAL_A, session_time=t0, library_root=root)
    assert again == first and len(_index(root)["entries"]) == 2
    entry = _index(root)["entries"][0]
    assert entry == {"camera": CAMERA, "serial": SERIAL_A, "session_time": "2017-06-14T09:45:06Z",
                     "fitted_utc": "2017-06-15T08:00:00Z", "store": first.relative_to(root).as_posix(),
                     "sha256": library.store_digest(tmp_path / "s1.zarr"), "session": "elsewhere"}
    # a copy that is gone is passed over
    shutil.rmtree(second)
    assert library.lookup(CAMERA, SERIAL_A, None, root).store == first


def test_record_fitted_reads_camera_serial_and_time(sessions, tmp_path) -> None:
    root = tmp_path / "library"
    path = library.record_fitted(_store(tmp_path / "c.zarr", 3.0), sessions[SERIAL_B], library_root=root)
    (entry,) = library.entries(root)
    assert path == entry.store and path.parent == root / CAMERA / SERIAL_B
    assert (entry.serial, entry.session_time, entry.session) == (SERIAL_B, T0, str(sessions[SERIAL_B].resolve()))
    # a store of another camera is not recorded under this one
    other = _store(tmp_path / "mx.zarr", 1.0, camera="micasense-rededge-mx")
    with pytest.raises(CalibrationStoreError, match="micasense-rededge-mx"):
        library.record(other, camera=CAMERA, serial=SERIAL_B, session_time=T0, library_root=root)
    assert len(library.entries(root)) == 1


def test_unknown_serial_and_time(tmp_path) -> None:
    """Without serial or session time: filed under unknown at the fit's time, never found."""
    root = tmp_path / "library"
    path = library.record(_store(tmp_path / "u.zarr", 1.0), camera=CAMERA, serial=None, session_time=None,
                          library_root=root)
    assert path.parent == root / CAMERA / "unknown" and path.name.startswith("20170615T080000Z-")
    assert library.entries(root)[0].time == datetime(2017, 6, 15, 8, tzinfo=timezone.utc)
    assert library.lookup(CAMERA, None, None, root) is None and library.lookup(CAMERA, "unknown", None, root) is None


def test_concurrent_records_all_end_up_in_the_index(tmp_path) -> None:
    root = tmp_path / "library"
    stores = [_store(tmp_path / f"s{k}.zarr", 1.0 + k) for k in range(6)]
    errors: list[BaseException] = []

    def rec(k: int) -> None:
        try:
            library.record(stores[k], camera=CAMERA, serial=SERIAL_A, session_time=T0 + timedelta(hours=k),
                           library_root=root)
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=rec, args=(k,)) for k in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and len(library.entries(root)) == 6
    assert library.lookup(CAMERA, SERIAL_A, T0 + timedelta(hours=2, minutes=30), root).store.name.startswith(
        "20170614T114506Z-")


@pytest.mark.parametrize("text, why", [("{not json", "not valid JSON"),
                                       ('{"format": "x", "entries": []}', "not a calibration library index"),
                                       ('{"format": "mscal-calibration-library/1", "entries": [{"camera": 3}]}',
                                        "entry 0: camera")])
def test_a_damaged_index_is_named_with_how_to_fix_it(tmp_path, text, why) -> None:
    root = tmp_path / "library"
    root.mkdir()
    (root / "index.json").write_text(text)
    with pytest.raises(InputError, match=why) as info:
        library.lookup(CAMERA, SERIAL_A, None, root)
    assert str(root / "index.json") in str(info.value) and "delete it" in str(info.value)
    with pytest.raises(InputError, match=why):
        library.record(_store(tmp_path / "s.zarr", 1.0), camera=CAMERA, serial=SERIAL_A, session_time=T0,
                       library_root=root)
    assert not (root / CAMERA).exists()  # nothing copied


def test_default_root_is_under_the_cache_folder(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("MSCAL_CACHE_DIR", str(tmp_path / "cache"))
    assert library.default_library_root() == tmp_path / "cache" / "library"
    from pipeline.run import runner

    assert runner.default_cache_dir() == tmp_path / "cache"
