"""Exclusive locks on outputs: one writer per survey folder or result store.

A lock is an exclusive, non-blocking ``flock`` on a lock file (the kernel
releases it when the holding process dies, so a killed run never leaves a
stale lock).  Rules:

- Contention (another process holds it) is :class:`LockBusy`, an
  :class:`InputError` naming the lock file, the holder's pid and what it is
  (its first line), so the caller can say "in use by another rsmb ...".
- Anything else (the folder cannot be written: ``EACCES``, ``EROFS``; the
  file system has no locks: ``ENOLCK``, ``EOPNOTSUPP``) is :class:`LockError`,
  an :class:`InputError` that says what happened, never "in use".
- With ``remove=True`` the lock file is deleted when the lock is released
  (a store's lock leaves nothing beside it).  Deleting a lock file races
  with a process that opened it just before: so a taker checks, once it holds
  the lock, that the path still names the file it locked, and tries again
  otherwise.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from rsmb.ops._errors import InputError, one_line

__all__ = ["FileLock", "LockBusy", "LockError", "acquire_lock", "lock_holder"]

_BUSY = {errno.EWOULDBLOCK, errno.EAGAIN}
_NO_LOCKS = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS}


class LockBusy(InputError):
    """Another process holds the lock."""


class LockError(InputError):
    """The lock could not be taken for another reason than contention."""


class FileLock:
    """A held lock (:func:`acquire_lock`); :meth:`release` or ``with`` ends it."""

    def __init__(self, path: Path, fd: int, remove: bool) -> None:
        self.path, self._fd, self._remove = path, fd, remove

    def release(self) -> None:
        """Release the lock (and delete its file when asked to): idempotent."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        if self._remove:
            try:  # unlinked while held: a process waiting on it sees the path changed and retries
                os.unlink(self.path)
            except OSError:
                pass
        os.close(fd)  # closing the descriptor releases the flock

    close = release

    def __enter__(self) -> FileLock:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _holder(path: Path) -> str:
    try:
        return " ".join(path.read_text(errors="replace").split()[:8])
    except OSError:
        return ""


def lock_holder(path: str | os.PathLike) -> str | None:
    """Who holds the lock ``path`` now (its file's text, such as ``pid 123``,
    or ``"another process"``), or None when nobody does, it does not exist or
    the platform has no ``flock``.  Read-only: the file is neither created
    nor written."""
    try:
        import fcntl
    except ImportError:
        return None
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as exc:
        return (_holder(Path(path)) or "another process") if exc.errno in _BUSY else None
    finally:
        os.close(fd)  # closing the descriptor releases a lock taken
    return None


def acquire_lock(path: str | os.PathLike, *, what: str, remove: bool = False) -> FileLock | None:
    """Take the exclusive lock ``path`` now or fail.

    Parameters
    ----------
    path : str or path-like
        The lock file (created when absent; its folder must exist).
    what : str
        Who holds it (``"rsmb survey"``), for another taker's message; the
        file holds the holder's pid.
    remove : bool
        Delete the file on release.

    Returns
    -------
    FileLock, or None where the platform has no ``flock`` (Windows).

    Raises
    ------
    LockBusy
        Another process holds it.
    LockError
        Anything else: the message says what (permission, read-only file
        system, no locks on this file system ...).
    """
    try:
        import fcntl
    except ImportError:  # no flock: the documented one-writer rule stands alone
        return None
    path = Path(path)
    for _ in range(100):  # a removed lock file is retaken at once; 100 is only a bound
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise LockError(f"{path}: cannot create the lock file ({exc.strerror or one_line(exc)})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in _BUSY:
                holder = _holder(path)
                raise LockBusy(f"{path}: in use by another {what}" + (f" ({holder})" if holder else "")) from None
            name = errno.errorcode.get(exc.errno, str(exc.errno))
            hint = "; this file system has no locks" if exc.errno in _NO_LOCKS else ""
            raise LockError(f"{path}: cannot lock ({exc.strerror or one_line(exc)}, {name}{hint})") from None
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if not same:  # the holder before us removed it as we opened it: take the new one
            os.close(fd)
            continue
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()}\n".encode())
        except OSError:
            pass  # the lock holds without its note
        return FileLock(path, fd, remove)
    raise LockError(f"{path}: cannot lock (the lock file keeps being replaced)")
