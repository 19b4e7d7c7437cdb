"""The zarr v3 output store: its arrays, their creation, writing and reading.

A run creates the store with :func:`create_result_store` in a partial
directory and makes it visible with :func:`finalize_result_store`
(:mod:`tiles._store_atomic`: atomic rename, overwrite and its repair).  Every
array carries ``dimension_names`` and the final store has consolidated
metadata, so

>>> import xarray as xr
>>> ds = xr.open_zarr("out.zarr")  # doctest: +SKIP

opens it with dims such as ``change_mask_reference (y, x)``, ``trajectory (row, axis)`` and
``gain (tile_y, tile_x)`` and without warnings; no extra argument is needed.
A georeferenced store also has ``x`` / ``y`` coordinates and a CF ``spatial_ref``
(:func:`tiles.write_spatial_coords`), which rioxarray reads.
(A store that was not finalized has no consolidated metadata: open it with
``xr.open_zarr(path, consolidated=False)``.)
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rsmb.ops._errors import InputError, ParameterError, one_line

from ._json import jsonable
from ._store_atomic import (_check_replaceable, _consolidate, _is_zarr_store, _replaced_path, abort_result_store,
                            check_writable, is_complete_store, partial_path, repair_interrupted_overwrite)

__all__ = [
    "ArraySpec",
    "create_result_store",
    "open_result_store",
    "update_attrs",
    "write_array",
]

#: The codec of the output store's image arrays (Blosc LZ4, byte shuffle), also for arrays written outside
#: :func:`create_result_store` (zarr's own default, Zstandard, costs more to write and to read).
IMAGE_COMPRESSORS = {"name": "blosc", "configuration": {"cname": "lz4", "clevel": 5, "shuffle": "shuffle"}}


@dataclass(frozen=True)
class ArraySpec:
    """Shape, dtype, chunking and dimension names of one output array.

    Attributes
    ----------
    shape : tuple of int
        Array shape, e.g. (H, W) in pixels.
    dtype : str
        NumPy dtype name, e.g. ``"uint8"`` or ``"float32"``.
    chunks : tuple of int
        Chunk shape, same length as ``shape`` (e.g. the core tile size).
    dims : tuple of str
        Dimension names, same length as ``shape``, e.g. ``("y", "x")``.
    fill_value : int or float, default 0
        Value of chunks never written.
    compressed : bool, default True
        Blosc LZ4 with byte shuffle (fast to write, see the README's figures);
        False for scratch arrays that
        are written once, read once and deleted.
    """

    shape: tuple[int, ...]
    dtype: str
    chunks: tuple[int, ...]
    dims: tuple[str, ...]
    fill_value: int | float = 0
    compressed: bool = True

    def __post_init__(self) -> None:
        shape = tuple(int(n) for n in self.shape)
        chunks = tuple(int(n) for n in self.chunks)
        dims = tuple(str(d) for d in self.dims)
        if not (len(shape) == len(chunks) == len(dims)):
            raise ParameterError(
                f"ArraySpec: shape {shape}, chunks {chunks} and dims {dims} must have "
                f"the same length"
            )
        if any(n < 0 for n in shape) or any(n < 1 for n in chunks):
            raise ParameterError(
                f"ArraySpec: expected shape >= 0 and chunks >= 1, got shape {shape}, "
                f"chunks {chunks}"
            )
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "chunks", chunks)
        object.__setattr__(self, "dims", dims)
        object.__setattr__(self, "dtype", np.dtype(self.dtype).name)


def create_result_store(
    path: str | os.PathLike,
    arrays: dict[str, ArraySpec],
    attrs: dict[str, Any],
    *,
    overwrite: bool,
    resume: bool = False,
):
    """Create the output zarr v3 group in a partial sibling directory.

    Parameters
    ----------
    path : str or path-like
        Final path of the store, e.g. ``out.zarr``.  Nothing is written there yet:
        the group lives in ``<path>.partial`` until
        :func:`finalize_result_store` (or :func:`abort_result_store`).
    arrays : dict of str to ArraySpec
        Arrays to create, filled with their ``fill_value``, with ``dimension_names``.
    attrs : dict
        Root attributes; converted with :func:`jsonable`.
    overwrite : bool
        Whether an existing store at ``path`` may be replaced at finalisation.
    resume : bool
        Reopen the partial directory an interrupted run left behind (its arrays
        and what was written to them are kept) instead of starting afresh.  A
        stale partial directory is removed when ``resume`` is False.

    Returns
    -------
    zarr.Group
        The writable group in the partial directory.

    Raises
    ------
    InputError
        If ``path`` exists and ``overwrite`` is False ("output exists; pass
        --overwrite to replace it"), or it exists and is not a zarr store.
    """
    import zarr

    final = Path(path)
    repair_interrupted_overwrite(final)
    _check_replaceable(final, overwrite=overwrite)
    check_writable(final)
    root_attrs = jsonable(attrs)
    tmp = partial_path(final)
    if _is_zarr_store(tmp):
        if resume and not is_complete_store(tmp):
            return zarr.open_group(store=str(tmp), mode="r+")
        abort_result_store(tmp)
    group = zarr.create_group(store=str(tmp), zarr_format=3, attributes=root_attrs)
    try:
        for name, spec in arrays.items():
            group.create_array(
                name,
                shape=spec.shape,
                chunks=spec.chunks,
                dtype=spec.dtype,
                dimension_names=spec.dims,
                fill_value=spec.fill_value,
                compressors=IMAGE_COMPRESSORS if spec.compressed else None,
            )
    except BaseException:
        abort_result_store(tmp)
        raise
    return group


def write_array(
    group, name: str, array: np.ndarray, region: tuple[slice, ...] | None = None
) -> None:
    """Write ``array`` into the array ``name`` of ``group``, whole or in a region.

    Parameters
    ----------
    group : zarr.Group
        A writable group, e.g. from :func:`create_result_store`.
    name : str
        Array name in the group.
    array : ndarray
        Values; shape equal to the array's shape, or to the region's shape.
    region : tuple of slice, optional
        Region to write, one slice per dimension (step 1).  Regions aligned with
        chunks can be written in parallel.

    Raises
    ------
    ParameterError
        If the array is missing from the group or the shapes do not match.
    """
    try:
        target = group[name]
    except KeyError:
        names = sorted(n for n, _ in group.arrays())
        raise ParameterError(f"name: expected one of {names}, got {name!r}") from None
    array = np.asarray(array)
    if region is None:
        region = tuple(slice(None) for _ in target.shape)
    region = tuple(region)
    if len(region) != len(target.shape):
        raise ParameterError(
            f"region: expected {len(target.shape)} slices for {name!r}, "
            f"got {len(region)}"
        )
    expected = tuple(len(range(*s.indices(n))) for s, n in zip(region, target.shape))
    if array.shape != expected:
        raise ParameterError(
            f"array: expected shape {expected} for {name!r}{_fmt_region(region)}, "
            f"got {array.shape}"
        )
    target[region] = array


def _fmt_region(region: tuple[slice, ...]) -> str:
    def bound(value: int | None) -> str:
        return "" if value is None else str(value)

    return "[" + ", ".join(f"{bound(s.start)}:{bound(s.stop)}" for s in region) + "]"


def update_attrs(path: str | os.PathLike, updates: dict[str, Any]) -> None:
    """Update the root attributes of a store (``updates`` through
    :func:`jsonable`) in one metadata write.  The consolidated metadata of a
    finished store lives in the same root document and holds only the
    children's metadata, which this leaves alone: it is kept as it is, and
    made only for a store that has none."""
    import zarr

    group = zarr.open_group(store=str(path), mode="r+", zarr_format=3)
    group.update_attributes(jsonable(updates))
    if group.metadata.consolidated_metadata is None:
        _consolidate(Path(path))


def open_result_store(path: str | os.PathLike, required: tuple[str, ...] = ()):
    """Open a finished output store read-only.

    Parameters
    ----------
    path : str or path-like
    required : sequence of str
        Arrays a caller reads: when given, the store must hold them and the
        ``tile_grid`` attribute every ``rsmb detect`` store has.

    Returns
    -------
    zarr.Group

    Raises
    ------
    InputError
        If ``path`` does not exist or is not a zarr group, or (with
        ``required``) is not an rsmb detect store with those arrays.
    """
    import zarr

    store = Path(path)
    if not store.exists():
        if os.path.lexists(_replaced_path(store)):
            raise InputError(f"{store}: an overwrite of this store was interrupted; run detect on it again "
                             f"to repair it")
        raise InputError(f"{store}: no such output store")
    try:
        node = zarr.open(store=str(store), mode="r")
    except Exception as exc:  # noqa: BLE001 - zarr raises many types for bad stores
        raise InputError(
            f"{store}: not a readable zarr store ({one_line(exc)})"
        ) from exc
    if not isinstance(node, zarr.Group):
        raise InputError(f"{store}: is a zarr array, expected a zarr group")
    missing = [name for name in required if name not in node]
    if missing:
        raise InputError(f"{store}: not an rsmb detect store (array(s) {', '.join(missing)} missing)")
    if required and "tile_grid" not in node.attrs:
        raise InputError(f"{store}: not an rsmb detect store (no 'tile_grid' attribute)")
    return node
