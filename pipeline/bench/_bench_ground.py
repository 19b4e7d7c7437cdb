"""The ``ground`` section of ``rsmb bench``: are a night's GIS products where
the changes are on the ground?

A synthetic georeferenced night (:mod:`._archive`): captures of windows of one
scene (a real aerial photograph from ``--data``'s ``aerial/``, else a
procedural scene) whose nominal georeferencing is off by a few metres, as real
navigation is.  Each pasted change's ground position is known: its pixels in
the scene, on the reference's grid.  Through ``rsmb survey``, per capture:

- the distance from each true change to its polygon in ``changes.gpkg``
  (centroid to centroid, in pixels; each polygon belongs to the true change
  nearest it, and a change found in parts is the union of its parts; inf for
  a change with none), and their median;
- the same for polygons made from the capture-frame arrays (``change_mask``,
  ``change_score``) on the capture's nominal transform: how the products were
  made before they moved to the ground frame;
- whether the COGs and the polygons agree with the store's
  ``change_mask_reference`` (and the score COG with ``change_score_reference``).
"""

import json
import time
from pathlib import Path

import numpy as np

from rsmb import tiles

from ._archive import PIXEL, CaptureSpec, scene_geo, write_capture, write_reference

__all__ = ["bench_ground", "capture_distances", "product_agreement", "true_changes"]

#: (east, north) metres by which each capture's nominal georeferencing is off.
OFFSETS_M = ((3.0, -2.0), (-4.0, 1.5), (2.5, 3.5), (-1.5, -4.0), (4.0, 2.0), (-3.0, -3.0))


def _echo(text):
    print(text, flush=True)


def true_changes(truth_dir):
    """The true changes of a capture written by :func:`write_capture`: the
    (x, y) centroids, in CRS units, of the 8-connected components of its pasted
    pixels on the ground (the scene's grid, whatever the capture claims)."""
    import cv2
    from scipy import ndimage

    truth_dir = Path(truth_dir)
    mask = cv2.imread(str(truth_dir / "change_mask_reference.png"), cv2.IMREAD_UNCHANGED) > 0
    origin = json.loads((truth_dir / "truth.json").read_text())["origin_yx"]
    labels, count = ndimage.label(mask, structure=np.ones((3, 3)))
    rows, cols = np.asarray(ndimage.center_of_mass(mask, labels, np.arange(1, count + 1))).reshape(-1, 2).T
    a, b, c, d, e, f = scene_geo(origin).transform
    return np.stack([a * (cols + 0.5) + b * (rows + 0.5) + c, d * (cols + 0.5) + e * (rows + 0.5) + f], axis=1)


def _distances_px(truth_xy, geometries, pixel=PIXEL):
    """Per true change, the distance from its centroid to its polygon's, in
    pixels.  Each polygon belongs to the true change whose centroid is nearest
    its own (a change found in parts has several); a change's polygon is the
    union of those.  inf for a change with none (missed)."""
    from shapely import union_all

    out = np.full(len(truth_xy), np.inf)
    if not len(geometries) or not len(truth_xy):
        return out
    centres = np.array([(g.centroid.x, g.centroid.y) for g in geometries])
    owner = np.hypot(truth_xy[None, :, 0] - centres[:, None, 0], truth_xy[None, :, 1] - centres[:, None, 1]).argmin(1)
    for k in np.unique(owner):
        c = union_all([g for g, o in zip(geometries, owner) if o == k]).centroid
        out[k] = float(np.hypot(truth_xy[k, 0] - c.x, truth_xy[k, 1] - c.y)) / pixel
    return out


def _gpkg_geometries(path):
    import shapely
    from pyogrio.raw import read

    _, _, geometry, _ = read(path, layer="changes")
    return [shapely.from_wkb(g) for g in geometry]


def _capture_frame_geometries(store):
    """Polygons from the capture-frame arrays on the capture's nominal
    transform: how ``changes.gpkg`` was made before the ground frame."""
    from rsmb.tiles._products import _geometry

    group = tiles.open_result_store(store)
    geo = tiles.GeoInfo.from_attrs(group.attrs.asdict())
    return [_geometry(f.polygons) for f in tiles.change_polygons(group["change_mask"][:] == 1,
                                                                 group["change_score"], geo)]


def capture_distances(folder, truth_dir):
    """Distances (pixels) from each true change of a capture to its polygon:
    ``{"ground": ..., "capture_frame": ...}`` for the polygons of the
    capture's ``changes.gpkg`` and for those of its capture-frame arrays."""
    truth = true_changes(truth_dir)
    folder = Path(folder)
    return {"ground": _distances_px(truth, _gpkg_geometries(folder / "changes.gpkg")),
            "capture_frame": _distances_px(truth, _capture_frame_geometries(folder / "changes.zarr"))}


