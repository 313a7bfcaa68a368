#!/usr/bin/env python3
"""The speed/accuracy trade of the reduced model, measured against the full-order reference.

    mpirun -n 2 python scripts/study_accuracy.py [-o DIR] [--grid default|control|tiny] [--truths E:DT,E:DT]
                                                 [--keep]
    python scripts/study_accuracy.py --report [-o DIR]      (rebuild the tables and plot from the CSVs)

1. Truth. For each scene (the paper's beam with 1, 4 and 9 constraints; the control grid adds the
   steam-generator tube, TUBE) the full-order model
   (dbf-hpc run --method full: one factorization, contact condensed on the constraint DOFs) runs at
   two resolutions, the second with half the element size and half the step, each on one rank (a
   beam's banded solve is fastest there), the truths dealt to the ranks. The trusted horizon T_h is where the two agree: the first time their
   constraint displacements differ by more than HORIZON_TOL of the peak ends it. The finer one is
   the truth, compared only on [0, T_h]: the impacting beam is chaotic (docs/design.md).
   The full-order peers (the grid's coarser meshes and steps of the same reference) run the same
   way; their errors and costs are what a user who does not reduce gets (peers.csv).
2. Bases. Every distinct basis of the grid is built once on all ranks (timed, from scratch).
3. Cases. The reduced model over the grid (modes N, basis kind, tolerance, ARKIMEX type, contact
   implicit/explicit, scene), each case on one rank (COMM_SELF), the cases dealt to the ranks,
   each integrated over the truth's span (its errors are taken over [0, T_h]). Every basis kind has N + N_L columns: "modes" is N + N_L modes alone,
   "static" N modes + one static attachment mode per constraint, "dbf" N modes + one DBF each at
   k auto (or k auto x 0.01, x 100: one k for all constraints, the geometric mean of theirs).
4. Errors against the truth, all from the HDF5 outputs over [0, T_h] (the same layout for both):
      w        max over constraints and samples of |w - w_truth|, over max |w_truth| at any
               constraint: the estimate's own measure (accuracy.relative_difference); w_each is
               the former per-constraint one (each constraint over its own peak)
      force    |peak |N| - truth's| / truth's (peaks over each sample interval, all constraints)
      rms      |RMS of w at mid-span - truth's| / truth's
      impacts  |count - truth's| / truth's: contact episodes at the sample resolution (a run of
               samples with a nonzero peak force counts once, so the full model's micro-chatter
               within one sample is one episode)
   Cost: the integration's wall time and steps on one rank, over the same span as the truth's
   (also on one rank); the basis's build time is reported separately (one build serves every case and
   every run of a parameter study). Truths already in DIR/runs are reused: delete them to rerun.
   The estimate: every case carries its a-posteriori estimate (the output's estimated_error) made
   over the truth's trusted horizon (basis.estimate_window = T_h), so that estimate and true error
   are the same measure over the same window; its cost (the richer basis and run) is a column of
   its own, not in the case's wall time. Where the truths' horizon is short (9 constraints: 0.105 s,
   just the first impact) the estimate is judged over that window only.
   The tolerance mode: each scene with [basis] tolerance = each of the grid's tolerances (modes from
   4, the scene's enrichment, calibrated over T_h; no full-order run), against the truth: what it
   picked, its estimate, its true error, its integration and its calibration apart, and the
   cheapest case of the grid whose true error meets the same tolerance.
5. Output in DIR (default study/): truth.csv (the references and their agreement), accuracy.csv
   (a row per case), accuracy.md (the cheapest cases within 1 % and 0.1 % error in w per scene,
   and the Pareto front; the estimate against the truth and the tolerance mode, each with the
   issue's targets as summary lines), pareto.png (w error against wall time, the cheapest 1 % and
   0.1 % settings marked), estimate.png (the estimate against the true error, log-log, the factor-2
   band drawn) and tolerance.csv (a row per tolerance-mode run).
"""
from __future__ import annotations

import argparse
import csv
import itertools
import json
import math
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

# The steam-generator tube as the study runs it: jobs/steam_generator_tube.toml with its 2 % modal
# damping replaced by Rayleigh damping (the full-order truth has no modal damping; 2 % at 3 Hz and
# 50 Hz: alpha = 2 zeta w1 w2 / (w1 + w2), beta = 2 zeta / (w1 + w2)) and its max_frequency_hz
# removed (the grid and the tolerance mode set the number of modes).
TUBE = "tube"
TUBE_JOB = "jobs/steam_generator_tube.toml"
TUBE_EDITS = [("max_frequency_hz = 100.0", "# max_frequency_hz: set by the study"),
              ("zeta = 0.02", "rayleigh_alpha = 0.7113   # 1/s\nrayleigh_beta = 1.2012e-4   # s")]
HORIZON_TOL = 1e-3   # the truths' disagreement that ends the trusted horizon, of max |w|
SAMPLE_DT = 1e-4     # s: every output is sampled alike
MIDSPAN = 0.5

