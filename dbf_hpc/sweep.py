"""Parameter studies: one base scene, many cases, spread over the MPI ranks.

A sweep file (TOML):

    scene = "paper_beam.toml"        # the base scene, relative to the sweep file
    output = "paper_sweep.h5"        # the summary (relative to the sweep file)
    keep_outputs = false             # also keep each case's full HDF5 output
    [axes]                           # a full grid over these scene values ...
    "excitation.frequency_hz" = [0.8, 1.0, 1.2]
    "constraint.clearance" = [1e-3, 2.5e-3]
    [[case]]                         # ... and/or listed cases (added after the grid)
    "constraint.law" = "linear"
    continuation = "excitation.frequency_hz"   # optional: an axis swept up and down with continuation
    directions = ["up", "down"]                # (default both)

Each case is the base scene with its values set (as `--set section.key=value`). `dbf-hpc sweep --set`
sets a base scene value for every case, and replaces an axis of one value of the same name (e.g.
`--set integrator.t_end=1` on a shipped sweep); a value the cases vary is refused. With continuation,
the cases along that axis form chains, one per direction and per combination of the other axes:
each case starts from the previous one's final physical state (a stepped sine: the excitation
continues its phase, and the total displacement and velocity are continuous); the summary gets a
`sweep_direction` column. The continuation axis must keep the reduced coordinates' meaning (not a
structure, basis or constraint-position value: refused before any work), and a numeric one is given
in increasing order, each value once ("up" runs it as listed, "down" reversed).

How it runs (collective on COMM_WORLD):
1. Every case's scene is validated before any work: a bad value stops the sweep at once, as does a
   case a run would refuse as endless (timestepping.check_work); a run's warnings before any work
   (run.scene_warnings: a coarse fixed step or sample interval, more snapshots than samples, estimate
   windows or DBF keys the case does not read) are given once for the cases they concern (and, with a
   loose atol, of a clearance or of a micro-structure's whole motion, once the models are built:
   _warn_loose_atol), and each case's record keeps them with the rest of what its run would warn
   (cases/warnings).
2. Each distinct reduced model (cases that differ only in law, excitation history or integrator
   share one) is built once on all ranks; the ranks keep only its small arrays. A model that
   cannot be built fails its cases, recorded with the error; the others go on.
3. The cases (chains) are dealt round-robin to the ranks; each rank integrates its cases alone.
4. Each finished case leaves a small result file (`OUT.cases/case-NNNNN.json`, written atomically;
   a rerun removes the temporary files of records a killed sweep left: errors.remove_dead_temporaries_in)
   with the identity of the case (its validated scene, the bytes of the files it reads, the rank
   count and callbacks, and in a chain its predecessors' identities): a rerun skips the cases that
   are done and still the same (with keep_outputs, whose complete output of that identity is still
   beside it), and reruns the others (on another rank count: all, and says why). A termination
   signal (SIGTERM, Ctrl-C) on any rank, even one rank alone, stops every rank at its running case's
   next step (checkpointed, no record) or before its next case; the command ends with one line and
   exit status 1; rerun the same command to go on. Once every rank has stopped or finished its
   cases, a signal is not acted on (the summary is written). The base scene is read once, at the
   start.
   A full disk (a record or a case's HDF5 file that cannot be written) stops every rank.
5. Rank 0 writes the summary. The summary is locked while a sweep runs: a second sweep on the
   same output is refused.

Cases carry no a-posteriori error estimate (accuracy.py) and the tolerance mode is refused: the
estimate's richer model, integrated over each case's window, would add 10 to 25 % to every case
(measured on the paper's beam) and a richer basis per structure, while a sweep's cases share one
basis and differ in law and excitation. Estimate a representative case with `dbf-hpc run` instead.
"""
from __future__ import annotations

import errno
import hashlib
import itertools
import json
import os
import signal
import socket
import sys
import time
import tomllib

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .checkpoint import Checkpoint
from .errors import (PARKED, TERMINATION, WRITE_ERRORS, DbfError, InputError, Interrupted, Unresumable, park,
                     read_regular_file, recording, remove_dead_temporaries_in, replacing, decided_on_rank0, from_rank0,
                     is_number, termination_signals, warn, write_failure)
from .excitation import Harmonic, time_functions
from .matrices import file_digest
from .output import LONGEST_PID, OutputLock, check_name_length, check_output_path, free_bytes
from .reductor import Reductor
from .rom_integrator import say_fallback
from .run import (STOP_TAG, RemoteStop, _interrupt_on_sigterm, basis_warnings, cap_refusal_before_basis, finished_output,
                  forcing_warning, form_warning, gyroscopic_checks, law_dimension, loose_atol_finding, result_warnings,
                  run_case, scene_callbacks, scene_warnings)
from .scene import load_scene, parse_override, relative_to_cwd
from . import __version__
from .schema import SECTIONS, unit_of
from .stats import DESCRIPTIONS_2D as DESCRIPTIONS, STATISTICS, STATISTICS_2D, UNITS_2D as UNITS
from .timestepping import check_work

SWEEP_KEYS = {"scene", "output", "keep_outputs", "axes", "case", "continuation", "directions"}
DIRECTION = "sweep_direction"
# What a reduced model depends on: everything but the laws, the excitation history and the integrator.
# The excitation's place and direction shape its load vector (a force, a random load, the support
# motion's influence on a beam of two planes); its time history is the case's own.
MODEL_KEYS = {"structure": None, "basis": None, "damping": None, "initial": None,
              "excitation": ("kind", "end", "x", "dof", "span", "direction"), "output": ("probes",)}
# Turbulence's histories and load matrix are made with the full-order model: all of it is the model's.
TURBULENCE_KEYS = ("psd", "band", "seed", "components", "correlation_length", "spectrum", "corner_hz", "slope")


def _typed(path: str, data: dict, key: str, kind, default):
    value = data.get(key, default)
    if not isinstance(value, kind) or isinstance(value, bool) != (kind is bool):
        raise InputError(f"{path}: {key} must be {'true or false' if kind is bool else 'a ' + kind.__name__}, "
                         f"got {value!r}")
    if isinstance(value, str) and "\x00" in value:   # red team: a NUL in output was an internal ValueError
        raise InputError(f"{path}: {key} contains a NUL character, which no file name may hold; remove it")
    return value


def _read(path: str) -> dict:
    try:   # a named pipe is refused, not waited on (red team: `dbf-hpc sweep FIFO` hung)
        data = tomllib.loads(read_regular_file(path).decode())
    except OSError as e:
        raise InputError(f"cannot read sweep {path!r}: {e.strerror}{relative_to_cwd(os.fspath(path), e)}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid TOML: {e}") from None
    if "scene" not in data and any(key in SECTIONS or key == "constraint" for key in data):
        raise InputError(f"{path}: is a scene, not a sweep file (scene = the base scene, and [axes] or [[case]]): "
                         f"run it with dbf-hpc run {path}")
    for key in data:
        if key not in SWEEP_KEYS:
            raise InputError(f"{path}: unknown key '{key}' (sweep files have {', '.join(sorted(SWEEP_KEYS))})")
    if "scene" not in data:
        raise InputError(f"{path}: scene (the base scene file) is required")
    return data


