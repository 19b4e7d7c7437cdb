"""The figures of ``rsmb report``, drawn from a detect store, and the block
reduction that keeps them small.

Large mosaics are reduced band by band straight from zarr (block mean for
images, block maximum for the mask and the score so that small changes stay
visible): one full-resolution array is never loaded whole.  The overlay is a
PNG composed pixel for pixel at the downsampled size; the other figures are
drawn with matplotlib (:mod:`._report_plots`).
"""

import math

import numpy as np

from rsmb.ops import ParameterError

FIGURES = ("before_after.jpg", "overlay.png", "trajectory.png", "gain.png", "agreement.png", "change_score.png")
_SCORE_SIDE = 1024  # the score figure shows a value per screen pixel (or a square of them), at most this many a side
_TRAJECTORY_WIDTH = 1000  # px
_PANEL = 520  # px, the longer side of each picture of before_after.jpg: both side by side fit the page (1100 px)

# overlay colours, RGB in [0, 1]
_NAN_RGB = np.array([0.16, 0.18, 0.32])
_GRID_RGB = np.array([0.30, 0.85, 1.00])
_MASK_RGB = np.array([1.00, 0.10, 0.10])
_EDGE_RGB = np.array([1.00, 0.92, 0.15])
_GRID_ALPHA = 0.35
_MASK_ALPHA = 0.45



def write_figures(group, attrs, out, factor):
    """Write every figure of :data:`FIGURES` the store has data for.

    Parameters
    ----------
    group : zarr.Group
        A finished detect store.
    attrs : dict
        Its root attributes.
    out : pathlib.Path
        Directory to write the figures into.
    factor : int
        Downsampling factor of the overlay (pixels per PNG pixel on a side).

    Returns
    -------
    figures : dict
        File name -> ``{"size": (width, height)}`` in pixels, and for the
        trajectory ``"flat_axes"``, the labels of the pose axes that are zero
        on every row and have no panel; for the score ``"vmax"`` and
        ``"zoom"``.  ``before_after.jpg`` is missing for a store without input
        previews (written before they were kept), ``agreement.png`` when the
        store has no ``tile_agreement``, both it and ``gain.png`` for a store
        of one tile (its gain is in the summary; one tile agrees with itself).
    score_factor : int
        Downsampling factor of the score figure (at least ``factor``; the figure
        shows at most 1024 values a side).
    """
    from ._previews import read_preview

    figures = {}
    before, before_factor = read_preview(group, "preview_reference")
    after, after_factor = read_preview(group, "preview_capture")
    if before is not None and after is not None:
        figures["before_after.jpg"] = _write_before_after(group, before, after, after_factor,
                                                          out / "before_after.jpg")
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
    if how == "max":
        return _block_fmax(block, factor)
    cells = block.reshape(block.shape[0] // factor, factor, block.shape[1] // factor, factor)
    finite = np.isfinite(cells)
    total = np.where(finite, cells, 0.0).sum(axis=(1, 3), dtype=np.float64)
    count = finite.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).astype(np.float32)


def _block_fmax(block, factor):
    """NaN-ignoring maximum of each ``factor`` x ``factor`` block of ``block``
    (both sides multiples of ``factor``): the same values as ``np.fmax.reduce``
    over the blocks' axes, taken as ``fmax`` of the ``factor ** 2`` strided
    views, whole-array operations where a reduction over an axis of a few
    elements runs an inner loop per element (several times slower)."""
    out = block[::factor, ::factor].copy()
    for i in range(factor):
        for j in range(factor):
            if i or j:
                np.fmax(out, block[i::factor, j::factor], out=out)
    return out