GRIDS = {
    # Paper's beam with 1, 4 and 9 constraints, 0.2 s: the first impacts (the first near 0.105 s).
    "default": {
        "scenes": {"1": "jobs/paper_beam.toml", "4": "jobs/paper_beam_4.toml", "9": "jobs/paper_beam_9.toml"},
        "t_end": 0.2,
        "truths": [(200, 5e-6), (400, 2.5e-6)],     # (elements, step)
        # The full-order peers: what a user would run instead of a reduced model, coarser meshes and
        # steps of the same fast reference, measured against the truth like the reduced cases.
        "peers": [(50, 4e-5), (50, 2e-5), (100, 4e-5), (100, 2e-5), (100, 1e-5), (200, 1e-5)],
        "modes": [4, 10, 20, 40, 80],
        "kinds": ["dbf", "dbf k x 0.01", "dbf k x 100", "static", "modes"],
        "rtol": [1e-4, 1e-6, 1e-8],
        "scheme": ["3", "4"],
        "contact": ["implicit", "explicit"],
    },
    # The accuracy control (docs/accuracy.md, "Error estimate and tolerance mode"): every case's
    # estimate against its true error, and the tolerance mode, on the paper's beam and the
    # steam-generator tube (TUBE), at a size that runs in about 15 minutes on two ranks.
    "control": {
        "scenes": {"1": "jobs/paper_beam.toml", "4": "jobs/paper_beam_4.toml", "9": "jobs/paper_beam_9.toml",
                   "tube": TUBE},
        "t_end": 0.2,
        "truths": [(200, 5e-6), (400, 2.5e-6)],
        "peers": [(50, 4e-5), (100, 2e-5), (100, 1e-5)],
        "modes": [4, 10, 20, 40],
        "kinds": ["dbf", "modes"],
        "rtol": [1e-4, 1e-6],
        "scheme": ["3"],
        "contact": ["implicit"],
        "tolerances": [0.05, 0.02, 0.01],
    },
    # Seconds, for the test: one constraint, coarse truths.
    "tiny": {
        "scenes": {"1": "jobs/paper_beam.toml"},
        "t_end": 0.115,
        "truths": [(50, 2e-5), (100, 1e-5)],
        "peers": [(50, 4e-5)],
        "modes": [4],
        "kinds": ["dbf", "static", "modes"],
        "rtol": [1e-6],
        "scheme": ["3"],
        "contact": ["implicit"],
        "tolerances": [0.1],
    },
}
# What differs for a scene (its label): the tube (a 10 m span, 12 support plates, forced at 3 Hz) is
# simulated over 0.3 s, which holds its first impacts (near 0.037 s) and many more; its truths are
# coarser in time and space (its modes up to the impacts' frequencies need fewer elements per
# metre), and they agree to 0.1 % of max |w| over all of it (measured: the trusted horizon is t_end).
OVERRIDES = {"tube": {"t_end": 0.3, "truths": [(400, 1e-5), (800, 5e-6)], "peers": [(200, 2e-5), (400, 2e-5)]}}


def log(message: str) -> None:
    from mpi4py import MPI
    if MPI.COMM_WORLD.rank == 0:
        print(message, flush=True)


def read_output(path: str, horizon: float) -> dict:
    """What the errors need from one run's HDF5 output, over [0, horizon]; with the run's estimate
    (NaN without one) and the effective scene (what the tolerance mode picked)."""
    import h5py
    import numpy as np

    with h5py.File(path, "r") as f:
        t = f["time"][:]
        keep = t <= horizon * (1 + 1e-9)
        return {"t": t[keep], "w": f["constraints/displacement"][:][keep],
                "force": np.abs(f["constraints/force_peak"][:][keep]),
                "mid": f["probes/displacement"][:, 0][keep],
                "stats": json.loads(f.attrs["solver_stats"]), "wall": json.loads(f.attrs["wall_times"]),
                "estimate": float(f.attrs.get("estimated_error", math.nan)),
                "estimate_window": float(f.attrs.get("estimated_error_window", math.nan)),
                "effective": json.loads(f.attrs.get("scene_effective", "{}"))}


def episodes(force) -> int:
    """Contact episodes at the sample resolution, over all constraints."""
    touching = force > 0
    starts = touching[1:] & ~touching[:-1]
    return int(starts.sum() + touching[0].sum())


def errors(run: dict, truth: dict) -> dict:
    """err_w is the estimate's own measure (accuracy.relative_difference); err_w_each the former
    per-constraint one (each constraint over its own peak), for comparison."""
    import numpy as np

    from dbf_hpc.accuracy import relative_difference_each

    n = min(run["t"].size, truth["t"].size)
    if n < truth["t"].size or not np.allclose(run["t"][:n], truth["t"][:n], atol=1e-9):
        raise ValueError("the run and the truth are not sampled alike")
    w_scale = np.abs(truth["w"]).max()
    rel = lambda a, b: abs(a - b) / b if b else (0.0 if a == b else math.inf)  # noqa: E731
    rms = lambda x: float(np.sqrt(np.mean(x * x)))  # noqa: E731
    return {"err_w": float(np.abs(run["w"][:n] - truth["w"][:n]).max() / w_scale),
            "err_w_each": relative_difference_each(run["w"][:n], truth["w"][:n]),
            "err_force": rel(float(run["force"].max()), float(truth["force"].max())),
            "err_rms": rel(rms(run["mid"][:n]), rms(truth["mid"][:n])),
            "err_impacts": rel(episodes(run["force"]), episodes(truth["force"]))}


def horizon_of(a: dict, b: dict, tol: float) -> float:
    """The last sample time up to which the two truths agree within tol of max |w|."""
    import numpy as np

    gap = np.abs(a["w"] - b["w"]).max(axis=1) / np.abs(b["w"]).max() if a["w"].shape[1] else np.zeros(a["t"].size)
    beyond = np.flatnonzero(gap > tol)
    return float(b["t"][-1] if beyond.size == 0 else b["t"][max(beyond[0] - 1, 0)])


