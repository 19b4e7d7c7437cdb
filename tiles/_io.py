"""Reading input images into float32 luminance and writing single-band GeoTIFFs.

Every input format (GeoTIFF/TIFF, PNG, JPEG, ``.npy``, an existing zarr array) ends
up as the same thing: a :class:`Raster` holding a float32 luminance image of shape
(H, W), a boolean validity mask (False where the input had nodata or a zero alpha),
the georeferencing as a :class:`GeoInfo` and a SHA-256 checksum of the input.

The dtype policy is written once, in :func:`as_float01`; colour to luminance once,
in :func:`_luminance`.  :func:`read_window` reads a window without loading the whole
image, so a tiled ingest can stream large GeoTIFFs.
"""

from __future__ import annotations

import hashlib
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rsmb.ops._errors import InputError, ParameterError

__all__ = [
    "GeoInfo",
    "Raster",
    "as_float01",
    "check_same_shape",
    "read_image",
    "read_window",
    "write_geotiff",
]

#: Extensions read with rasterio (GDAL).
RASTERIO_EXTENSIONS = (".tif", ".tiff", ".png", ".jpg", ".jpeg")
#: Extensions read with numpy.
NUMPY_EXTENSIONS = (".npy",)

# ITU-R BT.601 luma weights, as Python floats so float32 stays float32 (STYLE 6).
_LUMA_RGB = (0.299, 0.587, 0.114)
_HASH_BLOCK = 1 << 20
_NONFINITE_TO_JSON = {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}
_JSON_TO_NONFINITE = {v: float(k) for k, v in _NONFINITE_TO_JSON.items()}


# --------------------------------------------------------------------------- GeoInfo


@dataclass(frozen=True)
class GeoInfo:
    """Georeferencing of a raster, as far as the input had one.

    Attributes
    ----------
    crs : str or None
        Coordinate reference system as WKT2 (2019), None when the input had none.
    transform : tuple of 6 float or None
        Affine coefficients ``(a, b, c, d, e, f)`` in rasterio's ``Affine`` order:
        ``x = a * col + b * row + c`` and ``y = d * col + e * row + f``, with (col, row)
        pixel-corner coordinates and (x, y) in CRS units.  None when not georeferenced.
    nodata : float or None
        The nodata value of the first band of the input, None when it had none.
    """

    crs: str | None = None
    transform: tuple[float, ...] | None = None
    nodata: float | None = None

    def __post_init__(self) -> None:
        if self.transform is not None:
            coeffs = tuple(float(v) for v in self.transform)
            if len(coeffs) != 6:
                raise ParameterError(
                    f"transform: expected 6 affine coefficients (a, b, c, d, e, f), "
                    f"got {len(coeffs)}"
                )
            object.__setattr__(self, "transform", coeffs)
        if self.nodata is not None:
            object.__setattr__(self, "nodata", float(self.nodata))

    @property
    def is_empty(self) -> bool:
        """True when neither a CRS nor a transform is known."""
        return self.crs is None and self.transform is None

    def to_attrs(self) -> dict[str, Any]:
        """GeoZarr-style attributes, JSON-serialisable.

        Returns
        -------
        dict
            ``"proj:wkt2"`` (WKT2 string) and ``"proj:code"`` (e.g. ``"EPSG:32618"``,
            only when an authority code is found) when a CRS is known;
            ``"spatial:transform"`` (list of 6 floats) and ``"spatial:dimensions"``
            (``["y", "x"]``) when a transform is known; ``"nodata"`` always (None,
            a float, or ``"NaN"`` / ``"Infinity"`` / ``"-Infinity"`` for non-finite
            values, which strict JSON cannot hold).
        """
        attrs: dict[str, Any] = {}
        if self.crs is not None:
            attrs["proj:wkt2"] = self.crs
            code = _crs_code(self.crs)
            if code is not None:
                attrs["proj:code"] = code
        if self.transform is not None:
            attrs["spatial:transform"] = [float(v) for v in self.transform]
            attrs["spatial:dimensions"] = ["y", "x"]
        attrs["nodata"] = _float_to_json(self.nodata)
        return attrs

    @classmethod
    def from_attrs(cls, attrs: dict[str, Any]) -> GeoInfo:
        """Inverse of :meth:`to_attrs`; missing keys give None.

        ``"proj:wkt2"`` wins over ``"proj:code"``; a code alone is resolved to WKT2
        with rasterio.
        """
        crs = attrs.get("proj:wkt2")
        if crs is None and attrs.get("proj:code") is not None:
            from rasterio.crs import CRS

            crs = CRS.from_user_input(attrs["proj:code"]).to_wkt(version="WKT2_2019")
        transform = attrs.get("spatial:transform")
        nodata = attrs.get("nodata")
        if isinstance(nodata, str):
            nodata = _JSON_TO_NONFINITE[nodata]
        return cls(
            crs=crs,
            transform=None if transform is None else tuple(transform),
            nodata=nodata,
        )


