"""The zarr v3 output store: create in a partial directory, write, then rename.

A run writes into ``<path>.partial`` next to the final path and only
:func:`finalize_result_store` makes it visible under the final name, so a failed
run never leaves a half-written store at ``<path>``.  Every array carries
``dimension_names`` and the final store has consolidated metadata, so

>>> import xarray as xr
>>> ds = xr.open_zarr("out.zarr")  # doctest: +SKIP

opens it with dims such as ``change_mask (y, x)``, ``trajectory (row, axis)`` and
``gain (tile_y, tile_x)`` and without warnings; no extra argument is needed.
A georeferenced store also has ``x`` / ``y`` coordinates and a CF ``spatial_ref``
(:func:`tiles.write_spatial_coords`), which rioxarray reads.
(A store that was not finalized has no consolidated metadata: open it with
``xr.open_zarr(path, consolidated=False)``.)
"""

from __future__ import annotations

import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rsmb.ops._errors import InputError, ParameterError, one_line

from ._json import jsonable

__all__ = [
    "ArraySpec",
    "abort_result_store",
    "check_writable",
    "is_complete_store",
    "repair_interrupted_overwrite",
    "create_result_store",
    "finalize_result_store",
    "open_result_store",
    "partial_path",
    "update_attrs",
    "write_array",
]

_PARTIAL = ".partial"
_REPLACED = ".replaced"
_ZARR_MARKERS = ("zarr.json", ".zgroup", ".zarray")
#: Root attribute :func:`finalize_result_store` sets: the store is whole.
COMPLETE_ATTR = "complete"


# image arrays of the output store (see ArraySpec.compressed)
_COMPRESSORS = {"name": "blosc", "configuration": {"cname": "lz4", "clevel": 5, "shuffle": "shuffle"}}


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


# ------------------------------------------------------------------------- helpers


def _is_zarr_store(path: Path) -> bool:
    return path.is_dir() and any((path / m).exists() for m in _ZARR_MARKERS)


def _check_replaceable(path: Path, *, overwrite: bool) -> None:
    """InputError unless ``path`` is absent, or a zarr store and ``overwrite``."""
    if not os.path.lexists(path):
        return
    if not overwrite:
        raise InputError(f"{path}: output exists; pass --overwrite to replace it")
    if not _is_zarr_store(path):
        raise InputError(
            f"{path}: output exists and is not a zarr store; refusing to replace it"
        )


def check_writable(path: str | os.PathLike) -> None:
    """Raise :class:`InputError` unless ``path`` can be created: its nearest
    existing ancestor must be a directory in which a file can be written (tried,
    so that read-only file systems, permissions and quotas all count).

    Raises
    ------
    InputError
        One line naming ``path`` and the reason.
    """
    target = Path(os.path.abspath(path))
    parent = target.parent
    while not os.path.lexists(parent):
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{path}: cannot be created: {parent} is a file, not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=".rsmb-write-test-", dir=parent)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(f"{path}: cannot write in {parent} ({exc.strerror or exc})") from None


def _replaced_path(final: Path) -> Path:
    return final.with_name(f"{final.name}{_REPLACED}")


def is_complete_store(path: str | os.PathLike) -> bool:
    """True for a store :func:`finalize_result_store` finished (its root
    attribute ``complete`` says so)."""
    import json

    try:
        meta = json.loads((Path(path) / "zarr.json").read_text())
    except (OSError, ValueError):
        return False
    return bool(meta.get("attributes", {}).get(COMPLETE_ATTR))


