"""GDAL's own words in rsmb's errors, and none of its chatter on the terminal.

A failed rasterio read raises ``RasterioIOError("Read failed. See previous
exception for details.")``; what GDAL said (``TIFFFillTile:Read error ...; got N
bytes, expected M`` for a truncated file) hangs below it on the chain
of ``__cause__`` / ``__context__``.  :func:`gdal_cause` finds it, so the one-line
:class:`InputError` names the real cause.

rasterio also logs every GDAL failure at INFO ("GDAL signalled an error") on the
loggers ``rasterio._env`` and ``rasterio._err``, and pyogrio every layer it
writes ("Created N records", ``pyogrio._io``); a program that logs at INFO (the
CLI) printed those lines.  Inside :func:`quiet_gdal` (and so inside
:func:`gdal_errors`) INFO records of those loggers are demoted to DEBUG for the
calling thread only: hidden at INFO, shown with ``-vv``.  Warnings and errors
pass unchanged, and nothing changes for rasterio or pyogrio calls outside rsmb's
own reads and writes.
"""

from __future__ import annotations

import contextlib
import logging
import threading

from rsmb.ops._errors import InputError, one_line

_LOGGERS = ("rasterio._env", "rasterio._err", "pyogrio._io", "pyogrio._err")
_POINTER = "See previous exception"
_scope = threading.local()
_install_lock = threading.Lock()
_installed = False


def gdal_cause(exc: BaseException) -> str:
    """The most specific message on the chain of a rasterio error.

    Walks ``__cause__`` / ``__context__`` through rasterio's and GDAL's
    exceptions (``RasterioIOError``, ``CPLE_*``) and returns the deepest message
    that is not a pointer to another one ("See previous exception"); the
    message of ``exc`` itself when no other is found.
    """
    found = one_line(exc)
    seen = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        text = one_line(current)
        if text and _POINTER not in text:
            found = text
        current = current.__cause__ or current.__context__
        if current is not None and not type(current).__module__.startswith("rasterio"):
            break
    return found


class _DemoteInScope(logging.Filter):
    """INFO records become DEBUG records while the thread is inside quiet_gdal."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not getattr(_scope, "depth", 0) or record.levelno != logging.INFO:
            return True
        if not logging.getLogger(record.name).isEnabledFor(logging.DEBUG):
            return False
        record.levelno, record.levelname = logging.DEBUG, logging.getLevelName(logging.DEBUG)
        return True


def _install_filter() -> None:
    """Add the filter to the GDAL loggers of rasterio and pyogrio, once per
    process (it does nothing outside a quiet_gdal scope)."""
    global _installed
    with _install_lock:
        if _installed:
            return
        for name in _LOGGERS:
            logging.getLogger(name).addFilter(_DemoteInScope())
        _installed = True


@contextlib.contextmanager
def quiet_gdal():
    """Scope of rasterio or pyogrio calls whose INFO lines are demoted to DEBUG
    (this thread only); errors pass unchanged."""
    _install_filter()
    _scope.depth = getattr(_scope, "depth", 0) + 1
    try:
        yield
    finally:
        _scope.depth -= 1


@contextlib.contextmanager
def gdal_errors(path: str, action: str = "cannot read image"):
    """Scope of rasterio calls on ``path``: GDAL's INFO lines demoted to DEBUG
    (:func:`quiet_gdal`), rasterio errors and OSError re-raised as one-line
    :class:`InputError`.

    Raises
    ------
    InputError
        ``"<path>: <action> (<GDAL's message>)"``, chained to the original error.
    """
    from rasterio.errors import RasterioError

    with quiet_gdal():
        try:
            yield
        except (RasterioError, OSError) as exc:
            raise InputError(f"{path}: {action} ({gdal_cause(exc)})") from exc
