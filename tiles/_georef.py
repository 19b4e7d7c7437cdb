"""Georeferenced pairs: which reference pixels a capture is compared with.

DESIGN.md, "Georeferenced pairs": when the capture and every reference file are
georeferenced, georeferencing decides what is compared with what.  The reference
set may be larger than the capture, split over several files, or on another grid
(pixel size, CRS); :func:`reference_window` resamples it onto the capture's grid one
window at a time, reading from each file only the pixels under that window, so
memory is bounded by the window, never by the reference.  The pairing rule is in
:mod:`tiles._pairing`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence, Union

import numpy as np

from rsmb.ops._errors import InputError, ParameterError

from ._ingest import read_padded
from ._geo import GeoInfo
from ._io import ImageInfo, probe_header, read_window

__all__ = [
    "RasterGrid",
    "Coverage",
    "is_georeferenced",
    "reference_coverage",
    "reference_window",
    "resampling_for",
]

#: Points per edge when a footprint is carried into another CRS (edges curve).
_DENSIFY = 21
#: At most this many coverage samples along each side of the capture.
_COVERAGE_SAMPLES = 1024
#: Two grids whose origins differ by a whole number of pixels within this many
#: pixels (and share CRS, pixel size and rotation) are the same grid.
_ALIGN_TOL = 1e-6
#: Radius of the resampling kernels in reference pixels (lanczos: 3), widened by
#: the ratio of pixel sizes where the reference is finer: the reference pixels
#: read around a window beyond those under it.
_KERNEL_PAD = 3
#: A capture pixel that spans at least this many reference pixels along both of
#: its axes is the mean of the reference pixels under it (``average``); any
#: other pixel-size ratio is resampled with a Lanczos kernel.
_AVERAGE_RATIO = 2.0

PathOrGrid = Union[str, os.PathLike, "RasterGrid"]


# ------------------------------------------------------------------------- grids


def is_georeferenced(geo: GeoInfo) -> bool:
    """True when ``geo`` has both a CRS and a geotransform."""
    return geo.crs is not None and geo.transform is not None


@lru_cache(maxsize=64)
def _crs(wkt: str):
    from rasterio.crs import CRS

    return CRS.from_wkt(wkt)


@dataclass(frozen=True)
class RasterGrid:
    """The pixel grid of a georeferenced raster: where each pixel lies.

    Attributes
    ----------
    path : str
        The file the grid belongs to (named in error messages).
    crs : str
        Coordinate reference system, WKT.
    transform : tuple of 6 float
        Affine ``(a, b, c, d, e, f)`` in rasterio's order: ``x = a col + b row + c``,
        ``y = d col + e row + f`` for pixel-corner coordinates (col, row); x, y in
        CRS units.
    shape : tuple of int
        (H, W) in pixels.
    """

    path: str
    crs: str
    transform: tuple[float, ...]
    shape: tuple[int, int]

    def __post_init__(self) -> None:
        coeffs = tuple(float(v) for v in self.transform)
        if len(coeffs) != 6:
            raise ParameterError(f"transform: expected 6 affine coefficients, got {len(coeffs)}")
        if coeffs[0] * coeffs[4] - coeffs[1] * coeffs[3] == 0.0:
            raise InputError(f"{self.path}: degenerate geotransform {coeffs} (zero pixel area)")
        object.__setattr__(self, "transform", coeffs)
        object.__setattr__(self, "shape", (int(self.shape[0]), int(self.shape[1])))

    @classmethod
    def from_info(cls, info: ImageInfo) -> RasterGrid:
        """The grid of a probed image (:func:`rsmb.tiles.probe_image`).

        Raises
        ------
        InputError
            If the image has no CRS or no geotransform.
        """
        return cls._from_geo(info.path, tuple(info.shape), info.geo)

    @classmethod
    def from_path(cls, path: str | os.PathLike) -> RasterGrid:
        """The grid of an image file, from its header only (no pixel read, no checksum).

        Raises
        ------
        InputError
            Unreadable file, or no CRS or no geotransform.
        """
        name = os.fspath(path)
        shape, geo = probe_header(name)
        return cls._from_geo(name, shape, geo)

    @classmethod
    def _from_geo(cls, path: str, shape: tuple, geo: GeoInfo) -> RasterGrid:
        if not is_georeferenced(geo):
            missing = "CRS" if geo.crs is None else "geotransform"
            raise InputError(f"{path}: is not georeferenced (no {missing})")
        return cls(path, geo.crs, geo.transform, shape)

    @property
    def affine(self):
        """The transform as a rasterio ``Affine``."""
        from rasterio.transform import Affine

        return Affine(*self.transform)

    def window_affine(self, rows: slice, cols: slice):
        """``Affine`` of the window ``rows, cols`` (its pixel (0, 0) is (rows.start, cols.start))."""
        from rasterio.transform import Affine

        return self.affine @ Affine.translation(cols.start, rows.start)

    def footprint(self, crs: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Outline of the raster, densified, in ``crs`` (default: its own).

        Returns
        -------
        xs, ys : ndarray, shape (4 * 21 + 1,), float64
            A closed ring of the pixel-corner outline in CRS units.
        """
        return _ring(self.affine, self.shape, self.crs, crs)


