"""One run, stage by stage: scene -> operators -> basis -> reduced model -> integration -> output.

Collective on COMM_WORLD. The basis and the field reconstruction are distributed; the reduced
model is small and dense, so rank 0 integrates it while the other ranks wait (without spinning) and
then join the reconstruction of the snapshots.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pickle
import signal
import time

import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from .cache import obtain_basis
from .errors import DbfError, InputError, SolverError
from .full import FullProblem, FullSettings, Observer, initial_displacement, integrate_full
from .integrate import IntegratorSettings, integrate
from .laws import ConstraintLaws
from .model import build_operators, constraint_rows, operators_fingerprint
from .modes import counters
from .operators import values_at
from .output import OutputWriter, check_output_path
from .reduced import Harmonic, RandomProcess, build_reduced_model
from .structure import distributed_load
from .scene import Scene
from .stats import DESCRIPTIONS, UNITS, ImpactAccumulator


def integrator_settings(scene: Scene) -> IntegratorSettings:
    i = scene["integrator"]
    sample_dt = scene["output"]["sample_dt"] or i["t_end"] / 10000
    return IntegratorSettings(t_end=float(i["t_end"]), dt=float(i["dt"]), scheme=i["scheme"],
                              adaptive=i["adaptive"], rtol=float(i["rtol"]), atol=float(i["atol"]),
                              contact=i["contact"], sample_dt=float(sample_dt))


def probe_rows(scene: Scene, ops) -> np.ndarray:
    rows = []
    for p in scene["output"]["probes"]:
        if ops.mesh is not None:
            row = ops.mesh.w_row(p)
            if row < 0:
                raise InputError(f"probe at x = {p:g} m is on a support (a fixed DOF); move it")
        else:
            row = int(p)
            if row >= ops.size:
                raise InputError(f"probe dof {row} is outside the {ops.size} DOFs of the matrices")
        rows.append(row)
    return np.asarray(rows, dtype=np.int64)


def output_path(scene: Scene, override: str | None) -> str:
    path = override or scene["output"]["file"]
    if not path:
        raise InputError("no output file: give [output] file in the scene or -o OUT.h5")
    return check_output_path(path if override else scene.resolve(path))


def _wait_for_rank0(world) -> None:
    """Block until rank 0 arrives, sleeping instead of spinning (the integration may be long)."""
    request = world.Ibarrier()
    while not request.Test():
        time.sleep(0.02)


def excitation(scene: Scene, ops):
    """(support motion Omega(t), force F(t), the force's row or None, its load Vec or None) of the
    scene's excitation. Collective (the distributed load of random forcing)."""
    e = scene["excitation"]
    force_row = force_load = None
    if e["kind"] == "force":
        force_row = ops.mesh.w_row(e["x"]) if ops.mesh is not None else int(e["dof"])
        if force_row < 0 or force_row >= ops.size:
            raise InputError("the force acts on a fixed DOF or outside the structure; move it")
    support = Harmonic(e["amplitude"], e["frequency_hz"]) if e["kind"] == "base" else Harmonic()
    force = Harmonic(e["amplitude"], e["frequency_hz"]) if e["kind"] == "force" else Harmonic()
    if e["kind"] == "random":
        force = RandomProcess(e["psd"], e["band"], e["seed"], e["components"])
        force_load = distributed_load(ops, *e["span"])
    return support, force, force_row, force_load


def run(scene: Scene, out: str | None = None, progress: bool = True, comm=None, initial_state=None,
        resume: bool = False, method: str = "rom") -> dict:
    """Run the scene and write its HDF5 output. Returns a summary (same on every rank), with the
    final reduced state. initial_state = (q, q') starts from a previous run's final state instead of
    [initial] (continuation in a frequency sweep; the basis must be the same). With resume, a run
    that was killed continues from its last checkpoint (OUT.h5.checkpoint) and ends as an
    uninterrupted run would. method = "full" integrates the full-order model instead (full.py):
    the reference the reduced model is measured against, same scene, same output layout."""
    if method not in ("rom", "full"):
        raise InputError(f"--method {method!r}: choose rom or full")
    if method == "full" and (resume or initial_state is not None):
        raise InputError("--method full starts from [initial]: it has no checkpoints to resume from")
    comm = comm or PETSc.COMM_WORLD
    world = comm.tompi4py()
    say = (lambda m: PETSc.Sys.Print(m, comm=comm)) if progress else (lambda m: None)
    path = output_path(scene, out)
    settings = integrator_settings(scene)
    timings = {}
    t = time.perf_counter()

    ops = build_operators(scene, comm)
    rows = constraint_rows(scene, ops)
    probes = probe_rows(scene, ops)
    try:
        support, force, force_row, force_load = excitation(scene, ops)
    except InputError:
        ops.destroy()
        raise
    laws = ConstraintLaws([c.law for c in scene.constraints])
    timings["operators"] = time.perf_counter() - t
    say(f"dbf-hpc: {scene.path}: {ops.size} DOFs, {rows.size} constraint(s), {world.size} rank(s)")
    if method == "full":
        return _run_full(scene, path, ops, rows, probes, laws, (support, force, force_row, force_load),
                         settings, timings, say, progress)

    t, solves = time.perf_counter(), counters["eigen_solves"]
    basis = obtain_basis(ops, rows, scene.basis_settings(), operators_fingerprint(scene, ops),
                         scene.cache_dir(), [c.label for c in scene.constraints])
    timings["basis"] = time.perf_counter() - t
    extra = {"dbf": f"+ {basis.enrichment_count} DBFs", "static": f"+ {basis.enrichment_count} static modes",
             "none": "(no enrichment)"}[basis.enrichment]
    say(f"basis: {basis.mode_count} modes {extra} ({timings['basis']:.2f} s, cache {basis.stats.get('cache')})")
    for warning in basis.warnings([c.label for c in scene.constraints]):
        PETSc.Sys.Print(f"dbf-hpc: warning: {warning}", comm=comm)

    t = time.perf_counter()
    init = scene["initial"]
    model = build_reduced_model(basis, ops, laws, scene.damping(), support, force, force_row, force_load,
                                init["mode"], init["amplitude"])
    if force_load is not None:
        force_load.destroy()
    if initial_state is not None:
        q_start, p_start = (np.asarray(a, dtype=float) for a in initial_state)
        if q_start.shape != (model.size,) or p_start.shape != (model.size,):
            raise InputError(f"the initial state has {q_start.size} coordinates; this basis has {model.size}")
        model.q0, model.p0 = q_start, p_start
    probe_B = basis.rows(probes)
    probe_r = values_at(ops.influence, probes) if support.amplitude else np.zeros(probes.size)
    timings["reduce"] = time.perf_counter() - t

    # Integration on rank 0; the others wait, then learn the outcome.
    snapshot_times, snap_index = _snapshot_samples(scene, settings.sample_times)
    recorder, stats, failure = None, {}, None
    if world.rank == 0:
        t = time.perf_counter()
        try:
            checkpoint_dt = scene["output"]["checkpoint_dt"] or settings.t_end / 10
            recorder = Recorder(path, model, laws, probe_B, probe_r, snap_index, checkpoint_dt,
                                _scene_identity(scene), resume)
            start = recorder.start
            if resume:
                say(f"resuming from the checkpoint at t = {start['t']:.6g} s" if start else
                    "no usable checkpoint: starting from t = 0")
            say(f"integrating to t = {settings.t_end:g} s with ARKIMEX {settings.scheme} "
                f"(contact {settings.contact}, {'adaptive' if settings.adaptive else 'fixed'} step)")
            with _interrupt_on_sigterm(recorder):
                stats = integrate(model, settings, recorder.record, progress=progress,
                                  on_step=recorder.on_step, resume=start)
        except DbfError as exc:
            failure = str(exc)
        except OSError as exc:
            failure = f"cannot write {path}.partial: {exc.strerror or exc}"
        timings["integration"] = time.perf_counter() - t
        if failure and recorder is not None:
            failure += recorder.abort()
    else:
        with _interrupt_on_sigterm(None):
            _wait_for_rank0(world)
    if world.rank == 0:
        _wait_for_rank0(world)
    failure = world.bcast(failure, root=0)
    if failure:
        basis.destroy()
        ops.destroy()
        raise SolverError(failure)

    # Field snapshots: w = V q + r Omega, reconstructed in parallel from the distributed basis.
    t = time.perf_counter()
    snap_q = world.bcast(recorder.snapshot_coordinates() if world.rank == 0 else None, root=0)
    snap_t = settings.sample_times[snap_index] if snapshot_times.size else np.zeros(0)
    x, w = _snapshots(ops, basis, snap_q, snap_t, support, scene["excitation"]["end"])
    timings["snapshots"] = time.perf_counter() - t

    summary = {}
    if world.rank == 0:
        stats.update(eigen_solves=counters["eigen_solves"] - solves, cache=basis.stats.get("cache", ""))
        summary = _finish(scene, recorder, stats, timings, world.size, "rom", snap_t, x, w,
                          {"basis/omega": basis.omega, "basis/dbf_omega": basis.dbf_omega,
                           "basis/dbf_k": basis.dbf_k, "reduced/K": model.K, "reduced/B": model.B,
                           "reduced/D": model.D}, {"basis_enrichment": basis.enrichment})
        summary["final_state"] = [recorder.final[0].tolist(), recorder.final[1].tolist()]
        recorder.remove_checkpoint()
        say(f"done: {stats['steps']} steps ({stats['rejected_steps']} rejected, {stats['snes_failures']} Newton "
            f"failures) in {timings['integration']:.2f} s; wrote {recorder.path}")
    basis.destroy()
    ops.destroy()
    return world.bcast(summary, root=0)


def _snapshot_samples(scene: Scene, sample_times: np.ndarray):
    """The snapshot times asked for and the indices of the samples that carry them."""
    n_snap = scene["output"]["snapshots"]
    t_end = sample_times[-1]
    snapshot_times = np.linspace(0.0, t_end, n_snap) if n_snap else np.zeros(0)
    return snapshot_times, np.unique(np.searchsorted(sample_times, snapshot_times - 1e-12 * t_end))


def _finish(scene: Scene, recorder: "SampleRecorder", stats: dict, timings: dict, ranks: int, method: str,
            snap_t, x, w, extra: dict, extra_attrs: dict | None = None) -> dict:
    """Rank 0: write the fixed-size data and the attributes, rename the file into place, and return
    the run's summary."""
    timings["total"] = sum(timings.values())
    init = scene["initial"]
    positions = np.array([c.x if c.x is not None else c.dof for c in scene.constraints], dtype=float)
    writer = recorder.writer
    constraint_stats = recorder.impacts.result()
    probe_peak = np.abs(writer.series_data("probes/displacement")).max(axis=0, initial=0.0)
    writer.finish(
        datasets={"constraints/position": positions,
                  "constraints/clearance_minus": [c.law.clearance_minus for c in scene.constraints],
                  "constraints/clearance_plus": [c.law.clearance_plus for c in scene.constraints],
                  "probes/position": np.asarray(scene["output"]["probes"], dtype=float),
                  "snapshots/time": snap_t, "snapshots/x": x, "snapshots/w": w, "probes/peak": probe_peak,
                  **{f"constraints/stats/{k}": v for k, v in constraint_stats.items()}, **extra},
        dataset_attrs={f"constraints/stats/{k}": {"unit": UNITS[k], "description": DESCRIPTIONS[k]}
                       for k in constraint_stats},
        attrs={"scene": scene.text, "scene_path": os.path.abspath(scene.path), "method": method,
               "petsc_version": ".".join(map(str, PETSc.Sys.getVersion())),
               "slepc_version": ".".join(map(str, SLEPc.Sys.getVersion())),
               "mpi_ranks": ranks, "solver_stats": json.dumps(stats), "wall_times": json.dumps(timings),
               "initial_state": "at rest in relative coordinates (u = 0, u_t = 0); absolute velocity "
                                "Omega'(0) r" if not init["amplitude"] else
                                f"displacement {init['amplitude']} m peak in reference mode {init['mode']}",
               **(extra_attrs or {})})
    return {"path": recorder.path, "stats": stats, "timings": timings, "probe_peak": probe_peak.tolist(),
            "constraint_stats": {k: v.tolist() for k, v in constraint_stats.items()}}


def _run_full(scene: Scene, path: str, ops, rows, probes, laws: ConstraintLaws, excitation_, settings,
              timings: dict, say, progress: bool) -> dict:
    """The full-order reference (full.py) on ops.comm, every rank integrating its share of the
    state; rank 0 writes the same layout as a reduced run (no basis/ or reduced/ groups)."""
    support, force, force_row, force_load = excitation_
    world = ops.comm.tompi4py()
    n_dofs = ops.size
    problem = observer = u0 = recorder = None
    try:
        problem = FullProblem(ops, rows, laws, scene.damping(), support, force, force_row, force_load)
        init = scene["initial"]
        u0 = initial_displacement(ops, init["mode"], init["amplitude"])
        full_settings = FullSettings(t_end=settings.t_end, dt=settings.dt, rtol=settings.rtol,
                                     atol=settings.atol, sample_dt=settings.sample_dt)
        sample_times = full_settings.sample_times
        snapshot_times, snap_index = _snapshot_samples(scene, sample_times)
        observed = np.concatenate([rows, probes])
        moving = ops.influence is not None and support.amplitude != 0.0
        r_observed = values_at(ops.influence, observed) if moving else np.zeros(observed.size)
        r_field = _on_rank0(ops.influence) if moving and snapshot_times.size else None
        nc = rows.size
        opened = None
        if world.rank == 0:
            try:
                recorder = SampleRecorder(path, laws, probes.size)
            except OSError as exc:
                opened = f"cannot write {path}.partial: {exc.strerror or exc}"
        opened = world.bcast(opened, root=0)  # every rank stops if rank 0 cannot write
        if opened:
            raise SolverError(opened)
        snaps = {}

        def record(t, x, xd):
            total, rate = x + r_observed * support.value(t), xd + r_observed * support.rate(t)
            recorder.sample(t, total[:nc], rate[:nc], total[nc:])

        def on_step(t, x, xd):
            recorder.step(t, x[:nc] + r_observed[:nc] * support.value(t),
                          xd[:nc] + r_observed[:nc] * support.rate(t))

        def snapshot(i, values):
            if values is not None:
                total = values + (r_field * support.value(sample_times[i]) if r_field is not None else 0.0)
                snaps[i] = total

        observer = Observer(problem, observed, sample_times, record, on_step, snap_index, snapshot, progress)
        say(f"integrating the full-order model to t = {settings.t_end:g} s with generalized-alpha (TSALPHA2, "
            f"contact implicit, step {settings.dt:g} s)")
        t = time.perf_counter()
        stats = integrate_full(problem, full_settings, u0, observer)
        timings["integration"] = time.perf_counter() - t
    except (DbfError, OSError) as exc:
        left = ""
        if recorder is not None:
            recorder.writer.abort()
            left = f" (the samples up to the failure are in {recorder.writer.partial})"
        if isinstance(exc, OSError):
            raise SolverError(f"cannot write {path}.partial: {exc.strerror or exc}{left}") from None
        if left:
            raise type(exc)(f"{exc}{left}") from None
        raise
    finally:
        for obj in (problem, observer, u0, force_load):
            if obj is not None:
                obj.destroy()
        ops.destroy()
    summary = {}
    if world.rank == 0:
        x = ops.mesh.x if ops.mesh is not None else np.arange(n_dofs, dtype=float)
        snap_t = sample_times[snap_index] if snapshot_times.size else np.zeros(0)
        w = np.array([_nodal(ops, snaps[i], support.value(sample_times[i]), scene["excitation"]["end"])
                      for i in sorted(snaps)]).reshape(snap_t.size, x.size)
        stats["dofs"] = n_dofs
        summary = _finish(scene, recorder, stats, timings, world.size, "full", snap_t, x, w, {})
        say(f"done: {stats['steps']} steps ({stats['rejected_steps']} rejected, {stats['snes_failures']} Newton "
            f"failures, {stats['factorizations']} factorizations) in {timings['integration']:.2f} s; wrote {path}")
    return world.bcast(summary, root=0)


def _on_rank0(vec) -> np.ndarray | None:
    """The whole of a distributed Vec on rank 0 (None elsewhere). Collective."""
    scatter, full = PETSc.Scatter.toZero(vec)
    scatter.scatter(vec, full, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    values = full.getArray(readonly=True).copy() if vec.getComm().rank == 0 else None
    scatter.destroy()
    full.destroy()
    return values


class SampleRecorder:
    """Rank 0's output of a run, whichever model computed it: each sample (total displacement and
    velocity at the constraints, probe displacement, reduced coordinates if any) becomes a row of
    the output; the impact statistics accumulate over the solver's steps, and the peak force over
    the steps since the previous sample goes with each sample (impacts are often shorter than a
    sample)."""

    def __init__(self, path: str, laws: ConstraintLaws, n_probes: int, r: int = 0, writer=None):
        self.path, self.laws = path, laws
        n = laws.n
        self.impacts = ImpactAccumulator(n)
        self.peak = np.zeros(n)  # signed largest |N| at the steps since the previous sample
        self.writer = writer if writer is not None else OutputWriter(path, n, n_probes, r)

    def _track_peak(self, force) -> None:
        larger = np.abs(force) > np.abs(self.peak)
        self.peak[larger] = force[larger]

    def sample(self, t, z, v, probe, q=(), p=()) -> None:
        force = self.laws.force(z, v)
        self._track_peak(force)
        self.writer.append(**{"time": t, "constraints/displacement": z, "constraints/velocity": v,
                              "constraints/force": force, "constraints/force_peak": self.peak.copy(),
                              "probes/displacement": probe, "reduced/q": q, "reduced/qdot": p})
        self.peak[:] = 0.0

    def step(self, t, z, v) -> None:
        force = self.laws.force(z, v)
        self.impacts.add(t, z, v, force)
        self._track_peak(force)


class Recorder(SampleRecorder):
    """Rank 0's side of a reduced run: turns each sample of q into output rows, keeps the snapshot
    coordinates, and writes checkpoints.

    A checkpoint (OUT.h5.checkpoint, written atomically) is taken at the end of a step: the state,
    the next step size, the counters, the statistics so far and how many samples the .partial file
    holds. Resuming truncates the .partial file to that many samples and restarts the same step
    sequence, so nothing is lost or written twice."""

    def __init__(self, path, model, laws, probe_B, probe_r, snap_index, checkpoint_dt: float, identity: str,
                 resume: bool = False):
        self.model, self.probe_B, self.probe_r = model, probe_B, probe_r
        self.snap_index = set(int(i) for i in snap_index)
        self.snap_q = {}
        self.final = [model.q0, model.p0]
        self.checkpoint_path = f"{path}.checkpoint"
        self.checkpoint_dt, self.next_checkpoint = checkpoint_dt, checkpoint_dt
        self.identity = identity
        self.interrupted = False
        self.base = {}  # counters carried over from before a resume
        self.path, self.laws = path, laws
        self.start = self._resume() if resume else None
        if self.start is None:
            super().__init__(path, laws, probe_B.shape[0], model.size)

    def record(self, t, q, p):
        m = self.model
        index = self.writer.count + len(self.writer.buffer["time"])
        if index in self.snap_index:
            self.snap_q[index] = q
        z, v = m.constraint_state(t, q, p)
        self.sample(t, z, v, self.probe_B @ q + self.probe_r * m.support.value(t), q, p)
        self.final = [q, p]

    def on_step(self, ts, t, q, p):
        self.step(t, *self.model.constraint_state(t, q, p))
        if self.interrupted or t >= self.next_checkpoint:
            self.checkpoint(ts, t, q, p)
            self.next_checkpoint = t + self.checkpoint_dt
        if self.interrupted:
            return (f"stopped by a termination signal at t = {t:.6g} s; the run is checkpointed: "
                    f"rerun with --resume to continue")
        return None

    def checkpoint(self, ts, t, q, p) -> None:
        self.writer.flush()
        state = {"identity": self.identity, "t": t, "dt": ts.getTimeStep(), "steps": ts.getStepNumber(),
                 "q": q.copy(), "p": p.copy(), "samples": self.writer.count,
                 "rejected": self.base.get("rejected", 0) + ts.getStepRejections(),
                 "snes_failures": self.base.get("snes_failures", 0) + ts.getSNESFailures(),
                 "impacts": self.impacts, "peak": self.peak, "snap_q": self.snap_q, "final": self.final}
        tmp = f"{self.checkpoint_path}.tmp"
        with open(tmp, "wb") as f:
            pickle.dump(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.checkpoint_path)

    def _resume(self) -> dict | None:
        """The integrator's starting point from the checkpoint, or None to start afresh."""
        try:
            with open(self.checkpoint_path, "rb") as f:
                state = pickle.load(f)
        except (OSError, pickle.UnpicklingError, EOFError):
            return None
        if state.get("identity") != self.identity:
            raise InputError(f"{self.checkpoint_path} was written by a different scene; remove it or rerun "
                             f"without --resume")
        try:
            self.writer = OutputWriter.reopen(self.path, state["samples"])
        except (OSError, KeyError) as e:
            raise InputError(f"{self.path}.partial cannot be resumed ({e}); rerun without --resume") from None
        self.impacts, self.peak, self.snap_q, self.final = (state["impacts"], state["peak"], state["snap_q"],
                                                            state["final"])
        self.next_checkpoint = state["t"] + self.checkpoint_dt
        self.base = {"rejected": state["rejected"], "snes_failures": state["snes_failures"]}
        return {"t": state["t"], "dt": state["dt"], "steps": state["steps"], "q": state["q"], "p": state["p"],
                "next_sample": state["samples"], **self.base}

    def snapshot_coordinates(self) -> np.ndarray:
        return np.array([self.snap_q[i] for i in sorted(self.snap_q)])

    def abort(self) -> str:
        """Close after a failure; a note on what is left behind."""
        self.writer.abort()
        if os.path.exists(self.checkpoint_path):
            return f" (samples so far in {self.writer.partial}; checkpoint in {self.checkpoint_path})"
        return f" (the samples up to the failure are in {self.writer.partial})"

    def remove_checkpoint(self) -> None:
        if os.path.exists(self.checkpoint_path):
            os.remove(self.checkpoint_path)


@contextlib.contextmanager
def _interrupt_on_sigterm(recorder):
    """While integrating, SIGTERM (a batch system's time limit) asks rank 0 to checkpoint at the end
    of the current step and stop; the other ranks ignore it and wait for rank 0's word."""
    def handler(signum, frame):
        if recorder is not None:
            recorder.interrupted = True

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _scene_identity(scene: Scene) -> str:
    """What a checkpoint must match: every validated value of the scene."""
    content = json.dumps([scene.sections, [repr(c) for c in scene.constraints]], sort_keys=True, default=str)
    return hashlib.sha256(content.encode()).hexdigest()


def _nodal(ops, values: np.ndarray, support_value: float, moving_end: str) -> np.ndarray:
    """Total displacement w at every node (beam; the fixed w DOFs follow the support motion at the
    moving end and stay at rest elsewhere) or at every DOF (matrices), from all DOF values."""
    if ops.mesh is None:
        return np.asarray(values, dtype=float).copy()
    w_rows = ops.mesh.row[:, 0]
    out = np.zeros(w_rows.size)
    row_ok = w_rows >= 0
    out[row_ok] = values[w_rows[row_ok]]
    moving = np.zeros(w_rows.size)
    moving[0 if moving_end == "left" else -1] = 1.0
    out[~row_ok] = moving[~row_ok] * support_value
    return out


def _snapshots(ops, basis, q, times, support, moving_end: str):
    """(x, w): total displacement at every node (beam) or DOF (matrices) at the snapshot times,
    on rank 0. Collective."""
    x = ops.mesh.x if ops.mesh is not None else np.arange(ops.size, dtype=float)
    y = ops.K.createVecRight()
    scatter, full = PETSc.Scatter.toZero(y)
    out = np.zeros((times.size, x.size)) if ops.comm.rank == 0 else None
    for i, ti in enumerate(times):
        basis.vectors.multVec(1.0, 0.0, y, q[i])
        if support.amplitude and ops.influence is not None:
            y.axpy(support.value(ti), ops.influence)
        scatter.scatter(y, full, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        if ops.comm.rank == 0:
            out[i] = _nodal(ops, full.getArray(readonly=True), support.value(ti), moving_end)
    scatter.destroy()
    full.destroy()
    y.destroy()
    return x, out
