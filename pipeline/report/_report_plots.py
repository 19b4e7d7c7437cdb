"""The plotted figures of ``rsmb report``, drawn with matplotlib.

Each ``*_figure`` function takes arrays and returns a
:class:`matplotlib.figure.Figure` (no pyplot, no global state: reports may be
written in threads at once); :func:`save` writes it as a PNG (or JPEG).  Figures:

* :func:`before_after_figure`: the reference (before) and the capture (after)
  side by side, the changes outlined on both;
* :func:`trajectory_figure`: one panel per pose axis, the fused path and each
  tile column's own;
* :func:`tile_map_figure`: a per-tile map (gain, agreement) with its values in
  the cells;
* :func:`score_figure`: the change score, one value per block of screen
  pixels, and a colorbar with the threshold.
"""

import numpy as np
from matplotlib import colormaps
from matplotlib.artist import Artist
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle
from matplotlib.ticker import ScalarFormatter

from ._png import write_png

__all__ = ["before_after_figure", "save", "score_figure", "tile_map_figure", "trajectory_figure"]

DPI = 100
JPEG_QUALITY = 90
OUTLINE = "#ff2bd6"  # change outlines on the photographs: magenta, rare in aerial scenes
THRESHOLD = "cyan"  # the threshold on the score's colorbar
_NAN_GRAY = "#d9d9d9"  # an unknown tile value
_SMALL = 9  # preview pixels: a change this small or smaller also gets a circle, not only its outline


def save(fig, path):
    """Write ``fig`` as a PNG (:func:`._png.write_png`), or a JPEG when ``path`` ends
    in ``.jpg`` (photographs: a quarter of the PNG's size, in a fraction of
    its time); returns the figure entry ``{"size": (w, h)}`` in pixels."""
    if str(path).endswith(".jpg"):
        fig.savefig(path, dpi=DPI, format="jpeg", pil_kwargs={"quality": JPEG_QUALITY})
    else:
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        canvas = FigureCanvasAgg(fig)
        canvas.draw()
        write_png(np.asarray(canvas.buffer_rgba()), path)
    width, height = fig.get_size_inches() * DPI
    return {"size": (int(round(width)), int(round(height)))}


class _Pixels(Artist):
    """An RGBA image drawn pixel for pixel into its axes' box, each value a
    ``zoom`` x ``zoom`` square of screen pixels: the renderer's own image
    blend, without the resampling ``imshow`` does at draw time (which, at
    whole screen pixels per value, gives the same pixels, for values of alpha
    0 or 255, for several times the work).  The axes' box must be the image's size in pixels
    (:func:`_axes_px` at whole pixels); drawn under the spines and lines."""

    def __init__(self, rgba, zoom=1):
        super().__init__()
        self.rgba, self.zoom = np.asarray(rgba, np.uint8), int(zoom)
        self.set_zorder(0)

    def get_array(self):
        """The values drawn, uint8 RGBA (h, w, 4), top row first."""
        return self.rgba

    def draw(self, renderer):
        if not self.get_visible():
            return
        pixels = self.rgba
        if self.zoom > 1:
            pixels = np.repeat(np.repeat(pixels, self.zoom, axis=0), self.zoom, axis=1)
        box = self.axes.bbox
        gc = renderer.new_gc()
        renderer.draw_image(gc, round(box.x0), round(box.y0), pixels[::-1])  # the renderer's rows run bottom up
        gc.restore()
        self.stale = False


def _draw_pixels(ax, rgba, extent, zoom):
    """``rgba`` drawn pixel for pixel (:class:`_Pixels`) in ``ax``, whose data
    limits become ``extent`` = (left, right, bottom, top) as ``imshow``'s."""
    ax.add_artist(_Pixels(rgba, zoom))
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])


def _px_figure(width, height):
    return Figure(figsize=(width / DPI, height / DPI), dpi=DPI)


def _axes_px(fig, left, bottom, width, height):
    """Axes placed in pixels from the figure's bottom left corner."""
    w, h = fig.get_size_inches() * DPI
    return fig.add_axes((left / w, bottom / h, width / w, height / h))


# --------------------------------------------------------------------------- before and after


