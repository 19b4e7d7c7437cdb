"""The one root error class of rsmb and its few subclasses.

Callers catch :class:`RSMBError` for anything raised on purpose by the project,
or the builtin base (``ValueError``, ``OSError``) they already handle.
"""

__all__ = ["RSMBError", "InputError", "ParameterError", "SolverError", "RunError"]


class RSMBError(Exception):
    """Root of every error raised on purpose by rsmb."""


class InputError(RSMBError, ValueError):
    """An input file or array is unusable (unreadable, empty, constant, NaN, wrong size).

    The message names the file (or array) and the problem in one line.
    """


class ParameterError(RSMBError, ValueError):
    """A parameter has a value outside what is allowed; the message names the
    parameter, what was expected and what was given."""


class SolverError(RSMBError, RuntimeError):
    """A numerical solver did not reach an optimal solution (the message gives
    the solver and its status)."""


class RunError(RSMBError, RuntimeError):
    """A run could not go on for a reason outside its inputs (every dask worker
    gone, say); the message says what and for how long."""


def one_line(text: object) -> str:
    """``text`` (an exception, say) with every run of whitespace, newlines
    included, made one space: the form of a cause quoted in a one-line message."""
    return " ".join(str(text).split())
