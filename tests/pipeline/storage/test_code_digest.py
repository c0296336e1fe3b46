"""The code part of the calibration cache's keys and of apply's run fingerprint: every source of
mscal_core, pipeline and the catalogs, as the process that computes it finds them."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import pipeline
from pipeline.storage.cache import code_digest

ROOT = Path(pipeline.__file__).resolve().parents[1]
#: In a process started in a copy of the packages: where its modules come from, the code digest,
#: the stage cache keys' code part and apply's fingerprint (each computed where mscal does).
PROBE = (
    "import json, pipeline\n"
    "from pipeline.storage.cache import code_digest\n"
    "from pipeline.apply.options import ApplyOptions\n"
    "from pipeline.apply.record import run_fingerprint\n"
    "fp = run_fingerprint(['a' * 64], 'b' * 64, ApplyOptions())\n"
    "print(json.dumps({'file': pipeline.__file__, 'digest': code_digest(), 'fingerprint': fp}))\n"
)


def _copy(dest: Path) -> Path:
    for name in ("mscal_core", "pipeline", "catalogs"):
        shutil.copytree(ROOT / name, dest / name, ignore=shutil.ignore_patterns("__pycache__"))
    return dest


def _probe(copy: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONSAFEPATH")}
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=copy, env=env, capture_output=True, text=True,
                         timeout=300, check=True)
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert Path(doc["file"]).resolve() == (copy / "pipeline" / "__init__.py").resolve()  # the copy's code ran
    return doc


@pytest.mark.parametrize("module", ["pipeline/calibrate/bands.py", "pipeline/ingest/sunsensor.py"])
def test_an_edited_fit_module_changes_the_keys(tmp_path: Path, module: str) -> None:
    """A copy of the packages gives this process's digest (another process, another place);
    a comment added to a module the fits run in changes the digest, so the calibration cache's
    keys (``pipeline.run.runner.stage_keys``) and apply's fingerprint change; a README
    beside the modules changes nothing."""
    copy = _copy(tmp_path / "copy")
    first = _probe(copy)
    assert first["digest"] == code_digest()
    assert first["fingerprint"]["code_sha256"] == first["digest"]

    (copy / "pipeline" / "calibrate" / "README.md").write_text("notes, not code\n")
    assert _probe(copy)["digest"] == first["digest"]

    with (copy / module).open("a") as f:
        f.write("# an edit\n")
    edited = _probe(copy)
    assert edited["digest"] != first["digest"]
    assert edited["fingerprint"]["code_sha256"] == edited["digest"]
    assert {k: v for k, v in edited["fingerprint"].items() if k != "code_sha256"} == \
        {k: v for k, v in first["fingerprint"].items() if k != "code_sha256"}


def test_stage_keys_carry_the_code_digest(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every stage's cache key depends on the code digest (the response's directly, the others
    through the key before them)."""
    import pipeline.run.runner as runner
    from pipeline.sim.synth import write_session

    session = runner.load_session(write_session(tmp_path / "s", size="small"))
    keys = runner.stage_keys(session, "forward")
    monkeypatch.setattr(runner, "code_digest", lambda: "0" * 64)
    other = runner.stage_keys(session, "forward")
    assert set(keys) == set(other) == {"response", "vignetting", "illumination"}
    assert all(keys[s] != other[s] for s in keys)


def test_the_digest_names_files_by_place_not_by_name(tmp_path: Path) -> None:
    """Two modules of one name in two subpackages, moved or swapped, give another digest."""
    from pipeline.storage.cache import source_digest

    for sub, text in (("a", "x = 1\n"), ("b", "x = 2\n")):
        (tmp_path / "p" / sub).mkdir(parents=True)
        (tmp_path / "p" / sub / "m.py").write_text(text)
    first = source_digest({"p": tmp_path / "p"})
    (tmp_path / "p" / "a" / "m.py").write_text("x = 2\n")
    (tmp_path / "p" / "b" / "m.py").write_text("x = 1\n")
    assert source_digest({"p": tmp_path / "p"}) != first
    (tmp_path / "p" / "b" / "__pycache__").mkdir()
    (tmp_path / "p" / "b" / "__pycache__" / "m.py").write_text("stale\n")
    (tmp_path / "p" / "a" / "m.py").write_text("x = 1\n")
    (tmp_path / "p" / "b" / "m.py").write_text("x = 2\n")
    assert source_digest({"p": tmp_path / "p"}) == first
