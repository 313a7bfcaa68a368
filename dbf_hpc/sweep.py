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

Each case is the base scene with its values set (as `--set section.key=value`). With continuation,
the cases along that axis form chains, one per direction and per combination of the other axes:
each case starts from the previous one's final state (a stepped-sine sweep, which reveals the
hysteresis and jumps of an impacting structure; each step restarts the excitation at phase 0); the
summary gets a `sweep_direction` column.

How it runs (collective on COMM_WORLD):
1. Every case's scene is validated before any work: a bad value stops the sweep at once.
2. The distinct bases (cases that differ only in law, excitation, damping or integrator share one)
   are built once, in parallel over all ranks, into the basis cache.
3. The cases are dealt round-robin to the ranks; each rank runs its cases alone (COMM_SELF),
   reading the basis from the cache. A failed case is recorded with its error; the others go on.
4. Each finished case leaves a small result file next to the summary (`OUT.cases/case-NNNNN.json`,
   written atomically), so a killed sweep rerun skips what is done. Rank 0 then writes the summary.
"""
from __future__ import annotations

import itertools
import json
import os
import time
import tomllib

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .cache import basis_key, obtain_basis
from .errors import DbfError, InputError
from .model import build_operators, constraint_rows, operators_fingerprint
from .scene import load_scene, parse_override
from .stats import STATISTICS

SWEEP_KEYS = {"scene", "output", "keep_outputs", "axes", "case", "continuation", "directions"}
DIRECTION = "sweep_direction"


def load_sweep(path: str) -> dict:
    """Read a sweep file: {'scene', 'output', 'keep_outputs', 'cases': [[override, ...], ...],
    'parameters': [name, ...]}. All case scenes are validated here."""
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise InputError(f"cannot read sweep {path!r}: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: not valid TOML: {e}") from None
    for key in data:
        if key not in SWEEP_KEYS:
            raise InputError(f"{path}: unknown key '{key}' (sweep files have {', '.join(sorted(SWEEP_KEYS))})")
    folder = os.path.dirname(os.path.abspath(path))
    if "scene" not in data:
        raise InputError(f"{path}: scene (the base scene file) is required")
    scene = os.path.join(folder, data["scene"])
    output = os.path.join(folder, data.get("output", os.path.splitext(os.path.basename(path))[0] + ".h5"))
    axes = data.get("axes", {})
    listed = data.get("case", [])
    if not isinstance(axes, dict) or not isinstance(listed, list):
        raise InputError(f"{path}: [axes] is a table of lists and [[case]] an array of tables")
    for name, values in axes.items():
        if not isinstance(values, list) or not values:
            raise InputError(f"{path}: axis '{name}' must be a non-empty list of values")
    continuation = data.get("continuation")
    directions = data.get("directions", ["up", "down"])
    if continuation is not None and continuation not in axes:
        raise InputError(f"{path}: continuation '{continuation}' is not one of the [axes]")
    if not (isinstance(directions, list) and directions and set(directions) <= {"up", "down"}):
        raise InputError(f"{path}: directions must be a list of \"up\" and/or \"down\"")
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
        names = list(axes)
        for combo in itertools.product(*axes.values()):
            chains.append([len(cases)])
            cases.append(dict(zip(names, combo)))
    for c in listed:
        chains.append([len(cases)])
        cases.append(dict(c))
    if not cases:
        raise InputError(f"{path}: no cases: give [axes] or [[case]] entries")
    parameters = list(dict.fromkeys(name for case in cases for name in case))
    overrides = []
    for i, case in enumerate(cases):
        sets = [f"{name}={_toml_value(value)}" for name, value in case.items() if name != DIRECTION]
        for text in sets:
            parse_override(text)
        try:
            load_scene(scene, sets)
        except InputError as e:
            raise InputError(f"{path}: case {i + 1} ({', '.join(sets)}): {e}") from None
        overrides.append(sets)
    return {"scene": scene, "output": output, "keep_outputs": bool(data.get("keep_outputs", False)),
            "cases": overrides, "values": cases, "parameters": parameters, "chains": chains}


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


def _write_json(path: str, content: dict) -> None:
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(content, f)
    os.replace(tmp, path)


def _prepare_bases(sweep: dict, cache_dir: str, pending: list) -> None:
    """Build every distinct basis the pending cases need, once, on COMM_WORLD (into the cache)."""
    done = set()
    for index in pending:
        scene = load_scene(sweep["scene"], sweep["cases"][index] + [f"basis.cache={json.dumps(cache_dir)}"])
        ops = build_operators(scene, PETSc.COMM_WORLD)
        rows = constraint_rows(scene, ops)
        fingerprint = operators_fingerprint(scene, ops)
        key = basis_key(fingerprint, rows, scene.basis_settings())
        if key not in done:
            basis = obtain_basis(ops, rows, scene.basis_settings(), fingerprint, cache_dir,
                                 [c.label for c in scene.constraints])
            basis.destroy()
            done.add(key)
        ops.destroy()


def run_sweep(path: str, progress: bool = True) -> dict:
    """Run (or resume) a sweep. Collective on COMM_WORLD. Returns {'output', 'cases', 'failed'}."""
    from .run import run

    world = MPI.COMM_WORLD
    sweep = load_sweep(path)
    output = sweep["output"]
    folder = output + ".cases"
    if world.rank == 0:
        if not os.path.isdir(os.path.dirname(os.path.abspath(output))):
            folder = None
        else:
            os.makedirs(folder, exist_ok=True)
    folder = world.bcast(folder, root=0)
    if folder is None:
        raise InputError(f"sweep output {output!r}: its directory does not exist")
    n = len(sweep["cases"])
    pending = [i for i in range(n) if not os.path.exists(_case_file(folder, i))]
    say = (lambda m: PETSc.Sys.Print(m)) if progress else (lambda m: None)
    say(f"dbf-hpc sweep: {n} cases, {n - len(pending)} already done, {len(pending)} to run on {world.size} rank(s)")

    base = load_scene(sweep["scene"])
    cache_dir = base.cache_dir() or os.path.join(folder, "basis-cache")
    t0 = time.perf_counter()
    _prepare_bases(sweep, cache_dir, pending)
    say(f"bases ready ({time.perf_counter() - t0:.1f} s)")

    # Work units are chains (a single case unless continuation links them), dealt round-robin.
    chains = [c for c in sweep["chains"] if any(i in pending for i in c)]
    mine = chains[world.rank::world.size]
    start, done_here, total_here = time.perf_counter(), 0, sum(len(c) for c in mine)
    for chain in mine:
        state = None
        for index in chain:
            if index not in pending:  # finished before a kill: continue from its final state
                with open(_case_file(folder, index)) as f:
                    state = json.load(f).get("final_state")
                continue
            sets = sweep["cases"][index] + [f"basis.cache={json.dumps(cache_dir)}"]
            case_out = os.path.join(folder, f"case-{index:05d}.h5")
            record = {"index": index, "parameters": sweep["values"][index], "continued": state is not None}
            t = time.perf_counter()
            try:
                scene = load_scene(sweep["scene"], sets)
                summary = run(scene, case_out, progress=False, comm=PETSc.COMM_SELF,
                              initial_state=state if len(chain) > 1 else None)
                record.update(status="ok", stats=summary["constraint_stats"], probe_peak=summary["probe_peak"],
                              solver=summary["stats"], final_state=summary["final_state"])
                state = summary["final_state"]
            except DbfError as e:
                record.update(status="failed", error=str(e))
                state = None  # the chain goes on from rest
            record["wall_time"] = time.perf_counter() - t
            if not sweep["keep_outputs"] and os.path.exists(case_out):
                os.remove(case_out)
            _write_json(_case_file(folder, index), record)
            done_here += 1
            if progress and world.rank == 0:
                finished = sum(os.path.exists(_case_file(folder, i)) for i in range(n))
                elapsed = time.perf_counter() - start
                eta = elapsed / done_here * (total_here - done_here)
                print(f"  cases done: {finished}/{n}, ETA {eta:.0f} s", flush=True)
    world.Barrier()
    failed = 0
    if world.rank == 0:
        failed = _write_summary(sweep, folder, output)
        print(f"dbf-hpc sweep: wrote {output} ({n} cases, {failed} failed)", flush=True) if progress else None
    return world.bcast({"output": output, "cases": n, "failed": failed}, root=0)


def _write_summary(sweep: dict, folder: str, output: str) -> int:
    """The summary HDF5, a row per case: parameters, status, statistics per constraint."""
    import h5py

    records = []
    for i in range(len(sweep["cases"])):
        with open(_case_file(folder, i)) as f:
            records.append(json.load(f))
    n = len(records)
    width = max((len(r.get("stats", {}).get("impacts", [])) for r in records), default=0)
    probes = max((len(r.get("probe_peak", [])) for r in records), default=0)
    tmp = f"{output}.partial"
    with h5py.File(tmp, "w") as f:
        f.attrs["sweep"] = json.dumps({"scene": sweep["scene"], "parameters": sweep["parameters"]})
        for name in sweep["parameters"]:
            values = [r["parameters"].get(name) for r in records]
            if all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in values):
                # NaN where a listed case leaves the base scene's value
                f.create_dataset(f"cases/parameters/{name}",
                                 data=np.array([np.nan if v is None else v for v in values], dtype=float))
            else:
                f.create_dataset(f"cases/parameters/{name}", data=[json.dumps(v) for v in values])
        f.create_dataset("cases/status", data=[r["status"] for r in records])
        f.create_dataset("cases/error", data=[r.get("error", "") for r in records])
        f.create_dataset("cases/wall_time", data=[r["wall_time"] for r in records])
        for name in STATISTICS:
            table = np.full((n, width), np.nan)
            for i, r in enumerate(records):
                values = r.get("stats", {}).get(name, [])
                table[i, :len(values)] = values
            f.create_dataset(f"cases/stats/{name}", data=table)
        peaks = np.full((n, probes), np.nan)
        for i, r in enumerate(records):
            peaks[i, :len(r.get("probe_peak", []))] = r.get("probe_peak", [])
        f.create_dataset("cases/probe_peak", data=peaks)
        f.attrs["complete"] = True
    os.replace(tmp, output)
    return sum(r["status"] != "ok" for r in records)
