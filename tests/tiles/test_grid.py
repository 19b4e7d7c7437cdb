"""TileGrid geometry and the seam merge of per-tile labels."""

import numpy as np
import pytest
from scipy import ndimage

from rsmb.ops import ParameterError
from rsmb.tiles import (
    TileGrid,
    TileLabels,
    merge_tile_labels,
)


def test_tiles_cover_the_image_once_with_ragged_and_merged_edges():
    grid = TileGrid((1000, 1100), 256, 20)
    assert grid.grid_shape == (4, 4)
    # 1000 = 3 x 256 + 232 (kept ragged); 1100 = 4 x 256 + 76 (76 < 128: merged into the last tile)
    assert list(np.diff(grid.row_edges)) == [256, 256, 256, 232]
    assert list(np.diff(grid.col_edges)) == [256, 256, 256, 332]
    cover = np.zeros((1000, 1100), int)
    for tile in grid:
        cover[tile.core] += 1
        assert tile.window[0].start == tile.core[0].start - 20 and tile.window[1].stop == tile.core[1].stop + 20
    assert (cover == 1).all()


def test_single_tile_and_errors():
    grid = TileGrid((100, 120), 512, 8)
    assert len(grid) == 1 and grid[0, 0].core_shape == (100, 120)
    with pytest.raises(IndexError):
        grid[1, 0]
    with pytest.raises(ParameterError, match="tile size"):
        TileGrid((100, 100), 8, 0)
    with pytest.raises(ParameterError, match="halo"):
        TileGrid((100, 100), 64, -1)
    with pytest.raises(ParameterError, match="core"):
        grid[0, 0].check_core(np.zeros((99, 120)))


def test_seam_merge_equals_whole_image_labelling():
    rng = np.random.default_rng(0)
    mask = ndimage.binary_dilation(rng.random((300, 340)) > 0.985, iterations=3)
    score = rng.random(mask.shape).astype(np.float32)
    grid = TileGrid(mask.shape, 64, 0)
    summaries = {}
    for tile in grid:
        labels, n = ndimage.label(mask[tile.core], structure=np.ones((3, 3)))
        area = np.bincount(labels.ravel(), minlength=n + 1)
        peak = np.zeros(n + 1, np.float32)
        np.maximum.at(peak, labels.ravel(), score[tile.core].ravel())
        summaries[tile.index] = (TileLabels.from_labels(tile.index, labels, area, peak), labels)
    offsets, root, area, peak = merge_tile_labels({k: v[0] for k, v in summaries.items()}, grid.grid_shape)
    merged = np.zeros(mask.shape, np.int64)
    for tile in grid:
        labels = summaries[tile.index][1]
        merged[tile.core] = np.where(labels > 0, root[offsets[tile.index] + labels] + 1, 0)
    whole, n = ndimage.label(mask, structure=np.ones((3, 3)))
    # the same partition of the pixels, and the same component areas
    pairs = {(a, b) for a, b in zip(whole[mask], merged[mask])}
    assert len(pairs) == n == len({b for _, b in pairs})
    for a, b in pairs:
        assert (whole == a).sum() == area[b - 1]


@pytest.mark.parametrize("shape, tile", [((1000, 1100), 256), ((8192, 8192), 512), ((1100, 300), 240),
                                         ((700, 700), 100), ((96, 96), 64)])
@pytest.mark.parametrize("factor", [1, 2, 3])
def test_blocks_are_unions_of_tiles(shape, tile, factor):
    grid = TileGrid(shape, tile, 30)
    blocks = grid.coarsened(factor)
    assert blocks.halo == grid.halo
    assert set(blocks.row_edges) <= set(grid.row_edges) and set(blocks.col_edges) <= set(grid.col_edges)
    count = np.zeros(shape, int)
    for b in blocks:
        for ty, tx in grid.covering(b.core):  # every tile under a block lies inside it
            t = grid[ty, tx]
            assert all(c.start >= s.start and c.stop <= s.stop for c, s in zip(t.core, b.core))
            count[t.core] += 1
    assert (count == 1).all()  # so each tile belongs to exactly one block
    with pytest.raises(ParameterError, match="factor"):
        grid.coarsened(0)

