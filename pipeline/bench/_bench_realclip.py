"""``rsmb bench --sections realclip``: real aerial photographs with clipped
pixels at both ends (issue 15).

The USC-SIPI aerials of ``--data`` (``aerial/*.png``) are tiled and mirrored
into one scene and stretched as orthophoto products are: about 1 % of the
pixels at 0 and 1 % at 255 (:func:`orthophoto_scene`).  New objects are
pasted where clipping hides them from a rule that ignores clipped pixels:
dark ones on the brightest (clipped-white) areas, bright ones in the darkest
(clipped-black) (:func:`paste_on_extremes`).  The capture sees the scene
through in-plane rolling-shutter motion with blur, rendered by the
independent cubic renderer (never the solver's bilinear warp), and its 8-bit
sensor clips it again.  Both are written as 8-bit GeoTIFFs.

Printed: F, precision and recall of ``rsmb detect`` (defaults), recall on the
objects pasted on clipped areas, the share of pixels with no evidence (NaN
score) among those whose whole exposure sees the reference (beyond the image
border), how much of it is capture pixels clipped on the side their model is
open (eq. 13's ``chi`` unbounded both ways) and, of those, how many have a
model at that clip level too (within ``lambda_chi / 2``), wall seconds; and
OpenCV DIS dense flow (medium preset) on the same pair in the same run, its
residual turned into a mask by rsmb's own change rule (the soft-threshold,
the interpolation allowance, the noise threshold, components) on the common
intensity scale rsmb chose.
"""

import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from rsmb import ops
from rsmb import tiles

from ._baseline import dis_flow, opencv_threads
from ._bench_method import readout_path
from ..detection._detect import detect
from .._synth import _geo

__all__ = ["ClippedPair", "bench_realclip", "orthophoto_scene", "paste_on_extremes", "realclip_pair"]

EXPOSURE = 32.0  # row periods
#: In-plane rolling-shutter motion: (start, end[, wobble amplitude]) per axis, px and degrees.
MOTION = dict(tx=(-8.0, 8.0, 3.0), ty=(0.0, 6.0, 2.0), rz=(-0.6, 0.8))
#: An object counts as pasted on a clipped area when at least this share of
#: the reference under it is clipped.
ON_CLIPPED = 0.1


def orthophoto_scene(images, side, *, clipped=0.01):
    """A ``side`` x ``side`` scene tiled from ``images`` (each mirrored so that
    a block meets its neighbours along flipped edges), stretched linearly so
    that the ``clipped`` share of pixels falls below 0 and the same share
    above 1.  Not clipped: the scene's radiance; an 8-bit product clips it.

    Parameters
    ----------
    images : list of ndarray, shape (h, w), float in [0, 1]
    side : int

    Returns
    -------
    ndarray, shape (side, side), float32
    """
    images = [np.asarray(im, np.float32) for im in images]
    h = min(im.shape[0] for im in images)
    w = min(im.shape[1] for im in images)
    n = int(np.ceil(side / min(h, w)))
    rows = []
    for i in range(n):
        row = []
        for j in range(n):
            block = images[(i + 2 * j) % len(images)][:h, :w]
            row.append(block[::-1 if i % 2 else 1, ::-1 if j % 2 else 1])
        rows.append(np.concatenate(row, axis=1))
    scene = np.concatenate(rows, axis=0)[:side, :side]
    lo, hi = np.percentile(scene, [100 * clipped, 100 * (1 - clipped)])
    return ((scene - lo) / max(hi - lo, 1e-6)).astype(np.float32)


def _extremes(product, count, *, window, spacing, margin, brightest, taken):
    """Centres (y, x) of the ``count`` ``window`` boxes of ``product`` (on
    [0, 1]) that hold the most pixels at 1 (at 0), at least ``spacing`` apart
    and from ``taken``, ``margin`` from the border."""
    at_end = (product >= 1.0) if brightest else (product <= 0.0)
    # the densest clipped areas first, the brightest (darkest) among equals
    box = cv2.blur(at_end.astype(np.float32), (window, window))
    box += 0.01 * cv2.blur(product if brightest else 1.0 - product, (window, window))
    box[:margin] = box[-margin:] = -np.inf
    box[:, :margin] = box[:, -margin:] = -np.inf
    dy, dx = np.mgrid[-spacing:spacing + 1, -spacing:spacing + 1]
    disk = dy ** 2 + dx ** 2 < spacing ** 2

    def suppress(y, x):
        y0, x0 = y - spacing, x - spacing
        cy, cx = max(-y0, 0), max(-x0, 0)
        sub = box[max(y0, 0):y + spacing + 1, max(x0, 0):x + spacing + 1]
        sub[disk[cy:cy + sub.shape[0], cx:cx + sub.shape[1]]] = -np.inf

    for y, x in taken:
        suppress(y, x)
    out = []
    for _ in range(count):
        k = int(np.argmax(box))
        if not np.isfinite(box.flat[k]):
            break
        y, x = divmod(k, box.shape[1])
        out.append((y, x))
        suppress(y, x)
    return out


