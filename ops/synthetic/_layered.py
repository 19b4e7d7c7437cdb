"""Raised structures: a ground scene with depth layers above it (METHOD.md
section 3, item 8), for tests and the benchmark.

A structure is a flat roof at relative depth ``rho`` (its distance from the
camera over the ground's, 0 < rho < 1 for anything above the ground): the
camera's rotations move it as they move the ground, its translations
(``tx``, ``ty``, ``s``) by ``1 / rho`` times as much.  The reference is seen
from the path's origin, where every layer lines up with the ground below it;
the capture composites the layers over the ground, the nearest last, so the
ground a roof hid in the reference appears beside it in the capture.
"""

from dataclasses import dataclass

import cv2
import numpy as np

from .._forward import CameraPath, render

__all__ = []


@dataclass(frozen=True)
class Structure:
    """One raised structure in scene coordinates: its roof's footprint
    (bool, scene shape), the roof's intensities there, and its relative depth."""

    mask: np.ndarray
    roof: np.ndarray
    depth: float


def raise_structures(scene, *, count, depths, size_range, seed, margin, avoid=None):
    """``count`` rectangular roofs (long side in ``size_range`` px, depth
    uniform in ``depths``) inside ``scene``, at least ``margin`` px from its
    edges and off the pixels of ``avoid`` (bool, scene shape), each a tone
    contrasting with the ground around it, with texture."""
    rng = np.random.default_rng(seed)
    h, w = scene.shape
    taken = np.zeros((h, w), bool) if avoid is None else cv2.dilate(avoid.astype(np.uint8), np.ones((9, 9))) > 0
    out = []
    for _ in range(50 * count):
        if len(out) == count:
            break
        length = rng.uniform(*size_range)
        width = length * rng.uniform(0.5, 0.9)
        cy, cx = rng.uniform(margin + length, h - margin - length), rng.uniform(margin + length, w - margin - length)
        box = cv2.boxPoints(((cx, cy), (length, width), rng.uniform(0, 180))).astype(np.int32)
        mask = np.zeros((h, w), np.uint8)
        cv2.fillPoly(mask, [box], 1)
        mask = mask.astype(bool)
        if (mask & taken).any():
            continue
        local = float(scene[cv2.dilate(mask.astype(np.uint8), np.ones((15, 15))) > 0].mean())
        tone = rng.uniform(0.75, 0.9) if local < 0.45 else rng.uniform(0.1, 0.25)
        roof = np.clip(tone + 0.03 * rng.standard_normal((h, w)), 0, 1).astype(np.float32)
        out.append(Structure(mask, np.where(mask, roof, 0).astype(np.float32), float(rng.uniform(*depths))))
        taken |= cv2.dilate(mask.astype(np.uint8), np.ones((25, 25))) > 0
    return out


def with_roofs(ground, structures):
    """The scene as the reference sees it: every roof over the ground."""
    out = ground.copy()
    for s in sorted(structures, key=lambda s: -s.depth):
        out[s.mask] = s.roof[s.mask]
    return out


def _at_depth(path, depth):
    """The path as a layer at relative ``depth`` sees it: translations
    (tx, ty, s) divided by the depth, rotations as they are."""
    poses = path.poses.copy()
    poses[:, :3] /= depth
    return CameraPath(path.times, poses)


def render_layered(ground, structures, path, **kw):
    """The capture of the layered scene (keyword arguments of :func:`render`):
    (image (H, W) float32, the ground's RenderResult, parallax truth (H, W)
    bool: where a roof is seen, or the ground that a roof hid in the
    reference)."""
    base = render(ground, path, **kw)
    image = base.image.copy()
    parallax = np.zeros(image.shape, bool)
    for s in sorted(structures, key=lambda s: -s.depth):
        layer = _at_depth(path, s.depth)
        alpha = render(s.mask.astype(np.float32), layer, **kw).image
        roof = render(s.roof, layer, **kw).image
        image = image * (1.0 - alpha) + roof
        hidden = render(s.mask.astype(np.float32), path, **kw).image  # ground the roof hid in the reference
        parallax |= (alpha > 0.5) | (hidden > 0.5)
    return image.astype(np.float32), base, parallax
