"""Input formats: one small reader per format behind one dispatch.

:func:`open_source` picks the reader of a path: rasterio (GDAL) for GeoTIFF/TIFF,
PNG and JPEG files, numpy for ``.npy`` files, zarr for an array directory.  Every
reader answers the same three questions, with the dtype and luminance policy of
:mod:`._luminance`:

- ``probe()``: shape (H, W) and georeferencing, without reading pixels;
- ``read(rows, cols)``: luminance and validity of the whole image or a window,
  reading only that window;
- ``sha256()``: the checksum recorded in the output store.

Adding a format is one subclass of :class:`_Source` listed in ``_FORMATS``.
Errors are :class:`InputError` with one line that starts with the path.
"""

from __future__ import annotations

import functools
import hashlib
import os
import warnings

import numpy as np

from rsmb.ops._errors import InputError, ParameterError, one_line

from ._gdal import gdal_errors, quiet_gdal
from ._geo import GeoInfo
from ._luminance import array_to_luminance, bands_to_luminance, default_alpha_index

_HASH_BLOCK = 1 << 20


def resolve_slice(index: slice | None, size: int, label: str) -> tuple[int, int]:
    """``(start, stop)`` of a step-1 slice clipped to ``size`` (None: everything).

    Raises
    ------
    ParameterError
        If ``index`` is not a slice or its step is not 1; ``label`` names it.
    """
    if index is None:
        index = slice(None)
    if not isinstance(index, slice):
        raise ParameterError(f"{label}: expected a slice, got {type(index).__name__}")
    start, stop, step = index.indices(size)
    if step != 1:
        raise ParameterError(f"{label}: expected a slice with step 1, got step {step}")
    return start, max(start, stop)


def sha256_file(path: str) -> str:
    """Hex SHA-256 of a file's bytes, read in blocks of 1 MiB.  Remembered per
    process for a file of the same path, size, inode and modification time: a
    night hashes each file of a reference mosaic once, not once per capture."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise InputError(f"{path}: cannot read file ({one_line(exc)})") from exc
    return _sha256_file(os.path.abspath(path), st.st_size, st.st_ino, st.st_mtime_ns)


@functools.lru_cache(maxsize=4096)
def _sha256_file(path: str, size: int, inode: int, mtime_ns: int) -> str:
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(_HASH_BLOCK), b""):
                digest.update(block)
    except OSError as exc:
        raise InputError(f"{path}: cannot read file ({one_line(exc)})") from exc
    return digest.hexdigest()


def sha256_array(array) -> str:
    """Digest of the C-order bytes of a numpy or zarr array, read by strips of
    chunk rows (a zarr input is never loaded whole)."""
    digest = hashlib.sha256()
    step = max(int(getattr(array, "chunks", (256,))[0]), 1)
    for r0 in range(0, array.shape[0], step):
        digest.update(np.ascontiguousarray(array[r0:r0 + step]).tobytes())
    return digest.hexdigest()


# ----------------------------------------------------------------------- the base


class _Source:
    """An input image at ``path``; each subclass reads one format.

    Attributes
    ----------
    extensions : tuple of str
        Lower-case file extensions of the format (empty for a directory format).
    label : str or None
        How the unsupported-format message names a format without an extension.
    """

    extensions: tuple[str, ...] = ()
    label: str | None = None

    def __init__(self, path: str) -> None:
        self.path = path

    @classmethod
    def accepts(cls, path: str) -> bool:
        """Whether this format reads the existing ``path`` (by its extension)."""
        return not os.path.isdir(path) and os.path.splitext(path)[1].lower() in cls.extensions

    def probe(self) -> tuple[tuple[int, int], GeoInfo]:
        """``((H, W), geo)`` without reading the pixels."""
        raise NotImplementedError

    def read(
        self, rows: slice | None = None, cols: slice | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Luminance (float32) and validity (bool), both shape (h, w), of the
        window ``rows`` x ``cols`` (None: the whole axis)."""
        raise NotImplementedError

    def sha256(self) -> str:
        """Hex SHA-256 of the input file's bytes."""
        return sha256_file(self.path)


# ----------------------------------------------------------------------- rasterio


