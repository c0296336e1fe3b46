"""The ``mscal`` command line (SPEC.md, Command line).

Exit status 0 on success; on bad input a one-line reason on stderr and exit status 2, never a
traceback (an :class:`~mscal_core.errors.MscalError` is always caught here).
"""

from __future__ import annotations

import errno
import gc
import json
import logging
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import click
from mscal_core.errors import MscalError

from pipeline.run.console import (
    LOG_LEVELS,
    Summary,
    common_options,
    console,
    note,
    progress,
    report_warnings,
)
from pipeline.run.options import (
    ILLUMINATION_MODES,
    RESPONSE_METHOD_HELP,
    RESPONSE_METHODS,
    deprecated_alias,
    execution_options,
    products_options,
    writes,
)
from pipeline.run.summaries import echo_run, echo_serve, run_warnings
from pipeline.storage.process import stop_process_servers
from pipeline.storage.run_layout import run_value


def _summary(ds) -> str:  # xarray Dataset
    parts = [f"camera {ds.attrs.get('camera')}", f"{ds.sizes.get('band')} bands"]
    for stage in ("response", "vignetting", "illumination"):
        rep = ds.attrs.get(stage)
        if rep:
            skipped = len(rep.get("skipped", []))
            parts.append(f"{stage} {rep.get('seconds', 0):.1f} s" + (f" ({skipped} frame(s) skipped)" if skipped else ""))
    return ", ".join(parts)


def _report_skips(ds) -> None:
    for stage in ("response", "vignetting", "illumination"):
        for s in (ds.attrs.get(stage) or {}).get("skipped", []):
            note(f"skipped {stage} frame {s['file']}: {s['reason']}")


def _store_summary(command: str, ds, out: Path, headline: str, **details: Any) -> Summary:
    """The summary of a command that wrote calibration store ``out``: its fits, the frames
    each skipped, and the report's warnings on it."""
    skipped = {st: len((ds.attrs.get(st) or {}).get("skipped", [])) for st in ("response", "vignetting", "illumination")
               if ds.attrs.get(st)}
    return Summary(command, headline, outputs={"calibration store": out},
                   counts={"bands": int(ds.sizes.get("band", 0)), "frames_skipped": skipped},
                   warnings=report_warnings(calibration=out), details={"camera": ds.attrs.get("camera"), **details})



