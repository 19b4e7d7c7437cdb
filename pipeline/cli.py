"""The ``rsmb`` command line: thin wrappers, one library call per subcommand.

Exit codes: 0 success, 2 bad input (one line naming the file or parameter and
the problem), 1 anything else.
"""

import contextlib
import json
import logging
import os
import sys
from pathlib import Path

import click

from rsmb import ops
from rsmb.ops import RSMBError

from ._options import SYNTH_DEFAULTS as _S
from ._options import Number, _check_scheduler, _floats, bad_option, build_config, registration_options, \
    runtime_options, tile_option
from .archive._ledger import SETTLE

__all__ = ["main", "cli"]

log = logging.getLogger("rsmb")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors.")
@click.version_option(package_name="rsmb")
def cli(verbose, quiet):
    """Registration and change detection under rolling shutter and motion blur."""
    configure_output(logging.ERROR if quiet else (logging.DEBUG if verbose > 1 else logging.INFO))


def configure_output(level):
    """What the command's process prints on stderr, and a survey's products
    process's: rsmb's log lines from ``level`` on, no library warnings that
    say nothing to a user."""
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(message)s", stream=sys.stderr)
    log.setLevel(level)  # basicConfig configures once per process; the level holds per invocation
    logging.getLogger("distributed").setLevel(max(level, logging.WARNING))
    _quiet_library_warnings()


def _quiet_library_warnings():
    """PNG/JPEG/NPY inputs have no georeferencing by nature; rasterio's warning
    about it says nothing to a user.  Nor do numpy's all-NaN slice (rsmb
    handles NaN rows where it takes NaN medians and maxima) and zarr's note
    that consolidated metadata is not in the v3 specification (xarray reads
    it).  Warning filters set around a call are not thread-safe (a night's
    captures run in threads, and one capture's restored filters let
    another's warnings through), so these are silenced once here."""
    import warnings

    from rasterio.errors import NotGeoreferencedWarning

    warnings.filterwarnings("ignore", category=NotGeoreferencedWarning)
    warnings.filterwarnings("ignore", message="All-NaN slice encountered", category=RuntimeWarning)
    warnings.filterwarnings("ignore", message=".*[Cc]onsolidated metadata.*")


@cli.command()
@click.argument("reference", nargs=-1, required=True, type=click.Path(dir_okay=True))
@click.argument("distorted", type=click.Path(dir_okay=True))
@click.option("-o", "--output", required=True, type=click.Path(), help="Output zarr store.")
@registration_options
@tile_option("Core tile side, pixels (at least 32) [default: 1024 if the image holds 4 x 4 such tiles, else 512].")
@click.option("--overlap", type=click.IntRange(min=0), default=None,
              help="Tile halo, pixels. Default: the largest displacement the search range allows.")
@runtime_options
@click.option("--resume", is_flag=True,
              help="Continue an interrupted run: only missing tiles run (a finished run is left as it is).")
@click.option("--overwrite", is_flag=True, help="Replace an existing output store (and --geotiff files).")
@click.option("--geotiff", type=click.Path(file_okay=False), default=None,
              help="Also write the ground-frame masks and score as Cloud-Optimised GeoTIFFs into this directory "
                   "(change_mask_reference.tif, change_score_reference.tif, parallax_mask_reference.tif; "
                   "existing files need --overwrite).")
@click.option("--json", "as_json", is_flag=True, help="Print the run summary as JSON.")
def detect(reference, distorted, output, axes, half_width, step, slow_axes, search, shutter, solver, lambda_w,
           lambda_chi, threshold, min_area, no_layers, focal, tile_size, overlap, scheduler, workers, worker_timeout,
           resume, overwrite, geotiff, as_json):
    """Register DISTORTED against REFERENCE and write change masks to a zarr store.

    REFERENCE is one image, or, for a georeferenced capture, a reference set:
    several files, a folder of them, or a VRT (a mosaic: the first file with
    data wins).  Any raster GDAL opens is an input (GeoTIFF, COG, VRT, JPEG
    2000, PNG, JPEG ...), and .npy files and zarr arrays."""
    from .detection._detect import detect as run

    config = build_config(axes, half_width, step, search, shutter, solver, lambda_w, lambda_chi, threshold,
                          min_area, focal, tile_size, overlap, slow_axes=slow_axes, layers=not no_layers)
    summary = run(list(reference), distorted, output, config=config, scheduler=scheduler, workers=workers,
                  overwrite=overwrite, resume=resume, geotiff=geotiff, worker_timeout=worker_timeout)
    _print_summary(summary, as_json)