def _crs_code(wkt: str) -> str | None:
    """``"AUTH:CODE"`` for a WKT CRS, or None when rasterio finds no authority."""
    from rasterio.crs import CRS

    try:
        authority = CRS.from_wkt(wkt).to_authority()
    except Exception:  # noqa: BLE001 - a CRS without a code is fine
        return None
    if authority is None:
        return None
    return f"{authority[0]}:{authority[1]}"


def _float_to_json(value: float | None) -> float | str | None:
    if value is None or math.isfinite(value):
        return value
    return _NONFINITE_TO_JSON[str(float(value))]


# ---------------------------------------------------------------------------- Raster


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


# ------------------------------------------------------------------- dtype policy


def as_float01(array: np.ndarray, *, name: str) -> np.ndarray:
    """Convert an image array to float32 following the project's one dtype policy.

    Parameters
    ----------
    array : ndarray, any shape
        bool, integer or floating values.
    name : str
        File or array name used in error messages.

    Returns
    -------
    ndarray, same shape, float32
        ``uint8 / 255``, ``uint16 / 65535``, other integers divided by the maximum of
        their dtype (signed integers may give values in [-1, 0)), bool as 0 / 1;
        floating values unchanged (not rescaled).

    Raises
    ------
    InputError
        If the array holds NaN or infinite values (also after the cast to float32),
        or has a dtype that is not numeric.
    """
    array = np.asarray(array)
    kind = array.dtype.kind
    if kind == "b":
        return array.astype(np.float32)
    if kind in "ui":
        scale = float(np.iinfo(array.dtype).max)
        return array.astype(np.float32) / np.float32(scale)
    if kind == "f":
        if np.isnan(array).any():
            raise InputError(f"{name}: contains NaN")
        out = array.astype(np.float32, copy=False)
        if not np.isfinite(out).all():
            raise InputError(f"{name}: contains inf (or values beyond float32 range)")
        return out
    raise InputError(
        f"{name}: unsupported dtype {array.dtype}; expected bool, integer or float"
    )


def _luminance(
    bands: list[np.ndarray], invalid: np.ndarray, *, name: str
) -> tuple[np.ndarray, np.ndarray]:
    """Luminance and validity from colour bands (alpha already removed).

    Parameters
    ----------
    bands : list of ndarray, each shape (H, W)
        One gray band or three bands R, G, B, in their input dtype.
    invalid : ndarray, shape (H, W), bool
        True where the pixel is nodata or transparent.
    name : str
        File name for error messages.

    Returns
    -------
    data : ndarray, shape (H, W), float32
        ``0.299 R + 0.587 G + 0.114 B`` (or the gray band), 0 where invalid.
    valid : ndarray, shape (H, W), bool
    """
    any_invalid = bool(invalid.any())
    if len(bands) == 1:
        weights: tuple[float, ...] = (1.0,)
    else:
        weights = _LUMA_RGB
    data: np.ndarray | None = None
    for band, weight in zip(bands, weights):
        if any_invalid:
            band = np.where(invalid, np.zeros((), dtype=band.dtype), band)
        term = as_float01(band, name=name)
        if weight != 1.0:
            term = term * np.float32(weight)
        data = term if data is None else data + term
    assert data is not None
    data = np.ascontiguousarray(data, dtype=np.float32)
    if any_invalid:
        data[invalid] = 0.0
    return data, ~invalid