class MscalCommand(click.Command):
    """A command with ``-v``, ``-q`` and ``--json`` (:func:`pipeline.run.console.common_options`)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.params += common_options()


class MscalGroup(click.Group):
    """A group whose commands and subgroups take ``-v/-q/--json`` too, before or after their name."""

    command_class = MscalCommand

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.params += common_options()


MscalGroup.group_class = MscalGroup


def _version(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if not value or ctx.resilient_parsing:
        return
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("mscal")
    except PackageNotFoundError:  # run from a checkout without installing
        from mscal_core import __version__ as v
    click.echo(f"mscal {v}")
    ctx.exit()


@click.group(cls=MscalGroup, context_settings={"help_option_names": ["-h", "--help"]},
             epilog="-v/-q/--json may be given before or after the command name. "
                    "See 'mscal COMMAND --help' for each command.")
@click.option("--version", is_flag=True, expose_value=False, is_eager=True, callback=_version,
              help="Print mscal's version and exit.")
def cli() -> None:
    """mscal: field radiometric calibration of multispectral cameras (Khanna et al., ICRA 2017)."""
    logging.basicConfig(level=LOG_LEVELS[console().verbosity], format="%(name)s: %(message)s")
    click.get_current_context().call_on_close(stop_process_servers)  # no process of the command outlives it


@cli.command(short_help="Fit response, vignetting and illumination of a session.")
@writes("store", "calibration store")
@click.argument("session", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path), help="Calibration store (.zarr) to write.")
@click.option("--response-method", type=RESPONSE_METHODS, default="forward", show_default=True,
              help=RESPONSE_METHOD_HELP)
@click.option("--calibration", "partial", default=None, type=click.Path(path_type=Path),
              help="A store with intrinsics per band ('mscal fit intrinsics'), used when session.yaml gives none.")
def calibrate(session: Path, out: Path, response_method: str, partial: Path | None) -> None:
    """All three fits of a SESSION folder: response, vignetting, illumination."""
    from pipeline.calibrate.pool import session_pool
    from pipeline.calibrate.sweep import start_sweep

    t0 = time.perf_counter()
    # the band fits' workers start first, and the response fits on them, before this process
    # imports the rest of the calibration (xarray, zarr): the workers fit meanwhile
    with session_pool(session) as pool:
        sweep = start_sweep(session, response_method, pool)
        from pipeline.calibrate.fit import CALIBRATE_STEPS, calibrate_session

        with progress(CALIBRATE_STEPS, "calibrate") as advance:
            ds = calibrate_session(session, out, response_method=response_method, calibration=partial,
                                   advance=advance, pool=pool, sweep=sweep)
    _report_skips(ds)
    # recorded by camera and serial number, for later flights of the same camera; the store
    # is written whatever happens here, so a library that cannot be written is only a note
    from pipeline.calibrate.library import record_fitted

    try:
        library: str | None = str(record_fitted(out, session))
    except (MscalError, OSError) as exc:
        library = None
        note(f"not recorded in the calibration library: {exc}")
    summary = _store_summary("calibrate", ds, out, f"wrote {out} ({_summary(ds)}; {time.perf_counter() - t0:.1f} s)",
                             library=library)
    summary.outputs["calibration library"] = library
    summary.emit()


@cli.group(short_help="One fit at a time: U, V, S and B, or the intrinsics.")
def fit() -> None:
    """One fit at a time: response, vignetting, illumination or intrinsics."""


@fit.command("response", short_help="Inverse response U per band (Eq. 5-7).")
@writes("store", "calibration store")
@click.argument("directory", type=click.Path(path_type=Path))
@click.option("--camera", "camera", default=None, help="Camera catalog name (required for a plain frame folder).")
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Calibration store (.zarr) to write.")
@click.option("--response-method", type=RESPONSE_METHODS, default=None, help=RESPONSE_METHOD_HELP + "  [default: forward]")
@deprecated_alias("--method", "--response-method", "method")
def fit_response(directory: Path, camera: str | None, out: Path, response_method: str | None,
                 method: str | None) -> None:
    """Inverse response U per band (Eq. 5-7) from DIRECTORY: a frame folder with frames.csv,
    or a session (its response/ folder)."""
    from pipeline.calibrate.fit import fit_response_cli

    ds = fit_response_cli(directory, out, camera, response_method or method or "forward")
    _store_summary("fit response", ds, out, f"wrote {out} ({_summary(ds)})").emit()


def _stage_command(stage: str):
    @click.argument("session", type=click.Path(path_type=Path))
    @click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
                  help="Calibration store (.zarr) to write.")
    @click.option("--calibration", "partial", default=None, type=click.Path(path_type=Path),
                  help="A store holding the earlier fits; without it they are fitted from SESSION.")
    def command(session: Path, out: Path, partial: Path | None) -> None:
        from pipeline.calibrate.fit import fit_stage_cli

        ds = fit_stage_cli(stage, session, out, partial)
        _report_skips(ds)
        _store_summary(f"fit {stage}", ds, out, f"wrote {out} ({_summary(ds)})").emit()

    command.__doc__ = {
        "vignetting": "Per-pixel, per-band vignetting V (Eq. 8-10) from SESSION/vignetting.",
        "illumination": "Spectral factor S and reflector brightness B (Eq. 11-14) from SESSION/reflector.",
    }[stage]
    return fit.command(stage, short_help={"vignetting": "Per-pixel, per-band vignetting V (Eq. 8-10).",
                                          "illumination": "Spectral factor S and reflector brightness B (Eq. 11-14)."}[stage])(writes("store", "calibration store")(command))


_stage_command("vignetting")
_stage_command("illumination")


@fit.command("intrinsics", short_help="Camera intrinsics per band from board images (OpenCV).")
@writes("store", "calibration store")
@click.argument("frames", type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Calibration store (.zarr) to write.")
@click.option("--camera", default=None, help="Camera catalog name (default: session.yaml beside FRAMES).")
@click.option("--board", "kind", type=click.Choice(["charuco", "checkerboard"]), default=None,
              help="Board kind (default: FRAMES/board.yaml).")
@click.option("--squares", default=None, help="Squares of the board, COLUMNSxROWS, e.g. 7x5.")
@click.option("--square-m", type=float, default=None, help="Square side (m).")
@click.option("--marker-m", type=float, default=None, help="ChArUco marker side (m).")
@click.option("--dictionary", default="DICT_4X4_50", show_default=True, help="ChArUco marker dictionary.")
@click.option("--fix-k3", is_flag=True, help="Keep k3 = 0 (few or small board images: k2 and k3 trade off).")
def fit_intrinsics(frames: Path, out: Path, camera: str | None, kind: str | None, squares: str | None,
                   square_m: float | None, marker_m: float | None, dictionary: str, fix_k3: bool) -> None:
    """Camera intrinsics per band from FRAMES, images of a ChArUco board or a checkerboard
    (OpenCV); a multi-lens camera's lenses one by one."""
    from pipeline.calibrate.intrinsics import fit_intrinsics_cli

    board = None
    if kind is not None:
        board = {"kind": kind, "squares": squares, "square_m": square_m, "marker_m": marker_m,
                 "dictionary": dictionary}
    ds = fit_intrinsics_cli(frames, out, camera_name=camera, board=board, fix_k3=fix_k3)
    rep = ds.attrs["intrinsics"]
    for s in rep["skipped"]:
        note(f"skipped {s['file']}: {s['reason']}")
    summary = _store_summary(
        "fit intrinsics", ds, out, f"wrote {out} (camera {ds.attrs['camera']}, {rep['images']} images, views per band "
        f"{rep['views']}, reprojection rms {', '.join(f'{v:.2f}' for v in rep['rms_px'])} px)",
        reprojection_rms_px=list(rep["rms_px"]))
    summary.counts.update({"images": rep["images"], "views_per_band": rep["views"], "images_skipped": len(rep["skipped"])})
    summary.emit()


