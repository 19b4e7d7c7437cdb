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

@pytest.mark.parametrize("factor,phase", [(4, 0), (4, 2), (3, 1), (8, 7), (1, 0)])
def test_overview_by_blocks_equals_the_whole(factor, phase):
    """The overview assembled from the cell sums of blocks equals the cells'
    sums, least and largest values over the whole array, also where cells
    straddle block edges (64-px blocks, cells of 1 to 8 px at several
    phases; rows and columns before the first cell belong to none), and a
    no-data pixel makes its cell's sum NaN."""
    from rsmb.tiles import cell_sums, overview_from_sums

    array = np.random.default_rng(0).random((250, 190)).astype(np.float32)
    array[9, 11] = np.nan
    blocks = [cell_sums(array[r0:r0 + 64, c0:c0 + 64], (r0, c0), factor, phase)
              for r0 in range(0, 250, 64) for c0 in range(0, 190, 64)]
    sums, lows, highs = overview_from_sums(blocks, array.shape, factor, phase)
    n = ((250 - phase) // factor, (190 - phase) // factor)
    cells = array[phase:phase + n[0] * factor, phase:phase + n[1] * factor].reshape(n[0], factor, n[1], factor)
    assert sums.shape == lows.shape == highs.shape == n
    np.testing.assert_allclose(sums, cells.sum(axis=(1, 3), dtype=np.float64), rtol=1e-12)
    valid = np.isfinite(sums)
    assert (~valid).sum() == (9 >= phase and 11 >= phase and 9 < phase + n[0] * factor)
    np.testing.assert_array_equal(lows[valid], cells.min(axis=(1, 3))[valid])
    np.testing.assert_array_equal(highs[valid], cells.max(axis=(1, 3))[valid])


def test_cell_means_are_the_common_scale_of_the_cells():
    """The overview's cell means on the common scale equal the mean of the
    scaled pixels to float32 rounding, are NaN where a cell holds a clipped
    or no-data pixel, and cells of one pixel are :meth:`apply`'s values bit
    for bit."""
    from rsmb.ops import IntensityScale
    from rsmb.tiles import cell_sums, overview_from_sums

    rng = np.random.default_rng(2)
    array = np.round(rng.random((64, 64)) * 255).astype(np.float32) / 255  # 8-bit values, some at 0 and 1
    array[3, 3] = np.nan
    scale = IntensityScale(0.02, 0.97, (0.0, 1.0), (0.0, 1.0))
    scaled = scale.apply(array, "capture")
    one = scale.cell_means(*overview_from_sums([cell_sums(array, (0, 0), 1)], array.shape, 1), 1, "capture")
    np.testing.assert_array_equal(one, scaled)
    means = scale.cell_means(*overview_from_sums([cell_sums(array, (0, 0), 4)], array.shape, 4), 16, "capture")
    expected = scaled.reshape(16, 4, 16, 4).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
    assert np.array_equal(np.isnan(means), np.isnan(expected)) and np.isnan(means).sum() > 1
    np.testing.assert_allclose(means, expected, rtol=2e-7)


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
