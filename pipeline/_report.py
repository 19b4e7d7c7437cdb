"""``rsmb report``: an HTML page with PNG figures describing one ``rsmb detect`` run.

The page (``index.html``) is self-contained apart from the PNGs next to it: no
JavaScript, no network.  Figures:

``overlay.png``
    The change mask (red) and its outlines on the registered reference, tile
    grid drawn faintly; rendered pixel for pixel at the downsampled size, so
    the file never holds more than ``max_pixels`` pixels.
``trajectory.png``
    Per-row pose, one panel per axis: the fused path and each tile column's own.
``gain.png``, ``agreement.png``
    Per-tile maps with their values written in the cells.
``change_score.png``
    The change score, downsampled, with the threshold marked on the colorbar.

Large mosaics are reduced band by band straight from zarr (block mean for
images, block maximum for the mask and the score so that small changes stay
visible): one full-resolution array is never loaded whole.
"""

import datetime
import html
import json
import logging
import math
from pathlib import Path

import numpy as np

from rsmb import tiles
from rsmb.ops import InputError, ParameterError

__all__ = ["DEFAULT_MAX_PIXELS", "FIGURES", "block_reduce", "downsample_factor", "overlay_rgb", "write_report"]

log = logging.getLogger("rsmb")

DEFAULT_MAX_PIXELS = 2048 * 2048
_SCORE_PIXELS = 1024 * 1024  # the score figure shows about this many pixels; more would only be resampled
FIGURES = ("overlay.png", "trajectory.png", "gain.png", "agreement.png", "change_score.png")
_REQUIRED = ("change_mask", "change_score", "registered", "trajectory", "gain")
_STATES = {1: "solved", 2: "homogeneous", 3: "failed"}

# overlay colours, RGB in [0, 1]
_NAN_RGB = np.array([0.16, 0.18, 0.32])
_GRID_RGB = np.array([0.30, 0.85, 1.00])
_MASK_RGB = np.array([1.00, 0.10, 0.10])
_EDGE_RGB = np.array([1.00, 0.92, 0.15])
_GRID_ALPHA = 0.35
_MASK_ALPHA = 0.45


# --------------------------------------------------------------------------- public


