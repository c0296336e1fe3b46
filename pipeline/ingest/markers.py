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
from typing import Annotated, Any, Literal, Union

from mscal_core.charuco import CharucoSpec
from mscal_core.errors import InputError, SessionError
from pydantic import BeforeValidator, Discriminator, Tag

from pipeline.ingest.schema import Problem, Strict, integer, number, validate

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


def _dictionary(value: Any) -> str:
    """The name of an OpenCV ArUco/AprilTag dictionary (``DICT_4X4_50``, ...), checked."""
    import cv2

    name = str(value)
    if not (name.startswith("DICT_") and isinstance(getattr(cv2.aruco, name, None), int)):
        raise Problem("is not an OpenCV ArUco/AprilTag dictionary", value_first=True,
                      hint="e.g. DICT_4X4_50, DICT_5X5_100, DICT_APRILTAG_36h11")
    return name


#: session.yaml's name of an OpenCV ArUco/AprilTag dictionary.
Dictionary = Annotated[str, BeforeValidator(_dictionary)]
MarkerId = integer(0, text="a non-negative integer")


class _Aruco(Strict):
    TAGS, KEY = ("aruco",), "type"
    type: Literal["aruco"] = "aruco"
    dictionary: Dictionary
    id: MarkerId  # type: ignore[valid-type]
    size_m: number(positive=True)  # type: ignore[valid-type]
    border_m: number() = None  # type: ignore[valid-type, assignment]  # not given: a quarter of size_m


class _Charuco(Strict):
    TAGS, KEY = ("charuco",), "type"
    type: Literal["charuco"]
    squares_x: integer(2)  # type: ignore[valid-type]
    squares_y: integer(2)  # type: ignore[valid-type]
    square_mm: number(positive=True)  # type: ignore[valid-type]
    marker_mm: number(positive=True)  # type: ignore[valid-type]
    dictionary: Dictionary
    border_mm: number() = 0.0  # type: ignore[valid-type]


def _marker_type(value: Any) -> str:
    kind = value.get("type", "aruco") if isinstance(value, dict) else "aruco"  # not a mapping: aruco's message
    return kind if isinstance(kind, str) else repr(kind)


_Marker = Annotated[Union[Annotated[_Aruco, Tag("aruco")], Annotated[_Charuco, Tag("charuco")]],
                    Discriminator(_marker_type)]


def parse_marker(mk: Any, path: Path, reflector_size_m: tuple[float, float]) -> MarkerSpec:
    """session.yaml ``marker`` (see the module), checked against the reflector's size."""
    m = validate(_Marker, mk, path, SessionError, prefix="marker")
    if isinstance(m, _Charuco):
        try:
            board = CharucoSpec(m.squares_x, m.squares_y, m.square_mm / 1000, m.marker_mm / 1000, m.dictionary)
        except InputError as exc:
            raise SessionError(f"marker: {exc.reason}", path=path, hint=MARKER_EXAMPLE) from None
        marker = MarkerSpec(dictionary=m.dictionary, id=-1, size_m=max(board.size_m),
                            border_m=max(m.border_mm / 1000, 0.0), board=board)
    else:
        border = 0.25 * m.size_m if m.border_m is None else m.border_m
        marker = MarkerSpec(dictionary=m.dictionary, id=m.id, size_m=m.size_m, border_m=max(border, 0.0))
    if marker.size_m / 2 + marker.border_m >= min(reflector_size_m) / 2:
        raise SessionError(
            f"the {'board' if marker.board is not None else 'marker'} and its border cover the whole reflector",
            path=path,
            hint="check the marker's size and reflector.size_m (both in metres)",
        )
    return marker
