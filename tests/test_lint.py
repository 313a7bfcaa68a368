"""The code a newcomer reads has no unused imports, undefined names or shadowed definitions
(pyflakes over the package, its tests and scripts; scripts/setup installs python3-pyflakes)."""
import importlib.util
import os
import subprocess
import sys

import pytest
from mpi4py import MPI

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one look is enough (serial pass)")
@pytest.mark.skipif(importlib.util.find_spec("pyflakes") is None,
                    reason="pyflakes is not installed (scripts/setup installs it on Debian)")
def test_pyflakes_finds_nothing_in_the_package_tests_and_scripts():
    out = subprocess.run([sys.executable, "-m", "pyflakes", "dbf_hpc", "tests", "scripts"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and not out.stdout.strip(), out.stdout + out.stderr