@cli.command(short_help="Band co-registration of a multi-lens camera (homographies).")
@writes("store", "calibration store")
@click.argument("captures", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Calibration store (.zarr): the registration is added to it, or a new store is created.")
@click.option("--camera", default=None, help="Camera catalog name (default: the existing store's camera, else recognised "
              "from the files as apply does).")
@click.option("--reference-band", default=None,
              help="Band to align to (default: the lens in the middle of the rig).")
@deprecated_alias("--reference", "--reference-band", "reference", type=str)
@click.option("--min-ecc", default=0.3, show_default=True, type=float,
              help="Reject a band's transform whose gradient correlation after alignment is lower.")
@click.option("--max-captures", default=12, show_default=True, type=int,
              help="Register at most this many captures, evenly spread over those given.")
def register(captures: tuple[Path, ...], out: Path, camera: str | None, reference_band: str | None,
             reference: str | None, min_ecc: float, max_captures: int) -> None:
    """Band co-registration of a multi-lens camera from CAPTURES (folders or band files): one
    homography per band to the reference band, stored with its quality figures."""
    from mscal_core.registration import Thresholds

    from pipeline.calibrate.registration import register_cli

    t0 = time.perf_counter()
    # --reference is apply's light source; register's was renamed --reference-band (old spelling warns)
    ds, problems = register_cli(list(captures), out, camera, reference_band or reference, Thresholds(min_ecc=min_ecc), max_captures,
                                progress=lambda n: progress(n, "register"))
    for p in problems:
        note(f"not used {p['file']}: {p['reason']}")
    reg = ds.attrs["registration"]
    for f in reg["fallbacks"]:
        note(f"capture {f['capture']} fell back to the session transform for {', '.join(f['bands'])}: {f['reason']}")
    spread = {str(n): float(s) for n, s in zip(ds["band_name"].values, ds["registration_spread_px"].values)}
    summary = _store_summary(
        "register", ds, out,
        f"wrote {out} (reference band {reg['reference_band']}; {len(reg['captures'])} of {reg['registered_of']} "
        f"captures registered, {len(reg['fallbacks'])} fell back; spread px: "
        f"{', '.join(f'{n} {s:.2f}' for n, s in spread.items())}; {time.perf_counter() - t0:.1f} s)",
        reference_band=reg["reference_band"], registration_spread_px=spread)
    summary.counts.update({"captures_registered": len(reg["captures"]), "captures_given": reg["registered_of"],
                           "fell_back": len(reg["fallbacks"]), "files_not_used": len(problems)})
    summary.emit()


@cli.command(short_help="Reflectance, indices and TIFFs of a flight's captures (Eq. 15).")
@writes("folder", "output folder")
@click.argument("flight", type=click.Path(path_type=Path))
@click.option("--calibration", "calibration", required=True,
              help="Calibration store (.zarr) from 'mscal calibrate', or 'factory' for cameras with factory metadata.")
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path), help="Output folder.")
@click.option("--normalise", default="relative", show_default=True,
              help="relative (Eq. 15 as is), band:<name or nm> (that band's median is 1 in every frame), "
                   "or panel (see --panel).")
@click.option("--panel", default=None, help="FRAME:x0,y0,x1,y1 region of known reflectance (band-grid pixels). "
              "With --calibration factory: the panel capture name(s), comma-separated (default: found among "
              "the folder's first and last captures).")
@click.option("--panel-reflectance", default=None, help="Reflectance of the panel: a number or a target name.")
@click.option("--reference", default="auto", show_default=True, type=click.Choice(["auto", "panel", "dls", "panel-dls"]),
              help="--calibration factory only: reflectance from panel captures, from the sun sensor (DLS, "
                   "tilt-corrected), or panel-dls (panels anchor the scale, the sensor the change); auto: "
                   "panel-dls when --panel-reflectance is given and the captures have sensor readings.")
@click.option("--camera", default=None, help="--calibration factory: the catalog camera (default: recognised from "
              "the files' Make/Model and XMP; see 'mscal cameras FOLDER').")
@click.option("--float32", "float32", is_flag=True, help="Photogrammetry TIFFs as float32 instead of uint16 x 32768.")
@click.option("--export-bands", default=None, help="Comma-separated band names for the per-frame TIFFs (default: the camera's).")
@click.option("--strict", is_flag=True, help="Exit non-zero if any frame was quarantined.")
@click.option("--illumination", type=ILLUMINATION_MODES, default=None,
              help="Light of each frame between several reflector captures (with --calibration factory: "
                   "panel captures): the nearest capture in time, or linear in time (irradiance readings, if "
                   "any, scale the brightness in both). Default: linear; with --calibration factory and "
                   "--reference panel, the panels' mean factor for every capture.")
@click.option("--no-align", "no_align", is_flag=True,
              help="Keep each band on its own pixel grid even if the calibration has band transforms ('mscal register'), "
                   "or (--calibration factory) the band files their own registration (DJI DewarpData, CalibratedHMatrix).")
@click.option("--registration", default=None, type=click.Path(path_type=Path),
              help="--calibration factory: align the bands with the transforms of this store ('mscal register').")
@click.option("--centre-bands", "centre_bands", is_flag=True,
              help="Snapshot mosaics: resample every band to the mosaic's centre position (sub-pixel band offsets).")
@click.option("--field-calibration", default=None, type=click.Path(path_type=Path),
              help="--calibration factory: take components of the radiance model from this field calibration "
                   "of the same camera ('mscal calibrate' / 'mscal fit') instead of the factory's.")
@click.option("--field-components", default=None,
              help="With --field-calibration: response and/or vignetting, comma-separated (default: those the "
                   "store holds). E.g. 'vignetting': field V (Eq. 8-10) with the factory response.")