def paste_on_extremes(scene, count, *, seed, margin, size_range=(14, 36)):
    """Paste ``count`` objects into ``scene``: half dark (0.02 to 0.12) on
    its brightest areas (those an 8-bit product clips at 255 most densely),
    half bright (0.88 to 0.98) in its darkest (clipped at 0), as
    rotated rectangles or ellipses with a little texture.

    Parameters
    ----------
    scene : ndarray, shape (H, W), float32
        Radiance (may exceed [0, 1]); not modified.
    count : int
    seed : int
    margin : int
        Smallest distance of an object's centre from the border, px.

    Returns
    -------
    changed : ndarray, shape (H, W), float32
    labels : ndarray of int16, shape (H, W)
        Object ``k`` (1, 2, ...) on its pixels, 0 elsewhere.
    """
    rng = np.random.default_rng(seed)
    product = np.clip(scene, 0.0, 1.0).astype(np.float32)
    spacing = max(int(size_range[1]) * 2, min(scene.shape) // 14)
    dark = _extremes(product, count - count // 2, window=int(size_range[1]), spacing=spacing, margin=margin,
                     brightest=True, taken=[])
    bright = _extremes(product, count // 2, window=int(size_range[1]), spacing=spacing, margin=margin,
                       brightest=False, taken=dark)
    changed = scene.copy()
    labels = np.zeros(scene.shape, np.int16)
    for k, ((y, x), tone) in enumerate( [(c, rng.uniform(0.02, 0.12)) for c in dark] + [(c, rng.uniform(0.88, 0.98)) for c in bright], 1):
        long_side = rng.uniform(*size_range)
        short = long_side * rng.uniform(0.4, 1.0)
        angle = rng.uniform(0, 180)
        r = int(size_range[1])  # the object within a (2r + 1)^2 window around its centre
        window = (slice(y - r, y + r + 1), slice(x - r, x + r + 1))
        canvas = np.zeros((2 * r + 1, 2 * r + 1), np.uint8)
        if rng.random() < 0.5:
            cv2.ellipse(canvas, (r, r), (int(long_side / 2), int(short / 2)), angle, 0, 360, 1, -1)
        else:
            corners = cv2.boxPoints(((float(r), float(r)), (long_side, short), angle))
            cv2.fillPoly(canvas, [np.round(corners).astype(np.int32)], 1)
        mask = canvas.astype(bool)
        changed[window][mask] = tone + rng.normal(0, 0.015, int(mask.sum())).astype(np.float32)
        labels[window][mask] = k
    return changed, labels


class ClippedPair:
    """A pair built by :func:`realclip_pair`: the 8-bit reference and capture
    (uint8, (H, W)), the truth in the capture's grid (``change_mask``, and
    ``on_clipped`` for the objects pasted on clipped areas), ``covered`` (the
    capture pixels whose whole exposure sees the reference), the number of
    objects and of those on clipped areas, and the reference's clipped share."""

    def __init__(self, reference, capture, change_mask, on_clipped, covered, objects, objects_on_clipped,
                 reference_clipped):
        self.reference, self.capture = reference, capture
        self.change_mask, self.on_clipped, self.covered = change_mask, on_clipped, covered
        self.objects, self.objects_on_clipped = objects, objects_on_clipped
        self.reference_clipped = reference_clipped


def _eight_bit(image):
    return np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)


