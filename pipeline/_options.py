"""The options the ``rsmb`` commands share and how they are checked: numbers
per axis, the registration and change options of ``detect`` and ``survey``,
the runtime options, and the :class:`DetectConfig` they build.  A bad value is
a ``click.BadParameter`` naming its flag (exit 2, one line).

Defaults are not written here: :data:`METHOD_DEFAULTS` reads them off the
parameter dataclasses (:class:`ops.RegistrationParams`, :class:`ops.ChangeParams`,
:class:`DetectConfig`), in the options' own text form, and the workflow models
take theirs from it too, so a default changes in one place."""

import inspect

import click
import numpy as np

from rsmb import ops
from rsmb.ops.registration._params import SEARCH

from ._scheduler import WORKER_TIMEOUT
from .detection._plan import DetectConfig

__all__ = ["METHOD_DEFAULTS", "SYNTH_DEFAULTS", "build_config", "registration_options", "runtime_options", "tile_option"]


def _text(values):
    """Per-axis values as an option spells them: None is 'auto', one value
    stands for all axes when they agree."""
    words = ["auto" if v is None else f"{v:g}" for v in values]
    return words[0] if len(set(words)) == 1 else ",".join(words)


def _method_defaults():
    config = DetectConfig()
    reg, changes = config.registration, config.changes
    return {"axes": ",".join(reg.axes), "half_width": _text(reg.half_width), "step": _text(reg.step),
            "slow_axes": ",".join(reg.slow_axes) or "none", "search": None, "shutter": reg.shutter,
            "solver": reg.solver, "lambda_w": reg.lambda_w, "lambda_chi": reg.lambda_chi,
            "threshold": changes.threshold, "min_area": changes.min_area, "no_layers": not changes.layers,
            "focal": config.focal, "tile_size": config.tile, "overlap": config.overlap,
            "worker_timeout": WORKER_TIMEOUT}


#: option name (underscores) -> its default, as the command line spells it
METHOD_DEFAULTS = _method_defaults()
_D = METHOD_DEFAULTS


def _synth_defaults():
    from ._synth import synth

    return {name: p.default for name, p in inspect.signature(synth).parameters.items()
            if p.default is not inspect.Parameter.empty}


#: the keyword defaults of :func:`pipeline.synth`, which ``rsmb synth`` and a
#: workflow's synth step take as theirs
SYNTH_DEFAULTS = _synth_defaults()


def bad_option(message, option):
    """click's error for a bad value of ``option`` (``--name``), the option
    quoted as click quotes it in its own errors ("Invalid value for
    '--name': ...")."""
    return click.BadParameter(message, param_hint=f"'{option}'")


def _floats(text, name, count=None, allow_auto=False, minimum=None, positive=False):
    """Comma-separated numbers (``auto`` -> None when allowed), one per axis or
    one for all; each at least ``minimum`` (above 0 with ``positive``)."""
    values = []
    for token in text.split(","):
        token = token.strip()
        if allow_auto and token == "auto":
            values.append(None)
            continue
        try:
            value = float(token)
        except ValueError:
            raise bad_option(f"expected comma-separated numbers, got {text!r}", name) from None
        if not np.isfinite(value) or (positive and value <= 0) or (minimum is not None and value < minimum):
            bound = "> 0" if positive else f">= {minimum:g}"
            raise bad_option(f"expected numbers {bound}, got {token}", name)
        values.append(value)
    if count is not None and len(values) not in (1, count):
        raise bad_option(f"expected 1 or {count} values (one per axis), got {len(values)}", name)
    return tuple(values) if count is None or len(values) == count else tuple(values) * count


class Number(click.ParamType):
    """A finite number, optionally bounded below (``min`` inclusive, or
    exclusive with ``min_open``): click's FloatRange lets NaN through."""

    name = "number"

    def __init__(self, min=None, min_open=False):
        self.min, self.min_open = min, min_open

    def convert(self, value, param, ctx):
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"expected a number, got {value!r}", param, ctx)
        if not np.isfinite(number):
            self.fail(f"expected a finite number, got {value!r}", param, ctx)
        if self.min is not None and (number < self.min or (self.min_open and number == self.min)):
            self.fail(f"expected a number {'>' if self.min_open else '>='} {self.min:g}, got {value!r}", param, ctx)
        return number


def _check_threshold(ctx, param, value):
    try:
        ops.ChangeParams(threshold=value)
    except ops.ParameterError:
        raise click.BadParameter(f"expected 'noise', 'kapur' or a number > 0, got {value!r}") from None
    return value


def _check_scheduler(ctx, param, value):
    from ._scheduler import check_scheduler

    if value is not None:
        try:
            check_scheduler(value)
        except ops.ParameterError as exc:
            raise click.BadParameter(str(exc).split(": ", 1)[-1]) from None
    return value


def tile_option(help_text):
    return click.option("--tile-size", type=click.IntRange(min=32), default=_D["tile_size"], help=help_text)


