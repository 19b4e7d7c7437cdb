"""rsmb installs one import package, ``rsmb``, and lives beside distributions
whose top-level names are generic (the Operator Framework's ``ops``)."""

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _pip(*args, cwd):
    return subprocess.run([sys.executable, "-m", "pip", *args], cwd=cwd, capture_output=True, text=True)


@pytest.mark.slow
def test_one_package_beside_ops(tmp_path):
    # build from a copy: setuptools leaves a build/ folder in the tree it builds
    source = tmp_path / "source"
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(".venv", ".git", "build", "*.egg-info", "__pycache__",
                                                              ".pytest_cache", "*.zarr", "rsmb-demo", "bench-out"))
    build = _pip("wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"), str(source), cwd=tmp_path)
    assert build.returncode == 0, build.stderr
    wheel, = (tmp_path / "dist").glob("rsmb-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        top_level, = [n for n in names if n.endswith(".dist-info/top_level.txt")]
        assert zf.read(top_level).decode().split() == ["rsmb"]
    assert {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")} == {"rsmb"}
    assert {"rsmb/ops/__init__.py", "rsmb/tiles/__init__.py", "rsmb/pipeline/__init__.py"} <= set(names)

    target = tmp_path / "site"
    install = _pip("install", "--no-deps", "-q", "--target", str(target), str(wheel), cwd=tmp_path)
    assert install.returncode == 0, install.stderr
    other = _pip("install", "-q", "--target", str(target), "ops", cwd=tmp_path)
    if other.returncode != 0:
        pytest.skip(f"the package registry is out of reach: {other.stderr.strip().splitlines()[-1:]}")
    env = {"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"}
    check = subprocess.run(
        [sys.executable, "-c",
         "import ops, rsmb, rsmb.ops, sys; "
         "assert ops.__file__.startswith(sys.argv[1]) and rsmb.__file__.startswith(sys.argv[1]); "
         "assert hasattr(ops, 'CharmBase') and hasattr(rsmb.ops, 'ParameterError'); "
         "assert callable(rsmb.detect) and callable(rsmb.synth)", str(target)],
        cwd=tmp_path, env=env, capture_output=True, text=True)
    assert check.returncode == 0, check.stderr
    command = subprocess.run([str(target / "bin" / "rsmb"), "synth", str(tmp_path / "pair"), "--size", "64,64",
                              "--changes", "1"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert command.returncode == 0, command.stderr
    assert (tmp_path / "pair" / "distorted.png").is_file()