def realclip_pair(images, side, *, objects=40, seed=15, noise=0.002, samples=24):
    """The reference and capture of the ``realclip`` case from ``images``
    (luminance in [0, 1]); see the module docstring.

    Returns
    -------
    ClippedPair
    """
    path = readout_path(side, EXPOSURE, **MOTION)
    camera = ops.Camera.for_shape((side, side))
    margin = _reach(path, camera, side)
    scene = orthophoto_scene(images, side + 2 * margin)
    inner = scene[margin:margin + side, margin:margin + side]
    changed, labels = paste_on_extremes(inner, objects, seed=seed, margin=margin + 40)
    reference = _eight_bit(inner)
    clipped = (reference == 0) | (reference == 255)
    area = np.bincount(labels.ravel(), minlength=objects + 1)
    share = np.bincount(labels.ravel(), weights=clipped.ravel(), minlength=objects + 1) / np.maximum(area, 1)
    on = (share >= ON_CLIPPED) & (area > 0)
    on[0] = False
    source = scene.copy()
    source[margin:margin + side, margin:margin + side] = changed
    kw = dict(shape=(side, side), camera=camera, exposure=EXPOSURE, source_origin_yx=(margin, margin),
              interpolation="cubic")
    seen = ops.render(source, path, samples=samples, **kw).image
    seen = seen + np.random.default_rng(seed + 1).normal(0, noise, seen.shape).astype(np.float32)
    pasted = np.full(scene.shape, np.nan, np.float32)  # NaN outside the reference: its valid is the coverage
    pasted[margin:margin + side, margin:margin + side] = labels > 0
    truth = ops.render(pasted, path, samples=8, **kw)
    on_source = np.zeros(scene.shape, np.float32)
    on_source[margin:margin + side, margin:margin + side] = on[labels]
    on_truth = ops.render(on_source, path, samples=8, **kw).image > 0.5
    return ClippedPair(reference, _eight_bit(seen), truth.image > 0.5, on_truth, truth.valid, int((area[1:] > 0).sum()),
                       int(on.sum()), float(clipped.mean()))


def _reach(path, camera, side):
    """Pixels by which the path moves the frame's corners, at most, and a few more."""
    corners = np.array([[0, 0, 1], [side - 1, 0, 1], [0, side - 1, 1], [side - 1, side - 1, 1]], np.float64).T
    hom = ops.pose_homographies(path.poses, camera, inverse=True)
    pts = hom @ corners
    pts = pts[:, :2] / pts[:, 2:3]
    return int(np.ceil(np.abs(pts - corners[None, :2]).max())) + 8


def _write_geotiff(path, data):
    import rasterio

    geo = _geo()
    with rasterio.open(path, "w", driver="GTiff", height=data.shape[0], width=data.shape[1], count=1,
                       dtype="uint8", crs=geo.crs, transform=rasterio.Affine(*geo.transform), tiled=True,
                       blockxsize=256, blockysize=256, compress="deflate") as ds:
        ds.write(data, 1)
    return path