def _split_alpha(
    bands: list[np.ndarray], alpha_index: int | None, *, name: str
) -> tuple[list[np.ndarray], np.ndarray | None]:
    """Separate colour bands from an alpha band; check the band count."""
    alpha = None
    if alpha_index is not None:
        alpha = bands[alpha_index]
        bands = bands[:alpha_index] + bands[alpha_index + 1 :]
    if len(bands) not in (1, 3):
        total = len(bands) + (alpha is not None)
        raise InputError(
            f"{name}: has {total} bands; expected 1 (gray), 2 (gray+alpha), "
            f"3 (RGB) or 4 (RGBA)"
        )
    return bands, alpha


def _default_alpha_index(count: int) -> int | None:
    """Band roles by count: 2 = gray+alpha, 4 = RGBA; otherwise no alpha."""
    return count - 1 if count in (2, 4) else None


def _bands_to_luminance(
    bands: list[np.ndarray],
    *,
    alpha_index: int | None,
    nodatavals: list[float | None],
    name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Validity from alpha and per-band nodata, then luminance."""
    colour, alpha = _split_alpha(bands, alpha_index, name=name)
    colour_nodata = [v for i, v in enumerate(nodatavals) if i != alpha_index]
    shape = colour[0].shape
    invalid = np.zeros(shape, dtype=bool)
    if alpha is not None:
        invalid |= alpha == 0
    if colour_nodata and all(v is not None for v in colour_nodata):
        # A pixel is nodata when every colour band holds its nodata value.
        all_nodata = np.ones(shape, dtype=bool)
        for band, value in zip(colour, colour_nodata):
            all_nodata &= np.isnan(band) if math.isnan(value) else band == value
        invalid |= all_nodata
    return _luminance(colour, invalid, name=name)


# --------------------------------------------------------------------------- formats


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _kind(path: str) -> str:
    """'rasterio', 'numpy' or 'zarr' for an existing path; InputError otherwise."""
    if not os.path.exists(path):
        raise InputError(f"{path}: no such file or directory")
    if os.path.isdir(path):
        return "zarr"
    ext = os.path.splitext(path)[1].lower()
    if ext in RASTERIO_EXTENSIONS:
        return "rasterio"
    if ext in NUMPY_EXTENSIONS:
        return "numpy"
    supported = ", ".join(RASTERIO_EXTENSIONS + NUMPY_EXTENSIONS)
    raise InputError(
        f"{path}: unsupported format {ext or '(no extension)'!r}; "
        f"expected one of {supported} or a zarr array directory"
    )


def _open_rasterio(path: str):
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            return rasterio.open(path)
    except (RasterioError, OSError) as exc:
        raise InputError(f"{path}: cannot read image ({_one_line(exc)})") from exc


def _rasterio_alpha_index(ds) -> int | None:
    from rasterio.enums import ColorInterp

    for i, interp in enumerate(ds.colorinterp):
        if interp == ColorInterp.alpha:
            return i
    return _default_alpha_index(ds.count)


def _read_rasterio(
    path: str, rows: slice | None = None, cols: slice | None = None
) -> tuple[np.ndarray, np.ndarray, GeoInfo]:
    """Luminance, validity and georeferencing of a whole image or of a window."""
    from rasterio.errors import RasterioError
    from rasterio.windows import Window

    with _open_rasterio(path) as ds:
        window = None
        if rows is not None or cols is not None:
            r0, r1 = _resolve(slice(None) if rows is None else rows, ds.height, "rows")
            c0, c1 = _resolve(slice(None) if cols is None else cols, ds.width, "cols")
            window = Window(c0, r0, c1 - c0, r1 - r0)
        try:
            stack = ds.read(window=window)  # (bands, h, w)
        except (RasterioError, OSError) as exc:
            raise InputError(f"{path}: cannot read image ({_one_line(exc)})") from exc
        if window is None and 0 in stack.shape[1:]:
            raise InputError(f"{path}: is empty (shape {stack.shape[1:]})")
        data, valid = _bands_to_luminance(
            list(stack),
            alpha_index=_rasterio_alpha_index(ds),
            nodatavals=list(ds.nodatavals),
            name=path,
        )
        geo = _rasterio_geo(ds)
    return data, valid, geo


def _rasterio_geo(ds) -> GeoInfo:
    crs = None if ds.crs is None else ds.crs.to_wkt(version="WKT2_2019")
    transform = tuple(ds.transform)[:6]
    if crs is None and ds.transform.is_identity:
        transform = None
    return GeoInfo(crs=crs, transform=transform, nodata=ds.nodata)


def _array_to_luminance(
    array: np.ndarray, *, nodata: float | None = None, name: str
) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) or channel-last (H, W, 1..4) array -> luminance, valid.

    ``nodata`` (from a zarr array's ``"nodata"`` attribute) applies to every colour
    band, as for a GeoTIFF.
    """
    if array.ndim == 2:
        bands = [np.asarray(array)]
    elif array.ndim == 3 and 1 <= array.shape[2] <= 4:
        bands = [np.asarray(array[:, :, c]) for c in range(array.shape[2])]
    else:
        raise InputError(
            f"{name}: array of shape {tuple(array.shape)}; expected (H, W) gray or "
            f"(H, W, 3|4) RGB(A)"
        )
    return _bands_to_luminance(
        bands,
        alpha_index=_default_alpha_index(len(bands)),
        nodatavals=[nodata] * len(bands),
        name=name,
    )


def _load_npy(path: str) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read .npy file ({_one_line(exc)})") from exc


def _open_zarr_array(path: str):
    import zarr

    try:
        node = zarr.open(store=path, mode="r")
    except Exception as exc:  # noqa: BLE001 - zarr raises many types for bad stores
        raise InputError(
            f"{path}: is a directory but not a readable zarr array ({_one_line(exc)})"
        ) from exc
    if isinstance(node, zarr.Group):
        names = sorted(name for name, _ in node.arrays())
        raise InputError(
            f"{path}: is a zarr group, not an array; give <store>/<array> "
            f"(arrays here: {', '.join(names) or 'none'})"
        )
    return node


def _zarr_geo(zarray, *, name: str) -> GeoInfo:
    """GeoInfo from a zarr array's GeoZarr-style attributes (see GeoInfo.to_attrs)."""
    try:
        return GeoInfo.from_attrs(dict(zarray.attrs))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(
            f"{name}: invalid georeferencing attributes ({_one_line(exc)})"
        ) from exc


def _check_2d_nonempty(shape: tuple[int, ...], *, name: str) -> None:
    if len(shape) >= 2 and (shape[0] == 0 or shape[1] == 0):
        raise InputError(f"{name}: is empty (shape {tuple(shape)})")
    if len(shape) < 2 or 0 in shape:
        raise InputError(
            f"{name}: array of shape {tuple(shape)}; expected (H, W) gray or "
            f"(H, W, 3|4) RGB(A)"
        )


def _sha256_file(path: str) -> str:
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(_HASH_BLOCK), b""):
                digest.update(block)
    except OSError as exc:
        raise InputError(f"{path}: cannot read file ({_one_line(exc)})") from exc
    return digest.hexdigest()


