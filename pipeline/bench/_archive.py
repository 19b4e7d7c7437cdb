"""Synthetic survey archives with known truth, for tests and the benchmark.

A scene (procedural, or any image) is the ground; the reference is the scene
itself as a georeferenced orthomosaic (UTM 18N, 0.5 m pixels), written as one
file or split into several, optionally on another grid (pixel size, CRS).
Each capture sees a window of the scene, with new objects pasted into it,
through the RSMB forward model (:func:`ops.render`); it carries the nominal
georeferencing of its window, and its truth (change mask, trajectory) is
written beside it.  The same capture can also be written as a hand-cut pair:
the reference cut at the capture's window on the capture's grid.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rsmb import ops
from rsmb import tiles

from .._synth import DEMO_GEO, PairPaths

__all__ = ["CaptureSpec", "scene_geo", "write_reference", "write_capture"]

PIXEL = DEMO_GEO["transform"][0]  # m


@dataclass(frozen=True)
class CaptureSpec:
    """One capture of an archive.

    Attributes
    ----------
    origin_yx : tuple of int
        Row and column of the capture window's top-left pixel in the scene.
    shape : tuple of int
        (H, W) of the capture.
    seed : int
    changes : int
        Objects pasted into the window.
    motion : str
        A key of :data:`ops.MOTIONS`.
    exposure : float
        Row exposure in row periods.
    path : CameraPath or None
        The camera path, instead of a random one of ``motion``.
    interpolation : {"bilinear", "cubic"}
        How the capture is rendered (:func:`ops.render`).
    gain : float
        Illumination gain of the capture.
    """

    origin_yx: tuple
    shape: tuple
    seed: int = 0
    changes: int = 4
    motion: str = "inplane"
    exposure: float = 16.0
    path: object = None
    interpolation: str = "bilinear"
    gain: float = 1.0


def scene_geo(origin_yx=(0, 0)):
    """The archive's georeferencing (:data:`DEMO_GEO`) of the scene pixel
    ``origin_yx``'s grid: a :class:`tiles.GeoInfo`."""
    from rasterio.crs import CRS

    a, b, c, d, e, f = DEMO_GEO["transform"]
    return tiles.GeoInfo(crs=CRS.from_string(DEMO_GEO["crs"]).to_wkt(version="WKT2_2019"),
                         transform=(a, b, c + a * origin_yx[1], d, e, f + e * origin_yx[0]))