def repair_interrupted_overwrite(path: str | os.PathLike) -> str | None:
    """Finish or undo an overwrite that was killed between its two renames.

    :func:`finalize_result_store` moves an old store to ``<path>.replaced``,
    renames the new one from ``<path>.partial`` to ``<path>``, then deletes the
    old one.  Killed after the first rename, ``<path>`` is missing: the new
    store is put in place when it is complete, otherwise the old one is put
    back.  Killed before the deletion, the old store is deleted.

    Returns
    -------
    str or None
        What was done ("completed", "restored", "cleaned"), None if nothing was
        interrupted.
    """
    final = Path(path)
    old = _replaced_path(final)
    if not os.path.lexists(old):
        return None
    if os.path.lexists(final):
        shutil.rmtree(old, ignore_errors=True)
        return "cleaned"
    tmp = partial_path(final)
    if is_complete_store(tmp):
        os.replace(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
        return "completed"
    os.replace(old, final)
    return "restored"


def _group_path(group_or_path: Any) -> Path:
    """Local directory of a zarr group (or a path given as is)."""
    if isinstance(group_or_path, (str, os.PathLike)):
        return Path(group_or_path)
    store = getattr(group_or_path, "store", None)
    root = getattr(store, "root", None)
    if root is None:
        raise ParameterError(
            f"store: expected a path or a zarr group on a local directory, got "
            f"{type(group_or_path).__name__}"
        )
    return Path(root) / group_or_path.path


def _consolidate(path: Path) -> None:
    import zarr

    with warnings.catch_warnings():
        # zarr-python warns that consolidated metadata is not (yet) in the v3 spec;
        # xarray uses it, and it is what lets xr.open_zarr(path) work without warnings.
        warnings.filterwarnings("ignore", message=".*[Cc]onsolidated metadata.*")
        zarr.consolidate_metadata(str(path))


# ---------------------------------------------------------------------- public API


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
                compressors=_COMPRESSORS if spec.compressed else None,
            )
    except BaseException:
        abort_result_store(tmp)
        raise
    return group


def partial_path(path: str | os.PathLike) -> Path:
    """The directory where a run writes the store that will become ``path``."""
    final = Path(path)
    return final.with_name(f"{final.name}{_PARTIAL}")


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


def finalize_result_store(
    tmp_group_or_path, final_path: str | os.PathLike, *, overwrite: bool
) -> Path:
    """Consolidate the partial store's metadata and rename it to its final path.

    The rename is atomic (one ``os.replace`` on the same file system).  When
    ``overwrite`` is True an existing store is first moved to
    ``<final>.replaced`` and deleted only after the new store is in place; a
    run killed between the two renames is repaired by the next one (see
    :func:`repair_interrupted_overwrite`).

    Parameters
    ----------
    tmp_group_or_path : zarr.Group or path-like
        The group returned by :func:`create_result_store`, or its directory.
    final_path : str or path-like
        Final path of the store.
    overwrite : bool
        Replace an existing store at ``final_path``.

    Returns
    -------
    pathlib.Path
        ``final_path``.  The group object passed in no longer points at a store: open
        the result with :func:`open_result_store`.

    Raises
    ------
    InputError
        If ``final_path`` exists and ``overwrite`` is False, or is not a zarr store.
    """
    import zarr

    tmp = _group_path(tmp_group_or_path)
    final = Path(final_path)
    if not _is_zarr_store(tmp):
        raise InputError(f"{tmp}: no partial store to finalize")
    _check_replaceable(final, overwrite=overwrite)
    zarr.open_group(store=str(tmp), mode="r+").attrs[COMPLETE_ATTR] = True
    _consolidate(tmp)
    old = _replaced_path(final)
    if os.path.lexists(final):
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
    try:
        os.replace(tmp, final)
    except BaseException:
        if os.path.lexists(old) and not os.path.lexists(final):
            os.replace(old, final)
        raise
    shutil.rmtree(old, ignore_errors=True)
    return final


def update_attrs(path: str | os.PathLike, updates: dict[str, Any]) -> None:
    """Update the root attributes of a finished store (``updates`` through
    :func:`jsonable`) and consolidate its metadata again."""
    import zarr

    zarr.open_group(store=str(path), mode="r+").attrs.update(jsonable(updates))
    _consolidate(Path(path))


def abort_result_store(tmp_group_or_path) -> None:
    """Delete a partial store (a no-op if it is already gone).

    Raises
    ------
    ParameterError
        If the path is not a ``<name>.partial`` directory, so a final store
        is never deleted by mistake.
    """
    tmp = _group_path(tmp_group_or_path)
    if _PARTIAL not in tmp.name:
        raise ParameterError(
            f"store: expected a partial store '<name>{_PARTIAL}', got {tmp}"
        )
    shutil.rmtree(tmp, ignore_errors=True)


def open_result_store(path: str | os.PathLike):
    """Open a finished output store read-only.

    Returns
    -------
    zarr.Group

    Raises
    ------
    InputError
        If ``path`` does not exist or is not a zarr group.
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
    return node
