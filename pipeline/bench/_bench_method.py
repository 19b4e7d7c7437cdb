"""``rsmb bench`` sections for what real captures bring (issue 9), with the
default options throughout:

- ``yaw``: camera yaw and pitch up to +-3 deg with in-plane motion, captures
  of a real aerial photograph (``--data``; else a procedural scene) against a
  larger georeferenced reference, at 512 and 2048 px; the hardest case also
  without the slow yaw/pitch part;
- ``parallax``: raised structures at relative depths 0.4-0.8 under a
  translation of 15-19 px, with pasted changes, with and without the
  depth-layer step; four raised blocks with new objects on a roof and
  against a block (per-object recall of those two);
- ``intensity``: a capture 35 % brighter than its reference with a fifth of
  its pixels clipped, and one pair stored at four bit depths and units.

Every capture is rendered by the independent cubic renderer, never by the
solver's own warp.
"""

import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from rsmb import ops
from rsmb.ops.synthetic._synth import readout_path

from ._archive import CaptureSpec, write_capture, write_reference
from ..detection._detect import detect
from .._evaluate import evaluate
from ..detection._plan import DetectConfig
from .._synth import write_pair

__all__ = ["BIT_DEPTHS", "bench_intensity", "bench_parallax", "bench_yaw", "clipped_pair", "readout_path"]

EXPOSURE = 32.0  # row periods


def _echo(text):
    print(text, flush=True)


def _scores(store, truth):
    c = evaluate(store, truth).changes
    return {"f_measure": c.f_measure, "precision": c.precision, "recall": c.recall}


# -------------------------------------------------------------------------- yaw

YAW_CASES = {
    "yaw -3 -> +3 deg": dict(ry=(-3, 3), tx=(0, 4), ty=(1, 3)),
    "yaw +3 -> +2.5 deg, tx -20 px": dict(ry=(3, 2.5), tx=(-20, -18), ty=(1, 3)),
    "pitch +3 -> -3 deg": dict(rx=(3, -3), tx=(0, 4), ty=(1, 3)),
    "pitch and yaw +-3 deg with tx, ty, rz": dict(rx=(-3, 3), ry=(-3, 3), tx=(-5, 5, 2), ty=(-4, 4, 2),
                                                  rz=(-1.5, 1.5)),
    "in-plane only": dict(tx=(-8, 8, 3), ty=(0, 6, 2), rz=(-1, 1.5)),
}
HARDEST = "pitch and yaw +-3 deg with tx, ty, rz"


def _aerial(data, side):
    """The first aerial photograph of ``data`` as it is (luminance in [0, 1]),
    upscaled (bicubic) only when smaller than ``side``; else a procedural
    scene.  Returns (scene, its name)."""
    from rsmb import tiles

    images = sorted(Path(data, "aerial").glob("*.png")) if data else []
    if not images:
        return ops.aerial_scene((side, side), seed=5).astype(np.float32), "procedural"
    image = tiles.read_image(images[0]).data
    if min(image.shape) < side:
        image = np.clip(cv2.resize(image, (side, side), interpolation=cv2.INTER_CUBIC), 0.0, 1.0)
    return image, f"aerial/{images[0].name}"


