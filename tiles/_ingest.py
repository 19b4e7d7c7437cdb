"""Ingest: an input image becomes a zarr array chunked by tile.

Float32 luminance with NaN for nodata, one chunk per core tile, uncompressed
(the array is scratch: written once, read by the tile tasks, deleted).  Every
tile, or block of whole tiles, is read from the input with a windowed read and
written by one task, so no step holds the whole image.

A tile task reads its core plus halo with :func:`read_padded`, which touches
up to nine chunks.  Baking each tile's halo into a chunk of its own would
write and decode the image several times over when halos are large, to save
a few chunk reads per tile.
"""

from dataclasses import dataclass, field

import numpy as np

from rsmb.ops import InputError
from rsmb.ops import fill_zeros
from rsmb.ops._intensity import FILL_REACH, FILL_SQUARE

from ._io import read_window

__all__ = ["ingest_core", "CellSums", "cell_sums", "overview_from_sums", "read_clipped", "read_padded", "check_stats", "WindowStats"]


@dataclass(frozen=True)
class WindowStats:
    """The valid values of one ingested block: their count and range, how
    many sit at each end of the range, and a strided sample of them (every
    ``count // SAMPLE``-th value), which blocks add up to the image's."""

    count: int
    low: float
    high: float
    at_low: int = 0
    at_high: int = 0
    sample: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32), compare=False)

    def __add__(self, other):
        if self.count == 0:
            return other
        if other.count == 0:
            return self
        low, high = min(self.low, other.low), max(self.high, other.high)
        at_low = (self.at_low if self.low == low else 0) + (other.at_low if other.low == low else 0)
        at_high = (self.at_high if self.high == high else 0) + (other.at_high if other.high == high else 0)
        return WindowStats(self.count + other.count, low, high, at_low, at_high,
                           np.concatenate([self.sample, other.sample]))


#: Values each block keeps for the image's percentiles.
SAMPLE = 8192


def read_clipped(path, shape, rows, cols):
    """Window (rows, cols) of the image at ``path`` of ``shape`` (H, W), NaN
    where nodata or beyond the image."""
    out = np.full((rows.stop - rows.start, cols.stop - cols.start), np.nan, dtype=np.float32)
    r0, r1 = max(rows.start, 0), min(rows.stop, shape[0])
    c0, c1 = max(cols.start, 0), min(cols.stop, shape[1])
    if r1 > r0 and c1 > c0:
        data, valid = read_window(path, slice(r0, r1), slice(c0, c1))
        data = np.where(valid, data, np.nan).astype(np.float32)
        out[r0 - rows.start:r1 - rows.start, c0 - cols.start:c1 - cols.start] = data
    return out