def dis_changes(reference, capture, *, factor, params=ops.ChangeParams(), lambda_chi=0.02):
    """DIS dense flow's change mask by rsmb's rule: the residual on rsmb's
    common scale (``factor`` times the [0, 1] luminance), soft-thresholded as
    eq. 13's ``chi``, less the interpolation allowance; the noise threshold
    of its histogram; then candidates, components and holes as rsmb does.

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    registered = dis_flow(reference, capture) * np.float32(factor)
    residual = capture * np.float32(factor) - registered
    valid = np.isfinite(residual)
    residual = np.where(valid, residual, 0.0).astype(np.float32)
    score = ops.change_score(ops.optimal_chi(residual, lambda_chi=lambda_chi), registered, params=params)
    score = np.where(valid, score, 0.0).astype(np.float32)
    threshold = ops.change_threshold(ops.score_histogram(residual, score, valid), params=params)
    return ops.change_mask(score, threshold, params=params)


def bench_realclip(data, workdir, *, size=4096, workers=None):
    """The ``realclip`` case at ``size`` (see the module docstring); skipped
    without ``aerial/*.png`` under ``data``."""
    paths = sorted(Path(data, "aerial").glob("*.png")) if data else []
    if not paths:
        _echo(f"realclip: no aerial photographs under {data}; skipped")
        return {}
    images = [tiles.read_image(p).data for p in paths]
    objects = max(10, round(40 * (size / 4096) ** 2))
    pair = realclip_pair(images, size, objects=objects)
    directory = Path(workdir, f"realclip_{size}")
    directory.mkdir(parents=True, exist_ok=True)
    ref = _write_geotiff(directory / "reference.tif", pair.reference)
    dist = _write_geotiff(directory / "capture.tif", pair.capture)
    store = directory / "o.zarr"
    t, cpu = time.perf_counter(), _cpu_seconds()
    summary = detect(ref, dist, store, workers=workers, overwrite=True)
    seconds, cpu = time.perf_counter() - t, _cpu_seconds() - cpu
    group = tiles.open_result_store(store)
    mask = group["change_mask"][:] == 1
    score = group["change_score"][:]
    scale = group.attrs["intensity"]
    factor = ops.IntensityScale.from_dict(scale).scaled(1.0)
    c = ops.confusion(mask, pair.change_mask)
    out = {"size": size, "objects": pair.objects, "objects_on_clipped": pair.objects_on_clipped,
           "reference_clipped": pair.reference_clipped,
           "capture_clipped": float(np.mean((pair.capture == 0) | (pair.capture == 255))),
           "f_measure": c.f_measure, "precision": c.precision, "recall": c.recall,
           "recall_on_clipped": float(mask[pair.on_clipped].mean()) if pair.on_clipped.any() else float("nan"),
           "no_evidence_beyond_border": float(np.isnan(score[pair.covered]).mean()),
           "no_evidence": float(np.isnan(score).mean()), "seconds": seconds, "cpu_seconds": cpu,
           "registered_nan_beyond_border": float(np.isnan(group["registered"][:][pair.covered]).mean()),
           "no_evidence_summary": summary.no_evidence}
    # why: a clipped capture pixel with a model (registered) and no evidence is clipped on the side its model is
    # open (chi unbounded both ways, ops.changes._bounds); the rest have no model (e.g. failed rows)
    clipped_capture = (pair.capture == 0) | (pair.capture == 255)
    registered = group["registered"][:]
    silent = np.isnan(score) & clipped_capture & np.isfinite(registered)
    level = np.where(pair.capture == 255, 1.0, 0.0)
    at_level = np.abs(registered - level) * factor <= 0.01  # lambda_chi / 2 on the common scale
    out["no_evidence_clipped_same_side"] = float(silent[pair.covered].mean())
    out["no_evidence_model_at_clip"] = float((silent & at_level)[pair.covered].mean())
    t = time.perf_counter()
    reference = pair.reference.astype(np.float32) / 255.0
    capture = pair.capture.astype(np.float32) / 255.0
    with opencv_threads(workers) as threads:  # DIS on the cores rsmb had
        dis_mask = dis_changes(reference, capture, factor=factor)
    out["dis_seconds"] = time.perf_counter() - t
    out["rsmb_over_dis_seconds"] = seconds / out["dis_seconds"]
    d = ops.confusion(dis_mask, pair.change_mask)
    out["dis"] = {"threads": threads, "f_measure": d.f_measure, "precision": d.precision, "recall": d.recall,
                  "recall_on_clipped": float(dis_mask[pair.on_clipped].mean()) if pair.on_clipped.any()
                  else float("nan")}
    _echo(f"realclip {size} x {size} (aerials {', '.join(p.stem for p in paths)}, {100 * out['reference_clipped']:.1f} "
          f"% of the reference and {100 * out['capture_clipped']:.1f} % of the capture clipped; {pair.objects} new "
          f"objects, {pair.objects_on_clipped} on clipped areas): rsmb F {c.f_measure:.3f} (P {c.precision:.3f}, "
          f"R {c.recall:.3f}), recall on the objects on clipped areas {out['recall_on_clipped']:.3f}, no evidence "
          f"{100 * out['no_evidence_beyond_border']:.2f} % of the pixels beyond the border, of which "
          f"{100 * out['no_evidence_clipped_same_side']:.2f} % clipped in the capture on the side their model is open "
          f"({100 * out['no_evidence_model_at_clip']:.2f} % with the model at that clip level) "
          f"({100 * out['no_evidence']:.2f} % of all; registered NaN on {100 * out['registered_nan_beyond_border']:.2f} % "
          f"beyond the border), {seconds:.1f} s ({cpu:.1f} CPU-s); DIS dense flow (medium, OpenCV on "
          f"{threads} threads) with rsmb's change rule F {d.f_measure:.3f} "
          f"(P {d.precision:.3f}, R {d.recall:.3f}, recall on clipped areas "
          f"{out['dis']['recall_on_clipped']:.3f}), {out['dis_seconds']:.1f} s: rsmb takes "
          f"{out['rsmb_over_dis_seconds']:.2f}x DIS's time")
    shutil.rmtree(directory, ignore_errors=True)
    return out


def _cpu_seconds():
    """CPU-seconds of this process so far, every thread's (a wall time on a
    shared machine measures the neighbours too)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _echo(text):
    print(text, flush=True)