def write_report(store, out_dir=None, *, max_pixels=DEFAULT_MAX_PIXELS, overwrite=False):
    """Write an HTML report with figures of one ``rsmb detect`` output store.

    Parameters
    ----------
    store : str or path-like
        A finished output store of :func:`pipeline.detect`.
    out_dir : str or path-like, optional
        Directory to write ``index.html`` and the PNGs into; default
        ``<store>.report`` next to the store.
    max_pixels : int
        Most pixels of a downsampled mosaic: ``overlay.png`` holds at most this
        many; the score figure shows at most this many (and at most 1024 x 1024,
        which is what its axes can display).
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
    group = tiles.open_result_store(store)
    attrs = group.attrs.asdict()
    _check_store(group, attrs, store)
    out = _prepare_out_dir(store, out_dir, overwrite)
    grid = attrs["tile_grid"]
    shape = tuple(group["change_mask"].shape)
    factor = downsample_factor(shape, int(max_pixels))
    log.info("report %s: %d x %d px, downsampled by %d", out, shape[0], shape[1], factor)

    figures = {}
    figures["overlay.png"] = _write_overlay(group, grid, factor, out / "overlay.png")
    figures["trajectory.png"] = _write_trajectory(group, attrs, out / "trajectory.png")
    figures["gain.png"] = _write_gain(group, attrs, out / "gain.png")
    if "tile_agreement" in group:
        figures["agreement.png"] = _write_agreement(group, attrs, out / "agreement.png")
    score_factor = max(factor, downsample_factor(shape, _SCORE_PIXELS))
    figures["change_score.png"] = _write_score(group, attrs, score_factor, out / "change_score.png")
    page = _html_page(store, attrs, group, figures, factor, score_factor)
    index = out / "index.html"
    index.write_text(page, encoding="utf-8")
    return index


def downsample_factor(shape, max_pixels):
    """Smallest integer factor ``f`` with ``ceil(H/f) * ceil(W/f) <= max_pixels``."""
    h, w = shape
    f = max(1, math.ceil(math.sqrt(h * w / max_pixels)))
    while math.ceil(h / f) * math.ceil(w / f) > max_pixels:
        f += 1
    return f


def block_reduce(array, factor, how="mean"):
    """Reduce a 2-D (zarr or numpy) array by ``factor`` in both axes, band by band.

    Parameters
    ----------
    array : zarr.Array or ndarray, shape (H, W)
    factor : int
        Block side, pixels; edge blocks are partial.
    how : {"mean", "max"}
        NaN-ignoring block mean or block maximum; an all-NaN block gives NaN.

    Returns
    -------
    ndarray, float32, shape (ceil(H / factor), ceil(W / factor))
    """
    h, w = array.shape
    oh, ow = -(-h // factor), -(-w // factor)
    out = np.empty((oh, ow), np.float32)
    chunk_rows = getattr(array, "chunks", (h,))[0]
    band = factor * max(1, chunk_rows // factor)
    for r0 in range(0, h, band):
        block = np.asarray(array[r0:r0 + band], dtype=np.float32)
        out[r0 // factor:(r0 + block.shape[0] + factor - 1) // factor] = _reduce_band(block, factor, how)
    return out


# --------------------------------------------------------------------------- checks and output directory


def _check_store(group, attrs, store):
    missing = [name for name in _REQUIRED if name not in group]
    if missing:
        raise InputError(f"{store}: not an rsmb detect store (array(s) {', '.join(missing)} missing)")
    if "tile_grid" not in attrs:
        raise InputError(f"{store}: not an rsmb detect store (no 'tile_grid' attribute)")


def _prepare_out_dir(store, out_dir, overwrite):
    out = Path(out_dir) if out_dir is not None else store.with_name(store.name + ".report")
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: report directory exists and is a file")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise InputError(f"{out}: report directory exists and is not empty; pass --overwrite to replace it")
    out.mkdir(parents=True, exist_ok=True)
    if overwrite:
        for name in FIGURES + ("index.html",):
            (out / name).unlink(missing_ok=True)
    return out


# --------------------------------------------------------------------------- downsampling


def _reduce_band(block, factor, how):
    """Block-reduce a band whose row count is a multiple of ``factor`` except at the end."""
    rows, w = block.shape
    pr, pc = -rows % factor, -w % factor
    if pr or pc:
        block = np.pad(block, ((0, pr), (0, pc)), constant_values=np.nan)
    cells = block.reshape(block.shape[0] // factor, factor, block.shape[1] // factor, factor)
    if how == "max":
        return np.fmax.reduce(np.fmax.reduce(cells, axis=3), axis=1)
    if how != "mean":
        raise ParameterError(f"how: expected 'mean' or 'max', got {how!r}")
    finite = np.isfinite(cells)
    total = np.where(finite, cells, 0.0).sum(axis=(1, 3), dtype=np.float64)
    count = finite.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).astype(np.float32)


def _grid_lines(edges, factor, size):
    """Inner tile edges (px) as indices into an axis downsampled by ``factor``."""
    return sorted({min(size - 1, int(e) // factor) for e in list(edges)[1:-1]})


# --------------------------------------------------------------------------- overlay


def overlay_rgb(gray, mask, row_lines=(), col_lines=()):
    """Compose the change overlay.

    Parameters
    ----------
    gray : ndarray, shape (h, w)
        Image, any range; NaN where unknown (drawn dark blue).
    mask : ndarray, shape (h, w)
        Nonzero where changed: filled red, outlined yellow; components of a
        few pixels also get a yellow ring.
    row_lines, col_lines : sequence of int
        Rows and columns of the faint tile grid.

    Returns
    -------
    ndarray, uint8, shape (h, w, 3)
    """
    from scipy import ndimage

    finite = np.isfinite(gray)
    lo, hi = np.percentile(gray[finite], [0.5, 99.5]) if finite.any() else (0.0, 1.0)
    g = np.clip((np.where(finite, gray, lo) - lo) / max(float(hi - lo), 1e-6), 0.0, 1.0).astype(np.float32)
    rgb = np.repeat(g[..., None], 3, axis=-1)
    del g
    rgb[~finite] = _NAN_RGB
    rows, cols = list(row_lines), list(col_lines)
    rgb[rows, :] = (1 - _GRID_ALPHA) * rgb[rows, :] + _GRID_ALPHA * _GRID_RGB
    rgb[:, cols] = (1 - _GRID_ALPHA) * rgb[:, cols] + _GRID_ALPHA * _GRID_RGB
    changed = np.asarray(mask) > 0
    rgb[changed] = (1 - _MASK_ALPHA) * rgb[changed] + _MASK_ALPHA * _MASK_RGB
    rgb[changed & ~ndimage.binary_erosion(changed, border_value=0)] = _EDGE_RGB
    rgb[_rings(changed)] = _EDGE_RGB
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def _rings(changed, small=4):
    """A ring around every component of at most ``small`` pixels, which would
    otherwise be a dot in a downsampled overlay."""
    from scipy import ndimage

    labels, count = ndimage.label(changed)
    if count == 0:
        return np.zeros_like(changed)
    area = np.bincount(labels.ravel(), minlength=count + 1)
    tiny = (area <= small)[labels] & changed
    if not tiny.any():
        return np.zeros_like(changed)
    inner = ndimage.binary_dilation(tiny, iterations=2)
    return ndimage.binary_dilation(inner) & ~inner & ~changed


def _write_overlay(group, grid, factor, path):
    from PIL import Image

    mask = block_reduce(group["change_mask"], factor, "max")
    gray = block_reduce(group["registered"], factor, "mean")
    h, w = gray.shape
    rgb = overlay_rgb(gray, mask, _grid_lines(grid["row_edges"], factor, h),
                      _grid_lines(grid["col_edges"], factor, w))
    Image.fromarray(rgb, mode="RGB").save(path, optimize=True)
    return {"size": (w, h)}


# --------------------------------------------------------------------------- matplotlib figures


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path):
    fig.savefig(path, dpi=100)
    fig.clear()
    w, h = fig.canvas.get_width_height()
    return {"size": (w, h)}


def _write_trajectory(group, attrs, path):
    traj = np.asarray(group["trajectory"][:], dtype=np.float64)
    axes = list(group["trajectory"].attrs.get("pose_axes", attrs.get("pose_axes", [])))
    units = list(group["trajectory"].attrs.get("units", attrs.get("pose_units", [""] * len(axes))))
    per_tile = np.asarray(group["tile_trajectory"][:], dtype=np.float64) if "tile_trajectory" in group else None
    rows = np.arange(traj.shape[0])
    edges = attrs["tile_grid"]["row_edges"][1:-1]
    fig = _figure((10.0, 0.6 + 2.1 * traj.shape[1]))
    panels = fig.subplots(traj.shape[1], 1, sharex=True, squeeze=False)[:, 0]
    colors = _tile_colors(0 if per_tile is None else per_tile.shape[1])
    for d, ax in enumerate(panels):
        for tx in range(0 if per_tile is None else per_tile.shape[1]):
            ax.plot(rows, per_tile[:, tx, d], color=colors[tx], lw=0.8, alpha=0.85 if len(colors) <= 10 else 0.5,
                    label=f"tile column {tx}")
        ax.plot(rows, traj[:, d], color="black", lw=1.6, label="fused")
        for e in edges:
            ax.axvline(e, color="0.45", lw=0.8, ls="--")
        name = axes[d] if d < len(axes) else f"axis {d}"
        unit = units[d] if d < len(units) else ""
        ax.set_ylabel(f"{name} ({unit})" if unit else name)
        ax.grid(True, color="0.9", lw=0.6)
        ax.margins(x=0)
    panels[-1].set_xlabel("row (px); dashed: tile-row boundaries")
    _trajectory_legend(fig, panels[0], per_tile)
    panels[0].set_title("Per-row camera pose (centroid)")
    return _save(fig, path)


def _tile_colors(n):
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "viridis"]
    return [cmap(i if n <= 10 else i / max(n - 1, 1)) for i in range(n)]


def _trajectory_legend(fig, ax, per_tile):
    handles, labels = ax.get_legend_handles_labels()
    handles, labels = handles[-1:] + handles[:-1], labels[-1:] + labels[:-1]  # fused first
    if per_tile is not None and per_tile.shape[1] > 8:  # one entry for all tile columns
        handles, labels = handles[:2], ["fused", f"tile columns 0..{per_tile.shape[1] - 1}"]
    fig.legend(handles, labels, loc="outside upper center", ncol=len(handles), fontsize=9, frameon=False)


def _tile_map(values, *, title, label, fmt, cmap, vmin=None, vmax=None, marked=(), marked_label=None,
              line=None):
    """Figure of a (tiles_y, tiles_x) map with its values written in the cells."""
    from matplotlib import colormaps
    from matplotlib.patches import Patch, Rectangle
    from matplotlib.ticker import ScalarFormatter

    ny, nx = values.shape
    fig = _figure((min(11.0, max(6.4, 0.95 * nx + 2.6)), min(10.0, max(3.6, 0.8 * ny + 1.8))))
    ax = fig.subplots()
    image = ax.imshow(np.ma.masked_invalid(values), cmap=colormaps[cmap].with_extremes(bad="0.85"),
                      vmin=vmin, vmax=vmax, interpolation="nearest", aspect="auto")
    bar = fig.colorbar(image, ax=ax, label=label if line is None else f"{label}; line: {line[1]}")
    bar.formatter = ScalarFormatter(useOffset=False)
    bar.update_ticks()
    if line is not None:
        bar.ax.axhline(line[0], color="black", lw=2)
    _annotate_cells(ax, image, values, fmt)
    for ty, tx in marked:
        ax.add_patch(Rectangle((tx - 0.47, ty - 0.47), 0.94, 0.94, fill=False, ec="red", lw=2.5, ls="--"))
    if marked and marked_label:
        fig.legend([Patch(fill=False, ec="red", lw=2, ls="--")], [marked_label], loc="outside lower center",
                   fontsize=9, frameon=False)
    ax.set_xticks(_ticks(nx))
    ax.set_yticks(_ticks(ny))
    ax.set_xlabel("tile column (tile_x)")
    ax.set_ylabel("tile row (tile_y)")
    ax.set_title(title)
    return fig


def _ticks(n):
    return list(range(0, n, max(1, math.ceil(n / 16))))


def _annotate_cells(ax, image, values, fmt):
    ny, nx = values.shape
    if ny * nx > 400:
        return
    size = 10 if ny * nx <= 36 else (8 if ny * nx <= 144 else 6)
    for ty in range(ny):
        for tx in range(nx):
            v = values[ty, tx]
            if not np.isfinite(v):
                ax.text(tx, ty, "n/a", ha="center", va="center", fontsize=size, color="0.3")
                continue
            r, g, b, _ = image.cmap(image.norm(v))
            color = "black" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "white"
            ax.text(tx, ty, format(float(v), fmt), ha="center", va="center", fontsize=size, color=color)


def _write_gain(group, attrs, path):
    gain = np.asarray(group["gain"][:], dtype=np.float64)
    fig = _tile_map(gain, title="Illumination gain per tile", label="gain (capture / reference)",
                    fmt=".4f", cmap="cividis")
    return _save(fig, path)


def _write_agreement(group, attrs, path):
    agree = np.asarray(group["tile_agreement"][:], dtype=np.float64)
    summary = attrs.get("summary", {})
    resolved = [tuple(t) for t in summary.get("resolved_tiles", [])]
    tolerance = (attrs.get("parameters") or {}).get("agreement")
    finite = agree[np.isfinite(agree)]
    top = max([float(finite.max()) if finite.size else 0.0] + ([1.2 * tolerance] if tolerance else []))
    fig = _tile_map(agree, title="Tile path vs fused path", label="disagreement (px)",
                    fmt=".2f", cmap="magma_r", vmin=0.0, vmax=max(top, 1e-3), marked=resolved,
                    marked_label="re-solved around the other tiles' path",
                    line=(tolerance, f"tolerance {tolerance:g} px") if tolerance else None)
    return _save(fig, path)


def _score_vmax(score, threshold):
    """Top of the colour scale: the 99th percentile of the scores above the
    threshold (changes are sparse, a plain percentile would be zero), at least
    twice the threshold."""
    finite = score[np.isfinite(score)]
    floor = 2.0 * threshold if threshold else 0.0
    above = finite[finite > (threshold or 0.0)]
    top = float(np.percentile(above, 99.0)) if above.size else (float(finite.max()) if finite.size else 1.0)
    return max(top, floor, 1e-6)


def _write_score(group, attrs, factor, path):
    score = block_reduce(group["change_score"], factor, "max")
    threshold = (attrs.get("summary") or {}).get("threshold")
    h, w = score.shape
    vmax = _score_vmax(score, threshold)
    fig = _figure((11.0, min(14.0, max(3.0, 9.4 * h / w + 0.9))))
    ax = fig.subplots()
    image = ax.imshow(score, cmap="inferno", vmin=0.0, vmax=vmax, interpolation="nearest",
                      extent=(-0.5, w * factor - 0.5, h * factor - 0.5, -0.5))
    label = "change score (intensity units)" + ("; cyan line: threshold" if threshold is not None else "")
    bar = fig.colorbar(image, ax=ax, label=label, extend="max")
    if threshold is not None:
        bar.ax.axhline(threshold, color="cyan", lw=2)
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.set_title("Change score" + (f" (block maximum of {factor} x {factor} px)" if factor > 1 else ""))
    return {**_save(fig, path), "vmax": vmax}


# --------------------------------------------------------------------------- HTML

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 2em auto;
       max-width: 1100px; padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { margin-top: 1.6em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.92em; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
th { background: #f4f4f4; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
code, .mono { font-family: ui-monospace, Menlo, Consolas, monospace; font-size: 0.9em; word-break: break-all; }
figure { margin: 1.2em 0 2em; } figcaption { font-size: 0.92em; color: #444; max-width: 900px; margin-top: 0.4em; }
img { max-width: 100%; height: auto; border: 1px solid #ccc; }
img.pixels { image-rendering: pixelated; }
.meta { color: #666; font-size: 0.9em; }
pre { white-space: pre-wrap; font-size: 0.8em; background: #f8f8f8; padding: 0.5em; }
"""