@products_options
@execution_options
def apply(flight: Path, calibration: str, out: Path, normalise: str, panel: str | None, panel_reflectance: str | None,
          reference: str, camera: str | None, float32: bool, export_bands: str | None, strict: bool,
          illumination: str, no_align: bool, registration: Path | None, centre_bands: bool,
          field_calibration: Path | None, field_components: str | None, products: str | None, indices: str | None,
          tiffs: bool | None, scheduler: str, workers: int, direct_io: bool, keep_flagged: bool | None = None,
          shoulder_bound: float | None = None) -> None:
    """Reflectance, indices and photogrammetry TIFFs for a FLIGHT folder of captures (one file
    per capture, or one file per band: IMG_0000_1.tif ..., SD-card trees included): Eq. 15 with
    a calibration store, or with --calibration factory the band files' own metadata."""
    from mscal_core.errors import InputError

    from pipeline.apply.execution import Execution, flight_size_hint, start_worker_server
    from pipeline.ingest.products import cli_choice, resolve

    chosen = resolve(cli_choice(products, indices, tiffs, keep_flagged, shoulder_bound))  # bad ones fail first
    execution = Execution(scheduler=scheduler, workers=workers, direct_io=direct_io)
    start_worker_server(execution, flight_size_hint(flight))  # its imports run beside this process's

    from pipeline.apply.flight import apply_flight
    from pipeline.apply.options import ApplyOptions, PanelSpec

    bands = tuple(b.strip() for b in export_bands.split(",")) if export_bands else None
    if calibration == "factory":
        from pipeline.apply.factory import FactoryOptions, apply_factory

        if normalise != "relative":
            raise InputError("--normalise is for field calibrations; with --calibration factory use --reference")
        if centre_bands:
            raise InputError("--centre-bands is for snapshot mosaic cameras; --calibration factory is for "
                             "one-file-per-band cameras (align their bands with --registration)")
        if no_align and registration is not None:
            raise InputError("--no-align and --registration contradict each other", hint="give one of them")
        fopts = FactoryOptions(
            reference=reference, panel_captures=tuple(p.strip() for p in panel.split(",")) if panel else (),
            panel_reflectance=panel_reflectance, tiff_dtype="float32" if float32 else "uint16",
            export_bands=bands, strict=strict,
            registration=None if registration is None else str(registration), illumination=illumination,
            field_calibration=None if field_calibration is None else str(field_calibration),
            field_components=tuple(c.strip() for c in field_components.split(",") if c.strip())
            if field_components else (),
            execution=execution,
            camera=camera, align=not no_align, products=chosen,
        )
        stores = [p for p in (registration, field_calibration) if p is not None]
        _report_apply(apply_factory(flight, out, fopts), out, strict, stores)
        return
    if reference != "auto":
        raise InputError("--reference is for --calibration factory")
    if camera is not None:
        raise InputError("--camera is for --calibration factory; a calibration store names its camera")
    if field_calibration is not None or field_components is not None:
        raise InputError("--field-calibration/--field-components are for --calibration factory; "
                         "--calibration CALIB.zarr already uses every field fit")
    if registration is not None:
        raise InputError("--registration is for --calibration factory; a field calibration holds its own band "
                         "transforms ('mscal register CAPTURES -o CALIB.zarr')")
    if (panel is None) != (panel_reflectance is None):
        raise InputError("--panel and --panel-reflectance go together")
    spec = PanelSpec.parse(panel, panel_reflectance) if panel else None
    if spec is not None and normalise == "relative":
        normalise = "panel"
    opts = ApplyOptions(
        normalise=normalise, panel=spec, tiff_dtype="float32" if float32 else "uint16",
        export_bands=bands, strict=strict, illumination=illumination or "linear", align=not no_align,
        centre_bands=centre_bands, execution=execution, products=chosen,
    )
    _report_apply(apply_flight(flight, calibration, out, opts), out, strict, [Path(calibration)])


@cli.command(short_help="Which camera wrote a folder's captures and what it allows.")
@click.argument("folder", type=click.Path(path_type=Path))
@click.option("--camera", default=None, help="Catalog camera to read the folder as, instead of recognising it.")
def cameras(folder: Path, camera: str | None) -> None:
    """What camera wrote the captures in FOLDER (and its subfolders), how many captures and
    bands it holds, and which features (factory radiance, sun sensor, panel area, ...) its
    metadata allows."""
    from pipeline.ingest.identify import describe_folders

    lines = describe_folders(folder, camera)
    folders = [line[:-1] for line in lines if not line.startswith(" ")]
    if console().json:
        doc: dict[str, list[str]] = {}
        for line in lines:
            if not line.startswith(" "):
                key = line[:-1]
                doc[key] = []
            else:
                doc[key].append(line.strip())
        Summary("cameras", f"{len(folders)} folder(s) with images under {folder}", counts={"folders": len(folders)},
                details={"folders": doc}).emit()
        return
    for line in lines:
        click.echo(line)
    click.echo(f"{len(folders)} folder(s) with images under {folder}")


#: What an apply OUT folder holds (SPEC "Outputs of apply"), for the summary.
APPLY_OUTPUTS = {"reflectance": "reflectance.zarr", "raw DN": "raw.zarr", "photogrammetry TIFFs": "photogrammetry",
                 "NDVI": "ndvi", "run record": "run.json"}


