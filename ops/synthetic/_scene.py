"""Procedural aerial-like scenes and pasted changes, for tests, ``rsmb synth`` and the demo.

Nothing is downloaded: :func:`aerial_scene` draws fields (Voronoi parcels with ploughed,
mottled or smooth texture), hedgerows, roads, buildings with shadows and trees on a
multi-scale noise texture; :func:`paste_changes` adds objects that "appeared" with a
known mask. Everything is seeded and vectorised (numpy + OpenCV drawing), so a
4096 x 4096 scene takes a few seconds.

Registration needs horizontal gradients in every row (a row without texture makes its
``F_i`` rank-deficient) and change detection needs realistic homogeneous areas, so the
scene has fine texture everywhere and some fields with only fine texture.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.spatial import Voronoi

from rsmb.ops._errors import InputError, ParameterError

__all__ = ["aerial_scene", "paste_changes"]

_SHIFT = 4  # OpenCV fixed-point bits for sub-pixel drawing
_SCALE = float(1 << _SHIFT)
_REF_AREA = 512.0 * 512.0  # object densities below are per 512 x 512 pixels


def _check_shape(shape) -> tuple[int, int]:
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"shape: expected (H, W), got {shape!r}") from exc
    if h < 16 or w < 16:
        raise ParameterError(f"shape: expected H, W >= 16 pixels, got {shape!r}")
    return h, w


def _count(name: str, value, default: float) -> int:
    if value is None:
        return int(round(default))
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ParameterError(f"{name}: expected an integer >= 0 or None, got {value!r}")
    return int(value)


def _fixed(points: np.ndarray) -> np.ndarray:
    """(x, y) float points -> OpenCV fixed-point int32 array."""
    return np.round(np.asarray(points, dtype=np.float64) * _SCALE).astype(np.int32)


def _value_noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Smooth noise of unit-ish std with features of about ``cell`` pixels, float32 (H, W)."""
    h, w = shape
    small = rng.standard_normal(
        (max(2, math.ceil(h / cell) + 2), max(2, math.ceil(w / cell) + 2))
    ).astype(np.float32)
    big = cv2.resize(small, (w + 2 * int(cell) + 2, h + 2 * int(cell) + 2),
                     interpolation=cv2.INTER_CUBIC)
    o = int(cell) // 2
    out = big[o:o + h, o:o + w]
    return out / max(float(out.std()), 1e-6)


def _fields(rng, shape, field_size):
    """Voronoi parcels of a jittered grid: int32 label map (H, W) and the ridge segments."""
    h, w = shape
    ny, nx = math.ceil(h / field_size) + 1, math.ceil(w / field_size) + 1
    gy, gx = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    jitter = rng.uniform(0.1, 0.9, size=(2, ny, nx))
    seeds = np.stack([(gx + jitter[0]) * field_size - 0.5 * field_size,
                      (gy + jitter[1]) * field_size - 0.5 * field_size], -1).reshape(-1, 2)
    radius = 4.0 * max(h, w)
    ang = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    ring = np.stack([w / 2 + radius * np.cos(ang), h / 2 + radius * np.sin(ang)], -1)
    vor = Voronoi(np.concatenate([seeds, ring]))
    labels = np.zeros((h, w), np.int32)
    for i in range(len(seeds)):
        region = vor.regions[vor.point_region[i]]
        if region and -1 not in region:
            cv2.fillPoly(labels, [_fixed(vor.vertices[region])], i + 1, cv2.LINE_8, _SHIFT)
    ridges = [(vor.vertices[a], vor.vertices[b]) for (p, q), (a, b)
              in zip(vor.ridge_points, vor.ridge_vertices)
              if a >= 0 and b >= 0 and p < len(seeds) and q < len(seeds)]
    return labels, len(seeds) + 1, ridges


