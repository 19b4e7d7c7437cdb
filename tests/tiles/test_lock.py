"""Exclusive locks on outputs: contention is "in use", anything else says what it is."""

import errno
import fcntl
import os

import pytest

from rsmb.ops import InputError
from rsmb.tiles import LockBusy, LockError, acquire_lock


def test_one_holder_then_the_next(tmp_path):
    path = tmp_path / "x.lock"
    held = acquire_lock(path, what="rsmb test")
    with pytest.raises(LockBusy, match=rf"x\.lock: in use by another rsmb test \(pid {os.getpid()}\)"):
        acquire_lock(path, what="rsmb test")
    held.release()
    held.release()  # idempotent
    with acquire_lock(path, what="rsmb test"):
        assert path.exists()
    assert path.exists()  # kept unless asked to remove it


def test_removed_on_release_when_asked(tmp_path):
    path = tmp_path / "store.zarr.lock"
    with acquire_lock(path, what="rsmb detect", remove=True):
        assert path.read_text() == f"pid {os.getpid()}\n"
    assert not path.exists()


@pytest.mark.parametrize("code, words", [(errno.ENOLCK, "No locks available"),
                                         (errno.EOPNOTSUPP, "not supported"),
                                         (errno.EACCES, "Permission denied")])
def test_failures_that_are_not_contention_say_what_they_are(tmp_path, monkeypatch, code, words):
    def flock(fd, op):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(fcntl, "flock", flock)
    with pytest.raises(LockError, match=words) as info:
        acquire_lock(tmp_path / "x.lock", what="rsmb test")
    assert "in use" not in str(info.value) and isinstance(info.value, InputError)


def test_a_folder_that_cannot_be_written(tmp_path, monkeypatch):
    real_open = os.open

    def read_only(path, flags, *args):
        if str(path).endswith(".lock"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(os, "open", read_only)
    with pytest.raises(LockError, match="cannot create the lock file .*Read-only file system"):
        acquire_lock(tmp_path / "x.lock", what="rsmb test")


def test_lock_holder_reads_without_taking_or_writing(tmp_path):
    """Who holds a lock, told without creating, writing or keeping it."""
    from rsmb.tiles import acquire_lock, lock_holder

    path = tmp_path / "x.lock"
    assert lock_holder(path) is None and not path.exists()
    lock = acquire_lock(path, what="rsmb survey")
    before = path.read_bytes(), path.stat().st_mtime_ns
    assert lock_holder(path) == f"pid {os.getpid()}"
    assert (path.read_bytes(), path.stat().st_mtime_ns) == before
    lock.release()
    assert lock_holder(path) is None
    acquire_lock(path, what="rsmb survey").release()  # free to take again
