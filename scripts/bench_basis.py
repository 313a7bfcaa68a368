#!/usr/bin/env python3
"""Benchmark of the enrichment columns of the reduced basis against "the limit" (issue 16).

What it measures: for the paper's Table 1 beam (L = 1 m, E = 117 GPa, I = 8.78e-16 m^4,
A = 2.9e-7 m^2, rho = 11800 kg/m^3, pinned-pinned) meshed with 5000 elements (10^4 free DOFs),
with N_L = 1, 10, 100 constraints spread evenly inside the beam (x_j = j L / (N_L + 1)) and 6
reference modes, the wall time of
    limit         one MUMPS Cholesky of K plus N_L solves K psi = g_j (the factor's MatSolve on one
                  reused unit load: no KSP layer): the least any enrichment with one column per
                  constraint from a factored operator can cost
    limit, block  the same factorization and all N_L right-hand sides in one MatMatSolve (MUMPS solves
                  a block at a fraction of the cost of as many single solves)
    limit, PETSc  the same with PETSc's own Cholesky in the natural ordering (no fill on a band: the
                  shared DBF path's solver on one rank)
    static        the static attachment modes (enrichment.static_modes: the limit plus the
                  backward-error checks and the gathered matrix)
    DBF ritz      DbfEnrichment(solver="ritz").columns: the same factorization, Rayleigh-Ritz on
                  the reference modes plus a few Krylov vectors on g per constraint (dbf_ritz.py)
    DBF shared    DbfEnrichment(solver="shared").columns: one factorization of K - sigma M per
                  group, ~30 solves per constraint (dbf_shared.py)
    DBF factor    DbfEnrichment(solver="factor").columns: three factorizations per constraint
                  (dbf.py), the paper-faithful comparator
all measured in the same process, after a warm-up on a small beam; each the fastest of --repeat.
"peak" is the largest resident set (VmHWM, reset before each measurement through
/proc/self/clear_refs) of any rank while the limit (block) or the ritz path ran: what the process
held then, the structure and its modes included. The single-solve MUMPS limit is timed only up to
--single-max constraints (on the solid a single solve takes ~0.3 s).
With --structure solid the structure is the 3-D hexahedral bar of scripts/solid3d.py (104 040 DOFs,
20 reference modes; its matrices are generated into --solid when missing) with N_L stops on the z
DOFs of its top face, spread evenly; the factored path runs there only up to --factor-max.
The reference modes are computed once per N_L and are not part of any of these times.
The ratios are to "limit" (MUMPS) and "limit, PETSc" (the ritz and shared paths' solver on one
rank: like with like). "solves per DBF" counts every solve with the shared factor, the ritz path's
N per group (Phi^T M A^-1 M Phi) and any fallback's included.

The 5000-element beam is far beyond what double precision resolves for this beam (~580 elements,
modes.trust_check), so the check is switched off (-modes_trust_tol 1): the times are what they are,
the DBFs themselves are rounding-dominated at this size.

How to run (from the repository root; the script starts its own worker, on 1 rank by default):
    . .venv/bin/activate && python scripts/bench_basis.py              # full run, ~1-2 minutes
    . .venv/bin/activate && python scripts/bench_basis.py --quick      # smoke run, seconds
    . .venv/bin/activate && python scripts/bench_basis.py --ranks 1,2  # also 2 ranks (groups = 2)
    . .venv/bin/activate && python scripts/bench_basis.py -o bench.md  # also write the table
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

BEAM = dict(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, left="pinned", right="pinned")


def limit(ops, rows, solver_type: str, block: bool = False) -> float:
    """Seconds for one Cholesky of K (solver_type) and one solve per constraint row; block: all the
    rows' right-hand sides in one MatMatSolve. Collective."""
    from petsc4py import PETSc
    from dbf_hpc.petsctools import destroy, direct_solver, natural_fill_is_small

    t0 = time.perf_counter()
    ksp = direct_solver(PETSc.KSP().create(comm=ops.comm), PETSc.PC.Type.CHOLESKY)
    ksp.getPC().setFactorSolverType(solver_type)
    if solver_type == "petsc":   # the faster ordering: no fill on a band, nested dissection otherwise
        ksp.getPC().setFactorOrdering("natural" if natural_fill_is_small(ops.K) else "nd")
    ksp.setOperators(ops.K)
    if block:
        ksp.setUp()
        lo, hi = ops.K.getOwnershipRange()
        N = ops.K.getSize()[0]
        B = PETSc.Mat().createDense(((hi - lo, N), (PETSc.DECIDE, len(rows))), comm=ops.comm)
        X = PETSc.Mat().createDense(((hi - lo, N), (PETSc.DECIDE, len(rows))), comm=ops.comm)
        B.setUp()
        X.setUp()
        a = B.getDenseArray()
        a[:] = 0.0
        for j, row in enumerate(rows):
            if lo <= row < hi:
                a[row - lo, j] = 1.0
        B.assemble()
        X.assemble()
        ksp.getPC().getFactorMatrix().matSolve(B, X)
        destroy(B, X)
    else:   # the factor's own MatSolve on one reused unit load: no KSP layer, no allocation per row
        ksp.setUp()
        factor = ksp.getPC().getFactorMatrix()
        psi, g = ops.K.createVecRight(), ops.K.createVecLeft()
        for row in rows:
            g.setValue(int(row), 1.0)
            g.assemble()
            factor.solve(g, psi)
            g.setValue(int(row), 0.0)
            g.assemble()
        destroy(psi, g)
    elapsed = time.perf_counter() - t0
    destroy(ksp)
    return elapsed


