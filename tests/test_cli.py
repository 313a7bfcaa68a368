"""The dbf-hpc command as users run it: under mpirun -n 2, one clear line and a non-zero exit on
bad input, never a traceback. These tests start their own mpirun (serial pass only)."""
import os
import re
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")
pytestmark = pytest.mark.launcher


def dbf_hpc(*args, ranks=2, timeout=120):
    cmd = ["mpirun", "-n", str(ranks), sys.executable, "-m", "dbf_hpc.cli", *args]
    # env: Python's copy of the environment, without the variables this process's own MPI_Init set
    # at C level (with them, a nested mpirun exits 1 silently).
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=dict(os.environ))


def test_help_works_under_mpirun():
    out = dbf_hpc("--help")
    assert out.returncode == 0 and out.stdout.count("usage: dbf-hpc") == 2   # printed by each rank
    assert "modes" in out.stdout and "basis" in out.stdout and "stiffness" in out.stdout


def test_modes_of_the_paper_beam_are_the_euler_bernoulli_frequencies():
    out = dbf_hpc("modes", PAPER, "--set", "basis.modes=4", "-modes_eps_tol", "1e-12")
    assert out.returncode == 0, out.stderr
    rows = re.findall(r"^\s+(\d+)\s+([\d.e+-]+)\s+([\d.e+-]+)$", out.stdout, re.M)
    omega = np.array([float(r[2]) for r in rows])
    n = np.arange(1, 5)
    exact = np.sqrt(117e9 * 8.78e-16 / (11800 * 2.9e-7)) * (n * np.pi) ** 2
    assert len(rows) == 4 and np.allclose(omega, exact, rtol=1e-6)
    assert "on 2 rank(s)" in out.stdout


def test_basis_is_cached_and_reused_without_eigen_solves(tmp_path):
    args = ("basis", PAPER, "--set", f"basis.cache={tmp_path}")
    first, second = dbf_hpc(*args), dbf_hpc(*args)
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    assert "cache stored" in first.stdout and "cache hit" in second.stdout
    assert "0 eigen-solves" in second.stdout
    k = re.search(r"x = 0.25 m\s+([\d.e+-]+)", first.stdout).group(1)
    assert 0.01 < float(k) < 1.0


def test_stiffness_sweep_writes_data_and_figure(tmp_path):
    csv, png = tmp_path / "sweep.csv", tmp_path / "fig2.png"
    out = dbf_hpc("stiffness", PAPER, "--k", "1e-3,1e-1,1e3", "-o", str(csv), "--plot", str(png))
    assert out.returncode == 0, out.stderr
    data = np.loadtxt(csv, delimiter=",")
    assert data.shape == (3, 3) and np.all(np.diff(data[:, 1]) > 0)
    assert png.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("args,message", [
    (("modes", "jobs/missing.toml"), "cannot read scene"),
    (("modes", PAPER, "--set", "basis.mode=3"), "unknown key 'mode' in [basis]"),
    (("modes", PAPER, "--set", "structure.E=-5"), "E must be positive"),
    (("stiffness", PAPER, "--constraint", "3"), "the scene has 1 constraint"),
    (("stiffness", PAPER, "-o", "/nonexistent/dir/sweep.csv"), "does not exist"),
])
def test_bad_input_is_one_line_and_a_non_zero_exit(args, message):
    out = dbf_hpc(*args)
    assert out.returncode != 0
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("dbf-hpc: error:") and message in lines[0], out.stderr
    assert "Traceback" not in out.stderr + out.stdout
