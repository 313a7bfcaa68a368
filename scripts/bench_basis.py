#!/usr/bin/env python3
"""Benchmark of the reduced-basis build (dbf_hpc.basis.build_basis) on 1 and 2 MPI ranks.

What it measures: for the paper's Table 1 beam (L = 1 m, E = 117 GPa, I = 8.78e-16 m^4,
A = 2.9e-7 m^2, rho = 11800 kg/m^3, pinned-pinned) meshed finely enough for >= 10^4 free DOFs,
with N_L = 1, 10, 100 constraints spread evenly inside the beam (x_j = j L / (N_L + 1)) and 6
reference modes, the wall time of build_basis and of its three stages (basis.stats):
    modes         reference modes (SLEPc shift-and-invert on COMM_WORLD)
    DBFs          one DBF source per constraint (spring-perturbed eigenproblems and derivative
                  solves), the constraints shared among `groups` sub-communicators
    Gram-Schmidt  distributed M-orthonormalization of the DBFs (and the projection of K)
in three configurations: 1 rank; 2 ranks with groups = 1 (both ranks solve every constraint
together); 2 ranks with groups = 2 (each rank solves every other constraint on its own copy of K, M).
Each time is one measurement (after a small warm-up build), or the fastest of --repeat builds.

DBF derivative: the package default, "analytic" (one LU solve per constraint); --derivative central
times the paper's central difference (two more spring-perturbed eigen-solves per constraint).

How to run (from the repository root; the script starts its own workers, 1 rank and mpirun -n 2):
    . .venv/bin/activate && python scripts/bench_basis.py              # full run, a few minutes
    . .venv/bin/activate && python scripts/bench_basis.py --quick      # smoke run, < 30 s
    . .venv/bin/activate && python scripts/bench_basis.py -o bench.md  # also write the table

How to read the speed-ups (of the DBF stage only, the one parallelized over constraints):
    "DBF speed-up vs 1 rank"    t_DBF(1 rank) / t_DBF(this row) at the same N_L; 2 is ideal on 2 ranks.
    "DBF speed-up vs 1 group"   t_DBF(2 ranks, groups=1) / t_DBF(2 ranks, groups=2): what splitting
                                the constraints among groups gains over solving each one on both ranks.
With groups = 1 the speed-up vs 1 rank is the parallel efficiency of MUMPS/SLEPc on one banded
10^4-DOF problem (communication-bound: below 1 here). Groups trade that for independent
constraint solves, one per rank. With N_L = 1 one group is idle: that row only compares solving
the constraint on 1 rank (groups = 2) with solving it on 2 ranks (groups = 1).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

BEAM = dict(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, left="pinned", right="pinned")


def worker(args) -> None:
    """Run the builds on this process's COMM_WORLD; one JSON line per build on rank 0."""
    from petsc4py import PETSc
    from dbf_hpc.basis import BasisSettings, build_basis
    from dbf_hpc.structure import Beam, assemble_beam

    comm = PETSc.COMM_WORLD

    def run(elements: int, n_constraints: int, groups: int) -> dict:
        beam = Beam(elements=elements, **BEAM)
        positions = [beam.length * (j + 1) / (n_constraints + 1) for j in range(n_constraints)]
        ops = assemble_beam(beam, comm, points=positions)
        rows = [ops.mesh.w_row(x) for x in positions]
        comm.barrier()
        t0 = time.perf_counter()
        basis = build_basis(ops, rows, BasisSettings(modes=6, groups=groups, dbf_derivative=args.derivative))
        total = time.perf_counter() - t0
        record = dict(n_l=n_constraints, dofs=ops.size, ranks=comm.getSize(), groups=groups,
                      total=total, **basis.stats)
        basis.destroy()
        ops.destroy()
        return record

    groups = [int(g) for g in args.groups.split(",")]
    for g in groups:                      # warm-up: imports, MUMPS/SLEPc first calls, comm splits
        run(100, 2 * g, g)
    for n_l in (int(n) for n in args.constraints.split(",")):
        for g in groups:
            best = min((run(args.elements, n_l, g) for _ in range(args.repeat)), key=lambda r: r["total"])
            PETSc.Sys.Print(json.dumps(best), comm=comm)


def launch(args, ranks: int, groups: str) -> list[dict]:
    """Start this script as a worker on `ranks` ranks and collect its JSON lines."""
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--elements", str(args.elements),
           "--constraints", args.constraints, "--derivative", args.derivative, "--repeat", str(args.repeat),
           "--groups", groups]
    if ranks > 1:  # -m mpi4py: an exception on one rank aborts both instead of hanging the other
        cmd = ["mpirun", "-n", str(ranks), sys.executable, "-m", "mpi4py"] + cmd[1:]
    print(f"running: {' '.join(cmd)}", file=sys.stderr, flush=True)
    out = subprocess.run(cmd, env=dict(os.environ), stdout=subprocess.PIPE, text=True, check=True).stdout
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def table(records: list[dict]) -> str:
    """Markdown table with the DBF-stage speed-ups."""
    base = {(r["n_l"], r["ranks"], r["groups"]): r["time_dbf"] for r in records}
    lines = ["| N_L | DOFs | ranks | groups | modes (s) | DBFs (s) | Gram-Schmidt (s) | total (s) "
             "| DBF speed-up vs 1 rank | DBF speed-up vs 1 group |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in sorted(records, key=lambda r: (r["n_l"], r["ranks"], r["groups"])):
        vs_serial = base[(r["n_l"], 1, 1)] / r["time_dbf"]
        vs_group = (f"{base[(r['n_l'], r['ranks'], 1)] / r['time_dbf']:.2f}"
                    if r["groups"] > 1 else "-")
        lines.append(f"| {r['n_l']} | {r['dofs']} | {r['ranks']} | {r['groups']} | {r['time_modes']:.3f} "
                     f"| {r['time_dbf']:.3f} | {r['time_orthogonalization']:.3f} | {r['total']:.3f} "
                     f"| {vs_serial:.2f} | {vs_group} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--elements", type=int, default=None,
                        help="beam elements (free DOFs ~ 2 x elements; default 5000, --quick 200)")
    parser.add_argument("--constraints", default=None, help="comma-separated N_L (default 1,10,100)")
    parser.add_argument("--derivative", choices=("central", "analytic"), default="analytic",
                        help="BasisSettings.dbf_derivative (default analytic, as the package)")
    parser.add_argument("--repeat", type=int, default=1, help="builds per configuration; the fastest is kept")
    parser.add_argument("--quick", action="store_true", help="small sizes for a smoke run")
    parser.add_argument("-o", "--output", help="also write the markdown table to this file")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--groups", default="1", help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.elements = args.elements or (200 if args.quick else 5000)
    args.constraints = args.constraints or ("1,10" if args.quick else "1,10,100")
    if args.worker:
        worker(args)
        return
    if any(v in os.environ for v in ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK")):
        sys.exit("bench_basis.py starts its own MPI workers: run it without mpirun")
    start = time.perf_counter()
    records = launch(args, 1, "1") + launch(args, 2, "1,2")
    text = table(records)
    print(text)
    print(f"wall time of the benchmark: {time.perf_counter() - start:.1f} s", file=sys.stderr)
    if args.output:
        with open(args.output, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
