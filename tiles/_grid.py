"""The tile grid: core tiles that cover an image once, each with a halo."""

from dataclasses import dataclass

import numpy as np

from rsmb.ops import ParameterError

__all__ = ["TileGrid", "Tile"]


@dataclass(frozen=True)
class Tile:
    """One tile of a :class:`TileGrid`.

    Attributes
    ----------
    index : tuple of int
        (tile row, tile column).
    core : tuple of slice
        Rows and columns of the image the tile owns (writes).
    window : tuple of slice
        ``core`` grown by the halo; may extend beyond the image (padded with
        nodata when read).
    """

    index: tuple
    core: tuple
    window: tuple

    @property
    def core_shape(self):
        return (self.core[0].stop - self.core[0].start, self.core[1].stop - self.core[1].start)

    @property
    def core_origin(self):
        return (self.core[0].start, self.core[1].start)

    @property
    def window_origin(self):
        return (self.window[0].start, self.window[1].start)

    def grown(self, margin, shape):
        """The core grown by ``margin`` px on every side, clipped to an image of
        ``shape``: a tuple of slices."""
        return tuple(slice(max(c.start - margin, 0), min(c.stop + margin, n)) for c, n in zip(self.core, shape))

    def check_core(self, array):
        """Raise if ``array`` does not have this tile's core shape (the stitching
        guard: a tile writes exactly its core)."""
        if tuple(array.shape[:2]) != self.core_shape:
            raise ParameterError(f"tile {self.index}: expected a core of shape {self.core_shape}, "
                                 f"got {tuple(array.shape[:2])}")


def _edges(size, tile):
    """Tile boundaries along one axis; a remainder shorter than half a tile is
    merged into the last tile so that no tile is a thin sliver."""
    edges = list(range(0, size, tile)) + [size]
    if len(edges) > 2 and edges[-1] - edges[-2] < tile // 2:
        del edges[-2]
    return np.array(edges)


@dataclass(frozen=True)
class TileGrid:
    """Core tiles of ``tile`` x ``tile`` pixels with a ``halo`` on every side.

    Parameters
    ----------
    shape : tuple of int
        (H, W) of the image.
    tile : int
        Core tile side in pixels; edge tiles may be up to 1.5 x longer.
    halo : int
        Pixels added on every side of a core to make its window.
    """

    shape: tuple
    tile: int
    halo: int

    def __post_init__(self):
        shape = tuple(int(v) for v in self.shape)
        if len(shape) != 2 or min(shape) < 1:
            raise ParameterError(f"shape: expected (H, W) with H, W >= 1, got {self.shape}")
        if int(self.tile) < 32:
            raise ParameterError(f"tile size: expected at least 32 pixels, got {self.tile}")
        if int(self.halo) < 0:
            raise ParameterError(f"halo (overlap): expected >= 0 pixels, got {self.halo}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "tile", int(self.tile))
        object.__setattr__(self, "halo", int(self.halo))

    @property
    def row_edges(self):
        return _edges(self.shape[0], self.tile)

    @property
    def col_edges(self):
        return _edges(self.shape[1], self.tile)

    @property
    def grid_shape(self):
        """(tiles_y, tiles_x)."""
        return (len(self.row_edges) - 1, len(self.col_edges) - 1)

    def __len__(self):
        return int(np.prod(self.grid_shape))

    def __getitem__(self, index):
        ty, tx = index
        ny, nx = self.grid_shape
        if not (0 <= ty < ny and 0 <= tx < nx):
            raise IndexError(f"tile {index} outside a {ny} x {nx} grid")
        r0, r1 = self.row_edges[ty], self.row_edges[ty + 1]
        c0, c1 = self.col_edges[tx], self.col_edges[tx + 1]
        core = (slice(int(r0), int(r1)), slice(int(c0), int(c1)))
        h = self.halo
        window = (slice(int(r0) - h, int(r1) + h), slice(int(c0) - h, int(c1) + h))
        return Tile((ty, tx), core, window)

    def coarsened(self, factor):
        """The grid of blocks of ``factor`` x ``factor`` tiles (a merged edge tile
        stays whole) with the same halo.  Every block edge is a tile edge, so a
        block's core is a union of tile cores: writes by block never share a
        chunk of a tile-chunked array with another block."""
        if int(factor) < 1:
            raise ParameterError(f"factor: expected an integer >= 1, got {factor}")
        return TileGrid(self.shape, self.tile * int(factor), self.halo)

    def covering(self, window):
        """Indices of the tiles whose cores meet ``window`` (a tuple of slices
        inside the image)."""
        rows = self._span(self.row_edges, window[0])
        cols = self._span(self.col_edges, window[1])
        return [(ty, tx) for ty in rows for tx in cols]

    @staticmethod
    def _span(edges, window):
        first = int(np.searchsorted(edges, window.start, side="right")) - 1
        last = int(np.searchsorted(edges, window.stop - 1, side="right")) - 1
        return range(max(first, 0), min(last, len(edges) - 2) + 1)

    def __iter__(self):
        ny, nx = self.grid_shape
        for ty in range(ny):
            for tx in range(nx):
                yield self[ty, tx]