def _field_texture(rng, labels, n_labels, noise_med, noise_coarse):
    """Per-field brightness and texture (ploughed stripes, mottled or smooth), float32."""
    h, w = labels.shape
    mean = rng.uniform(0.22, 0.62, n_labels).astype(np.float32)
    kind = rng.choice(3, size=n_labels, p=[0.4, 0.35, 0.25])  # stripes, mottled, smooth
    amp_stripe = np.where(kind == 0, rng.uniform(0.03, 0.07, n_labels), 0.0).astype(np.float32)
    amp_med = np.select([kind == 0, kind == 1], [0.015, rng.uniform(0.04, 0.07, n_labels)],
                        0.008).astype(np.float32)
    amp_coarse = np.select([kind == 2], [0.015], rng.uniform(0.03, 0.06, n_labels)
                           ).astype(np.float32)
    theta = rng.uniform(0, np.pi, n_labels)
    period = rng.uniform(4.0, 11.0, n_labels)
    kx = (2 * np.pi * np.cos(theta) / period).astype(np.float32)
    ky = (2 * np.pi * np.sin(theta) / period).astype(np.float32)
    phase = rng.uniform(0, 2 * np.pi, n_labels).astype(np.float32)
    ys = np.arange(h, dtype=np.float32)[:, None]
    xs = np.arange(w, dtype=np.float32)[None, :]
    stripes = np.sin(xs * kx[labels] + ys * ky[labels] + phase[labels])
    return (mean[labels] + amp_stripe[labels] * stripes
            + amp_med[labels] * noise_med + amp_coarse[labels] * noise_coarse)


def _draw_roads(rng, img, n_roads, noise_med):
    """Bright roads (4 to 12 px wide) at angles at least 15 degrees from horizontal,
    with a dashed centre line, so no image row lies along a road."""
    h, w = img.shape
    mask = np.zeros((h, w), np.uint8)
    dash = np.zeros((h, w), np.uint8)
    diag = math.hypot(h, w)
    for _ in range(n_roads):
        c = rng.uniform([0, 0], [w, h])
        ang = math.radians(rng.uniform(15, 165))
        half = 0.5 * diag * rng.uniform(0.4, 1.2)
        d = np.array([math.cos(ang), math.sin(ang)])
        p0, p1 = c - half * d, c + half * d
        width = int(rng.integers(4, 13))
        cv2.line(mask, tuple(_fixed(p0)), tuple(_fixed(p1)), 1, width, cv2.LINE_8, _SHIFT)
        n_dash = max(1, int(2 * half / 12))
        t = np.linspace(0, 1, n_dash + 1)
        pts = p0[None] + t[:, None] * (p1 - p0)[None]
        for a, b in zip(pts[0:-1:2], pts[1::2]):
            cv2.line(dash, tuple(_fixed(a)), tuple(_fixed(b)), 1, 1, cv2.LINE_8, _SHIFT)
    road = mask.astype(bool)
    tone = np.float32(rng.uniform(0.72, 0.85))
    img[road] = tone + 0.02 * noise_med[road]
    centre = road & dash.astype(bool)
    img[centre] = np.minimum(img[centre] + 0.12, 1.0)
    return road


def _rotated_rect(centre, length, width, angle):
    """Corners (4, 2) in (x, y) of a rectangle rotated by ``angle`` radians."""
    c, s = math.cos(angle), math.sin(angle)
    u = np.array([c, s]) * length / 2
    v = np.array([-s, c]) * width / 2
    return np.array([centre + u + v, centre - u + v, centre - u - v, centre + u - v])