def _report_apply(res: Any, out: Path, strict: bool, stores: list[Path]) -> None:
    """Notes on skipped and quarantined files (stderr), then the summary with the warnings
    report.html would show for this flight and the calibration stores it used."""
    skipped = run_value(res.run, "skipped") or []
    if skipped:
        note(f"skipped {len(skipped)} file(s) that are not captures: "
             f"{', '.join(s['file'] for s in skipped[:5])}{' ...' if len(skipped) > 5 else ''}")
    for q in res.quarantined:
        note(f"quarantined {q['file']}: {q['reason']}")
    state = "up to date" if res.up_to_date else f"{res.run['timings_s']['total']:.1f} s"
    # the store apply has read already, when it says so (0.07 s less than reading it again)
    first = res.calibration if res.calibration is not None else stores[0] if stores else None
    warnings = report_warnings(calibration=first, flights=[out])
    for extra in stores[1:]:
        warnings += report_warnings(calibration=extra)
    sat = res.run.get("saturated_pixels") or {}
    Summary("apply", f"wrote {out} ({res.run['frames_out']} frames, {len(res.quarantined)} quarantined; {state})",
            outputs={k: out / v for k, v in APPLY_OUTPUTS.items() if (out / v).exists()},
            counts={"frames_in": res.run.get("frames_in"), "frames_out": res.run["frames_out"],
                    "quarantined": len(res.quarantined), "files_skipped": len(skipped),
                    "saturated_pixels": sat.get("total")},
            warnings=warnings, details={"up_to_date": res.up_to_date, "reference": run_value(res.run, "reference"),
                                        "products": res.run.get("products")}).emit()
    if strict and res.quarantined:
        raise SystemExit(3)


@cli.command(short_help="Index map of an orthomosaic as a Cloud Optimized GeoTIFF.")
@writes("file", "index map")
@click.argument("ortho", type=click.Path(path_type=Path))
@click.option("--index", "index_name", default="ndvi", show_default=True, help="Index name from catalogs/indices.")
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Index map (.tif, a Cloud Optimized GeoTIFF) to write.")
@click.option("--bands", default=None, help="Band numbers of the roles, e.g. red=3,nir=5 (default: from band descriptions).")
def index(ortho: Path, index_name: str, out: Path, bands: str | None) -> None:
    """Index map of a reflectance orthomosaic as a Cloud Optimized GeoTIFF."""
    from mscal_core.errors import InputError

    from pipeline.products.indexmap import georeferenced, index_map

    mapping = None
    if bands:
        try:
            mapping = {k.strip(): int(v) for k, v in (item.split("=") for item in bands.split(","))}
        except ValueError:
            raise InputError(f"--bands {bands!r} is not ROLE=NUMBER,...", hint="e.g. --bands red=3,nir=5") from None
    index_map(ortho, index_name, out, bands=mapping)
    geo = georeferenced(out)
    if not geo:
        note(f"{ortho} has no georeferencing (no CRS or geotransform): the index map has none either "
             "(fine for a single frame; an orthomosaic for GIS needs one)")
    Summary("index", f"wrote {out} ({index_name}{'' if geo else ', not georeferenced'})", outputs={"index map": out},
            details={"index": index_name, "georeferenced": geo}).emit()


@cli.command(short_help="Build or update the STAC catalog of every flight under ROOT.")
@click.argument("root", type=click.Path(path_type=Path))
@click.option("--project-level", type=int, default=None,
              help="Collections by the folder this many levels below ROOT (0: one collection named after ROOT; "
                   "default: as the catalog was built, else 0). mscal-project.yaml files override it.")
@click.option("--validate-only", is_flag=True, help="Only validate ROOT/catalog.json and everything it links to.")
def catalog(root: Path, project_level: int | None, validate_only: bool) -> None:
    """Build or update the STAC catalog ROOT/catalog.json of every flight under ROOT
    (one collection per project, one item per flight), validated offline."""
    from pipeline.products.stac import update_catalog, validate_catalog

    if validate_only:
        n = validate_catalog(root)
        Summary("catalog", f"{root / 'catalog.json'}: {n} STAC object(s) valid", outputs={"catalog": root / "catalog.json"},
                counts={"valid_objects": n}).emit()
        return
    s = update_catalog(root, project_level=project_level)
    for key in s["removed"]:
        note(f"removed {key} (its flight is gone)")
    Summary("catalog", f"wrote {s['catalog']} ({s['items']} item(s) in {len(s['collections'])} collection(s): "
            f"{len(s['added'])} added, {len(s['updated'])} updated, {s['unchanged']} unchanged, "
            f"{len(s['removed'])} removed)", outputs={"catalog": s["catalog"]},
            counts={"items": s["items"], "collections": len(s["collections"]), "added": len(s["added"]),
                    "updated": len(s["updated"]), "unchanged": s["unchanged"], "removed": len(s["removed"])}).emit()


@cli.command(short_help="Per-field statistics of an index over orthomosaics (a table).")
@click.argument("orthos", nargs=-1, type=click.Path(path_type=Path))
@click.option("--fields", "fields_path", required=True, type=click.Path(path_type=Path),
              help="GeoJSON of the fields (polygons; WGS 84 unless it names a CRS or --fields-crs is given).")
@click.option("--index", "index_name", default="ndvi", show_default=True, help="Index name from catalogs/indices.")
@click.option("--catalog", "catalog_path", default=None, type=click.Path(path_type=Path),
              help="An mscal catalog (ROOT or ROOT/catalog.json): every flight's index map or orthomosaic.")
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path),
              help="Table to write: OUT.parquet and OUT.csv.")