def _ring(affine, shape, src_crs: str, dst_crs: str | None):
    """Closed, densified outline of a (H, W) pixel rectangle, in ``dst_crs``."""
    h, w = shape
    t = np.linspace(0.0, 1.0, _DENSIFY, endpoint=False)
    cols = np.concatenate([t * w, np.full_like(t, w), (1 - t) * w, np.zeros_like(t), [0.0]])
    rows = np.concatenate([np.zeros_like(t), t * h, np.full_like(t, h), (1 - t) * h, [0.0]])
    xs, ys = affine @ (cols, rows)
    return _transform_points(src_crs, dst_crs, np.asarray(xs), np.asarray(ys))


def _transform_points(src_crs: str, dst_crs: str | None, xs: np.ndarray, ys: np.ndarray):
    if dst_crs is None or _crs(src_crs) == _crs(dst_crs):
        return xs, ys
    from rasterio.warp import transform

    xt, yt = transform(_crs(src_crs), _crs(dst_crs), xs.tolist(), ys.tolist())
    return np.asarray(xt, dtype=np.float64), np.asarray(yt, dtype=np.float64)


def _as_grids(references: PathOrGrid | Sequence[PathOrGrid]) -> list[RasterGrid]:
    if isinstance(references, (str, os.PathLike, RasterGrid)):
        references = [references]
    grids = [r if isinstance(r, RasterGrid) else RasterGrid.from_path(r) for r in references]
    if not grids:
        raise ParameterError("references: expected at least one reference file, got none")
    return grids


# ---------------------------------------------------------------------- coverage


@dataclass(frozen=True)
class Coverage:
    """How much of a capture the reference set covers (by footprints, not pixels).

    Attributes
    ----------
    fraction : float
        Fraction in [0, 1] of the capture's footprint inside the union of the
        reference footprints, measured on the capture's pixel centres (on a regular
        subsample of at most 1024 x 1024 of them for larger captures).
    files : tuple of str
        The reference files whose footprint overlaps the capture's, in the order
        given.
    file_fractions : tuple of float
        For every reference given (same order), the fraction of the capture it
        covers on its own.
    """

    fraction: float
    files: tuple[str, ...]
    file_fractions: tuple[float, ...]


