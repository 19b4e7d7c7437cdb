"""The figures of ``rsmb report``: PNGs drawn from a detect store, and the block
reduction that keeps them small.

Large mosaics are reduced band by band straight from zarr (block mean for
images, block maximum for the mask and the score so that small changes stay
visible): one full-resolution array is never loaded whole.  The overlay is
rendered pixel for pixel at the downsampled size, and so is the score image
inside its matplotlib frame; the other figures are drawn with matplotlib's
object API (no pyplot, no global state) on fixed margins.
"""

import math

import numpy as np

from rsmb.ops import ParameterError

FIGURES = ("overlay.png", "trajectory.png", "gain.png", "agreement.png", "change_score.png")
_SCORE_SIDE = 1024  # the score figure shows a value per PNG pixel (or a square of them), at most this many a side

# overlay colours, RGB in [0, 1]
_NAN_RGB = np.array([0.16, 0.18, 0.32])
_GRID_RGB = np.array([0.30, 0.85, 1.00])
_MASK_RGB = np.array([1.00, 0.10, 0.10])
_EDGE_RGB = np.array([1.00, 0.92, 0.15])
_GRID_ALPHA = 0.35
_MASK_ALPHA = 0.45

_DPI = 100  # matplotlib figures: pixels per inch
# zlib level of every PNG: higher levels cost much more CPU on the photo-like overlay for a file hardly smaller
_PNG_LEVEL = 2


def write_figures(group, attrs, out, factor):
    """Write every figure of :data:`FIGURES` the store has data for.

    Parameters
    ----------
    group : zarr.Group
        A finished detect store.
    attrs : dict
        Its root attributes.
    out : pathlib.Path
        Directory to write the PNGs into.
    factor : int
        Downsampling factor of the overlay (pixels per PNG pixel on a side).

    Returns
    -------
    figures : dict
        File name -> ``{"size": (width, height)}`` in PNG pixels (and ``"vmax"``
        for the score figure, ``"flat_axes"``, the labels of the pose axes that
        are zero on every row and have no panel, for the trajectory); ``agreement.png`` is missing when the store has
        no ``tile_agreement``, both it and ``gain.png`` for a store of one tile
        (its gain is in the summary; one tile agrees with itself).
    score_factor : int
        Downsampling factor of the score figure (at least ``factor``; the figure
        shows at most 1024 values a side).
    """
    figures = {}
    figures["overlay.png"] = _write_overlay(group, attrs["tile_grid"], factor, out / "overlay.png")
    figures["trajectory.png"] = _write_trajectory(group, attrs, out / "trajectory.png")
    if list(attrs["tile_grid"]["tiles"]) != [1, 1]:  # one tile: its gain is in the summary, no agreement
        figures["gain.png"] = _write_gain(group, attrs, out / "gain.png")
        if "tile_agreement" in group:
            figures["agreement.png"] = _write_agreement(group, attrs, out / "agreement.png")
    shape = tuple(group["change_score"].shape)
    score_factor = max(factor, math.ceil(shape[0] / _SCORE_SIDE), math.ceil(shape[1] / _SCORE_SIDE))
    figures["change_score.png"] = _write_score(group, attrs, score_factor, out / "change_score.png")
    return figures, score_factor


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


# --------------------------------------------------------------------------- block reduction


