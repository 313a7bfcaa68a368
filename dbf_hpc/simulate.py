"""Runs from Python, results in memory (the scene front end, run.py, streams to HDF5 instead).

    result = simulate_reduced(rom, IntegratorSettings(t_end=0.5, sample_dt=1e-3))
    result.displacement[:, j]      # total w at constraint j, m

simulate_reduced integrates on the calling rank alone (the reduced model is the same on every
rank); simulate_full is collective on the full-order model's communicator and returns the same
Result on every rank. Keep these for runs whose samples fit in memory.
"""
from __future__ import annotations

import dataclasses
import types

import numpy as np
from petsc4py import PETSc

from .errors import InputError, check_number, decided_on_rank0, warn
from .fom import FullOrderModel, Observation
from .fom_integrator import ignored_settings, integrate_full
from .output import MemoryWriter
from .petsctools import petsc_errors_as_one_line
from .recorder import FullRecorder, ReducedRecorder, Result
from .rom import ReducedModel
from .rom_integrator import integrate_reduced
from .timestepping import IntegratorSettings, sample_count


def snapshot_samples(count: int, times: np.ndarray) -> np.ndarray:
    """The indices of the samples that carry `count` evenly spaced snapshots (run.py's too): every
    sample when `count` exceeds them (snapshot_cap_warning says so)."""
    if not count:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.searchsorted(times, np.linspace(0.0, times[-1], count) - 1e-12 * times[-1]))


def snapshot_cap_warning(count: int, settings: IntegratorSettings, key: str = "[output] snapshots") -> str | None:
    """The warning for more snapshots than output samples (each snapshot is one sample, so every
    sample is taken), or None. Red team: snapshots = 50 on a run shortened to 6 samples wrote 6
    without a word. A warning, not a refusal: a scene's count is written for its own t_end, and
    shortening the run on the command line keeps every sample as a snapshot, which is right."""
    samples = sample_count(settings.t_end, settings.sample_dt)
    if count <= samples:
        return None
    return (f"{key} = {count} is more than the {samples} output samples (t_end = {settings.t_end:g} s at "
            f"sample_dt = {settings.sample_dt:g} s), the only times a snapshot is taken at: all {samples} are "
            f"snapshots; for more, reduce sample_dt")


# the lines simulate_reduced has warned before a run in this process: once each (a script's loop of runs)
_WARNED = set()


def simulate_reduced(model: ReducedModel, settings: IntegratorSettings, snapshots: int = 0, say=None) -> Result:
    """Integrate a reduced model (rom_integrator.py) and return its samples, statistics and, with
    `snapshots` > 0 and a model reduced with field=True, that many field snapshots. Warns, as `dbf-hpc
    run` does, where an adaptive run's atol lets w err by over 1 % of a clearance (or of the motion's
    scale, run.motion_reach; run.loose_atol), where a fixed step or the samples are too coarse for the
    forcing (coarse_warnings), where the forcing lies above the basis' highest reference mode
    (above_basis_warning, which the run says with its basis), and where `snapshots` exceeds the samples
    (snapshot_cap_warning): once per process and message, on rank 0 of COMM_WORLD (the model is
    replicated: a script calls this on every rank, and the line is printed once). After the integration it
    warns of the result as `dbf-hpc run` does (run.result_warnings: a stop never reached, Hunt-Crossley damping beyond its range, impacts a
    fixed step does not resolve), on rank 0 of COMM_WORLD, each call. Not collective."""
    _check_settings(settings, say, "simulate_reduced")
    if hasattr(model, "probe_sample_shape"):
        from .run import loose_atol

        loose = loose_atol(model, settings.atol) if settings.adaptive else None
        for message in [*coarse_warnings(model, settings, not settings.adaptive), above_basis_warning(model), loose]:
            if message and message not in _WARNED:
                _WARNED.add(message)
                warn(message, PETSc.COMM_WORLD)
    capped = snapshot_cap_warning(snapshots, settings, "simulate_reduced snapshots") if isinstance(snapshots, int) else None
    if capped and capped not in _WARNED:
        _WARNED.add(capped)
        warn(capped, PETSc.COMM_WORLD)
    result = integrate_samples(model, settings, snapshots, say)
    warn_result(result, model.constraints, "rom", settings, PETSc.COMM_WORLD)
    return result


def coarse_warnings(model, settings: IntegratorSettings, fixed_step: bool) -> list:
    """What `dbf-hpc run` warns before any work of the same settings (run.coarse_step_warning where the
    steps are fixed, run.coarse_samples_warning), from the model's support motion and force histories,
    naming the IntegratorSettings fields. Not collective."""
    from .excitation import fastest_hz
    from .run import coarse_samples_warning, coarse_step_warning

    fastest = fastest_hz(model.support, model.force)
    messages = (coarse_step_warning(settings, fastest) if fixed_step else None,
                coarse_samples_warning(settings, fastest))
    return [_api_names(m) for m in messages if m]


