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


def run(scene: Scene, out: str | None = None, progress: bool = True, comm=None, initial_state=None,
        resume: bool = False) -> dict:
    """Run the scene and write its HDF5 output. Returns a summary (same on every rank), with the
    final reduced state. initial_state = (q, q') starts from a previous run's final state instead of
    [initial] (continuation in a frequency sweep; the basis must be the same). With resume, a run
    that was killed continues from its last checkpoint (OUT.h5.checkpoint) and ends as an
    uninterrupted run would."""
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
    e = scene["excitation"]
    force_row = None
    if e["kind"] == "force":
        force_row = ops.mesh.w_row(e["x"]) if ops.mesh is not None else int(e["dof"])
        if force_row < 0 or force_row >= ops.size:
            raise InputError("the force acts on a fixed DOF or outside the structure; move it")
    timings["operators"] = time.perf_counter() - t
    say(f"dbf-hpc: {scene.path}: {ops.size} DOFs, {rows.size} constraint(s), {world.size} rank(s)")

    t, solves = time.perf_counter(), counters["eigen_solves"]
    basis = obtain_basis(ops, rows, scene.basis_settings(), operators_fingerprint(scene, ops),
                         scene.cache_dir(), [c.label for c in scene.constraints])
    timings["basis"] = time.perf_counter() - t
    say(f"basis: {basis.mode_count} modes + {rows.size} DBFs ({timings['basis']:.2f} s, cache "
        f"{basis.stats.get('cache')})")
    for warning in basis.warnings([c.label for c in scene.constraints]):
        PETSc.Sys.Print(f"dbf-hpc: warning: {warning}", comm=comm)

    t = time.perf_counter()
    laws = ConstraintLaws([c.law for c in scene.constraints])
    support = Harmonic(e["amplitude"], e["frequency_hz"]) if e["kind"] == "base" else Harmonic()
    force, force_load = Harmonic(e["amplitude"], e["frequency_hz"]) if e["kind"] == "force" else Harmonic(), None
    if e["kind"] == "random":
        force = RandomProcess(e["psd"], e["band"], e["seed"], e["components"])
        force_load = distributed_load(ops, *e["span"])
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
    n_snap = scene["output"]["snapshots"]
    snapshot_times = np.linspace(0.0, settings.t_end, n_snap) if n_snap else np.zeros(0)
    sample_times = settings.sample_times
    snap_index = np.unique(np.searchsorted(sample_times, snapshot_times - 1e-12 * settings.t_end))
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
    snap_t = sample_times[snap_index] if n_snap else np.zeros(0)
    x, w = _snapshots(ops, basis, snap_q, snap_t, support, e["end"])
    timings["snapshots"] = time.perf_counter() - t

    summary = {}
    if world.rank == 0:
        timings["total"] = sum(timings.values())
        stats.update(eigen_solves=counters["eigen_solves"] - solves, cache=basis.stats.get("cache", ""))
        positions = np.array([c.x if c.x is not None else c.dof for c in scene.constraints], dtype=float)
        writer = recorder.writer
        constraint_stats = recorder.impacts.result()
        probe_peak = np.abs(writer.series_data("probes/displacement")).max(axis=0, initial=0.0)
        writer.finish(
            datasets={"constraints/position": positions,
                      "constraints/clearance_minus": [c.law.clearance_minus for c in scene.constraints],
                      "constraints/clearance_plus": [c.law.clearance_plus for c in scene.constraints],
                      "probes/position": np.asarray(scene["output"]["probes"], dtype=float),
                      "basis/omega": basis.omega, "basis/dbf_omega": basis.dbf_omega, "basis/dbf_k": basis.dbf_k,
                      "reduced/K": model.K, "reduced/B": model.B, "reduced/D": model.D,
                      "snapshots/time": snap_t, "snapshots/x": x, "snapshots/w": w, "probes/peak": probe_peak,
                      **{f"constraints/stats/{k}": v for k, v in constraint_stats.items()}},
            dataset_attrs={f"constraints/stats/{k}": {"unit": UNITS[k], "description": DESCRIPTIONS[k]}
                           for k in constraint_stats},
            attrs={"scene": scene.text, "scene_path": os.path.abspath(scene.path), "method": "rom",
                   "petsc_version": ".".join(map(str, PETSc.Sys.getVersion())),
                   "slepc_version": ".".join(map(str, SLEPc.Sys.getVersion())),
                   "mpi_ranks": world.size, "solver_stats": json.dumps(stats), "wall_times": json.dumps(timings),
                   "initial_state": "at rest in relative coordinates (u = 0, u_t = 0); absolute velocity "
                                    "Omega'(0) r" if not init["amplitude"] else
                                    f"displacement {init['amplitude']} m peak in reference mode {init['mode']}"})
        summary = {"path": path, "stats": stats, "timings": timings, "probe_peak": probe_peak.tolist(),
                   "final_state": [recorder.final[0].tolist(), recorder.final[1].tolist()],
                   "constraint_stats": {k: v.tolist() for k, v in constraint_stats.items()}}
        recorder.remove_checkpoint()
        say(f"done: {stats['steps']} steps ({stats['rejected_steps']} rejected, {stats['snes_failures']} Newton "
            f"failures) in {timings['integration']:.2f} s; wrote {path}")
    basis.destroy()
    ops.destroy()
    return world.bcast(summary, root=0)


