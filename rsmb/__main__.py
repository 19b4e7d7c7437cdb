"""``python -m rsmb`` and the ``rsmb`` command: the command line
(:func:`rsmb.pipeline.cli.main`) in a process of its own."""

import atexit
import os
import sys


def command():
    """Run the command line; returns its exit code.

    The process then ends once every exit handler has run (the libraries'
    own, the log's), the standard streams flushed, without the interpreter's
    teardown (freeing every module and object one by one, which a process
    that is about to end does not need).  Only for a process that exists to
    run the command: a program that calls :func:`rsmb.pipeline.cli.main` ends
    as it always does.
    """
    status = [1]  # what Python itself exits with after an uncaught exception
    atexit.register(_end, status)  # registered before any library's: runs after all of them
    from rsmb.pipeline.cli import main

    status[0] = main()
    return status[0]


def _end(status):
    """The last exit handler: the standard streams flushed, then the process
    ends with ``status[0]``."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):  # no stream, a closed one, a reader gone
            pass
    os._exit(status[0])


if __name__ == "__main__":
    sys.exit(command())