def reference_coverage(references: PathOrGrid | Sequence[PathOrGrid], capture: RasterGrid) -> Coverage:
    """Fraction of the capture covered by the reference set, and which files cover it.

    Each reference's outline (its full pixel rectangle: nodata inside it counts as
    covered) is carried into the capture's CRS with densified edges and rasterised
    onto the capture's pixel centres.

    Parameters
    ----------
    references : path, RasterGrid or sequence of them
        The reference set (paths are read for their header only).
    capture : RasterGrid

    Returns
    -------
    Coverage
    """
    from rasterio.features import rasterize
    from rasterio.transform import Affine

    grids = _as_grids(references)
    h, w = capture.shape
    step = max(1, math.ceil(max(h, w) / _COVERAGE_SAMPLES))
    nh, nw = math.ceil(h / step), math.ceil(w / step)
    sample_affine = capture.affine @ Affine.scale(w / nw, h / nh)
    union = np.zeros((nh, nw), dtype=bool)
    fractions = []
    for grid in grids:
        xs, ys = grid.footprint(capture.crs)
        ok = np.isfinite(xs) & np.isfinite(ys)
        covered = np.zeros((nh, nw), dtype=bool)
        if ok.sum() >= 4:
            ring = list(zip(xs[ok].tolist(), ys[ok].tolist()))
            shape = {"type": "Polygon", "coordinates": [ring]}
            covered = rasterize([(shape, 1)], out_shape=(nh, nw), transform=sample_affine,
                                fill=0, dtype="uint8").astype(bool)
        union |= covered
        fractions.append(float(covered.mean()))
    files = tuple(g.path for g, f in zip(grids, fractions) if f > 0.0)
    return Coverage(float(union.mean()), files, tuple(fractions))


# ------------------------------------------------------------------ resampling


def _pixel_steps(reference: RasterGrid, capture: RasterGrid) -> tuple[float, float]:
    """Length, in reference pixels, of one capture pixel step along the capture's
    columns and along its rows, at the capture's centre."""
    h, w = capture.shape
    cols = np.array([w / 2, w / 2 + 1, w / 2])
    rows = np.array([h / 2, h / 2, h / 2 + 1])
    xs, ys = capture.affine @ (cols, rows)
    xs, ys = _transform_points(capture.crs, reference.crs, np.asarray(xs, float), np.asarray(ys, float))
    c, r = ~reference.affine @ (xs, ys)
    c, r = np.asarray(c), np.asarray(r)
    return float(np.hypot(c[1] - c[0], r[1] - r[0])), float(np.hypot(c[2] - c[0], r[2] - r[0]))


def resampling_for(reference: RasterGrid, capture: RasterGrid) -> str:
    """How ``reference`` is resampled onto ``capture``'s grid, from the ratio of
    their pixel sizes at the capture's centre.

    Parameters
    ----------
    reference, capture : RasterGrid

    Returns
    -------
    str
        ``"copy"`` when the two are one grid (a whole-pixel offset apart);
        ``"average"`` when a capture pixel spans at least two reference pixels
        along both of its axes (the reference pixels under it are averaged);
        ``"lanczos"`` otherwise (a coarser reference, a similar pixel size, or
        finer along one axis only).  Names of ``rasterio.enums.Resampling``.
    """
    if _grid_offset(reference, capture) is not None:
        return "copy"
    steps = _pixel_steps(reference, capture)
    if all(math.isfinite(v) for v in steps) and min(steps) >= _AVERAGE_RATIO:
        return "average"
    return "lanczos"


# ------------------------------------------------------------------ the window


