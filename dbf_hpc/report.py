"""What `dbf-hpc info` prints: a run's output (complete, or the .partial file of a run that did not
finish), or a sweep summary. Plain text lines from the HDF5 files; nothing here is collective."""
from __future__ import annotations

import json
import os

import h5py
import numpy as np

from . import layout
from .accuracy import KINDS_NOTE, percent
from .errors import InputError, lock_problem, not_a_regular_file
from .output import OutputLock, has_hdf5_signature

# The impact statistics a tube-vibration engineer reads first, with how to print them.
HEADLINE = (("impacts", "{:.0f} impacts"), ("impact_rate", "{:.3g}/s"), ("contact_fraction", "in contact {:.2%}"),
            ("force_rms", "force RMS {:.3g} N"), ("impact_power_mean", "impact power {:.3g} W"),
            ("work_rate", "work rate {:.3g} W"), ("work_rate_ci95", "+- {:.2g} W (95 %)"),
            ("wear_volume", "wear volume {:.3g} m^3"), ("wear_volume_ci95", "+- {:.2g} m^3 (95 %)"))


def open_output(path: str):
    """(open h5py file, complete?) of a run's output, or of its .partial file when only that exists
    (or when it is the file named)."""
    kind = not_a_regular_file(path)
    if kind is None:
        target = path
    elif not os.path.lexists(path) and not_a_regular_file(path + ".partial") is None:
        target = path + ".partial"
    else:   # red team: a named pipe, a device or a broken link "does not exist" (and a pipe is never opened)
        raise InputError(f"{path!r} {kind}" + ("" if kind.startswith("does not exist") else
                                               f": give it without the {os.sep!r}" if kind.startswith("ends in") else
                                               ", not a dbf-hpc output: give a run's output or a sweep's summary"))
    try:
        f = h5py.File(target, "r")
    except OSError as e:
        why = str(e).splitlines()[0]
        if not os.access(target, os.R_OK):   # red team: a file this user may not read "is not an HDF5 file"
            raise InputError(f"{target!r} cannot be read: permission denied (ask its owner, or read it as a user "
                             f"who may)") from None
        raise InputError(f"cannot open {target!r}: {lock_problem(e)}" if lock_problem(e) else
                         f"{target!r} cannot be read ({why}): a run killed before HDF5 wrote its first samples "
                         f"leaves it so; rerun the run (`--resume` continues from its checkpoint if one exists)"
                         if target.endswith(".partial") and has_hdf5_signature(target) else
                         f"{target!r} is damaged ({why})" if has_hdf5_signature(target) else
                         f"{target!r} is not an HDF5 file") from None
    try:
        holds_run = layout.TIME in f or "cases" in f
        if not holds_run:
            shapes = "shapes" in f and "dbf_hpc_version" in f.attrs
            # new-user pass: `info OUT.h5.checkpoint` and `info` on a cached basis said only "is not a
            # dbf-hpc output"; name what the file is and what reads it
            checkpoint = str(f.attrs.get("format", "")).startswith("dbf-hpc-checkpoint")
            cached = "V" in f and "key" in f.attrs and "dbf_hpc_version" in f.attrs
        complete = bool(f.attrs.get("complete", False))
    except (RuntimeError, KeyError) as e:   # it opens, and its root group's links or attributes cannot be read:
        f.close()                           # "internal error (RuntimeError)" in info and plot (red team)
        raise InputError(f"{target!r} is damaged ({str(e).splitlines()[0]})") from None
    if not holds_run:
        f.close()
        run = target[:-len(".checkpoint")] if target.endswith(".checkpoint") else "OUT.h5"
        raise InputError(f"{target!r} holds the mode shapes of a `dbf-hpc basis --xdmf`, not a run: open its .xdmf "
                         f"in ParaView" if shapes else
                         f"{target!r} is a run's checkpoint (its state, not its samples): give the run's output, "
                         f"{run!r}" if checkpoint else
                         f"{target!r} is a cached basis, not a run: `dbf-hpc cache list` describes it" if cached else
                         f"{target!r} is not a dbf-hpc output")
    return f, complete and not target.endswith(".partial")


