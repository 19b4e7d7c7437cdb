"""The exceptions rsmb raises on purpose, for callers to catch.

Every one derives from :class:`RSMBError`, and each also from the builtin a
caller may already handle::

    from rsmb.errors import InputError, RSMBError

    try:
        rsmb.detect("reference.tif", "capture.tif", "changes.zarr")
    except InputError as exc:   # also a ValueError: a file is unusable
        ...

- :class:`InputError` (``ValueError``): an input file or array is unusable;
- :class:`ParameterError` (``ValueError``): a parameter is out of range;
- :class:`SolverError` (``RuntimeError``): a numerical solver did not reach a solution;
- :class:`RunError` (``RuntimeError``): a run could not go on (every dask worker gone).

They are defined once, in :mod:`rsmb.ops`; this module only names them, so
``rsmb.errors.InputError is rsmb.ops.InputError``.
"""

from rsmb.ops._errors import InputError, ParameterError, RSMBError, RunError, SolverError

__all__ = ["RSMBError", "InputError", "ParameterError", "SolverError", "RunError"]