def reference_window(
    references: PathOrGrid | Sequence[PathOrGrid],
    capture: RasterGrid,
    rows: slice,
    cols: slice,
) -> np.ndarray:
    """The reference set's luminance resampled onto a window of the capture grid.

    Parameters
    ----------
    references : path, RasterGrid or sequence of them
        Georeferenced reference files, a mosaic: at each pixel the first file (in
        the order given) with valid data wins.  Any CRS and pixel size.
    capture : RasterGrid
        The grid to resample onto.
    rows, cols : slice
        Window of the capture grid in pixels (integer start and stop, step 1).  It
        may extend beyond the capture (a tile's halo, the search margin): the
        reference is resampled there too where it has data.

    Returns
    -------
    ndarray, shape (rows.stop - rows.start, cols.stop - cols.start), float32
        Luminance with the dtype policy of :func:`rsmb.tiles.read_image`
        (``as_float01``; ``0.299 R + 0.587 G + 0.114 B``), NaN where no reference
        has data (nodata, alpha 0, outside every file).

    Notes
    -----
    Resampling is chosen once per reference file from the ratio of pixel sizes
    (:func:`resampling_for`, the same for every window of a capture, so windows
    stitch seamlessly): where a capture pixel spans at least two reference pixels
    along both axes, the mean of the reference pixels under it (GDAL's
    ``average``, what a coarser sensor integrates); otherwise a Lanczos kernel
    (GDAL's ``lanczos``, windowed sinc of 3 lobes: detail near the reference's
    sampling limit keeps most of its contrast, where bilinear interpolation would
    soften a coarser reference; where the reference is finer along one axis GDAL
    widens the kernel along it).  Nodata pixels are left out of the kernel and
    its weights renormalised over the valid ones; a capture pixel is valid where
    its centre lies on valid reference data.  A reference on the capture's own
    grid (same CRS, pixel size and rotation, origin a whole number of pixels
    away) is copied, not resampled: the result is exact.

    Only the reference pixels under the window (plus a few for the kernel) are
    read from each file; consecutive files on one grid are mosaicked before
    resampling, so their seams are invisible.  Memory is the window's size times
    the squared ratio of capture to reference pixel size.
    """
    rows, cols = _check_window(rows, "rows"), _check_window(cols, "cols")
    out = np.full((rows.stop - rows.start, cols.stop - cols.start), np.nan, dtype=np.float32)
    if out.size == 0:
        return out
    dst_affine = capture.window_affine(rows, cols)
    for run in _same_grid_runs(_as_grids(references)):
        _fill_from_run(out, run, capture.crs, dst_affine, resampling_for(run[0][0], capture))
        if not np.isnan(out).any():
            break
    return out


def _check_window(index: slice, label: str) -> slice:
    if not isinstance(index, slice) or index.step not in (None, 1):
        raise ParameterError(f"{label}: expected a slice with step 1, got {index!r}")
    if not isinstance(index.start, (int, np.integer)) or not isinstance(index.stop, (int, np.integer)):
        raise ParameterError(f"{label}: expected integer start and stop, got {index!r}")
    if index.stop < index.start:
        raise ParameterError(f"{label}: expected stop >= start, got {index!r}")
    return slice(int(index.start), int(index.stop))


def _grid_offset(base: RasterGrid, other: RasterGrid) -> tuple[int, int] | None:
    """(row, col) of ``other``'s pixel (0, 0) in ``base``'s grid when both are the
    same grid (whole-pixel offset), else None."""
    if base.crs != other.crs and _crs(base.crs) != _crs(other.crs):
        return None
    m = ~base.affine @ other.affine  # other's pixels in base's pixels
    if not (abs(m.a - 1) < _ALIGN_TOL and abs(m.e - 1) < _ALIGN_TOL
            and abs(m.b) < _ALIGN_TOL and abs(m.d) < _ALIGN_TOL):
        return None
    dc, dr = round(m.c), round(m.f)
    if abs(m.c - dc) > _ALIGN_TOL or abs(m.f - dr) > _ALIGN_TOL:
        return None
    return int(dr), int(dc)


def _same_grid_runs(grids: list[RasterGrid]) -> list[list[tuple[RasterGrid, tuple[int, int]]]]:
    """Consecutive files on one grid, each with its offset in the run's first grid
    (order kept, so the first-wins rule holds across runs)."""
    runs: list[list[tuple[RasterGrid, tuple[int, int]]]] = []
    for grid in grids:
        offset = _grid_offset(runs[-1][0][0], grid) if runs else None
        if offset is None:
            runs.append([(grid, (0, 0))])
        else:
            runs[-1].append((grid, offset))
    return runs