def _write(path, image, geo, dtype="uint16"):
    import rasterio

    data = image if dtype == "float32" else (np.clip(image, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
    profile = dict(driver="GTiff", height=image.shape[0], width=image.shape[1], count=1, dtype=dtype,
                   crs=geo.crs, transform=rasterio.Affine(*geo.transform), tiled=True, blockxsize=256,
                   blockysize=256, compress="deflate")
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(data.astype(dtype), 1)
    return Path(path)


def write_reference(directory, scene, *, split=1, crs=None, pixel=None):
    """The scene as a georeferenced reference mosaic in ``directory``.

    Parameters
    ----------
    scene : ndarray, shape (H, W), float32 in [0, 1]
    split : int
        Number of files, vertical strips of the scene (a capture may straddle two).
    crs : str, optional
        Another CRS (e.g. "EPSG:3857"): the mosaic is warped to it (bilinear).
    pixel : float, optional
        Another pixel size, in the target CRS's units.

    Returns
    -------
    list of Path
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    edges = np.linspace(0, scene.shape[1], split + 1).round().astype(int)
    paths = []
    for k, (c0, c1) in enumerate(zip(edges[:-1], edges[1:])):
        path = _write(directory / f"mosaic_{k}.tif", scene[:, c0:c1], scene_geo((0, c0)))
        if crs is not None or pixel is not None:
            path = _warp(path, directory / f"mosaic_{k}_warped.tif", crs, pixel)
        paths.append(path)
    return paths


def _warp(source, target, crs, pixel):
    """``source`` reprojected to ``crs`` (and/or ``pixel`` size), bilinear; the
    source file is removed."""
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    with rasterio.open(source) as src:
        dst_crs = crs or src.crs
        transform, width, height = calculate_default_transform(src.crs, dst_crs, src.width, src.height,
                                                               *src.bounds, resolution=pixel)
        profile = src.profile | dict(crs=dst_crs, transform=transform, width=width, height=height, nodata=0)
        with rasterio.open(target, "w", **profile) as dst:
            reproject(rasterio.band(src, 1), rasterio.band(dst, 1), resampling=Resampling.bilinear, dst_nodata=0)
    Path(source).unlink()
    return Path(target)


def _capture(scene, spec, noise):
    """(capture image, truth mask, trajectory) of ``spec`` over ``scene``."""
    (r0, c0), (h, w) = spec.origin_yx, spec.shape
    camera = ops.Camera.for_shape((h, w))
    path = spec.path or ops.motion_path(spec.motion, duration=h + spec.exposure + 1.0, seed=spec.seed)
    window = scene[r0:r0 + h, c0:c0 + w]
    changed_window, pasted_window = ops.paste_changes(window, count=spec.changes, size_range=(14, 36),
                                                      seed=spec.seed + 1, margin=24)
    changed, pasted = scene.copy(), np.zeros(scene.shape, np.float32)
    changed[r0:r0 + h, c0:c0 + w] = changed_window
    pasted[r0:r0 + h, c0:c0 + w] = pasted_window
    kw = dict(shape=(h, w), camera=camera, exposure=spec.exposure, source_origin_yx=(r0, c0),
              interpolation=spec.interpolation)
    seen = ops.render(changed, path, **kw)
    truth = ops.render(pasted, path, **kw)
    image = seen.image * np.float32(spec.gain) + np.random.default_rng(spec.seed + 2).normal(0, noise, (h, w)).astype(np.float32)
    return np.where(seen.valid, image, 0.0).astype(np.float32), truth.image > 0.5, pasted_window, seen.centroid


def write_capture(path, scene, spec, *, noise=0.002, georeferenced=True, offset_m=(0.0, 0.0), hand_cut=None):
    """Write the capture ``spec`` of ``scene`` to ``path`` (GeoTIFF) and its truth
    to ``<path without suffix>.truth/`` (the layout :func:`read_truth` reads).

    Parameters
    ----------
    georeferenced : bool
        False writes the capture without georeferencing.
    offset_m : tuple of float
        (east, north) metres added to the capture's georeferencing (a capture
        that claims to be elsewhere).
    hand_cut : str or Path, optional
        Also write the hand-cut same-grid pair into this directory:
        ``reference.tif`` (the scene at the capture's window) and
        ``distorted.tif``.

    Returns
    -------
    PairPaths or None
        The hand-cut pair when asked for.
    """
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image, mask, mask_reference, trajectory = _capture(scene, spec, noise)
    geo = scene_geo(spec.origin_yx)
    a, b, c, d, e, f = geo.transform
    geo = tiles.GeoInfo(crs=geo.crs, transform=(a, b, c + offset_m[0], d, e, f + offset_m[1]))
    _write(path, image, geo if georeferenced else tiles.GeoInfo(crs=None, transform=(1, 0, 0, 0, 1, 0)))
    truth = path.with_suffix(".truth")
    truth.mkdir(parents=True, exist_ok=True)
    (r0, c0), (h, w) = spec.origin_yx, spec.shape
    reference = scene[r0:r0 + h, c0:c0 + w]
    cv2.imwrite(str(truth / "change_mask.png"), mask.astype(np.uint8) * 255)
    cv2.imwrite(str(truth / "change_mask_reference.png"), mask_reference.astype(np.uint8) * 255)
    np.savetxt(truth / "trajectory.csv", trajectory, delimiter=",", header=",".join(ops.POSE_AXES), comments="",
               fmt="%.6f")
    np.save(truth / "gain.npy", np.ones((h, w), np.float32))
    import json

    (truth / "truth.json").write_text(json.dumps({"shape": [h, w], "origin_yx": list(spec.origin_yx),
                                                  "seed": spec.seed, "motion": spec.motion}))
    if hand_cut is None:
        return None
    hand_cut = Path(hand_cut)
    hand_cut.mkdir(parents=True, exist_ok=True)
    return PairPaths(_write(hand_cut / "reference.tif", reference, scene_geo(spec.origin_yx)),
                     _write(hand_cut / "distorted.tif", image, scene_geo(spec.origin_yx)))