def _print_summary(summary, as_json):
    if as_json:
        click.echo(json.dumps(summary.as_dict(), indent=2))
        return
    gain = "n/a (no tile had data)" if summary.gain_min is None else \
        f"{summary.gain_min:.3f}..{summary.gain_max:.3f}"
    click.echo(f"{summary.output}: {summary.changed_pixels} changed px in {summary.components} "
               f"component(s), threshold {summary.threshold:.3f}, gain {gain}, "
               f"{summary.tiles[0]}x{summary.tiles[1]} tiles, "
               f"{summary.timings['total_s']:.1f} s ({summary.megapixels_per_s:.2f} MP/s)")


@cli.command()
@click.argument("out_dir", type=click.Path(file_okay=False))
@click.option("--size", default=",".join(map(str, _S["shape"])), show_default=True, help="H,W of the images.")
@click.option("--motion", type=click.Choice(sorted(ops.MOTIONS)), default=_S["motion"], show_default=True)
@click.option("--shutter", type=click.Choice(["rolling", "global"]), default=_S["shutter"], show_default=True)
@click.option("--exposure", type=Number(min=0), default=_S["exposure"], help="Row exposure in row periods (default H/16).")
@click.option("--scale", type=Number(), default=_S["scale"], show_default=True, help="Multiplies every motion amplitude.")
@click.option("--gain", default=str(_S["gain"]), show_default=True,
              help="Illumination gain, or LEFT,RIGHT for a gain varying across the columns.")
@click.option("--changes", type=click.IntRange(min=0), default=_S["changes"], show_default=True,
              help="Number of pasted objects.")
@click.option("--noise", type=Number(min=0), default=_S["noise"], show_default=True,
              help="Noise sigma, intensities in [0, 1].")
@click.option("--seed", type=int, default=_S["seed"], show_default=True)
@click.option("--format", "fmt", type=click.Choice(["png", "tif", "npy"]), default=_S["fmt"], show_default=True,
              help="png (16 bit), tif (GeoTIFF with a made-up UTM georeferencing) or npy (float32).")
@click.option("--overwrite", is_flag=True, help="Write into a non-empty directory.")
def synth(out_dir, size, motion, shutter, exposure, scale, gain, changes, noise, seed, fmt, overwrite):
    """Make a reference, a distorted capture and the truth in OUT_DIR."""
    from ._synth import synth as run

    shape = tuple(int(v) for v in _floats(size, "--size", minimum=32))
    if len(shape) != 2:
        raise bad_option("expected H,W", "--size")
    ref, dist = run(out_dir, shape=shape, motion=motion, shutter=shutter, exposure=exposure, scale=scale,
                    gain=_floats(gain, "--gain", positive=True), changes=changes, noise=noise, seed=seed, fmt=fmt,
                    overwrite=overwrite)
    click.echo(f"wrote {ref}, {dist} and the truth in {out_dir}/truth")


