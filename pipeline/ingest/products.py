"""Which outputs apply writes (SPEC.md, Outputs of apply): the default set and the opt-in ones.

The default set is what a survey needs: ``reflectance.zarr`` with ``reflectance``, ``ndvi``
and ``vegetation_mask``; ``raw.zarr``; the per-band photogrammetry TIFFs (``photogrammetry/``,
``panels/``, ``thermal/``) and the NDVI TIFFs; ``run.json``. Opt in to:

- ``radiance`` (``--products radiance``): the factory chain's radiance cube beside
  reflectance (cameras with factory radiometry only; reflectance is radiance times one factor
  per band, which run.json holds either way);
- further indices of ``catalogs/indices`` (``--indices ndre,...``); NDVI is always made when
  the camera's bands allow it;
- and out of the TIFFs (``--no-tiffs``): an analytics-only run writes the two stores and
  run.json;
- the values of flagged pixels (``--keep-flagged``): reflectance is NaN where
  ``reflectance.zarr/quality`` flags a pixel unless kept (:mod:`pipeline.apply.quality`);
  ``--shoulder-bound`` sets the relative uncertainty of the response above which a DN is on
  its shoulder (default 0.03).

A choice is given as a partial mapping ``{"radiance": bool, "indices": [names], "tiffs":
bool, "keep_flagged": bool, "shoulder_bound": float}`` (any key may be missing): from the command line (:func:`cli_choice`) and from
``session.yaml``'s ``products`` key (:func:`yaml_choice`); :func:`resolve` lays them over the
defaults, the command line over session.yaml, key by key. The resolved :class:`Products` is
part of the run's fingerprint (a different choice redoes the flight) and is recorded in
run.json ``products`` (:meth:`Products.record`). Apply's side (stale outputs, the radiance
factor's record): :mod:`pipeline.apply.products`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from mscal_core.errors import InputError, SessionError
from mscal_core.quality import DEFAULT_BOUND

from pipeline.ingest.catalog import Camera, Index, list_entries, load_index

#: Products that are off unless asked for (``--products``).
OPT_IN = ("radiance",)
#: The index always made (when the camera's bands allow it).
BASE_INDEX = "ndvi"
#: Keys of a products choice (session.yaml ``products``; run.json ``products``).
CHOICE_KEYS = ("radiance", "indices", "tiffs", "keep_flagged", "shoulder_bound")
#: The word that clears a list option (``--products none``, ``--indices none``).
NONE = "none"


def available_indices() -> list[str]:
    """Names of the indices of ``catalogs/indices``."""
    return list_entries("indices")


def _index_names(names: Sequence[str], where: str) -> tuple[str, ...]:
    """``ndvi`` then the other names in the order given, each once; InputError for a name
    that is not in ``catalogs/indices`` (listing the ones that are)."""
    known = available_indices()
    unknown = [n for n in names if n not in known]
    if unknown:
        raise InputError(f"{where}: no index {', '.join(repr(n) for n in unknown)} in catalogs/indices",
                         hint=f"available: {', '.join(known)}; add catalogs/indices/NAME.yaml for another")
    out = [BASE_INDEX]
    out += [n for n in dict.fromkeys(names) if n != BASE_INDEX]
    return tuple(out)


@dataclass(frozen=True)
class Products:
    """The outputs a run writes beyond raw.zarr and reflectance (module docstring).
    ``indices``: the indices asked for, NDVI first (``()``: none at all, for the Python API
    only); ``radiance``: the factory radiance cube; ``tiffs``: the per-frame TIFFs;
    ``keep_flagged``: the values of pixels the quality mask flags (else NaN);
    ``shoulder_bound``: the relative uncertainty of U above which a DN is on the shoulder."""

    radiance: bool = False
    indices: tuple[str, ...] = (BASE_INDEX,)
    tiffs: bool = True
    keep_flagged: bool = False
    shoulder_bound: float = DEFAULT_BOUND

    def record(self, made: Sequence[Index] | None = None) -> dict[str, Any]:
        """run.json ``products``; ``made``: the indices written (NDVI is left out for a camera
        whose bands cannot make it), else those asked for."""
        names = list(self.indices) if made is None else [ix.name for ix in made]
        return {"radiance": self.radiance, "indices": names, "tiffs": self.tiffs, "keep_flagged": self.keep_flagged,
                "shoulder_bound": self.shoulder_bound}

    def fingerprint(self) -> dict[str, Any]:
        """What a re-run compares: the choice as asked."""
        return self.record()


DEFAULT = Products()


def cli_choice(products: str | None = None, indices: str | None = None, tiffs: bool | None = None,
               keep_flagged: bool | None = None, shoulder_bound: float | None = None) -> dict[str, Any]:
    """The keys the command line gives (None: not given): ``--products radiance`` (comma
    list of :data:`OPT_IN`, ``none`` for none), ``--indices ndre,...`` (``none``: NDVI only),
    ``--tiffs/--no-tiffs``, ``--keep-flagged``, ``--shoulder-bound``. InputError for an unknown
    product or index, or a bound that is not positive."""
    choice: dict[str, Any] = {}
    if products is not None:
        names = [p.strip() for p in products.split(",") if p.strip()]
        names = [] if names == [NONE] else names
        unknown = [n for n in names if n not in OPT_IN]
        if unknown:
            raise InputError(f"--products {', '.join(repr(n) for n in unknown)}: not an opt-in product",
                             hint=f"opt-in products: {', '.join(OPT_IN)} (or {NONE}); indices go to --indices, "
                                  "the TIFFs are left out with --no-tiffs")
        choice["radiance"] = "radiance" in names
    if indices is not None:
        names = [n.strip() for n in indices.split(",") if n.strip()]
        choice["indices"] = list(_index_names([] if names == [NONE] else names, "--indices"))
    if tiffs is not None:
        choice["tiffs"] = bool(tiffs)
    if keep_flagged:
        choice["keep_flagged"] = True
    if shoulder_bound is not None:
        if not shoulder_bound > 0:
            raise InputError(f"--shoulder-bound {shoulder_bound}: must be positive (a relative uncertainty, e.g. 0.03)")
        choice["shoulder_bound"] = float(shoulder_bound)
    return choice


def yaml_choice(value: Any, path: str | Path) -> dict[str, Any]:
    """session.yaml's ``products`` mapping, checked: ``radiance`` and ``tiffs`` booleans,
    ``indices`` a list of index names; every key optional, no other key. SessionError
    naming the file, in one line."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise SessionError(f"products must be a mapping of {', '.join(CHOICE_KEYS)}, got {value!r}", path=path,
                           hint="e.g. products: {radiance: true, indices: [ndre], tiffs: false}")
    unknown = [str(k) for k in value if k not in CHOICE_KEYS]
    if unknown:
        raise SessionError(f"products: unknown key(s) {', '.join(unknown)}", path=path,
                           hint=f"allowed keys: {', '.join(CHOICE_KEYS)}")
    choice: dict[str, Any] = {}
    for key in ("radiance", "tiffs", "keep_flagged"):
        if key in value:
            if not isinstance(value[key], bool):
                raise SessionError(f"products.{key} must be true or false, got {value[key]!r}", path=path)
            choice[key] = value[key]
    if "shoulder_bound" in value:
        bound = value["shoulder_bound"]
        if isinstance(bound, bool) or not isinstance(bound, (int, float)) or not bound > 0:
            raise SessionError(f"products.shoulder_bound must be a positive number, got {bound!r}", path=path,
                               hint="e.g. shoulder_bound: 0.03 (relative uncertainty of the response)")
        choice["shoulder_bound"] = float(bound)
    if "indices" in value:
        names = value["indices"]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise SessionError(f"products.indices must be a list of index names, got {names!r}", path=path,
                               hint="e.g. indices: [ndre]")
        try:
            choice["indices"] = list(_index_names(names, "products.indices"))
        except InputError as exc:
            raise SessionError(exc.reason, path=path, hint=exc.hint) from None
    return choice