def _expand(path: str, axes: dict, listed: list, continuation, directions) -> tuple:
    """(cases as {name: value}, chains as lists of case indices)."""
    cases, chains = [], []
    if axes and continuation:
        others = [n for n in axes if n != continuation]
        for combo in itertools.product(*(axes[n] for n in others)):
            for direction in directions:
                values = axes[continuation] if direction == "up" else axes[continuation][::-1]
                chain = []
                for value in values:
                    chain.append(len(cases))
                    cases.append({**dict(zip(others, combo)), continuation: value, DIRECTION: direction})
                chains.append(chain)
    elif axes:
        for combo in itertools.product(*axes.values()):
            chains.append([len(cases)])
            cases.append(dict(zip(axes, combo)))
    for c in listed:
        if not isinstance(c, dict):
            raise InputError(f"{path}: each [[case]] is a table of section.key = value")
        chains.append([len(cases)])
        cases.append(dict(c))
    if not cases:
        raise InputError(f"{path}: no cases: give [axes] or [[case]] entries")
    return cases, chains


def load_sweep(path: str, overrides=()) -> dict:
    """Read a sweep file: {'scene', 'output', 'keep_outputs', 'cases': [[override, ...], ...],
    'values', 'parameters', 'chains', 'scenes'}. `overrides` ('section.key=value', --set) apply to every
    case before its own values; one naming an axis of one value replaces that value. All case scenes are validated here, and kept (the cases run them)."""
    data = _read(path)
    folder = os.path.dirname(os.path.abspath(path))
    scene = os.path.join(folder, _typed(path, data, "scene", str, None))
    name = _typed(path, data, "output", str, os.path.splitext(os.path.basename(path))[0] + ".h5")
    if not name.strip() or name.endswith(os.sep):   # red team: "" was refused as the sweep's folder, "a directory"
        raise InputError(f"{path}: output {name!r} names no file: give the summary's file name, e.g. output = "
                         f"\"{os.path.splitext(os.path.basename(path))[0]}.h5\" (the default)")
    output = os.path.join(folder, name)
    keep = _typed(path, data, "keep_outputs", bool, False)
    axes, listed = data.get("axes", {}), data.get("case", [])
    if not isinstance(axes, dict) or not isinstance(listed, list):
        raise InputError(f"{path}: [axes] is a table of lists and [[case]] an array of tables")
    for name, values in axes.items():
        if "." not in name:
            raise InputError(f"{path}: axis '{name}' must be a scene value written section.key")
        if not isinstance(values, list) or not values:
            raise InputError(f"{path}: axis '{name}' must be a non-empty list of values")
    continuation = data.get("continuation")
    directions = data.get("directions", ["up", "down"])
    # red team: continuation = ["x"] or directions = [[1]] was an internal TypeError (unhashable), and
    # directions = ["up", "up"] ran every chain twice, the summary holding each case twice
    if continuation is not None and not isinstance(continuation, str):
        raise InputError(f"{path}: continuation must name one of the [axes] (a string), got {continuation!r}")
    if continuation is not None and continuation not in axes:
        raise InputError(f"{path}: continuation '{continuation}' is not one of the [axes]")
    if not (isinstance(directions, list) and directions and all(d in ("up", "down") for d in directions)
            and len(set(directions)) == len(directions)):
        raise InputError(f"{path}: directions must be a list of \"up\" and/or \"down\", each once, got "
                         f"{directions!r}")
    axes, overrides = _set_single_valued_axes(axes, listed, continuation, overrides)
    cases, chains = _expand(path, axes, listed, continuation, directions)
    parameters = list(dict.fromkeys(name for case in cases for name in case))
    _refuse_sets_the_cases_replace(path, overrides, [name for name in parameters if name != DIRECTION])
    if continuation is not None:
        _refuse_unordered_continuation(path, continuation, axes[continuation])
    sets, coordinates, scenes, warnings = [], [], [], {}
    for i, case in enumerate(cases):
        own = [f"{name}={_toml_value(value)}" for name, value in case.items() if name != DIRECTION]
        try:
            for name in case:   # a [[case]] key: as an axis' (red team: a nested table was named a --set)
                if name != DIRECTION and "." not in name:
                    raise InputError(f"'{name}' must be a scene value written section.key")
            for text in own:
                parse_override(text)
            loaded = load_scene(scene, [*overrides, *own])
            if loaded["basis"]["tolerance"] is not None:
                raise InputError("[basis] tolerance is for runs; a sweep's cases share bases of a given size "
                                 "(set basis.modes, e.g. to what `dbf-hpc run` picked)")
            try:   # integrator settings the integrator refuses fail their case when it runs (recorded)
                settings, fastest = loaded.integrator_settings(), loaded.fastest_forcing_hz()
            except InputError:
                settings = None
            # what `dbf-hpc run` refuses before any work, a case too (red team: integrator.t_end = 1e9 or a
            # 1e9 Hz forcing, refused by a run, integrated on and on in a sweep)
            if settings is not None:
                check_work(settings, fastest, adaptive=settings.adaptive)
        except InputError as e:
            raise InputError(f"{path}: case {i + 1} ({', '.join(own)}): {e}") from None
        # and what a run warns before any work (run.scene_warnings; red team: a fixed dt of 5 steps a period
        # ran every case of a sweep silently, where `dbf-hpc run` said so, and so did estimate windows or DBF
        # keys the case does not read)
        for message in ([] if settings is None else scene_warnings(loaded, settings)):
            warnings.setdefault(message, []).append(i + 1)
        sets.append([*overrides, *own])
        scenes.append(loaded)
        coordinates.append(_coordinates_key(loaded))
    for message, numbers in warnings.items():
        warn(f"{path}: case{'s' if len(numbers) > 1 else ''} {', '.join(map(str, numbers))}: {message}",
             MPI.COMM_WORLD)
    for chain in chains:
        if len({coordinates[i] for i in chain}) > 1:
            raise InputError(f"{path}: continuation '{continuation}' changes the reduced model's coordinates along "
                             f"a chain (its structure, basis, constraint positions or moving support), so a final "
                             f"state cannot start the next case; make it an ordinary axis, or continue along an "
                             f"excitation, law, damping or integrator value")
    return {"scene": scene, "output": output, "keep_outputs": keep, "cases": sets, "values": cases,
            "parameters": parameters, "chains": chains, "scenes": scenes}