def _stats(data):
    values = data[np.isfinite(data)]
    if values.size == 0:
        return WindowStats(0, np.inf, -np.inf)
    low, high = float(values.min()), float(values.max())
    return WindowStats(int(values.size), low, high, int((values == low).sum()), int((values == high).sum()),
                       values[::max(1, values.size // SAMPLE)].astype(np.float32))


def read_padded(array, rows, cols):
    """``array[rows, cols]`` of a 2-D array (zarr, :class:`ChunkFiles` or
    numpy), NaN where the window extends beyond the array."""
    out = np.full((rows.stop - rows.start, cols.stop - cols.start), np.nan, dtype=np.float32)
    r0, r1 = max(rows.start, 0), min(rows.stop, array.shape[0])
    c0, c1 = max(cols.start, 0), min(cols.stop, array.shape[1])
    if r1 > r0 and c1 > c0:
        out[r0 - rows.start:r1 - rows.start, c0 - cols.start:c1 - cols.start] = array[r0:r1, c0:c1]
    return out


def ingest_core(read, tile, array, offset=(0, 0), overview=None):
    """Write ``tile``'s core (a tile or a block of tiles) of ``array`` from
    ``read(rows, cols)`` (float32, NaN for nodata) of the source window at the
    core less ``offset`` (an array padded by a margin holds source pixel (r, c)
    at (r + margin, c + margin)).  Returns (:class:`WindowStats` of the core,
    its :func:`cell_sums` of the array's overview given ``overview``, a
    (factor, phase) pair, else None): the overview made from the values
    written, without reading them again."""
    rows, cols = tile.core
    m = FILL_SQUARE + FILL_REACH  # the margin that decides which zeros of the core are fill
    data = read(slice(rows.start - offset[0] - m, rows.stop - offset[0] + m),
                slice(cols.start - offset[1] - m, cols.stop - offset[1] + m))
    fill = fill_zeros(data)
    data = data[m:-m, m:-m]
    if fill.any():
        data = np.where(fill[m:-m, m:-m], np.float32(np.nan), data)
    array[tile.core] = data
    cells = None if overview is None else cell_sums(data, (rows.start, cols.start), *overview)
    return _stats(data), cells


#: A capture with fewer valid pixels than this share of its own has too
#: little data to register (a reference may cover less: it is read under the
#: capture's footprint).
MIN_VALID_SHARE = 0.01


def check_stats(stats, path, pixels=None):
    """Raise :class:`ops.InputError` for an image without valid or varying
    pixels, or (given its ``pixels``) with fewer valid ones than
    :data:`MIN_VALID_SHARE` of them."""
    if stats.count == 0:
        raise InputError(f"{path}: has no valid pixel (all nodata, NaN or transparent)")
    if pixels is not None and stats.count < MIN_VALID_SHARE * pixels:
        raise InputError(f"{path}: has too little valid data ({stats.count} valid pixels of {pixels}; "
                         f"at least {MIN_VALID_SHARE:.0%} needed)")
    if stats.low == stats.high:
        raise InputError(f"{path}: is constant (every valid pixel equals {stats.low:g})")


@dataclass(frozen=True)
class CellSums:
    """The part of an overview's cells (``factor`` x ``factor`` px, starting
    at rows and columns ``phase + j * factor`` of the array) that one window
    holds: per cell touched, from cell ``first`` (row, column) on, the float64
    sum of its values there (NaN where one is no-data) and their least and
    largest.  Windows that tile an array add up to its overview
    (:func:`overview_from_sums`)."""

    first: tuple
    sums: np.ndarray
    lows: np.ndarray
    highs: np.ndarray


def _reduce_cells(x, origin, factor, phase, axis, ufunc, dtype):
    """``ufunc`` reduced over the run of each cell along ``axis`` (0 or 1) of
    ``x``, whose index 0 is array index ``origin``: the part of a cell that
    starts before it, the whole cells (rows as one reshaped reduction,
    columns by strided slices, which stay fast for small factors), a tail.
    Returns (index of the first cell touched, reduced array of ``dtype``)."""
    def cut(a, b):
        return x[a:b] if axis == 0 else x[:, a:b]

    n = x.shape[axis]
    first = (origin - phase) // factor  # the cell holding index 0 (-1: before the array's first cell)
    head = min(phase + (first + 1) * factor - origin, n)  # x's indices in that cell
    whole = (n - head) // factor
    parts = [ufunc.reduce(cut(0, head), axis=axis, dtype=dtype, keepdims=True)] if first >= 0 else []
    if whole:
        part = cut(head, head + whole * factor)
        if axis == 0:
            parts.append(ufunc.reduce(part.reshape(whole, factor, -1), axis=1, dtype=dtype))
        else:
            out = part[:, 0::factor].astype(dtype)
            for k in range(1, factor):
                ufunc(out, part[:, k::factor], out=out)
            parts.append(out)
    if head + whole * factor < n:
        parts.append(ufunc.reduce(cut(head + whole * factor, n), axis=axis, dtype=dtype, keepdims=True))
    return max(first, 0), np.concatenate(parts, axis=axis)


def cell_sums(data, origin_yx, factor, phase=0):
    """The :class:`CellSums` of the window ``data`` (float32, NaN for no-data)
    at ``origin_yx`` (array rows, columns) of an array's overview."""
    data = np.asarray(data, dtype=np.float32)
    if factor == 1:
        return CellSums(tuple(origin_yx), data.astype(np.float64), data, data)
    out = []
    for ufunc, dtype in ((np.add, np.float64), (np.minimum, np.float32), (np.maximum, np.float32)):
        row, rows = _reduce_cells(data, origin_yx[0], factor, phase, 0, ufunc, dtype)
        col, cells = _reduce_cells(rows, origin_yx[1], factor, phase, 1, ufunc, dtype)
        out.append(cells)
    return CellSums((row, col), *out)


def overview_from_sums(parts, shape, factor, phase=0):
    """The whole cells of the overview of an array of ``shape`` from the
    :class:`CellSums` of windows that tile it: (sums float64, lows, highs)
    per cell, the cells of rows and columns ``phase + j * factor`` that end
    inside the array."""
    n = [max((s - phase) // factor, 0) for s in shape]
    sums = np.zeros(n, np.float64)
    lows = np.full(n, np.inf, np.float32)
    highs = np.full(n, -np.inf, np.float32)
    for part in parts:  # in the order given: the sums' bits depend on it
        (r, c), (h, w) = part.first, part.sums.shape
        h, w = min(h, n[0] - r), min(w, n[1] - c)  # cells beyond the array's last whole one dropped
        if h > 0 and w > 0:
            at = (slice(r, r + h), slice(c, c + w))
            sums[at] += part.sums[:h, :w]
            np.fmin(lows[at], part.lows[:h, :w], out=lows[at])
            np.fmax(highs[at], part.highs[:h, :w], out=highs[at])
    return sums, lows, highs
