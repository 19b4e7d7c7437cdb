"""The ``rsmb`` command's process (``python -m rsmb``, the console script):
its exit code, its output flushed, every exit handler run, no teardown."""

import os
import subprocess
import sys

import pytest


def _rsmb(*args):
    return subprocess.run([sys.executable, "-m", "rsmb", *map(str, args)], capture_output=True, text=True)


def test_output_and_exit_code_reach_the_caller(tmp_path):
    version = _rsmb("--version")  # stdout is a pipe (block buffered): flushed before the process ends
    assert version.returncode == 0 and "version" in version.stdout
    bad = _rsmb("-q", "detect", tmp_path / "missing.tif", tmp_path / "missing.tif", "-o", tmp_path / "out.zarr")
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1 and "missing.tif" in bad.stderr
    assert not (tmp_path / "out.zarr").exists()


@pytest.mark.parametrize("code", [0, 3])
def test_exit_handlers_registered_during_the_command_run_before_it_ends(tmp_path, code):
    # a library's exit handler (registered while the command runs, as zarr's and logging's are) still runs,
    # and its output is flushed; the process ends with the command's code
    marker = tmp_path / "handler.txt"
    script = (
        "import atexit, sys\n"
        "import rsmb.pipeline.cli as cli\n"
        "from rsmb.__main__ import command\n"
        "def main():\n"
        f"    atexit.register(lambda: open({str(marker)!r}, 'w').write('ran'))\n"
        "    print('command output')\n"
        f"    return {code}\n"
        "cli.main = main\n"
        "sys.exit(command())\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert proc.returncode == code
    assert proc.stdout == "command output\n"
    assert marker.read_text() == "ran"


def test_numba_caches_where_the_user_may_write(tmp_path, monkeypatch):
    """A user who may write neither beside the kernels' source nor in a
    cache folder of their home gets a cache folder of the temporary
    directory that only they may write (the next of a series where that
    folder is not theirs alone); a ``NUMBA_CACHE_DIR`` already set, or a
    writable place, is left to numba."""
    import stat
    import tempfile

    import rsmb

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("NUMBA_CACHE_DIR", "")  # recorded: the variable is as it was after the test
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    rsmb._numba_cache(writable=lambda path: True)
    assert "NUMBA_CACHE_DIR" not in os.environ
    rsmb._numba_cache(writable=lambda path: False)
    own = tmp_path / f"rsmb-numba-cache-{os.getuid()}"
    assert os.environ["NUMBA_CACHE_DIR"] == str(own)
    assert stat.S_IMODE(own.stat().st_mode) == 0o700
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    own.chmod(0o777)  # another user could have put kernels there: the next private name of the series
    rsmb._numba_cache(writable=lambda path: False)
    assert os.environ["NUMBA_CACHE_DIR"] == str(own) + "-1"
    assert stat.S_IMODE(os.stat(str(own) + "-1").st_mode) == 0o700
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    rsmb._numba_cache(writable=lambda path: False)  # the same one the next time: its kernels are kept
    assert os.environ["NUMBA_CACHE_DIR"] == str(own) + "-1"
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/somewhere/chosen")
    rsmb._numba_cache(writable=lambda path: False)
    assert os.environ["NUMBA_CACHE_DIR"] == "/somewhere/chosen"
