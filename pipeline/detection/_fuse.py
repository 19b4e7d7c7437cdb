"""Tiles check one another: the per-row paths of tiles sharing rows are fused by
a median, each tile's disagreement with the fused path is measured at its row
ends, and tiles that stray from their band are chosen for a re-solve around
the others' path (METHOD.md section 6)."""

import warnings

import numpy as np

from rsmb import ops

__all__ = []


def _row_end_points(tile):
    """Global (x, y) of the two ends of every core row of ``tile``: (rows, 2, 2)."""
    rows = np.arange(tile.core[0].start, tile.core[0].stop, dtype=np.float64)
    left = np.stack([np.full_like(rows, tile.core[1].start), rows], -1)
    right = np.stack([np.full_like(rows, tile.core[1].stop - 1), rows], -1)
    return np.stack([left, right], 1)


def _disagreement(path, reference, tile, camera, axes):
    """Per row, the largest displacement (px) between two paths at the row ends
    (NaN where either path is unknown)."""
    ok = np.isfinite(path).all(1) & np.isfinite(reference).all(1)
    out = np.full(len(ok), np.nan)
    if not ok.any():
        return out
    pts = _row_end_points(tile)[ok]
    ha = ops.pose_homographies(path[ok], camera, axes=axes)
    hb = ops.pose_homographies(reference[ok], camera, axes=axes)
    homog = np.concatenate([pts, np.ones(pts.shape[:2] + (1,))], -1)
    pa = np.einsum("rij,rpj->rpi", ha, homog)
    pb = np.einsum("rij,rpj->rpi", hb, homog)
    out[ok] = np.linalg.norm(pa[..., :2] / pa[..., 2:] - pb[..., :2] / pb[..., 2:], axis=-1).max(-1)
    return out


def _fuse(paths, states):
    """Per-row median over tiles of solved rows; rows no tile solved take the
    median of whatever the tiles have, then interpolation."""
    good = np.where((states == 1)[..., None], paths, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows are handled below
        fused = np.nanmedian(good, axis=1)
        fallback = np.nanmedian(paths, axis=1)
    fused = np.where(np.isnan(fused), fallback, fused)
    rows = np.arange(fused.shape[0])
    for d in range(fused.shape[1]):
        bad = np.isnan(fused[:, d])
        if bad.all():
            fused[:, d] = 0.0
        elif bad.any():
            fused[bad, d] = np.interp(rows[bad], rows[~bad], fused[~bad, d])
    return fused


def _agreement(paths, states, grid, camera, axes):
    fused = _fuse(paths, states)
    ny, nx = grid.grid_shape
    agree = np.full((ny, nx), np.nan)  # RMS displacement from the fused path, px
    worst = np.full((ny, nx), np.nan)  # its 95th percentile over rows: a stretch of wrong rows
    for tile in grid:
        ty, tx = tile.index
        rows = tile.core[0]
        d = _disagreement(np.where((states[rows, tx] == 1)[:, None], paths[rows, tx], np.nan),
                          fused[rows], tile, camera, axes)
        if np.isfinite(d).any():
            agree[ty, tx] = np.sqrt(np.nanmean(d ** 2))
            worst[ty, tx] = np.nanpercentile(d, 95)
    return fused, agree, worst


def _outliers(worst, residual_level, tolerance):
    """Tiles to re-solve: in each band of two or more tiles, those whose path
    strays from the fused one by more than ``tolerance`` px and by more than
    three times the band's typical strayness (tiles fit their rows a little
    differently; a tile on a large change or a periodic texture strays far).
    With two tiles that both stray, the one that fits worse is taken."""
    out = []
    for ty in range(worst.shape[0]):
        row = worst[ty]
        if row.size < 2 or not np.isfinite(row).any():
            continue
        # a median of two is their mean: with two tiles only the tolerance can judge
        limit = tolerance if row.size == 2 else max(tolerance, 3.0 * float(np.nanmedian(row)))
        bad = [tx for tx in range(row.size) if not row[tx] <= limit]
        if row.size == 2 and len(bad) == 2:
            bad = [int(np.nanargmax(residual_level[ty]))]
        if len(bad) < row.size:
            out.extend((ty, tx) for tx in bad)
    return out