def _refuse_unordered_continuation(path: str, name: str, values: list) -> None:
    """A numeric continuation axis must be strictly increasing: "up" runs its values as listed and
    "down" in reverse, and the summary's sweep_direction says so (red team: [1.4, 1.2, 1.0] ran
    down under "up", and [1.0, 1.1, 1.0] ran the same chain twice, once called "down")."""
    if all(is_number(v) for v in values) and any(b <= a for a, b in zip(values, values[1:])):
        raise InputError(f"{path}: continuation '{name}' = {values}: give its values in increasing order, each once; "
                         f"directions = [\"up\", \"down\"] sweeps them up, then down")


def _target(name: str) -> tuple:
    """(section, key, constraint number or None) of a 'section.key' or 'constraint.J.key' name."""
    section, _, key = name.partition(".")
    number, dot, rest = key.partition(".")
    if section == "constraint" and dot and number.isdigit():
        return section, rest, int(number)
    return section, key, None


def _set_single_valued_axes(axes: dict, listed: list, continuation, overrides) -> tuple:
    """(axes, the --set values left for the base scene): a --set of an axis of one value (the shipped
    sweeps give integrator.t_end so) replaces that value, as it replaces a run's: the value is every
    case's, and the summary's column shows it (red team: `--set integrator.t_end=1` to try a sweep
    quickly was refused). An axis of several values, the continuation axis and a [[case]] value
    stay the sweep file's (_refuse_sets_the_cases_replace)."""
    axes, left = dict(axes), []
    listed_names = {name for case in listed if isinstance(case, dict) for name in case}
    for text in overrides:
        name = text.partition("=")[0].strip()
        values = axes.get(name)
        if isinstance(values, list) and len(values) == 1 and name != continuation and name not in listed_names:
            axes[name] = [parse_override(text)[2]]
        else:
            left.append(text)
    return axes, left


def _refuse_sets_the_cases_replace(path: str, overrides, parameters: list) -> None:
    """A --set of a value the sweep's cases set themselves: each case's own value is applied after the
    --set and would replace it in silence (red team: `--set integrator.t_end=0.1` on a sweep whose axes
    hold integrator.t_end ran every case 20 s), so it is refused before any work."""
    for text in overrides:
        section, key, number = _target(text.partition("=")[0].strip())
        for name in parameters:
            other = _target(name)
            if other[:2] == (section, key) and (number is None or other[2] is None or number == other[2]):
                raise InputError(f"--set {text}: the sweep {path} sets {name} in its cases, which would replace "
                                 f"this value; change it in the sweep file's [axes] or [[case]] instead (a --set "
                                 f"replaces only an axis of one value, given by the same name)")


def _toml_value(value) -> str:
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def _case_file(folder: str, index: int) -> str:
    return os.path.join(folder, f"case-{index:05d}.json")