def above_basis_warning(model) -> str | None:
    """What `dbf-hpc run` warns where the model's support motion or force lies above its basis' highest
    reference mode (run.forcing_warning), naming the BasisSettings fields, or None: the reduced model's own
    histories, so a case given another force (with_case) is judged by its own. Not collective."""
    from .excitation import fastest_hz
    from .run import forcing_warning

    omega = np.asarray(getattr(model, "basis_info", {}).get("omega", ()), dtype=float)
    message = forcing_warning(fastest_hz(model.support, model.force), omega)
    return message and message.replace("(basis.modes or basis.max_frequency_hz)",
                                       "(BasisSettings modes or max_frequency_hz)")


def _api_names(message: str) -> str:
    """A run's warning with the scene keys it advises named as the IntegratorSettings fields."""
    return message.replace("[integrator] ", "IntegratorSettings ").replace("[output] sample_dt",
                                                                         "IntegratorSettings sample_dt")


def warn_result(result: Result, constraints, method: str, settings: IntegratorSettings, comm) -> None:
    """The warnings `dbf-hpc run` prints of the same result (run.result_warnings), from a Result and the
    model's ConstraintSet; each [integrator] key they advise is named as the IntegratorSettings field.
    Not collective: every rank of `comm` calls it with the same Result (rank 0 prints)."""
    from .run import result_warnings

    summary = {"constraint_stats": result.statistics, "alpha_speed": np.asarray(result.alpha_speed).tolist(),
               "stats": result.solver}
    named = [types.SimpleNamespace(label=label, law=law) for label, law in zip(constraints.labels, constraints.laws.laws)]
    for message in result_warnings(summary, named, method, settings):
        warn(_api_names(message), comm)


@petsc_errors_as_one_line("the reduced integration", ("rom_",))
def integrate_samples(model: ReducedModel, settings: IntegratorSettings, snapshots: int = 0, say=None) -> Result:
    """simulate_reduced without its warning: the error estimate's richer runs and the tolerance mode's
    probes (accuracy.py), whose atol the run's own warning or calibration covers. Not collective."""
    _check_settings(settings, say, "simulate_reduced")
    snapshots = check_number("simulate_reduced snapshots", snapshots, 0, integer=True)
    if isinstance(model, FullOrderModel) or not hasattr(model, "probe_sample_shape"):
        raise InputError(f"simulate_reduced integrates a reduced model (Reductor(...).reduce()), got "
                         f"{type(model).__name__}; simulate_full integrates a FullOrderModel")
    writer = MemoryWriter(model.constraints.shape, model.probe_sample_shape, model.size)
    recorder = ReducedRecorder(writer, model, snapshot_samples(snapshots, settings.sample_times))
    stats = integrate_reduced(model, settings, say=say, recorder=recorder)
    result = Result.from_recorder(recorder, stats)
    result.snapshot_time, result.snapshot_w = recorder.snapshots(settings.sample_times)
    return result


@petsc_errors_as_one_line("the full-order integration", ("full_",))
def simulate_full(fom: FullOrderModel, settings: IntegratorSettings, say=None) -> Result:
    """Integrate the full-order model (fom_integrator.py) and return the same Result as
    simulate_reduced (q and qdot of width 0). Warns as `dbf-hpc run --method full` does, on rank 0 of the
    model's communicator: before the integration of a setting it ignores and of a step or samples too coarse
    for the forcing (coarse_warnings), after it of the result (run.result_warnings, warn_result: also a
    contact stiffer than the step resolves). Collective; the Result is on every rank."""
    _check_settings(settings, say, "simulate_full")
    if not isinstance(fom, FullOrderModel):
        raise InputError(f"simulate_full integrates a FullOrderModel (FullOrderModel.build), got {type(fom).__name__}")
    world = fom.comm.tompi4py()
    # the reduced model's settings given other than their defaults: each a warning (the loop ignores them)
    defaults = {f.name: f.default for f in dataclasses.fields(IntegratorSettings)}
    values = {name: getattr(settings, name) for name in ("rtol", "atol", "scheme", "contact", "callbacks",
                                                         "max_step_scale") if getattr(settings, name) != defaults[name]}
    names = {name: f"IntegratorSettings {name}" for name in (*values, "dt")}
    for message in [*ignored_settings(values, settings.dt, "simulate_full", names),
                    *coarse_warnings(fom, settings, fixed_step=True)]:   # its steps are fixed
        warn(message, fom.comm)
    observation = Observation(fom)
    recorder = FullRecorder(MemoryWriter(fom.constraints.shape, fom.probes.shape, 0), fom.constraints, observation)
    stats = integrate_full(fom, settings, observation.rows, recorder.block, say=say)
    result = decided_on_rank0(world, Result.from_recorder, recorder, stats)   # what it raises, every rank raises
    warn_result(result, fom.constraints, "full", settings, fom.comm)   # every rank: the same Result
    return result


def _check_settings(settings, say, where: str) -> None:
    if not isinstance(settings, IntegratorSettings):
        raise InputError(f"give IntegratorSettings(t_end=..., ...), got {settings!r}")
    if say is not None and not callable(say):   # red team: a str was taken, and failed in the first progress line
        raise InputError(f"{where} say: give a function of one line (print) or None, got {say!r}")