def basis_sets(kind: str, modes: int, n_constraints: int, k_auto: float) -> list:
    if kind == "modes":
        return [f"basis.modes={modes + n_constraints}", "basis.enrichment=none"]
    if kind == "static":
        return [f"basis.modes={modes}", "basis.enrichment=static"]
    factor = 1.0 if kind == "dbf" else float(kind.split(" x ")[1])
    stiffness = '"auto"' if factor == 1.0 else repr(k_auto * factor)
    return [f"basis.modes={modes}", "basis.enrichment=dbf", f"basis.dbf_stiffness={stiffness}"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", default="study", help="output directory (default study/)")
    parser.add_argument("--grid", choices=sorted(GRIDS), default="default",
                        help="default: the paper's beam with 1, 4 and 9 stops (docs/accuracy-study); control: "
                             "the estimate and the tolerance mode, the tube too (docs/accuracy-control); tiny: a "
                             "smoke run")
    parser.add_argument("--keep", action="store_true", help="keep every case's HDF5 output")
    parser.add_argument("--truths", metavar="E:DT,E:DT",
                        help="the two truth resolutions as elements:step, coarse then fine (default: the grid's, "
                             "200:5e-6,400:2.5e-6); a finer pair resolves smaller errors at 4x the cost per halving")
    parser.add_argument("--report", action="store_true",
                        help="only rebuild accuracy.md and pareto.png from the CSV files in the output directory")
    args = parser.parse_args(argv)
    if args.report:
        report(os.path.abspath(args.output))
        return 0

    from dbf_hpc import _petsc
    _petsc.init([])
    import numpy as np
    from mpi4py import MPI
    from petsc4py import PETSc

    from dbf_hpc.errors import DbfError, InputError, decided_on_rank0
    from dbf_hpc.reductor import Reductor
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    world = MPI.COMM_WORLD
    grid = dict(GRIDS[args.grid])
    if args.truths:
        try:
            grid["truths"] = [(int(e), float(dt)) for e, dt in (pair.split(":") for pair in args.truths.split(","))]
        except ValueError:
            grid["truths"] = []
        (e1, dt1), (e2, dt2) = grid["truths"] if len(grid["truths"]) == 2 else ((0, 0.0), (0, 0.0))
        # (each rank's run of a truth the scene refused ended in a traceback beside the other's barrier)
        if min(e1, e2) < 1 or not min(dt1, dt2) > 0 or e2 < e1 or dt2 > dt1 or (e1, dt1) == (e2, dt2):
            parser.error(f"--truths {args.truths!r}: give two elements:step pairs, elements >= 1 and steps > 0, the "
                         f"second finer (more elements or a smaller step, neither coarser), e.g. "
                         f"400:2.5e-6,800:1.25e-6")
    out = os.path.abspath(args.output)
    try:   # rank 0 writes; its failure is every rank's (red team: -o FILE was rank 0's traceback, a hang)
        decided_on_rank0(world, _prepare_folder, out, args.output, TUBE in grid["scenes"].values())
    except InputError as e:
        if world.rank == 0:
            print(f"{parser.prog}: error: {e}", file=sys.stderr, flush=True)
        return 1
    cache = os.path.join(out, "basis-cache")
    common = [f"output.sample_dt={SAMPLE_DT}", f"output.probes=[{MIDSPAN}]", "output.snapshots=0",
              f"basis.cache={json.dumps(cache)}"]

    def of(label, key):
        """The grid's value, or the scene's own (OVERRIDES)."""
        return OVERRIDES.get(label, {}).get(key, grid[key]) if key != "truths" or not args.truths else grid[key]

    def scene_path(label):
        path = grid["scenes"][label]
        return os.path.join(out, "steam_generator_tube_rayleigh.toml") if path == TUBE else os.path.join(ROOT, path)

    # 1. The truths, each on one rank, dealt to the ranks (the finest first).
    def truth_name(label, elements, dt):
        return os.path.join(out, "runs", f"truth-{label}-{elements}-{dt:g}-{of(label, 't_end'):g}.h5")

    jobs = sorted(((label, elements, dt) for label in grid["scenes"]
                   for elements, dt in of(label, "truths") + of(label, "peers")), key=lambda job: (-job[1], job[2]))
    failed = None
    for label, elements, dt in jobs[world.rank::world.size]:
        name = truth_name(label, elements, dt)
        if not os.path.exists(name):  # a truth already there is reused: delete it to rerun
            try:
                scene = load_scene(scene_path(label),
                                   common + [f"structure.elements={elements}", f"integrator.dt={dt}",
                                             f"integrator.t_end={of(label, 't_end')}", "basis.estimate=false"])
                run(scene, name, progress=False, method="full", comm=PETSc.COMM_SELF)
            except DbfError as e:   # every rank stops, not the one alone beside the others' barrier
                failed = f"the full-order run of {label} ({elements} elements, step {dt:g} s): {str(e).splitlines()[0]}"
                break
    failed = next((f for f in world.allgather(failed) if f), None)
    if failed:
        if world.rank == 0:
            print(f"{parser.prog}: error: {failed}", file=sys.stderr, flush=True)
        return 1
    truths, truth_rows = {}, []
    for label in grid["scenes"]:
        outputs = []
        for elements, dt in of(label, "truths"):
            name = truth_name(label, elements, dt)
            result = read_output(name, of(label, "t_end"))
            outputs.append((name, elements, dt, result["wall"]["integration"], result["stats"]["steps"]))
            log(f"truth {label} constraint(s), {elements} elements, step {dt:g} s: "
                f"{result['wall']['integration']:.1f} s")
        coarse, fine = (read_output(o[0], of(label, "t_end")) for o in outputs)
        horizon = horizon_of(coarse, fine, HORIZON_TOL)
        truth = read_output(outputs[-1][0], horizon)
        coarse_h = read_output(outputs[0][0], horizon)
        agreement = errors(coarse_h, truth)
        truths[label] = {"data": truth, "horizon": horizon, "wall": outputs[-1][3], "steps": outputs[-1][4],
                         "elements": outputs[-1][1], "dt": outputs[-1][2], "path": scene_path(label)}
        truth_rows.append({"constraints": label, "elements": outputs[-1][1], "dt": outputs[-1][2],
                           "coarse_elements": outputs[0][1], "coarse_dt": outputs[0][2], "horizon": horizon,
                           "wall_time": outputs[-1][3], "steps": outputs[-1][4],
                           **{f"truths_{k}": v for k, v in agreement.items()}})
        log(f"  trusted horizon {horizon:.4g} s (the two truths within {HORIZON_TOL:g} of max |w|); "
            f"there they differ by {agreement['err_w']:.2g} in w, {agreement['err_force']:.2g} in peak force")

    # 2. Every distinct basis once, on all ranks, timed from scratch.
    basis_time, k_auto, count = {}, {}, {}
    for label, info in truths.items():
        scene = load_scene(info["path"], common)
        with scene.full_order_model(PETSc.COMM_WORLD) as fom:
            count[label] = n_constraints = fom.constraints.count
            for kind, modes in itertools.product(grid["kinds"], grid["modes"]):
                if kind.startswith("dbf k x") and label not in k_auto:
                    with Reductor(fom, scene.basis_settings(), cache) as probe:
                        k_auto[label] = float(np.exp(np.mean(np.log(probe.basis().dbf_k_auto))))
                sets = basis_sets(kind, modes, n_constraints, k_auto.get(label, 0.0))
                t = time.perf_counter()
                with Reductor(fom, load_scene(info["path"], common + sets).basis_settings(), cache) as reductor:
                    reductor.basis()
                basis_time[label, kind, modes] = world.allreduce(time.perf_counter() - t, op=MPI.MAX)
    peer_rows = []
    for label, info in truths.items():
        for elements, dt in of(label, "peers"):
            result = read_output(truth_name(label, elements, dt), info["horizon"])
            peer_rows.append({"constraints": label, "elements": elements, "dt": dt,
                              "wall_time": result["wall"]["integration"], "steps": result["stats"]["steps"],
                              **errors(result, info["data"])})
    log(f"bases ready: {len(basis_time)}")

    # 3. The cases, each on one rank; the costliest first, dealt in turn. Each carries its estimate
    # over the truth's trusted horizon (estimate_window), so that the estimate and the true error
    # are the same measure over the same window. The tolerance mode's runs of one scene go to one
    # rank, the loosest tolerance first (its candidates' bases are cached for the tighter ones).
    cases = [dict(zip(("constraints", "kind", "modes", "rtol", "scheme", "contact"), c))
             for c in itertools.product(grid["scenes"], grid["kinds"], grid["modes"], grid["rtol"],
                                        grid["scheme"], grid["contact"])]
    cases.sort(key=lambda c: (-count[c["constraints"]], -c["modes"], c["rtol"]))
    tolerance_jobs = [[{"constraints": label, "tolerance": tol} for tol in sorted(grid["tolerances"], reverse=True)]
                      for label in grid["scenes"]]
    work = [("case", i) for i in range(len(cases))]
    mine = [("tolerance", i) for i in range(world.rank, len(tolerance_jobs), world.size)]
    mine += work[world.rank::world.size]
    rows_out, tolerance_out = [], []
    log(f"{len(cases)} cases and {sum(map(len, tolerance_jobs))} tolerance-mode runs on {world.size} rank(s)")
    start = last = time.perf_counter()
    for done, (what, index) in enumerate(mine):
        if world.rank == 0 and time.perf_counter() - last > 30:
            last = time.perf_counter()
            print(f"  rank 0: {done} of its {len(mine)} jobs done, ETA "
                  f"{(last - start) / done * (len(mine) - done):.0f} s", flush=True)
        if what == "tolerance":
            for job in tolerance_jobs[index]:
                tolerance_out.append(tolerance_run(job, truths[job["constraints"]], of(job["constraints"], "t_end"),
                                                   common, out, args.keep))
            continue
        case = cases[index]
        info = truths[case["constraints"]]
        sets = common + basis_sets(case["kind"], case["modes"], count[case["constraints"]],
                                   k_auto.get(case["constraints"], 0.0)) + [
            f"integrator.t_end={of(case['constraints'], 't_end')}", f"integrator.rtol={case['rtol']}",
            f"integrator.atol={case['rtol'] * 1e-3}", f"integrator.scheme={json.dumps(case['scheme'])}",
            f"integrator.contact={case['contact']}", f"basis.estimate_window={info['horizon']}"]
        name = os.path.join(out, "runs", f"case-{index:04d}.h5")
        row = {**case, "basis_size": case["modes"] + count[case["constraints"]],
               "basis_time": basis_time[case["constraints"], case["kind"], case["modes"]]}
        try:
            run(load_scene(info["path"], sets), name, progress=False, comm=PETSc.COMM_SELF)
            result = read_output(name, info["horizon"])
            err = errors(result, info["data"])
            row.update(status="ok", wall_time=result["stats"]["time_integration"], steps=result["stats"]["steps"],
                       **err, **estimate_of({**result, **err}))
        except DbfError as e:
            row.update(status=f"failed: {e}", wall_time=math.nan, steps=0, err_w=math.nan, err_w_each=math.nan,
                       err_force=math.nan, err_rms=math.nan, err_impacts=math.nan, estimate=math.nan,
                       estimate_ratio=math.nan, estimate_time=math.nan)
        if not args.keep and os.path.exists(name):
            os.remove(name)
        rows_out.append((index, row))
    gathered = world.gather(rows_out, root=0)
    gathered_tol = world.gather(tolerance_out, root=0)
    if world.rank == 0:
        table = [row for _, row in sorted(itertools.chain.from_iterable(gathered), key=lambda x: x[0])]
        order = {(label, tol): i for i, (label, tol) in
                 enumerate(itertools.product(grid["scenes"], sorted(grid["tolerances"], reverse=True)))}
        tol_table = sorted(itertools.chain.from_iterable(gathered_tol),
                           key=lambda r: order[r["constraints"], r["tolerance"]])
        write_results(out, table, truth_rows, peer_rows, tol_table)
    world.Barrier()
    return 0


def estimate_of(result: dict) -> dict:
    """The run's estimate (root attribute estimated_error), its ratio to the true error in the same
    measure, and its cost (the richer basis and its integration), apart from the run's own."""
    true = result.get("err_w", math.nan)
    wall = result["wall"]
    return {"estimate": result["estimate"], "estimate_window": result["estimate_window"],
            "estimate_time": wall.get("estimate_basis", 0.0) + wall.get("estimate", 0.0),
            **({"estimate_ratio": result["estimate"] / true if true > 0 else math.nan} if "err_w" in result else {})}


def tolerance_run(job: dict, info: dict, t_end: float, common: list, out: str, keep: bool) -> dict:
    """One run of the tolerance mode ([basis] tolerance, the scene's own enrichment, modes from 4)
    on this rank, calibrated over the truth's trusted horizon; what it picked, its estimate, its
    true error and its costs."""
    from petsc4py import PETSc

    from dbf_hpc.errors import DbfError
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    label, tol = job["constraints"], job["tolerance"]
    name = os.path.join(out, "runs", f"tolerance-{label}-{tol:g}.h5")
    sets = common + [f"integrator.t_end={t_end}", f"basis.tolerance={tol}", "basis.modes=4",
                     f"basis.estimate_window={info['horizon']}"]
    row = dict(job)
    try:
        run(load_scene(info["path"], sets), name, progress=False, comm=PETSc.COMM_SELF)
        result = read_output(name, info["horizon"])
        err = errors(result, info["data"])
        wall = result["wall"]
        row.update(status="ok", modes=result["effective"]["basis"]["modes"],
                   rtol=result["effective"]["integrator"]["rtol"], wall_time=result["stats"]["time_integration"],
                   steps=result["stats"]["steps"], calibration_time=wall.get("tolerance", 0.0),
                   basis_time=wall.get("basis", 0.0), err_w=err["err_w"], err_w_each=err["err_w_each"],
                   **estimate_of({**result, "err_w": err["err_w"]}))
    except DbfError as e:
        row.update(status=f"failed: {e}", modes=0, rtol=math.nan, wall_time=math.nan, steps=0,
                   calibration_time=math.nan, basis_time=math.nan, err_w=math.nan, err_w_each=math.nan,
                   estimate=math.nan, estimate_window=math.nan, estimate_time=math.nan, estimate_ratio=math.nan)
    if not keep and os.path.exists(name):
        os.remove(name)
    return row


FIELDS = ["constraints", "kind", "modes", "basis_size", "rtol", "scheme", "contact", "status", "wall_time", "steps",
          "basis_time", "err_w", "err_w_each", "err_force", "err_rms", "err_impacts", "estimate", "estimate_window",
          "estimate_ratio", "estimate_time", "version"]
TOLERANCE_FIELDS = ["constraints", "tolerance", "status", "modes", "rtol", "wall_time", "steps", "calibration_time",
                    "basis_time", "err_w", "err_w_each", "estimate", "estimate_window", "estimate_ratio",
                    "estimate_time", "version"]


def write_results(out: str, table: list, truth_rows: list, peer_rows: list, tol_table: list) -> None:
    from dbf_hpc import __version__

    for row in table + tol_table:   # the report says which estimator measured them
        row.setdefault("version", __version__)
    for name, rows, fields in (("accuracy.csv", table, FIELDS), ("truth.csv", truth_rows, list(truth_rows[0])),
                               ("peers.csv", peer_rows, list(peer_rows[0])),
                               ("tolerance.csv", tol_table, TOLERANCE_FIELDS)):
        with open(os.path.join(out, name), "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields)
            writer.writeheader()
            writer.writerows(rows)
    report(out)


def _read_csv(path: str) -> list:
    rows = []
    with open(path) as f:
        for row in csv.DictReader(f):
            rows.append({k: _number(v) if k not in ("constraints", "kind", "scheme", "contact", "status", "version") and v != ""
                         else v for k, v in row.items()})
    return rows


def _number(text: str):
    value = float(text)
    return int(value) if value.is_integer() and "." not in text and "e" not in text.lower() else value


def report(out: str) -> None:
    """accuracy.md and pareto.png from accuracy.csv and truth.csv."""
    table, truth_rows = _read_csv(os.path.join(out, "accuracy.csv")), _read_csv(os.path.join(out, "truth.csv"))
    peer_path = os.path.join(out, "peers.csv")
    peers = _read_csv(peer_path) if os.path.exists(peer_path) else []
    truths = {t["constraints"]: t for t in truth_rows}

    def best_peer(label, target):
        """The cheapest full-order peer within the target, or None."""
        within = [p for p in peers if p["constraints"] == label and p["err_w"] <= target]
        return min(within, key=lambda p: p["wall_time"]) if within else None
    tightest, middle = min(r["rtol"] for r in table), sorted({r["rtol"] for r in table})[len({r["rtol"] for r in table}) // 2]

    def setting(r):
        return (f"{r['kind']}, N = {r['modes']} (size {r['basis_size']}), ARKIMEX {r['scheme']}, rtol {r['rtol']:g}, "
                f"contact {r['contact']}")

    def twin(r, rtol):
        """The same setting at another tolerance, or None."""
        match = [x for x in table if x["rtol"] == rtol and x["status"] == "ok" and
                 all(x[k] == r[k] for k in ("constraints", "kind", "modes", "scheme", "contact"))]
        return match[0] if match else None

    def same_at(r, rtol):
        match = twin(r, rtol)
        return f"{match['err_w']:.2%}" if match else "-"

    versions = sorted({r.get("version") or "" for r in table})
    measured = (f"Measured with dbf_hpc {', '.join(versions)}." if all(versions) else
                "Measured by a dbf_hpc that did not record its version (before 0.2.3): its error estimate and "
                "tolerance mode may differ from today's (docs/accuracy.md).")
    lines = ["# Accuracy and cost of the reduced model against the full-order truth", "", measured, "",
             "Truths (full-order, generalized-alpha with one factorization and the contact condensed on the "
             "constraint DOFs, each on one rank):", "",
             "| constraints | truth mesh, step | checked against | trusted horizon | truths differ in w | "
             "in peak force | truth wall time | steps |", "|---|---|---|---|---|---|---|---|"]
    for t in truth_rows:
        lines.append(f"| {t['constraints']} | {t['elements']} el., {t['dt']:g} s | {t['coarse_elements']} el., "
                     f"{t['coarse_dt']:g} s | {t['horizon']:.4g} s | {t['truths_err_w']:.2%} | "
                     f"{t['truths_err_force']:.1%} | {t['wall_time']:.1f} s | {t['steps']} |")
    if peers:
        lines += ["", "Full-order peers (the same reference on coarser meshes and steps, one rank, over the truth's "
                  "span): what a user who does not reduce would run.", "",
                  "| constraints | mesh, step | error in w | peak force | wall time | steps |", "|---|---|---|---|---|---|"]
        for p in peers:
            lines.append(f"| {p['constraints']} | {p['elements']} el., {p['dt']:g} s | {p['err_w']:.2%} | "
                         f"{p['err_force']:.0%} | {p['wall_time']:.3f} s | {p['steps']} |")
    lines += ["", "Cheapest reduced settings (wall time of the integration on one rank over the truth's span; the "
              "basis is built once). The last column is the same setting at the tightest tolerance: where it is "
              "larger, the cheap case's error was partly cancelled by its own time-stepping error, and a "
              "second row gives the cheapest setting whose error holds at the tightest tolerance too.",
              "", "| constraints | target | setting | error in w | peak force | RMS mid-span | impacts | "
              "wall time | steps | basis build | speed-up vs truth | with the basis build | "
              "vs the cheapest full-order peer within the target | "
              f"same at rtol {tightest:g} |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, truth in truths.items():
        ok = [r for r in table if r["constraints"] == label and r["status"] == "ok"]
        for target in (1e-2, 1e-3):
            within = [r for r in ok if r["err_w"] <= target]
            if not within:
                lines.append(f"| {label} | {target:.1%} | none of the grid reaches it "
                             f"(best {min(r['err_w'] for r in ok):.2%}) | | | | | | | | | | | |" if ok else
                             f"| {label} | {target:.1%} | no case ran | | | | | | | | | | | |")
                continue
            cheapest = min(within, key=lambda r: r["wall_time"])
            # The cheapest whose error holds when its time steps are converged (its twin at the
            # tightest tolerance is within the target too): no luck from cancelling errors.
            holding = [r for r in within if (twin(r, tightest) or {"err_w": math.inf})["err_w"] <= target]
            picks = [cheapest] + ([min(holding, key=lambda r: r["wall_time"])] if holding else [])
            for r in (picks if len(picks) == 1 or picks[0] is not picks[1] else picks[:1]):
                lines.append(f"| {label} | {target:.1%} | {setting(r)} | {r['err_w']:.2%} | {r['err_force']:.0%} | "
                             f"{r['err_rms']:.2%} | {r['err_impacts']:.0%} | {r['wall_time']:.3f} s | {r['steps']} | "
                             f"{r['basis_time']:.2f} s | {truth['wall_time'] / r['wall_time']:.0f}x | "
                             f"{truth['wall_time'] / (r['wall_time'] + r['basis_time']):.0f}x | "
                             f"{peer_ratio(best_peer(label, target), r)} | {same_at(r, tightest)} |")
    kinds = list(dict.fromkeys(r["kind"] for r in table))
    lines += ["", f"Basis kinds at the same size (N + N_L columns), ARKIMEX 3, rtol {middle:g}, implicit contact: "
              "error in w / error in peak force:", "",
              "| constraints | N | " + " | ".join(kinds) + " |", "|---|---|" + "---|" * len(kinds)]
    for label in truths:
        for n in sorted({r["modes"] for r in table}):
            cells = []
            for kind in kinds:
                match = [r for r in table if r["constraints"] == label and r["modes"] == n and r["kind"] == kind
                         and r["scheme"] == "3" and r["rtol"] == middle and r["contact"] == "implicit"
                         and r["status"] == "ok"]
                cells.append(f"{match[0]['err_w']:.2%} / {match[0]['err_force']:.0%}" if match else "-")
            lines.append(f"| {label} | {n} | " + " | ".join(cells) + " |")
    lines += ["", "Pareto front (no other case is both cheaper and more accurate in w):", "",
              "| constraints | setting | error in w | wall time |", "|---|---|---|---|"]
    for label in truths:
        for r in pareto([r for r in table if r["constraints"] == label and r["status"] == "ok"]):
            lines.append(f"| {label} | {setting(r)} | {r['err_w']:.2%} | {r['wall_time']:.3f} s |")
    failed = [r for r in table if r["status"] != "ok"]
    lines += ["", f"{len(table)} cases, {len(failed)} failed."]
    tol_path = os.path.join(out, "tolerance.csv")
    tol_table = _read_csv(tol_path) if os.path.exists(tol_path) else []
    if "estimate" in table[0]:
        lines += [""] + estimate_lines(table, truths)
    if tol_table:
        lines += [""] + tolerance_lines(tol_table, table)
    with open(os.path.join(out, "accuracy.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    plot(out, table, truths)
    if "estimate" in table[0]:
        plot_estimate(out, table, tol_table)
    print(f"wrote {out}/accuracy.md and pareto.png ({len(table)} cases, {len(failed)} failed)", flush=True)


def _fraction(hits: int, total: int) -> str:
    return f"{hits / total:.0%} ({hits} of {total})" if total else "- (no case)"


def estimate_summary(rows: list) -> tuple:
    """(within 2x, optimistic by more than 2x where true > 1 %): the issue's two targets for the estimate."""
    ok = [r for r in rows if r["status"] == "ok" and r["err_w"] > 0 and math.isfinite(r["estimate"])]
    within = sum(0.5 <= r["estimate"] / r["err_w"] <= 2 for r in ok)
    optimistic = [r for r in ok if r["err_w"] > 0.01 and r["estimate"] < 0.5 * r["err_w"]]
    return (f"estimate within 2x of the true error in {_fraction(within, len(ok))} of the cases (target: 90 %); "
            f"optimistic by more than 2x where the true error exceeds 1 %: {len(optimistic)} case(s) (target: 0)")


def estimate_lines(table: list, truths: dict) -> list:
    """The estimate (root attribute estimated_error, over the trusted horizon) against the true error."""
    lines = ["## The a-posteriori estimate against the truth", "",
             "Every case's estimate (`estimated_error`, the richer basis of max(2N, N + N_L) modes, and 1.5 times those where "
             "that differs by 2 % or more, at a 10 times tighter rtol, over the truth's trusted horizon: `estimate_window`) next to its true error in the same measure "
             "(error in w: the largest |w - w_truth| at any constraint over the largest |w_truth| at any "
             "constraint). \"each\" is the former per-constraint measure (each constraint over its own peak), for "
             "comparison. The estimate's cost (its richer basis and integration) is apart from the run's.", "",
             "**" + estimate_summary(table) + "**", ""]
    for label in truths:
        rows = [r for r in table if r["constraints"] == label]
        lines.append(f"- {label}: {estimate_summary(rows)}")
    lines += ["", "| constraints | setting | true error in w | each | estimate | ratio | wall time | estimate cost |",
              "|---|---|---|---|---|---|---|---|"]
    for r in table:
        if r["status"] != "ok":
            continue
        lines.append(f"| {r['constraints']} | {r['kind']}, N = {r['modes']}, rtol {r['rtol']:g} | {r['err_w']:.2%} | "
                     f"{r['err_w_each']:.2%} | {r['estimate']:.2%} | {r['estimate'] / r['err_w']:.2f} | "
                     f"{r['wall_time']:.3f} s | {r['estimate_time']:.3f} s |")
    return lines


def cheapest_within(table: list, label: str, tol: float):
    within = [r for r in table if r["constraints"] == label and r["status"] == "ok" and r["err_w"] <= tol]
    return min(within, key=lambda r: r["wall_time"]) if within else None


def tolerance_summary(tol_table: list, table: list) -> tuple:
    ran = [r for r in tol_table]
    met = [r for r in ran if r["status"] == "ok" and r["err_w"] <= r["tolerance"]]
    paired = [(r, cheapest_within(table, r["constraints"], r["tolerance"])) for r in met]
    paired = [(r, c) for r, c in paired if c is not None]
    cheap = sum(r["wall_time"] <= 2 * c["wall_time"] for r, c in paired)
    cheap_all = sum(r["wall_time"] + r["calibration_time"] + r["basis_time"] <= 2 * (c["wall_time"] + c["basis_time"])
                    for r, c in paired)
    return (f"the tolerance mode met its tolerance in {_fraction(len(met), len(ran))} of the runs (target: 90 %); "
            f"its integration cost was within 2x of the cheapest grid setting that meets the same tolerance in "
            f"{_fraction(cheap, len(paired))} of those met (target: all; {cheap_all} of {len(paired)} counting "
            f"the calibration and the basis on both sides)")


def tolerance_lines(tol_table: list, table: list) -> list:
    lines = ["## The tolerance mode", "",
             "`[basis] tolerance` (modes from 4, the scene's enrichment, calibrated over the trusted horizon; no "
             "full-order run) against the truth, and the cheapest setting of the grid above whose true error meets "
             "the same tolerance. Costs: the run's integration, the calibration (every candidate's basis, run and "
             "richer run) apart.", "", "**" + tolerance_summary(tol_table, table) + "**", "",
             "| constraints | tolerance | picked | estimate | true error in w | met | integration | calibration | "
             "cheapest grid setting within it | its error | its integration | cost ratio | with calibration |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in tol_table:
        if r["status"] != "ok":
            lines.append(f"| {r['constraints']} | {r['tolerance']:.0%} | {r['status']} | | | no | | | | | | | |")
            continue
        c = cheapest_within(table, r["constraints"], r["tolerance"])
        total = r["wall_time"] + r["calibration_time"] + r["basis_time"]
        grid = (f"{c['kind']}, N = {c['modes']}, rtol {c['rtol']:g} | {c['err_w']:.2%} | {c['wall_time']:.3f} s, "
                f"{c['steps']} steps | {r['wall_time'] / c['wall_time']:.1f}x | "
                f"{total / (c['wall_time'] + c['basis_time']):.1f}x" if c else "none of the grid | | | |")
        lines.append(f"| {r['constraints']} | {r['tolerance']:.0%} | N = {r['modes']}, rtol {r['rtol']:g} | "
                     f"{r['estimate']:.2%} | {r['err_w']:.2%} | {'yes' if r['err_w'] <= r['tolerance'] else 'no'} | "
                     f"{r['wall_time']:.3f} s, {r['steps']} steps | {r['calibration_time']:.2f} s | {grid} |")
    return lines


def plot_estimate(out: str, table: list, tol_table: list) -> None:
    """estimate.png: the estimate against the true error (log-log), the factor-2 band drawn."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 5.5))
    rows = [r for r in table if r["status"] == "ok" and r["err_w"] > 0 and r["estimate"] > 0]
    for label, marker in zip(dict.fromkeys(r["constraints"] for r in table), "osD^v<>"):
        mine = [r for r in rows if r["constraints"] == label]
        ax.scatter([r["err_w"] for r in mine], [r["estimate"] for r in mine], marker=marker, s=20, alpha=0.7,
                   label=f"{label} constraint(s)" if label != TUBE else "steam-generator tube")
    tol_rows = [r for r in tol_table if r["status"] == "ok" and r["err_w"] > 0]
    if tol_rows:
        ax.scatter([r["err_w"] for r in tol_rows], [r["estimate"] for r in tol_rows], marker="*", s=90,
                   facecolors="none", edgecolors="k", label="tolerance mode")
    values = [v for r in rows + tol_rows for v in (r["err_w"], r["estimate"])]
    lo, hi = (min(values) / 2, max(values) * 2) if values else (1e-4, 1)
    x = [lo, hi]
    ax.plot(x, x, "k-", lw=0.8, label="estimate = true")
    ax.fill_between(x, [v / 2 for v in x], [v * 2 for v in x], color="tab:green", alpha=0.15, label="within 2x")
    ax.axvline(0.01, color="tab:red", lw=0.6, ls="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_xlabel("true error in w (against the full-order truth, over the trusted horizon)")
    ax.set_ylabel("estimated_error (same measure and window)")
    ax.set_title(estimate_summary(table).split(";")[0], fontsize=8)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "estimate.png"), dpi=120)
    plt.close(fig)


def peer_ratio(peer, r) -> str:
    """The peer's wall time over the reduced case's (with the basis build in brackets)."""
    if peer is None:
        return "no peer reaches it"
    return (f"{peer['wall_time'] / r['wall_time']:.1f}x ({peer['wall_time'] / (r['wall_time'] + r['basis_time']):.1f}x); "
            f"peer {peer['elements']} el., {peer['dt']:g} s, {peer['wall_time']:.3f} s")


def pareto(rows: list) -> list:
    front, best = [], math.inf
    for r in sorted(rows, key=lambda r: (r["wall_time"], r["err_w"])):
        if r["err_w"] < best:
            front.append(r)
            best = r["err_w"]
    return front


def plot(out: str, table: list, truths: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(truths)
    fig, axes = plt.subplots(1, len(labels), figsize=(5.5 * len(labels), 4.5), squeeze=False)
    markers = {"dbf": "o", "dbf k x 0.01": "v", "dbf k x 100": "^", "static": "s", "modes": "x"}
    for ax, label in zip(axes[0], labels):
        ok = [r for r in table if r["constraints"] == label and r["status"] == "ok"]
        for kind, marker in markers.items():
            rows = [r for r in ok if r["kind"] == kind]
            if rows:
                ax.scatter([r["wall_time"] for r in rows], [max(r["err_w"], 1e-7) for r in rows], marker=marker,
                           label=kind, alpha=0.6, s=18)
        front = pareto(ok)
        if front:
            ax.step([r["wall_time"] for r in front], [max(r["err_w"], 1e-7) for r in front], where="post",
                    color="k", lw=0.8, label="Pareto front")
        for target, color in ((1e-2, "tab:green"), (1e-3, "tab:red")):
            ax.axhline(target, color=color, lw=0.6, ls="--")
            within = [r for r in ok if r["err_w"] <= target]
            if within:
                r = min(within, key=lambda r: r["wall_time"])
                ax.scatter([r["wall_time"]], [max(r["err_w"], 1e-7)], s=160, facecolors="none", edgecolors=color,
                           lw=2, label=f"cheapest within {target:.1%}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time of the reduced integration (s, one rank)")
        ax.set_ylabel("max relative error in w at the constraints")
        ax.set_title(f"{label} constraint(s), errors over {truths[label]['horizon']:.3g} s; "
                     f"truth {truths[label]['wall_time']:.0f} s")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "pareto.png"), dpi=120)
    plt.close(fig)


def _prepare_folder(out: str, given: str, tube: bool) -> None:
    """The study's folder and, for the tube, its Rayleigh-damped scene (rank 0); an InputError when
    they cannot be written there."""
    from dbf_hpc.errors import InputError

    try:
        os.makedirs(os.path.join(out, "runs"), exist_ok=True)
        if tube:
            with open(os.path.join(ROOT, TUBE_JOB)) as f:
                text = f.read()
            for old, new in TUBE_EDITS:
                text = text.replace(old, new)
            with open(os.path.join(out, "steam_generator_tube_rayleigh.toml"), "w") as f:
                f.write(text)
    except OSError as e:
        raise InputError(f"-o {given!r}: cannot write the study there ({e.strerror or e}); give a directory") from None


def main_or_abort(argv=None) -> int:
    """main(), with an exception it did not expect (a bug; an error a case raised on its rank alone)
    ending every rank: printed with its traceback, then MPI_Abort. The other ranks wait in a collective
    call (gather, Barrier) this rank will never make: the job hung until its time limit (red team)."""
    try:
        return main(argv)
    except Exception:
        mpi = sys.modules.get("mpi4py.MPI")
        if mpi is not None and mpi.Is_initialized() and not mpi.Is_finalized() and mpi.COMM_WORLD.size > 1:
            import traceback

            traceback.print_exc()
            sys.stderr.flush()
            mpi.COMM_WORLD.Abort(1)
        raise


if __name__ == "__main__":
    sys.exit(main_or_abort())
