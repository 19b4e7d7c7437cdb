"""Small colour previews of a detect run's two inputs, kept in its store.

A report shows the reference (before) and the capture (after) as a surveyor
sees them, in colour where the inputs have it; it must not depend on the
inputs still being where the run found them.  So ``rsmb detect`` makes both
(:func:`preview_arrays`, in a thread of its own beside the run's tasks) and
stores them at its end (:func:`write_previews`) as small RGBA arrays:

``preview_capture``
    The capture on its own pixel grid (sensor frame), block mean of
    ``factor`` x ``factor`` pixels.
``preview_reference``
    The reference as it was compared: in pixel mode its own pixels (the same
    grid as the capture's); when georeferenced, the reference set resampled
    (GDAL ``average``, the first file with data wins) onto the capture's
    nominal grid (ground frame), the grid ``change_mask_reference`` is on.

Both are uint8, shape ``(ceil(H / factor), ceil(W / factor), 4)`` with the
longer side at most :data:`PREVIEW_SIDE`; alpha 0 where the input has no data
(alpha band, nodata, NaN, outside the reference).  8-bit inputs keep their
values; other bit depths and floats are stretched from their 0.5th to 99.5th
percentile of valid values (each image on its own).  One or two bands are
gray, three or more the first three colour bands.  Inputs are read in strips
(memory bounded by a strip, never by the image).
"""

import contextlib
import math
import os
import warnings

import numpy as np

from rsmb import tiles

from ._report_figures import _reduce_band

__all__ = ["PREVIEW_NAMES", "PREVIEW_SIDE", "preview_arrays", "preview_factor", "read_preview", "reduce_preview",
           "write_previews"]

PREVIEW_SIDE = 1024  # px, the longer side of a preview at most
PREVIEW_NAMES = ("preview_reference", "preview_capture")
_STRIP_ROWS = 256  # input rows read at a time (rounded up to whole preview rows)
_STRETCH = (0.5, 99.5)  # percentiles mapped to 0 and 255 for inputs that are not 8-bit


def preview_factor(shape, side=PREVIEW_SIDE):
    """Input pixels per preview pixel on a side: the smallest integer leaving
    the longer side of ``shape`` at most ``side``."""
    return max(1, math.ceil(max(shape) / side))


