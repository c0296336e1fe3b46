"""The inbox of ``mscal serve``: which session folders are complete and not yet processed.

A session folder ``INBOX/<name>/`` is a field session (``session.yaml``, ``response/``, ...)
or a flight folder as it comes off the camera's card (no ``session.yaml`` needed,
:mod:`pipeline.run.card`). It is **complete** when it holds a file and either a ``READY``
file (the uploader writes it last) or no file in it was modified for ``settle_s`` seconds.
Nothing in the inbox is passed over without a word: a folder still being copied, an empty
folder and a file that is not in a folder are named with the reason (:func:`waiting`, kept in
the state file's ``waiting`` and said in serve's summary). Each complete session is processed once: the state file
``OUTROOT/.mscal-serve.json`` (written atomically) records every session processed, with
the fingerprint of its listing (names, sizes, modification times) and the sha256 of its
content. A session is processed again only if its content changed; a restart reads the state
file and does not reprocess anything. A session whose run failed is recorded as failed and
retried only once its content changes.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from mscal_core.errors import InputError

from pipeline.storage.atomic import write_json_atomic
from pipeline.storage.store import content_hashes

READY = "READY"
STATE_FILE = ".mscal-serve.json"
STATE_FORMAT = "mscal-serve/1"


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file())


def listing_fingerprint(folder: Path) -> str:
    """sha256 of the relative names, sizes and modification times of every file (cheap)."""
    h = hashlib.sha256()
    for p in _files(folder):
        st = p.stat()
        h.update(f"{p.relative_to(folder).as_posix()}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def content_sha256(folder: Path) -> str:
    """sha256 over the relative names and content hashes of every file (reads every byte)."""
    return hashlib.sha256(json.dumps(content_hashes(_files(folder), folder), sort_keys=True).encode()).hexdigest()


def is_complete(folder: Path, settle_s: float, now: float | None = None) -> bool:
    """A file besides ``READY``, and a ``READY`` file or nothing modified for ``settle_s``."""
    return incomplete_reason(folder, settle_s, now) is None


def incomplete_reason(folder: Path, settle_s: float, now: float | None = None) -> str | None:
    """Why ``folder`` is not complete yet (one line), or None when it is."""
    files = [p for p in _files(folder) if p.name != READY]
    if not files:
        return "empty folder: nothing to process"
    if (folder / READY).is_file():
        return None
    now = time.time() if now is None else now
    age = now - max(p.stat().st_mtime for p in files)
    if age >= settle_s:
        return None
    return (f"still being copied: a file was modified {max(age, 0.0):.0f} s ago and there is no {READY} file; "
            f"processed once nothing changed for {settle_s:g} s (or once {READY} is written)")


def waiting(inbox: str | Path, settle_s: float, now: float | None = None) -> dict[str, str]:
    """``{name: reason}`` of what in the inbox is not processed in this look: folders not
    complete (:func:`incomplete_reason`) and files that are not in a session folder."""
    inbox = Path(inbox)
    out: dict[str, str] = {}
    for p in sorted(inbox.iterdir()):
        if p.name.startswith(".") or p.name == STATE_FILE:
            continue
        if p.is_dir():
            why = incomplete_reason(p, settle_s, now)
            if why is not None:
                out[p.name] = why
        else:
            out[p.name] = "a file, not a folder: put each flight or session in a folder of its own in the inbox"
    return out


def reason_kind(reason: str) -> str:
    """The kind of a :func:`waiting` reason, without its figures: the text before the first
    colon ("still being copied", "empty folder", "a file, not a folder")."""
    return reason.split(":", 1)[0].strip()


def newly_waiting(before: dict[str, Any], now: dict[str, str]) -> dict[str, str]:
    """The part of this look's :func:`waiting` to name in serve's summary: folders that were
    not waiting at the last look, or were for another kind of reason (``before`` is the state
    file's ``waiting``, :func:`load_waiting`). A scheduled serve prints a folder still being
    copied once, not at every look; the state file keeps every waiting folder each look."""
    return {n: r for n, r in now.items()
            if reason_kind(str((before.get(n) or {}).get("reason", ""))) != reason_kind(r)}


def record_waiting(out_root: Path, names: dict[str, str]) -> None:
    """Keep this look's :func:`waiting` in the state file (``waiting``: name -> reason, time)."""
    if not names and not (out_root / STATE_FILE).is_file():
        return
    utc = datetime.now(timezone.utc).isoformat(timespec="seconds")
    _write_state(out_root, load_state(out_root), {n: {"reason": r, "utc": utc} for n, r in names.items()})


def _read_state(out_root: Path) -> dict[str, Any]:
    """The state file as written (empty if there is none yet); :class:`InputError` naming it
    when it cannot be read."""
    path = out_root / STATE_FILE
    if not path.is_file():
        return {}
    try:
        return dict(json.loads(path.read_text()))
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the serve state ({exc})", path=path,
                         hint="restore it, or delete it to process every session in the inbox again") from None


def _write_state(out_root: Path, sessions: dict[str, Any], waiting: dict[str, Any]) -> None:
    out_root.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out_root / STATE_FILE, {"format": STATE_FORMAT, "sessions": sessions, "waiting": waiting})


def load_state(out_root: Path) -> dict[str, Any]:
    """The state file's ``sessions`` mapping (empty if there is none yet)."""
    return dict(_read_state(out_root).get("sessions", {}))


def load_waiting(out_root: Path) -> dict[str, Any]:
    """The state file's ``waiting`` mapping (what the last look did not process, and why)."""
    return dict(_read_state(out_root).get("waiting", {}))


def record(out_root: Path, name: str, *, listing: str, content: str, status: str, detail: str = "") -> None:
    """Record a processed session in the state file (read, update, atomic rewrite)."""
    state = _read_state(out_root)
    sessions = dict(state.get("sessions", {}))
    sessions[name] = {"listing": listing, "content_sha256": content, "status": status, "detail": detail,
                      "utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    _write_state(out_root, sessions, {k: v for k, v in state.get("waiting", {}).items() if k != name})


@dataclass(frozen=True)
class Pending:
    """A complete session to process now."""

    name: str
    path: str
    listing: str
    content: str


def pending_sessions(inbox: str | Path, out_root: str | Path, settle_s: float, now: float | None = None) -> list[Pending]:
    """Complete sessions of ``inbox`` not processed with their current content, by name.

    A session whose listing changed but whose content did not (copied again, touched) has its
    listing updated in the state file and is not processed again.
    """
    inbox, out_root = Path(inbox), Path(out_root)
    if not inbox.is_dir():
        raise InputError("inbox folder not found", path=inbox)
    state = load_state(out_root)
    out: list[Pending] = []
    for folder in sorted(p for p in inbox.iterdir() if p.is_dir()):
        if not is_complete(folder, settle_s, now):
            continue
        done = state.get(folder.name, {})
        listing = listing_fingerprint(folder)
        if done.get("listing") == listing:
            continue
        content = content_sha256(folder)
        if done.get("content_sha256") == content:
            record(out_root, folder.name, listing=listing, content=content, status=done["status"], detail=done.get("detail", ""))
            continue
        out.append(Pending(folder.name, str(folder), listing, content))
    return out


def next_time(cron: str, after: datetime) -> datetime:
    """The next time ``cron`` fires after ``after``; :class:`InputError` if it is not valid."""
    from croniter import croniter

    if not croniter.is_valid(cron):
        raise InputError(f"--cron {cron!r} is not a cron expression", hint="e.g. --cron '*/15 * * * *' (every 15 minutes)")
    return croniter(cron, after).get_next(datetime)