class RasterioSource(_Source):
    """GeoTIFF/TIFF, PNG and JPEG, and any other raster GDAL opens (VRT,
    JPEG 2000, COG ...: :func:`open_source` tries), through rasterio: windowed
    reads, every band, alpha from the colour interpretation or the band count."""

    extensions = (".tif", ".tiff", ".png", ".jpg", ".jpeg")

    def _open(self):
        import rasterio
        from rasterio.errors import NotGeoreferencedWarning

        with gdal_errors(self.path), warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            return rasterio.open(self.path)

    def probe(self) -> tuple[tuple[int, int], GeoInfo]:
        with self._open() as ds:
            _check_tiff_length(ds, self.path)
            return (ds.height, ds.width), _rasterio_geo(ds)

    def read(
        self, rows: slice | None = None, cols: slice | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        from rasterio.windows import Window

        with self._open() as ds:
            window = None
            if rows is not None or cols is not None:
                r0, r1 = resolve_slice(rows, ds.height, "rows")
                c0, c1 = resolve_slice(cols, ds.width, "cols")
                window = Window(c0, r0, c1 - c0, r1 - r0)
            with gdal_errors(self.path):
                stack = ds.read(window=window)  # (bands, h, w)
            if window is None and 0 in stack.shape[1:]:
                raise InputError(f"{self.path}: is empty (shape {stack.shape[1:]})")
            return bands_to_luminance(
                list(stack),
                alpha_index=_rasterio_alpha_index(ds),
                nodatavals=list(ds.nodatavals),
                name=self.path,
            )


def _check_tiff_length(ds, path) -> None:
    """Raise :class:`InputError` when a TIFF's last block of some band ends
    beyond the file: a file cut short (still being copied, or a copy that
    broke off) whose header opens.  Read from the header's block offsets and
    sizes only; other formats pass."""
    if ds.driver != "GTiff":
        return
    length = os.path.getsize(path)
    for bidx, (bh, bw) in zip(ds.indexes, ds.block_shapes):
        x, y = -(-ds.width // bw) - 1, -(-ds.height // bh) - 1
        offset = ds.get_tag_item(f"BLOCK_OFFSET_{x}_{y}", "TIFF", bidx=bidx)
        size = ds.get_tag_item(f"BLOCK_SIZE_{x}_{y}", "TIFF", bidx=bidx)
        if offset and size and int(offset) + int(size) > length:
            raise InputError(f"{path}: cut short: its data ends at byte {int(offset) + int(size)} of a "
                             f"{length}-byte file (still being copied?)")


def _rasterio_alpha_index(ds) -> int | None:
    from rasterio.enums import ColorInterp

    for i, interp in enumerate(ds.colorinterp):
        if interp == ColorInterp.alpha:
            return i
    return default_alpha_index(ds.count)


def _rasterio_geo(ds) -> GeoInfo:
    crs = None if ds.crs is None else ds.crs.to_wkt(version="WKT2_2019")
    transform = tuple(ds.transform)[:6]
    if crs is None and ds.transform.is_identity:
        transform = None
    return GeoInfo(crs=crs, transform=transform, nodata=ds.nodata)


# ------------------------------------------------------------------------- arrays


class _ArraySource(_Source):
    """An (H, W) gray or (H, W, 1..4) channel-last array read by slicing."""

    _cached = None

    def _load(self):
        """The array object (numpy memory map, zarr array): nothing read yet."""
        raise NotImplementedError

    def _geo(self, array) -> GeoInfo:
        return GeoInfo()

    def _array(self):
        if self._cached is None:
            array = self._load()
            _check_layout(array.shape, name=self.path)
            self._cached = array
        return self._cached

    def probe(self) -> tuple[tuple[int, int], GeoInfo]:
        array = self._array()
        return (int(array.shape[0]), int(array.shape[1])), self._geo(array)

    def read(
        self, rows: slice | None = None, cols: slice | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        array = self._array()
        r0, r1 = resolve_slice(rows, array.shape[0], "rows")
        c0, c1 = resolve_slice(cols, array.shape[1], "cols")
        window = np.asarray(array[r0:r1, c0:c1])
        return array_to_luminance(window, nodata=self._geo(array).nodata, name=self.path)


def _check_layout(shape: tuple[int, ...], *, name: str) -> None:
    if len(shape) >= 2 and (shape[0] == 0 or shape[1] == 0):
        raise InputError(f"{name}: is empty (shape {tuple(shape)})")
    if len(shape) < 2 or 0 in shape:
        raise InputError(
            f"{name}: array of shape {tuple(shape)}; expected (H, W) gray or "
            f"(H, W, 3|4) RGB(A)"
        )


class NumpySource(_ArraySource):
    """A ``.npy`` file, memory-mapped (never pickled); no georeferencing."""

    extensions = (".npy",)

    def _load(self):
        try:
            return np.load(self.path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"{self.path}: cannot read .npy file ({one_line(exc)})") from exc


class ZarrSource(_ArraySource):
    """A zarr v2/v3 array directory (``store.zarr/name``); georeferencing and
    nodata from its GeoZarr-style attributes (:meth:`GeoInfo.to_attrs`); its
    checksum is of the array's C-ordered bytes in its stored dtype."""

    label = "a zarr array directory"

    @classmethod
    def accepts(cls, path: str) -> bool:
        return os.path.isdir(path)

    def _load(self):
        import zarr

        try:
            node = zarr.open(store=self.path, mode="r")
        except Exception as exc:  # noqa: BLE001 - zarr raises many types for bad stores
            raise InputError(
                f"{self.path}: is a directory but not a readable zarr array ({one_line(exc)})"
            ) from exc
        if isinstance(node, zarr.Group):
            names = sorted(name for name, _ in node.arrays())
            raise InputError(
                f"{self.path}: is a zarr group, not an array; give <store>/<array> "
                f"(arrays here: {', '.join(names) or 'none'})"
            )
        return node

    def _geo(self, array) -> GeoInfo:
        try:
            return GeoInfo.from_attrs(dict(array.attrs))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(
                f"{self.path}: invalid georeferencing attributes ({one_line(exc)})"
            ) from exc

    def sha256(self) -> str:
        return sha256_array(self._array())


# ----------------------------------------------------------------------- dispatch

#: The formats, asked in this order; a directory is only ever a zarr array.
_FORMATS: tuple[type[_Source], ...] = (ZarrSource, RasterioSource, NumpySource)


def open_source(path: str) -> _Source:
    """The reader of an existing input ``path``.

    Raises
    ------
    InputError
        If ``path`` does not exist or cannot be reached (a folder on its path
        the user may not enter), or no format reads it (the message lists the
        supported extensions).
    """
    try:
        os.stat(path)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file or directory") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied (a folder on its path cannot be entered)") from None
    except OSError as exc:  # a file used as a folder on the path, a name too long ...
        raise InputError(f"{path}: {exc.strerror or exc}") from None
    for fmt in _FORMATS:
        if fmt.accepts(path):
            return fmt(path)
    if _gdal_opens(path):  # any raster GDAL reads (VRT, JPEG 2000, COG ...), known by opening it
        return RasterioSource(path)
    extensions = ", ".join(ext for fmt in _FORMATS for ext in fmt.extensions)
    others = "".join(f" or {fmt.label}" for fmt in _FORMATS if fmt.label)
    ext = os.path.splitext(path)[1].lower()
    raise InputError(
        f"{path}: unsupported format {ext or '(no extension)'!r}; "
        f"expected one of {extensions}{others}, or any other raster GDAL opens (this one it does not)"
    )


def _gdal_opens(path: str) -> bool:
    """Whether GDAL opens the file ``path`` as a raster (its header only).
    GDAL's INFO line about a file it does not recognise is demoted to DEBUG
    (:func:`quiet_gdal`): the caller's one-line error says it."""
    if os.path.isdir(path):
        return False
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    try:
        with quiet_gdal(), warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path) as ds:
                return ds.count > 0 and ds.width > 0 and ds.height > 0
    except (RasterioIOError, OSError, ValueError):
        return False


def is_zarr_array(path: str) -> bool:
    """Whether the directory ``path`` is a zarr array (v3 ``zarr.json`` of
    node type array, or v2 ``.zarray``)."""
    import json

    if os.path.isfile(os.path.join(path, ".zarray")):
        return True
    try:
        with open(os.path.join(path, "zarr.json")) as fh:
            return json.load(fh).get("node_type") == "array"
    except (OSError, ValueError, AttributeError):
        return False


def expand_references(paths) -> list[str]:
    """A reference set as files: each of ``paths`` is a raster file (GDAL's,
    ``.npy``), a zarr array directory, or a folder of reference files (its
    rasters, sorted by name; other files left out).  Mosaic order is kept:
    the first file with data wins.

    Raises
    ------
    InputError
        A folder with no raster in it (named).
    """
    out = []
    for path in paths:
        path = os.fspath(path)
        if not os.path.isdir(path) or is_zarr_array(path):
            out.append(path)
            continue
        found = []
        for name in sorted(os.listdir(path)):
            member = os.path.join(path, name)
            if name.startswith(".") or not os.path.isfile(member):
                continue
            if os.path.splitext(name)[1].lower() in NumpySource.extensions + RasterioSource.extensions \
                    or _gdal_opens(member):
                found.append(member)
        if not found:
            raise InputError(f"{path}: a folder of reference files with no raster in it")
        out.extend(found)
    return out
