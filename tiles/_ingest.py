"""Ingest: an input image becomes zarr arrays laid out for one-chunk tile reads.

Two layouts, both float32 luminance with NaN for nodata:

- ``windows`` (the reference): array (tiles_y, tiles_x, Hw, Ww), one chunk per
  tile holding its core *and halo*, padded with NaN beyond the image.  A tile
  task reads exactly one chunk, whatever the halo; the price is storing the
  overlap twice (a factor ``((T + 2h) / T)^2`` on disk).
- ``plain`` (the distorted capture): array (H, W) chunked by tile; a tile task
  reads its core, one chunk (two to four for the longer edge tiles).

Every tile is read from the input with a windowed read and written by one task,
so neither step ever holds the whole image.
"""

from dataclasses import dataclass

import numpy as np

from ops import InputError

from ._io import read_window

__all__ = ["ingest_window", "ingest_core", "check_stats", "WindowStats"]


@dataclass(frozen=True)
class WindowStats:
    """Range of the valid values of one ingested tile (to reject constant images)."""

    count: int
    low: float
    high: float

    def __add__(self, other):
        if self.count == 0:
            return other
        if other.count == 0:
            return self
        return WindowStats(self.count + other.count, min(self.low, other.low), max(self.high, other.high))


def _read_clipped(path, shape, rows, cols):
    """Window (rows, cols) of the image, NaN where nodata or beyond the image."""
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
    return WindowStats(int(values.size), float(values.min()), float(values.max()))


def ingest_window(path, shape, tile, array):
    """Write ``tile``'s window (core and halo) of the image at ``path`` into the
    ``windows`` layout ``array`` (tiles_y, tiles_x, Hw, Ww).

    Returns
    -------
    WindowStats
        Of the tile's core.
    """
    data = _read_clipped(path, shape, *tile.window)
    padded = np.full(array.shape[2:], np.nan, dtype=np.float32)
    padded[:data.shape[0], :data.shape[1]] = data
    array[tile.index[0], tile.index[1]] = padded
    return _stats(data[tile.core_in_window])


def ingest_core(path, shape, tile, array):
    """Write ``tile``'s core of the image at ``path`` into the ``plain`` layout
    ``array`` (H, W).  Returns :class:`WindowStats` of the core."""
    data = _read_clipped(path, shape, *tile.core)
    array[tile.core] = data
    return _stats(data)


def check_stats(stats, path):
    """Raise :class:`ops.InputError` for an image without valid or varying pixels."""
    if stats.count == 0:
        raise InputError(f"{path}: has no valid pixel (all nodata or transparent)")
    if stats.low == stats.high:
        raise InputError(f"{path}: is constant (every valid pixel equals {stats.low:g})")