def product_agreement(folder):
    """Do a capture's products hold its store's ground frame?  Each COG
    against the store array of its name (NaN equal to NaN), and the polygons
    of ``changes.gpkg`` rasterised on the store's grid against
    ``change_mask_reference == 1``, with their ``pixels`` field summed."""
    import rasterio
    from pyogrio.raw import read
    from rasterio.features import rasterize

    folder = Path(folder)
    group = tiles.open_result_store(folder / "changes.zarr")
    out = {}
    for name in ("change_mask_reference", "change_score_reference", "parallax_mask_reference"):
        with rasterio.open(folder / f"{name}.tif") as ds:
            out[name] = bool(np.array_equal(ds.read(1), group[name][:], equal_nan=True))
            transform, shape = ds.transform, ds.shape
    changed = group["change_mask_reference"][:] == 1
    geometries = _gpkg_geometries(folder / "changes.gpkg")
    burnt = rasterize([(g, 1) for g in geometries], out_shape=shape, transform=transform, fill=0,
                      dtype="uint8") if geometries else np.zeros(shape, np.uint8)
    out["polygons"] = bool(np.array_equal(burnt == 1, changed))
    out["pixels"] = bool(int(read(folder / "changes.gpkg", layer="changes")[3][0].sum()) == int(changed.sum()))
    return out


def write_night(root, scene, *, captures, side, changes, seed=60):
    """Captures of ``side`` px over ``scene`` at spread-out windows, each with
    its nominal georeferencing off by :data:`OFFSETS_M`; a reference mosaic of
    two files.  Returns (reference paths, captures folder)."""
    root = Path(root)
    references = write_reference(root / "reference", scene, split=2)
    h, w = scene.shape
    spots_r = np.linspace(32, h - side - 32, 2).astype(int)
    spots_c = np.linspace(32, w - side - 32, -(-captures // 2)).astype(int)
    origins = [(int(r), int(c)) for c in spots_c for r in spots_r][:captures]
    for k, origin in enumerate(origins):
        write_capture(root / "incoming" / f"capture_{k}.tif", scene,
                      CaptureSpec(origin, (side, side), seed=seed + k, changes=changes, exposure=32.0),
                      offset_m=OFFSETS_M[k % len(OFFSETS_M)])
    return references, root / "incoming"


def bench_ground(data, workdir, *, quick=False):
    """A night whose polygons are checked against the true ground positions."""
    from ._bench_survey import _measured, _scene

    captures, side = (2, 384) if quick else (6, 768)
    work = Path(workdir, "ground")
    scene, source = _scene(data, (side * 2 + 64, side * 3 + 64) if not quick else (side * 2 + 64, side + 64))
    references, incoming = write_night(work, scene, captures=captures, side=side, changes=8 if quick else 12)
    start = time.perf_counter()
    proc = _measured("-q", "survey", *references, "--captures", incoming / "*.tif", "-o", work / "out", "--json",
                     "--no-report", "--settle", "0", codes=(0, 3))
    seconds = time.perf_counter() - start
    summary = json.loads(proc.stdout)
    out = {"scene": source, "captures": [], "seconds": seconds, "failed": summary["failed"]}
    _echo(f"ground ({source}): {captures} captures of {side} x {side}, nominal georeferencing off by "
          f"{', '.join(f'({e:+.1f}, {n:+.1f})' for e, n in OFFSETS_M[:captures])} m (east, north); "
          f"distance from each true change to its polygon, px (0.5 m)")
    for c in summary["captures"]:
        if c["status"] != "done":
            out["captures"].append({"capture": Path(c["capture"]).name, "status": c["status"], "reason": c["reason"]})
            _echo(f"  {Path(c['capture']).name}: {c['status']} {c['reason']}")
            continue
        truth = Path(c["capture"]).with_suffix(".truth")
        dist = capture_distances(c["output"], truth)
        agree = product_agreement(c["output"])
        found = np.isfinite(dist["ground"])
        row = {"capture": Path(c["capture"]).name, "status": "done", "true_changes": len(dist["ground"]),
               "found": int(found.sum()), "polygons": c["changes"], "median_px": float(np.median(dist["ground"])),
               "max_px_found": float(dist["ground"][found].max()) if found.any() else float("nan"),
               "median_px_capture_frame": float(np.median(dist["capture_frame"])), "agreement": agree}
        out["captures"].append(row)
        _echo(f"  {row['capture']}: {row['true_changes']} true changes ({row['found']} with a polygon), "
              f"{row['polygons']} polygons: median {row['median_px']:.2f} px (max {row['max_px_found']:.2f} over "
              f"those found); from the capture-frame arrays "
              f"{row['median_px_capture_frame']:.2f} px; products agree with change_mask_reference: "
              f"{all(agree.values())} {'' if all(agree.values()) else agree}")
    done = [r for r in out["captures"] if r["status"] == "done"]
    out["worst_median_px"] = max((r["median_px"] for r in done), default=float("nan"))
    out["worst_median_px_capture_frame"] = max((r["median_px_capture_frame"] for r in done), default=float("nan"))
    _echo(f"  worst capture's median: {out['worst_median_px']:.2f} px (capture-frame arrays "
          f"{out['worst_median_px_capture_frame']:.2f} px); survey {seconds:.1f} s")
    return out
