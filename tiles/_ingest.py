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

__all__ = ["ingest_core", "block_overview", "overview_cells", "read_clipped", "read_padded", "check_stats", "WindowStats"]


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


def ingest_core(read, tile, array, offset=(0, 0)):
    """Write ``tile``'s core (a tile or a block of tiles) of ``array`` from
    ``read(rows, cols)`` (float32, NaN for nodata) of the source window at the
    core less ``offset`` (an array padded by a margin holds source pixel (r, c)
    at (r + margin, c + margin)).  Returns :class:`WindowStats` of the core."""
    rows, cols = tile.core
    m = FILL_SQUARE + FILL_REACH  # the margin that decides which zeros of the core are fill
    data = read(slice(rows.start - offset[0] - m, rows.stop - offset[0] + m),
                slice(cols.start - offset[1] - m, cols.stop - offset[1] + m))
    fill = fill_zeros(data)
    data = data[m:-m, m:-m]
    if fill.any():
        data = np.where(fill[m:-m, m:-m], np.float32(np.nan), data)
    array[tile.core] = data
    return _stats(data)


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


def overview_cells(data, origin_yx, factor, phase=0):
    """The mean of every ``factor`` x ``factor`` cell of an array's overview that
    lies inside the window ``data`` at ``origin_yx`` (array rows, columns):
    cells start at rows and columns ``phase + j * factor``.  Returns ((first
    cell row, col), cells float32 (n, m)), NaN where a cell holds nodata."""
    first = [-(-(o - phase) // factor) for o in origin_yx]  # ceil
    start = [phase + f * factor - o for f, o in zip(first, origin_yx)]
    count = [max((n - s) // factor, 0) for n, s in zip(data.shape, start)]
    part = np.asarray(data[start[0]:start[0] + count[0] * factor, start[1]:start[1] + count[1] * factor])
    cells = part.reshape(count[0], factor, count[1], factor).mean(axis=(1, 3), dtype=np.float64)
    return (first[0], first[1]), cells.astype(np.float32)


def block_overview(array, core, factor, phase=0):
    """The cells of ``array``'s overview (:func:`overview_cells`) that start in
    the block ``core`` (row and column slices): the block is read through the
    end of its last cell, the rows and columns of the cells that straddle its
    far edges (none when the cells end on its edges: no neighbouring chunk
    is read), so that blocks together give the overview of the whole array."""
    (r0, r1), (c0, c1) = [(s.start, s.stop) for s in core]
    ends = [phase + -(-(stop - phase) // factor) * factor for stop in (r1, c1)]  # of the last cell starting before stop
    data = array[r0:min(ends[0], array.shape[0]), c0:min(ends[1], array.shape[1])]
    (row, col), cells = overview_cells(data, (r0, c0), factor, phase)
    rows = max(0, min(cells.shape[0], -(-(r1 - phase) // factor) - row))
    cols = max(0, min(cells.shape[1], -(-(c1 - phase) // factor) - col))
    return (row, col), cells[:rows, :cols]
