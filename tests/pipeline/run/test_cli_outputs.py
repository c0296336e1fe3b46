"""-o is checked before any work, for every command that writes: one line naming the path,
exit status 2, nothing of the user's replaced (calibrate -o FILE once replaced a file)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.run.cli import main


def _cases(tmp_path: Path) -> list[tuple[Path, str]]:
    f = tmp_path / "notes.txt"
    f.write_text("the user's notes")
    return [(f, "is an existing file"), (f / "out", "which is a file, not a folder"),
            (Path("/proc/mscal-out"), "cannot write here")]


@pytest.mark.parametrize("command", ["calibrate", "apply", "fit-response"])
def test_bad_output_paths_refused_before_any_work(small, tmp_path: Path, capsys, command: str) -> None:
    session, calib = small
    for out, expect in _cases(tmp_path):
        argv = {
            "calibrate": ["calibrate", str(session), "-o", str(out)],
            "apply": ["apply", str(session / "flights" / "field"), "--calibration", str(calib), "-o", str(out)],
            "fit-response": ["fit", "response", str(session), "-o", str(out)],
        }[command]
        assert main(argv) == 2, (command, out)
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("mscal: error: "), err
        assert expect in err[0] and str(out) in err[0]
    assert (tmp_path / "notes.txt").read_text() == "the user's notes"


def test_report_into_an_existing_folder_or_under_a_file_is_refused(small, tmp_path: Path, capsys) -> None:
    _, calib = small
    assert main(["report", "--calibration", str(calib), "-o", str(tmp_path)]) == 2
    assert "is an existing folder; mscal writes a file here" in capsys.readouterr().err
    (tmp_path / "f").write_text("x")
    assert main(["report", "--calibration", str(calib), "-o", str(tmp_path / "f" / "report.html")]) == 2
    assert "which is a file, not a folder" in capsys.readouterr().err


def test_store_over_a_folder_mscal_did_not_write(small, tmp_path: Path, capsys) -> None:
    session, _ = small
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "a.jpg").write_bytes(b"jpeg")
    assert main(["calibrate", str(session), "-o", str(photos)]) == 2
    assert "existing folder that mscal did not write" in capsys.readouterr().err
    assert (photos / "a.jpg").read_bytes() == b"jpeg"