@pytest.mark.parametrize("factor,phase", [(4, 0), (4, 2), (3, 1)])
def test_overview_by_blocks_equals_the_whole(factor, phase):
    """The overview assembled from blocks equals the overview of the whole
    array, also where cells straddle block edges (64-px blocks, cells of 3 or
    4 px at several phases)."""
    from rsmb.tiles import block_overview, overview_cells

    array = np.random.default_rng(0).random((250, 190)).astype(np.float32)
    (r, c), whole = overview_cells(array, (0, 0), factor, phase)
    assert (r, c) == (0, 0) and whole.shape == ((250 - phase) // factor, (190 - phase) // factor)
    out = np.full(whole.shape, np.nan, np.float32)
    for r0 in range(0, 250, 64):
        for c0 in range(0, 190, 64):
            (row, col), cells = block_overview(array, (slice(r0, min(r0 + 64, 250)), slice(c0, min(c0 + 64, 190))),
                                               factor, phase)
            out[row:row + cells.shape[0], col:col + cells.shape[1]] = cells
    np.testing.assert_allclose(out, whole, rtol=1e-6)


@pytest.mark.parametrize("factor, phase, beyond", [(4, 0, (0, 0)), (8, 0, (0, 0)), (4, 2, (2, 2)), (3, 1, (0, 1))])
def test_block_overview_reads_through_its_last_cell_only(factor, phase, beyond):
    """A block's overview reads its rows and columns through the end of the
    last cell starting in it: nothing beyond the block when the cells end on
    its edges (no neighbouring chunk touched), else the straddling cells'
    pixels; its cells are those of the whole array's overview."""
    from rsmb.tiles import block_overview, overview_cells

    class Recorded:
        def __init__(self, array):
            self.array, self.shape, self.keys = array, array.shape, []

        def __getitem__(self, key):
            self.keys.append(key)
            return self.array[key]

    array = np.random.default_rng(1).random((128, 128)).astype(np.float32)
    recorded = Recorded(array)
    (row, col), cells = block_overview(recorded, (slice(32, 64), slice(64, 96)), factor, phase)
    (rows, cols), = recorded.keys
    # (3, 1): the last cells starting in rows 32-63 and columns 64-95 start at 61 (ends 64) and 94 (ends 97)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (32, 64 + beyond[0], 64, 96 + beyond[1])
    _, whole = overview_cells(array, (0, 0), factor, phase)
    np.testing.assert_array_equal(cells, whole[row:row + cells.shape[0], col:col + cells.shape[1]])
    assert row * factor + phase >= 32 and (row + cells.shape[0] - 1) * factor + phase < 64


def _old_components(edges, total):
    """What the seam merge did before scipy.sparse.csgraph: a Python
    union-find over the seam pairs, each component named by its smallest id."""
    def find(parent, i):
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return root

    parent = np.arange(total)
    for pairs in edges:
        for a, b in pairs:
            ra, rb = find(parent, int(a)), find(parent, int(b))
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    return np.array([find(parent, i) for i in range(total)], dtype=np.int64)


@pytest.mark.parametrize("seed, tile", [(0, 64), (1, 50), (2, 37), (3, 512)])
def test_seam_merge_equals_the_union_find_it_replaced(seed, tile):
    from rsmb.ops import label_components
    from rsmb.tiles._stitch import _seam_edges

    rng = np.random.default_rng(seed)
    mask = ndimage.binary_dilation(rng.random((230, 301)) > 0.97, iterations=2 + seed % 2)
    score = rng.random(mask.shape).astype(np.float32)
    grid = TileGrid(mask.shape, tile, 0)
    summaries = {t.index: TileLabels.from_labels(t.index, *label_components(mask[t.core], score[t.core]))
                 for t in grid}
    offsets, root, area, peak = merge_tile_labels(summaries, grid.grid_shape)
    edges = _seam_edges(summaries, offsets, grid.grid_shape)
    np.testing.assert_array_equal(root, _old_components(edges, len(root)))
    assert root.dtype == np.int64
    if len(grid) > 1:
        assert (root != np.arange(len(root))).any()  # some labels were merged across a seam