def bench_yaw(data, workdir, *, sizes=(512, 2048), workers=None):
    """Each capture a window in the middle of the scene, which is the
    georeferenced reference (at least 200 px larger on every side)."""
    out = {}
    for size in sizes:
        scene, source = _aerial(data, size + 400)
        margin = (min(scene.shape) - size) // 2
        directory = Path(workdir, f"yaw_{size}")
        references = write_reference(directory / "reference", scene)
        results = out[size] = {"scene": source}
        for k, (name, axes) in enumerate(YAW_CASES.items()):
            spec = CaptureSpec((margin, margin), (size, size), seed=k + 1, changes=8 * max(1, size // 512) ** 2,
                               exposure=EXPOSURE, path=readout_path(size, EXPOSURE, **axes), interpolation="cubic")
            capture = directory / f"capture_{k}.tif"
            write_capture(capture, scene, spec)
            configs = {"default": DetectConfig()}
            if name == HARDEST:
                configs["without the slow part"] = DetectConfig(registration=ops.RegistrationParams(slow_axes=()))
            for label, config in configs.items():
                store = directory / f"capture_{k}_{len(label)}.zarr"
                t = time.perf_counter()
                detect(references, capture, store, config=config, workers=workers, overwrite=True)
                r = results[name if label == "default" else f"{name}, {label}"] = {
                    **_scores(store, capture.with_suffix(".truth")), "seconds": time.perf_counter() - t}
                _echo(f"yaw/pitch {size} x {size} ({source}), {name}{'' if label == 'default' else ', ' + label}: "
                      f"F {r['f_measure']:.3f} (P {r['precision']:.3f}, R {r['recall']:.3f}), {r['seconds']:.1f} s")
                shutil.rmtree(store, ignore_errors=True)
        shutil.rmtree(directory, ignore_errors=True)
    return out


# --------------------------------------------------------------------- parallax


def bench_parallax(workdir, *, sizes=(512, 1024), workers=None):
    out = {}
    for size in sizes:
        n = max(1, size // 512) ** 2
        path = readout_path(size, 24.0, tx=(15, 19), ty=(3, 6), rz=(-0.5, 0.5))
        pair = ops.synthesize_pair((size, size), path=path, exposure=24.0, changes=6 * n, structures=6 * n,
                                   noise=0.002, seed=5, interpolation="cubic")
        directory = Path(workdir, f"parallax_{size}")
        paths = write_pair(directory, pair, fmt="npy", overwrite=True)
        results = out[size] = {"true_depths": sorted(float(d) for d in pair.depths)}
        for label, config in (("layers", DetectConfig()),
                              ("no layers", DetectConfig(changes=ops.ChangeParams(layers=False)))):
            store = directory / f"{label.replace(' ', '_')}.zarr"
            s = detect(paths.reference, paths.distorted, store, config=config, workers=workers, overwrite=True)
            r = results[label] = {**_scores(store, directory), "parallax_components": s.parallax_components,
                                  "seconds": s.timings["total_s"]}
        a, b = results["layers"], results["no layers"]
        _echo(f"parallax {size} x {size}, {len(pair.depths)} raised structures (depth "
              f"{min(pair.depths):.2f}-{max(pair.depths):.2f}), translation 15-19 px, {6 * n} changes: depth layers "
              f"P {a['precision']:.3f}, R {a['recall']:.3f}, F {a['f_measure']:.3f} ({a['parallax_components']} "
              f"parallax components, {a['seconds']:.1f} s); --no-layers P {b['precision']:.3f}, R {b['recall']:.3f}, "
              f"F {b['f_measure']:.3f} ({b['seconds']:.1f} s)")
        shutil.rmtree(directory, ignore_errors=True)
    out["objects on and against blocks"] = _bench_blocks(workdir, workers=workers)
    return out


def _bench_blocks(workdir, *, size=512, workers=None):
    """Four raised blocks (parallax up to 20 px) with new objects on the ground
    around them, one on the nearest roof and one touching a block: per-pixel
    parallax keeps those two changes (issue 15)."""
    from rsmb import tiles
    from rsmb.ops.synthetic._raised import AWAY, raised_pair

    pair, objects = raised_pair((size, size), seed=7)
    directory = Path(workdir, "blocks")
    paths = write_pair(directory, pair, fmt="npy", overwrite=True)
    results = {"true_depths": sorted(float(d) for d in pair.depths)}
    for label, config in (("layers", DetectConfig()),
                          ("no layers", DetectConfig(changes=ops.ChangeParams(layers=False)))):
        store = directory / f"{label.replace(' ', '_')}.zarr"
        detect(paths.reference, paths.distorted, store, config=config, workers=workers, overwrite=True)
        arrays = tiles.open_result_store(store)
        mask, parallax = arrays["change_mask"][:] == 1, arrays["parallax_mask"][:] == 1
        results[label] = {**_scores(store, directory), "objects": [
            {"kind": kind, "pixels": int(m.sum()), "recall": float(mask[m].mean()),
             "in_parallax": float(parallax[m].mean())} for kind, m in objects if kind != AWAY]}
    a, b = results["layers"], results["no layers"]
    near = ", ".join(f"{o['kind']} {o['recall']:.2f} ({o['in_parallax']:.2f} in parallax_mask)" for o in a["objects"])
    _echo(f"parallax {size} x {size}, 4 raised blocks (depth {min(pair.depths):.2f}-{max(pair.depths):.2f}, parallax "
          f"up to 20 px), {len(objects)} new objects: depth layers P {a['precision']:.3f}, R {a['recall']:.3f}, "
          f"F {a['f_measure']:.3f}; recall of the object {near}; --no-layers P {b['precision']:.3f}, "
          f"R {b['recall']:.3f}, F {b['f_measure']:.3f}")
    shutil.rmtree(directory, ignore_errors=True)
    return results


# -------------------------------------------------------------------- intensity


def _geotiff(path, data):
    import rasterio

    with rasterio.open(path, "w", driver="GTiff", height=data.shape[0], width=data.shape[1], count=1,
                       dtype=data.dtype) as ds:
        ds.write(data, 1)
    return path


def _png(path, data, dtype):
    if not cv2.imwrite(str(path), data.astype(dtype)):
        raise OSError(f"{path}: could not be written")
    return path


#: One image (intensities in [0, 1]) written at a bit depth and unit: name ->
#: writer(path without suffix, image) -> path written.
BIT_DEPTHS = {
    "8-bit png": lambda p, x: _png(p.with_suffix(".png"), np.round(x * 255), np.uint8),
    "12-bit in 16-bit png": lambda p, x: _png(p.with_suffix(".png"), np.round(x * 4095), np.uint16),
    "16-bit tif": lambda p, x: _geotiff(p.with_suffix(".tif"), np.round(x * 65535).astype(np.uint16)),
    "float32 tif, offset and scale": lambda p, x: _geotiff(p.with_suffix(".tif"),
                                                           (1234.5 + 37.25 * x).astype(np.float32)),
}


def clipped_pair(directory, shape, *, seed=32, gain=1.35, clipped=0.2):
    """A capture ``gain`` times brighter than its reference whose 8-bit sensor
    saturates on its brightest ``clipped`` share (bright fields, and the new
    objects that are bright: an object takes the tone that contrasts with the
    ground around it), both written as 8-bit PNGs in ``directory``
    with the truth beside them.  Returns (pair, reference path, capture path)."""
    side = int(1.5625 * max(shape))
    scene = (0.25 + 0.7 * ops.aerial_scene((side, side), seed=seed + 1)).astype(np.float32)
    pair = ops.synthesize_pair(shape, motion="inplane", changes=max(6, shape[0] * shape[1] // 11000), noise=0.002,
                               seed=seed, gain=gain, interpolation="cubic", scene=scene)
    saturation = np.percentile(pair.distorted, 100 * (1 - clipped))  # radiance at which the sensor saturates
    directory = Path(directory)
    write_pair(directory, pair, fmt="npy", overwrite=True)  # the truth
    eight = [_png(directory / f"{name}.png", np.round(np.clip(image / saturation, 0, 1) * 255), np.uint8)
             for name, image in (("reference", pair.reference), ("distorted", pair.distorted))]
    return pair, eight[0], eight[1]


def bench_intensity(workdir, *, size=1024, workers=None):
    from rsmb import tiles

    directory = Path(workdir, "clipped")
    pair, ref, dist = clipped_pair(directory, (size, size))
    store = directory / "o.zarr"
    s = detect(ref, dist, store, workers=workers, overwrite=True)
    arrays = tiles.open_result_store(store)
    mask = arrays["change_mask"][:] == 1
    clipped = tiles.read_image(dist).data >= 1.0  # at the 8-bit sensor's saturation value
    outside = ~pair.change_mask & pair.valid  # clipped pixels included
    unclipped = ops.confusion(mask, pair.change_mask, valid=~clipped)
    out = {"clipped": {**_scores(store, directory), "false_change_pwc": 100.0 * float(mask[outside].mean()),
                       "clipped_capture": s.clipped_capture,
                       "true_changes_clipped": float(clipped[pair.change_mask].mean()),
                       "recall_clipped": float(mask[pair.change_mask & clipped].mean()),
                       "f_measure_where_not_clipped": unclipped.f_measure}}
    r = out["clipped"]
    _echo(f"clipped {size} x {size}: capture 35 % brighter, {100 * r['clipped_capture']:.1f} % of its pixels "
          f"clipped: F {r['f_measure']:.3f} (P {r['precision']:.3f}, R {r['recall']:.3f}; "
          f"{100 * r['true_changes_clipped']:.0f} % of the true change pixels are clipped, recall on them "
          f"{r['recall_clipped']:.3f}, F on the rest {r['f_measure_where_not_clipped']:.3f}), false changes "
          f"{r['false_change_pwc']:.3f} % of the pixels outside the true changes (clipped ones included)")
    shutil.rmtree(directory, ignore_errors=True)
    pair = ops.synthesize_pair((size, size), motion="inplane", changes=max(6, size * size // 11000), noise=0.002,
                               seed=31, interpolation="cubic")
    masks = {}
    for k, (name, write) in enumerate(BIT_DEPTHS.items()):
        d = Path(workdir, f"bits_{k}")
        d.mkdir(parents=True, exist_ok=True)
        ref = write(d / "reference", np.clip(pair.reference, 0, 1))
        dist = write(d / "distorted", np.clip(pair.distorted, 0, 1))
        detect(ref, dist, d / "o.zarr", workers=workers, overwrite=True)
        masks[name] = tiles.open_result_store(d / "o.zarr")["change_mask"][:] == 1
        shutil.rmtree(d, ignore_errors=True)
    names = list(masks)
    iou = {f"{a} / {b}": float((masks[a] & masks[b]).sum() / max((masks[a] | masks[b]).sum(), 1))
           for i, a in enumerate(names) for b in names[i + 1:]}
    f = {name: ops.confusion(m, pair.change_mask).f_measure for name, m in masks.items()}
    out["bit_depths"] = {"iou": iou, "f_measure": f}
    _echo(f"bit depths {size} x {size}: change-mask IoU between every two of {', '.join(names)}: min "
          f"{min(iou.values()):.4f}; F {' / '.join(f'{v:.3f}' for v in f.values())}")
    return out