@cli.command()
@click.argument("store", type=click.Path(exists=False))
@click.argument("truth_dir", type=click.Path(exists=False))
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def evaluate(store, truth_dir, as_json):
    """Scores of a detect STORE against the truth of `rsmb synth`."""
    from ._evaluate import evaluate as run

    result = run(store, truth_dir)
    if as_json:
        click.echo(json.dumps(result.as_dict(), indent=2))
        return
    for key in ("changes", "changes_reference"):
        m = getattr(result, key)
        click.echo(f"{key:18s} F {m.f_measure:.3f}  precision {m.precision:.3f}  recall {m.recall:.3f}  "
                   f"PWC {m.pwc:.3f} %  IoU {m.iou:.3f}")
    for axis, m in result.trajectory.items():
        click.echo(f"trajectory {axis:7s} RMSE {m['rmse']:.3f}  max {m['max_abs']:.3f}")
    click.echo(f"gain               max relative error {result.gain['max_relative_error']:.4f}")
    if result.registration_rmse_255 is not None:
        click.echo(f"registration RMSE  {result.registration_rmse_255:.2f} (0..255, outside true changes)")


@cli.command()
@click.option("--sections", default="oracle,speed,real,yaw,parallax,intensity,realclip,scale,gain,survey,history,ledger,ground",
              show_default=True,
              help="Comma-separated sections to run.")
@click.option("--data", type=click.Path(file_okay=False), default="../shared/data", show_default=True,
              help="Directory of real images (aerial/, rolling_shutter/); missing parts are skipped.")
@click.option("--quick", is_flag=True, help="Small sizes: a smoke run in about a minute.")
@click.option("--sizes", default=None, help="Image sides of the scale section, e.g. 2048,4096,8192.")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="Local worker threads (default: one per core).")
@click.option("--tile-size", type=click.IntRange(min=32), default=None,
              help="Tile side of the scale section [default: detect's default and 512 px, side by side].")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None, help="Also write results here.")
def bench(sections, data, quick, sizes, workers, tile_size, json_path):
    """Measure accuracy against the cvxpy oracle, speed, memory and real captures."""
    from .bench._bench import SECTIONS, run_bench

    chosen = tuple(x.strip() for x in sections.split(",") if x.strip())
    unknown = [x for x in chosen if x not in SECTIONS]
    if unknown:
        raise bad_option(f"unknown sections {unknown}; expected some of {SECTIONS}", "--sections")
    size_list = tuple(int(v) for v in _floats(sizes, "--sizes", minimum=64)) if sizes else None
    results = run_bench(sections=chosen, data=data, quick=quick, sizes=size_list, workers=workers, tile=tile_size)
    if json_path:
        with open(json_path, "w") as fh:
            json.dump(results, fh, indent=2, default=str)


@cli.command()
@click.option("-o", "--output", "out_dir", default="rsmb-demo", show_default=True, type=click.Path(file_okay=False),
              help="Directory for the demo's inputs, store, GeoTIFFs and report.")
@click.option("--size", type=click.IntRange(min=256), default=2048, show_default=True,
              help="Side of the demo scene, pixels.")
@tile_option("Core tile side [default: detect's].")
@click.option("--scheduler", default="threads", show_default=True, callback=_check_scheduler,
              help="threads, processes, synchronous, a tcp:// address or a scheduler file.")
@click.option("--overwrite", is_flag=True, help="Replace a previous demo in the directory.")
def demo(out_dir, size, tile_size, scheduler, overwrite):
    """The main job on an embedded default: synthesise, detect, evaluate, report."""
    from ._demo import run_demo

    result = run_demo(out_dir, size=size, tile=tile_size, scheduler=scheduler, overwrite=overwrite)
    s, m = result["summary"], result["scores"]
    click.echo(f"demo: {s.shape[0]} x {s.shape[1]} px in {s.timings['total_s']:.1f} s "
               f"({s.megapixels_per_s:.2f} MP/s); changes F {m.changes.f_measure:.3f}, "
               f"precision {m.changes.precision:.3f}, recall {m.changes.recall:.3f}; "
               f"per-tile gain error max {100 * m.gain['max_relative_error']:.2f} %")
    click.echo(f"store:  {result['store']}")
    click.echo(f"report: {result['report']}")


@cli.command()
@click.argument("store", type=click.Path(exists=False))
@click.option("-o", "--out-dir", type=click.Path(file_okay=False), default=None,
              help="Report directory. Default: STORE.report next to the store.")
