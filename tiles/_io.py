"""Reading input images into float32 luminance and writing single-band GeoTIFFs.

Every input format (GeoTIFF/TIFF, PNG, JPEG, ``.npy``, an existing zarr array) ends
up as the same thing: a :class:`Raster` holding a float32 luminance image of shape
(H, W), a boolean validity mask (False where the input had nodata or a zero alpha),
the georeferencing as a :class:`GeoInfo` and a SHA-256 checksum of the input.

The public entry points live here; the formats are the readers of
:mod:`._sources` (one class each), the dtype and luminance policy is
:mod:`._luminance` and the georeferencing :mod:`._geo`.  :func:`read_window`
reads a window without loading the whole image, so a tiled ingest can stream
large GeoTIFFs.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rsmb.ops._errors import InputError, ParameterError

from ._geo import GeoInfo
from ._sources import expand_references, open_source


@dataclass(frozen=True, eq=False)
class Raster:
    """An input image as float32 luminance with its validity mask and provenance.

    Attributes
    ----------
    data : ndarray, shape (H, W), float32
        Luminance; integer inputs scaled to [0, 1] (see :func:`as_float01`), float
        inputs kept as they are.  0 where ``valid`` is False.
    valid : ndarray, shape (H, W), bool
        False where the input had nodata (every band equal to its nodata value) or a
        zero alpha.
    geo : GeoInfo
        Georeferencing (empty for PNG, JPEG, NPY and zarr inputs without it).
    path : str
        The path the image was read from.
    sha256 : str
        Hex SHA-256 of the input file's bytes; for a zarr array, of the array's
        C-ordered bytes in its stored dtype.
    """

    data: np.ndarray
    valid: np.ndarray
    geo: GeoInfo
    path: str
    sha256: str

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return self.data.shape  # type: ignore[return-value]


@dataclass(frozen=True)
class ImageInfo:
    """What is known of an input image before reading its pixels.

    Attributes
    ----------
    path : str
    shape : tuple of int
        (H, W) in pixels.
    geo : GeoInfo
    sha256 : str
        Hex digest of the file (of the array bytes for a zarr array).
    """

    path: str
    shape: tuple
    geo: GeoInfo
    sha256: str


def read_image(path: str | os.PathLike) -> Raster:
    """Read an image as float32 luminance with a validity mask and its georeferencing.

    Parameters
    ----------
    path : str or path-like
        A GeoTIFF/TIFF, PNG or JPEG file (read with rasterio, all bands), a ``.npy``
        file holding an (H, W) gray or (H, W, 3|4) RGB(A) array, or a zarr v2/v3 array
        directory (``store.zarr/arrayname``) with the same layouts, whose
        GeoZarr-style attributes (:meth:`GeoInfo.to_attrs`), if any, give its ``geo``
        and its nodata value.

    Returns
    -------
    Raster
        ``data`` float32 shape (H, W): luminance ``0.299 R + 0.587 G + 0.114 B`` (or
        the gray band) scaled per :func:`as_float01`; ``valid`` bool shape (H, W):
        False where every band equals the nodata value or where alpha is 0 (those
        pixels hold 0 in ``data``); ``geo``: CRS, transform and nodata of a GeoTIFF
        (empty for PNG, JPEG and NPY).

    Raises
    ------
    InputError
        One-line message starting with the path: missing or unreadable file,
        unsupported extension, empty image, NaN or inf values, no valid pixel, a
        constant image, or an unsupported band layout.
    """
    name = os.fspath(path)
    source = open_source(name)
    _, geo = source.probe()
    data, valid = source.read()
    if data.size == 0:
        raise InputError(f"{name}: is empty (shape {data.shape})")
    _check_content(data, valid, name=name)
    return Raster(data=data, valid=valid, geo=geo, path=name, sha256=source.sha256())


def read_window(
    path: str | os.PathLike, rows: slice, cols: slice
) -> tuple[np.ndarray, np.ndarray]:
    """Read a rectangular window of an image as luminance and validity.

    Only the window is read: rasterio windowed reads for GeoTIFF/PNG/JPEG, a
    memory-mapped slice for ``.npy``, a zarr slice for zarr arrays.  The dtype and
    luminance policy is the one of :func:`read_image`, so ``read_window(p, r, c)``
    equals ``read_image(p).data[r, c]`` (and ``.valid[r, c]``).  No constant / no-valid
    checks are made: a window may legitimately be constant.

    Parameters
    ----------
    path : str or path-like
        As for :func:`read_image`.
    rows, cols : slice
        Row and column ranges in pixels; step must be None or 1; negative and None
        bounds follow Python slicing and are clipped to the image.

    Returns
    -------
    data : ndarray, shape (h, w), float32
    valid : ndarray, shape (h, w), bool
    """
    return open_source(os.fspath(path)).read(rows, cols)


def probe_image(path: str | os.PathLike) -> ImageInfo:
    """Shape, georeferencing and checksum of an image without loading its pixels
    (formats as :func:`read_image`).

    Raises
    ------
    InputError
        Missing, unreadable, unsupported or empty input (one line naming the file).
    """
    name = os.fspath(path)
    source = open_source(name)
    shape, geo = _header(source)
    return ImageInfo(name, shape, geo, source.sha256())


def probe_header(path: str | os.PathLike) -> tuple[tuple[int, int], GeoInfo]:
    """(H, W) and georeferencing of an image from its header only: no pixel is
    read and no checksum computed (cheap enough for every file of a large
    reference mosaic).

    Raises
    ------
    InputError
        Missing, unreadable, unsupported or empty input (one line naming the file).
    """
    return _header(open_source(os.fspath(path)))


def _header(source):
    shape, geo = source.probe()
    if 0 in shape:
        raise InputError(f"{source.path}: is empty (shape {tuple(shape)})")
    return (int(shape[0]), int(shape[1])), geo


def _check_content(data: np.ndarray, valid: np.ndarray, *, name: str) -> None:
    """No valid pixel / constant image checks on a whole image."""
    if not valid.any():
        raise InputError(f"{name}: has no valid pixel (all nodata, NaN or transparent)")
    values = data[valid]
    first = float(values[0])
    if bool((values == first).all()):
        raise InputError(f"{name}: is constant (every valid pixel equals {first:g})")


def check_same_shape(reference: Raster, distorted: Raster) -> None:
    """Raise if two rasters differ in shape.

    Raises
    ------
    InputError
        One line naming both files and both (H, W) shapes.
    """
    if reference.data.shape != distorted.data.shape:
        raise InputError(
            f"{distorted.path}: shape {tuple(distorted.data.shape)} differs from "
            f"reference {reference.path} shape {tuple(reference.data.shape)}"
        )


_GEOTIFF_BLOCK = 256


def write_geotiff(
    path: str | os.PathLike,
    array: np.ndarray,
    geo: GeoInfo,
    *,
    nodata: float | None = None,
    description: str | None = None,
    compress: str | None = "deflate",
) -> Path:
    """Write a single-band GeoTIFF (deflate compressed, 256 x 256 tiles).

    Parameters
    ----------
    path : str or path-like
        Output file; overwritten if it exists.
    array : ndarray or zarr array, shape (H, W)
        bool or uint8 (written as uint8) or floating (written as float32);
        read and written in strips of 256 rows.
    geo : GeoInfo
        CRS and transform to record; may be empty (no georeferencing written).
        ``geo.nodata`` is not used: pass ``nodata`` explicitly.
    nodata : float, optional
        Nodata value to record in the file.
    description : str, optional
        Band description (what the values are), shown by GIS tools.
    compress : str or None
        GDAL compression; None writes the tiles uncompressed (a scratch file
        that is read once, as :func:`tiles.write_cog`'s).

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    ParameterError
        If ``array`` is not 2-D or has another dtype.
    """
    import rasterio
    from rasterio.crs import CRS
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.transform import Affine
    from rasterio.windows import Window

    if not hasattr(array, "dtype"):
        array = np.asarray(array)
    if len(array.shape) != 2:
        raise ParameterError(f"array: expected shape (H, W), got {tuple(array.shape)}")
    dtype = np.dtype(array.dtype)
    if dtype.kind == "b" or dtype == np.uint8:
        dtype = np.dtype(np.uint8)
    elif dtype.kind == "f":
        dtype = np.dtype(np.float32)
    else:
        raise ParameterError(
            f"array: expected dtype bool, uint8 or floating, got {dtype}"
        )
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "height": array.shape[0],
        "width": array.shape[1],
        "count": 1,
        "dtype": dtype.name,
        "tiled": True,
        "blockxsize": _GEOTIFF_BLOCK,
        "blockysize": _GEOTIFF_BLOCK,
    }
    if geo.crs is not None:
        profile["crs"] = CRS.from_user_input(geo.crs)
    if geo.transform is not None:
        profile["transform"] = Affine(*geo.transform)
    if nodata is not None:
        profile["nodata"] = nodata
    if compress is not None:
        profile["compress"] = compress
    out = Path(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(out, "w", **profile) as ds:
            if description is not None:
                ds.set_band_description(1, description)
            # strips of one block row: a zarr array is never read whole
            for r0 in range(0, array.shape[0], _GEOTIFF_BLOCK):
                strip = np.asarray(array[r0:r0 + _GEOTIFF_BLOCK]).astype(dtype, copy=False)
                ds.write(strip, 1, window=Window(0, r0, strip.shape[1], strip.shape[0]))
    return out