_SUMMARY_LABELS = {
    "shape": "image size (H, W), px",
    "tiles": "tiles (y, x)",
    "tile_size": "core tile side, px",
    "halo": "tile halo, px",
    "threshold": "change threshold (score units)",
    "changed_pixels": "changed pixels",
    "changed_fraction": "changed fraction",
    "components": "change components",
    "gain_min": "gain, smallest tile",
    "gain_max": "gain, largest tile",
    "resolved_tiles": "re-solved tiles (y, x)",
    "tile_agreement_px_max": "largest tile disagreement, px",
    "tasks_per_tile": "tasks per tile",
    "megapixels_per_s": "throughput, megapixels/s",
}


def _esc(value):
    return html.escape(str(value), quote=True)


def _fmt(value):
    """Short text of an attribute value."""
    if value is None:
        return "&ndash;"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return _esc(f"{value:.6g}") if value == value else "NaN"
    if isinstance(value, list) and value and all(isinstance(v, list) for v in value):
        return _esc(", ".join("(" + ", ".join(str(x) for x in v) + ")" for v in value))
    if isinstance(value, list):
        return _esc(", ".join(str(v) for v in value)) if value else "none"
    if isinstance(value, dict):
        return f"<code>{_esc(json.dumps(value, default=str))}</code>"
    return _esc(value)