@click.option("--max-pixels", type=click.IntRange(min=1), default=2048 * 2048, show_default=True,
              help="Most pixels of a downsampled mosaic figure (the overlay PNG holds at most this many).")
@click.option("--overwrite", is_flag=True, help="Write into an existing non-empty report directory.")
def report(store, out_dir, max_pixels, overwrite):
    """An HTML page with figures of one detect STORE: reference and capture side by side with the changes outlined,
    change overlay, trajectory, gain, tile agreement, score."""
    from .report._report import write_report

    index = write_report(store, out_dir, max_pixels=max_pixels, overwrite=overwrite)
    click.echo(f"wrote {index}")


def _check_captures(ctx, param, value):
    if value is not None and not value.strip():
        raise click.BadParameter(f"expected a glob of the night's captures, got {value!r}")
    return value


@cli.command()
@click.argument("references", nargs=-1, required=True, type=click.Path())
@click.option("--captures", required=True, callback=_check_captures,
              help="Glob of the night's captures ('**' recurses); quote it.")
@click.option("-o", "--output", "out_dir", required=True, type=click.Path(),
              help="The survey's folder: captures/<capture path>/ per capture, ledger.sqlite, nights/, index.html, the change "
                   "history changes.gpkg and the STAC catalog stac/. New, empty, "
                   "or the folder of earlier nights.")
@registration_options
@tile_option("Core tile side, pixels (at least 32) [default: 1024: captures run side by side, each in few tiles].")
@click.option("--overlap", type=click.IntRange(min=0), default=None,
              help="Tile halo, pixels. Default: the largest displacement the search range allows.")
@runtime_options
@click.option("--parallel", type=click.IntRange(min=1), default=None,
              help="Captures detected at once (their tasks share the scheduler's workers; each one's products "
                   "and report are written beside the next ones' detection) [default: cores + 1].")
@click.option("--settle", type=Number(min=0), default=SETTLE, show_default=True,
              help="Seconds: a capture modified less long ago is still being written and waits for the next night "
                   "(skipped, reason 'still being written').")
@click.option("--dry-run", is_flag=True, help="Say what would run and why (new, changed, retry, still being "
                                              "written, skip); write nothing.")
@click.option("--no-report", is_flag=True, help="Skip each capture's HTML report.")
@click.option("--json", "as_json", is_flag=True, help="Print the night's summary as JSON on stdout.")
@click.pass_context
def survey(ctx, references, captures, out_dir, axes, half_width, step, slow_axes, search, shutter, solver, lambda_w,
           lambda_chi, threshold, min_area, no_layers, focal, tile_size, overlap, scheduler, workers, worker_timeout,
           parallel, settle, dry_run, no_report, as_json):
    """A night of georeferenced captures (--captures GLOB) against REFERENCE files.

    Each capture gets a folder (captures/<its path>/) with its store,
    changes.gpkg, COGs, thumbnail and report; a capture done with the same
    inputs and parameters is skipped, one modified less than --settle seconds
    ago waits for the next night.  One night at a time per folder (a second
    exits 2).  Ctrl-C or SIGTERM stops the night, recording what finished
    (exit 130 or 143).
    Across nights: the change history (changes.gpkg: new, persisting, gone,
    unobserved), a STAC catalog (stac/) and a map on index.html.
    Exit code 3 when some captures failed (the rest finished), 2 for bad
    input (a captures folder that does not exist included)."""
    from .archive._survey import survey as run

    config = build_config(axes, half_width, step, search, shutter, solver, lambda_w, lambda_chi, threshold,
                          min_area, focal, tile_size, overlap, slow_axes=slow_axes, layers=not no_layers)
    _check_captures_glob(captures, references)
    with _stopped_by_signals() as stop:
        result = run(references, captures, out_dir, config=config, scheduler=scheduler, workers=workers,
                     parallel=parallel, dry_run=dry_run, worker_timeout=worker_timeout, report=not no_report,
                     settle=settle, stop=stop)
    if not result.captures:
        click.echo(f"rsmb: no capture matches {captures!r}: a night of 0 captures", err=True)
    if as_json:
        click.echo(json.dumps(result.as_dict(), indent=2))
    else:
        for c in result.captures:
            reason = c.reason.removeprefix(f"{c.capture}: ")  # an error names its file: the line does already
            detail = f" ({c.changes} changes)" if c.status == "done" else (f": {reason}" if reason else "")
            click.echo(f"{c.status:10s} {c.capture}{detail}")
        if dry_run:
            counts = {s: sum(c.status == f"would {s}" for c in result.captures) for s in ("run", "skip", "wait")}
            click.echo(f"dry run: {counts['run']} to run, {counts['skip']} to skip, {counts['wait']} still being "
                       f"written; nothing written")
        else:
            click.echo(f"{result.done} done, {result.skipped} skipped, {result.failed} failed"
                       + (f"; {result.index}" if result.index else ""))
    if result.interrupted:
        click.echo(f"rsmb: survey stopped by {stop.why}: finished captures recorded, the others run next night",
                   err=True)
        _exit_now(_interrupted_code(stop.signum))
    if result.failed:
        ctx.exit(3)


