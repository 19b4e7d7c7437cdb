"""``rsmb report``: an HTML page with figures describing one ``rsmb detect`` run.

The page (``index.html``) is self-contained apart from the figure files next
to it: no JavaScript, no network.  Figures (PNG; the photographs JPEG):

``before_after.jpg``
    The reference (before) and the capture (after) side by side, in colour
    where the inputs have it, from the previews the store keeps
    (:mod:`._previews`), the changes outlined on both.
``overlay.png``
    The change mask (red) and its outlines on the registered reference, tile
    grid drawn faintly; rendered pixel for pixel at the downsampled size, so
    the file never holds more than ``max_pixels`` pixels.
``trajectory.png``
    Per-row pose, one panel per axis: the fused path and each tile column's own;
    an axis that is zero on every row gets no panel, only a note (figure and
    caption).
``gain.png``, ``agreement.png``
    Per-tile maps with their values written in the cells (a store of more
    than one tile).
``change_score.png``
    The change score, downsampled by block maximum, one value per square of
    screen pixels, with a colorbar and the threshold marked.

The figures and the block reduction that keeps them small are
:mod:`._report_figures`, drawn with matplotlib in :mod:`._report_plots`; the
page is :mod:`._report_html`.
"""

import logging
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from rsmb import tiles
from rsmb.ops import InputError, ParameterError

from ._report_figures import FIGURES, block_reduce, downsample_factor, overlay_rgb, write_figures
from ._report_html import html_page

__all__ = ["DEFAULT_MAX_PIXELS", "FIGURES", "block_reduce", "downsample_factor", "overlay_rgb", "write_report"]

log = logging.getLogger("rsmb")

DEFAULT_MAX_PIXELS = 2048 * 2048
_REQUIRED = ("change_mask", "change_score", "registered", "trajectory", "gain")
# written by earlier versions: removed on overwrite, not left to look current
_OLD_FIGURES = ("trajectory.svg", "gain.svg", "agreement.svg")


# --------------------------------------------------------------------------- public


def write_report(store, out_dir=None, *, max_pixels=DEFAULT_MAX_PIXELS, overwrite=False):
    """Write an HTML report with figures of one ``rsmb detect`` output store.

    Parameters
    ----------
    store : str or path-like
        A finished output store of :func:`pipeline.detect`.
    out_dir : str or path-like, optional
        Directory to write ``index.html`` and the figures into; default
        ``<store>.report`` next to the store.
    max_pixels : int
        Most pixels of a downsampled mosaic: ``overlay.png`` holds at most this
        many; the score figure shows at most this many (and at most 1024 x 1024,
        one value per PNG pixel).
    overwrite : bool
        Write into an existing non-empty directory, replacing the report files.

    Returns
    -------
    Path
        The ``index.html`` written.

    Raises
    ------
    InputError
        If the store is missing or not a ``rsmb detect`` store, or ``out_dir``
        exists, is not empty and ``overwrite`` is false.
    ParameterError
        If ``max_pixels`` is not a positive integer.
    """
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, (int, np.integer)) or max_pixels < 1:
        raise ParameterError(f"max_pixels: expected a positive integer, got {max_pixels!r}")
    store = Path(store)
    group = tiles.open_result_store(store, required=_REQUIRED)
    attrs = group.attrs.asdict()
    out = _prepare_out_dir(store, out_dir, overwrite)
    shape = tuple(group["change_mask"].shape)
    factor = downsample_factor(shape, int(max_pixels))
    log.info("report %s: %d x %d px (width x height), downsampled by %d", out, shape[1], shape[0], factor)
    # drawn aside and moved in when complete: a report that fails (a damaged
    # store, a full disk) leaves the folder as it was, an earlier report included
    stage = _stage(out)
    try:
        figures, score_factor = write_figures(group, attrs, stage, factor)
        page = html_page(store, attrs, group, figures, factor, score_factor)
        (stage / "index.html").write_text(page, encoding="utf-8")
        if stage.parent == out:  # an existing folder: each file replaced, on the folder's own file system
            written = {path.name for path in stage.iterdir()}
            for name in written:
                os.replace(stage / name, out / name)
            for name in FIGURES + _OLD_FIGURES + ("index.html",):  # an earlier report's others
                if name not in written:
                    (out / name).unlink(missing_ok=True)
        else:
            os.replace(stage, out)  # a new folder, renamed into place whole
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return out / "index.html"


# --------------------------------------------------------------------------- checks and output directory


def _stage(out):
    """A new folder to draw the report ``out`` in: inside ``out`` when it
    exists (its files then move on that folder's file system, a mount or a
    link's target included), else beside it (then renamed to ``out``)."""
    parent = out if out.is_dir() else out.parent
    parent.mkdir(parents=True, exist_ok=True)
    stage = parent / f".{out.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.partial"
    stage.mkdir()
    return stage


def _prepare_out_dir(store, out_dir, overwrite):
    out = Path(out_dir) if out_dir is not None else store.with_name(store.name + ".report")
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: report directory exists and is a file")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise InputError(f"{out}: report directory exists and is not empty; pass --overwrite to replace it")
    tiles.check_writable(out / "index.html")
    return out