def _table(rows, header=None, numeric=()):
    """HTML table from rows of already escaped cell text."""
    head = "<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in header) + "</tr>" if header else ""
    body = []
    for row in rows:
        cells = [f'<td class="num">{c}</td>' if i in numeric else f"<td>{c}</td>" for i, c in enumerate(row)]
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table>{head}{''.join(body)}</table>"


def _flatten(mapping, prefix=""):
    for key, value in mapping.items():
        if isinstance(value, dict) and value:
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _inputs_table(attrs):
    inputs = attrs.get("inputs") or {}
    rows = [[_esc(role), f"<code>{_esc(info.get('path', ''))}</code>", f"<code>{_esc(info.get('sha256', ''))}</code>"]
            for role, info in inputs.items()]
    return _table(rows, ["input", "path", "sha256"]) if rows else "<p>No input record in the store.</p>"


def _summary_table(summary):
    keys = [k for k in _SUMMARY_LABELS if k in summary]
    keys += [k for k in summary if k not in _SUMMARY_LABELS and k not in ("timings", "output")]
    rows = [[_esc(_SUMMARY_LABELS.get(k, k)), _fmt(summary[k])] for k in keys]
    return _table(rows, ["quantity", "value"], numeric=(1,))


def _timings_table(timings):
    rows = []
    for key, value in timings.items():
        label = key[:-2] + " (s)" if key.endswith("_s") else (key[:-6] + " (s, summed over tasks)"
                                                              if key.endswith("_s_sum") else key)
        text = f"{value:.3f}" if isinstance(value, float) else _fmt(value)
        rows.append([_esc(label.replace("_", " ")), text])
    return _table(rows, ["stage", "value"], numeric=(1,)) if rows else "<p>No timings recorded.</p>"