def before_after_figure(before, after, before_mask, after_mask, *, titles, factor=1, zoom=1):
    """The two inputs side by side with the changes outlined.

    Parameters
    ----------
    before, after : ndarray, uint8, shape (h, w, 4)
        RGBA previews (alpha 0: no data, shown gray).
    before_mask, after_mask : ndarray, shape (h, w)
        Nonzero where changed, on each preview's grid.
    titles : pair of str
    factor : int
        Input pixels per preview pixel (the axes are in input pixels).
    zoom : int
        Screen pixels per preview pixel on a side: the previews are drawn
        pixel for pixel (``zoom`` 1) or enlarged without resampling.
    """
    h, w = before.shape[:2]
    panel, panel_h = w * zoom, h * zoom
    fig = _px_figure(2 * panel + 60, panel_h + 50)
    for k, (image, mask, title) in enumerate(((before, before_mask, titles[0]), (after, after_mask, titles[1]))):
        ax = _axes_px(fig, 20 + k * (panel + 20), 10, panel, panel_h)
        ax.set_facecolor("#808080")
        _draw_pixels(ax, image, (0, w * factor, h * factor, 0), zoom)
        _outline(ax, np.asarray(mask) > 0, factor)
        ax.set_title(title, fontsize=12)
        ax.set_xticks([])
        ax.set_yticks([])
    return fig


def _outline(ax, changed, factor):
    """Contours of the changes; a circle around those of at most :data:`_SMALL` pixels."""
    if not changed.any():
        return
    h, w = changed.shape
    centres = (np.arange(w) + 0.5) * factor, (np.arange(h) + 0.5) * factor
    padded = np.pad(changed.astype(np.float32), 1)  # changes on the border are closed too
    xs = np.concatenate([[0.0], centres[0], [w * factor]])
    ys = np.concatenate([[0.0], centres[1], [h * factor]])
    ax.contour(xs, ys, padded, levels=[0.5], colors=OUTLINE, linewidths=1.4)
    from skimage import measure

    small = [r.centroid for r in measure.regionprops(measure.label(changed, connectivity=1)) if r.area <= _SMALL]
    if small:
        cy, cx = np.array(small).T
        ax.scatter((cx + 0.5) * factor, (cy + 0.5) * factor, s=120, facecolors="none", edgecolors=OUTLINE,
                   linewidths=1.4)
    ax.set_xlim(0, w * factor)
    ax.set_ylim(h * factor, 0)


# --------------------------------------------------------------------------- trajectory

_TAB10 = colormaps["tab10"]


def tile_colors(n):
    """Colours of ``n`` tile columns: tab10, or viridis beyond 10."""
    if n <= 10:
        return [_TAB10(i) for i in range(n)]
    return list(colormaps["viridis"](np.linspace(0.0, 1.0, n)))


def trajectory_figure(rows, fused, per_tile, labels, *, boundaries=(), flat=(), width=1000):
    """Per-row pose, one panel per axis.

    Parameters
    ----------
    rows : ndarray, shape (H,)
    fused : ndarray, shape (H, D)
        The fused path of the axes drawn.
    per_tile : ndarray, shape (H, tiles_x, D) or None
        Each tile column's own path (NaN: unsolved rows, where its line breaks).
    labels : list of str
        ``"tx (px)"``... of the D axes drawn.
    boundaries : sequence of int
        Tile-row boundaries (dashed verticals).
    flat : sequence of str
        Axes not drawn (zero on every row), named in a note.
    """
    n = len(labels)
    panel_h, top, bottom = 170, 60, 70 + (20 if flat else 0)
    fig = _px_figure(width, top + bottom + n * panel_h)
    colors = tile_colors(0 if per_tile is None else per_tile.shape[1])
    axes = []
    for d, label in enumerate(labels):
        ax = _axes_px(fig, 90, bottom + (n - 1 - d) * panel_h + 8, width - 110, panel_h - 16)
        if axes:
            ax.sharex(axes[0])
        for tx, color in enumerate(colors):
            ax.plot(rows, per_tile[:, tx, d], color=color, linewidth=0.8)
        ax.plot(rows, fused[:, d], color="black", linewidth=1.6)
        for b in boundaries:
            ax.axvline(b, color="0.5", linewidth=0.8, linestyle="--")
        ax.set_ylabel(label)
        if len(rows) > 1:
            ax.set_xlim(rows[0], rows[-1])
        ax.grid(True, linewidth=0.3, alpha=0.5)
        if d < n - 1:
            ax.tick_params(labelbottom=False)
        axes.append(ax)
    axes[-1].set_xlabel("row (px); dashed: tile-row boundaries")
    handles = [Line2D([], [], color="black", linewidth=1.6, label="fused")]
    handles += [Line2D([], [], color=c, linewidth=0.8, label=f"tile column {i}") for i, c in enumerate(colors)]
    fig.legend(handles=handles, loc="upper center", ncols=min(len(handles), 6), frameon=False, fontsize=9)
    if flat:
        fig.text(0.01, 0.01, "Not drawn, zero on every row: " + ", ".join(flat), fontsize=9, color="0.3")
    return fig


# --------------------------------------------------------------------------- per-tile maps