def runtime_options(func):
    """Where and how a run executes (defined once for detect, demo and run)."""
    options = [
        click.option("--scheduler", default="threads", show_default=True, callback=_check_scheduler,
                     help="threads, processes, synchronous, a tcp:// address, a scheduler file, or slurm / "
                          "pbs (dask-jobqueue from dask's configuration; the cluster extra)."),
        click.option("--workers", type=click.IntRange(min=1), default=None,
                     help="Workers of a local scheduler (default: one per core), jobs of slurm/pbs."),
        click.option("--worker-timeout", type=Number(min=0, min_open=True), default=_D["worker_timeout"],
                     show_default=True,
                     help="Seconds a cluster run waits with no dask worker left before it fails (exit 1)."),
    ]
    for option in reversed(options):
        func = option(func)
    return func



def registration_options(func):
    """Options shared by commands that run the method (defined once)."""
    options = [
        click.option("--axes", default=_D["axes"], show_default=True,
                     help=f"Pose axes searched, from {','.join(ops.POSE_AXES)}."),
        click.option("--half-width", default=_D["half_width"], show_default=True,
                     help="Row neighbourhood half-width b per axis (px, 1 or deg), or 'auto': 3 steps "
                          "(tx,ty N(c,3,1) px as in the paper); widened automatically to the blur found in "
                          "the middle rows."),
        click.option("--step", default=_D["step"], show_default=True,
                     help="Grid step s per axis, or 'auto': 1 px for tx,ty; for rotations the angle that "
                          "moves the farthest pixel by 1 px (the paper's rz step 0.5 deg: --step 1,1,0.5)."),
        click.option("--slow-axes", default=_D["slow_axes"], show_default=True,
                     help="Out-of-plane rotations (camera pitch rx, yaw ry) estimated as a slow part of the path "
                          "on the whole capture before the rows, or 'none'."),
        click.option("--search", default=_D["search"],
                     help="Largest motion the initial wide search covers (+-) per axis. Default "
                          + ", ".join(f"{a} {SEARCH[a]:g} {ops.AXIS_UNITS[a]}" for a in SEARCH if SEARCH[a])
                          + "."),
        click.option("--shutter", type=click.Choice(["rolling", "global"]), default=_D["shutter"],
                     show_default=True, help="'global' solves one weight vector for every row (captures known to be GS)."),
        click.option("--solver", type=click.Choice(["fast", "exact"]), default=_D["solver"], show_default=True,
                     help="Row solver: the fast active-set solver or the exact cvxpy (CLARABEL) oracle "
                          "(seconds per row; small images only)."),
        click.option("--lambda-w", type=Number(min=0), default=_D["lambda_w"], show_default=True,
                     help="Weight of ||w||_1 in eq. 13 (intensities in [0, 1])."),
        click.option("--lambda-chi", type=Number(min=0, min_open=True), default=_D["lambda_chi"], show_default=True,
                     help="Weight of ||chi||_1 in eq. 13: the change term chi takes up residuals beyond half of it; the mask is decided by --threshold."),
        click.option("--threshold", default=_D["threshold"], show_default=True, callback=_check_threshold,
                     help="Change threshold: 'noise' (k robust sigmas of the residual), 'kapur' (the paper's "
                          "entropy threshold) or a number (score units, intensities in [0, 1])."),
        click.option("--min-area", type=click.IntRange(min=0), default=_D["min_area"], show_default=True,
                     help="Smallest change kept, pixels."),
        click.option("--no-layers", is_flag=True, default=_D["no_layers"],
                     help="Do not test candidate changes against depth layers (by default one that registers at "
                          "some relative depth is parallax, in parallax_mask, not change) and do not re-render "
                          "unexplained residual at the relative depth that explains it (a dense depth map, with the "
                          "rows' weights re-solved at those depths where it took depths widely)."),
        click.option("--focal", type=Number(min=0, min_open=True), default=_D["focal"],
                     help="Focal length in pixels of the whole image. Default 1.2 x the larger side."),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def build_config(axes, half_width, step, search, shutter, solver, lambda_w, lambda_chi, threshold, min_area,
                 focal, tile=None, overlap=None, *, slow_axes=_D["slow_axes"], layers=not _D["no_layers"]):
    """A :class:`pipeline.DetectConfig` from command-line values."""
    axes = tuple(a.strip() for a in axes.split(",") if a.strip())
    unknown = [a for a in axes if a not in ops.POSE_AXES]
    if unknown or not axes or len(set(axes)) != len(axes):
        raise bad_option(f"expected distinct names from {','.join(ops.POSE_AXES)}, got {','.join(axes) or 'none'}",
                         "--axes")
    reg = ops.RegistrationParams(
        axes=axes,
        half_width=_floats(half_width, "--half-width", len(axes), allow_auto=True, minimum=0),
        step=_floats(step, "--step", len(axes), allow_auto=True, positive=True),
        search=_floats(search, "--search", len(axes), minimum=0) if search else None,
        shutter=shutter, solver=solver, lambda_w=lambda_w, lambda_chi=lambda_chi,
        slow_axes=_slow_axes(slow_axes))
    changes = ops.ChangeParams(threshold=threshold, min_area=min_area, layers=layers)
    return DetectConfig(registration=reg, changes=changes, tile=tile, overlap=overlap, focal=focal)


def _slow_axes(text):
    """``--slow-axes``: names from rx, ry, or 'none'."""
    names = tuple(a.strip() for a in text.split(",") if a.strip())
    if names == ("none",):
        return ()
    if not names or any(a not in ("rx", "ry") for a in names) or len(set(names)) != len(names):
        raise bad_option(f"expected rx, ry, rx,ry or none, got {text!r}", "--slow-axes")
    return names