def _row_state_table(group):
    if "tile_row_state" not in group:
        return ""
    states = np.asarray(group["tile_row_state"][:])
    rows = []
    for tx in range(states.shape[1]):
        counts = [int((states[:, tx] == s).sum()) for s in _STATES]
        rows.append([str(tx)] + [str(c) for c in counts] + [str(int(states.shape[0] - sum(counts)))])
    header = ["tile column"] + list(_STATES.values()) + ["no tile rows"]
    return "<h3>Rows per tile column by solver state</h3>" + _table(rows, header, numeric=(1, 2, 3, 4))


def _geo_rows(attrs, prefix=""):
    keys = [k for k in attrs if k.startswith(("proj:", "spatial:")) or k in ("crs", "transform", "nodata")]
    rows = []
    for key in keys:
        value = attrs[key]
        if isinstance(value, str) and len(value) > 120:
            text = f"<details><summary>{_esc(value[:60])}&hellip;</summary><pre>{_esc(value)}</pre></details>"
        else:
            text = _fmt(value)
        rows.append((key, value, [f"<code>{_esc(prefix + key)}</code>", text]))
    return rows


def _geo_section(attrs):
    rows = _geo_rows(attrs) + _geo_rows(attrs.get("reference_georeferencing") or {}, "reference ")
    if not any(key != "nodata" and value is not None for key, value, _ in rows):
        return "<h2>Georeferencing</h2><p>The capture had no georeferencing (pixel coordinates only).</p>"
    return "<h2>Georeferencing</h2>" + _table([cells for _, _, cells in rows], ["attribute", "value"])


