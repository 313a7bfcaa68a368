"""One run of a scene, writing its HDF5 output: the front end of `dbf-hpc run` and of the sweep.

    scene -> full-order model -> (reductor -> reduced model) -> integrator -> output

Collective on `comm` (default COMM_WORLD). The full-order model and the basis are distributed; the
reduced model is small and the same on every rank, so rank 0 integrates it while the other ranks
wait (without spinning). A full-order run integrates on every rank; rank 0 writes.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import signal
import socket
import sys
import time

import h5py
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc
from slepc4py import SLEPc

from . import __version__, layout, xdmf
from .xdmf import geometry_datasets, node_vectors
from .accuracy import (KINDS_NOTE, RICH_STEP, TOLERANCE_MARGIN, Estimate, blind_to_contact, estimate_window,
                       first_contact, constraint_kinds, flexibility_warning, is_long, nested_estimate, pick_basis, relative_difference,
                       reused_estimate, richer_models, statistics_estimate, statistics_window, zeta_per_vector)
from .basis import SUSPICIOUS_HZ
from .checkpoint import Checkpoint, arrays_sha256, identity
from .errors import (TERMINATION, WRITE_ERRORS, DbfError, InputError, Interrupted, SolverError, Unresumable, WriteFailed,
                     decided_on_rank0, from_rank0, petsc_failure, recorded, recording, temporary_path,
                     termination_signals, wait_for_rank0, warn, write_failure)
from .fom import Observation
from .fom_integrator import check_step, ignored_settings, integrate_full, step_count
from .fom_integrator import options as full_options
from .matrices import file_digest
from .modes import REPEATED_TOL, count_below, counters
from .output import (LONGEST_PID, SNAPSHOT_OVERHEAD_BYTES, OutputLock, OutputWriter, check_free_space,
                     check_name_length, check_output_path, free_bytes, is_dbf_checkpoint, is_dbf_partial, output_bytes)
from .petsctools import (command_option_names, mark_options_read, options_read_anywhere, petsc_comm,
                         petsc_errors_as_one_line, unread_options, unused_option_warning)
from .recorder import FullRecorder, ReducedRecorder, SampleRecorder
from .reductor import Reductor
from .rom import ReducedModel
from .rom_integrator import c_counters, effective_callbacks, integrate_reduced, say_fallback
from .scene import Scene
from .excitation import Harmonic
from .schema import SECTIONS
from .simulate import snapshot_cap_warning, snapshot_samples
from .stats import DESCRIPTIONS_2D as DESCRIPTIONS, UNITS_2D as UNITS
from .timestepping import (MIN_STEP_FRACTION, STEPS_PER_PERIOD, TIME_ULPS, cap_refusal, cap_refused_below_hz, check_work,
                           refuse_settings_options)


def output_path(scene: Scene, override: str | None, resume: bool = False) -> str:
    """The run's output file, refused before any work when it, or the .partial and .checkpoint the
    run writes and removes beside it, exists and is not dbf-hpc's (red team: a file named like them
    was replaced or deleted). A resume reads the checkpoint, and refuses a foreign one itself. An
    output another job is writing is refused first, naming that job (its lock, output.OutputLock)."""
    if override is not None and not str(override).strip():   # red team: "" wrote the scene's [output] file
        raise InputError(f"output {override!r} is an empty name: give a file name, or none for the scene's [output] "
                         f"file")
    path = override or scene.output().file
    if not path:
        raise InputError("no output file: give [output] file in the scene or -o OUT.h5")
    # before the files are opened: HDF5 refuses to open the .partial a running job writes, and that line
    # ("another process has it open for writing") named neither the job nor its lock (red team)
    OutputLock(path).refuse_if_held()
    check_output_path(path, scene.inputs())
    # the longest names the run writes beside it: its checkpoint's temporary file, the lock a next job sets
    # aside (OutputLock._take_over), the ParaView file's temporary file
    check_name_length(path, [f"{path}.checkpoint.tmp", f"{path}.lock.stale-{socket.gethostname()}-{LONGEST_PID}",
                             *([temporary_path(xdmf.sidecar(path), pid=LONGEST_PID)]
                               if scene.output().snapshots else [])])
    check_output_path(f"{path}.partial", scene.inputs(), replaceable=is_dbf_partial, beside=path)
    if not resume:
        check_output_path(f"{path}.checkpoint", scene.inputs(), replaceable=is_dbf_checkpoint, beside=path)
    if scene.output().snapshots:
        xdmf.check_sidecar(path, scene.inputs())
    return path


@contextlib.contextmanager
def claimed(path: str, comm):
    """Rank 0 holds the output's lock (output.OutputLock) for the block; every rank learns at once
    whether it could. Collective. On a normal exit every rank leaves after the lock is gone (a
    script that looks for OUT.h5.lock on another rank right after run() returns finds none); on an
    exception no rank waits for the others (they may be inside another collective)."""
    lock = OutputLock(path)
    lock.expect(comm)   # before rank 0 takes it: a rank that aborts the job removes it (cli._abort)
    try:
        decided_on_rank0(comm, lock.acquire)
    except BaseException:
        lock.forget()   # rank 0 took none (a no-op there: a failed acquire releases what it made)
        raise
    try:
        yield
    finally:
        if comm.getRank() == 0:
            lock.release()
        else:
            lock.forget()
    comm.barrier()


@petsc_errors_as_one_line()
def run(scene: Scene, out: str | None = None, progress: bool = True, comm=None, initial_state=None,
        resume: bool = False, method: str = "rom") -> dict:
    """Run the scene and write its HDF5 output. Returns a summary (the same on every rank) with the
    final reduced state. initial_state = (q, q') starts from a previous run's final state instead of
    [initial] (continuation in a frequency sweep; the basis must be the same). With resume, a run
    that was killed continues from its last checkpoint (OUT.h5.checkpoint) and ends as an
    uninterrupted run would, and a finished output of the same question (finished_output) is kept:
    its summary is read back, nothing is computed, and the warnings its run printed are printed
    again. method = "full" integrates the full-order model instead: the reference the reduced model
    is measured against, same scene, same output layout. `out` (default the scene's [output] file,
    relative to the scene's folder), `progress`: the progress lines on stdout (rank 0 of comm). The
    summary's "warnings" lists what the run warned (the output's `warnings` attribute: what it said
    before its output was complete, of its result, and of the command's PETSc options no solver read,
    petsctools.command_options). Collective on comm (a petsc4py or mpi4py communicator, default
    COMM_WORLD): every rank of it calls run with the same scene, and a DbfError is raised on all of
    them."""
    with recording() as warned:
        return _run_recorded(scene, out, progress, comm, initial_state, resume, method, warned)


def _run_recorded(scene: Scene, out, progress: bool, comm, initial_state, resume: bool, method: str,
                  warned: list) -> dict:
    """run, recording its warnings in `warned` (errors.recording): the output stores them (finish), and
    a --resume of a finished output shows those this invocation has not (its summary's "warnings")."""
    if method not in ("rom", "full"):
        raise InputError(f"--method {method!r}: choose rom or full")
    if method == "full" and initial_state is not None:
        raise InputError("--method full starts from [initial] (or resumes from its checkpoint), not from a reduced state")
    comm = petsc_comm(comm, "run")
    say = (lambda m: PETSc.Sys.Print(m, comm=comm)) if progress else None
    # rank 0 writes the output, so its look at the files decides (red team: each rank looked itself)
    path = decided_on_rank0(comm, output_path, scene, out, resume)
    settings = scene.integrator_settings()
    check_work(settings, scene.fastest_forcing_hz(), adaptive=settings.adaptive and method == "rom")
    if method == "full":     # before the output is claimed (the loop checks again)
        check_step(settings)
        _warn_ignored_by_full(scene, settings, comm)
    if method == "rom":      # before the basis is built (the integrator checks again)
        refuse_settings_options("rom_", settings.adaptive)
    # The warnings below say a result may be wrong: -q (progress=False) silences the progress, not them
    # (red team: --method full -q at 2.5 steps a period of the forcing wrote a wrong response with no word)
    for message in scene_warnings(scene, settings, method):
        warn(message, comm)
    TERMINATION.finished = False
    with claimed(path, comm):
        digests = scene.file_digests(comm)   # once: the request and the run's identity hold the same bytes
        request = request_identity(scene, comm, method, initial_state, digests)
        done = finished_output(path, identity(request=request), scene, comm) if resume else None
        if done is not None:   # a requeued batch job whose run had finished: nothing is computed again
            decided_on_rank0(comm, _drop_leftover_checkpoint, path)
            _say(say, f"{path} is already complete for this scene and setup: nothing to resume (`dbf-hpc info "
                      f"{path}` shows it; rerun without --resume to compute it again)")
            # what its run warned, each line once (a requeued job's log said nothing of it); an output
            # written before outputs stored them: what its summary shows (result_warnings)
            stored = done["warnings"] if "warnings" in done else result_warnings(done, scene.constraints, method,
                                                                                  settings)
            # the command's PETSc options were read by the run that wrote it, which stored the lines of those
            # no solver read (finish): said again here, and the command does not call the others unused
            mark_options_read(command_option_names())
            _say_unsaid(stored, warned, comm)
            TERMINATION.finished = True
            return done
        if method == "rom":   # decided alike on every rank, though rank 0 alone integrates
            say_fallback(settings.callbacks, law_dimension(scene), comm)
        summary = _run(scene, path, settings, say, comm, initial_state, resume, method, request, digests)
    # what finish stored and the run has not said yet: its result's (result_warnings), the PETSc options no
    # solver read (unused_option_lines); every rank records them (the command says none of them again)
    _say_unsaid(summary["warnings"], warned, comm)
    return summary


def _say_unsaid(messages: list, warned: list, comm) -> None:
    """Each of `messages` (the warnings an output stores: a finished one's, or this run's own) that this
    invocation has not said yet (`warned`, its recording), once the output is complete. Not collective:
    every rank on this path."""
    for message in messages:
        if message not in warned:
            warn(message, comm)


def scene_warnings(scene: Scene, settings, method: str = "rom") -> list:
    """What a run warns before any work, from its scene and integrator settings alone, in the order it
    says them: a fixed step too coarse for the forcing (coarse_step_warning; a full-order run's steps are
    always fixed), [basis] keys it does not read (unused_estimate_keys_warning, unused_dbf_keys_warning),
    samples too coarse for the forcing (coarse_samples_warning) and more snapshots than samples
    (simulate.snapshot_cap_warning). The one list `dbf-hpc run` (run.run) says and a sweep says once for the
    cases it concerns and keeps in each case's row (sweep.load_sweep, sweep._said_for_the_sweep): a case
    says what the run of its scene says. Not collective."""
    fastest = scene.fastest_forcing_hz()
    messages = (coarse_step_warning(settings, fastest) if method == "full" or not settings.adaptive else None,
                unused_estimate_keys_warning(scene), unused_dbf_keys_warning(scene),
                coarse_samples_warning(settings, fastest), snapshot_cap_warning(scene.output().snapshots, settings))
    return [message for message in messages if message]


def options_read(comm) -> tuple | None:
    """(the command's PETSc options, whether a solver on any rank of comm has read each so far:
    petsctools.options_read_anywhere), or None where the command gave none (petsctools.command_option_names:
    the same on every rank, the same command line). Taken once every rank is done with its solvers, for
    unused_option_lines as rank 0 writes the output. Collective."""
    names = command_option_names()
    return (names, options_read_anywhere(names, comm)) if names else None


def unused_option_lines(options: tuple | None) -> list:
    """The warning for each of the command's PETSc options no solver read (`options`: options_read, and this
    rank's reads since), stored with the run's other warnings in its output (finish): `dbf-hpc info` shows
    them and --resume of the finished output says them again. Not collective."""
    if not options:
        return []
    return [unused_option_warning(name) for name in unread_options(*options)]


def result_warnings(summary: dict, constraints, method: str, settings) -> list:
    """What a run warns of its result, from its summary, after the integration: a stop never reached
    (idle_warnings), Hunt-Crossley damping beyond its range, impacts a fixed step does not resolve, and
    (full order) a contact stiffer than the step resolves. `constraints`: each with .label and .law, in
    the model's order. The same lines wherever the same result is produced: run.run (`dbf-hpc run`),
    and simulate_full / simulate_reduced (simulate.py). Not collective."""
    out = idle_warnings(summary, constraints) + hunt_crossley_warnings(summary, constraints, method)
    if method == "full" or not settings.adaptive:
        out += unresolved_warnings(summary, constraints, settings.dt, "" if method == "full" else
                                   ", or set [integrator] adaptive = true")
    if method == "full":
        out += contact_stiffness_warnings(summary, constraints, settings.dt)
    return out


# The reduced model's settings a full-order run does not read (fom_integrator.ignored_settings), by section
REDUCED_ONLY = {"integrator": ("rtol", "atol", "adaptive", "scheme", "contact", "callbacks"),
                "basis": ("tolerance", "estimate_statistics_window")}


def _warn_ignored_by_full(scene: Scene, settings, comm) -> None:
    """A warning for each reduced-model setting the scene (or a --set) gave that --method full ignores,
    naming what it does instead. Not collective (every rank has the scene)."""
    values = {key: scene[section][key] for section, keys in REDUCED_ONLY.items() for key in keys
              if (section, key) in scene.given}
    names = {key: f"[{section}] {key}" for section, keys in REDUCED_ONLY.items() for key in keys}
    for message in ignored_settings(values, settings.dt, "--method full", {**names, "dt": "[integrator] dt"}):
        warn(message, comm)


def unused_estimate_keys_warning(scene: Scene) -> str | None:
    """A warning when the scene (or a --set) gives [basis] estimate_window or estimate_statistics_window
    and the run makes no estimate: [basis] estimate = false (and no tolerance mode, which makes its own),
    or no constraints. Red team: estimate_window = 0.05 with estimate = false ran without a word, the
    window read nowhere. A warning, not a refusal: --set basis.estimate=false is the way to skip the
    estimate of a scene that sets its window. Not collective."""
    given = [key for key in ("estimate_window", "estimate_statistics_window") if ("basis", key) in scene.given]
    if not given:
        return None
    b = scene["basis"]
    if not scene.constraints:
        why = "the scene has no constraints, and the estimate measures w at them"
    elif not b["estimate"] and b["tolerance"] is None:
        why = "[basis] estimate = false"
    else:
        return None
    verb, it = ("is", "it") if len(given) == 1 else ("are", "them")
    return f"[basis] {' and '.join(given)} {verb} not used: {why}, so the run makes no error estimate; remove {it}"


# The [basis] keys only the DBFs read (BasisSettings.strategy: DbfEnrichment)
DBF_KEYS = ("dbf_stiffness", "dbf_derivative", "dbf_solver", "groups")


def unused_dbf_keys_warning(scene: Scene) -> str | None:
    """A warning when the scene (or a --set) gives a DBF key (DBF_KEYS) and [basis] enrichment is not
    "dbf": the comparators ("static", "none") read none of them. Red team: dbf_stiffness = 1e5 with
    enrichment = "static" ran without a word. A warning, not a refusal: --set basis.enrichment=static
    is how one runs the comparator of a scene that tunes its DBFs. Not collective."""
    enrichment = scene["basis"]["enrichment"]
    defaults = SECTIONS["basis"][1]
    given = [key for key in DBF_KEYS if ("basis", key) in scene.given and scene["basis"][key] != defaults[key].default]
    if enrichment == "dbf" or not given:
        return None
    verb, it, they = ("is", "it", "it tunes") if len(given) == 1 else ("are", "them", "they tune")
    return (f"[basis] {', '.join(given)} {verb} not used by enrichment = \"{enrichment}\" ({they} the DBFs of "
            f"enrichment = \"dbf\"); remove {it} or set enrichment = \"dbf\"")


def _warn_gyroscopically_held(ops) -> None:
    """A warning when an undamped moving beam is above its critical speed sqrt((T + P_cr) / m_t) with
    no mode growing: K has an even number of negative eigenvalues and the gyroscopic forces alone hold
    it (red team: a band at 93 m/s, U_c = 92.56 m/s, ran without a word); any damping makes it grow
    (Kelvin-Tait-Chetaev), so the response has no damped counterpart. Collective."""
    from .structure import buckling_load, critical_speed

    beam = ops.mesh.beam
    u_c = critical_speed(beam, buckling_load(ops.comm, ops.mesh))
    if abs(beam.axial_speed) > u_c:
        warn(f"axial speed {beam.axial_speed:g} m/s is above the critical speed U_c = sqrt((T + P_cr) / m_t) = "
             f"{u_c:.6g} m/s: K is not positive definite and only the gyroscopic forces hold the undamped structure "
             f"(no mode grows); any damping makes it grow (Kelvin-Tait-Chetaev), so this response has no damped "
             f"counterpart", ops.comm)


def form_warning(scene: Scene, fom) -> str | None:
    """A warning where [basis] gyroscopic_form = "state_space" is given for a structure without G (a reduced
    run: its reduced model is the second-order one), or None; a run and a sweep's model say it (red team:
    the form was silently not used). Not collective."""
    if fom.operators.G is None and scene["basis"]["gyroscopic_form"] == "state_space":
        return ('[basis] gyroscopic_form = "state_space" is for gyroscopic structures (axial_speed, or a '
                'matrices G); this one has no G, so its reduced model is the usual second-order one')
    return None


def gyroscopic_checks(scene: Scene, fom, method: str) -> None:
    """A gyroscopic structure (issue 19): refused above its critical speed (an unstable mode among the
    [basis] modes lowest, or the lowest 8, without and with its damping), and warned about if undamped
    above it with no mode growing (_warn_gyroscopically_held); the reduced model
    (gyroscopic_basis.py) takes no modal damping ratios (its basis vectors are not modes) and no
    tolerance mode. Collective."""
    from .gyroscopic import check_damped_stable, check_stable

    s = scene["structure"]
    speed = f"{s['axial_speed']:g} m/s" if scene.is_beam else "of the given gyroscopic matrix"
    count = scene["basis"]["modes"] or 8
    check_stable(fom.operators, count, speed)
    if fom.damping.kind != "modal" and fom.damping_matrix() is not None:   # modal: refused below, or by --method full
        check_damped_stable(fom.operators, fom.velocity_matrix(), count, speed)
    elif scene.is_beam and fom.damping.kind != "modal":
        _warn_gyroscopically_held(fom.operators)
    if method == "rom" and fom.damping.kind == "modal":
        raise InputError("[damping] zeta: modal damping ratios have no meaning for the real basis of a gyroscopic "
                         "structure's complex modes; give Rayleigh coefficients (rayleigh_alpha, rayleigh_beta)")
    if method == "rom" and scene.estimate_settings().tolerance is not None:
        raise InputError("[basis] tolerance: the tolerance mode is not available for a gyroscopic structure; give "
                         "[basis] modes")


# How far below the frequency where timestepping.cap_refusal starts to refuse the highest reference mode must
# lie for cap_refusal_before_basis to refuse: the inertia counts exact eigenvalues, the basis' computed ones
# are right to about 5e-6 in frequency (modes.TRUST_TOL); a mode within this margin is left to the integrator.
CAP_MARGIN = 1e-4


def cap_refusal_before_basis(scene: Scene, fom, settings) -> str | None:
    """The line timestepping.configure refuses an adaptive reduced run with whose output samples cap its
    step at or below its floor (timestepping.cap_refusal: red team, t_end = 1e-9 s), said before any basis
    is built where it is certain, else None (the integrator checks again, as before). The floor depends on
    the highest reference mode's frequency F, known only once the modes are solved; before them:
    timestepping.cap_refused_below_hz gives the F up to which the settings are refused (usually none: no
    work), and the refusal is made here only where F certainly lies below it (CAP_MARGIN) and the line
    does not depend on F (F up to 1/STEPS_PER_PERIOD of 1/dt, where the floor is dt x MIN_STEP_FRACTION):
    by [basis] max_frequency_hz, which bounds F where no eigenvalue of (K, M) lies within 2 REPEATED_TOL
    above its own (two inertia counts: a repeated eigenvalue, or a chain of eigenvalues each within
    REPEATED_TOL of the next, at the cutoff is kept whole, beyond it), or for [basis] modes = N by counting
    the eigenvalues of (K, M) below it (modes.count_below: one factorization, no eigensolve; N of them: F
    is below it). Never a run the integrator would accept. Not made (left to the integrator) for a gyroscopic structure
    (complex modes), the tolerance mode (its candidates' modes) and where the inertia cannot be counted.
    Collective on the model's communicator."""
    below = cap_refused_below_hz(settings)
    if not settings.adaptive or below is None:
        return None
    same = math.inf if TIME_ULPS * float(np.spacing(settings.t_end)) >= settings.dt * MIN_STEP_FRACTION else \
        1.0 / (STEPS_PER_PERIOD * settings.dt)   # up to here the floor, and so the line, is F's alone
    limit = min(below, same) * (1 - CAP_MARGIN)
    if limit == math.inf:
        return cap_refusal(settings)
    if fom.operators.G is not None or scene.estimate_settings().tolerance is not None:
        return None
    basis = scene.basis_settings()
    comm = fom.comm.tompi4py()
    if basis.modes is None:
        if not basis.max_frequency_hz * (1 + REPEATED_TOL) < limit:
            return None
        # max_frequency_hz bounds F only where no eigenvalue lies just above its lambda: the basis keeps a repeated
        # eigenvalue at the cutoff whole, and modes.reference_modes' "whole" chains eigenvalues each within
        # REPEATED_TOL of the next (red team: 250 modes 1e-6 apart in lambda made F 1.2e-4 above the cutoff, and a
        # run the integrator accepts was refused). None found within 2 REPEATED_TOL above it: the chain ends below.
        lam = (2 * math.pi * basis.max_frequency_hz) ** 2 if basis.max_frequency_hz < 1e150 else math.inf
        if not math.isfinite(lam * (1 + 2 * REPEATED_TOL)):
            return None
        below_max = comm.bcast(count_below(fom.operators, lam), root=0)
        below_gap = comm.bcast(count_below(fom.operators, lam * (1 + 2 * REPEATED_TOL)), root=0)
        return cap_refusal(settings) if below_max is not None and below_max == below_gap else None
    sigma = (2 * math.pi * limit) ** 2 if limit < 1e150 else math.inf
    if not math.isfinite(sigma):
        return None
    count = comm.bcast(count_below(fom.operators, sigma), root=0)
    return cap_refusal(settings) if count is not None and count >= basis.modes else None


def _run(scene: Scene, path: str, settings, say, comm, initial_state, resume: bool, method: str,
         request: str | None = None, digests: dict | None = None) -> dict:
    timings, t = {}, time.perf_counter()
    with scene.full_order_model(comm) as fom:
        timings["operators"] = time.perf_counter() - t
        _say(say, f"dbf-hpc: {scene.path}: {fom.size} DOFs, {fom.constraints.count} constraint(s), "
                  f"{comm.getSize()} rank(s)")
        if fom.operators.G is not None:
            gyroscopic_checks(scene, fom, method)
        elif method == "rom":
            form = form_warning(scene, fom)
            if form:
                warn(form, comm)
        if method == "rom":   # before any basis (the integrator checks again)
            refusal = cap_refusal_before_basis(scene, fom, settings)
            if refusal:
                raise InputError(refusal)
        if method == "full":
            return _run_full(scene, fom, path, settings, timings, say, resume, request, digests)
        t, solves = time.perf_counter(), counters["eigen_solves"]
        estimate, pick = scene.estimate_settings(), None
        if estimate.tolerance is not None:
            if zeta_per_vector(fom):
                raise InputError("[damping] zeta gives one ratio per basis vector, but [basis] tolerance picks the "
                                 "number of modes: give one zeta for all, or Rayleigh damping")
            pick = pick_basis(fom, scene.basis_settings(), scene.cache_dir(), settings, estimate, comm, say)
            scene = scene.with_values("basis", modes=pick.modes, max_frequency_hz=None)
            scene = scene.with_values("integrator", rtol=pick.rtol, atol=pick.atol)
            settings = scene.integrator_settings()
            timings["tolerance"] = time.perf_counter() - t
            _say(say, f"tolerance {estimate.tolerance:g}: picked {pick.modes} modes, rtol {pick.rtol:g} and atol "
                      f"{pick.atol:g}: the first candidate whose estimate ({pick.estimate.value:.3g}) is at most "
                      f"{TOLERANCE_MARGIN:g} x the tolerance over [0, {pick.estimate.window:g}] s")
            t = time.perf_counter()
        with Reductor(fom, scene.basis_settings(), scene.cache_dir(), warn_basis=False) as reductor:   # _say_basis
            basis = reductor.basis()
            timings["basis"] = time.perf_counter() - t
            _say_basis(say, basis, timings["basis"], fom.constraints.component_labels, comm, scene.fastest_forcing_hz(),
                       fom.operators.rigid_modes, fom.constraints.dimension)
            t = time.perf_counter()
            model = reductor.reduce(field=scene.output().snapshots > 0)
            if pick is None and settings.adaptive:   # (the tolerance mode's atol is measured by its calibration)
                loose = loose_atol(model, settings.atol, scene.constraints)
                if loose:
                    warn(loose, comm)
            basis_key = {"fingerprint": fom.fingerprint, "basis": basis.settings.key(),
                         "rows": basis.constraint_rows.tolist()}
            cache_state = basis.stats.get("cache", "")
            timings["reduce"] = time.perf_counter() - t
            rich, window = (pick.estimate, pick.estimate.window) if pick else (None, estimate.window)
            second = None   # the estimate's second richer model (accuracy.nested_estimate)
            if estimate.enabled and initial_state is None and pick is None and fom.constraints.count:
                t = time.perf_counter()
                rich, second = richer_models(fom, basis, scene.cache_dir())
                timings["estimate_basis"] = time.perf_counter() - t
    if initial_state is not None:
        model = _continue_from(model, initial_state)
    ident = run_identity(scene, basis_key, comm, "rom", model.coordinates_digest(), request, digests)
    return _run_reduced(scene, model, path, settings, timings, say, comm, resume, ident,
                        {"eigen_solves": counters["eigen_solves"] - solves, "cache": cache_state},
                        (rich, window, estimate.statistics_window, second) if rich is not None and initial_state is None
                        else None, options_read(comm))   # every rank's solvers but rank 0's integration are done


# The most of a constraint's smallest clearance the adaptive steps' absolute tolerance may let w err
# by (atol times the 1-norm of the basis' row at the constraint) before a run is warned.
ATOL_REACH = 1e-2


def atol_reach(model, atol: float, laws=None) -> tuple | None:
    """(ratio, j, reach, clearance) of the constraint j where [integrator] atol lets w err most against
    its smallest clearance (reach = atol times the 1-norm of B's row there, m), if the ratio is over
    ATOL_REACH; else None. `laws`: one law per constraint in the model's order (None: the model's own,
    model.constraints.laws). None for a model without B (the state-space form) or without a clearance.
    Not collective."""
    B = getattr(model, "B", None)
    if B is None or getattr(model, "form", "") == "state_space" or not B.size:
        return None
    if laws is None:
        laws = model.constraints.laws.laws
    d = model.constraints.dimension
    worst = None
    for j, law in enumerate(laws):
        law = getattr(law, "law", law)   # a scene's Constraint, or its law
        ks = (law.k_minus, law.k_plus) if hasattr(law, "k_minus") else (getattr(law, "k", 0.0),) * 2
        gaps = [c for c, k in zip((getattr(law, "clearance_minus", 0.0), getattr(law, "clearance_plus", 0.0)), ks)
                if k > 0 and c > 0]
        if not gaps:
            continue
        reach = atol * float(np.abs(B[j * d:(j + 1) * d]).sum(axis=1).max())
        ratio = reach / min(gaps)
        if ratio > ATOL_REACH and (worst is None or ratio > worst[0]):
            worst = (ratio, j, reach, min(gaps))
    return worst


def loose_atol(model, atol: float, constraints=None) -> str | None:
    """A warning when [integrator] atol (modal units) lets w at a constraint (`constraints`, the scene's,
    in the model's order; None: the model's own laws) err by more than
    ATOL_REACH of its smallest clearance: atol times the 1-norm of B's row at the constraint (w = B q) bounds the
    w error the error control allows where |q| is small. M-orthonormal q scale as the square root of
    the mass, so the default 1e-9 is loose for a structure of small masses and displacements in SI
    (a MEMS part). Red team (new user): the frame of 23 kg with its K and M times 1e-9 and clearances
    of 1 um ran its steps at the 10-sample limit, 24 % off the same run in kg over the estimate
    window, while the estimate (its richer run at atol / 10, as loose) said 9.8 %. Every entry point
    that integrates a reduced model says it once: `dbf-hpc run` and run.run (_run), a sweep (one line
    naming its cases, sweep._warn_loose_atol) and simulate_reduced. Where no clearance is within
    reach, the same bound against the motion's own scale (motion_reach: a micro-beam without
    constraints). Not collective."""
    finding = loose_atol_finding(model, atol, constraints)
    return None if finding is None else finding[2]


def loose_atol_finding(model, atol: float, constraints=None) -> tuple | None:
    """(kind, ratio, line) of loose_atol: kind "clearance" (atol_reach's worst constraint) or "motion"
    (motion_reach, where no clearance is within reach), ratio the reach over that length, line loose_atol's;
    or None. A sweep says the line once for the cases of each kind, with its worst case's numbers
    (sweep._warn_loose_atol). Not collective."""
    worst = atol_reach(model, atol, constraints)
    if worst is not None:
        return "clearance", worst[0], loose_atol_message(atol, *worst)
    motion = motion_reach(model, atol)
    return None if motion is None else ("motion", motion[0], loose_motion_message(atol, *motion))


def motion_reach(model, atol: float) -> tuple | None:
    """(ratio, reach, scale, what) where [integrator] atol lets w err by over ATOL_REACH of the motion's
    own scale (m), else None: the clearance check (atol_reach) has nothing to compare with on a
    structure without stops, and a micro-beam's whole motion can lie below what atol controls. reach
    is atol times the largest 1-norm of a row of B, the probes' and the field's rows (w = B q); the
    scale is the largest of the initial displacement there (its velocity over each column's
    frequency), the support's amplitude, and the static deflection there under a harmonic force's
    amplitude (K_r's pseudo-inverse: rigid-body columns take none). A random load has no such
    scale here: not checked. None for the state-space form and a model at rest. Not collective."""
    B = getattr(model, "B", None)
    if B is None or getattr(model, "form", "") == "state_space":
        return None
    rows = [a for a in (B, getattr(model, "probe_B", None), getattr(getattr(model, "field", None), "V", None))
            if a is not None and a.size]
    if not rows:
        return None
    W = np.vstack(rows)
    reach = atol * float(np.abs(W).sum(axis=1).max())
    K = np.asarray(model.K)
    stiff = np.diag(K)
    omega = np.sqrt(np.where(stiff > 0, stiff, np.inf))
    scales = {"the initial displacement": max(float(np.abs(W @ model.q0).max()),
                                              float(np.abs(W @ (model.p0 / omega)).max()))}
    support = getattr(model, "support", None)
    scales["the support's motion"] = abs(float(getattr(support, "amplitude", 0.0)))
    force, shape = getattr(model, "force", None), np.asarray(model.force_shape)
    if isinstance(force, Harmonic) and shape.ndim == 1 and force.amplitude:
        static = np.linalg.pinv(K, hermitian=True) @ shape * force.amplitude
        scales["the static deflection under the force"] = float(np.abs(W @ static).max())
    what, scale = max(scales.items(), key=lambda item: item[1])
    if not scale > 0 or reach <= ATOL_REACH * scale:
        return None
    return reach / scale, reach, scale, what


def loose_motion_message(atol: float, ratio: float, reach: float, scale: float, what: str) -> str:
    """loose_atol's line for motion_reach's finding."""
    return (f"[integrator] atol = {atol:g} (modal units, m kg^(1/2)) lets w err by up to {reach:.3g} m, {ratio:.3g} x "
            f"the motion's scale {scale:.3g} m ({what}): the steps do not control the error, and the estimate's "
            f"richer run (atol / 10) cannot see it (small masses or displacements in SI units); set [integrator] "
            f"atol = {atol * ATOL_REACH * 1e-2 / ratio:.2g} or below")


def loose_atol_message(atol: float, ratio: float, j: int, reach: float, gap: float) -> str:
    """loose_atol's line for atol_reach's worst constraint."""
    return (f"[integrator] atol = {atol:g} (modal units, m kg^(1/2)) lets w at constraint {j + 1} err by up to "
            f"{reach:.3g} m, {ratio:.3g} x its clearance {gap:g} m: the steps do not control the error there, and "
            f"the estimate's richer run (atol / 10) cannot see it (small masses or displacements in SI units); set "
            f"[integrator] atol = {atol * ATOL_REACH * 1e-2 / ratio:.2g} or below")


def _say(say, message: str) -> None:
    if say is not None:
        say(message)


def _say_basis(say, basis, seconds: float, labels, comm, forcing_hz: float, rigid_modes: int = 0,
               dimension: int = 1) -> None:
    """The basis lines of a run; labels has one entry per component, `dimension` per constraint."""
    strategy = basis.settings.strategy
    extra = f"+ {basis.constraint_omega().size} {strategy.column_name}s" if strategy.column_name else "(no enrichment)"
    f = basis.omega / (2 * np.pi)
    modes = f"{basis.complex_modes} complex modes" if basis.complex_modes else f"{basis.mode_count} modes"
    columns = f", Re and Im: {basis.size} real columns" if basis.complex_modes else ""
    if getattr(basis, "form", "") == "state_space":
        columns = f", Re and Im of the state vectors: {basis.size} real states, A-orthonormal"
    # rigid-body modes are 0 Hz (their round-off, 1e-5 Hz on the free-free paper beam, is no frequency)
    rigid = min(rigid_modes, f.size)
    span = f"{f[0]:.4g} ... {f[-1]:.4g} Hz" if not rigid else f"{rigid} rigid-body at 0 Hz" + (
        f", {f[rigid]:.4g} ... {f[-1]:.4g} Hz" if rigid < f.size else "")
    _say(say, f"basis: {modes} ({span}) {extra} ({seconds:.2f} s, "
              f"cache {basis.stats.get('cache')}{columns})")
    flex = basis.flexibility_captured
    if flex.size and np.any(np.isfinite(flex)):
        j = int(np.nanargmin(flex))
        _say(say, f"static flexibility captured (a-priori indicator): min {flex[j]:.4f} at constraint "
                  f"{j // dimension + 1} ({labels[j]})")
    warnings = basis_warnings(basis, labels, rigid_modes, dimension)
    above = forcing_warning(forcing_hz, basis.omega)
    if above:
        warnings.append(above)
    for warning in warnings:
        warn(warning, comm)


def basis_warnings(basis, labels, rigid_modes: int = 0, dimension: int = 1) -> list:
    """What a run warns of its basis, whatever the forcing: its enrichment's (basis.warnings), a static
    flexibility captured below accuracy.FLEXIBILITY_WARN, a lowest elastic frequency that suggests a unit
    slip. A sweep warns them once for the cases of each model (sweep._prepare_models). Not collective."""
    warnings = basis.warnings(labels)
    low = flexibility_warning(basis.flexibility_captured, labels, dimension)
    if low:
        warnings.append(low)
    # The rigid-body modes' 0 Hz comes out as round-off (1e-5 Hz on the free-free paper beam, 2e-6 of
    # its top mode): they are not the lowest elastic frequency, and no sign of a unit slip (red team)
    f = basis.omega / (2 * np.pi)
    elastic = f[rigid_modes:] if rigid_modes else f[f > 1e-9 * f[-1]] if f.size and f[-1] > 0 else f
    if elastic.size and elastic[0] < SUSPICIOUS_HZ:
        warnings.append(f"the lowest elastic frequency is {elastic[0]:.3g} Hz: check the structure's units (SI: E in "
                        f"Pa, lengths in m, rho in kg/m^3; matrices in N/m and kg, and the stiffness and mass files "
                        f"not swapped)")
    return warnings


def forcing_warning(forcing_hz: float, omega) -> str | None:
    """A forcing above the basis' highest reference mode (omega, rad/s), or None."""
    top = float(np.max(omega)) / (2 * np.pi) if np.size(omega) else 0.0
    if forcing_hz > top:
        return (f"the excitation ({forcing_hz:g} Hz) lies above the highest reference mode ({top:.4g} Hz): "
                f"the basis cannot follow it; add modes (basis.modes or basis.max_frequency_hz)")
    return None


def coarse_step_warning(settings, fastest_hz: float) -> str | None:
    """A warning when a fixed step takes fewer than STEPS_PER_PERIOD steps per period of the fastest
    forcing, or None (red team: --method full with dt = 0.3 s under a 10 Hz force took one step of 0.05 s
    and reported a 727 N peak force and 0 impacts, with no word; generalized-alpha is unconditionally
    stable, so nothing else fails). The scheme's phase error is (omega dt)^2 / 12 per radian. Said by a
    run and a sweep (scene_warnings) and by the Python API (simulate.coarse_warnings)."""
    if fastest_hz > 0 and settings.dt * fastest_hz * STEPS_PER_PERIOD > 1:
        return (f"[integrator] dt = {settings.dt:g} s takes {1 / (settings.dt * fastest_hz):.2g} fixed steps per "
                f"period of the {fastest_hz:g} Hz excitation, fewer than {STEPS_PER_PERIOD}: the step does not "
                f"resolve the forcing, so the response is wrong; reduce [integrator] dt to at most "
                f"{1 / (STEPS_PER_PERIOD * fastest_hz):.3g} s")
    return None


def coarse_samples_warning(settings, fastest_hz: float) -> str | None:
    """A warning when the samples are fewer than two per period of the fastest forcing (Nyquist), or
    None: the sampled series alias the response (red team: a 99 Hz force sampled every 0.01 s wrote a 1 Hz
    oscillation, and probes/peak, the peak over the samples, missed the response's, with no word). Said
    by a run and a sweep (scene_warnings) and by the Python API (simulate.coarse_warnings)."""
    if fastest_hz > 0 and 2 * settings.sample_dt * fastest_hz > 1:
        return (f"[output] sample_dt = {settings.sample_dt:g} s takes {1 / (settings.sample_dt * fastest_hz):.2g} "
                f"samples per period of the {fastest_hz:g} Hz excitation, fewer than 2: the sampled series (time, "
                f"probes, constraints) alias the response and the peaks over the samples miss it; reduce [output] "
                f"sample_dt to at most {1 / (2 * fastest_hz):.3g} s")
    return None


STEPS_PER_IMPACT = 3   # fewer on average, at a fixed step: contact forces and times depend on dt


def unresolved_warnings(summary: dict, constraints, dt: float, also: str = "") -> list:
    """A message for each constraint whose impacts last fewer than STEPS_PER_IMPACT fixed steps on
    average (red team: at 1e12 N/m the peak force was k times a penetration set by dt, 96 kN at
    1e-5 s, 3 kN at 5e-7 s, with no word). Durations are measured on the steps (the recorders'
    impact statistics), so the sample interval does not hide this (a sweep warns them for its cases
    too)."""
    stats = summary.get("constraint_stats", {})
    if not stats:
        return []
    return [f"the impacts of constraint {j + 1} at {constraints[j].label} last {duration / dt:.2g} fixed steps "
            f"on average ({duration:.3g} s at dt = {dt:.3g} s): the step does not resolve them, so contact forces "
            f"and times depend on dt; reduce [integrator] dt (5 to 10 steps an impact){also}"
            for j, (impacts, duration) in enumerate(zip(stats["impacts"], stats["impact_duration_mean"]))
            if impacts > 0 and duration < STEPS_PER_IMPACT * dt]


# The largest alpha |v| a Hunt-Crossley contact damping is meant for. Hunt & Crossley (1975) derived alpha from
# the coefficient of restitution, e = 1 - (2/3) alpha v_impact, for alpha v small; it reaches e = 0, a perfectly
# plastic impact, at alpha v = 3/2, and within it the separation speed e v_impact keeps alpha v below 3/8, so the
# law never pulls (it does beyond 1). Above it the contact is overdamped: the impact stops in a phase shorter than
# the elastic impact (by about 1 / sqrt(alpha v)) and a fixed step that resolves the impact does not resolve it
# (measured, the paper's beam at alpha = 1000 s/m, alpha v = 24: the full-order peak force 0.146 N at dt = 2e-6 s,
# 0.299 N at 5e-7 s, 0.303 N at 1.25e-7 s, and the impact power twice as large, with 120 steps an impact; at
# alpha v = 2.4, 7 %; at 0.24, 0.2 %).
HUNT_CROSSLEY_MAX = 1.5


def hunt_crossley_warnings(summary: dict, constraints, method: str) -> list:
    """A warning for each Hunt-Crossley constraint whose alpha |v| (|v_n| on a support of two directions)
    at a step in contact exceeded HUNT_CROSSLEY_MAX (the recorders' alpha_speed, over the solver's steps).
    Not collective: the summary is every rank's (a sweep warns them for its cases too)."""
    out = []
    for j, speed in enumerate(summary.get("alpha_speed", ())):
        if not speed > HUNT_CROSSLEY_MAX:
            continue
        constraint = constraints[j]
        alpha = constraint.law.alpha
        steps = (", and the full-order force and dissipated energy depend on dt (by a factor of 2 on the paper's beam "
                 "at alpha v = 24, with 120 steps an impact)" if method == "full" else "")
        out.append(f"constraint {j + 1} at {constraint.label}: Hunt-Crossley damping reached alpha |v| = {speed:.3g} "
                   f"in contact (alpha = {alpha:g} s/m, |v| = {speed / alpha:.3g} m/s), above {HUNT_CROSSLEY_MAX:g}, "
                   f"where Hunt & Crossley's restitution e = 1 - (2/3) alpha v falls to 0: the contact is overdamped, "
                   f"outside the law's range{steps}; give alpha = 3 (1 - e) / (2 v) for the restitution e at the "
                   f"impact speed v, at most {HUNT_CROSSLEY_MAX * alpha / speed:.3g} s/m here")
    return out


def contact_stiffness_warnings(summary: dict, constraints, dt: float) -> list:
    """A warning for each constraint of a full-order run whose contact, at its stiffest, oscillates on its own
    with a half-period of fewer than STEPS_PER_IMPACT steps, where the impacts' durations do not say so (a
    contact that stays closed: a clearance of 0 or 1e-15 m, a preload). The integrator keeps D_jj |dN/dz|
    (fom_integrator.FullIntegrator.stiffness: the law's stiffness against the step's, D = G^T K_eff^-1 G);
    for a contact on a mass m, D = 1 / (s_A m), so the contact's omega h = sqrt(D k a_m / (a_f beta)) and
    its half-period lasts pi / (omega h) steps. Red team, the paper's beam: hertz at k = 1e12 N/m and
    clearance 0 gave a mean impact power of 1.7e-5 W, 3.2e-4 W and 2.0e-3 W at dt = 1e-5, 2.5e-6 and
    6.25e-7 s; a deadband of 1e-15 m at k = 1e14 N/m 91 impacts and a 36 kN peak at 2e-6 s, 3650 and 1.5 kN
    at 5e-7 s; with no word (their single impact lasted the whole run). Not collective."""
    from .fom_integrator import Alpha2

    solver = summary.get("stats", {})
    ratios = solver.get("contact_stiffness") or []
    P = Alpha2(float(solver.get("alpha_radius", 0.9)))
    warned = {m.split(" at ")[0] for m in unresolved_warnings(summary, constraints, dt)}
    out = []
    for j, ratio in enumerate(ratios):
        if not ratio > 0 or f"the impacts of constraint {j + 1}" in warned:
            continue
        steps = np.pi / np.sqrt(ratio * P.am / (P.af * P.beta))
        if steps >= STEPS_PER_IMPACT:
            continue
        out.append(f"the contact of constraint {j + 1} at {constraints[j].label} is too stiff for dt = {dt:.3g} s: at "
                   f"its stiffest it rings with a half-period of {steps:.2g} fixed steps (its law's dN/dz against the "
                   f"structure's mass there), so contact forces, impacts and impact power depend on dt, however long "
                   f"the contact lasts; reduce [integrator] dt to about {dt * steps / 5:.2g} s (5 steps a half-period) "
                   f"or soften the law")
    return out


# A stop is suspected of a clearance in the wrong unit when the motion there stays below this fraction of
# the clearance (mm given as m is 1000 times too far). A stop merely not reached (an idle support plate of
# a tube, a short run: 4.7 % of it after 5 ms of the paper's beam) is physics, and the warning fired for
# the shipped 2-D tube six times.
IDLE_FRACTION = 0.01


def idle_warnings(summary: dict, constraints) -> list:
    """A message for each constraint that never touched its stop and whose motion stayed below
    IDLE_FRACTION of its clearance: often a clearance in the wrong unit (a sweep warns them for its
    cases too)."""
    out = []
    stats = summary.get("constraint_stats", {})
    for j, constraint in enumerate(constraints):
        law = constraint.law
        if law.kind in ("deadband", "power", "hertz", "circular", "flat_bar") and stats and stats["impacts"][j] == 0:
            # the sides that have a stop (a one-sided stop's other side has k = 0)
            ks = (law.k_minus, law.k_plus) if hasattr(law, "k_minus") else (law.k, law.k)
            gaps = [c for c, k in zip((law.clearance_minus, law.clearance_plus), ks) if k > 0]
            if not gaps:
                continue
            gap = min(gaps)
            if not stats["displacement_peak"][j] < IDLE_FRACTION * gap:
                continue
            out.append(f"constraint {j + 1} at {constraint.label} never reached its stop (max |w| "
                       f"{stats['displacement_peak'][j]:.3g} m, clearance {gap:.3g} m): check the clearance's unit (m)")
    return out


def _continue_from(model: ReducedModel, initial_state) -> ReducedModel:
    q, p = (np.asarray(a, dtype=float) for a in initial_state)
    if q.shape != (model.size,) or p.shape != (model.size,):
        raise InputError(f"the initial state has {q.size} coordinates; this basis has {model.size}")
    return model.with_case(q0=q, p0=p)


def law_dimension(scene: Scene) -> int:
    """The most directions a constraint law of `scene` acts in (1 without constraints): what the C
    callbacks cover (rom_integrator.c_core)."""
    return max((getattr(c.law, "dimension", 1) for c in scene.constraints), default=1)


def scene_callbacks(scene: Scene) -> str:
    """"c" or "python": the callbacks a reduced run of `scene` integrates with on this installation
    (rom_integrator.effective_callbacks: the same for either gyroscopic form)."""
    return effective_callbacks(scene.integrator_settings().callbacks, law_dimension(scene))


def run_identity(scene: Scene, basis_key: dict | None, comm, method: str, coordinates: str | None = None,
                 request: str | None = None, digests: dict | None = None) -> dict:
    """What a checkpoint must match to be resumed: every part that changes the result: the scene, the
    bytes of every file it reads (not [structure] cells, which only draw the field: cells_attrs),
    the operators and basis, the PETSc options, the rank count, the
    method, the callbacks, the package version, and (reduced) what the coordinates q mean
    (ReducedModel.coordinates_digest: a basis rebuilt in another orientation of a repeated frequency
    holds the same key, not the same q); with `request` (request_identity), also the question as it
    was asked. The finished output stores it too (finished_output). `digests`: the scene's
    file_digests when already made (they are not hashed again). Collective."""
    callbacks = scene_callbacks(scene) if method == "rom" else None
    files = scene.file_digests(comm) if digests is None else digests
    return identity(scene=[scene.result_sections(), [repr(c) for c in scene.constraints]], files=files,
                    structure=basis_key, coordinates=coordinates, options=PETSc.Options().getAll(),
                    ranks=comm.getSize(), method=method, callbacks=callbacks, version=__version__,
                    **({"request": request} if request else {}))


def request_identity(scene: Scene, comm, method: str, initial_state=None, digests: dict | None = None) -> str:
    """The question a run answers, known before any work: run_identity's parts without the basis (the
    scene as given, before the tolerance mode picks its basis; its files; the PETSc options; the rank
    count; the method; the callbacks; the version) and the initial state given. One sha256. Collective."""
    parts = run_identity(scene, None, comm, method, digests=digests)
    if initial_state is not None:
        parts["initial_state"] = arrays_sha256({"q": np.asarray(initial_state[0], dtype=float),
                                                "p": np.asarray(initial_state[1], dtype=float)})
    return identity(request=parts)["request"]


def finished_output(path: str, ident: dict, scene: Scene, comm=None) -> dict | None:
    """The summary of `path` if it is a finished output of this very run, else None: complete, no
    .partial beside it, its stored run identity equal to `ident` on every part `ident` names, and its
    ParaView file present when the scene asks for snapshots, and the one its run wrote for it (not an
    earlier run's, left where this run's write failed: xdmf.describes). A checkpoint beside it does not count:
    without its .partial it cannot be resumed, and a run killed between the output's rename and the
    checkpoint's removal leaves one (red team: a requeued `--resume` then refused the finished run).
    The summary is read back from the file (the same keys and values the run returned; "final_state"
    from its last sample). An output that cannot be read is not finished: the run computes it again.
    With comm, rank 0 reads and every rank gets the answer (collective); without, this rank reads
    (not collective)."""
    if comm is not None:   # whatever else rank 0's look raises, every rank raises (decided_on_rank0)
        return decided_on_rank0(comm, finished_output, path, ident, scene)
    if not os.path.isfile(path) or os.path.exists(f"{path}.partial"):
        return None
    if scene.output().snapshots and not os.path.isfile(xdmf.sidecar(path)):
        return None
    try:
        cells = scene.cells_file()
        cells_digest = file_digest(cells, PETSc.COMM_SELF, "cells") if cells else ""
    except InputError:   # (the run that follows says so, on every rank)
        return None
    try:
        with h5py.File(path, "r") as f:
            stored = json.loads(f.attrs["run_identity"]) if f.attrs.get("complete") else {}
            if not ident or any(stored.get(part) != value for part, value in ident.items()):
                return None
            if f.attrs.get("field_cells_sha256", "") != cells_digest:   # its ParaView file shows other cells
                return None
            if scene.output().snapshots and not xdmf.describes(xdmf.sidecar(path), f):   # an earlier run's
                return None
            if cells_digest and f.attrs.get("field_cells") != (scene["structure"]["cell_type"] or xdmf.CELL_TYPES.get(
                    int(f.attrs.get("field_cell_nodes", 0)))):                    # or of another type
                return None
            return _stored_summary(f, path)
    except (OSError, KeyError, ValueError, TypeError, RuntimeError):   # RuntimeError: damaged metadata
        return None


def cells_attrs(field) -> dict:
    """The attributes that say an output's field is drawn with cells ([structure] cells): their XDMF
    type, nodes a cell, count and the sha256 of the cells file; none without cells. The run identity leaves the
    cells out (they change no number), so finished_output compares these instead."""
    if field.cells is None:
        return {}
    return {"field_cells": field.cell_type, "field_cell_nodes": int(field.cells.shape[1]),
            "field_cell_count": int(field.cells.shape[0]), "field_cells_sha256": field.cells_sha256}


def _drop_leftover_checkpoint(path: str) -> None:
    """Rank 0: remove the checkpoint beside a finished output, if dbf-hpc's (a kill between the
    output's rename and the checkpoint's removal leaves it; it cannot be resumed without its
    .partial). Another file of that name is left alone."""
    leftover = f"{path}.checkpoint"
    try:
        if os.path.isfile(leftover) and not os.path.exists(f"{path}.partial") and is_dbf_checkpoint(leftover):
            os.remove(leftover)
    except (OSError, InputError):   # read-only, or unreadable: it does no harm where it is
        pass


def _stored_summary(f, path: str) -> dict:
    """The summary run_case / _run_full returned, from the output they wrote (finish)."""
    summary = {"path": path, "stats": json.loads(f.attrs["solver_stats"]),
               "timings": json.loads(f.attrs["wall_times"]), "probe_peak": f[layout.PROBE_PEAK][()].tolist(),
               "constraint_stats": {k: v[()].tolist() for k, v in f[layout.CONSTRAINT_STATS].items()}}
    summary["alpha_speed"] = summary["stats"].get("alpha_speed", [])
    if "warnings" in f.attrs:   # (not in an output written before they were stored)
        summary["warnings"] = [w for w in str(f.attrs["warnings"]).split("\n") if w]
    if "estimated_error" in f.attrs:
        summary["estimated_error"] = float(f.attrs["estimated_error"])
        summary["estimated_error_window"] = float(f.attrs["estimated_error_window"])
    if layout.STATISTICS_ERROR in f:
        group = f[layout.STATISTICS_ERROR]
        names = [k[:-len("_sampling_ci95")] for k in group if k.endswith("_sampling_ci95")]
        summary["estimated_statistics"] = {
            "window": float(f.attrs["estimated_statistics_window"]), "note": str(f.attrs["estimated_statistics_note"]),
            **{name: {"error": group[name][()].tolist(), "sampling_ci95": group[f"{name}_sampling_ci95"][()].tolist(),
                      "model": group[f"{name}_model"][()].tolist(),
                      "reduced_ci95": group[f"{name}_window_reduced_ci95"][()].tolist(),
                      "rich_ci95": group[f"{name}_window_rich_ci95"][()].tolist()} for name in sorted(names)}}
    if f.attrs.get("method") == "rom":
        summary["final_state"] = [f[layout.REDUCED_Q][-1].tolist(), f[layout.REDUCED_QDOT][-1].tolist()]
    return summary


def _run_reduced(scene, model, path, settings, timings, say, comm, resume, ident, basis_stats, estimator=None,
                 options=None) -> dict:
    """Rank 0 integrates and writes; the others wait and learn the outcome. `options`: options_read."""
    world = comm.tompi4py()
    summary, failure, unexpected, sent = {}, None, [], 0
    remote = RemoteStop(world) if world.size > 1 and world.rank == 0 else None
    if world.rank == 0:
        try:
            summary = run_case(scene, model, path, say=say, resume=resume, ident=ident, extra_stats=basis_stats,
                               ranks=world.size, timings=timings, estimator=estimator, remote=remote, options=options)
        except DbfError as exc:
            failure = (type(exc).__name__, str(exc))
        except BaseException as exc:   # a bug, an h5py error no write foresaw: every rank raises it (from_rank0;
            unexpected.append(exc)     # red team: it left the other ranks in _wait_telling for ever)
    # The other ranks: a signal while rank 0 runs is sent to it (RemoteStop). Once rank 0's run has
    # ended, the outcome is its: a signal on any rank is not acted on until every rank knows it (red
    # team: the command's handler, taking it here, said "before the integration began; nothing was
    # written" of a finished output, and on 2 ranks waited 10 s and aborted)
    with _interrupt_on_sigterm(None):
        if world.rank == 0:
            wait_for_rank0(world)
        else:
            sent = _wait_telling(world)
        sent = world.reduce(sent, root=0)
        if remote is not None:
            remote.drain(sent)
        failure = from_rank0(world, failure, unexpected)
        summary = world.bcast(summary if not failure else None, root=0)
    if failure:
        kinds = {kind.__name__: kind for kind in (InputError, Unresumable, SolverError, Interrupted)}
        raise kinds.get(failure[0], DbfError)(failure[1])
    TERMINATION.finished = True
    return summary


# A stop's advice where the run can be finished from its checkpoint (_left_behind rewrites it where none
# was written yet)
RESUME_ADVICE = "rerun with --resume to finish from the last checkpoint"


def run_case(scene: Scene, model: ReducedModel, path: str, *, say=None, resume: bool = False, ident=None,
             extra_stats=None, ranks: int = 1, timings=None, estimator=None, keep: bool = True,
             remote: RemoteStop | None = None, options: tuple | None = None) -> dict:
    """Integrate a reduced model on this rank alone and write the run's output to `path` (rank 0 of
    a run, or any rank of a sweep). Checkpoints every [output] checkpoint_dt; SIGTERM checkpoints
    and stops (errors.Interrupted); with resume, continues from a valid checkpoint. With estimator =
    (the richer reduced model, or the tolerance mode's calibration Estimate, or why there is none;
    window or None; the statistics window or None; the second richer model or None), the output carries the a-posteriori estimate (accuracy.py). Returns the
    summary with the final state and excitation phase (for continuation). keep False (a sweep's
    case without keep_outputs): the samples go to path.partial for the checkpoints alone, and the
    finished run writes no output (finish). `remote`: how rank 0 of a run hears of a termination
    signal on another rank during the integration. `options` (a run's, options_read; None in a sweep's
    case): the output stores a warning for each of the command's PETSc options no solver read (finish)."""
    settings, output = scene.integrator_settings(), scene.output()
    timings = {} if timings is None else timings
    checkpoint = Checkpoint(f"{path}.checkpoint", ident or {})
    done = finished_output(path, ident, scene) if resume else None
    if done is not None:   # a sweep's case that finished before its record was written
        _say(say, f"{path} is already complete for this case: nothing to resume")
        if options:   # (a run's: read by the run that wrote it, whose stored warnings name those no solver read)
            mark_options_read(options[0])
        return done
    writer = recorder = stepper = None
    try:
        state = checkpoint.read() if resume else None
        if resume:
            _say(say, f"resuming from the checkpoint at t = {float(state['t']):.6g} s" if state else
                 "no usable checkpoint: starting from t = 0")
        field = model.field.positions.size if model.field is not None else 0
        needed = output_bytes(settings.sample_times.size - (int(state["samples"]) if state else 0),
                              model.constraints.count * model.constraints.dimension, model.probe_B.shape[0],
                              model.size, output.snapshots, field)
        check_free_space(path, needed + 8.0 * (2 * model.size + 64))   # the output and its checkpoint
        writer = (_reopen(path, state) if state else
                  OutputWriter(path, model.constraints.shape, model.probe_sample_shape, model.size))
        recorder = ReducedRecorder(writer, model, snapshot_samples(output.snapshots, settings.sample_times))
        if state:
            recorder.restore(state)
        stepper = Checkpointing(recorder, checkpoint, output.checkpoint_dt, state, output.checkpoint_wall, remote)
        _say(say, f"integrating to t = {settings.t_end:g} s with ARKIMEX {settings.scheme} "
                  f"(contact {settings.contact}, {'adaptive' if settings.adaptive else 'fixed'} step)")
        t = time.perf_counter()
        with _interrupt_on_sigterm(stepper):
            stats = integrate_reduced(model, settings, None, stepper.on_step, say, stepper.start, recorder=recorder,
                                      due=stepper.due)
        timings["integration"] = stats["time_integration"]   # a resumed run's whole, not this part
        writer.flush()   # the last samples: a write that fails is this block's error, not the estimate's
    except PETSc.Error as exc:   # before WRITE_ERRORS: petsc4py's Error is a RuntimeError
        raise SolverError(_left_behind(f"the reduced integration: {petsc_failure(exc)}; check the -rom_ options",
                                       writer, checkpoint)) from None
    except WRITE_ERRORS as exc:
        raise SolverError(_left_behind(f"cannot write {path}.partial or its checkpoint: {write_failure(exc)}",
                                       writer, checkpoint, failed_write=True)) from None
    except DbfError as exc:
        kind = Interrupted if stepper is not None and stepper.interrupted else type(exc)
        raise kind(_left_behind(str(exc), writer, checkpoint)) from None
    stats.update(extra_stats or {})
    try:
        with _stop_on_sigterm(estimator is not None, "stopped by a termination signal during the error estimates, "
                              f"after the integration; {RESUME_ADVICE}",
                              remote):
            estimate = _estimate(estimator, writer, settings, timings, say)
            long_run = _estimate_statistics(estimator, estimate, writer, model.constraints, settings, timings, say)
    except DbfError as exc:   # SIGTERM during the estimate: the samples and the last checkpoint stay
        raise type(exc)(_left_behind(str(exc), writer, checkpoint)) from None
    t = time.perf_counter()
    try:
        with _stop_on_sigterm(True, AFTER_INTEGRATION):
            snap_t, snap_w = recorder.snapshots(settings.sample_times)
            timings["snapshots"] = time.perf_counter() - t
            summary = finish(scene, recorder, stats, timings, ranks, "rom", model.field_points, snap_t, snap_w, model,
                             {**(estimate.attrs() if estimate else {}), **(long_run.attrs() if long_run else {})},
                             long_run.datasets(layout.STATISTICS_ERROR) if long_run else None, checkpoint, keep,
                             options)
            checkpoint.remove()
    except Interrupted as exc:
        raise Interrupted(_left_behind(str(exc), writer, checkpoint)) from None
    except WRITE_ERRORS as exc:   # the last samples' flush (a full disk); finish's own writes say theirs
        raise SolverError(_left_behind(f"cannot write {path}.partial or its checkpoint: {write_failure(exc)}",
                                       writer, checkpoint, failed_write=True)) from None
    if estimate:
        summary["estimated_error"], summary["estimated_error_window"] = estimate.value, estimate.window
    if long_run:
        summary["estimated_statistics"] = long_run.summary()
        for line in long_run.lines({k: np.asarray(v) for k, v in summary["constraint_stats"].items()}):
            _say(say, line)
    summary["final_state"] = [recorder.final[0].tolist(), recorder.final[1].tolist()]
    _say(say, f"done: {stats['steps']} steps ({stats['rejected_steps']} rejected, {stats['snes_failures']} Newton "
              f"failures) in {timings['integration']:.2f} s; wrote {path}")
    return summary


# A termination signal after the integration and its estimates, before the output is written (the
# samples' statistics, the snapshots): red team, the command's own handler said "before the
# integration began; nothing was written" while the .partial and the checkpoint stayed.
AFTER_INTEGRATION = (f"stopped by a termination signal after the integration, before its output was written; "
                     f"{RESUME_ADVICE}")


def _estimate(estimator, writer, settings, timings: dict, say):
    """Rank 0: the a-posteriori estimate of the samples just written (reading back only the window),
    or None without an estimator. Not collective."""
    if estimator is None:
        return None
    rich, window, second = estimator[0], estimator[1], estimator[3] if len(estimator) > 3 else None
    times = writer.series_data(layout.TIME)
    if isinstance(rich, str):   # why there is no richer model: said like an estimate, not only stored
        estimate = Estimate(np.nan, 0.0, 0.0, rich)
        _say(say, estimate.line())
        return estimate
    contact = _first_contact(writer, times)
    end = estimate_window(times, contact, settings.t_end, window)
    k = int(np.searchsorted(times, end * (1 + 1e-12), side="right"))
    writer.flush()
    w = writer.series[layout.CONSTRAINT_DISPLACEMENT][:k]
    if isinstance(rich, Estimate):   # the tolerance mode's calibration: its richer run is reused
        estimate = reused_estimate(rich, times[:k], w)
    else:
        estimate = nested_estimate(rich, settings, times[:k], w, end, second)
    estimate = blind_to_contact(estimate, contact)
    timings["estimate"] = estimate.seconds
    _say(say, estimate.line())
    return estimate


def _estimate_statistics(estimator, estimate, writer, constraints, settings, timings: dict, say=None):
    """Rank 0: the statistics' errors of a long run (accuracy.is_long: t_end beyond STATISTICS_WINDOWS
    times the pointwise window), or None (a short run, no richer model, the tolerance mode's reused
    calibration). Reads the run's constraint samples back a batch at a time. Not collective."""
    if estimator is None or estimate is None or isinstance(estimator[0], (str, Estimate)) or \
            not is_long(settings.t_end, estimate.window):
        if estimator is not None and estimate is not None and isinstance(estimator[0], Estimate) and \
                is_long(settings.t_end, estimate.window):   # a long run that might expect them (day-one user)
            _say(say, "statistics errors: none in the tolerance mode (it reuses its calibration run over the "
                      "estimate window); run the picked modes and rtol without [basis] tolerance for them")
        return None
    writer.flush()
    times = writer.series_data(layout.TIME)
    names = (layout.TIME, layout.CONSTRAINT_DISPLACEMENT, layout.CONSTRAINT_VELOCITY, layout.CONSTRAINT_FORCE)

    def read(lo, hi):   # a batch of the samples from the file: memory stays flat however long the run
        return tuple(writer.series[name][lo:hi] for name in names)

    laws = constraints.laws if constraints.dimension == 2 else None
    end = statistics_window(settings.t_end, settings.sample_dt, estimator[2])
    result = statistics_estimate(estimator[0], settings, read, times, end, laws)
    timings["estimate_statistics"] = result.seconds
    return result


def _first_contact(writer, times: np.ndarray, block: int = 1 << 16):
    """The first impact in a written output (accuracy.first_contact; read in blocks)."""
    writer.flush()
    series = writer.series[layout.CONSTRAINT_FORCE_PEAK]
    for lo in range(0, times.size, block):
        t = first_contact(times[lo:lo + block], series[lo:lo + block], None if lo == 0 else series[lo - 1])
        if t is not None:
            return t
    return None


def _reopen(path: str, state: dict) -> OutputWriter:
    if not os.path.isfile(f"{path}.partial"):   # moved or removed, or the run finished into `path`
        raise Unresumable(f"{path}.partial, the samples its checkpoint continues, is missing: the checkpoint cannot "
                          f"be resumed; rerun without --resume") from None
    try:
        return OutputWriter.reopen(path, int(state["samples"]), state.get("samples_sha256"))
    except (OSError, KeyError, ValueError, RuntimeError) as e:   # RuntimeError: metadata a failed write damaged
        raise Unresumable(f"{path}.partial cannot be resumed ({str(e).splitlines()[0]}); rerun without "
                          f"--resume") from None


def _left_behind(message: str, writer, checkpoint: Checkpoint | None, failed_write: bool = False) -> str:
    """Close the output after a failure (park it after a failed write: OutputWriter.abort); the
    message says what is left behind. A run that failed before its second sample leaves nothing (its
    one sample is the initial state)."""
    if writer is None:
        return message
    if not (checkpoint is not None and os.path.exists(checkpoint.path)):
        # red team: a run too short for a checkpoint, stopped in its estimates, was told to finish "from the
        # last checkpoint"; there is none, and a --resume runs it again from the start
        message = message.replace(RESUME_ADVICE, "rerun it (it was too short for a checkpoint: --resume starts it over)")
    samples = writer.count + writer.pending
    writer.abort(failed_write)
    if samples <= 1 and not (checkpoint is not None and os.path.exists(checkpoint.path)):
        if os.path.exists(writer.partial):   # parked, it is never written again (the command ends in os._exit)
            os.remove(writer.partial)
        return message
    if checkpoint is not None and os.path.exists(checkpoint.path):
        return f"{message} (samples so far in {writer.partial}; checkpoint in {checkpoint.path})"
    return f"{message} (the samples up to the failure are in {writer.partial})"


class Checkpointing:
    """Rank 0's per-step hook of a reduced run: a checkpoint every checkpoint_dt of simulated time (one
    due sooner than `min_wall` s of wall time after the start or the last is skipped:
    OutputSettings.checkpoint_wall) and when SIGTERM asked for one, then a stop with the advice to
    resume."""

    def __init__(self, recorder: ReducedRecorder, checkpoint: Checkpoint, interval: float, state: dict | None,
                 min_wall: float = 0.0, remote: RemoteStop | None = None):
        self.recorder, self.checkpoint, self.interval, self.min_wall = recorder, checkpoint, interval, min_wall
        self.remote = remote
        self.interrupted = False
        self.start = None
        self.next = interval
        self.base = {"rejected": 0, "snes_failures": 0, "wall": 0.0, "newton_iterations": 0}
        self.base_c = None   # the C callbacks' counters before this part (rom_integrator.C_COUNTERS)
        if state:
            self.base = {name: float(state[name]) for name in self.base}
            self.base_c = np.array(state["c_counters"]) if "c_counters" in state else None
            self.start = {"t": float(state["t"]), "dt": float(state["dt"]), "steps": int(state["steps"]),
                          "next_sample": int(state["samples"]), "q": np.array(state["q"]),
                          "p": np.array(state["p"]), "rejected": int(self.base["rejected"]),
                          "snes_failures": int(self.base["snes_failures"]), "wall": self.base["wall"],
                          "newton_iterations": int(self.base["newton_iterations"]), "c_counters": self.base_c}
            self.next = float(state["t"]) + interval
        self.clock = self.saved = time.perf_counter()

    def due(self) -> float:
        """The simulated time from which on_step has work to do (the integrator may skip it before).
        Called after every step: another rank's termination signal is looked for here (RemoteStop)."""
        if not self.interrupted and self.remote is not None and self.remote.poll():
            self.interrupted = True
        return -np.inf if self.interrupted else self.next

    def on_step(self, ts, t, q, p):
        """After a step (the recorder has taken its statistics): a checkpoint when due or asked for."""
        if not self.interrupted and self.remote is not None and self.remote.poll():
            self.interrupted = True
        due = t >= self.next
        if due:
            self.next = t + self.interval
        if self.interrupted or (due and time.perf_counter() - self.saved >= self.min_wall):
            self.save(ts, t, q, p)
        if self.interrupted:
            return (f"stopped by a termination signal at t = {t:.6g} s; the run is checkpointed: "
                    f"rerun with --resume to continue")
        return None

    def save(self, ts, t, q, p) -> None:
        self.recorder.writer.flush()
        wall = self.base["wall"] + time.perf_counter() - self.clock
        counts = c_counters(ts)
        if counts is not None and self.base_c is not None:
            counts = counts + self.base_c
        self.checkpoint.write({"t": t, "dt": ts.getTimeStep(), "steps": ts.getStepNumber(), "q": q, "p": p,
                               "samples": self.recorder.writer.count,
                               "samples_sha256": self.recorder.writer.digest(),
                               "rejected": self.base["rejected"] + ts.getStepRejections(),
                               "snes_failures": self.base["snes_failures"] + ts.getSNESFailures(), "wall": wall,
                               "newton_iterations": self.base["newton_iterations"] + ts.getSNESIterations(),
                               **({} if counts is None else {"c_counters": counts}), **self.recorder.state()})
        self.saved = time.perf_counter()


@contextlib.contextmanager
def _on_sigterm(handler):
    """SIGTERM (and SIGINT, Ctrl-C: errors.termination_signals) calls handler(signum, frame) while
    the block runs (None: leave it as it is); the previous handlers come back after. Not in the main
    thread, signals are left alone."""
    previous = {}
    if handler is not None:
        try:
            for signum in termination_signals():
                previous[signum] = signal.signal(signum, handler)
        except ValueError:  # not the main thread
            pass
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def _interrupt_on_sigterm(stepper):
    """While integrating, SIGTERM (a batch system's time limit) on any rank asks rank 0 to checkpoint
    at the end of the current step and stop: rank 0's own sets `stepper`'s flag, another rank's
    errors.TERMINATION, which reaches rank 0 at its next control point (a full-order run's) or as a
    message (RemoteStop: a reduced run's, integrated by rank 0 alone)."""
    TERMINATION.requested = False

    def handler(signum, frame):
        TERMINATION.requested = True
        if stepper is not None:
            stepper.interrupted = True

    return _on_sigterm(handler)


STOP_TAG = 7301     # a termination signal on a rank other than 0, sent to rank 0 (RemoteStop)


class RemoteStop:
    """Rank 0 of a reduced run integrates alone while the others wait (_run_reduced, _wait_telling):
    a termination signal on another rank reaches it as a message, looked for at most every POLL s
    of the integration's wall time (Checkpointing.due and on_step); rank 0 then checkpoints and stops
    as at its own signal. Every message sent is received by the end (drain): none is left in MPI."""

    POLL = 0.05

    def __init__(self, world):
        self.world, self.received, self.last = world, 0, -float("inf")

    def poll(self) -> bool:
        now = time.perf_counter()
        if now - self.last < self.POLL:
            return False
        self.last = now
        got = False
        while self.world.iprobe(source=MPI.ANY_SOURCE, tag=STOP_TAG):
            self.world.recv(source=MPI.ANY_SOURCE, tag=STOP_TAG)
            self.received, got = self.received + 1, True
        return got

    def drain(self, sent: int) -> None:
        """Receive the messages still on their way (`sent`: how many the other ranks sent in all)."""
        while self.received < sent:
            self.world.recv(source=MPI.ANY_SOURCE, tag=STOP_TAG)
            self.received += 1


def _wait_telling(world) -> int:
    """A rank other than 0 while rank 0 integrates alone: errors.wait_for_rank0, telling rank 0 of a
    termination signal received meanwhile (RemoteStop). Returns how many messages it sent (0 or 1)."""
    request, sent, message = world.Ibarrier(), 0, None
    while not request.Test():
        if TERMINATION.requested and not sent:
            message, sent = world.isend(True, dest=0, tag=STOP_TAG), 1
        time.sleep(0.02)
    if message is not None:
        message.wait()
    return sent


@contextlib.contextmanager
def _stop_on_sigterm(active: bool, message: str, remote: RemoteStop | None = None):
    """While the block runs (rank 0's error estimates after its integration, when active), SIGTERM
    stops it with errors.Interrupted(message) instead of the command's message for a job that has
    not integrated yet. With `remote`, another rank's signal too: the estimates integrate a richer
    model with no hook of ours (they may cost what the run did: a long run's statistics), so an alarm
    (SIGALRM, every ALARM s of wall time, system calls restarted) looks for the message and raises
    as the signal would (red team: a SIGTERM to rank 1 alone in the estimate was not acted on)."""
    def handler(signum, frame):
        raise Interrupted(message)

    def alarm(signum, frame):
        if remote.poll():
            raise Interrupted(message)

    with _on_sigterm(handler if active else None):
        armed = previous = None
        if active and remote is not None:
            try:
                previous = signal.signal(signal.SIGALRM, alarm)
                signal.siginterrupt(signal.SIGALRM, False)
                armed = signal.setitimer(signal.ITIMER_REAL, ALARM, ALARM)
            except ValueError:  # not the main thread
                pass
        try:
            yield
        finally:
            if armed is not None:
                try:   # the timer off first: SIGALRM's default action ends the process
                    signal.setitimer(signal.ITIMER_REAL, *armed)
                finally:
                    signal.signal(signal.SIGALRM, previous)


ALARM = 0.1   # s: how often rank 0's error estimates look for another rank's termination signal


def sample_work_rate_ci95(writer, constraints) -> np.ndarray:
    """stats.batch_means_ci95 of |F_n| |v_t| at the samples, per support (2-D laws)."""
    from .stats import batch_means_ci95

    t = writer.series_data(layout.TIME)
    z, v, force = (writer.series_data(name).reshape(t.size, -1) for name in
                   (layout.CONSTRAINT_DISPLACEMENT, layout.CONSTRAINT_VELOCITY, layout.CONSTRAINT_FORCE))
    _, _, _, fn, vt, _ = constraints.laws.radial(z, v, force)
    return batch_means_ci95(t, fn * vt)


def _initial_text(init) -> str:
    if not (init.amplitude or init.velocity):
        return "at rest in relative coordinates (u = 0, u_t = 0); absolute velocity Omega'(0) r"
    if init.velocity or init.direction != (1.0, 0.0):   # a beam of two planes
        return (f"displacement {init.amplitude} m peak along (dy, dz) = ({init.direction[0]:.4g}, "
                f"{init.direction[1]:.4g}) and velocity {init.velocity} m/s peak along "
                f"({init.velocity_direction[0]:.4g}, {init.velocity_direction[1]:.4g}) in planar mode {init.mode}")
    return f"displacement {init.amplitude} m peak in reference mode {init.mode}"


def finish(scene: Scene, recorder: SampleRecorder, stats: dict, timings: dict, ranks: int, method: str,
           field, snap_t, snap_w, model: ReducedModel | None = None, extra_attrs: dict | None = None,
           extra_datasets: dict | None = None, checkpoint: Checkpoint | None = None, write: bool = True,
           options: tuple | None = None) -> dict:
    """Rank 0: write the fixed-size data and the attributes, rename the file into place (and, with
    snapshots, an XDMF file beside it for ParaView), and return the run's summary. `field` is the
    PointValues the snapshots are taken at; `checkpoint` the run's (a failed write names it). With
    write False (a sweep's case whose output is not kept), the summary only: the .partial is closed
    and removed, nothing is written to `path`."""
    timings["total"] = sum(timings.values())
    constraints, output, init = recorder.constraints, scene.output(), scene.initial()
    snap_w = np.asarray(snap_w, dtype=float).reshape(np.size(snap_t), field.count)
    writer = recorder.writer
    constraint_stats = recorder.impacts.result()
    if recorder.planar:   # supports of two directions: the work rate's confidence interval from the samples
        from .stats import wear_volume

        constraint_stats["work_rate_ci95"] = sample_work_rate_ci95(writer, constraints)
        t = writer.series_data(layout.TIME)
        constraint_stats["wear_volume"], constraint_stats["wear_volume_ci95"] = wear_volume(
            [c.wear_coefficient for c in scene.constraints], float(t[-1] - t[0]) if t.size else 0.0,
            constraint_stats["work_rate"], constraint_stats["work_rate_ci95"])
    probe_peak = np.abs(writer.series_data(layout.PROBE_DISPLACEMENT)).max(axis=0, initial=0.0)
    # Hunt-Crossley's largest alpha |v| in contact, also in the output's solver_stats (a finished output's
    # summary, read back by --resume, warns as the run did)
    stats = {**stats, "alpha_speed": recorder.alpha_speed.tolist()}
    summary = {"path": writer.path, "stats": stats, "timings": timings, "probe_peak": probe_peak.tolist(),
               "constraint_stats": {k: v.tolist() for k, v in constraint_stats.items()},
               "alpha_speed": stats["alpha_speed"]}
    # what the run warned (run.run records it), what it warns of this result once the output is complete
    # (result_warnings) and of the command's PETSc options no solver read (unused_option_lines, `options`):
    # stored, so that `info` and a --resume of the output show them
    summary["warnings"] = list(dict.fromkeys(recorded() + result_warnings(summary, scene.constraints, method,
                                                                            scene.integrator_settings())
                                             + unused_option_lines(options)))
    if not write:   # some 80 datasets with their units, 50 ms a case, written to be removed (sweep._run_one)
        writer.discard()
        return summary
    geometry = field.geometry()
    datasets = {layout.CONSTRAINT_POSITION: constraints.positions,
                layout.CONSTRAINT_CLEARANCE_MINUS: constraints.clearance_minus,
                layout.CONSTRAINT_CLEARANCE_PLUS: constraints.clearance_plus,
                layout.PROBE_POSITION: np.asarray(output.probes, dtype=float),
                layout.SNAPSHOT_TIME: snap_t, layout.SNAPSHOT_X: field.positions, layout.SNAPSHOT_W: snap_w,
                layout.PROBE_PEAK: probe_peak, **geometry_datasets(geometry, "snapshots"),
                **{f"{layout.CONSTRAINT_STATS}/{k}": v for k, v in constraint_stats.items()}}
    if snap_t.size:
        datasets.update(node_vectors(geometry, snap_w, "snapshots"))
    datasets.update(extra_datasets or {})
    attrs = {"field_kind": geometry[0], **cells_attrs(field), "warnings": "\n".join(summary["warnings"]),
             **(extra_attrs or {})}
    if model is not None:
        info = model.basis_info
        datasets.update({layout.BASIS_OMEGA: info["omega"], layout.BASIS_ENRICHMENT_OMEGA: info["enrichment_omega"],
                         layout.BASIS_DBF_K: info["dbf_k"],
                         layout.BASIS_FLEXIBILITY_CAPTURED: info.get("flexibility_captured", np.zeros(0)),
                         layout.BASIS_FLEXIBILITY_EXACT: info.get("flexibility_exact", np.zeros(0)),
                         layout.REDUCED_M: model.M, layout.REDUCED_K: model.K,
                         layout.REDUCED_B: model.B, layout.REDUCED_D: model.damping})
        attrs["basis_enrichment"] = info["enrichment"]
        for key in ("mass_orthonormality_defect", "mode_coupling_defect"):
            if key in info:
                attrs[f"basis_{key}"] = float(info[key])
        if "turned_in_span" in info:
            attrs["basis_turned_in_span"] = bool(info["turned_in_span"])
        if info.get("complex_modes"):   # a gyroscopic basis: Re and Im columns of each complex mode and DBF
            attrs["basis_complex_modes"] = int(info["complex_modes"])
            attrs["reduced_form"] = info.get("form", "second_order")
    # The disk may have filled since the run began: a final write that fails leaves HDF5's metadata
    # damaged (the .partial then cannot be resumed), so its room is checked first
    needed = sum(np.asarray(v).nbytes for v in datasets.values()) + snap_t.size * SNAPSHOT_OVERHEAD_BYTES + 2**16
    free = free_bytes(os.path.dirname(os.path.abspath(writer.partial)))
    if free < 1.1 * needed + 2**20:
        resume = "rerun with --resume" if checkpoint is not None else "rerun"
        raise SolverError(_left_behind(f"cannot finish {writer.path}: its final data needs about "
                                       f"{needed / 2**20:.3g} MiB and its disk has {free / 2**20:.3g} MiB free; free "
                                       f"some space, then {resume}", writer, checkpoint)) from None
    # A termination signal while the fixed data is written waits for it (a few seconds): stopped
    # halfway, the .partial held datasets a resume would write again (red team). A write that fails
    # all the same is one line; h5py reports some as KeyError or ValueError ("Unable to ...").
    deferred = []
    with _on_sigterm(lambda signum, frame: deferred.append(signum)):
        _write_output(writer, datasets, constraint_stats, scene, method, stats, timings, ranks, init, attrs,
                      checkpoint, snap_t, geometry)
    if deferred:
        print(f"dbf-hpc: warning: a termination signal came while {writer.path} was written; it was finished first",
              file=sys.stderr, flush=True)
    return summary


def _write_output(writer, datasets, constraint_stats, scene, method, stats, timings, ranks, init, attrs, checkpoint,
                  snap_t, geometry) -> None:
    """Rank 0, finish's writes: the fixed data and attributes, the rename into place, and the ParaView
    file beside it (finish defers termination signals for all of it: a signal between the rename and
    the ParaView file left a complete output without its sidecar, beside its checkpoint; red team)."""
    try:
        _write_fixed(writer, datasets, constraint_stats, scene, method, stats, timings, ranks, init, attrs,
                     checkpoint.identity if checkpoint is not None else None)
    except (*WRITE_ERRORS, KeyError, ValueError) as exc:
        if isinstance(exc, (KeyError, ValueError)) and "Unable to" not in str(exc):
            raise
        resume = " with --resume (it says if the failed write damaged the .partial)" if checkpoint is not None else ""
        raise SolverError(_left_behind(f"cannot finish {writer.path}: {write_failure(exc)}; free some space, then "
                                       f"rerun{resume}", writer, checkpoint, failed_write=True)) from None
    if snap_t.size:
        sidecar = xdmf.sidecar(writer.path)
        try:
            xdmf.write(sidecar, writer.path, "snapshots", geometry[0], geometry[1].shape[0], snap_t,
                       cells=geometry[4], cell_type=geometry[5])
        except (OSError, DbfError) as exc:   # errors.replacing: a DbfError naming the file and the cause
            # Red team (a disk full at the sidecar): the failure read "cannot write OUT.xdmf" only, and the
            # checkpoint stayed beside the finished output, so --resume refused ("OUT.h5.partial cannot be
            # resumed"). The output is complete: nothing is left to resume.
            if checkpoint is not None:
                checkpoint.remove()
            cause = write_failure(exc) if isinstance(exc, OSError) else str(exc).rsplit(": ", 1)[-1]
            raise SolverError(f"wrote {writer.path}, but not its ParaView file {sidecar}: {cause}; free some "
                              f"space and rerun for it") from None


def _write_fixed(writer, datasets, constraint_stats, scene, method, stats, timings, ranks, init, attrs,
                 ident=None) -> None:
    writer.finish(
        datasets=datasets,
        dataset_attrs={f"{layout.CONSTRAINT_STATS}/{k}": {"unit": UNITS[k], "description": DESCRIPTIONS[k]}
                       for k in constraint_stats},
        attrs={"scene": scene.text, "scene_path": os.path.abspath(scene.path), "method": method,
               "scene_effective": json.dumps(scene.effective(), default=str),
               "petsc_version": ".".join(map(str, PETSc.Sys.getVersion())),
               "slepc_version": ".".join(map(str, SLEPc.Sys.getVersion())),
               "mpi_ranks": ranks, "solver_stats": json.dumps(stats), "wall_times": json.dumps(timings),
               "initial_state": _initial_text(init),
               **({"run_identity": json.dumps(ident, sort_keys=True)} if ident else {}),
               **attrs})


class FullCheckpointing:
    """Rank 0's control of a full-order run (fom_integrator.integrate_full's `control`): a checkpoint
    every checkpoint_dt of simulated time (one due sooner than `min_wall` s of wall time after the
    start or the last is skipped: OutputSettings.checkpoint_wall) and when SIGTERM asked for one, then
    a stop with the advice to resume. A checkpoint holds the distributed state gathered on rank 0
    (the rank count is part of the run's identity), the recorder's statistics and the snapshots taken
    so far."""

    def __init__(self, recorder: SampleRecorder, checkpoint: Checkpoint, interval: float, state: dict | None,
                 snaps: dict, min_wall: float = 0.0, save_at: int | None = None):
        self.recorder, self.checkpoint, self.interval, self.snaps = recorder, checkpoint, interval, snaps
        self.min_wall, self.save_at = min_wall, save_at
        self.interrupted = False
        self.next = float(state["next_checkpoint"]) if state else interval
        self.wall = float(state["wall"]) if state else 0.0
        self.clock = self.saved = time.perf_counter()

    def at(self, t: float, steps: int):
        if self.interrupted:
            return "save and stop"
        if self.save_at is not None and steps >= self.save_at:
            # the integration's end, before the error estimate (which integrates again, up to 4 times as
            # long): a stop in the estimate resumes from here and only redoes the estimate (red team: it
            # redid the integration from the last checkpoint on)
            return "save"
        if t >= self.next:
            self.next = t + self.interval
            if time.perf_counter() - self.saved >= self.min_wall:
                return "save"
        return None

    def save(self, state: dict) -> None:
        self.recorder.writer.flush()
        index = sorted(self.snaps)
        width = len(self.snaps[index[0]]) if index else 0
        self.checkpoint.write({**state, "samples": self.recorder.writer.count,
                               "samples_sha256": self.recorder.writer.digest(), "next_checkpoint": self.next,
                               "wall": self.wall + time.perf_counter() - self.clock,
                               "snapshot_index": np.array(index, dtype=np.int64),
                               "snapshot_w": np.array([self.snaps[i] for i in index]).reshape(len(index), width),
                               **self.recorder.state()})
        self.saved = time.perf_counter()

    def stop_message(self, t: float) -> str:
        return f"stopped by a termination signal at t = {t:.6g} s; the run is checkpointed: rerun with --resume to continue"


_RESUME_SCALARS = ("t", "steps", "next_sample", "lam", "pushing", "counters")


class _EstimateControl:
    """Rank 0's control of the full-order estimate's run (integrate_full's `control`): no checkpoints;
    SIGTERM stops it at the next control point, on every rank."""

    interrupted = False

    def at(self, t: float, steps: int):
        return "save and stop" if self.interrupted else None

    def save(self, state: dict) -> None:
        pass

    def stop_message(self, t: float) -> str:
        return f"stopped by a termination signal during the error estimate, after the integration; {RESUME_ADVICE}"


def _full_estimate(scene: Scene, fom, settings, observation, recorder, timings: dict, say) -> Estimate | None:
    """A full-order run's a-posteriori estimate of its time step's error (docs/full-order.md): the same
    model over the estimate's window (accuracy.estimate_window: twice the first contact) at a step RICH_STEP
    times shorter (as a reduced run's richer run of fixed steps), compared at the constraints
    as a reduced run's estimate is (accuracy.relative_difference). The mesh's own error is not in it.
    None with [basis] estimate = false or without constraints. Collective; the Estimate on rank 0
    (None elsewhere)."""
    chosen = scene.estimate_settings()
    if not chosen.enabled or not fom.constraints.count:
        return None
    world = fom.comm.tompi4py()
    times = contact = end = None
    if world.rank == 0:
        try:   # the samples just written, read back; a failure must not leave the others in the bcast
            times = recorder.writer.series_data(layout.TIME)
            contact = _first_contact(recorder.writer, times)
            end = estimate_window(times, contact, settings.t_end, chosen.window)
        except Exception as exc:
            end = f"cannot read the run's samples back: {exc}"
    end = world.bcast(end, root=0)
    if isinstance(end, str):
        raise SolverError(end)
    rich = dataclasses.replace(settings, t_end=end, dt=settings.dt / RICH_STEP)   # the full order's step is fixed
    blocks, rich_times = [], []

    def on_block(steps, samples):
        if samples[0].size:
            rich_times.append(samples[0])
            blocks.append(observation.block_totals(*samples[:3])[0])

    control = _EstimateControl() if world.rank == 0 else None
    _say(say, f"estimating the step's error: the same model to t = {end:g} s at a step of {rich.dt:g} s")
    start = time.perf_counter()
    failure = None
    try:
        with _interrupt_on_sigterm(control):
            integrate_full(fom, rich, observation.rows, on_block if world.rank == 0 else None, say=say,
                           control=control)
    except Interrupted:   # a SolverError too, but the run's to stop (every rank: control's word)
        raise
    except SolverError as exc:   # every rank's (integrate_full's errors are collective)
        failure = f"the run at a fixed step of {rich.dt:g} s failed: {exc}"
    seconds = time.perf_counter() - start

    def judged() -> Estimate:   # rank 0: its samples against the richer run's
        note = f"against the same model at a fixed step of {rich.dt:g} s: the step's error, not the mesh's"
        kinds = constraint_kinds(fom.operators, fom.constraints)
        note += KINDS_NOTE if kinds else ""
        k = int(np.searchsorted(times, end * (1 + 1e-12), side="right"))
        if failure:
            estimate = Estimate(np.nan, end, seconds, failure)
        elif sum(b.size for b in rich_times) != k or not np.allclose(np.concatenate(rich_times), times[:k], rtol=0,
                                                                      atol=1e-9 * max(end, 1e-300)):
            estimate = Estimate(np.nan, end, seconds, "the run at the shorter step is not sampled alike")
        else:
            recorder.writer.flush()
            w = recorder.writer.series[layout.CONSTRAINT_DISPLACEMENT][:k]
            estimate = Estimate(relative_difference(w, np.concatenate(blocks), kinds), end, seconds, note,
                                kinds=kinds)
        estimate = blind_to_contact(estimate, contact)
        timings["estimate"] = seconds
        _say(say, estimate.line())
        return estimate

    estimate, unexpected = None, []
    if world.rank == 0:
        try:
            estimate = judged()
        except BaseException as exc:   # (a bug, a failed flush) every rank raises it: they go on to a bcast
            unexpected.append(exc)
    from_rank0(world, None, unexpected)
    return estimate


def _run_full(scene: Scene, fom, path: str, settings, timings: dict, say, resume: bool,
              request: str | None = None, digests: dict | None = None) -> dict:
    """The full-order reference on fom.comm, every rank integrating its share of the state; rank 0
    writes the same layout as a reduced run (no basis/ or reduced/ groups) and the checkpoints."""
    world = fom.comm.tompi4py()
    fom.damping_matrix()  # modal damping and bad -full_ options are errors before any file is opened
    full_options()
    constraints, observation = fom.constraints, Observation(fom)
    support, field = fom.support, fom.operators.field_map()
    output = scene.output()
    snap_index = snapshot_samples(output.snapshots, settings.sample_times)
    field_support = fom.field_support()
    checkpoint = Checkpoint(f"{path}.checkpoint", run_identity(scene, {"fingerprint": fom.fingerprint}, fom.comm,
                                                                "full", request=request, digests=digests))
    recorder = control = state = None
    snaps, opened, unexpected = {}, None, []
    if world.rank == 0:
        try:
            state = checkpoint.read() if resume else None
            if resume:
                _say(say, f"resuming from the checkpoint at t = {float(state['t']):.6g} s" if state else
                     "no usable checkpoint: starting from t = 0")
            samples_left = settings.sample_times.size - (int(state["samples"]) if state else 0)
            check_free_space(path, output_bytes(samples_left, constraints.count * constraints.dimension,
                                                fom.probes.count, 0,
                                                output.snapshots, field.count) + 8.0 * 3 * fom.size)
            writer = (_reopen(path, state) if state else
                      OutputWriter(path, constraints.shape, fom.probes.shape, 0))
            recorder = FullRecorder(writer, constraints, observation)
            if state:
                recorder.restore(state)
                snaps = {int(i): np.array(w) for i, w in zip(state["snapshot_index"], state["snapshot_w"])}
            estimated = scene.estimate_settings().enabled and constraints.count
            control = FullCheckpointing(recorder, checkpoint, output.checkpoint_dt, state, snaps,
                                        output.checkpoint_wall,
                                        step_count(settings.t_end, settings.dt)[0] if estimated else None)
        except DbfError as exc:
            opened = (type(exc).__name__, str(exc))
        except WRITE_ERRORS as exc:
            opened = ("SolverError", f"cannot write {path}.partial: {write_failure(exc)}")
        except BaseException as exc:   # (a bug) every rank raises it: from_rank0
            unexpected.append(exc)
    opened = from_rank0(world, opened, unexpected)  # every rank stops if rank 0 cannot write or resume
    if opened:
        raise (InputError if opened[0] == "InputError" else SolverError)(opened[1])
    scalars = world.bcast({k: state[k] for k in _RESUME_SCALARS} if state else None, root=0)
    resume_state = None if scalars is None else {**scalars, **({k: state[k] for k in ("X", "V", "A")} if state else {})}

    def snapshot(i, values):
        if values is not None:
            snaps[i] = field.take(values) + field_support * support.value(settings.sample_times[i])

    _say(say, f"integrating the full-order model to t = {settings.t_end:g} s with generalized-alpha (one "
              f"factorization, contact condensed on {constraints.count * constraints.dimension} DOF(s), step "
              f"{settings.dt:g} s)")
    t = time.perf_counter()
    try:
        with _interrupt_on_sigterm(control):
            stats = integrate_full(fom, settings, observation.rows, recorder.block if recorder else None, snap_index,
                                   snapshot, say, control=control, resume=resume_state)
    except PETSc.Error as exc:   # an option PETSc refused in the set-up; the ranks fail alike
        raise SolverError(_left_behind(f"the full-order integration: {petsc_failure(exc)}; check the -full_ "
                                       f"options", recorder.writer if recorder else None, checkpoint)) from None
    except DbfError as exc:   # a failed write (WriteFailed) parks the .partial: closing it could crash HDF5
        raise type(exc)(_left_behind(str(exc), recorder.writer if recorder else None, checkpoint,
                                     failed_write=isinstance(exc, WriteFailed))) from None
    timings["integration"] = time.perf_counter() - t + (control.wall if control else 0.0)
    try:
        estimate = _full_estimate(scene, fom, settings, observation, recorder, timings, say)
    except DbfError as exc:   # SIGTERM during the estimate: the samples and the last checkpoint stay
        raise type(exc)(_left_behind(str(exc), recorder.writer if recorder else None, checkpoint)) from None
    summary, failure, unexpected = {}, None, []
    options = options_read(fom.comm)   # every rank is done with its solvers
    if world.rank == 0:   # a failed or stopped write is every rank's error (they waited in bcast for ever)
        try:
            with _stop_on_sigterm(True, AFTER_INTEGRATION):
                snap_t = settings.sample_times[sorted(snaps)] if snaps else np.zeros(0)
                snap_w = np.array([snaps[i] for i in sorted(snaps)]).reshape(snap_t.size, field.positions.size)
                summary = finish(scene, recorder, stats, timings, world.size, "full", field, snap_t, snap_w,
                                 extra_attrs=estimate.attrs() if estimate else None, checkpoint=checkpoint,
                                 options=options)
                checkpoint.remove()
            if estimate:
                summary["estimated_error"], summary["estimated_error_window"] = estimate.value, estimate.window
        except Interrupted as exc:
            failure = ("Interrupted", _left_behind(str(exc), recorder.writer, checkpoint))
        except DbfError as exc:
            failure = (type(exc).__name__, str(exc))
        except BaseException as exc:   # (a bug, an h5py error no write foresaw) every rank raises it: from_rank0
            failure = ("DbfError", type(exc).__name__)
            unexpected.append(exc)
        if failure is None:
            _say(say, f"done: {stats['steps']} steps ({stats['factorizations']} factorization(s), "
                      f"{stats['contact_steps']} steps with contact) in {timings['integration']:.2f} s; wrote "
                      f"{summary['path']}")
    with _interrupt_on_sigterm(None):   # the other ranks: a signal now is rank 0's to act on
        failure, summary = from_rank0(world, (failure, summary), unexpected)
    if failure:
        kinds = {kind.__name__: kind for kind in (InputError, Unresumable, SolverError, Interrupted)}
        raise kinds.get(failure[0], DbfError)(failure[1])
    TERMINATION.finished = True
    return summary


class _CallableModule(type(sys)):
    """`from dbf_hpc import run` gives this module, not the function: importing a package's submodule
    binds its name in the package, over the package's lazy `run` (dbf_hpc/__init__.py). Red team:
    the documented `run(scene, out)` raised "TypeError: 'module' object is not callable". Calling the
    module runs run.run; its attributes stay the module's."""

    def __call__(self, *args, **kwargs):
        return self.run(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
