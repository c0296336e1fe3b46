"""session.yaml ``marker``: the single ArUco marker at the reflector's centre, or a ChArUco board.

``marker: {dictionary, id, size_m, border_m}`` (``border_m``: the white paper around the black
square, default a quarter of its side), or
``marker: {type: charuco, squares_x, squares_y, square_mm, marker_mm, dictionary, border_mm}``
for a ChArUco board centred on the reflector (``border_mm``: white margin around the board,
default 0). Either way the excluded centre of the reflector is the square of half side
``size_m / 2 + border_m`` (a board: its larger side).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mscal_core.charuco import CharucoSpec
from mscal_core.errors import InputError, SessionError

from pipeline.ingest.catalog import check_keys, finite_number

MARKER_EXAMPLE = ("marker: {dictionary: DICT_4X4_50, id: 3, size_m: 0.1}, or marker: {type: charuco, squares_x: 7, "
                  "squares_y: 5, square_mm: 40, marker_mm: 30, dictionary: DICT_4X4_50}")


@dataclass(frozen=True)
class MarkerSpec:
    dictionary: str
    id: int
    size_m: float
    border_m: float  # white paper around the black square, excluded from reflector pixels
    board: CharucoSpec | None = None  # a ChArUco board instead of the single marker (id unused)

    @property
    def label(self) -> str:
        """How messages name it: ``marker DICT_4X4_50 id 3`` or ``ChArUco board 7x5 DICT_4X4_50``."""
        if self.board is not None:
            return f"ChArUco board {self.board.squares_x}x{self.board.squares_y} {self.dictionary}"
        return f"marker {self.dictionary} id {self.id}"


def marker_dictionary(value: Any, path: Path, where: str) -> str:
    """The name of an OpenCV ArUco/AprilTag dictionary (``DICT_4X4_50``, ...), checked."""
    import cv2

    name = str(value)
    if not (name.startswith("DICT_") and isinstance(getattr(cv2.aruco, name, None), int)):
        raise SessionError(f"{where}.dictionary {name!r} is not an OpenCV ArUco/AprilTag dictionary", path=path,
                           hint="e.g. DICT_4X4_50, DICT_5X5_100, DICT_APRILTAG_36h11")
    return name


def _number(value: Any, path: Path, where: str, *, positive: bool = False) -> float:
    v = finite_number(value)
    if v is None:
        raise SessionError(f"{where} must be a number, got {value!r}", path=path)
    if positive and v <= 0:
        raise SessionError(f"{where} must be positive, got {value!r}", path=path)
    return v


def _count(value: Any, path: Path, where: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < 2:
        raise SessionError(f"{where} must be an integer of at least 2, got {value!r}", path=path)
    return int(value)


def parse_marker(mk: Any, path: Path, reflector_size_m: tuple[float, float]) -> MarkerSpec:
    """session.yaml ``marker`` (see the module), checked against the reflector's size."""
    if not isinstance(mk, dict):
        raise SessionError("marker must be a mapping {dictionary, id, size_m}", path=path, hint=MARKER_EXAMPLE)
    kind = mk.get("type", "aruco")
    if kind == "charuco":
        check_keys(mk, {"type", "squares_x", "squares_y", "square_mm", "marker_mm", "dictionary"}, {"border_mm"},
                   path, "marker")
        name = marker_dictionary(mk["dictionary"], path, "marker")
        try:
            board = CharucoSpec(_count(mk["squares_x"], path, "marker.squares_x"),
                                _count(mk["squares_y"], path, "marker.squares_y"),
                                _number(mk["square_mm"], path, "marker.square_mm", positive=True) / 1000,
                                _number(mk["marker_mm"], path, "marker.marker_mm", positive=True) / 1000, name)
        except InputError as exc:
            raise SessionError(f"marker: {exc.reason}", path=path, hint=MARKER_EXAMPLE) from None
        border = _number(mk.get("border_mm", 0.0), path, "marker.border_mm") / 1000
        marker = MarkerSpec(dictionary=name, id=-1, size_m=max(board.size_m), border_m=max(border, 0.0), board=board)
    elif kind == "aruco":
        check_keys(mk, {"dictionary", "id", "size_m"}, {"border_m", "type"}, path, "marker")
        if not isinstance(mk["id"], int) or isinstance(mk["id"], bool) or mk["id"] < 0:
            raise SessionError(f"marker.id must be a non-negative integer, got {mk['id']!r}", path=path)
        msize = _number(mk["size_m"], path, "marker.size_m", positive=True)
        border = _number(mk.get("border_m", 0.25 * msize), path, "marker.border_m")
        marker = MarkerSpec(dictionary=marker_dictionary(mk["dictionary"], path, "marker"), id=int(mk["id"]),
                            size_m=msize, border_m=max(border, 0.0))
    else:
        raise SessionError(f"marker.type must be aruco or charuco, got {kind!r}", path=path, hint=MARKER_EXAMPLE)
    if marker.size_m / 2 + marker.border_m >= min(reflector_size_m) / 2:
        raise SessionError(
            f"the {'board' if marker.board is not None else 'marker'} and its border cover the whole reflector",
            path=path,
            hint="check the marker's size and reflector.size_m (both in metres)",
        )
    return marker