def _captions(attrs, factor, score_factor):
    s = attrs.get("summary") or {}
    tile = attrs["tile_grid"]["tile"]
    tol = (attrs.get("parameters") or {}).get("agreement")
    down = (f"Downsampled by {factor} (block mean of the image, block maximum of the mask, so that small changes "
            f"stay visible)." if factor > 1 else "Full resolution, one image pixel per PNG pixel.")
    overlay = (f"Detected changes (red fill, yellow outline, a ring around tiny ones; {s.get('changed_pixels', '?')} "
               f"px in {s.get('components', '?')} component(s)) on the registered reference, i.e. the reference "
               f"warped and blurred to match the capture (grayscale; dark blue where unknown). Faint cyan lines: "
               f"the {tile} px tile grid. {down}")
    agreement = ("How far each tile's path is from the fused one: RMS over rows of the largest displacement of the "
                 "row ends, px." + (f" Tolerance {tol:g} px (black line on the colorbar)." if tol else "")
                 + f" Dashed red outlines: tiles re-solved around the other tiles' path "
                   f"({len(s.get('resolved_tiles', []))}).")
    score = ("Magnitude of the change term."
             + (f" Threshold {s['threshold']:.4g} (cyan line on the colorbar)." if "threshold" in s else "")
             + (f" Block maximum over {score_factor} x {score_factor} px, so that small changes stay visible."
                if score_factor > 1 else ""))
    return {
        "overlay.png": overlay,
        "trajectory.png": "Per-row camera pose in global pose coordinates, one panel per axis. Black: the fused "
                          "trajectory (median over tiles of solved rows); thin coloured lines: each tile column's "
                          "own estimate; dashed verticals: tile-row boundaries.",
        "gain.png": "Illumination gain of the capture against the reference, one value per tile.",
        "agreement.png": agreement,
        "change_score.png": score,
    }