def _source_window(base: RasterGrid, dst_crs: str, dst_affine, shape) -> tuple[int, int, int, int]:
    """(r0, r1, c0, c1) of ``base``'s pixels under the destination window, padded
    for the resampling kernel (may extend beyond ``base``)."""
    xs, ys = _ring(dst_affine, shape, dst_crs, base.crs)
    ok = np.isfinite(xs) & np.isfinite(ys)
    if not ok.any():
        return 0, 0, 0, 0
    c, r = ~base.affine @ (xs[ok], ys[ok])
    c, r = np.asarray(c), np.asarray(r)
    ratio = max((c.max() - c.min()) / shape[1], (r.max() - r.min()) / shape[0], 1.0)
    pad = math.ceil(_KERNEL_PAD * ratio) + 1
    return (math.floor(r.min()) - pad, math.ceil(r.max()) + pad,
            math.floor(c.min()) - pad, math.ceil(c.max()) + pad)


def _mosaic_run(run, window) -> np.ndarray | None:
    """The run's files pasted into ``window`` of the first file's grid (first valid
    wins), NaN elsewhere; None when no file meets the window."""
    r0, r1, c0, c1 = window
    mosaic = None
    for grid, (dr, dc) in run:
        a0, a1 = max(r0, dr), min(r1, dr + grid.shape[0])
        b0, b1 = max(c0, dc), min(c1, dc + grid.shape[1])
        if a1 <= a0 or b1 <= b0:
            continue
        if mosaic is None:
            mosaic = np.full((r1 - r0, c1 - c0), np.nan, dtype=np.float32)
        data, valid = read_window(grid.path, slice(a0 - dr, a1 - dr), slice(b0 - dc, b1 - dc))
        target = mosaic[a0 - r0:a1 - r0, b0 - c0:b1 - c0]
        np.copyto(target, data, where=valid & np.isnan(target))  # (masked copy: no boolean gather and scatter)
    return mosaic


def _fill_from_run(out: np.ndarray, run, dst_crs: str, dst_affine, resampling: str) -> None:
    """Fill the NaN pixels of ``out`` with one run of same-grid reference files,
    resampled with ``resampling`` (:func:`resampling_for`)."""
    from rasterio.transform import Affine

    base = run[0][0]
    window = _source_window(base, dst_crs, dst_affine, out.shape)
    if window[1] <= window[0] or window[3] <= window[2]:
        return
    mosaic = _mosaic_run(run, window)
    if mosaic is None:
        return
    src_affine = base.affine @ Affine.translation(window[2], window[0])
    warped = _resample(mosaic, base.crs, src_affine, dst_crs, dst_affine, out.shape, resampling)
    np.copyto(out, warped, where=np.isnan(out))


def _resample(src: np.ndarray, src_crs: str, src_affine, dst_crs: str, dst_affine, shape,
              resampling: str) -> np.ndarray:
    """``src`` (NaN = no data) onto the destination grid: a copy when the grids
    coincide up to a whole-pixel offset, else with ``resampling`` (a name of
    ``rasterio.enums.Resampling``)."""
    from rasterio.enums import Resampling
    from rasterio.warp import reproject

    src_grid = RasterGrid("", src_crs, tuple(src_affine)[:6], src.shape)
    dst_grid = RasterGrid("", dst_crs, tuple(dst_affine)[:6], shape)
    offset = _grid_offset(src_grid, dst_grid)
    if offset is not None:
        return read_padded(src, slice(offset[0], offset[0] + shape[0]),
                                   slice(offset[1], offset[1] + shape[1]))
    dst = np.full(shape, np.nan, dtype=np.float32)
    reproject(source=src, destination=dst, src_transform=src_affine, src_crs=_crs(src_crs),
              src_nodata=np.nan, dst_transform=dst_affine, dst_crs=_crs(dst_crs),
              dst_nodata=np.nan, resampling=Resampling["lanczos" if resampling == "copy" else resampling])
    return dst
