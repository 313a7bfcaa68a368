#!/usr/bin/env python3
"""The full-order reference's cost per step against one solve with the same factored matrix,
measured in the same run (fom_integrator.py: one factorization, contact condensed on the N_L
constraint DOFs).

    python scripts/bench_full.py [-o OUT.md] [--ranks 1,2] [--cases paper,beam10k,solid3d] [--solid DIR]

Cases (each run as a real integration: samples, statistics, the contact Newton):
  paper     the paper's beam, 160 elements (320 DOFs), one deadband stop at 0.25 m, the left support
            moving 5 mm at 1 Hz, 2 us steps over 0.2 s (100 000 steps, ~360 impacts), a sample every
            10 steps (what `dbf-hpc run` writes by default)
  paper-mumps  the same with -full_pc_factor_mat_solver_type mumps (MUMPS's Cholesky, distributed),
            over the first 0.02 s only (10 000 steps, before the first impact)
  beam10k   the same beam with 5000 elements (10^4 DOFs) and 10 stops (clearance 2.5 mm), released
            from a 5 mm half sine: contact from the first steps; 10 us steps, 2000 steps
  solid3d   a steel cantilever block of trilinear hexahedra (scripts/solid3d.py, 104 040 DOFs) with
            10 stops on the top edge (clearance 20 um), released from a bent shape (tip 0.1 mm);
            10 us steps, 40 steps. Its matrices are generated into --solid (default
            /tmp/dbf_hpc_solid3d) when missing.
For each case and rank count: the wall time per step of the stepping loop (factorizations
excluded; samples, statistics and contact included), the wall time of one solve with the same
factorization (median of 5 batches, measured after the run), their ratio, the factorizations and
the steps with contact. The machine's load average is printed with the table: timings on a shared
machine vary, the ratios within one run less.

Run from the activated venv; each case runs in its own `mpirun -n R` process.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

PAPER = dict(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0)
CASES = ("paper", "paper-mumps", "beam10k", "solid3d")   # what --cases can name


def _released(fom, shape):
    """Make the model start from the displacement `shape(u)` (a bench device: the scene format starts
    from rest or a mode). shape fills a Vec laid out like K."""
    def initial():
        u = fom.operators.K.createVecRight()
        shape(u)
        return u
    fom.initial_displacement = initial


def build(case: str, solid: str):
    """(model, settings)."""
    import numpy as np

    from dbf_hpc import Beam, BaseMotion, Constraint, FullOrderModel, IntegratorSettings, MatrixFiles, law
    from dbf_hpc.excitation import NoExcitation

    if case == "paper-mumps":  # the same with MUMPS's distributed Cholesky instead of the default
        from petsc4py import PETSc
        PETSc.Options().setValue("full_pc_factor_mat_solver_type", "mumps")
        fom, settings = build("paper", solid)
        return fom, IntegratorSettings(t_end=0.02, dt=2e-6, sample_dt=2e-5)
    if case == "paper":
        beam = Beam(elements=160, **PAPER)
        stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
        fom = FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0), probes=[0.5])
        return fom, IntegratorSettings(t_end=0.2, dt=2e-6, sample_dt=2e-5)
    if case == "beam10k":
        beam = Beam(elements=5000, **PAPER)
        xs = [(j + 0.5) / 10 for j in range(10)]
        stops = [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=x) for x in xs]
        fom = FullOrderModel.build(beam, stops, BaseMotion(amplitude=5e-3, frequency_hz=1.0), probes=[0.5])
        mesh = fom.operators.mesh

        def half_sine(u):
            lo, hi = u.getOwnershipRange()
            values = np.zeros(hi - lo)
            for dof, f in ((0, 5e-3 * np.sin(np.pi * mesh.x)), (1, 5e-3 * np.pi * np.cos(np.pi * mesh.x))):
                rows = mesh.row[:, dof]
                mine = (rows >= lo) & (rows < hi)
                values[rows[mine] - lo] = f[mine]
            u.setArray(values)

        _released(fom, half_sine)
        return fom, IntegratorSettings(t_end=2000 * 1e-5, dt=1e-5, sample_dt=1e-4)
    if case == "solid3d":
        if not os.path.exists(os.path.join(solid, "dofs.json")):
            from mpi4py import MPI
            if MPI.COMM_WORLD.rank == 0:
                subprocess.run([sys.executable, os.path.join(ROOT, "scripts", "solid3d.py"), solid], check=True)
            MPI.COMM_WORLD.Barrier()
        info = json.load(open(os.path.join(solid, "dofs.json")))
        top = info["top_z"]
        nx = len(top)
        picks = [top[round((j + 1) * nx / 10) - 1] for j in range(10)]
        stops = [Constraint(law("deadband", clearance=2e-5, k=1e8), dof=d) for d in picks]
        files = MatrixFiles(stiffness=os.path.join(solid, "K.bin"), mass=os.path.join(solid, "M.bin"))
        fom = FullOrderModel.build(files, stops, NoExcitation(), probes=[info["tip_z"]])
        per_node = 3

        def bent(u):
            # w = 1e-4 (x/L)^2 on every node's z displacement (free DOFs are node-major from x = dx on)
            lo, hi = u.getOwnershipRange()
            rows = np.arange(lo, hi)
            node, comp = rows // per_node, rows % per_node
            i = node % nx + 1
            u.setArray(np.where(comp == 2, 1e-4 * (i / nx) ** 2, 0.0))

        _released(fom, bent)
        return fom, IntegratorSettings(t_end=40 * 1e-5, dt=1e-5, sample_dt=1e-5)
    raise SystemExit(f"unknown case {case!r}")


def solve_batch(step_seconds: float, comm) -> int:
    """Solves per timed batch (~0.2 s of them, 1 to 2000), the same on every rank: each solve is
    collective, and each rank's own loop time (a local clock) gave the ranks different counts, one
    rank left waiting in a solve the others never made. Collective."""
    from mpi4py import MPI

    step = comm.allreduce(step_seconds, op=MPI.MAX)
    return max(1, min(2000, int(0.2 / max(step, 1e-6))))


def worker(case: str, solid: str) -> None:
    import numpy as np
    from mpi4py import MPI

    from dbf_hpc.fom import Observation
    from dbf_hpc.fom_integrator import Alpha2, ConstraintRows, EffectiveSystem, integrate_full, options
    from dbf_hpc.output import MemoryWriter
    from dbf_hpc.recorder import FullRecorder

    world = MPI.COMM_WORLD
    fom, settings = build(case, solid)
    with fom:
        observation = Observation(fom)
        recorder = FullRecorder(MemoryWriter(fom.constraints.shape, fom.probes.shape, 0), fom.constraints,
                                observation)
        started = time.perf_counter()
        stats = integrate_full(fom, settings, observation.rows, recorder.block if world.rank == 0 else None)
        total = time.perf_counter() - started
        # One solve with the same matrix and the same factorization options, timed after the run.
        X = fom.operators.K.createVecRight()
        crow = ConstraintRows(X, fom.constraints.flat_rows)
        S = EffectiveSystem(fom.operators.K, fom.operators.M, fom.damping_matrix(), Alpha2(options()["rho"]),
                            settings.dt, crow, fom.operators.G is None)
        b, x = X.duplicate(), X.duplicate()
        b.setRandom()
        S.solve(b, x)
        batch = solve_batch(stats["step_time"] / stats["steps"], world)
        times = []
        for _ in range(5):
            world.Barrier()
            t0 = time.perf_counter()
            for _ in range(batch):
                S.solve(b, x)
            times.append((time.perf_counter() - t0) / batch)
        one = float(np.median(times))
        S.destroy()
        for v in (X, b, x):
            v.destroy()
    if world.rank == 0:
        step = stats["step_time"] / stats["steps"]
        print(json.dumps({"case": case, "dofs": stats["dofs"], "constraints": int(fom.constraints.count),
                          "ranks": world.size, "steps": stats["steps"], "us_per_step": step * 1e6,
                          "one_solve_us": one * 1e6, "ratio": step / one, "factorizations": stats["factorizations"],
                          "factorization": stats["factorization"], "factorization_s": stats["factorization_time"],
                          "contact_steps": stats["contact_steps"], "impacts": int(recorder.impacts.result()["impacts"].sum()),
                          "total_s": total}), flush=True)


def driver(args) -> int:
    rows = []
    load = open("/proc/loadavg").read().split()[:3] if os.path.exists("/proc/loadavg") else ["?"] * 3
    for case in args.cases.split(","):
        for ranks in (int(r) for r in args.ranks.split(",")):
            cmd = ["mpirun", "-n", str(ranks), sys.executable, "-m", "mpi4py", os.path.abspath(__file__),
                   "--case", case, "--solid", args.solid]
            env = dict(os.environ, OMP_NUM_THREADS="1")
            out = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if out.returncode != 0:
                print(out.stdout, out.stderr, file=sys.stderr)
                return 1
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"{case} on {ranks} rank(s): {row['us_per_step']:.1f} us/step, one solve {row['one_solve_us']:.1f} us, "
                  f"ratio {row['ratio']:.2f} ({row['factorization']})", flush=True)
    load_end = open("/proc/loadavg").read().split()[:3] if os.path.exists("/proc/loadavg") else ["?"] * 3
    lines = ["| model | DOFs | N_L | ranks | steps | us/step | one solve (us) | step / solve | factorizations | "
             "factorization | steps with contact |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    names = {"paper": "paper's beam", "paper-mumps": "paper's beam, MUMPS", "beam10k": "beam",
             "solid3d": "3-D solid (hex8)"}
    for r in rows:
        lines.append(f"| {names[r['case']]} | {r['dofs']} | {r['constraints']} | {r['ranks']} | {r['steps']} | "
                     f"{r['us_per_step']:.1f} | {r['one_solve_us']:.1f} | {r['ratio']:.2f} | {r['factorizations']} | "
                     f"{r['factorization']} | {r['contact_steps']} |")
    lines.append("")
    lines.append(f"Load average (1, 5, 15 min) at the start {' '.join(load)}, at the end {' '.join(load_end)}.")
    text = "\n".join(lines)
    print(text)
    if args.output:
        with open(args.output, "w") as f:
            f.write(text + "\n")
        with open(os.path.splitext(args.output)[0] + ".json", "w") as f:
            json.dump(rows, f, indent=1)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", default="", metavar="OUT.md",
                        help="also write the table (markdown) here, and the rows beside it (OUT.json)")
    parser.add_argument("--ranks", default="1,2", help="comma-separated rank counts (default 1,2)")
    parser.add_argument("--cases", default="paper,beam10k,solid3d",
                        help="comma-separated cases: paper, paper-mumps, beam10k, solid3d (default "
                             "paper,beam10k,solid3d)")
    parser.add_argument("--solid", default="/tmp/dbf_hpc_solid3d",
                        help="the solid's matrices (generated if missing; default /tmp/dbf_hpc_solid3d)")
    parser.add_argument("--case", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.case:
        worker(args.case, args.solid)
        return 0
    try:
        ranks = [int(r) for r in args.ranks.split(",")]
    except ValueError:
        ranks = []
    if not ranks or min(ranks) < 1:   # mpirun -n 0 ran on every slot, the table naming that count
        parser.error(f"--ranks {args.ranks!r}: give comma-separated rank counts >= 1, e.g. 1,2")
    unknown = [c for c in args.cases.split(",") if c not in CASES]
    if unknown:   # else it was found only after the cases before it had run
        parser.error(f"--cases: {', '.join(unknown)}: choose from {','.join(CASES)}")
    return driver(args)


if __name__ == "__main__":
    sys.exit(main())