def _figures_html(figures, captions):
    parts = []
    for name in FIGURES:
        if name not in figures:
            parts.append(f"<p>{_esc(name)}: not available (the store has no data for it).</p>")
            continue
        w, h = figures[name]["size"]
        cls = ' class="pixels"' if name == "overlay.png" else ""
        parts.append(f'<figure id="{_esc(name[:-4])}"><a href="{_esc(name)}"><img src="{_esc(name)}"{cls} '
                     f'width="{w}" height="{h}" alt="{_esc(name)}"></a>'
                     f"<figcaption>{_esc(captions[name])}</figcaption></figure>")
    return "\n".join(parts)


def _html_page(store, attrs, group, figures, factor, score_factor):
    summary = attrs.get("summary") or {}
    params = attrs.get("parameters") or {}
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    meta = (f"Store <code>{_esc(store.resolve())}</code> &middot; rsmb {_esc(attrs.get('rsmb_version', '?'))} "
            f"&middot; scheduler {_esc(attrs.get('scheduler', '?'))} &middot; report written {now}")
    param_rows = [[f"<code>{_esc(k)}</code>", _fmt(v)] for k, v in _flatten(params)]
    sections = [
        f"<h1>rsmb report: {_esc(store.name)}</h1>", f'<p class="meta">{meta}</p>',
        "<h2>Inputs</h2>", _inputs_table(attrs),
        "<h2>Summary</h2>", _summary_table(summary), _row_state_table(group),
        "<h2>Figures</h2>", _figures_html(figures, _captions(attrs, factor, score_factor)),
        "<h2>Timings</h2>", _timings_table(summary.get("timings") or {}),
        "<h2>Parameters</h2>", _table(param_rows, ["parameter", "value"]),
        _geo_section(attrs),
    ]
    body = "\n".join(sections)
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
            f"<title>rsmb report: {_esc(store.name)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n{body}\n"
            f"</body>\n</html>\n")
