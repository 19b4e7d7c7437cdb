"""``rsmb synth``: write a synthetic pair and its truth to a directory.

Files: ``reference.<ext>``, ``distorted.<ext>`` (16-bit PNG, GeoTIFF or float32
NPY), ``truth/change_mask.png``, ``truth/change_mask_reference.png`` (0/255),
``truth/trajectory.csv`` (per-row centroid pose, all six axes),
``truth/gain.npy`` (per-pixel gain) and ``truth/truth.json`` (everything else).
GeoTIFFs carry a made-up projected georeferencing (UTM 18N, 0.5 m pixels) so
that the geospatial path can be exercised end to end.
"""

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from rsmb import ops
from rsmb import tiles
from rsmb.ops import InputError
from rsmb.ops._errors import one_line

__all__ = ["FORMATS", "PairPaths", "synth", "write_pair", "read_truth", "DEMO_GEO"]

FORMATS = ("png", "tif", "npy")
DEMO_GEO = dict(crs="EPSG:32618", transform=(0.5, 0.0, 500000.0, 0.0, -0.5, 4500000.0))


class PairPaths(NamedTuple):
    """The two images of a written pair (the truth is in ``<out_dir>/truth``)."""

    reference: Path
    distorted: Path


def _geo():
    from rasterio.crs import CRS

    return tiles.GeoInfo(crs=CRS.from_string(DEMO_GEO["crs"]).to_wkt(version="WKT2_2019"),
                         transform=DEMO_GEO["transform"], nodata=None)


def _write_image(path, image, fmt):
    if fmt == "npy":
        np.save(path, image.astype(np.float32))
        return
    data = (np.clip(image, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
    if fmt == "tif":
        import rasterio

        geo = _geo()
        h, w = data.shape
        with rasterio.open(path, "w", driver="GTiff", height=h, width=w, count=1, dtype="uint16", crs=geo.crs,
                           transform=rasterio.Affine(*geo.transform), tiled=True, blockxsize=256, blockysize=256,
                           compress="deflate") as ds:
            ds.write(data, 1)
        return
    import cv2

    if not cv2.imwrite(str(path), data):
        raise InputError(f"{path}: could not write the image")


def _check_out_dir(out_dir, overwrite):
    """``out_dir`` as a Path, refused when it is a file, holds files without
    ``overwrite``, or cannot be created."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: output exists and is a file")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise InputError(f"{out}: output exists and is not empty; pass --overwrite to replace it")
    tiles.check_writable(out / "truth")
    return out


def synth(out_dir, *, shape=(512, 512), motion="inplane", shutter="rolling", exposure=None, scale=1.0, gain=1.0,
          changes=8, noise=0.002, seed=0, fmt="png", overwrite=False):
    """Make a synthetic pair with its truth (:func:`ops.synthesize_pair`) and
    write it to ``out_dir`` (:func:`write_pair`); returns its :class:`PairPaths`.

    ``gain`` is a number or a (left, right) pair (a gain varying across the
    columns); the other parameters are those of :func:`ops.synthesize_pair`.
    """
    _check_out_dir(out_dir, overwrite)
    gain = tuple(gain) if isinstance(gain, (list, tuple)) else gain
    if isinstance(gain, tuple) and len(gain) == 1:
        gain = gain[0]
    pair = ops.synthesize_pair(tuple(shape), motion=motion, shutter=shutter, exposure=exposure, scale=scale,
                               gain=gain, changes=changes, noise=noise, seed=seed)
    meta = {"motion": motion, "shutter": shutter, "exposure": exposure, "scale": scale, "gain": gain,
            "changes": changes, "noise": noise, "seed": seed}
    return write_pair(out_dir, pair, fmt=fmt, overwrite=overwrite, meta=meta)


def write_pair(out_dir, pair, *, fmt="png", overwrite=False, meta=None):
    """Write a :class:`ops.SyntheticPair` to ``out_dir``; returns its :class:`PairPaths`."""
    import cv2

    if fmt not in FORMATS:
        raise ops.ParameterError(f"format: expected one of {FORMATS}, got {fmt!r}")
    out = _check_out_dir(out_dir, overwrite)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    ref_path, dist_path = out / f"reference.{fmt}", out / f"distorted.{fmt}"
    _write_image(ref_path, pair.reference, fmt)
    _write_image(dist_path, pair.distorted, fmt)
    cv2.imwrite(str(out / "truth" / "change_mask.png"), pair.change_mask.astype(np.uint8) * 255)
    cv2.imwrite(str(out / "truth" / "change_mask_reference.png"), pair.change_mask_reference.astype(np.uint8) * 255)
    np.savetxt(out / "truth" / "trajectory.csv", pair.trajectory, delimiter=",", header=",".join(ops.POSE_AXES),
               comments="", fmt="%.6f")
    np.save(out / "truth" / "gain.npy", pair.gain.astype(np.float32))
    info = {"shape": list(pair.reference.shape), "focal_px": pair.camera.focal,
            "center_xy": list(pair.camera.center_xy), "pose_axes": list(ops.POSE_AXES),
            "gain_mean": float(pair.gain.mean()), "changed_fraction": float(pair.change_mask.mean()),
            **(meta or {})}
    (out / "truth" / "truth.json").write_text(json.dumps(tiles.jsonable(info), indent=2))
    return PairPaths(ref_path, dist_path)


def read_truth(truth_dir):
    """The truth a :func:`write_pair` directory holds, as a dict of arrays.

    Raises
    ------
    InputError
        If the directory or one of its files is missing.
    """
    import cv2

    base = Path(truth_dir)
    base = base / "truth" if (base / "truth").is_dir() else base
    need = ["change_mask.png", "change_mask_reference.png", "trajectory.csv", "gain.npy", "truth.json"]
    for name in need:
        if not (base / name).is_file():
            raise InputError(f"{base / name}: truth file missing (expected the layout written by rsmb synth)")
    def mask(path):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError("not a readable PNG")
        return image > 0

    out = {}
    for key, name, read in (
            ("change_mask", "change_mask.png", mask),
            ("change_mask_reference", "change_mask_reference.png", mask),
            ("trajectory", "trajectory.csv", lambda p: np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)),
            ("gain", "gain.npy", np.load),
            ("info", "truth.json", lambda p: json.loads(p.read_text()))):
        try:
            out[key] = read(base / name)
        except Exception as exc:  # noqa: BLE001 - cv2, numpy and json raise many types for a damaged file
            raise InputError(f"{base / name}: unreadable truth file ({type(exc).__name__}: {one_line(exc)})") \
                from None
    return out