def _draw_buildings(rng, img, n_buildings, sun):
    """Rectangular buildings with a two-tone roof (ridge) and a cast shadow."""
    h, w = img.shape
    shadow = np.zeros((h, w), np.uint8)
    roofs = []
    for _ in range(n_buildings):
        centre = rng.uniform([0, 0], [w, h])
        length, width = rng.uniform(10, 34), rng.uniform(7, 18)
        angle = rng.uniform(0, np.pi)
        corners = _rotated_rect(centre, length, width, angle)
        height = rng.uniform(3, 9)
        cv2.fillPoly(shadow, [_fixed(corners + height * sun)], 1, cv2.LINE_8, _SHIFT)
        roofs.append((centre, length, width, angle, corners))
    img[shadow.astype(bool)] *= np.float32(0.5)
    for centre, length, width, angle, corners in roofs:
        tone = rng.uniform(0.35, 0.95)
        # two halves split along the long axis: the roof ridge
        half = _rotated_rect(centre + np.array([-math.sin(angle), math.cos(angle)]) * width / 4,
                             length, width / 2, angle)
        cv2.fillPoly(img, [_fixed(corners)], float(tone), cv2.LINE_8, _SHIFT)
        cv2.fillPoly(img, [_fixed(half)], float(tone * 0.8), cv2.LINE_8, _SHIFT)


def _draw_trees(rng, img, n_trees, sun):
    """Trees: small dark crowns in clumps (woods, orchards), each with a shadow."""
    h, w = img.shape
    if n_trees == 0:
        return
    n_clumps = max(1, n_trees // 25)
    centres = rng.uniform([0, 0], [w, h], size=(n_clumps, 2))
    spread = rng.uniform(8, 40, n_clumps)
    which = rng.integers(0, n_clumps, n_trees)
    xy = centres[which] + rng.standard_normal((n_trees, 2)) * spread[which, None]
    radius = rng.uniform(2.0, 5.5, n_trees)
    tone = rng.uniform(0.08, 0.25, n_trees)
    shadow = np.zeros((h, w), np.uint8)
    for p, r in zip(xy, radius):
        cv2.circle(shadow, tuple(_fixed(p + 1.2 * r * sun)), int(r * _SCALE), 1, -1,
                   cv2.LINE_8, _SHIFT)
    img[shadow.astype(bool)] *= np.float32(0.6)
    for p, r, t in zip(xy, radius, tone):
        cv2.circle(img, tuple(_fixed(p)), int(r * _SCALE), float(t), -1, cv2.LINE_8, _SHIFT)
        cv2.circle(img, tuple(_fixed(p - 0.35 * r * sun)), int(0.45 * r * _SCALE),
                   float(t + 0.08), -1, cv2.LINE_8, _SHIFT)


def aerial_scene(
    shape,
    *,
    seed,
    field_size: float = 160.0,
    n_roads: int | None = None,
    n_buildings: int | None = None,
    n_trees: int | None = None,
    blur_sigma: float = 0.7,
) -> np.ndarray:
    """Procedural aerial-like grey image: fields, hedgerows, roads, buildings, trees.

    Parameters
    ----------
    shape : (int, int)
        ``(H, W)`` in pixels, each >= 16.
    seed : int or numpy.random.Generator
        Seed of every random choice: the same seed gives the same image.
    field_size : float, optional
        Typical field (Voronoi parcel) width in pixels. Default 160.
    n_roads, n_buildings, n_trees : int, optional
        Object counts. Default: proportional to the image size (per 512 x 512
        pixels: about 3 roads, 40 buildings, 300 trees in clumps; roads scale with
        the image side).
    blur_sigma : float, optional
        Gaussian optical blur applied last, pixels (band-limits the drawn edges and the
        noise so that sub-pixel warps interpolate well). 0 disables it. Default 0.7.

    Returns
    -------
    ndarray of float32, shape (H, W)
        Intensities in [0, 1].

    Notes
    -----
    Every pixel carries fine texture (noise of a few pixels' scale), so nearly every
    row has a horizontal gradient; roads are at least 15 degrees away from horizontal
    and carry a dashed centre line. About a quarter of the fields are smooth (fine
    texture only): realistic homogeneous-ish patches. Shadows fall in one direction
    per scene.
    """
    h, w = _check_shape(shape)
    if not (isinstance(field_size, (int, float)) and field_size >= 8):
        raise ParameterError(f"field_size: expected a number of pixels >= 8, got {field_size!r}")
    if not (isinstance(blur_sigma, (int, float)) and blur_sigma >= 0):
        raise ParameterError(f"blur_sigma: expected a number >= 0 pixels, got {blur_sigma!r}")
    rng = np.random.default_rng(seed)
    scale = h * w / _REF_AREA
    n_roads = _count("n_roads", n_roads, 3.0 * math.sqrt(scale))
    n_buildings = _count("n_buildings", n_buildings, 40.0 * scale)
    n_trees = _count("n_trees", n_trees, 300.0 * scale)

    noise_med = _value_noise(rng, (h, w), 5.0)
    noise_coarse = _value_noise(rng, (h, w), 28.0)
    noise_large = _value_noise(rng, (h, w), 250.0)
    labels, n_labels, ridges = _fields(rng, (h, w), float(field_size))
    img = _field_texture(rng, labels, n_labels, noise_med, noise_coarse)
    img += np.float32(0.04) * noise_large

    hedges = np.zeros((h, w), np.uint8)
    for a, b in ridges:
        if rng.random() < 0.35:
            cv2.line(hedges, tuple(_fixed(a)), tuple(_fixed(b)), 1, int(rng.integers(1, 4)),
                     cv2.LINE_8, _SHIFT)
    hedge = hedges.astype(bool)
    img[hedge] = np.float32(0.18) + np.float32(0.05) * noise_med[hedge]

    _draw_roads(rng, img, n_roads, noise_med)
    sun_angle = rng.uniform(0, 2 * np.pi)
    sun = np.array([math.cos(sun_angle), math.sin(sun_angle)])
    _draw_buildings(rng, img, n_buildings, sun)
    _draw_trees(rng, img, n_trees, sun)

    img += np.float32(0.03) * rng.standard_normal((h, w), dtype=np.float32)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), float(blur_sigma), borderType=cv2.BORDER_REFLECT)
    np.clip(img, 0.0, 1.0, out=img)
    return img.astype(np.float32, copy=False)


