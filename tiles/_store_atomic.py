"""Where a result store lives on disk while it is written, and how it is made
visible: never half-written, never clobbered by accident.

A run writes into ``<path>.partial`` next to the final path, and only
:func:`finalize_result_store` makes it visible under the final name, with one
``os.replace`` on the same file system, so a failed run never leaves a
half-written store at ``<path>``.  An existing store is replaced only with
``overwrite``: it is moved aside to ``<path>.replaced`` and deleted once the new
store is in place; a run killed between the two renames is finished or undone
by the next one (:func:`repair_interrupted_overwrite`).  Only ``*.partial``
directories are ever deleted as scratch (:func:`abort_result_store`).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any

from rsmb.ops._errors import InputError, ParameterError

__all__ = [
    "abort_result_store",
    "check_writable",
    "finalize_result_store",
    "is_complete_store",
    "partial_path",
    "repair_interrupted_overwrite",
    "swap_into_place",
]

_PARTIAL = ".partial"
_REPLACED = ".replaced"
_ZARR_MARKERS = ("zarr.json", ".zgroup", ".zarray")
#: Root attribute :func:`finalize_result_store` sets: the store is whole.
COMPLETE_ATTR = "complete"


# ------------------------------------------------------------------- paths and checks


def partial_path(path: str | os.PathLike) -> Path:
    """The directory where a run writes the store that will become ``path``."""
    final = Path(path)
    return final.with_name(f"{final.name}{_PARTIAL}")


def _replaced_path(final: Path) -> Path:
    return final.with_name(f"{final.name}{_REPLACED}")


def _is_zarr_store(path: Path) -> bool:
    return path.is_dir() and any((path / m).exists() for m in _ZARR_MARKERS)


def is_complete_store(path: str | os.PathLike) -> bool:
    """True for a store :func:`finalize_result_store` finished (its root
    attribute ``complete`` says so)."""
    import json

    try:
        meta = json.loads((Path(path) / "zarr.json").read_text())
    except (OSError, ValueError):
        return False
    return bool(meta.get("attributes", {}).get(COMPLETE_ATTR))


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


# --------------------------------------------------------------- finalize, abort, repair


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
    swap_into_place(tmp, final, overwrite=overwrite)
    return final


def swap_into_place(tmp: str | os.PathLike, final: str | os.PathLike, *, overwrite: bool) -> Path:
    """Make ``tmp``, a file or a directory written aside on the same file
    system, visible as ``final``: the one way rsmb puts an output in place.

    A file is renamed with one ``os.replace`` (without ``overwrite``, a hard
    link first, so that a ``final`` that appeared meanwhile is never
    clobbered).  A directory replacing another is two renames: the old one
    is moved to ``<final>.replaced``, ``tmp`` renamed to ``final``, then the
    old one deleted (put back if the second rename fails; a run killed
    between them is finished or undone by :func:`repair_interrupted_overwrite`).

    Raises
    ------
    InputError
        ``final`` exists and ``overwrite`` is False (``tmp`` is left as it is).
    """
    tmp, final = Path(tmp), Path(final)
    if os.path.lexists(final) and not overwrite:
        raise InputError(f"{final}: output exists; pass --overwrite to replace it")
    if not tmp.is_dir():
        _swap_file(tmp, final, overwrite)
        return final
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


def _swap_file(tmp: Path, final: Path, overwrite: bool) -> None:
    if overwrite:
        os.replace(tmp, final)
        return
    try:
        os.link(tmp, final)
    except FileExistsError:
        raise InputError(f"{final}: output exists; pass --overwrite to replace it") from None
    except OSError:  # no hard links on this file system
        os.replace(tmp, final)
        return
    os.unlink(tmp)


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