def describe(path: str) -> list:
    """The lines `info` prints for a run's output or a sweep summary."""
    f, complete = open_output(path)
    run = path[:-len(".partial")] if path.endswith(".partial") else path   # its checkpoint is run.checkpoint
    with f:
        try:
            if "cases" in f:
                return _sweep_lines(path, f)
            return _run_lines(path, f) if complete else _partial_lines(run, f)
        # HDF5's metadata damaged (a write that failed on a full disk), a dataset's data address (an OSError:
        # "Can't read data (addr overflow ...)", which was an internal error; red team), an attribute's bytes
        except (RuntimeError, KeyError, OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
            raise InputError(f"{f.filename!r} is damaged ({str(e).splitlines()[0] if str(e) else type(e).__name__})") \
                from None


def _run_lines(path: str, f) -> list:
    stats, walls = json.loads(f.attrs["solver_stats"]), json.loads(f.attrs["wall_times"])
    t = f[layout.TIME][:]
    lines = [f"{path}: method {f.attrs['method']}, scene {f.attrs.get('scene_path', '?')}",
             f"  dbf-hpc {f.attrs['dbf_hpc_version']}, PETSc {f.attrs['petsc_version']}, "
             f"SLEPc {f.attrs['slepc_version']}, {f.attrs['mpi_ranks']} rank(s)"]
    if "basis" in f:
        kind = f.attrs.get("basis_enrichment", "dbf")
        extra = {"dbf": "DBFs", "static": "static modes", "none": "enrichment columns"}[kind]
        omega = f[layout.BASIS_OMEGA][:] / (2 * np.pi)
        enriched = layout.read(f, layout.BASIS_ENRICHMENT_OMEGA).size
        if "basis_complex_modes" in f.attrs:   # gyroscopic: Re and Im columns (gyroscopic_basis.py)
            lines.append(f"  basis: {int(f.attrs['basis_complex_modes'])} complex modes ({omega[0]:.4g} ... "
                         f"{omega[-1]:.4g} Hz), {f[layout.BASIS_DBF_K].size if kind != 'none' else 0} {extra}; "
                         + (f"state space: {omega.size + enriched} real states (A-orthonormal)"
                            if f.attrs.get("reduced_form") == "state_space" else
                            f"Re and Im: {omega.size + enriched} real columns"))
        else:
            lines.append(f"  basis: {omega.size} reference modes ({omega[0]:.4g} ... {omega[-1]:.4g} Hz), "
                         f"{enriched} {extra}")
        if layout.BASIS_FLEXIBILITY_CAPTURED in f and f[layout.BASIS_FLEXIBILITY_CAPTURED].size:
            flex = f[layout.BASIS_FLEXIBILITY_CAPTURED][:]
            lines.append("  static flexibility captured (a-priori indicator): "
                         + ", ".join(f"{v:.4f}" for v in flex))
    else:
        lines.append(f"  full-order model: {stats.get('dofs', '?')} DOFs")
    drawn = (f" (drawn on {f.attrs['field_cell_count']} {f.attrs['field_cells']} cells)"
             if "field_cells" in f.attrs and f[layout.SNAPSHOT_TIME].size else "")
    lines.append(f"  samples: {t.size} from {t[0]:g} to {t[-1]:g} s; snapshots: {f[layout.SNAPSHOT_TIME].size}{drawn}")
    scheme = "generalized-alpha" if stats["scheme"] == "alpha2" else f"ARKIMEX {stats['scheme']}"
    lines.append(f"  integrator: {scheme}, contact {stats['contact']}, {stats['steps']} steps, "
                 f"{stats['rejected_steps']} rejected, {stats['snes_failures']} Newton failures")
    lines.append("  wall time: " + ", ".join(f"{k} {v:.3g} s" for k, v in walls.items()))
    lines += _estimate_lines(f)
    # what the run warned, that its result may be wrong (an output written before they were stored has none)
    lines += [f"  warning: {w}" for w in str(f.attrs.get("warnings", "")).split("\n") if w]
    return lines + _constraint_lines(f) + _probe_lines(f)


def _estimate_lines(f) -> list:
    """The a-posteriori estimate (accuracy.py), when the run carries one."""
    if "estimated_error" not in f.attrs:
        return []
    value, window = float(f.attrs["estimated_error"]), float(f.attrs.get("estimated_error_window", np.nan))
    if not np.isfinite(value):
        return [f"  estimated error: not available ({f.attrs.get('estimated_error_note', '')})"]
    kind = " of its kind" if KINDS_NOTE in str(f.attrs.get("estimated_error_note", "")) else ""
    return [f"  estimated error in w at the constraints: {value:.3g} ({percent(value)} of the largest |w|{kind} at any "
            f"constraint) over [0, {window:g}] s "
            f"({f.attrs.get('estimated_error_note', '')})"] + _statistics_error_lines(f)


def _statistics_error_lines(f) -> list:
    """A long run's statistics' errors (accuracy.StatisticsEstimate), when it carries them."""
    from .accuracy import ESTIMATED_STATISTICS_2D, statistics_lines

    if layout.STATISTICS_ERROR not in f:
        return []
    group, stats = f[layout.STATISTICS_ERROR], f.get(layout.CONSTRAINT_STATS)
    error = {name: group[name][:] for name in ESTIMATED_STATISTICS_2D if name in group}
    values = {name: stats[name][:] for name in error if stats is not None and name in stats}
    window = float(f.attrs.get("estimated_statistics_window", np.nan))
    head = (f"  statistics' estimated errors (run's 95 % CI + |richer - reduced| over [0, {window:g}] s + both CIs; "
            f"{f.attrs.get('estimated_statistics_note', '')}):")
    return [head] + ["  " + line for line in statistics_lines(error, values)]


def _constraint_lines(f, partial: bool = False) -> list:
    z, force = f[layout.CONSTRAINT_DISPLACEMENT][:], f[layout.CONSTRAINT_FORCE_PEAK][:]
    # a .partial has no positions yet (written at the end): constraints by number only
    where = ([_at(f, x) for x in f[layout.CONSTRAINT_POSITION][:]] if layout.CONSTRAINT_POSITION in f
             else [""] * z.shape[1])
    stats = f.get(layout.CONSTRAINT_STATS)
    lines = []
    for j, at in enumerate(where):
        if z.ndim == 3:   # a support of two directions (y, z): radial values
            # the samples hold each direction's peak over an interval, reached at different instants:
            # their hypot bounds |F| from above; the statistics hold the peak of |F| itself
            peak = (f"peak |F| {stats['force_peak'][j]:.6g} N" if stats is not None and not partial
                    and "force_peak" in stats else f"peak |F| at most {np.hypot(*force[:, j].T).max():.6g} N")
            line = f"  constraint {j + 1}{at}: max |u| {np.hypot(*z[:, j].T).max():.6g} m, {peak}"
        else:
            line = (f"  constraint {j + 1}{at}: w in [{z[:, j].min():.6g}, {z[:, j].max():.6g}] m, "
                    f"peak force {np.abs(force[:, j]).max():.6g} N")
        if stats is not None and not partial:
            line += "; " + ", ".join(fmt.format(stats[name][j]) for name, fmt in HEADLINE
                                     if name in stats and not (name.startswith("wear") and np.isnan(stats[name][j])))
        lines.append(line)
    return lines


def _at(f, position) -> str:
    """Where a constraint or probe is, in words: x on a beam (m), else the DOF."""
    try:
        beam = json.loads(f.attrs.get("scene_effective", "{}")).get("structure", {}).get("kind", "beam") == "beam"
    except (TypeError, ValueError):
        beam = True
    return f" at {position:g} m" if beam else f" at DOF {int(position)}"


def _probe_lines(f) -> list:
    if layout.PROBE_DISPLACEMENT not in f or not f[layout.PROBE_DISPLACEMENT].shape[1]:
        return []
    w = f[layout.PROBE_DISPLACEMENT][:]
    positions = f[layout.PROBE_POSITION][:] if layout.PROBE_POSITION in f else np.arange(w.shape[1])
    if w.ndim == 3:   # (y, z) at each probe
        return [f"  probe{_at(f, x)}: peak |(y, z)| {np.hypot(*w[:, p].T).max():.6g} m" for p, x in enumerate(positions)]
    return [f"  probe{_at(f, x)}: peak |w| {np.abs(w[:, p]).max():.6g} m" for p, x in enumerate(positions)]


def _partial_lines(path: str, f) -> list:
    t = f[layout.TIME][:] if layout.TIME in f else np.zeros(0)
    # Red team: read while its run was still going (HDF5_USE_FILE_LOCKING=FALSE), a .partial said "a
    # checkpoint exists: rerun with --resume", which the run's lock then refused
    holder = OutputLock(path).live_holder()
    lines = [f"{path}.partial: INCOMPLETE: " + (f"being written by a run now ({holder}; {path}.lock)" if holder else
                                                "the run did not finish") + f" ({t.size} samples"
             + (f" up to t = {t[-1]:g} s)" if t.size else ")"),
             f"  wait for that run to end, or remove {path}.lock if it is gone" if holder else
             "  a checkpoint exists: rerun with --resume to continue" if os.path.exists(path + ".checkpoint")
             else "  no checkpoint: a rerun starts from t = 0"]
    if t.size and layout.CONSTRAINT_DISPLACEMENT in f:
        lines += _constraint_lines(f, partial=True)
    return lines


def _sweep_lines(path: str, f) -> list:
    meta = json.loads(f.attrs["sweep"])
    status = [s.decode() if isinstance(s, bytes) else s for s in f["cases/status"][:]]
    errors = [e.decode() if isinstance(e, bytes) else e for e in f["cases/error"][:]]
    names = meta["parameters"]
    lines = [f"{path}: sweep of {meta['scene']}, {len(status)} cases ({status.count('ok')} ok, "
             f"{len(status) - status.count('ok')} failed)", f"  parameters: {', '.join(names)}"]
    peak = f["cases/stats/displacement_peak"][:]
    impacts = f["cases/stats/impacts"][:]
    force = f["cases/stats/force_peak"][:]
    columns = {name: f[f"cases/parameters/{name}"][:] for name in names}
    warned = [w.decode() if isinstance(w, bytes) else w for w in f["cases/warnings"][:]] if "cases/warnings" in f \
        else [""] * len(status)
    for i, state in enumerate(status):
        values = ", ".join(f"{name.split('.')[-1]} {_value(columns[name][i])}" for name in names
                           if not _missing(columns[name][i]))
        if state == "ok":
            lines.append(f"  case {i + 1} ({values}): max |w| {np.nanmax(peak[i]):.4g} m, "
                         f"{np.nansum(impacts[i]):.0f} impacts at the {impacts.shape[1]} constraint(s) together, "
                         f"peak force {np.nanmax(force[i]):.4g} N"
                         + _work_summary(f, i))
            lines += [f"    warning: {w}" for w in warned[i].split("\n") if w]
        else:
            lines.append(f"  case {i + 1} ({values}): FAILED: {errors[i]}")
    return lines


def _work_summary(f, i: int) -> str:
    """Supports of two directions: the largest work rate over the supports with its 95 % interval (and
    the wear volume there, when a wear coefficient was given)."""
    if "cases/stats/work_rate" not in f:
        return ""
    rate = f["cases/stats/work_rate"][i]
    if not np.any(np.isfinite(rate)):
        return ""
    j = int(np.nanargmax(rate))
    text = f", max work rate {rate[j]:.3g} W"
    if "cases/stats/work_rate_ci95" in f:
        text += f" +- {f['cases/stats/work_rate_ci95'][i, j]:.2g} W"
    text += f" (constraint {j + 1})"
    if "cases/stats/wear_volume" in f and np.isfinite(f["cases/stats/wear_volume"][i, j]):
        text += f", wear volume {f['cases/stats/wear_volume'][i, j]:.3g} m^3"
    return text


def _missing(v) -> bool:
    """A listed case that leaves the base scene's value: NaN (numbers) or null (others)."""
    if isinstance(v, bytes):
        return json.loads(v.decode()) is None
    return v is None or (isinstance(v, (float, np.floating)) and np.isnan(v))


def _value(v) -> str:
    if isinstance(v, bytes):
        return json.loads(v.decode())
    return f"{v:g}" if isinstance(v, (float, np.floating)) else str(v)