def measured(comm, repeat: int, seconds) -> float:
    """The fastest of `repeat` calls of seconds() (each returns its own elapsed time on this rank),
    each started after a barrier, as the slowest rank saw it: the DBF paths are timed so (`timed`),
    and the limit was rank 0's own clock, without the barrier. Collective."""
    from mpi4py import MPI

    best = float("inf")
    for _ in range(repeat):
        comm.barrier()
        best = min(best, comm.tompi4py().allreduce(seconds(), op=MPI.MAX))
    return best


def reset_peak() -> None:
    """Start a new peak resident set for this process (Linux >= 4.0; elsewhere the peak since start)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def peak_mb() -> float:
    """This process's peak resident set since the last reset_peak, in MB (VmHWM; 0 if unknown)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def worker(args) -> None:
    """Run the measurements on this process's COMM_WORLD; one JSON line per N_L on rank 0."""
    import numpy as np
    from mpi4py import MPI
    from petsc4py import PETSc
    PETSc.Options().setValue("modes_trust_tol", "1")
    from dbf_hpc import dbf_ritz, dbf_shared
    from dbf_hpc.enrichment import DbfEnrichment, static_modes
    from dbf_hpc.modes import reference_modes
    from dbf_hpc.petsctools import natural_fill_is_small
    from dbf_hpc.structure import Beam, assemble_beam

    comm = PETSc.COMM_WORLD

    def timed(fn) -> float:
        def once() -> float:
            t0 = time.perf_counter()
            out = fn()
            elapsed = time.perf_counter() - t0
            out.destroy()
            return elapsed
        return measured(comm, args.repeat, once)

    def peak(fn):
        """(fn(), the largest peak resident set of any rank while it ran, MB)."""
        reset_peak()
        out = fn()
        return out, comm.tompi4py().allreduce(peak_mb(), op=MPI.MAX)

    def structure(elements: int, n_l: int, solid: bool):
        """(ops, constraint rows, reference modes) of the beam or the solid."""
        if solid:
            from dbf_hpc.matrices import MatrixFiles, load_operators
            files = MatrixFiles(os.path.join(args.solid, "K.bin"), os.path.join(args.solid, "M.bin"))
            ops = load_operators(files, comm)
            surface = np.array(solid_surface(args.solid))
            rows = surface[np.linspace(0, surface.size - 1, n_l).round().astype(int)]
            if np.unique(rows).size != n_l:
                raise SystemExit(f"bench_basis: the solid's top face has {surface.size} z DOFs, fewer than {n_l}")
            return ops, rows.astype(np.int64), reference_modes(ops, count=20)
        beam = Beam(elements=elements, **BEAM)
        positions = [beam.length * (j + 1) / (n_l + 1) for j in range(n_l)]
        ops = assemble_beam(beam, comm, points=positions)
        rows = np.array([ops.mesh.w_row(x) for x in positions], dtype=np.int64)
        return ops, rows, reference_modes(ops, count=6)

    def limit_timed(*a, **kw) -> float:
        """The limit measured as `timed` measures the DBF paths: the fastest of --repeat, each
        started together on every rank and counted until the slowest rank is done."""
        return measured(comm, args.repeat, lambda: limit(*a, **kw))

    def run(elements: int, n_l: int, paths, solid: bool = False) -> dict:
        ops, rows, modes = structure(elements, n_l, solid)
        limit_block, peak_limit = peak(lambda: limit_timed(ops, rows, "mumps", block=True))
        record = dict(n_l=n_l, dofs=ops.size, ranks=comm.getSize(),
                      limit=limit_timed(ops, rows, "mumps") if n_l <= args.single_max else None,
                      limit_block=limit_block, peak_limit=peak_limit,
                      # PETSc's own Cholesky only where the package uses it (a banded matrix on one rank;
                      # on the 3-D solid it did not finish in minutes)
                      limit_petsc=limit_timed(ops, rows, "petsc")
                      if comm.getSize() == 1 and natural_fill_is_small(ops.K) else None,
                      static=timed(lambda: static_modes(ops, rows)))
        for path in paths:
            solves, fallbacks = dbf_shared.counters["solves"], dbf_ritz.counters["fallbacks"]
            record[path], record[f"peak_{path}"] = peak(
                lambda: timed(lambda: DbfEnrichment(solver=path).columns(ops, rows, modes).matrix))
            if path in ("shared", "ritz"):   # solves per DBF, the ritz path's per-group ones included
                record[f"solves_{path}"] = (dbf_shared.counters["solves"] - solves) / (args.repeat * max(n_l, 1))
            if path == "ritz":
                record["fallbacks"] = (dbf_ritz.counters["fallbacks"] - fallbacks) / args.repeat
        modes.destroy()
        ops.destroy()
        return record

    run(100, 4, ("ritz", "shared", "factor"))      # warm-up: imports, first calls of MUMPS and SLEPc
    for n_l in (int(n) for n in args.constraints.split(",")):
        paths = ("ritz",) + tuple(p for p, top in (("shared", args.shared_max), ("factor", args.factor_max))
                                  if n_l <= top)
        PETSc.Sys.Print(json.dumps(run(args.elements, n_l, paths, args.structure == "solid")), comm=comm)


