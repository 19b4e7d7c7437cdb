"""Seam merge of per-tile connected components.

Each tile labels the change candidates of its core on its own.  Two labels of
neighbouring tiles belong to one component when 8-connected pixels across their
shared seam (or corner) carry them; the connected components of the graph of
those pairs (``scipy.sparse.csgraph``) are the global components, whose area
and peak are the sums and maxima of their pieces.  An
object cut by a seam is thus measured whole before the minimum area applies.
"""

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

__all__ = ["TileLabels", "merge_tile_labels"]


@dataclass(frozen=True)
class TileLabels:
    """Summary of one tile's local labelling.

    Attributes
    ----------
    index : tuple of int
    area, peak : ndarray, shape (n + 1,)
        Per local label (0 = background).
    top, bottom : ndarray of int32, shape (w,)
        Labels of the first and last core rows.
    left, right : ndarray of int32, shape (h,)
        Labels of the first and last core columns.
    """

    index: tuple
    area: np.ndarray
    peak: np.ndarray
    top: np.ndarray
    bottom: np.ndarray
    left: np.ndarray
    right: np.ndarray

    @classmethod
    def from_labels(cls, index, labels, area, peak):
        return cls(tuple(index), area, peak, labels[0].copy(), labels[-1].copy(), labels[:, 0].copy(),
                   labels[:, -1].copy())


def _pairs_8(a, b):
    """Label pairs of two facing pixel lines touching 8-connectedly."""
    out = []
    for shift in (-1, 0, 1):
        if shift < 0:
            x, y = a[1:], b[:-1]
        elif shift > 0:
            x, y = a[:-1], b[1:]
        else:
            x, y = a, b
        both = (x > 0) & (y > 0)
        out.append(np.stack([x[both], y[both]], axis=1))
    return np.unique(np.concatenate(out), axis=0) if out else np.zeros((0, 2), int)


def merge_tile_labels(summaries, grid_shape):
    """Global components of per-tile labels.

    Parameters
    ----------
    summaries : dict of tuple to TileLabels
        One per tile index of a grid of ``grid_shape`` (tiles_y, tiles_x).

    Returns
    -------
    offsets : dict of tuple to int
        Global id of a tile's local label ``l`` is ``offsets[index] + l``.
    root : ndarray of int64
        Global id -> component id.
    area, peak : ndarray
        Per component id (indexed by ``root`` values).
    """
    offsets, total = {}, 0
    for index in sorted(summaries):
        offsets[index] = total
        total += len(summaries[index].area)
    root = _components(_seam_edges(summaries, offsets, grid_shape), total)
    area = np.zeros(total, dtype=np.int64)
    peak = np.zeros(total, dtype=np.float32)
    for index, s in summaries.items():
        ids = root[offsets[index]:offsets[index] + len(s.area)]
        np.add.at(area, ids, s.area)
        np.maximum.at(peak, ids, s.peak)
    return offsets, root, area, peak


def _seam_edges(summaries, offsets, grid_shape):
    """Pairs of global labels that touch across a seam or a corner (arrays of
    shape (n, 2), one per touching pair of tiles)."""
    edges = []

    def link(pairs, oa, ob):
        edges.append(np.asarray(pairs, np.int64).reshape(-1, 2) + (oa, ob))

    ny, nx = grid_shape
    for (ty, tx), s in summaries.items():
        if tx + 1 < nx:
            right = summaries[(ty, tx + 1)]
            link(_pairs_8(s.right, right.left), offsets[(ty, tx)], offsets[(ty, tx + 1)])
        if ty + 1 < ny:
            below = summaries[(ty + 1, tx)]
            link(_pairs_8(s.bottom, below.top), offsets[(ty, tx)], offsets[(ty + 1, tx)])
            # diagonal neighbours touch at one corner pixel
            if tx + 1 < nx:
                d = summaries[(ty + 1, tx + 1)]
                if s.bottom[-1] > 0 and d.top[0] > 0:
                    link([(s.bottom[-1], d.top[0])], offsets[(ty, tx)], offsets[(ty + 1, tx + 1)])
            if tx > 0:
                d = summaries[(ty + 1, tx - 1)]
                if s.bottom[0] > 0 and d.top[-1] > 0:
                    link([(s.bottom[0], d.top[-1])], offsets[(ty, tx)], offsets[(ty + 1, tx - 1)])
    return edges


def _components(edges, total):
    """Component id of each of ``total`` nodes joined by ``edges`` (arrays of
    pairs): the smallest node id of its component."""
    pairs = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
    graph = sparse.coo_matrix((np.ones(len(pairs), np.int32), (pairs[:, 0], pairs[:, 1])), shape=(total, total))
    _, component = csgraph.connected_components(graph, directed=False)
    smallest = np.full(component.max(initial=-1) + 1, total, np.int64)
    np.minimum.at(smallest, component, np.arange(total))
    return smallest[component]