def preview_arrays(pairing, *, side=PREVIEW_SIDE):
    """The two previews of a run's inputs, read from the input files (no
    store needed: ``rsmb detect`` makes them beside its tasks).

    Parameters
    ----------
    pairing : tiles.Pairing
        How the run compared the capture with its reference set.
    side : int
        Longest side of a preview, px.

    Returns
    -------
    factor : int
    previews : dict
        ``{name: (rgba uint8 (h, w, 4), frame)}`` for :data:`PREVIEW_NAMES`.
    """
    factor = preview_factor(pairing.shape, side)
    shape = tuple(-(-n // factor) for n in pairing.shape)
    capture = _read_preview(pairing.capture, factor)
    if pairing.mode == "georeferenced":
        reference = _warp_preview(pairing.reference_grids, pairing.grid, factor, shape)
        frame = "ground: the reference set resampled onto the capture's nominal grid"
    else:
        reference = _read_preview(pairing.references[0], factor)
        frame = "the reference's own pixels (compared pixel for pixel)"
    return factor, {"preview_reference": (reference, frame),
                    "preview_capture": (capture, "sensor: the capture's own pixels")}


def write_previews(group, pairing, *, side=PREVIEW_SIDE, previews=None):
    """Write ``preview_reference`` and ``preview_capture`` into a detect store.

    Parameters
    ----------
    group : zarr.Group
        The store being written (replaced if the arrays exist).
    pairing : tiles.Pairing
        How the run compared the capture with its reference set.
    side : int
        Longest side of a preview, px.
    previews : tuple, optional
        What :func:`preview_arrays` returned for ``pairing`` and ``side``
        (made now when not given).
    """
    factor, arrays = preview_arrays(pairing, side=side) if previews is None else previews
    for name in PREVIEW_NAMES:
        rgba, where = arrays[name]
        # written whole, as one chunk that is never all fill (alpha 0 everywhere: an input with no data):
        # zarr's check for an empty chunk compares (h, w, 4) against a broadcast 0, an inner loop of 4
        # elements per call, slower than the compression (``write_empty_chunks`` skips the check)
        array = group.create_array(name, shape=rgba.shape, dtype="uint8", chunks=rgba.shape,
                                   dimension_names=["preview_row", "preview_col", "rgba"], overwrite=True,
                                   compressors=tiles.IMAGE_COMPRESSORS, config={"write_empty_chunks": True})
        array[:] = rgba
        array.update_attributes({"factor": factor, "frame": where,
                            "description": "RGBA preview, block mean of factor x factor input pixels; "
                                           "alpha 0 where the input has no data"})


def read_preview(group, name):
    """A stored preview (uint8 RGBA) and its factor, or ``(None, None)`` for a
    store written before previews were kept."""
    if name not in group:
        return None, None
    array = group[name]
    return np.asarray(array[:]), int(array.attrs.get("factor", 1))


def reduce_preview(rgba, factor):
    """A preview ``factor`` times smaller on a side: block mean of the colours
    of its pixels with data; alpha 0 where a block has none."""
    if factor == 1:
        return rgba
    h, w = rgba.shape[:2]
    if h % factor == 0 and w % factor == 0 and (rgba[..., 3] == 255).all():  # whole blocks, all with data
        # the block sums in integers, as whole-array adds of the factor ** 2 strided views (a sum over an
        # axis of a few elements runs an inner loop per element), divided in float32: the same bytes as the
        # float32 block mean, whose sums are exact
        sums = np.zeros((h // factor, w // factor, 3), np.uint32)
        for i in range(factor):
            for j in range(factor):
                sums += rgba[i::factor, j::factor, :3]
        rgb = (sums.astype(np.float32) / np.float32(factor * factor) + np.float32(0.5)).astype(np.uint8)
        return np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], axis=-1)
    bands = np.where(rgba[..., 3] > 0, np.moveaxis(rgba[..., :3], -1, 0).astype(np.float32), np.float32(np.nan))
    return _to_rgba(np.stack([_reduce_band(b, factor, "mean") for b in bands]), True)


# --------------------------------------------------------------------------- reading the inputs


def _read_preview(path, factor):
    """RGBA preview of one image file or zarr/NPY array, read in strips."""
    strip = factor * max(1, -(-_STRIP_ROWS // factor))
    parts = []
    with _strip_reader(path) as (reader, height, eight_bit):
        for r0 in range(0, height, strip):
            bands, valid = reader(r0, min(height, r0 + strip))
            bands = np.where(valid, bands, np.float32(np.nan))
            parts.append(np.stack([_reduce_band(b, factor, "mean") for b in bands]))
    return _to_rgba(np.concatenate(parts, axis=1), eight_bit)


@contextlib.contextmanager
def _strip_reader(path):
    """``(read(r0, r1) -> (bands (n, rows, W) float32, valid (rows, W)), H, 8-bit?)``."""
    if os.path.isdir(path) or path.lower().endswith(".npy"):
        yield _array_reader(path)
        return
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        ds = rasterio.open(path)
    with ds:
        yield _raster_reader(ds)


def _color_bands(count, alpha):
    """Indices of the bands drawn: the first three that are not alpha, or the first (gray)."""
    color = [i for i in range(count) if i != alpha]
    return color[:3] if len(color) >= 3 else color[:1]


def _array_reader(path):
    import zarr

    array = zarr.open_array(store=path, mode="r") if os.path.isdir(path) else np.load(path, mmap_mode="r")
    channels = 1 if array.ndim == 2 else array.shape[2]
    alpha = channels - 1 if channels in (2, 4) else None
    bands = _color_bands(channels, alpha)
    nodata = array.attrs.get("nodata") if hasattr(array, "attrs") else None

    def read(r0, r1):
        block = np.asarray(array[r0:r1])
        block = block[..., None] if block.ndim == 2 else block
        data = np.moveaxis(block[..., bands], -1, 0).astype(np.float32)
        valid = np.isfinite(data).all(axis=0)
        if alpha is not None:
            valid &= block[..., alpha] > 0
        if nodata is not None:
            valid &= ~(data == np.float32(nodata)).any(axis=0)
        return data, valid

    return read, int(array.shape[0]), np.dtype(array.dtype) == np.uint8


def _alpha_index(ds):
    """The alpha band of a rasterio dataset: by colour interpretation, else by
    count (2: gray + alpha, 4: RGBA), as the ingest reads it."""
    from rasterio.enums import ColorInterp

    alpha = [i for i, interp in enumerate(ds.colorinterp) if interp == ColorInterp.alpha]
    return alpha[0] if alpha else (ds.count - 1 if ds.count in (2, 4) else None)


def _raster_reader(ds):
    from rasterio.windows import Window

    alpha = _alpha_index(ds)
    bands = _color_bands(ds.count, alpha)
    nodata = ds.nodata

    def read(r0, r1):
        window = Window(0, r0, ds.width, r1 - r0)
        data = ds.read([b + 1 for b in bands], window=window).astype(np.float32)
        valid = np.isfinite(data).all(axis=0)
        if alpha is not None:
            valid &= ds.read(alpha + 1, window=window) > 0
        if nodata is not None:
            valid &= ~(data == np.float32(nodata)).any(axis=0)
        return data, valid

    return read, ds.height, ds.dtypes[bands[0]] == "uint8"


def _warp_preview(grids, capture, factor, shape):
    """The reference set on the capture's grid coarsened by ``factor``: each
    file resampled (``average``) where the files before it left no data.  A
    set of gray files stays one band, stretched as the three copies of it a
    colour preview draws (:func:`_to_rgba`'s ``copies``)."""
    import rasterio
    from rasterio.transform import Affine
    from rasterio.warp import Resampling, reproject

    out, eight_bit = None, True
    for grid in grids:
        with rasterio.open(grid.path) as ds:
            alpha = _alpha_index(ds)
            bands = [b + 1 for b in _color_bands(ds.count, alpha)]
            dest = np.full((len(bands),) + shape, np.nan, np.float32)
            reproject(rasterio.band(ds, bands), dest, src_transform=ds.transform, src_crs=ds.crs,
                      src_nodata=ds.nodata, src_alpha=0 if alpha is None else alpha + 1,
                      dst_transform=capture.affine @ Affine.scale(factor), dst_crs=capture.crs, dst_nodata=np.nan,
                      resampling=Resampling.average)
            eight_bit &= ds.dtypes[bands[0] - 1] == "uint8"
        if out is not None and len(out) != len(dest):  # gray so far, a colour file now: gray as three bands
            out, dest = (np.repeat(out, 3, axis=0), dest) if len(out) == 1 else (out, np.repeat(dest, 3, axis=0))
        if out is None:
            out = dest
        else:
            fill = ~np.isfinite(out).all(axis=0) & np.isfinite(dest).all(axis=0)
            out[:, fill] = dest[:, fill]
    return _to_rgba(out, eight_bit, copies=3 if len(out) == 1 else 1)


def _to_rgba(bands, eight_bit, *, copies=1):
    """``(n, h, w)`` float bands (NaN: no data) -> uint8 RGBA ``(h, w, 4)``.

    One band is gray: drawn in the three colours.  ``copies``: how many
    identical bands the ``bands`` given stand for, which the stretch of an
    image that is not 8-bit counts (its percentiles are those of every copy:
    a gray reference set is stretched as the three bands it is drawn in)."""
    valid = np.isfinite(bands).all(axis=0)
    if eight_bit:
        scaled = bands + 0.5
    else:
        lo, hi = _percentiles_of_copies(bands[:, valid], _STRETCH, copies) if valid.any() else (0.0, 1.0)
        scaled = (bands - lo) * (255.0 / max(float(hi - lo), 1e-12))
        scaled += 0.5
    # in place on the one new array (the same values as np.clip(np.nan_to_num(s, nan=0) + 0.5, 0, 255)):
    # NaN + 0.5 is NaN, and 0.5 on no-data instead of 0 rounds down to the same 0
    np.nan_to_num(scaled, copy=False, nan=0.0)
    rgb = np.clip(scaled, 0, 255, out=scaled).astype(np.uint8)
    rgb = np.repeat(rgb, 3, axis=0) if rgb.shape[0] == 1 else rgb
    return np.concatenate([np.moveaxis(rgb, 0, -1), (valid * 255).astype(np.uint8)[..., None]], axis=-1)


def _percentiles_of_copies(values, q, copies=1):
    """``np.percentile(np.tile(values, copies), q)`` (numpy's default,
    ``linear``) without the copies: the order statistic ``j`` of the copies
    is the values' ``j // copies``, so each percentile needs two order
    statistics of ``values`` (one partition of them, not of ``copies`` times
    as many), interpolated by numpy itself (``np.quantile`` of the pair at
    the same fraction), the same bytes as numpy's answer.  Written for the
    gray reference previews, stretched as three copies: numpy's partition of
    the copies was most of a 1-MP preview's stretch."""
    values = np.asarray(values).ravel()
    n = values.size * copies
    virtual = (n - 1) * np.true_divide(q, 100)  # numpy's virtual index of the linear method
    below = np.floor(virtual).astype(np.intp)
    above = np.minimum(below + 1, n - 1)
    part = np.partition(values, np.unique(np.concatenate([below, above]) // copies))
    return np.array([np.quantile(part[[b // copies, a // copies]], v - b) for v, b, a in zip(virtual, below, above)])