@click.option("--bands", default=None, help="Band numbers of the roles in the orthomosaics, e.g. red=3,nir=5.")
@click.option("--id-property", default=None, help="Feature property holding the field id (default: id, field_id, name, fid).")
@click.option("--fields-crs", default=None, help="CRS of the fields file when it names none and is not lon/lat.")
@click.option("--workers", type=int, default=None, help="Mosaics processed at once (default: one per core).")
@click.option("--plot", "plot", default=None, type=click.Path(path_type=Path),
              help="Also write a self-contained HTML page with each field's season plot.")
def stats(orthos: tuple[Path, ...], fields_path: Path, index_name: str, catalog_path: Path | None, out: Path,
          bands: str | None, id_property: str | None, fields_crs: str | None, workers: int | None,
          plot: Path | None) -> None:
    """Per-field statistics (mean, median, std, p10, p90, valid fraction) of an index over
    reflectance orthomosaics ORTHOS and/or the flights of a --catalog, as a tidy table."""
    from pipeline.products.indexmap import parse_bands_option
    from pipeline.products.zonal import mosaics_from_catalog, mosaics_from_files, read_fields, write_table, zonal_table

    fields = read_fields(fields_path, id_property=id_property, crs=fields_crs)
    mosaics = mosaics_from_files(orthos) if orthos else []
    if catalog_path is not None:
        skipped: list[str] = []
        mosaics += mosaics_from_catalog(catalog_path, index_name, skipped)
        if skipped:
            note(f"{len(skipped)} flight(s) of the catalog have no orthomosaic or {index_name} map, so no "
                 f"statistics: {', '.join(skipped[:10])}{' ...' if len(skipped) > 10 else ''}")
    t0 = time.perf_counter()
    df = zonal_table(fields, mosaics, index_name, bands=parse_bands_option(bands) if bands else None, workers=workers)
    pq, csv = write_table(df, out)
    not_ok = df[df["status"] != "ok"]
    for r in not_ok.itertuples():
        note(f"field {r.field_id}{' on ' + r.flight if r.flight else ''}: {r.status}")
    if plot is not None:
        from pipeline.products.report import write_season_report

        write_season_report(df, plot)
    Summary("stats", f"wrote {pq} and {csv} ({len(fields.fields)} field(s), {len(mosaics)} mosaic(s), {len(df)} row(s)"
            f"{f', {len(not_ok)} not ok' if len(not_ok) else ''}; {time.perf_counter() - t0:.1f} s)",
            outputs={"table (Parquet)": pq, "table (CSV)": csv, "season plots": plot},
            counts={"fields": len(fields.fields), "mosaics": len(mosaics), "rows": len(df), "rows_not_ok": len(not_ok)}
            ).emit()


#: Entry-point group through which ``flows`` registers the Prefect flows the commands run
#: (``pyproject.toml``); the command line never imports ``flows`` itself.
FLOW_GROUP = "mscal.flows"


def _flow(name: str):  # a Prefect flow
    """The flow registered as ``name`` in :data:`FLOW_GROUP`, loaded after Prefect's
    environment is set (runner.configure_prefect)."""
    from importlib.metadata import entry_points

    from pipeline.run.runner import configure_prefect

    found = [ep for ep in entry_points(group=FLOW_GROUP) if ep.name == name]
    if not found:
        raise click.ClickException(
            f"no flow {name!r} is registered in the entry-point group {FLOW_GROUP!r}: mscal is not installed "
            "as a package (run `make setup`, or `pip install -e .` in the checkout)")
    configure_prefect()
    # Prefect's console handler names each flow and task run; it stands back if root has one.
    logging.getLogger().handlers.clear()
    return found[0].load()


def _logged(out: Any, command: str):  # a context manager
    """Prefect's and Dask's records (and tracebacks) of the block into ``OUT/logs/<time>-<command>.log``,
    to the terminal too with -v (:func:`pipeline.run.logs.command_log`). Enter it after
    :func:`_flow` (importing Prefect installs its console handler, which is taken off here)."""
    from pipeline.run.logs import command_log
    from pipeline.run.runner import default_cache_dir, is_remote

    verbose = bool(click.get_current_context().find_root().params.get("verbose"))
    return command_log(default_cache_dir() if is_remote(str(out)) else out, command, verbose=verbose)


@cli.command(short_help="Calibrate a session and apply it to every flight (Prefect).")
@writes("folder", "output folder")
@click.argument("session")
@click.option("-o", "--output", "out", required=True, help="Output folder or fsspec URL (s3://bucket/prefix).")
@click.option("--response-method", type=RESPONSE_METHODS, default="forward", show_default=True,
              help=RESPONSE_METHOD_HELP)
@click.option("--normalise", default="relative", show_default=True, help="relative, or band:<name or nm>.")
@click.option("--dask-address", default=None,
              help="tcp://HOST:PORT of a running 'dask scheduler' (default: a local cluster for long flights).")
@click.option("--cache-dir", default=None, help="Calibration cache, and Prefect's home unless PREFECT_HOME is set "
                   "(default: $MSCAL_CACHE_DIR or ~/.cache/mscal).")
@click.option("--work-dir", default=None, help="Where remote (s3://) inputs and outputs are staged (default: a temporary folder).")
@click.option("--catalog-root", default=None,
              help="Local output root whose STAC catalog (ROOT/catalog.json) is updated after the run (default: OUT).")
