"""rsmb: registration and change detection under rolling shutter and motion blur.

The public Python API.  Each function is the one the command of the same name
calls::

    import rsmb
    summary = rsmb.detect("reference.tif", "capture.tif", "changes.zarr")

The subpackages hold the rest: :mod:`rsmb.ops` (numerical kernels),
:mod:`rsmb.tiles` (tile grids, zarr stores, raster I/O) and
:mod:`rsmb.pipeline` (scheduling, the command line, reports).  They are
imported on first use, so ``import rsmb.ops`` stays light.
"""

import atexit
import importlib
import importlib.util
import os
import shutil
import tempfile

__all__ = ["detect", "survey", "synth", "evaluate", "report", "SurveyResult", "DetectConfig", "DetectResult", "Evaluation", "PairPaths",
           "__version__"]

# public name -> (module, attribute)
_API = {
    "detect": ("rsmb.pipeline.detection._detect", "detect"),
    "DetectConfig": ("rsmb.pipeline.detection._detect", "DetectConfig"),
    "DetectResult": ("rsmb.pipeline.detection._detect", "DetectResult"),
    "synth": ("rsmb.pipeline._synth", "synth"),
    "PairPaths": ("rsmb.pipeline._synth", "PairPaths"),
    "evaluate": ("rsmb.pipeline._evaluate", "evaluate"),
    "Evaluation": ("rsmb.pipeline._evaluate", "Evaluation"),
    "report": ("rsmb.pipeline.report._report", "write_report"),
    "survey": ("rsmb.pipeline.archive._survey", "survey"),
    "SurveyResult": ("rsmb.pipeline.archive._survey", "SurveyResult"),
}


def __getattr__(name):
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("rsmb")
        except PackageNotFoundError:  # running from a source tree that is not installed
            return "0+unknown"
    if name in _API:
        module, attribute = _API[name]
        value = getattr(importlib.import_module(module), attribute)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'rsmb' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


def _writable(path):
    """Whether ``path`` can be written, or made in its nearest existing folder."""
    while not os.path.exists(path):
        parent = os.path.dirname(path)
        if parent == path:
            return False
        path = parent
    return os.path.isdir(path) and os.access(path, os.W_OK | os.X_OK)


def _numba_cache(writable=_writable):
    """Where numba keeps rsmb's compiled kernels (they are cached: ``cache=True``).

    numba writes beside the kernels' source or in the user's cache folder; a
    user who may write neither (a read-only install run by an account
    without a writable home) would see every command fail on import.  Such a
    user's kernels are cached in a folder of the temporary directory that
    only they may write (``NUMBA_CACHE_DIR``): ``rsmb-numba-cache-<uid>``, or
    the first of ``...-1`` to ``...-9`` that is theirs alone where another
    user took it, else one of the process's own, removed at its exit.  A
    ``NUMBA_CACHE_DIR`` already set is kept.  Runs before numba is
    imported: numba reads its settings then."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    spec = importlib.util.find_spec("rsmb.ops")
    sources = list(spec.submodule_search_locations or []) if spec is not None else []
    user = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
                        "numba")
    if any(writable(os.path.join(s, "__pycache__")) for s in sources) or writable(user):
        return
    uid = os.getuid() if hasattr(os, "getuid") else None
    base = os.path.join(tempfile.gettempdir(), f"rsmb-numba-cache-{uid if uid is not None else 'user'}")
    for path in [base] + [f"{base}-{k}" for k in range(1, 10)]:
        try:
            os.makedirs(path, mode=0o700, exist_ok=True)
            st = os.lstat(path)
        except OSError:
            continue
        if (uid is None or st.st_uid == uid) and os.path.isdir(path) and not os.path.islink(path) \
                and not st.st_mode & 0o077:
            os.environ["NUMBA_CACHE_DIR"] = path
            return
    path = tempfile.mkdtemp(prefix="rsmb-numba-cache-")  # all ten taken by others: this process's own
    atexit.register(shutil.rmtree, path, True)
    os.environ["NUMBA_CACHE_DIR"] = path


_numba_cache()
