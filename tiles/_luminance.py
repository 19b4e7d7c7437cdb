"""The dtype and luminance policy, written once for every input format.

Integers are scaled to [0, 1] by the maximum of their dtype, floats are kept as
they are (:func:`as_float01`); colour becomes luminance with the ITU-R BT.601
weights (:func:`_luminance`); an alpha band and per-band nodata become a validity
mask, never a magic number (:func:`bands_to_luminance`).  Band roles follow the
band count: 1 gray, 2 gray + alpha, 3 RGB, 4 RGBA.
"""

from __future__ import annotations

import math

import numpy as np

from rsmb.ops._errors import InputError

# ITU-R BT.601 luma weights, as Python floats so float32 stays float32 (STYLE 6).
_LUMA_RGB = (0.299, 0.587, 0.114)


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


def default_alpha_index(count: int) -> int | None:
    """Band roles by count: 2 = gray+alpha, 4 = RGBA; otherwise no alpha."""
    return count - 1 if count in (2, 4) else None


def bands_to_luminance(
    bands: list[np.ndarray],
    *,
    alpha_index: int | None,
    nodatavals: list[float | None],
    name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Validity from alpha and per-band nodata, then luminance.

    Parameters
    ----------
    bands : list of ndarray, each shape (H, W)
        Every band of the input in its input dtype, alpha included.
    alpha_index : int or None
        Position of the alpha band in ``bands``; None when there is none.
    nodatavals : list of float or None
        Nodata value of each band; a pixel is invalid when every colour band
        holds its own value (NaN matches NaN).
    name : str
        File name for error messages.

    Returns
    -------
    data : ndarray, shape (H, W), float32
        Luminance, 0 where invalid (see :func:`_luminance`).
    valid : ndarray, shape (H, W), bool
        False where alpha is 0, every colour band is nodata, or a float band
        is NaN.
    """
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
    for band in colour:  # NaN in a float band is no-data, with or without a nodata tag
        if band.dtype.kind == "f":
            invalid |= np.isnan(band)
    return _luminance(colour, invalid, name=name)


def array_to_luminance(
    array: np.ndarray, *, nodata: float | None = None, name: str
) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) or channel-last (H, W, 1..4) array -> luminance, valid.

    Band roles follow the channel count (:func:`default_alpha_index`); ``nodata`` (from a zarr array's ``"nodata"`` attribute) applies to every colour
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
    return bands_to_luminance(
        bands,
        alpha_index=default_alpha_index(len(bands)),
        nodatavals=[nodata] * len(bands),
        name=name,
    )