def resolve(*choices: Mapping[str, Any] | None) -> Products:
    """The defaults with each choice laid over them in turn, key by key: ``resolve(session_yaml,
    command_line)`` gives the command line the last word on every key it names."""
    merged: dict[str, Any] = {}
    for choice in choices:
        merged.update(choice or {})
    return Products(radiance=bool(merged.get("radiance", DEFAULT.radiance)),
                    indices=tuple(merged.get("indices", DEFAULT.indices)),
                    tiffs=bool(merged.get("tiffs", DEFAULT.tiffs)),
                    keep_flagged=bool(merged.get("keep_flagged", DEFAULT.keep_flagged)),
                    shoulder_bound=float(merged.get("shoulder_bound", DEFAULT.shoulder_bound)))


def radiance_refused(products: Products, what: str) -> None:
    """InputError when radiance is asked of a run without factory radiometry (``what`` says
    which: a field calibration's Eq. 15 gives reflectance only)."""
    if products.radiance:
        raise InputError(f"--products radiance is for cameras with factory radiometry (--calibration factory); "
                         f"{what} gives reflectance (Eq. 15) and no radiance",
                         hint="leave radiance out of --products and of session.yaml's products")


def indices_for(camera: Camera, products: Products) -> list[Index]:
    """The indices to write for ``camera``: NDVI when its bands make it, each other index asked
    for (InputError naming the band roles it needs that the camera does not define)."""
    out = []
    for name in products.indices:
        ix = load_index(name)
        missing = [r for r in ix.inputs if r not in camera.index_bands]
        if not missing:
            out.append(ix)
        elif name != BASE_INDEX:
            have = ", ".join(sorted(camera.index_bands)) or "none"
            raise InputError(f"index {name} needs band role(s) {', '.join(missing)} that camera {camera.name} does not "
                             f"have (its index roles: {have})",
                             hint=f"leave {name} out of --indices and of session.yaml's products.indices")
    return out