def _sha256_array(array) -> str:
    """Digest of the C-order bytes of a numpy or zarr array, read by strips of
    chunk rows (a zarr input is never loaded whole)."""
    digest = hashlib.sha256()
    step = max(int(getattr(array, "chunks", (256,))[0]), 1)
    for r0 in range(0, array.shape[0], step):
        digest.update(np.ascontiguousarray(array[r0:r0 + step]).tobytes())
    return digest.hexdigest()


def _check_content(data: np.ndarray, valid: np.ndarray, *, name: str) -> None:
    """No valid pixel / constant image checks on a whole image."""
    if not valid.any():
        raise InputError(f"{name}: has no valid pixel (all nodata or transparent)")
    values = data[valid]
    first = float(values[0])
    if bool((values == first).all()):
        raise InputError(f"{name}: is constant (every valid pixel equals {first:g})")


# ------------------------------------------------------------------------ public API


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
    kind = _kind(name)
    if kind == "rasterio":
        data, valid, geo = _read_rasterio(name)
        sha = _sha256_file(name)
    elif kind == "numpy":
        array = _load_npy(name)
        _check_2d_nonempty(array.shape, name=name)
        data, valid = _array_to_luminance(array, name=name)
        geo = GeoInfo()
        sha = _sha256_file(name)
    else:
        zarray = _open_zarr_array(name)
        _check_2d_nonempty(zarray.shape, name=name)
        array = np.asarray(zarray[...])
        geo = _zarr_geo(zarray, name=name)
        data, valid = _array_to_luminance(array, nodata=geo.nodata, name=name)
        sha = _sha256_array(array)
    if data.size == 0:
        raise InputError(f"{name}: is empty (shape {data.shape})")
    _check_content(data, valid, name=name)
    return Raster(data=data, valid=valid, geo=geo, path=name, sha256=sha)


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
    name = os.fspath(path)
    kind = _kind(name)
    if kind == "rasterio":
        data, valid, _ = _read_rasterio(name, rows, cols)
        return data, valid
    if kind == "numpy":
        array = _load_npy(name)
        nodata = None
    else:
        array = _open_zarr_array(name)
        nodata = _zarr_geo(array, name=name).nodata
    _check_2d_nonempty(array.shape, name=name)
    (r0, r1), (c0, c1) = (
        _resolve(rows, array.shape[0], "rows"),
        _resolve(cols, array.shape[1], "cols"),
    )
    window = np.asarray(array[r0:r1, c0:c1])
    return _array_to_luminance(window, nodata=nodata, name=name)