@click.option("--illumination", type=ILLUMINATION_MODES, default="linear", show_default=True,
              help="Light of each frame between several reflector captures: nearest or linear in time.")
@products_options
@execution_options
def run(session: str, out: str, response_method: str, normalise: str, dask_address: str | None,
        cache_dir: str | None, work_dir: str | None, catalog_root: str | None,
        illumination: str, products: str | None, indices: str | None, tiffs: bool | None, scheduler: str,
        workers: int, direct_io: bool, keep_flagged: bool | None = None, shoulder_bound: float | None = None) -> None:
    """The whole post-flight flow on Prefect's embedded server. SESSION is a field session
    (session.yaml with response/, vignetting/, reflector/): calibrate it (cached by content) and
    apply it to every SESSION/flights/<name>. Or SESSION is a flight folder as it comes off the
    camera's card (no session.yaml needed): camera and serial from the files, one
    OUT/flights/<name>/ per flight (SET folder, or captures more than 30 min apart), factory
    radiometry or the field calibration of that serial, the light from the panel or sun sensor.
    SESSION and OUT may be s3:// URLs. --products, --indices, --tiffs/--no-tiffs apply to every
    flight, over session.yaml's products key (docs/products.md)."""
    from pipeline.ingest.products import cli_choice
    from pipeline.run.runner import check_run_inputs

    choice = cli_choice(products, indices, tiffs, keep_flagged, shoulder_bound)
    check_run_inputs(session, out, normalise=normalise, dask_address=dask_address, catalog_root=catalog_root,
                     illumination=illumination, cache_dir=cache_dir, products=choice)
    if cache_dir:
        os.environ["MSCAL_CACHE_DIR"] = cache_dir  # before Prefect starts: its home follows
    post_flight = _flow("post_flight")
    with _logged(out, "run") as log_file:
        record = post_flight(session=session, out=out, response_method=response_method, normalise=normalise,
                             dask_address=dask_address, cache_dir=cache_dir, work_dir=work_dir,
                             catalog_root=catalog_root, illumination=illumination, scheduler=scheduler,
                             workers=workers, direct_io=direct_io, products=choice)
    echo_run(record, log_file)


@cli.command(short_help="Process each complete session of an inbox on a cron schedule.")
@click.option("--inbox", "inbox_dir", required=True, type=click.Path(path_type=Path),
              help="Folder of session folders: field sessions, or flight folders as they come off a camera's card.")
@click.option("-o", "--output", "out_root", required=True, type=click.Path(path_type=Path),
              help="Outputs: OUT_ROOT/<session name>/, and the state file OUT_ROOT/.mscal-serve.json.")
@click.option("--cron", default="*/15 * * * *", show_default=True, help="When to look at the inbox (cron expression).")
@click.option("--settle-seconds", default=600.0, show_default=True, type=float,
              help="A session without a READY file is complete once nothing in it changed for this long.")
@click.option("--once", is_flag=True, help="Look at the inbox once and exit.")
@click.option("--response-method", type=RESPONSE_METHODS, default="forward", show_default=True,
              help=RESPONSE_METHOD_HELP)
@click.option("--dask-address", default=None, help="tcp://HOST:PORT of a running 'dask scheduler'.")
@products_options
def serve(inbox_dir: Path, out_root: Path, cron: str, settle_seconds: float, once: bool, response_method: str,
          dask_address: str | None, products: str | None, indices: str | None, tiffs: bool | None,
          keep_flagged: bool | None = None, shoulder_bound: float | None = None) -> None:
    """Process every complete session folder of an INBOX once, now and then on a cron schedule.

    A session folder is a field session or a flight folder as it comes off the camera's card (no
    session.yaml needed). Complete: a READY file, or nothing modified for --settle-seconds.
    Processed sessions are recorded in OUT_ROOT/.mscal-serve.json; a restart does not redo them.
    --products, --indices, --tiffs/--no-tiffs apply to every flight of every session, over each
    session.yaml's products key (docs/products.md)."""
    from datetime import datetime

    from pipeline.ingest.products import cli_choice
    from pipeline.run.inbox import next_time, pending_sessions

    choice = cli_choice(products, indices, tiffs, keep_flagged, shoulder_bound)  # bad ones fail before anything runs

    next_time(cron, datetime.now())  # a bad expression fails before anything runs
    pending_sessions(inbox_dir, out_root, settle_seconds)  # and so does a missing inbox
    process_inbox = _flow("process_inbox")
    while True:
        with _logged(out_root, "serve") as log_file:
            done = process_inbox(str(inbox_dir), str(out_root), settle_seconds=settle_seconds,
                                 response_method=response_method, dask_address=dask_address, products=choice)
        if all(s == "waiting" for s in done.values()):  # a look that processed nothing keeps no log
            Path(log_file).unlink(missing_ok=True)
        echo_serve(done, out_root)
        if once:
            return
        wake = next_time(cron, datetime.now())
        click.echo(f"next look at {inbox_dir}: {wake:%Y-%m-%d %H:%M}", err=True)
        time.sleep(max(0.0, (wake - datetime.now()).total_seconds()))


@cli.command(short_help="Self-contained HTML QA report of calibrations and flights.")
@writes("file", "report")
@click.option("--calibration", "calibration", default=None, type=click.Path(path_type=Path),
              help="Calibration store (.zarr) to report on; calibration.json is written beside the report.")
@click.option("--flight", "flights", multiple=True, type=click.Path(path_type=Path),
              help="An 'mscal apply' OUT folder (repeat for several flights).")