class Recorder:
    """Rank 0's side of a run: turns each sample into output rows, accumulates the impact
    statistics over the steps, keeps the snapshot coordinates, and writes checkpoints.

    A checkpoint (OUT.h5.checkpoint, written atomically) is taken at the end of a step: the state,
    the next step size, the counters, the statistics so far and how many samples the .partial file
    holds. Resuming truncates the .partial file to that many samples and restarts the same step
    sequence, so nothing is lost or written twice."""

    def __init__(self, path, model, laws, probe_B, probe_r, snap_index, checkpoint_dt: float, identity: str,
                 resume: bool = False):
        self.path, self.model, self.laws = path, model, laws
        self.probe_B, self.probe_r = probe_B, probe_r
        n = model.B.shape[0]
        self.impacts = ImpactAccumulator(n)   # statistics over the solver's steps, not the samples
        self.peak = np.zeros(n)               # signed largest |N| at the steps since the previous sample
        self.snap_index = set(int(i) for i in snap_index)
        self.snap_q = {}
        self.final = [model.q0, model.p0]
        self.checkpoint_path = f"{path}.checkpoint"
        self.checkpoint_dt, self.next_checkpoint = checkpoint_dt, checkpoint_dt
        self.identity = identity
        self.interrupted = False
        self.base = {}  # counters carried over from before a resume
        self.start = self._resume() if resume else None
        if self.start is None:
            self.writer = OutputWriter(path, n, probe_B.shape[0], model.size)

    def _track_peak(self, force) -> None:
        larger = np.abs(force) > np.abs(self.peak)
        self.peak[larger] = force[larger]

    def record(self, t, q, p):
        m = self.model
        z, v = m.constraint_state(t, q, p)
        force = self.laws.force(z, v)
        self._track_peak(force)
        if self.writer.count + len(self.writer.buffer["time"]) in self.snap_index:
            self.snap_q[self.writer.count + len(self.writer.buffer["time"])] = q
        self.writer.append(**{"time": t, "constraints/displacement": z, "constraints/velocity": v,
                              "constraints/force": force, "constraints/force_peak": self.peak.copy(),
                              "probes/displacement": self.probe_B @ q + self.probe_r * m.support.value(t),
                              "reduced/q": q, "reduced/qdot": p})
        self.peak[:] = 0.0
        self.final = [q, p]

    def on_step(self, ts, t, q, p):
        z, v = self.model.constraint_state(t, q, p)
        force = self.laws.force(z, v)
        self.impacts.add(t, z, v, force)
        self._track_peak(force)
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


def _snapshots(ops, basis, q, times, support, moving_end: str):
    """(x, w): total displacement at every node (beam) or DOF (matrices) at the snapshot times,
    on rank 0. Collective."""
    if ops.mesh is not None:
        x = ops.mesh.x
        w_rows = ops.mesh.row[:, 0]
        moving = np.zeros(x.size)  # fixed w DOFs: the moving support follows Omega, the rest stay
        moving[0 if moving_end == "left" else -1] = 1.0
    else:
        x = np.arange(ops.size, dtype=float)
        w_rows = np.arange(ops.size)
        moving = np.zeros(x.size)
    y = ops.K.createVecRight()
    scatter, full = PETSc.Scatter.toZero(y)
    out = np.zeros((times.size, x.size)) if ops.comm.rank == 0 else None
    for i, ti in enumerate(times):
        basis.vectors.multVec(1.0, 0.0, y, q[i])
        if support.amplitude and ops.influence is not None:
            y.axpy(support.value(ti), ops.influence)
        scatter.scatter(y, full, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        if ops.comm.rank == 0:
            values = full.getArray(readonly=True)
            row_ok = w_rows >= 0
            out[i, row_ok] = values[w_rows[row_ok]]
            out[i, ~row_ok] = moving[~row_ok] * support.value(ti)
    scatter.destroy()
    full.destroy()
    y.destroy()
    return x, out