def _grid_lines(edges, factor, size):
    """Inner tile edges (px) as indices into an axis downsampled by ``factor``."""
    return sorted({min(size - 1, int(e) // factor) for e in list(edges)[1:-1]})


# --------------------------------------------------------------------------- overlay


def overlay_rgb(gray, mask, row_lines=(), col_lines=()):
    """Compose the change overlay.

    Parameters
    ----------
    gray : ndarray, shape (h, w), or uint8 RGBA, shape (h, w, 4)
        Image, any range; NaN where unknown (drawn dark blue).  Or an input
        preview (:mod:`._previews`), drawn in its colours; alpha 0 unknown.
    mask : ndarray, shape (h, w)
        Nonzero where changed: filled red, outlined yellow; components of a
        few pixels also get a yellow ring.
    row_lines, col_lines : sequence of int
        Rows and columns of the faint tile grid.

    Returns
    -------
    ndarray, uint8, shape (h, w, 3)
    """
    if gray.ndim == 3:
        finite = gray[..., 3] > 0
        rgb = gray[..., :3].astype(np.float32) / np.float32(255.0)
    else:
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
    mask = block_reduce(_Changed(group["change_mask"]), factor, "max")
    gray = block_reduce(group["registered"], factor, "mean")
    h, w = gray.shape
    rgb = overlay_rgb(gray, mask, _grid_lines(grid["row_edges"], factor, h),
                      _grid_lines(grid["col_edges"], factor, w))
    return _write_png(rgb, path)


# --------------------------------------------------------------------------- PNG


def _write_png(rgb, path):
    """Write uint8 RGB pixels as a PNG with Pillow (its row filters keep a
    photo-like overlay a third smaller than :func:`._png.write_png` does);
    return the figure entry ``{"size": (w, h)}``."""
    from PIL import Image

    from ._png import PNG_LEVEL

    Image.fromarray(rgb, mode="RGB").save(path, compress_level=PNG_LEVEL)
    return {"size": (rgb.shape[1], rgb.shape[0])}


# --------------------------------------------------------------------------- before and after


def _write_before_after(group, before, after, factor, path):
    """``before_after.jpg``: the stored previews side by side, each at most
    :data:`_PANEL` px a side (block mean of whole preview pixels, drawn pixel
    for pixel: the page shows the figure at its size), each with the changes
    of its own grid outlined (``change_mask_reference`` on the reference,
    ``change_mask`` on the capture), block maxima at the panel's size so that
    no change is lost."""
    from . import _report_plots as plots  # matplotlib: imported when a report is drawn
    from ._previews import reduce_preview

    k = max(1, math.ceil(max(before.shape[:2]) / _PANEL))
    before, after = reduce_preview(before, k), reduce_preview(after, k)
    masks = []
    for image, name in ((before, "change_mask_reference"), (after, "change_mask")):
        mask = (block_reduce(_Changed(group[name]), factor * k, "max") if name in group
                else np.zeros(image.shape[:2]))
        masks.append(mask[:image.shape[0], :image.shape[1]])
    fig = plots.before_after_figure(before, after, masks[0], masks[1], factor=factor * k,
                                    zoom=max(1, _PANEL // max(before.shape[:2])),
                                    titles=("Reference (before)", "Capture (after)"))
    return plots.save(fig, path)


class _Changed:
    """A mask array read as 1 where changed, 0 elsewhere ("no evidence", 255, included)."""

    def __init__(self, array):
        self.array, self.shape, self.chunks = array, array.shape, getattr(array, "chunks", array.shape)

    def __getitem__(self, index):
        return np.asarray(self.array[index]) == 1


# --------------------------------------------------------------------------- trajectory


def _write_trajectory(group, attrs, path):
    """``trajectory.png``: one panel per pose axis that is not zero on every
    row; the others are named in a note under the panels (and returned as
    ``"flat_axes"``)."""
    from . import _report_plots as plots  # matplotlib: imported when a report is drawn

    traj = np.asarray(group["trajectory"][:], dtype=np.float64)
    per_tile = np.asarray(group["tile_trajectory"][:], dtype=np.float64) if "tile_trajectory" in group else None
    labels = _axis_labels(group, attrs, traj.shape[1])
    drawn, flat = flat_axes_split(traj, per_tile)
    fig = plots.trajectory_figure(np.arange(traj.shape[0], dtype=np.float64), traj[:, drawn],
                                  None if per_tile is None else per_tile[:, :, drawn], [labels[d] for d in drawn],
                                  boundaries=list(attrs["tile_grid"]["row_edges"][1:-1]),
                                  flat=[labels[d] for d in flat], width=_TRAJECTORY_WIDTH)
    return {**plots.save(fig, path), "flat_axes": [labels[d] for d in flat]}


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


# --------------------------------------------------------------------------- per-tile maps


def _write_gain(group, attrs, path):
    from . import _report_plots as plots  # matplotlib: imported when a report is drawn

    gain = np.asarray(group["gain"][:], dtype=np.float64)
    fig = plots.tile_map_figure(gain, cmap="cividis", title="Illumination gain per tile",
                                label="gain (capture / reference)", fmt=".4f")
    return plots.save(fig, path)


def _write_agreement(group, attrs, path):
    from . import _report_plots as plots  # matplotlib: imported when a report is drawn

    agree = np.asarray(group["tile_agreement"][:], dtype=np.float64)
    summary = attrs.get("summary", {})
    resolved = [tuple(t) for t in summary.get("resolved_tiles", [])]
    tolerance = (attrs.get("parameters") or {}).get("agreement")
    finite = agree[np.isfinite(agree)]
    top = max([float(finite.max()) if finite.size else 0.0] + ([1.2 * tolerance] if tolerance else []))
    fig = plots.tile_map_figure(agree, cmap="magma_r", lo=0.0, hi=max(top, 1e-3), title="Tile path vs fused path",
                                label="disagreement (px)", fmt=".2f", marked=resolved,
                                marked_label="re-solved around the other tiles' path",
                                line=(tolerance, f"tolerance {tolerance:g} px") if tolerance else None)
    return plots.save(fig, path)


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
    """``change_score.png``: the block-maximum score, each value a ``zoom`` x
    ``zoom`` square of screen pixels (``zoom`` > 1 when the map is small), a
    colorbar with the threshold.  Returns the figure entry with ``"vmax"`` and
    ``"zoom"``."""
    from . import _report_plots as plots  # matplotlib: imported when a report is drawn

    score = block_reduce(group["change_score"], factor, "max")
    threshold = (attrs.get("summary") or {}).get("threshold")
    zoom = max(1, min(512 // min(score.shape), _SCORE_SIDE // max(score.shape)))
    vmax = _score_vmax(score, threshold)
    fig = plots.score_figure(score, vmax=vmax, threshold=threshold, factor=factor, zoom=zoom)
    return {**plots.save(fig, path), "vmax": vmax, "zoom": zoom}