def record_checksum(record: dict) -> str:
    """sha256 of a case's record without its own "sha256" entry (written with it, checked on read)."""
    body = {key: value for key, value in record.items() if key != "sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def _write_json(path: str, content: dict) -> None:
    # clean=False: no listing of the case folder per record (a killed writer's case-NNNNN.json.tmp-* is removed
    # once, as the sweep starts its cases: _sweep)
    with replacing(path, clean=False) as tmp, open(tmp, "w") as f:
        json.dump({**content, "sha256": record_checksum(content)}, f)


# What a case's record holds (_run_one), and what a finished one adds: a file without them is rerun
RECORD_KEYS = ("index", "identity", "parameters", "continued", "status", "wall_time")
RECORD_KEYS_OK = ("stats", "probe_peak", "solver", "final_state", "final_time", "final_phase", "final_support",
                  "coordinates")


def _read_json(path: str) -> dict | None:
    """A case's record, or None when it is missing or not one (truncated, edited, a changed digit:
    its checksum): the case is run again. A path that is not a regular file is not opened (red team: a
    named pipe there hung the sweep's look at its records, the open waiting for a writer for ever)."""
    if not os.path.isfile(path):
        return None
    try:
        with open(path) as f:
            record = json.load(f)
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or any(key not in record for key in RECORD_KEYS):
        return None
    if record.get("sha256") != record_checksum(record):
        return None
    if record["status"] == "ok" and any(key not in record for key in RECORD_KEYS_OK):
        return None
    return record


def _scene_files(scene) -> list:
    """The files a case's result depends on (not its cells file, which only draws it)."""
    return [path for what, path in scene.inputs() if what not in ("scene", "cells file")]


def _setup(scene) -> dict:
    """What a case's result depends on besides its scene and files: the rank count (the reduced model is
    projected on all ranks, and its round-off differs with their number: 0.2 % on the chaotic tube) and
    the callbacks the case integrates with ("c" or "python", also round-off apart)."""
    try:
        callbacks = scene_callbacks(scene)
    except InputError:   # integrator settings the case refuses when it runs (recorded as failed)
        callbacks = None
    return {"ranks": MPI.COMM_WORLD.size, "callbacks": callbacks}


def _file_digests(scenes: list) -> dict:
    """The sha256 of every file the cases read (hashed once, on rank 0). Collective."""
    files = sorted({path for scene in scenes for path in _scene_files(scene)})
    return {path: file_digest(path, PETSc.COMM_WORLD) for path in files}


def _identities(sweep: dict, scenes: list, digests: dict | None = None, setups: list | None = None) -> list:
    """Per case, the sha256 of what its result depends on: the validated scene (`scenes`, as the
    cases run it), the bytes of every file it reads (`digests`, _file_digests), the PETSc options, the
    package version, the rank count and the callbacks (_setup, or `setups`[i] where given: the
    identity the case would have on that setup), and in a continuation chain its predecessors'. A
    sweep rerun on another rank count reruns its finished cases, as a run's --resume on another rank
    count starts again: a summary mixing both would be neither's answer, and no rerun of the command
    would reproduce it (red team). Collective without `digests`, else not."""
    digests = _file_digests(scenes) if digests is None else digests
    options = PETSc.Options().getAll()
    out = []
    for i, scene in enumerate(scenes):
        setup = _setup(scene) if setups is None or setups[i] is None else setups[i]
        content = [scene.result_sections(), [repr(c) for c in scene.constraints],
                   {path: digests[path] for path in _scene_files(scene)}, options, __version__, setup]
        out.append(hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest())
    # a case of a chain starts from its predecessor's final state: its identity holds the chain's
    for chain in sweep["chains"]:
        for before, index in zip(chain, chain[1:]):
            out[index] = hashlib.sha256((out[before] + out[index]).encode()).hexdigest()
    return out


def _look(sweep: dict, folder: str, identities: list) -> tuple:
    """Rank 0: (every case's record, or {}; the finished cases whose full output keep_outputs asks for
    is not beside it as this case's, complete: they run again). Red team: keep_outputs turned on after
    a sweep reused every record and kept no case's output, in silence."""
    records = [_read_json(_case_file(folder, i)) or {} for i in range(len(identities))]
    unkept = set()
    if sweep["keep_outputs"]:
        for i, record in enumerate(records):
            if record.get("identity") == identities[i] and record.get("status") == "ok" and \
                    finished_output(os.path.join(folder, f"case-{i:05d}.h5"), {"case": identities[i]},
                                    sweep["scenes"][i]) is None:
                unkept.add(i)
    return records, unkept


def _coordinates_key(scene) -> str:
    """What the reduced coordinates q mean: the basis (structure, [basis], constraint positions) and
    the relative coordinates' moving support. A continuation chain must keep it."""
    parts = {"structure": scene.result_sections()["structure"], "basis": scene["basis"],
             "support": [scene["excitation"]["kind"], scene["excitation"]["end"], scene["excitation"]["direction"]],
             "constraints": [(c.x, c.dof) for c in scene.constraints]}
    return json.dumps(parts, sort_keys=True, default=str)


def _model_key(scene) -> str:
    parts = {section: (scene[section] if keys is None else {k: scene[section][k] for k in keys})
             for section, keys in MODEL_KEYS.items()}
    if scene["excitation"]["kind"] == "turbulence":
        parts["turbulence"] = {k: scene["excitation"][k] for k in TURBULENCE_KEYS}
    parts["constraints"] = [(c.x, c.dof) for c in scene.constraints]
    parts["field"] = scene.output().snapshots > 0
    return json.dumps(parts, sort_keys=True, default=str)


def _prepare_models(sweep: dict, pending, cache_dir: str, say, models: dict | None = None) -> dict:
    """Each distinct reduced model of the pending cases, built once on COMM_WORLD (model key ->
    the model, or the error that stopped it), added to `models`; what a run warns of each basis
    (run.basis_warnings) is warned once naming the model's cases and kept, after what the model's build
    warned (errors.recording: its matrix files ...), in sweep["basis_warnings"] (model key -> lines) for
    their records. Collective."""
    models = {} if models is None else models
    for index in pending:
        scene = sweep["run_scenes"][index]
        key = _model_key(scene)
        if key in models:
            continue
        try:
            with recording() as built, scene.full_order_model(PETSc.COMM_WORLD) as fom:
                # what a run refuses of a gyroscopic structure, a case too (red team: a sweep ran modal damping
                # ratios on the complex modes' real basis, and skipped the stability check with damping)
                if fom.operators.G is not None:
                    gyroscopic_checks(scene, fom, "rom")
                else:   # as a run says it (kept in the rows with the build's lines)
                    form = form_warning(scene, fom)
                    if form:
                        warn(form, PETSc.COMM_WORLD)
                # what a run refuses before its basis (run.cap_refusal_before_basis), a case too: it fails with
                # the line, and a model all of whose cases fail so is not built
                if _refused_before_basis(sweep, [i for i in pending if _model_key(sweep["run_scenes"][i]) == key],
                                         fom):
                    models[key] = "its every case is refused before its basis"
                    continue
                with Reductor(fom, scene.basis_settings(), cache_dir, warn_basis=False) as reductor:
                    models[key] = reductor.reduce(field=scene.output().snapshots > 0)
                    # what a run warns of its basis (a flexibility captured below 99 %, a lowest frequency
                    # that suggests a unit slip ...): the sweep said nothing of it (warnings parity)
                    warned = basis_warnings(reductor.basis(), fom.constraints.component_labels,
                                            fom.operators.rigid_modes, fom.constraints.dimension)
            # with what its build warned (its matrix files ...: printed as they came), in the run's order
            sweep.setdefault("basis_warnings", {})[key] = [*built, *warned]
            cases = [i + 1 for i in pending if _model_key(sweep["run_scenes"][i]) == key]
            for message in warned:   # once for the cases of the model, as the loose atol's line
                warn(f"sweep: case{'s' if len(cases) > 1 else ''} {', '.join(map(str, cases))}: {message}",
                     PETSc.COMM_WORLD)
        except Interrupted:   # a termination signal stops the sweep (red team: its cases were recorded as
            raise             # failed with the signal's line, and the sweep went on to its other models)
        except DbfError as e:
            models[key] = str(e)
    say(f"reduced models ready: {len(models)}")
    return models


def _refused_before_basis(sweep: dict, cases, fom) -> bool:
    """Whether every one of `cases` (indices of the pending cases of one model) is refused before the basis
    as its run would be (run.cap_refusal_before_basis), its line kept in sweep["refused"] (index -> line)
    for _run_one. A case whose settings are refused otherwise fails on its own. Collective (every rank
    has the same cases)."""
    lines = {}
    for index in cases:
        scene = sweep["run_scenes"][index]
        try:
            settings = scene.integrator_settings()
        except InputError:
            continue
        if settings not in lines:   # one count of the eigenvalues per distinct settings
            lines[settings] = cap_refusal_before_basis(scene, fom, settings)
        if lines[settings]:
            sweep.setdefault("refused", {})[index] = lines[settings]
    return bool(cases) and all(index in sweep.get("refused", {}) for index in cases)


def _stale_chains(sweep, records, pending: set, models: dict, cache_dir: str) -> set:
    """The cases of every chain whose next step would continue from a finished step's final state q
    in a basis that is not the one q was computed in (ReducedModel.coordinates_digest: the cache
    cleared and the basis rebuilt on another rank layout turns a repeated frequency's modes). Not
    collective; every rank finds the same, from the same records."""
    stale = set()
    for chain in sweep["chains"]:
        for before, index in zip(chain, chain[1:]):
            if before in pending or index not in pending:
                continue
            scene = sweep["run_scenes"][index]
            built = models.get(_model_key(scene))
            if not isinstance(built, str) and records[before].get("coordinates") != built.coordinates_digest():
                stale.update(chain)
                break
    return stale


def _continued(model, scene, previous: dict | None):
    """The case's reduced model with its laws and excitation history, started from the previous
    case's final state when it continues a chain (the stepped sine keeps its phase, and the jump of
    r Omega and r Omega' is taken up by q as far as the basis represents r: the total displacement
    stays continuous to round-off, the velocity up to the part of r outside the basis)."""
    support, force = time_functions(scene.excitation())
    if scene["excitation"]["kind"] == "turbulence":
        force = model.force   # its histories came with the model (the model key holds all of turbulence)
    laws = type(model.constraints.laws)([c.law for c in scene.constraints])   # ConstraintLaws or PlanarLaws
    if previous is None:
        return model.with_case(constraints=model.constraints.with_laws(laws), support=support, force=force)
    phase = previous["final_phase"]
    if support.amplitude:
        support = Harmonic(support.amplitude, support.frequency_hz, phase)
    elif isinstance(force, Harmonic) and force.amplitude:
        force = Harmonic(force.amplitude, force.frequency_hz, phase)
    q, p = (np.asarray(a, dtype=float) for a in previous["final_state"])
    old_value, old_rate = previous["final_support"]
    dq, dp = model.support_jump(old_value - support.value(0.0), old_rate - support.rate(0.0))
    q, p = q + dq, p + dp
    return model.with_case(constraints=model.constraints.with_laws(laws), support=support, force=force, q0=q, p0=p)


def _final_excitation(model, t_end: float) -> dict:
    history = model.support if model.support.amplitude else model.force
    phase = (2 * np.pi * history.frequency_hz * t_end + history.phase) if isinstance(history, Harmonic) else 0.0
    return {"final_time": t_end, "final_phase": float(np.mod(phase, 2 * np.pi)),
            "final_support": [float(model.support.value(t_end)), float(model.support.rate(t_end))]}


class _Stop(RemoteStop):
    """A termination signal during a sweep, on any rank, stops every rank (red team: SIGTERM to rank 1
    alone stopped rank 1, and rank 0 ran all its remaining cases before the sweep ended). The
    signalled rank tells every other rank with a message (STOP_TAG, on a communicator of the sweep's
    own) as soon as it sees its signal: between cases, at its running case's steps (run_case's
    `remote`: Checkpointing polls `poll`), or while it waits for the others at the end (finish). A
    rank that hears it checkpoints its running case at the end of the step, as at its own signal, or
    starts no new case. finish receives every message sent: none is left in MPI. run.RemoteStop's
    polling and draining on a communicator of the sweep's own. Collective: made, finished and closed
    on every rank."""

    def __init__(self, world):
        self.comm = world.Dup()
        super().__init__(self.comm)
        self.requested = self.heard = False
        self.sends = []

    def __enter__(self):
        TERMINATION.requested = False
        self.previous = {}
        try:
            for signum in termination_signals():   # SIGTERM, and Ctrl-C
                self.previous[signum] = signal.signal(signum, self._handle)
        except ValueError:  # not the main thread
            pass
        return self

    def _handle(self, signum, frame):
        self.requested = True

    def tell(self) -> None:
        """Tell every other rank that this one was signalled (once)."""
        self.requested = True
        if not self.sends and self.comm.size > 1:
            self.sends = [self.comm.isend(True, dest=rank, tag=STOP_TAG) for rank in range(self.comm.size)
                          if rank != self.comm.rank]

    def poll(self, wait: bool = True) -> bool:
        """Whether the sweep is to stop: this rank's signal (the sweep's handler, or the running case's:
        errors.TERMINATION), told to the others, or another rank's message, looked for at most every
        POLL s (wait False: now). Not collective."""
        if self.requested or TERMINATION.requested:
            self.tell()
            return True
        if not self.heard:
            if not wait:
                self.last = -float("inf")
            self.heard = super().poll()
        return self.heard

    def finish(self) -> bool:
        """Every rank, its cases done or stopped: wait for the others without blocking (a signal
        meanwhile is told to them, who may still be running cases), then receive the messages still
        on their way. Returns whether any rank was signalled. Collective."""
        request = self.comm.Ibarrier()
        while not request.Test():
            self.poll()
            time.sleep(0.02)
        told = self.comm.allgather(bool(self.sends))
        self.drain(sum(told) - told[self.comm.rank])
        MPI.Request.Waitall(self.sends)
        self.sends = []
        self.comm.Free()   # here, not in __exit__: an exception on one rank must not meet a collective call
        return any(told)

    def __exit__(self, *exc):
        for signum, previous in self.previous.items():
            signal.signal(signum, previous)


def _record(sweep, index: int, identity: str, continued: bool) -> dict:
    """What every record of case `index` starts with (RECORD_KEYS but its status and wall time)."""
    return {"index": index, "identity": identity, "parameters": sweep["values"][index], "continued": continued,
            **_setup(sweep["scenes"][index])}


def _run_one(sweep, index, folder, cache_dir, models, identity, previous, stop=None) -> dict:
    """One case on this rank: its record (status ok or failed), or Interrupted (a signal on this rank
    or, through `stop` (_Stop), another's)."""
    record = _record(sweep, index, identity, previous is not None)
    t = time.perf_counter()
    case_out = os.path.join(folder, f"case-{index:05d}.h5")
    try:
        scene = sweep["run_scenes"][index]
        if index in sweep.get("refused", {}):   # before the basis, as its run (_prepare_models)
            raise InputError(sweep["refused"][index])
        built = models[_model_key(scene)]
        if isinstance(built, str):
            raise DbfError(built)
        model = _continued(built, scene, previous)
        # what q means is part of it, as in a run's (run.run_identity; red team: a case stopped on 2 ranks
        # resumed its q in the basis a 1-rank rerun rebuilt, and its statistics were neither run's)
        ident = {"case": identity, "coordinates": model.coordinates_digest()}
        _drop_stale_checkpoint(case_out, ident)
        keep = sweep["keep_outputs"]
        try:
            summary = run_case(scene, model, case_out, resume=True, ident=ident, keep=keep, remote=stop)
        except Unresumable:   # a valid checkpoint, a .partial that cannot continue: the case starts again
            _remove(f"{case_out}.partial", f"{case_out}.checkpoint")
            summary = run_case(scene, model, case_out, resume=True, ident=ident, keep=keep, remote=stop)
        record.update(status="ok", stats=summary["constraint_stats"], probe_peak=summary["probe_peak"],
                      solver=summary["stats"], final_state=summary["final_state"],
                      coordinates=model.coordinates_digest(),
                      warnings=_case_warnings(scene, built, summary, sweep.get("basis_warnings", {}).get(
                          _model_key(scene), ())),
                      **_final_excitation(model, scene.integrator_settings().t_end))
    except Interrupted:
        raise
    except DbfError as e:
        record.update(status="failed", error=str(e))
    except OSError as e:   # the case's own files (a directory in the way, a full disk): a failed case, retried
        record.update(status="failed", error=f"{case_out}: {write_failure(e)}")
    record["wall_time"] = time.perf_counter() - t
    if not sweep["keep_outputs"]:
        _remove(case_out, f"{case_out}.partial", f"{case_out}.checkpoint", os.path.splitext(case_out)[0] + ".xdmf")
        if "error" in record:   # the files run.py's message says are left behind are not (red team)
            record["error"] = record["error"].split(f" (samples so far in {case_out}")[0].split(
                f" (the samples up to the failure are in {case_out}")[0]
    if "error" in record:   # a sweep resumes its cases itself: `dbf-hpc sweep` takes no --resume
        record["error"] = record["error"].replace("rerun with --resume", "rerun the sweep").replace(
            "rerun without --resume", "rerun the sweep")
    return record


def _warn_loose_atol(sweep, pending, models: dict, world) -> None:
    """The warning `dbf-hpc run` prints where atol lets w err by over 1 % of a clearance, or of the
    motion's own scale where no clearance is within reach (a micro-beam: run.loose_atol, whose
    loose_atol_finding decides it for both), once for the sweep: per kind, one line naming every pending
    case it concerns, with the worst case's numbers (its advised atol is enough for all). Each case is
    judged as its own run: its laws, support motion and force from [initial] (_said_for_the_sweep). Every
    rank holds every model (_prepare_models) and computes the same; rank 0 prints. Not collective."""
    found = {}
    for index in pending:
        scene = sweep["run_scenes"][index]
        finding = _loose_finding(scene, models.get(_model_key(scene)))
        if finding is not None:
            kind, ratio, line = finding
            cases, worst = found.get(kind, ([], None))
            cases.append(index + 1)
            found[kind] = (cases, worst if worst is not None and worst[0] >= ratio else (ratio, line, index + 1))
    for cases, (_, line, case) in found.values():
        warn(f"sweep: case{'s' if len(cases) > 1 else ''} {', '.join(map(str, cases))}: "
             f"{line}{f' (case {case}, the worst)' if len(cases) > 1 else ''}", world)


def _loose_finding(scene, model) -> tuple | None:
    """run.loose_atol_finding of the case's run: its model (the built one, `model`) with its own laws and
    excitation history, from [initial] as `dbf-hpc run` of its scene starts; None where the case has
    fixed steps, no model (its build failed) or settings it refuses (it fails on its own, recorded so).
    Not collective."""
    try:
        settings = scene.integrator_settings()
    except InputError:   # the case fails on its own, and is recorded so (not the whole sweep: CI caught it)
        return None
    if isinstance(model, str) or model is None or not settings.adaptive:
        return None
    return loose_atol_finding(_continued(model, scene, None), settings.atol, scene.constraints)


def _warn_done(sweep, records, pending, world) -> None:
    """What the finished cases a rerun keeps warned when they ran (their records' warnings), each line
    once naming its cases, as `dbf-hpc run --resume` of a finished output prints its run's warnings
    again (a requeued sweep's log said nothing of them); the lines before any work (run.scene_warnings)
    load_sweep has just said for every case are not repeated. Every rank holds the records; rank 0
    prints. Not collective."""
    lines, pending = {}, set(pending)
    for index, record in enumerate(records):
        if index in pending or record.get("status") != "ok":
            continue
        before = _said_for_the_sweep(sweep["run_scenes"][index], None)[0]
        for message in record.get("warnings", []):
            if message not in before:
                lines.setdefault(message, []).append(index + 1)
    for message, cases in lines.items():
        warn(f"case{'s' if len(cases) > 1 else ''} {', '.join(map(str, cases))} (done before): {message}", world)


def _case_warnings(scene, model, summary: dict, basis_warned=()) -> list:
    """What `dbf-hpc run` warns of the same case, in its order, that its result may be wrong (red team: a
    clearance in mm given as m, a basis below the forcing, impacts a fixed step does not resolve: each run
    warned, and a sweep of the same cases said nothing): kept in its record and the summary
    (cases/warnings), and printed by the rank that ran the case but for those the sweep printed once for
    its cases before they ran (_said_for_the_sweep: run.scene_warnings, a loose atol; red team:
    cases/warnings held no trace of these; a basis' warnings, basis_warned, it did not print at all).
    `model`: the case's built model (not continued: a run of its scene starts from [initial])."""
    settings = scene.integrator_settings()
    before, basis, loose = _said_for_the_sweep(scene, model, basis_warned)
    above = forcing_warning(scene.fastest_forcing_hz(), model.basis_info.get("omega", ()))
    # the result's, as the run words them (result_warnings; the unresolved impacts' advice named dt alone)
    out = result_warnings(summary, scene.constraints, "rom", settings)
    return [*before, *basis, *(w for w in (above, loose) if w), *out]


def _said_for_the_sweep(scene, model, basis_warned=()) -> tuple:
    """(what its run warns before any work (run.scene_warnings), its basis' warnings (basis_warned), the
    loose-atol warning or None (_loose_finding)) of a case, as its run gives them: the sweep prints them
    once, naming its cases (load_sweep, _prepare_models, _warn_loose_atol). `model`: the case's built
    model (None: no loose-atol line). Not collective."""
    basis_warned = list(basis_warned)
    try:
        settings = scene.integrator_settings()
    except InputError:   # (the case fails on its own)
        return [], basis_warned, None
    loose = _loose_finding(scene, model)
    return scene_warnings(scene, settings), basis_warned, None if loose is None else loose[2]


def _drop_stale_checkpoint(case_out: str, ident: dict) -> None:
    """A case's checkpoint from an earlier, different version of the case is removed, not resumed."""
    try:
        Checkpoint(f"{case_out}.checkpoint", ident).read()
    except InputError:
        _remove(f"{case_out}.partial", f"{case_out}.checkpoint")


def _remove(*paths: str) -> None:
    for path in paths:
        if os.path.exists(path):
            os.remove(path)


def _run_chains(sweep, mine, pending, folder, cache_dir, models, identities, stop, tell) -> int:
    """This rank's chains; returns how many cases it ran; tell(line) reports each case (from any
    rank). Stops at a termination signal on any rank (`stop`, _Stop: Interrupted)."""
    done = 0
    for chain in mine:
        previous = broken = None
        for index in chain:
            if index not in pending:  # finished before: continue from its final state
                previous = _read_json(_case_file(folder, index))
                previous = previous if previous and previous.get("status") == "ok" else None
                continue
            if stop.poll(wait=False):
                raise Interrupted("stopped by a termination signal")
            parked = len(PARKED)
            if broken is not None:
                # a step continues from the one before it: started from rest instead, it would answer
                # another question under an "ok" (red team); a rerun retries the chain from the failed step
                record = {**_record(sweep, index, identities[index], False), "status": "failed", "wall_time": 0.0,
                          "error": f"not run: case {broken + 1}, the step before it in its continuation chain, failed"}
            else:
                record = _run_one(sweep, index, folder, cache_dir, models, identities[index],
                                  previous if len(chain) > 1 else None, stop)
            _write_json(_case_file(folder, index), record)
            previous = record if record["status"] == "ok" else None
            if record["status"] != "ok" and len(chain) > 1 and broken is None:
                broken = index
            done += 1
            tell(f"  case {index + 1}: {record['status']}")
            scene = sweep["run_scenes"][index]
            before, basis, loose = _said_for_the_sweep(scene, models.get(_model_key(scene)),
                                                       sweep.get("basis_warnings", {}).get(_model_key(scene), ()))
            for message in record.get("warnings", []):   # -q silences the progress, not these
                if message not in (*before, *basis, loose):
                    print(f"dbf-hpc: warning: case {index + 1}: {message}", file=sys.stderr, flush=True)
            if len(PARKED) > parked:
                # an HDF5 write of the case failed (a full disk): its file is kept open (errors.park),
                # and HDF5 crashed (signal 11) at the next failed write of this process (red team): the
                # sweep stops on every rank (_sweep)
                raise DbfError(f"case {index + 1} failed: {record.get('error', '')}")
    return done


def run_sweep(path: str, progress: bool = True, overrides=()) -> dict:
    """Run (or resume) a sweep. Collective on COMM_WORLD. Returns {'output', 'cases', 'failed',
    'first_failure'} (the first failed case's number and error, or None)."""
    world = MPI.COMM_WORLD
    # rank 0 reads the sweep file and its scenes, every rank runs them: each rank's own read could
    # differ (a file edited while the job started) or fail alone (a node that cannot read the path)
    sweep = decided_on_rank0(world, load_sweep, path, overrides)
    TERMINATION.finished = False
    output, folder = sweep["output"], sweep["output"] + ".cases"
    say = (lambda m: PETSc.Sys.Print(m)) if progress else (lambda m: None)
    lock = OutputLock(output, "sweep summary")
    lock.expect(world)   # before rank 0 takes it: a rank that aborts the job removes it (cli._abort)

    def claim():   # rank 0: whatever it raises, every rank raises (decided_on_rank0; red team: anything but an
        try:       # InputError or OSError left the other ranks in the broadcast after it)
            check_output_path(output, [("sweep file", os.path.abspath(path)), ("base scene", sweep["scene"])])
            check_name_length(output, [f"{output}.partial", f"{output}.lock.stale-{socket.gethostname()}-{LONGEST_PID}"],
                              "sweep summary")
            lock.acquire()
            os.makedirs(folder, exist_ok=True)
        except OSError as e:   # red team: "[Errno 17] File exists: '...cases'", and the lock left behind
            lock.release()
            what = "is a file, not a directory" if os.path.lexists(folder) and not os.path.isdir(folder) else \
                f"cannot be made ({e.strerror or e})"
            raise InputError(f"the sweep's case folder {folder!r} {what}: move it away, or give the sweep another "
                             f"output") from None
        except BaseException:
            lock.release()
            raise

    try:
        decided_on_rank0(world, claim)
    except BaseException:
        lock.forget()   # (a no-op on rank 0, which released it)
        raise
    try:
        result = _sweep(sweep, folder, output, world, say, progress)
    finally:
        if world.rank == 0:
            lock.release()
        else:
            lock.forget()
    world.Barrier()   # as run.claimed: a returned sweep has released its lock on every rank
    return result


def _sweep(sweep, folder, output, world, say, progress) -> dict:
    n = len(sweep["cases"])
    # Every case runs the scene load_sweep read and checked, rank 0's for all (run_sweep): the cases run
    # what their identities hold (red team: the scene, read again for each case, was edited while the
    # sweep ran; the summary mixed clearances, and the records, under the old scene's identity, were
    # reused once restored)
    scenes = sweep["scenes"]
    # the records a sweep killed (SIGKILL) as it wrote them left at their temporary names, which no `finally`
    # removed (red team: they piled up in the case folder): each rank removes those of dead processes of its
    # host, once, before any rank of this sweep writes one; a live process's (another rank's) is kept
    remove_dead_temporaries_in(folder, r"case-\d{5}\.json")
    digests = _file_digests(scenes)
    identities = _identities(sweep, scenes, digests)
    # rank 0's reading for all: which cases are pending decides collective calls (_prepare_models)
    records, unkept = decided_on_rank0(world, _look, sweep, folder, identities)   # (what it raises: every rank)
    # a failed case is retried: its cause may have been the machine's (a full disk), since mended
    pending = {i for i in range(n) if records[i].get("identity") != identities[i] or records[i].get("status") != "ok"}
    pending |= unkept
    retried = sum(records[i].get("identity") == identities[i] for i in pending)
    # the finished cases that rerun for their setup alone: on the setup they ran on, their identity
    # would be the one recorded (new-user pass: a sweep rerun on 1 rank with --set integrator.t_end=1,
    # another question, said "18 finished case(s) rerun: they ran on 2 rank(s) ... (rerun on that
    # setup to reuse them)", advice that would not have reused them either)
    recorded = [{"ranks": r["ranks"], "callbacks": r.get("callbacks")} if "ranks" in r else None for r in records]
    as_recorded = _identities(sweep, scenes, digests, recorded)
    moved = [i for i in pending if records[i].get("status") == "ok" and "ranks" in records[i] and
             (records[i]["ranks"], records[i].get("callbacks")) != tuple(_setup(scenes[i]).values())
             and records[i].get("identity") == as_recorded[i]]
    for chain in sweep["chains"]:   # a step rerun starts the steps after it anew (they began from rest before)
        for k, index in enumerate(chain):
            if index in pending:
                pending.update(chain[k:])
                break
    pending = sorted(pending)
    say(f"dbf-hpc sweep: {n} cases, {n - len(pending)} already done, {len(pending)} to run on {world.size} rank(s)"
        + (f" ({retried} failed before: retried)" if retried else ""))
    if moved:
        first = records[moved[0]]
        say(f"  {len(moved)} finished case(s) rerun: they ran on {first['ranks']} rank(s) with the {first['callbacks']} "
            f"callbacks, and the rank count and callbacks change a case's round-off (rerun on that setup to reuse them)")
    cache_dir = scenes[0].cache_dir() or os.path.join(folder, "basis-cache")
    sweep = {**sweep, "run_scenes": [scene.with_values("basis", cache=cache_dir) for scene in scenes]}
    models = _prepare_models(sweep, pending, cache_dir, say)
    stale = _stale_chains(sweep, records, set(pending), models, cache_dir)
    if stale:
        say(f"  {len(stale - set(pending))} finished case(s) rerun: the basis of their chain was rebuilt, and the "
            f"state a finished step ends in means another state in it")
        pending = sorted(set(pending) | stale)
        _prepare_models(sweep, pending, cache_dir, say, models)
    _warn_done(sweep, records, pending, world)
    _warn_loose_atol(sweep, pending, models, world)
    for index in pending:   # every rank alike, rank 0 says it once: not each rank as it integrates its first case
        try:
            say_fallback(sweep["run_scenes"][index].integrator_settings().callbacks,
                         law_dimension(sweep["run_scenes"][index]), world)
        except InputError:   # (the case fails on its own, recorded so)
            pass
    chains = [c for c in sweep["chains"] if any(i in pending for i in c)]
    mine = chains[world.rank::world.size]
    stopped = unwritten = None
    with _Stop(world) as stop:
        try:
            tell = (lambda m: print(m, flush=True)) if progress else (lambda m: None)   # every rank's cases
            _run_chains(sweep, mine, set(pending), folder, cache_dir, models, identities, stop, tell)
        except Interrupted:
            stopped = True
            if not stop.heard:   # this rank's own signal (also one that stopped its case after the integration)
                stop.tell()
        except DbfError as e:   # a case's record, or a case's HDF5 file, could not be written (a full disk)
            unwritten = str(e)
        stop.finish()   # a rank that had run out of cases, signalled while it waited, stops the others too
    # After the agreement point a signal is not acted on (the summary is written, or every rank stops
    # alike): the command's handler, taking it, said "before the integration began; nothing was written"
    # and, on several ranks, aborted the job after 10 s, its summary half written (red team)
    with _interrupt_on_sigterm(None):
        # every rank hears of either (red team: a record that failed on one rank left the other in this
        # reduction, and the job ended in the command's 10 s timeout and MPI_Abort, the lock left behind)
        unwritten = next((p for p in world.allgather(unwritten) if p), None)
        if unwritten:
            raise DbfError(f"{unwritten}; the cases recorded so far are kept in {folder}: free some space, then "
                           f"rerun the same command")
        stopped = world.allreduce(bool(stopped), op=MPI.LOR)
        if stopped:
            finished = [_read_json(_case_file(folder, i)) or {} for i in range(n)]
            done = sum(r.get("identity") == identities[i] and r.get("status") == "ok"
                       for i, r in enumerate(finished))
            raise Interrupted(f"sweep stopped by a termination signal with {done} of {n} cases done; rerun the "
                              f"same command to continue (finished cases are kept, a running one resumes from its "
                              f"checkpoint)")
        failed = problem = None
        unexpected = []
        if world.rank == 0:
            try:
                failed = _write_summary(sweep, folder, output)
            except BaseException as e:   # every rank hears of it (the case files stay: a rerun only writes this)
                if os.path.isfile(f"{output}.partial") and not os.path.islink(f"{output}.partial"):
                    os.remove(f"{output}.partial")
                if not isinstance(e, WRITE_ERRORS):   # (a bug) every rank raises it: errors.from_rank0
                    problem = type(e).__name__
                    unexpected.append(e)
                else:
                    problem = (f"cannot write the sweep summary {output}: {write_failure(e)}; the cases are kept "
                               f"in {folder}")
            if progress and problem is None:
                print(f"dbf-hpc sweep: wrote {output} ({n} cases, {failed} failed)", flush=True)
        failed, problem = from_rank0(world, (failed, problem), unexpected)
    if problem:
        raise DbfError(problem)
    TERMINATION.finished = True
    first = next(((i, r) for i, r in enumerate(_read_json(_case_file(folder, i)) or {} for i in range(n))
                  if r.get("status") == "failed"), None) if failed else None
    return {"output": output, "cases": n, "failed": failed,
            "first_failure": f"case {first[0] + 1}: {first[1].get('error', '')}" if first else None}


def _units(f, parameters) -> None:
    """Every dataset of a summary with its unit and meaning."""
    for name in parameters:
        f[f"cases/parameters/{name}"].attrs.update(unit=unit_of(name) or "1", description=f"the case's {name} "
                                                   "(NaN or null: the base scene's value)")
    for name in f["cases/stats"]:
        f[f"cases/stats/{name}"].attrs.update(unit=UNITS[name], description=DESCRIPTIONS[name] + " (case x constraint)")
    f["cases/probe_peak"].attrs.update(unit="m", description="max |w| at each probe (case x probe; on a beam of two "
                                                             "planes the larger of the y and z peaks)")
    f["cases/wall_time"].attrs.update(unit="s", description="wall time of the case")
    for name in ("status", "error"):
        f[f"cases/{name}"].attrs.update(unit="", description=f"the case's {name}")
    f["cases/warnings"].attrs.update(unit="", description="what `dbf-hpc run` warns of the case, that its result may "
                                                          "be wrong (one line each; empty: none)")


def _write_summary(sweep: dict, folder: str, output: str) -> int:
    """The summary HDF5, a row per case: parameters, status, statistics per constraint."""
    import h5py

    records = [_read_json(_case_file(folder, i)) for i in range(len(sweep["cases"]))]
    n = len(records)
    # each row's parameters are the sweep's as asked now, not the record's: a record is reused when its
    # case's scene is the same, however the sweep file spells the value (red team: an axis renamed from
    # constraint.k to constraint.1.k reused both records, and the summary's constraint.1.k read NaN, "the
    # base scene's value", for cases that set 1e5 and 2e5 N/m)
    values = sweep["values"]
    width = max((len(r.get("stats", {}).get("impacts", [])) for r in records), default=0)
    probes = max((len(r.get("probe_peak", [])) for r in records), default=0)
    tmp = f"{output}.partial"
    # A write that fails on a full disk crashed HDF5 in its close (signal 11) once a failed case's file
    # had been kept open in this process (errors.park; red team, a 3 MB tmpfs): the room is checked first
    needed = 8.0 * n * (len(sweep["parameters"]) + (len(STATISTICS_2D) + 1) * width + probes + 3) + \
        sum(len(json.dumps(v)) + len(r.get("error", "")) + sum(len(w) + 1 for w in r.get("warnings", [])) + 16
            for r, v in zip(records, values)) + 2**16
    free = free_bytes(os.path.dirname(os.path.abspath(output)))
    if free < 1.1 * needed + 2**20:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    f = None
    # a file left at the temporary name (a killed sweep's) is removed, not written through: a symlink
    # there had HDF5 overwrite the file it pointed to (red team); a directory there is the write's error
    if os.path.lexists(tmp) and not os.path.isdir(tmp):
        os.remove(tmp)
    try:
        f = h5py.File(tmp, "w")
        f.attrs["sweep"] = json.dumps({"scene": sweep["scene"], "parameters": sweep["parameters"]})
        for name in sweep["parameters"]:
            column = [case.get(name) for case in values]
            if all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in column):
                # NaN where a listed case leaves the base scene's value
                f.create_dataset(f"cases/parameters/{name}",
                                 data=np.array([np.nan if v is None else v for v in column], dtype=float))
            else:
                f.create_dataset(f"cases/parameters/{name}", data=[json.dumps(v) for v in column])
        f.create_dataset("cases/status", data=[r["status"] for r in records])
        f.create_dataset("cases/error", data=[r.get("error", "") for r in records])
        f.create_dataset("cases/wall_time", data=[r["wall_time"] for r in records])
        f.create_dataset("cases/warnings", data=["\n".join(r.get("warnings", [])) for r in records])
        # supports of two directions add the work rate (and what follows from it) to the 1-D statistics
        names = [*STATISTICS, *(k for k in STATISTICS_2D if k not in STATISTICS
                                and any(k in r.get("stats", {}) for r in records))]
        for name in names:
            table = np.full((n, width), np.nan)
            for i, r in enumerate(records):
                values = r.get("stats", {}).get(name, [])
                table[i, :len(values)] = values
            f.create_dataset(f"cases/stats/{name}", data=table)
        peaks = np.full((n, probes), np.nan)
        for i, r in enumerate(records):
            peak = np.asarray(r.get("probe_peak", []), dtype=float)
            if peak.ndim == 2:   # two planes: (y, z) peaks per probe; the summary keeps the larger
                peak = peak.max(axis=1)
            peaks[i, :peak.size] = peak
        f.create_dataset("cases/probe_peak", data=peaks)
        _units(f, sweep["parameters"])
        f.attrs["dbf_hpc_version"] = __version__
        f.attrs["complete"] = True
        f.close()
    except WRITE_ERRORS:
        # closed (as `with` did) or freed after a failed write, the file crashed HDF5 (signal 11; red team:
        # a summary on a disk the failed cases had left a few kB free)
        park(f)
        raise
    os.replace(tmp, output)
    return sum(r["status"] != "ok" for r in records)
