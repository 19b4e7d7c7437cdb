"""The pairing rule: how a capture is compared with its reference set.

Called once before any work (:func:`pair_images`):

* capture and every reference georeferenced (a CRS *and* a geotransform): the pair
  is georeferenced.  The reference files are a mosaic (the first file with valid
  data at a pixel wins, in the order given); the footprints must overlap
  (:func:`reference_coverage`), otherwise :class:`InputError`.  Partial overlap is
  allowed: the uncovered part of the capture has no reference data (NaN).
* neither georeferenced: pixel for pixel, one reference file of the capture's size
  (the rule of ungeoreferenced pairs, unchanged).
* exactly one side georeferenced: pixel for pixel as well, with the same size
  rule; the georeferencing present is ignored for the pairing (it is still
  recorded with the outputs).  Without georeferencing on one side nothing says
  where that image lies, so the only defensible pairing is the one the user made
  by cutting the images to the same size (a PNG reference cut by hand for a
  GeoTIFF capture keeps working); guessing a placement would produce silently
  wrong masks.

A file with a geotransform but no CRS (or a CRS but no geotransform) counts as not
georeferenced: two such files cannot be placed relative to each other.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from rsmb.ops._errors import InputError, ParameterError

from ._georef import (Coverage, RasterGrid, _check_window, is_georeferenced, reference_coverage, reference_window,
                      resampling_for)
from ._ingest import read_clipped
from ._io import probe_header

__all__ = ["Pairing", "pair_images"]


@dataclass(frozen=True)
class Pairing:
    """How a capture is compared with its reference set (see the module's rule).

    Attributes
    ----------
    mode : {"georeferenced", "pixel"}
    capture : str
        The capture's path.
    shape : tuple of int
        The capture's (H, W) in pixels: the grid of every output.
    references : tuple of str
        Every reference file given, in order.
    reason : str
        One line saying why this mode was chosen.
    grid : RasterGrid or None
        The capture's grid (georeferenced mode).
    reference_grids : tuple of RasterGrid
        The references that overlap the capture, in the order given (georeferenced
        mode); empty in pixel mode.
    coverage : Coverage or None
        Coverage of the capture by the reference set (georeferenced mode).
    """

    mode: str
    capture: str
    shape: tuple[int, int]
    references: tuple[str, ...]
    reason: str
    grid: RasterGrid | None = None
    reference_grids: tuple[RasterGrid, ...] = field(default=())
    coverage: Coverage | None = None

    def reference_window(self, rows: slice, cols: slice) -> np.ndarray:
        """The reference under the capture window ``rows, cols``.

        Returns
        -------
        ndarray, shape (rows.stop - rows.start, cols.stop - cols.start), float32
            NaN where there is no reference data.  Georeferenced mode:
            :func:`reference_window`; pixel mode: the reference's own pixels (NaN
            beyond its edges, as for the capture's tiles).
        """
        if self.mode == "georeferenced":
            return reference_window(self.reference_grids, self.grid, rows, cols)
        rows, cols = _check_window(rows, "rows"), _check_window(cols, "cols")
        return read_clipped(self.references[0], self.shape, rows, cols)


def pair_images(references: str | os.PathLike | Sequence[str | os.PathLike],
                capture: str | os.PathLike) -> Pairing:
    """Decide how ``capture`` is compared with ``references``, before any work.

    Reads headers only (no pixels, no checksums).

    Parameters
    ----------
    references : path or sequence of paths
        One reference image, or a georeferenced reference set (a mosaic).
    capture : path
        The distorted capture; its grid is the grid of every output.

    Returns
    -------
    Pairing

    Raises
    ------
    InputError
        One line naming the files: unreadable files; footprints that do not
        overlap; in pixel mode, several reference files or a reference of another
        size.
    ParameterError
        No reference given.
    """
    paths = [os.fspath(references)] if isinstance(references, (str, os.PathLike)) else \
        [os.fspath(r) for r in references]
    if not paths:
        raise ParameterError("references: expected at least one reference file, got none")
    cap = os.fspath(capture)
    cap_shape, cap_geo = probe_header(cap)
    headers = [probe_header(p) for p in paths]
    georef = [is_georeferenced(geo) for _, geo in headers]
    if is_georeferenced(cap_geo) and all(georef):
        return _pair_georeferenced(paths, headers, cap, cap_shape, cap_geo)
    if not is_georeferenced(cap_geo) and not any(georef):
        reason = "neither image is georeferenced: compared pixel for pixel"
    else:
        lacking = cap if not is_georeferenced(cap_geo) else paths[georef.index(False)]
        reason = (f"{lacking} is not georeferenced: compared pixel for pixel, "
                  f"georeferencing ignored for the pairing")
    return _pair_pixels(paths, headers, cap, cap_shape, reason)


def _pair_pixels(paths, headers, cap, cap_shape, reason) -> Pairing:
    if len(paths) > 1:
        raise InputError(f"{cap}: {len(paths)} reference files given but {reason.split(':')[0]}; "
                         f"a reference set of several files needs georeferencing on every file "
                         f"and on the capture")
    ref_shape = headers[0][0]
    if ref_shape != cap_shape:
        raise InputError(f"{cap}: size {cap_shape} differs from the reference {paths[0]} "
                         f"{ref_shape}; give images of the same size ({reason})")
    return Pairing("pixel", cap, cap_shape, tuple(paths), reason)


def _pair_georeferenced(paths, headers, cap, cap_shape, cap_geo) -> Pairing:
    grid = RasterGrid._from_geo(cap, cap_shape, cap_geo)
    ref_grids = [RasterGrid._from_geo(p, shape, geo) for p, (shape, geo) in zip(paths, headers)]
    coverage = reference_coverage(ref_grids, grid)
    if not coverage.files:
        raise InputError(f"{cap}: footprint does not overlap the reference {_name_files(paths)}")
    overlapping = tuple(g for g in ref_grids if g.path in coverage.files)
    how = ", ".join(dict.fromkeys(resampling_for(g, grid) for g in overlapping))
    reason = (f"both georeferenced: the reference set is resampled onto the capture grid "
              f"({how}; {coverage.fraction:.1%} of the capture covered)")
    return Pairing("georeferenced", cap, cap_shape, tuple(paths), reason, grid, overlapping, coverage)


def _name_files(paths: Sequence[str], limit: int = 3) -> str:
    names = ", ".join(paths[:limit])
    if len(paths) > limit:
        names += f" and {len(paths) - limit} more"
    return names
