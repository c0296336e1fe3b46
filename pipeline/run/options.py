"""Options shared by several ``mscal`` commands (:mod:`pipeline.run.cli`): how apply's pass
runs (:func:`execution_options`), which products it writes (:func:`products_options`), the
output guard (:func:`writes`) and deprecated spellings (:func:`deprecated_alias`)."""

from __future__ import annotations

from typing import Any

import click

RESPONSE_METHODS = click.Choice(["forward", "alternating"])
RESPONSE_METHOD_HELP = "'forward' fits the response with the noise on DN; 'alternating' is the paper's Eq. 6/7."
ILLUMINATION_MODES = click.Choice(["nearest", "linear"])  # mscal_core.illumination.INTERPOLATION_MODES
SCHEDULERS = click.Choice(["auto", "threads", "processes"])  # pipeline.apply.execution.SCHEDULERS


def execution_options(command: Any) -> Any:
    """``--scheduler``, ``--workers``, ``--direct-io/--no-direct-io`` of apply and run: how the
    per-frame pass runs (never what it computes), each defaulting to its environment variable."""
    command = click.option(
        "--direct-io/--no-direct-io", "direct_io", default=True, show_default=True, envvar="MSCAL_DIRECT_IO",
        show_envvar=True, help="Write outputs past the page cache (O_DIRECT) where the file system allows it.")(command)
    command = click.option(
        "--workers", type=click.IntRange(min=0), default=0, show_default=True, envvar="MSCAL_APPLY_WORKERS",
        show_envvar=True, help="Frames processed at once (0: one per core).")(command)
    return click.option(
        "--scheduler", type=SCHEDULERS, default="auto", show_default=True, envvar="MSCAL_APPLY_SCHEDULER",
        show_envvar=True, help="Threads, or worker processes (they take 1-2 s to start; every core busy); auto: "
                               "processes from 32 frames on.")(command)


def products_options(command: Any) -> Any:
    """``--products``, ``--indices``, ``--tiffs/--no-tiffs``, ``--keep-flagged``,
    ``--shoulder-bound`` of apply, run and serve: which outputs apply writes beyond raw.zarr and
    reflectance, and whether the pixels the quality mask flags keep their values
    (:mod:`pipeline.ingest.products`, docs/products.md). Each is None when not given: run and
    serve then take session.yaml's ``products`` key for it, else the default."""
    command = click.option(
        "--shoulder-bound", "shoulder_bound", type=float, default=None, metavar="REL",
        help="Relative uncertainty of the response U (the calibration's response_uncertainty) above which a DN "
             "is on the response's shoulder: flagged in reflectance.zarr/quality.  [default: 0.03]")(command)
    command = click.option(
        "--keep-flagged", "keep_flagged", is_flag=True, default=None,
        help="Keep the reflectance of pixels reflectance.zarr/quality flags (the response's shoulder, outside "
             "the sweep, vignetting unobserved, band not co-registered) instead of NaN; saturated pixels stay NaN.")(
        command)
    command = click.option(
        "--tiffs/--no-tiffs", "tiffs", default=None,
        help="Write the per-frame TIFFs (photogrammetry/, panels/, thermal/, ndvi/), or not: an analytics-only run "
             "writes the two stores and run.json.  [default: tiffs]")(command)
    command = click.option(
        "--indices", "indices", default=None, metavar="NAME,...",
        help="Indices of catalogs/indices besides NDVI (always made), comma-separated, e.g. ndre; 'none': NDVI only.")(
        command)
    return click.option(
        "--products", "products", default=None, metavar="NAME,...",
        help="Opt-in products, comma-separated: radiance (the factory radiance cube in reflectance.zarr; "
             "--calibration factory only); 'none': none.  [default: none]")(command)


def writes(kind: str, what: str):
    """Check the command's ``-o`` before any work and lock it while the command runs.

    Writable, never a file or folder mscal did not write (``pipeline.storage.outputs``);
    ``--wait`` waits for another process writing the same output instead of refusing (exit
    status 75). Remote (``s3://``) outputs are staged locally and uploaded: not checked here.
    """
    import functools

    def deco(f):
        @functools.wraps(f)
        def wrapper(*args: Any, wait: bool = False, **kwargs: Any) -> Any:
            out = kwargs.get("out")
            if out is None or "://" in str(out):
                return f(*args, **kwargs)
            from pipeline.storage.outputs import guarded_output

            with guarded_output(out, kind=kind, wait=wait, what=what):
                return f(*args, **kwargs)

        return click.option("--wait", is_flag=True, help="If another mscal process is writing the same output, "
                            "wait for it to finish instead of refusing.")(wrapper)

    return deco


def deprecated_alias(old: str, new: str, dest: str, type: Any = RESPONSE_METHODS) -> Any:
    """A hidden ``old`` spelling of option ``new`` that still works and says it is deprecated."""
    def warn(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
        if value is not None:
            click.echo(f"mscal: warning: {old} is deprecated, use {new}", err=True)
        return value

    return click.option(old, dest, default=None, hidden=True, callback=warn, expose_value=True,
                        type=type, help=f"Deprecated spelling of {new}.")
