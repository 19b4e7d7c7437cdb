"""A pair with raised blocks and new objects on and against them (issue 15,
item 5): what tells a per-pixel parallax rule from a per-component one.

A few flat roofs (:mod:`ops.synthetic._layered`) stand above a procedural
ground; new objects appear on the ground away from them, on the ground
touching one of them, and on one roof (they move with that roof's depth).
The capture is rendered by the independent cubic renderer, never by the
solver's warp.  Each object keeps its own truth mask in the capture grid (the
part of it the capture sees: a roof may hide some of a ground object).
"""

import math

import cv2
import numpy as np

from .._camera import Camera
from .._forward import render
from ._layered import Structure, _at_depth, raise_structures, render_layered, with_roofs
from ._scene import aerial_scene
from ._synth import SyntheticPair, _margin, readout_path

__all__ = []

#: Kinds of object, in the order of :func:`raised_pair`'s ``objects``.
ON_ROOF, AGAINST_BLOCK, AWAY = "on a roof", "against a block", "away from the blocks"


def raised_pair(shape=(512, 512), *, seed=7, blocks=4, away=3, depths=(0.5, 0.8), block_size=(40, 64),
                object_size=(16, 24), noise=0.002, exposure=24.0):
    """A reference and a capture of raised blocks with new objects around them.

    Parameters
    ----------
    shape : tuple of int
        (H, W) of both images.
    seed : int
    blocks : int
        Raised blocks (flat roofs, long side in ``block_size`` px, relative
        depth uniform in ``depths``); at least 2.
    away : int
        New objects on the ground at least 24 px from every block.
    depths : tuple of float
    block_size, object_size : tuple of float
        Long side ranges, px.
    noise : float
        Standard deviation of Gaussian noise added to the capture.
    exposure : float
        Row exposure in row periods.

    Returns
    -------
    SyntheticPair, list of (str, ndarray of bool (H, W))
        The pair (``change_mask`` the union of the objects) and each object's
        kind (:data:`ON_ROOF`, :data:`AGAINST_BLOCK`, :data:`AWAY`) and truth.
    """
    height, width = int(shape[0]), int(shape[1])
    rng = np.random.default_rng(seed)
    camera = Camera.for_shape(shape)
    path = readout_path(height, exposure, tx=(15.0, 19.0), ty=(3.0, 6.0), rz=(-0.5, 0.5))
    margin = _margin(path, camera, shape)
    scene = (0.05 + 0.7 * aerial_scene((height + 2 * margin, width + 2 * margin), seed=seed)).astype(np.float32)
    raised = raise_structures(scene, count=blocks, depths=depths, size_range=block_size, seed=seed + 3,
                              margin=margin + 40)
    kw = dict(shape=shape, camera=camera, row_delay=1.0, exposure=exposure, source_origin_yx=(margin, margin),
              interpolation="cubic")
    raised = sorted(raised, key=lambda s: s.depth)  # the object on a roof goes on the nearest
    ground, seen_by_capture, placed = scene.copy(), list(raised), []
    roof = _on_roof(rng, raised[0], object_size)
    seen_by_capture[0] = Structure(raised[0].mask, _paint(rng, raised[0].roof.copy(), roof, with_roofs(scene, raised[:1])),
                                   raised[0].depth)
    placed.append((ON_ROOF, roof, raised[0].depth))
    against = _against(rng, raised[1], raised, object_size)
    _paint(rng, ground, against, scene)
    placed.append((AGAINST_BLOCK, against, 1.0))
    taken = np.zeros(scene.shape, bool)
    for s in raised:
        taken |= s.mask
    taken = cv2.dilate(taken.astype(np.uint8), np.ones((49, 49), np.uint8)) > 0
    for _ in range(away):
        obj = _away(rng, taken, object_size, margin + 16)
        _paint(rng, ground, obj, scene)
        taken |= cv2.dilate(obj.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        placed.append((AWAY, obj, 1.0))
    image, seen, parallax = render_layered(ground, seen_by_capture, path, **kw)
    covered = np.zeros(shape, np.float32)
    for s in raised:
        covered = np.maximum(covered, render(s.mask.astype(np.float32), _at_depth(path, s.depth), **kw).image)
    objects = []
    for kind, mask, depth in placed:
        truth = render(mask.astype(np.float32), _at_depth(path, depth), **kw).image > 0.5
        objects.append((kind, truth if kind == ON_ROOF else truth & (covered <= 0.5)))
    distorted = image + np.random.default_rng(seed + 2).normal(0, noise, image.shape).astype(np.float32)
    crop = (slice(margin, margin + height), slice(margin, margin + width))
    reference = np.ascontiguousarray(with_roofs(scene, raised)[crop])
    change = np.any([m for _, m in objects], axis=0)
    change_ref = np.any([m[crop] for _, m, _ in placed], axis=0)
    pair = SyntheticPair(reference, distorted.astype(np.float32), change, change_ref, seen.centroid,
                         np.ones(shape, np.float32), seen.valid, camera, path, parallax & ~change,
                         tuple(s.depth for s in raised))
    return pair, objects


def _shape(rng, size):
    """A filled rotated rectangle or ellipse, long side in ``size`` px: bool patch."""
    length = rng.uniform(*size)
    breadth = length * rng.uniform(0.5, 0.9)
    extent = int(math.ceil(length)) + 3
    patch = np.zeros((extent, extent), np.uint8)
    centre = (extent / 2.0 - 0.5, extent / 2.0 - 0.5)
    angle = rng.uniform(0, 180)
    if rng.random() < 0.5:
        cv2.fillPoly(patch, [np.round(cv2.boxPoints((centre, (length, breadth), angle))).astype(np.int32)], 1)
    else:
        cv2.ellipse(patch, (centre, (length, breadth), angle), 1, -1)
    return patch.astype(bool)


def _put(patch, shape, top, left):
    """``patch`` placed at (top, left) in a bool array of ``shape``."""
    out = np.zeros(shape, bool)
    out[top:top + patch.shape[0], left:left + patch.shape[1]] = patch
    return out


def _on_roof(rng, block, size):
    """An object well inside ``block``'s roof (4 px from its edges)."""
    inner = cv2.erode(block.mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    for _ in range(200):
        patch = _shape(rng, (size[0] * 0.8, size[1] * 0.8))
        rows, cols = np.nonzero(inner)
        k = int(rng.integers(len(rows)))
        obj = _put(patch, block.mask.shape, rows[k] - patch.shape[0] // 2, cols[k] - patch.shape[1] // 2)
        if obj.any() and not (obj & ~inner).any():
            return obj
    raise ValueError("block: no room for an object on its roof")


def _against(rng, block, blocks, size):
    """An object on the ground touching ``block``'s footprint (its gap at most
    1 px), off every other block."""
    others = np.zeros(block.mask.shape, bool)
    for s in blocks:
        others |= s.mask
    ring = (cv2.dilate(block.mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0) & ~block.mask
    rows, cols = np.nonzero(ring)
    middle = np.argwhere(block.mask).mean(axis=0)
    for _ in range(200):
        patch = _shape(rng, size)
        k = int(rng.integers(len(rows)))
        start = np.array([rows[k], cols[k]], float)
        outward = (start - middle) / max(float(np.hypot(*(start - middle))), 1e-9)
        for step in range(patch.shape[0]):  # slide it outwards until it is off every block
            top, left = np.round(start + step * outward - np.array(patch.shape) / 2).astype(int)
            obj = _put(patch, block.mask.shape, top, left)
            if not (obj & others).any():
                if (obj & ring).any():
                    return obj
                break
    raise ValueError("block: no room for an object against it")


def _away(rng, taken, size, margin):
    h, w = taken.shape
    for _ in range(500):
        patch = _shape(rng, size)
        top, left = int(rng.integers(margin, h - margin - patch.shape[0])), \
            int(rng.integers(margin, w - margin - patch.shape[1]))
        obj = _put(patch, taken.shape, top, left)
        if not (obj & taken).any():
            return obj
    raise ValueError("scene: no room for an object away from the blocks")


def _paint(rng, image, obj, background):
    """Paint ``obj`` into ``image`` (in place) with a tone contrasting with
    ``background`` around it, and a little texture; returns ``image``."""
    around = cv2.dilate(obj.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
    local = float(background[around & ~obj].mean())
    tone = rng.uniform(0.82, 0.92) if local < 0.5 else rng.uniform(0.06, 0.16)
    image[obj] = np.clip(tone + 0.025 * rng.standard_normal(int(obj.sum())), 0, 1)
    return image