def _resolve(index: slice, size: int, label: str) -> tuple[int, int]:
    if not isinstance(index, slice):
        raise ParameterError(f"{label}: expected a slice, got {type(index).__name__}")
    start, stop, step = index.indices(size)
    if step != 1:
        raise ParameterError(f"{label}: expected a slice with step 1, got step {step}")
    return start, max(start, stop)


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
        "compress": "deflate",
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


def probe_image(path: str | os.PathLike) -> ImageInfo:
    """Shape, georeferencing and checksum of an image without loading its pixels
    (formats as :func:`read_image`).

    Raises
    ------
    InputError
        Missing, unreadable, unsupported or empty input (one line naming the file).
    """
    name = os.fspath(path)
    shape, geo = _probe_header(name)
    if _kind(name) == "zarr":
        sha = _sha256_array(_open_zarr_array(name))
    else:
        sha = _sha256_file(name)
    return ImageInfo(name, shape, geo, sha)


def _probe_header(name: str) -> tuple[tuple[int, int], GeoInfo]:
    """(H, W) and georeferencing of an image from its header only: no pixel is
    read and no checksum computed (cheap enough to call per tile on a large
    reference mosaic)."""
    kind = _kind(name)
    if kind == "rasterio":
        with _open_rasterio(name) as ds:
            shape, geo = (ds.height, ds.width), _rasterio_geo(ds)
    elif kind == "numpy":
        array = _load_npy(name)
        _check_2d_nonempty(array.shape, name=name)
        shape, geo = array.shape[:2], GeoInfo()
    else:
        zarray = _open_zarr_array(name)
        _check_2d_nonempty(zarray.shape, name=name)
        shape, geo = zarray.shape[:2], _zarr_geo(zarray, name=name)
    if 0 in shape:
        raise InputError(f"{name}: is empty (shape {tuple(shape)})")
    return (int(shape[0]), int(shape[1])), geo