def _reduce_band(block, factor, how):
    """Block-reduce a band whose row count is a multiple of ``factor`` except at the end."""
    if how not in ("mean", "max"):
        raise ParameterError(f"how: expected 'mean' or 'max', got {how!r}")
    if factor == 1:  # every block is one pixel
        return block
    rows, w = block.shape
    pr, pc = -rows % factor, -w % factor
    if pr or pc:
        block = np.pad(block, ((0, pr), (0, pc)), constant_values=np.nan)
    cells = block.reshape(block.shape[0] // factor, factor, block.shape[1] // factor, factor)
    if how == "max":
        return np.fmax.reduce(np.fmax.reduce(cells, axis=3), axis=1)
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
    rgb[_outlines(changed)] = _EDGE_RGB
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def _outlines(changed):
    """Pixels drawn in the outline colour: each change's edge and the rings
    around the tiny ones."""
    return _edges(changed) | _rings(changed)


def _edges(changed):
    """Changed pixels with a 4-neighbour unchanged or outside the image (the
    complement of a binary erosion by a cross, with shifted slices)."""
    inner = changed.copy()
    inner[1:] &= changed[:-1]
    inner[:-1] &= changed[1:]
    inner[:, 1:] &= changed[:, :-1]
    inner[:, :-1] &= changed[:, 1:]
    inner[[0, -1], :] = False
    inner[:, [0, -1]] = False
    return changed & ~inner


def _rings(changed, small=4, many=64):
    """A ring around every component of at most ``small`` pixels, which would
    otherwise be a dot in a downsampled overlay: the one-pixel border of the
    component dilated twice, outside every change.

    The dilations run in a window around each tiny component (or over the whole
    image when there are more than ``many``); a ring lies within 3 px of its
    component, inside the window, and a window's edge only loses pixels."""
    from scipy import ndimage

    labels, count = ndimage.label(changed)
    if count == 0:
        return np.zeros_like(changed)
    area = np.bincount(labels.ravel(), minlength=count + 1)
    tiny = np.nonzero(area[1:] <= small)[0] + 1
    if tiny.size == 0:
        return np.zeros_like(changed)
    if tiny.size > many:
        inner = ndimage.binary_dilation(np.isin(labels, tiny), iterations=2)
        return ndimage.binary_dilation(inner) & ~inner & ~changed
    objects = ndimage.find_objects(labels)
    windows = [tuple(slice(max(0, s.start - 4), s.stop + 4) for s in objects[i - 1]) for i in tiny]
    inner = np.zeros_like(changed)
    for i, win in zip(tiny, windows):
        inner[win] |= ndimage.binary_dilation(labels[win] == i, iterations=2)
    ring = np.zeros_like(changed)
    for win in windows:
        ring[win] |= ndimage.binary_dilation(inner[win]) & ~inner[win] & ~changed[win]
    return ring


def _write_overlay(group, grid, factor, path):
    mask = block_reduce(group["change_mask"], factor, "max")
    gray = block_reduce(group["registered"], factor, "mean")
    h, w = gray.shape
    rgb = overlay_rgb(gray, mask, _grid_lines(grid["row_edges"], factor, h),
                      _grid_lines(grid["col_edges"], factor, w))
    return _write_png(rgb, path)


# --------------------------------------------------------------------------- matplotlib figures
#
# Figures are laid out with fixed margins in pixels, sized from the font (no
# constrained layout: its tight-bbox passes would cost more than the drawing),
# drawn once and written by pillow.


def _font_px():
    """Height of the default font, figure pixels."""
    from matplotlib import rcParams

    return rcParams["font.size"] * _DPI / 72.0


def _figure(width, height):
    """A figure of ``width`` x ``height`` pixels on an Agg canvas, no layout engine."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width / _DPI, height / _DPI), dpi=_DPI)
    FigureCanvasAgg(fig)
    return fig


def _add_axes(fig, left, top, width, height, **kwargs):
    """Axes whose box is ``width`` x ``height`` pixels at ``(left, top)`` pixels
    from the figure's top-left corner."""
    w, h = fig.canvas.get_width_height()
    return fig.add_axes((left / w, 1.0 - (top + height) / h, width / w, height / h), **kwargs)


def _render(fig):
    """Draw ``fig`` once and return its pixels, uint8 RGB, shape (height, width, 3).

    The figure is left to the garbage collector: ``fig.clear()`` would rebuild
    every axes' ticks only to drop them."""
    fig.canvas.draw()
    return np.array(np.asarray(fig.canvas.buffer_rgba())[..., :3])


def _write_png(rgb, path):
    """Write uint8 RGB pixels as a PNG (RGB, not matplotlib's RGBA: a quarter
    fewer bytes to compress); return the figure entry ``{"size": (w, h)}``."""
    from PIL import Image

    Image.fromarray(rgb, mode="RGB").save(path, compress_level=_PNG_LEVEL)
    return {"size": (rgb.shape[1], rgb.shape[0])}


def _save(fig, path):
    return _write_png(_render(fig), path)


# --------------------------------------------------------------------------- trajectory


def _write_trajectory(group, attrs, path):
    """One panel per pose axis that is not zero on every row; the others are
    named in a note under the panels (and returned as ``"flat_axes"``)."""
    traj = np.asarray(group["trajectory"][:], dtype=np.float64)
    per_tile = np.asarray(group["tile_trajectory"][:], dtype=np.float64) if "tile_trajectory" in group else None
    labels = _axis_labels(group, attrs, traj.shape[1])
    drawn, flat = flat_axes_split(traj, per_tile)
    fs = _font_px()
    left, right, top, gap, panel = 6.5 * fs, 1.5 * fs, 4.2 * fs, 0.9 * fs, 170
    bottom = 3.4 * fs + (1.6 * fs if flat else 0.0)
    width = 1000
    fig = _figure(width, round(top + len(drawn) * panel + (len(drawn) - 1) * gap + bottom))
    ncols = 0 if per_tile is None else per_tile.shape[1]
    colors = _tile_colors(ncols)
    rows = np.arange(traj.shape[0], dtype=np.float64)
    edges = list(attrs["tile_grid"]["row_edges"][1:-1])
    panels = []
    for i, d in enumerate(drawn):
        ax = _add_axes(fig, left, top + i * (panel + gap), width - left - right, panel,
                       sharex=panels[0] if panels else None)
        _trajectory_panel(ax, rows, traj[:, d], None if per_tile is None else per_tile[:, :, d], colors, edges)
        ax.set_ylabel(labels[d])
        ax.tick_params(labelbottom=i == len(drawn) - 1)
        panels.append(ax)
    panels[-1].set_xlabel("row (px); dashed: tile-row boundaries")
    fig.text(0.5, 1.0 - 0.4 * fs / fig.bbox.height, "Per-row camera pose (centroid)", ha="center", va="top",
             fontsize="large")
    _trajectory_legend(fig, colors, 2.0 * fs)
    if flat:
        names = ", ".join(labels[d] for d in flat)
        fig.text(left / width, 0.4 * fs / fig.bbox.height, f"Not drawn, zero on every row: {names}",
                 ha="left", va="bottom", fontsize="small")
    return {**_save(fig, path), "flat_axes": [labels[d] for d in flat]}


def flat_axes_split(traj, per_tile=None):
    """Pose axes worth a panel, and those that are zero on every row.

    Parameters
    ----------
    traj : ndarray, shape (H, D)
        Fused trajectory.
    per_tile : ndarray, shape (H, tiles_x, D), optional
        Each tile column's own trajectory; NaN (unsolved rows) is ignored.

    Returns
    -------
    drawn, flat : list of int
        Axis indices; ``flat`` holds the axes whose every finite value, fused
        and per tile, is zero (and that have one: an axis never solved is
        drawn, empty).  ``drawn`` is never empty: when every axis is
        flat, the first one is drawn.
    """
    values = traj if per_tile is None else np.concatenate([traj[:, None, :], per_tile], axis=1)
    values = values.reshape(-1, traj.shape[1])
    finite = np.isfinite(values)
    zero = [bool(finite[:, d].any() and np.all(values[finite[:, d], d] == 0.0)) for d in range(traj.shape[1])]
    drawn = [d for d in range(traj.shape[1]) if not zero[d]] or [0]
    return drawn, [d for d in range(traj.shape[1]) if d not in drawn]


def _axis_labels(group, attrs, count):
    """``"tx (px)"`` ... for every pose axis; ``"axis 5"`` for an unnamed one."""
    names = list(group["trajectory"].attrs.get("pose_axes", attrs.get("pose_axes", [])))
    units = list(group["trajectory"].attrs.get("units", attrs.get("pose_units", [""] * len(names))))
    labels = []
    for d in range(count):
        name = names[d] if d < len(names) else f"axis {d}"
        unit = units[d] if d < len(units) else ""
        labels.append(f"{name} ({unit})" if unit else name)
    return labels


def _trajectory_panel(ax, rows, fused, per_tile, colors, edges):
    """One axis: the tile columns' paths as one line collection, the fused path
    on top, tile-row boundaries dashed; limits set here, no autoscaling."""
    from matplotlib.collections import LineCollection
    from matplotlib.ticker import MaxNLocator

    if per_tile is not None and per_tile.shape[1]:
        segments = [np.column_stack([rows, per_tile[:, tx]]) for tx in range(per_tile.shape[1])]
        ax.add_collection(LineCollection(segments, colors=colors, linewidths=0.8,
                                         alpha=0.85 if len(colors) <= 10 else 0.5), autolim=False)
    ax.plot(rows, fused, color="black", lw=1.6, scalex=False, scaley=False)
    if edges:
        ax.vlines(edges, 0.0, 1.0, transform=ax.get_xaxis_transform(), colors="0.45", lw=0.8, linestyles="--")
    ax.set_xlim(rows[0], max(rows[-1], rows[0] + 1.0))
    ax.set_ylim(*_padded_range(fused if per_tile is None else np.concatenate([fused, per_tile.ravel()])))
    ax.yaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10]))  # 4 to 6 ticks: each is costly to draw
    ax.grid(True, color="0.9", lw=0.6)