def tile_map_figure(values, *, cmap, title, label, fmt, lo=None, hi=None, marked=(), marked_label=None, line=None):
    """A ``(tiles_y, tiles_x)`` map, each cell coloured and labelled with its value.

    ``lo``/``hi`` default to the finite values' range (widened around a single
    value); ``marked`` tiles (ty, tx) are outlined dashed red, named by
    ``marked_label``; ``line`` = (value, text) marks a value on the colorbar.
    """
    values = np.asarray(values, dtype=np.float64)
    ty, tx = values.shape
    finite = values[np.isfinite(values)]
    lo = (float(finite.min()) if finite.size else 0.0) if lo is None else lo
    hi = (float(finite.max()) if finite.size else 1.0) if hi is None else hi
    if hi <= lo:
        pad = max(1e-3 * abs(lo), 1e-6)
        lo, hi = lo - pad, hi + pad
    cell = int(np.clip(480 // max(tx, ty), 24, 130))  # a few tiles: tall enough for the colorbar label
    fig = _px_figure(tx * cell + 230, ty * cell + 110)
    ax = _axes_px(fig, 60, 50, tx * cell, ty * cell)
    image = ax.imshow(values, cmap=colormaps[cmap].with_extremes(bad=_NAN_GRAY), vmin=lo, vmax=hi,
                      interpolation="nearest")
    size = 11 if cell >= 60 else 8 if cell >= 40 else 6
    colours = image.to_rgba(np.ma.masked_invalid(values))
    for (i, j), v in np.ndenumerate(values):
        text = "n/a" if not np.isfinite(v) else format(v, fmt)
        dark = float(colours[i, j, :3] @ np.array([0.299, 0.587, 0.114])) < 0.5  # white text on dark cells
        ax.text(j, i, text, ha="center", va="center", fontsize=size, color="white" if dark else "black")
    for y, x in marked:
        ax.add_patch(Rectangle((x - 0.45, y - 0.45), 0.9, 0.9, fill=False, edgecolor="red", linestyle="--",
                               linewidth=2))
    if marked:
        ax.legend(handles=[Rectangle((0, 0), 1, 1, fill=False, edgecolor="red", linestyle="--",
                                     label=marked_label)], loc="upper left", bbox_to_anchor=(0, -0.08),
                  frameon=False, fontsize=9)
    ax.set_xticks(range(tx))
    ax.set_yticks(range(ty))
    ax.set_xlabel("tile column")
    ax.set_ylabel("tile row")
    ax.set_title(title)
    cax = _axes_px(fig, 60 + tx * cell + 20, 50, 18, ty * cell)
    bar = fig.colorbar(image, cax=cax, format=ScalarFormatter(useOffset=False))  # 1.0004, not 0.0004 + 1
    bar.set_label(label + (f"; line: {line[1]}" if line else ""))
    if line:  # black on a white halo: seen on dark and light colours
        cax.axhline(line[0], color="white", linewidth=4)
        cax.axhline(line[0], color="black", linewidth=2)
    return fig


# --------------------------------------------------------------------------- change score


def score_figure(score, *, vmax, threshold=None, factor=1, zoom=1):
    """The change score with a colorbar from 0 to ``vmax`` and the threshold on it.

    Parameters
    ----------
    score : ndarray, shape (h, w)
        The (block-maximum) score; NaN drawn white.  Coloured by inferno on
        ``[0, vmax]`` before it is drawn.
    vmax : float
    threshold : float, optional
        Marked in cyan on the colorbar.
    factor : int
        Image pixels per score value (the axes are in image pixels).
    zoom : int
        Screen pixels per score value on a side: each value is drawn as a
        ``zoom`` x ``zoom`` square, never resampled.
    """
    h, w = score.shape
    fig = _px_figure(w * zoom + 230, h * zoom + 100)
    ax = _axes_px(fig, 80, 60, w * zoom, h * zoom)
    cmap = colormaps["inferno"].with_extremes(bad="white")
    with np.errstate(invalid="ignore"):  # coloured here: a lookup, where imshow would normalise a masked copy
        rgba = cmap(score / np.float32(vmax), bytes=True)
    _draw_pixels(ax, rgba, (0, w * factor, h * factor, 0), zoom)
    image = ScalarMappable(norm=Normalize(0.0, vmax), cmap=cmap)
    ax.set_title("Change score")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    cax = _axes_px(fig, 80 + w * zoom + 20, 60, 18, h * zoom)
    bar = fig.colorbar(image, cax=cax)
    if threshold is not None:
        cax.axhline(threshold, color=THRESHOLD, linewidth=2)
        bar.set_label(f"score; cyan line: threshold {threshold:.4g}")
    else:
        bar.set_label("score")
    return fig