def _object_mask(rng, size_range, h, w, margin):
    """One random rectangle or ellipse drawn into a local uint8 patch.

    Returns the patch (bool), its top-left (row, col) and the object kind.
    """
    lo, hi = size_range
    length = rng.uniform(lo, hi)
    width = length * rng.uniform(0.4, 1.0)
    angle = rng.uniform(0, np.pi)
    kind = "ellipse" if rng.random() < 0.35 else "rectangle"
    extent = int(math.ceil(length)) + 3
    if h - 2 * margin < extent or w - 2 * margin < extent:
        return None
    r0 = int(rng.integers(margin, h - margin - extent + 1))
    c0 = int(rng.integers(margin, w - margin - extent + 1))
    patch = np.zeros((extent, extent), np.uint8)
    centre = np.array([extent / 2.0 - 0.5, extent / 2.0 - 0.5])
    if kind == "rectangle":
        cv2.fillPoly(patch, [_fixed(_rotated_rect(centre, length, width, angle))], 1,
                     cv2.LINE_8, _SHIFT)
    else:
        cv2.ellipse(patch, tuple(_fixed(centre)),
                    (int(length / 2 * _SCALE), int(width / 2 * _SCALE)),
                    math.degrees(angle), 0, 360, 1, -1, cv2.LINE_8, _SHIFT)
    return patch.astype(bool), r0, c0, kind