def _padded_range(values):
    """Axis limits around the finite ``values`` with 5 % room (a flat or empty
    series gets a unit-wide range)."""
    finite = values[np.isfinite(values)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
    pad = 0.05 * (hi - lo) if hi > lo else max(0.5, 0.05 * abs(lo))
    return lo - pad, hi + pad


def _tile_colors(n):
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "viridis"]
    return [cmap(i if n <= 10 else i / max(n - 1, 1)) for i in range(n)]


def _trajectory_legend(fig, colors, top):
    """Fused first, then one entry per tile column (one for all beyond 8)."""
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color="black", lw=1.6)]
    labels = ["fused"]
    if len(colors) > 8:
        handles.append(Line2D([], [], color=colors[len(colors) // 2], lw=0.8))
        labels.append(f"tile columns 0..{len(colors) - 1}")
    else:
        handles += [Line2D([], [], color=c, lw=0.8) for c in colors]
        labels += [f"tile column {tx}" for tx in range(len(colors))]
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 1.0 - top / fig.bbox.height),
               ncol=len(handles), fontsize=9, frameon=False, borderaxespad=0.0)


# --------------------------------------------------------------------------- per-tile maps


def _tile_map(values, *, title, label, fmt, cmap, vmin=None, vmax=None, marked=(), marked_label=None,
              line=None):
    """Figure of a (tiles_y, tiles_x) map with its values written in the cells."""
    from matplotlib import colormaps
    from matplotlib.patches import Patch, Rectangle
    from matplotlib.ticker import ScalarFormatter

    ny, nx = values.shape
    fs = _font_px()
    width = round(_DPI * min(11.0, max(6.4, 0.95 * nx + 2.6)))
    height = round(_DPI * min(10.0, max(3.6, 0.8 * ny + 1.8)))
    legend = bool(marked and marked_label)
    left, top, bar_w, bar_room = 5.0 * fs, 2.4 * fs, 0.9 * fs, 7.5 * fs
    bottom = 3.4 * fs + (1.6 * fs if legend else 0.0)
    fig = _figure(width, height)
    ax = _add_axes(fig, left, top, width - left - bar_room - bar_w - 1.2 * fs, height - top - bottom)
    cax = _add_axes(fig, width - bar_room - bar_w, top, bar_w, height - top - bottom)
    image = ax.imshow(np.ma.masked_invalid(values), cmap=colormaps[cmap].with_extremes(bad="0.85"),
                      vmin=vmin, vmax=vmax, interpolation="nearest", aspect="auto")
    bar = fig.colorbar(image, cax=cax, label=label if line is None else f"{label}; line: {line[1]}")
    bar.formatter = ScalarFormatter(useOffset=False)
    bar.update_ticks()
    if line is not None:
        bar.ax.axhline(line[0], color="black", lw=2)
    _annotate_cells(ax, image, values, fmt)
    for ty, tx in marked:
        ax.add_patch(Rectangle((tx - 0.47, ty - 0.47), 0.94, 0.94, fill=False, ec="red", lw=2.5, ls="--"))
    if legend:
        fig.legend([Patch(fill=False, ec="red", lw=2, ls="--")], [marked_label], loc="lower center",
                   bbox_to_anchor=(0.5, 0.2 * fs / height), fontsize=9, frameon=False, borderaxespad=0.0)
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


# --------------------------------------------------------------------------- change score


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
    """The block-maximum score, one value per PNG pixel (a square of ``zoom``
    pixels when the map is small), coloured with numpy (matplotlib would
    resample it), in a matplotlib frame of axes, title and colorbar drawn
    around an empty box the image is pasted into."""
    score = block_reduce(group["change_score"], factor, "max")
    threshold = (attrs.get("summary") or {}).get("threshold")
    zoom = max(1, min(512 // min(score.shape), _SCORE_SIDE // max(score.shape)))
    vmax = _score_vmax(score, threshold)
    pixels = _score_rgba(score, vmax)[..., :3].repeat(zoom, axis=0).repeat(zoom, axis=1)
    h, w = pixels.shape[:2]
    fig, (left, top) = _score_frame(h, w, factor, zoom, vmax, threshold)
    rgb = _render(fig)
    rgb[top:top + h, left:left + w] = pixels
    return {**_write_png(rgb, path), "vmax": vmax}


def _score_frame(h, w, factor, zoom, vmax, threshold):
    """Figure with a transparent ``w`` x ``h`` px axes box (1 px inside its
    spines) in full-resolution pixel coordinates (a score value is ``factor``
    of them a side and ``zoom`` figure pixels), and the colorbar.

    Returns the figure and the box's top-left corner ``(left, top)``, pixels
    from the figure's top-left corner."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    fs = _font_px()
    left, top, bottom = round(5.5 * fs), round(2.4 * fs), round(3.4 * fs)
    bar_w, bar_room = round(1.4 * fs), round(7.0 * fs)
    bar_h = max(h + 2, round(29 * fs))  # room for the colorbar's label beside a short image
    width = max(left + w + 2 + round(1.6 * fs) + bar_w + bar_room, 640)
    height = top + max(h + 2 + bottom, bar_h + round(1.0 * fs))
    fig = _figure(width, height)
    ax = _add_axes(fig, left - 1, top - 1, w + 2, h + 2)
    ax.patch.set_visible(False)
    scale = factor / zoom  # full-resolution pixels per figure pixel
    ax.set_xlim(-0.5 - scale, w * scale - 0.5 + scale)
    ax.set_ylim(h * scale - 0.5 + scale, -0.5 - scale)
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    ax.set_title("Change score" + (f" (block maximum of {factor} x {factor} px)" if factor > 1 else ""))
    cax = _add_axes(fig, left + w + 2 + round(1.6 * fs), top - 1, bar_w, bar_h)
    label = "change score (intensity units)" + ("; cyan line: threshold" if threshold is not None else "")
    bar = fig.colorbar(ScalarMappable(Normalize(0.0, vmax), colormaps["inferno"]), cax=cax, label=label,
                       extend="max")
    if threshold is not None:
        bar.ax.axhline(threshold, color="cyan", lw=2)
    return fig, (left, top)


def _score_rgba(score, vmax):
    """``score`` coloured by inferno on [0, vmax], uint8 RGBA; NaN white (the
    page's background, as an unknown score was before)."""
    from matplotlib import colormaps

    with np.errstate(invalid="ignore"):
        return colormaps["inferno"].with_extremes(bad="white")(score / np.float32(vmax), bytes=True)
