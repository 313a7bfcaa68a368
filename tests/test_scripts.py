"""The benchmarks in scripts/ still run against the package (a smoke run each, outside the timed
tables: they are never timed here)."""
import os
import subprocess
import sys

import pytest
from mpi4py import MPI

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="starts its own processes (serial pass)")


def script(name, *args, timeout=600):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_COMM_WORLD", "PMIX_", "PMI_"))}
    env.setdefault("OMPI_MCA_rmaps_base_oversubscribe", "1")
    return subprocess.run([sys.executable, os.path.join(ROOT, "scripts", name), *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, env=env)


def test_the_full_order_benchmark_runs_the_papers_beam_at_one_factorization(tmp_path):
    out = script("bench_full.py", "--ranks", "1", "--cases", "paper", "-o", str(tmp_path / "full.md"))
    assert out.returncode == 0, out.stderr[-2000:]
    row = [line for line in (tmp_path / "full.md").read_text().splitlines() if line.startswith("| paper's beam |")]
    assert len(row) == 1 and row[0].split("|")[9].strip() == "1"       # factorizations


def test_the_basis_benchmark_runs_every_dbf_path(tmp_path):
    out = script("bench_basis.py", "--quick", "-o", str(tmp_path / "basis.md"))
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [line for line in (tmp_path / "basis.md").read_text().splitlines() if line.startswith("| 1")]
    assert rows and all(line.count("|") > 10 for line in rows)