@click.option("-o", "--output", "out", required=True, type=click.Path(path_type=Path), help="HTML file to write.")
@click.option("--title", default=None, help="Page title (default: 'mscal QA report: CAMERA').")
@click.option("--stats", "stats_table", default=None, type=click.Path(path_type=Path),
              help="An 'mscal stats' table (.parquet or .csv): adds each field's season plot.")
def report(calibration: Path | None, flights: tuple[Path, ...], out: Path, title: str | None,
           stats_table: Path | None) -> None:
    """Self-contained HTML QA report (plots embedded, opens offline) of a calibration, flights
    and the season of each field."""
    from pipeline.products.report import write_report_sections

    t0 = time.perf_counter()
    _, sections = write_report_sections(out, calibration=calibration, flights=flights, title=title, stats=stats_table,
                                        progress=lambda n: progress(n, "report"))
    outputs = {"QA report": out, "calibration summary": out.parent / "calibration.json" if calibration else None}
    extra = f" and {outputs['calibration summary']}" if calibration is not None else ""
    Summary("report", f"wrote {out}{extra} ({out.stat().st_size / 1e6:.1f} MB; {time.perf_counter() - t0:.1f} s)",
            outputs=outputs, counts={"sections": len(sections), "figures": sum(len(s.figures) for s in sections)},
            warnings=[{"section": s.title, **asdict(w)} for s in sections for w in s.warnings]).emit()


@cli.command(short_help="Run the whole flow on a synthetic session and score it.")
@writes("folder", "demo folder")
@click.option("-o", "--output", "out", default=Path("demo-out"), show_default=True, type=click.Path(path_type=Path),
              help="Folder for the session, the outputs and evaluation.json.")
@click.option("--size", type=click.Choice(["small", "full"]), default="small", show_default=True,
              help="'full' is the paper-sized session (40 views, 14-frame sweep).")
@click.option("--seed", default=0, show_default=True, type=int, help="Seed of the synthetic session.")
def demo(out: Path, size: str, seed: int) -> None:
    """Synthesize a session with known truth (two flights), run the whole post-flight flow on
    it and compare the calibration with the truth."""
    from pipeline.run.demo import run_demo

    post_flight = _flow("post_flight")
    with _logged(out, "demo"):
        summary = run_demo(out, size=size, seed=seed, flow=post_flight)
    record = json.loads(Path(summary["run_json"]).read_text())
    errors = summary["errors_vs_truth"]
    Summary("demo", f"wrote {out} (demo session, {len(summary['flights'])} flight(s); calibration "
            f"{'reused from the cache' if summary['calibration_cached'] else 'fitted'})",
            outputs={"outputs": summary["outputs"], "session": summary["session"], "run record": summary["run_json"],
                     "report": summary.get("report"), "evaluation": out / "evaluation.json",
                     **{f"flight {k}": v for k, v in summary["flights"].items()},
                     **{f"error vs truth: {k}": (f"{v:.4g}" if isinstance(v, float) else v)
                        for k, v in errors.items() if not isinstance(v, (dict, list))}},
            counts={"flights": len(summary["flights"])}, warnings=run_warnings(out, record),
            details={"demo": summary}).emit()


def main(argv: list[str] | None = None) -> int:
    """Entry point: MscalError -> one line on stderr, exit 2."""
    try:
        cli.main(args=argv, prog_name="mscal", standalone_mode=False)
    except MscalError as exc:
        click.echo(f"mscal: error: {exc}" + (f" (log: {exc.log_file})" if exc.log_file else ""), err=True)
        return exc.exit_code
    except (click.exceptions.Abort, KeyboardInterrupt):  # Ctrl-C, e.g. of a long mscal serve
        click.echo("mscal: aborted", err=True)
        return 130
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except SystemExit as exc:
        return int(exc.code or 0)
    except OSError as exc:
        hint = _OS_HINTS.get(exc.errno or 0)
        if hint is None:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(f"mscal: error: {where}{exc.strerror or exc} ({hint})", err=True)
        return 2
    return 0


#: Errors of the machine rather than of mscal's input, reported in one line like an
#: MscalError. Outputs are written under temporary names and renamed, so what was complete
#: stays, and the same command run again resumes.
_OS_HINTS = {
    errno.ENOSPC: "the disk is full: free space, or give another -o, and run the same command again; "
                  "finished outputs are kept and the run resumes",
    errno.EDQUOT: "the disk quota is used up: free space and run the same command again; the run resumes",
    errno.EACCES: "no permission: check that you may write to the output folder and read the inputs",
    errno.EROFS: "the file system is read-only: give an output folder on a writable disk",
}


def script_main() -> None:
    """The ``mscal`` executable: :func:`main`, then exit with its status.

    Before the interpreter shuts down, every object is moved out of the garbage collector's
    reach (``gc.freeze``): its shutdown otherwise walks the ~1,600 modules' objects in
    several full collections, 0.3-0.4 s of CPU after ``mscal calibrate`` (a tenth of what is
    left of it once the fits are done). The exit handlers (logging, multiprocessing, zarr)
    still run and open files are still flushed; only reference cycles still alive at exit
    are not collected, and Python does not promise to finalise those anyway. Tests call
    :func:`main` in their own process instead, which stays as it was.
    """
    status = main()
    gc.freeze()
    sys.exit(status)


if __name__ == "__main__":
    script_main()