def _check_captures_glob(captures, references):
    """Refuse a ``--captures`` without a wildcard beside which REFERENCE files
    of its suffix lie: the shell expanded an unquoted glob, its first match
    became the captures and the others references (the night would redo or
    skip them)."""
    if any(c in captures for c in "*?["):
        return
    path = Path(captures).absolute()
    beside = [r for r in references if Path(r).absolute().parent == path.parent and os.path.isfile(r)
              and Path(r).suffix.lower() == path.suffix.lower()]
    if beside:
        raise click.BadParameter(
            f"{captures!r} has no wildcard and {len(beside)} REFERENCE file(s) lie beside it ({beside[0]}): "
            f"was an unquoted glob expanded by the shell? Quote it: --captures '{path.parent}/*{path.suffix}'",
            param_hint="'--captures'")


#: The signal that interrupted the command (SIGINT or SIGTERM), for its exit code.
_SIGNALLED = []


def _interrupted_code(signum):
    """130 after SIGINT, 143 after SIGTERM: 128 plus the signal's number."""
    import signal

    return 128 + int(signum or signal.SIGINT)


@contextlib.contextmanager
def _on_signals(handler):
    """``handler`` on SIGINT and SIGTERM meanwhile, the handlers before put
    back after.  Outside the main thread (a program calling :func:`main`
    from a thread) signals are left as they are."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, previous in saved.items():
            signal.signal(s, previous)


def _interrupt(signum, frame):
    """SIGINT and SIGTERM interrupt the command at once (KeyboardInterrupt: its
    cleanup runs, locks are released, partial outputs removed), the signal
    recorded for the exit code."""
    _SIGNALLED.append(signum)
    raise KeyboardInterrupt


@contextlib.contextmanager
def _stopped_by_signals():
    """A night's stop (pipeline.archive._survey._Stop) that SIGINT and SIGTERM
    set while a night listens for it (``stop.listening``, set by the survey
    while its night runs); a second signal, or one while no night listens (a
    workflow's other steps), interrupts at once (:func:`_interrupt`)."""
    import signal

    from .archive._survey import _Stop

    stop = _Stop()

    def handler(signum, frame):
        if stop.event.is_set() or not stop.listening:  # a second signal, or no night to stop in order: now
            _interrupt(signum, frame)
        _SIGNALLED.append(signum)
        stop.signum = signum
        stop.event.set()
        log.warning("survey: %s received: stopping (queued captures cancelled, running ones finish or are "
                    "abandoned within seconds)", signal.Signals(signum).name)

    with _on_signals(handler):
        yield stop


def _now(code):
    """``code``, returned when this thread is the only one; else the process
    exits with it at once, without waiting for the threads of the work it
    interrupted (a night's detections would hold the interpreter's exit)."""
    import threading

    if threading.active_count() > 1:
        sys.stdout.flush()
        sys.stderr.flush()
        logging.shutdown()
        os._exit(code)
    return code


def _exit_now(code):
    """Exit with ``code`` without waiting for the tasks an interrupted run
    abandoned (:func:`_now`)."""
    raise click.exceptions.Exit(_now(code))


@cli.command("run")
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--scheduler", default=None, callback=_check_scheduler, help="Override the workflow's scheduler.")
@click.option("--check", is_flag=True, help="Validate the workflow and its inputs, list the steps, run nothing.")
@click.pass_context
def run_command(ctx, workflow, scheduler, check):
    """Run a nightly WORKFLOW file (YAML): synth, detect, evaluate, report and survey steps.

    Exit code 3 when a step failed, a survey step included when some of its
    captures failed (the summary says which and why); 130 or 143 when
    stopped by Ctrl-C or SIGTERM (a survey step's night stops in order)."""
    from .workflow._workflow import check_inputs, load_workflow, run_workflow

    if check:
        flow = load_workflow(workflow)
        check_inputs(flow)
        for number, (kind, _) in enumerate(flow.steps, 1):
            click.echo(f"step {number} {kind}")
        click.echo(f"{flow.path}: valid, {len(flow.steps)} steps; summary would go to {flow.summary}")
        return
    with _stopped_by_signals() as stop:
        results = run_workflow(workflow, scheduler=scheduler, stop=stop)
    for step in results:
        why = f": {step['reason']}" if step["status"] in ("failed", "interrupted") else ""
        click.echo(f"step {step['step']} {step['kind']}: {step['status']} ({step['seconds']:.1f} s){why}")
    if stop.event.is_set():
        click.echo(f"rsmb: workflow stopped by {stop.why}: its survey recorded what finished; the summary says "
                   f"which steps ran", err=True)
        _exit_now(_interrupted_code(stop.signum))
    if any(step["status"] == "failed" for step in results):
        ctx.exit(3)


def _one_line(text):
    return " ".join(str(text).split())


def main(argv=None):
    """Entry point: runs the CLI and maps errors to exit codes (0 success, 2 bad
    input or option, 1 anything else), each error as one line on stderr."""
    from ._scheduler import configure_process

    configure_process()  # the rsmb command is its own process: its settings are rsmb's
    _SIGNALLED.clear()
    try:
        with _on_signals(_interrupt):
            code = cli.main(args=argv, prog_name="rsmb", standalone_mode=False)
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.ClickException as exc:  # bad options and arguments: click's own three lines made one
        click.echo(f"rsmb: error: {_one_line(exc.format_message())}", err=True)
        return 2 if isinstance(exc, click.UsageError) else exc.exit_code
    except (click.exceptions.Abort, KeyboardInterrupt):
        import signal

        log.debug("interrupted", exc_info=True)
        signum = _SIGNALLED[-1] if _SIGNALLED else signal.SIGINT  # Ctrl-C at a prompt: click's Abort
        click.echo(f"rsmb: interrupted by {signal.Signals(signum).name}", err=True)
        return _now(_interrupted_code(signum))
    except RSMBError as exc:  # bad input or option: 2; a run that could not go on (solver, workers): 1
        click.echo(f"rsmb: error: {_one_line(exc)}", err=True)
        return 2 if isinstance(exc, (ops.InputError, ops.ParameterError)) else 1
    except Exception as exc:  # noqa: BLE001 - the CLI's last resort
        log.debug("unexpected error", exc_info=True)
        click.echo(f"rsmb: unexpected error: {type(exc).__name__}: {_one_line(exc)} (rerun with -vv for the "
                   f"traceback)", err=True)
        return 1
    return code if isinstance(code, int) else 0  # a command's ctx.exit(n) comes back as n


if __name__ == "__main__":
    sys.exit(main())