def solid_surface(folder: str) -> list:
    """The top face's z DOFs of the generated solid (scripts/solid3d.py), from its dofs.json."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import solid3d
    nx, ny, nz = json.load(open(os.path.join(folder, "dofs.json")))["elements"]
    return solid3d.top_surface_z_dofs(nx, ny, nz)


def launch(args, ranks: int) -> list[dict]:
    """Start this script as a worker on `ranks` ranks and collect its JSON lines."""
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--elements", str(args.elements),
           "--constraints", args.constraints, "--repeat", str(args.repeat), "--factor-max", str(args.factor_max),
           "--shared-max", str(args.shared_max), "--single-max", str(args.single_max), "--structure", args.structure,
           "--solid", args.solid]
    if ranks > 1:  # -m mpi4py: an exception on one rank aborts both instead of hanging the other
        cmd = ["mpirun", "-n", str(ranks), sys.executable, "-m", "mpi4py"] + cmd[1:]
    print(f"running: {' '.join(cmd)}", file=sys.stderr, flush=True)
    out = subprocess.run(cmd, env=dict(os.environ), stdout=subprocess.PIPE, text=True, check=True).stdout
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def table(records: list[dict]) -> str:
    """Markdown table: times and their ratios to the limit."""
    def s(x):
        return "-" if x is None else f"{x:.3f}"

    def ratio(a, b):
        return "-" if a is None or b is None else f"{a / b:.1f}"

    lines = ["| N_L | DOFs | ranks | limit (s) | limit, block (s) | limit, PETSc (s) | static (s) | DBF ritz (s) "
             "| DBF shared (s) | DBF factor (s) | solves per DBF: ritz, shared | ritz fallbacks | ritz / limit "
             "| ritz / limit block | ritz / limit PETSc | shared / limit | shared / limit PETSc | factor / limit "
             "| peak per rank (MB): limit block, ritz |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in sorted(records, key=lambda r: (r["n_l"], r["ranks"])):
        f, shared = r.get("factor"), r.get("shared")
        solves_shared = "-" if shared is None else f"{r['solves_shared']:.0f}"
        lines.append(f"| {r['n_l']} | {r['dofs']} | {r['ranks']} | {s(r.get('limit'))} | {s(r.get('limit_block'))} "
                     f"| {s(r['limit_petsc'])} "
                     f"| {s(r['static'])} | {s(r['ritz'])} | {s(shared)} | {s(f)} "
                     f"| {r['solves_ritz']:.1f}, {solves_shared} | {r['fallbacks']:.0f} "
                     f"| {ratio(r['ritz'], r.get('limit'))} | {ratio(r['ritz'], r.get('limit_block'))} "
                     f"| {ratio(r['ritz'], r['limit_petsc'])} "
                     f"| {ratio(shared, r.get('limit'))} | {ratio(shared, r['limit_petsc'])} "
                     f"| {ratio(f, r.get('limit'))} | {r['peak_limit']:.0f}, {r['peak_ritz']:.0f} |")
    return "\n".join(lines)


def check_options(parser, args) -> None:
    """Refuse, in one line, what the workers would have met as a traceback (or measured as
    something else: --ranks 0 ran on one rank)."""
    def counts(text: str, name: str, least: int) -> None:
        try:
            values = [int(v) for v in text.split(",")]
        except ValueError:
            values = []
        if not values or min(values) < least:
            parser.error(f"{name} {text!r}: give comma-separated whole numbers >= {least}")
    counts(args.ranks, "--ranks", 1)
    counts(args.constraints, "--constraints", 1)
    for name in ("elements", "repeat"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} {getattr(args, name)}: give a whole number >= 1")
    for name in ("factor_max", "shared_max", "single_max"):
        if getattr(args, name) < 0:
            parser.error(f"--{name.replace('_', '-')} {getattr(args, name)}: give a whole number >= 0")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--elements", type=int, default=None,
                        help="beam elements (free DOFs ~ 2 x elements; default 5000, --quick 200)")
    parser.add_argument("--constraints", default=None, help="comma-separated N_L (default 1,10,100,1000)")
    parser.add_argument("--ranks", default="1", help="comma-separated rank counts (default 1)")
    parser.add_argument("--repeat", type=int, default=1, help="measurements per configuration; the fastest is kept")
    parser.add_argument("--factor-max", type=int, default=100,
                        help="time the factored DBF path only up to this N_L (it costs ~0.4 s per constraint)")
    parser.add_argument("--shared-max", type=int, default=100, help="time the shared DBF path only up to this N_L")
    parser.add_argument("--single-max", type=int, default=100,
                        help="time the single-solve MUMPS limit only up to this N_L (the block limit always)")
    parser.add_argument("--structure", choices=("beam", "solid"), default="beam",
                        help="the Table 1 beam (default) or the 3-D hexahedral bar of scripts/solid3d.py")
    parser.add_argument("--solid", default="/tmp/dbf_hpc_solid3d", help="the solid's matrices (generated if missing)")
    parser.add_argument("--quick", action="store_true", help="small sizes for a smoke run")
    parser.add_argument("-o", "--output", help="also write the markdown table to this file")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.elements is None:   # (`or` made --elements 0 the default size, silently)
        args.elements = 200 if args.quick else 5000
    if args.constraints is None:
        args.constraints = "1,10" if args.quick else "1,10,100,1000"
    if not args.worker:
        check_options(parser, args)
    if args.worker:
        worker(args)
        return
    if any(v in os.environ for v in ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK")):
        sys.exit("bench_basis.py starts its own MPI workers: run it without mpirun")
    if args.structure == "solid" and not os.path.exists(os.path.join(args.solid, "dofs.json")):
        subprocess.run([sys.executable, os.path.join(os.path.dirname(os.path.abspath(__file__)), "solid3d.py"),
                        args.solid], check=True)
    start = time.perf_counter()
    records = [r for ranks in args.ranks.split(",") for r in launch(args, int(ranks))]
    text = table(records)
    print(text)
    print(f"wall time of the benchmark: {time.perf_counter() - start:.1f} s", file=sys.stderr)
    if args.output:
        with open(args.output, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