def paste_changes(
    scene,
    *,
    count: int,
    size_range=(12, 40),
    seed,
    margin: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Paste ``count`` new objects (buildings, vehicles) into a scene: the known changes.

    Parameters
    ----------
    scene : ndarray, shape (H, W)
        Intensities in [0, 1] (e.g. from :func:`aerial_scene`); not modified.
    count : int
        Number of objects, >= 0.
    size_range : (float, float), optional
        Range of an object's long side, pixels (``2 <= lo <= hi``). The short side is
        0.4 to 1 times the long side. Default (12, 40).
    seed : int or numpy.random.Generator
        Seed of every random choice.
    margin : int, optional
        Minimum distance of every object pixel from the image border, pixels.

    Returns
    -------
    changed : ndarray of float32, shape (H, W)
        The scene with the objects; equal to ``scene`` outside ``mask``.
    mask : ndarray of bool, shape (H, W)
        Exactly the pasted pixels.

    Notes
    -----
    Objects are rotated rectangles (with a ridge line, like a roof) or ellipses.
    Each takes a bright (0.82 to 0.95) or dark (0.05 to 0.18) tone, whichever is
    farther from the mean of the scene around it, so its mean contrast against the
    local background is at least about 0.3, plus a little internal texture. Objects
    do not touch each other (2 px gap at least).

    Raises
    ------
    ParameterError
        Bad ``count``, ``size_range`` or ``margin``, or if ``count`` objects cannot be
        placed without overlap (image too small or too crowded).
    InputError
        If ``scene`` is not a finite 2-D array.
    """
    s = np.asarray(scene)
    if s.ndim != 2:
        raise InputError(f"scene: expected a 2-D array (H, W), got shape {s.shape}")
    s = s.astype(np.float32)
    if not np.all(np.isfinite(s)):
        raise InputError("scene: holds NaN or infinite values")
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 0:
        raise ParameterError(f"count: expected an integer >= 0, got {count!r}")
    try:
        lo, hi = (float(x) for x in size_range)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"size_range: expected (lo, hi) in pixels, got {size_range!r}") from exc
    if not (2 <= lo <= hi):
        raise ParameterError(f"size_range: expected 2 <= lo <= hi pixels, got {size_range!r}")
    if isinstance(margin, bool) or not isinstance(margin, (int, np.integer)) or margin < 0:
        raise ParameterError(f"margin: expected an integer >= 0 pixels, got {margin!r}")
    rng = np.random.default_rng(seed)
    h, w = s.shape
    changed = s.copy()
    mask = np.zeros((h, w), bool)
    occupied = np.zeros((h, w), bool)  # pasted objects dilated by the gap
    gap = 2
    placed, attempts = 0, 0
    while placed < count:
        attempts += 1
        if attempts > 200 * count + 1000:
            raise ParameterError(
                f"count: could place only {placed} of {count} non-overlapping objects of "
                f"size {size_range!r} in an image of shape {s.shape} with margin={margin}"
            )
        drawn = _object_mask(rng, (lo, hi), h, w, int(margin))
        if drawn is None:
            raise ParameterError(
                f"size_range: objects up to {hi} px do not fit in shape {s.shape} "
                f"with margin={margin}"
            )
        obj, r0, c0, kind = drawn
        e = obj.shape[0]
        window = (slice(r0, r0 + e), slice(c0, c0 + e))
        if not obj.any() or np.any(occupied[window] & obj):
            continue
        _paint_object(rng, changed, s, obj, r0, c0, kind)
        mask[window] |= obj
        occupied[window] |= cv2.dilate(obj.astype(np.uint8), np.ones((2 * gap + 1,) * 2,
                                                                     np.uint8)).astype(bool)
        placed += 1
    return changed, mask


def _paint_object(rng, changed, scene, obj, r0, c0, kind):
    """Give the pixels of one object a contrasting tone plus texture (in place)."""
    h, w = scene.shape
    e = obj.shape[0]
    pad = e // 2 + 2
    around = scene[max(0, r0 - pad):min(h, r0 + e + pad), max(0, c0 - pad):min(w, c0 + e + pad)]
    local = float(around.mean())
    bright, dark = rng.uniform(0.82, 0.95), rng.uniform(0.05, 0.18)
    tone = bright if abs(bright - local) >= abs(dark - local) else dark
    texture = 0.025 * rng.standard_normal(obj.shape)
    if kind == "rectangle":
        # a ridge / roof line across the middle of the patch
        texture[e // 2, :] += -0.06 if tone > 0.5 else 0.06
    values = np.clip(tone + texture, 0.0, 1.0).astype(np.float32)
    window = changed[r0:r0 + e, c0:c0 + e]
    window[obj] = values[obj]
