"""Basis cache: a basis is computed once per structure, constraint set and basis settings, and reused
by every run that changes only the law, the excitation, damping or the integrator (paper,
conclusion 2).

A cache file `basis-<key>.h5` holds V (n x r), the frequencies, k_j, the constraint rows, the
settings and the full key; r is the number of columns actually present (the modes and one column
per constraint, or the modes alone for enrichment = "none"). It is written under a temporary name
and renamed when complete, so a crash never leaves a file that looks usable. The whole file is
sealed: a sha256 of everything after HDF5's user block is written in that block (sealed.py), and checked
before HDF5 parses the file, since HDF5 crashes the process (a segmentation fault, not an error) on
some damaged metadata. On load, the key and the stored constraint rows must match what is asked,
and the basis must still be what it claims: V^T M V = I (to VERIFY_TOL beyond the basis's own
defect, stored with it: many modes carry SLEPc's, amplified by Gram-Schmidt), and diag(V^T K V) =
omega^2 for the modes and hat-omega^2 for the other columns, on the operators at hand; what those
cannot check (k_j, k_auto, the branches, f_exact) carries a sha256 written with it. Anything else
(stale, corrupt, unreadable, or from an older version) is reported and rebuilt, never used. The key
holds the kind of enrichment and only the settings and solver options that kind uses. A gyroscopic
basis in the second-order form (gyroscopic_basis.py) is cached too: its file adds the complex-mode
count and the columns of each constraint, and on load its reduced model must still have the stored
complex frequencies. So is the state-space basis (state_space.py; its own algorithm name in the key):
its file holds the velocity and displacement parts Psi_v, Psi_w (n x r each, no V), the raw DBFs d_R,
d_I (n x N_L each) and their varpi (what the error estimate's richer basis reuses), and the attribute
form = "state_space"; on load Psi^T A Psi = I, its reduced A_r eta' + B_r eta = 0 (conservative B)
must have the stored complex frequencies, each DBF pair its stored hat-omega (Eq. 20) and each raw
DBF's state vectors must lie in span Psi (_state_space_problem). Two builds of it may differ at
round-off (4e-8 measured on a CI machine), and a --resume, whose checkpoint holds what the reduced
coordinates mean, needs the very basis its run had: the cache gives it. The error estimate's richer
bases take their reference modes from the cache too (obtain_modes): an entry of that many modes without
enrichment or constraint rows; a gyroscopic structure's richer basis (complex modes, either form) is an
entry of its own, whole (obtain_richer), so that a resumed run's estimate is the uninterrupted run's.

All functions are collective on ops.comm.
"""
from __future__ import annotations

import hashlib
import json
import os
import re

import h5py
import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from . import __version__, sealed
from .basis import BasisSettings, ReducedBasis, build_basis, check_pairs
from .checkpoint import arrays_sha256
from .errors import (WRITE_ERRORS, InputError, decided_on_rank0, from_rank0, lock_problem, park, refused_lock,
                     temporary_tag, warn, write_failure)
from .output import check_free_space, has_hdf5_signature
from .operators import Operators
from .petsctools import destroy

# Bump when the construction changes what a basis is (an older file then has another key).
# 4: enrichment strategies; hat-omega of every enrichment column as enrichment_omega. 5: f_exact of
# every constraint (the captured-flexibility indicator, accuracy.py).
ALGORITHM = "dbf-basis-5"
VERIFY_TOL = 1e-8
SEAL = b"dbf-hpc basis cache sha256 "   # the tag of the file's seal (sealed.py)
ARRAYS = ("omega", "enrichment_omega", "dbf_k", "dbf_k_auto", "dbf_branch", "constraint_rows", "flexibility_exact")


def solver_options(prefixes=("modes_", "dbf_"), observers: bool = False) -> dict:
    """The PETSc options under `prefixes` that can change a basis (those of the solvers it uses); with
    observers, also those that only show a solve (-modes_eps_view, -..._monitor, -..._converged_reason:
    they change no number, so they are no part of the key; helper L's red team: -modes_eps_view made
    every run build the basis again)."""
    prefixes = tuple(prefixes)
    return {k: v for k, v in sorted(PETSc.Options().getAll().items())
            if k.startswith(prefixes) and (observers or not _observes(k))}


def _observes(name: str) -> bool:
    """Whether a PETSc option only shows a solve (a viewer, a monitor, the converged reason)."""
    words = name.split("_")
    return "view" in words or any(w.startswith("monitor") for w in words) or name.endswith("converged_reason")


def _mark_used(options: dict) -> None:
    """Read each of a cache hit's key options once, so that PETSc counts it used: they found the
    basis, and the run that built it read them (and warned of any no solver read). Red team: a hit
    warned that -modes_eps_tol was "not used: a misspelling". Not collective."""
    database = PETSc.Options()
    for name in options:
        database.getString(name, "")


def basis_key(fingerprint: dict, rows, settings: BasisSettings, gyroscopic: bool = False,
              whole: str = "refuse", richer_of: dict | None = None) -> str:
    """sha256 of everything that determines the basis (the options only of the solvers its kind uses),
    and the package version (a release may build it otherwise without a new ALGORITHM).
    A gyroscopic basis has its own algorithm name, one per form (second order, state space: settings.key()
    has no gyroscopic_form, which only a gyroscopic structure reads): its operators' fingerprint
    already holds U, m_t and T (a beam) or G's bytes (matrices). `whole` = "extend" (obtain_modes: a
    count inside a repeated frequency taken to its end) is part of the key; a user's count ("refuse")
    keeps the key it had (red team: the estimate's 6 modes stored for a count of 5 served a run asking
    5 modes alone, which without the cache is refused, as 5 cut a pair). `richer_of`: the settings key of
    the run's basis whose error-estimate richer basis this is (obtain_richer: its enrichment columns are
    that basis', not its own)."""
    form = "-state-space" if gyroscopic and settings.gyroscopic_form == "state_space" else ""
    content = {"algorithm": ALGORITHM + ("-gyroscopic" if gyroscopic else "") + form, "version": __version__,
               "operators": fingerprint,
               "rows": [int(r) for r in rows], "settings": settings.key(),
               "options": solver_options(settings.strategy.solver_prefixes),
               **({"whole": whole} if whole != "refuse" else {}),
               **({"richer_of": richer_of} if richer_of is not None else {})}
    return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()


def seal(path: str) -> None:
    """Seal a basis file (sealed.py; save() does it before the rename). Not collective."""
    sealed.seal(path, SEAL)


def seal_problem(path: str) -> str | None:
    """Why the basis file's seal does not hold (None if it does), read without HDF5. Not collective."""
    return sealed.seal_problem(path, SEAL, "this cache")


def _say(comm, message: str) -> None:
    PETSc.Sys.Print(f"dbf-hpc: {message}", comm=comm)




def _is_state_space(basis_or_settings, ops: Operators | None = None) -> bool:
    """Whether a basis is the state-space one (state_space.py), or settings ask for it on `ops`."""
    if ops is None:
        return getattr(basis_or_settings, "form", "") == "state_space"
    return ops.G is not None and basis_or_settings.gyroscopic_form == "state_space"


def _columns(basis) -> tuple:
    """(global rows n, this rank's first row, {dataset: this rank's rows of its columns}) of a basis: V
    (n x r), or the state-space basis' velocity and displacement parts (n x r each) and its raw DBFs
    d_R, d_I (n x N_L each: what the error estimate's richer basis reuses, state_space.richer_state_space_basis).
    Collective (a BV's dense matrix)."""
    if _is_state_space(basis):
        from .state_space import _local

        lo, hi = basis.displacement[0].getOwnershipRange()

        def local(vecs):
            return _local(vecs) if vecs else np.zeros((hi - lo, 0))

        return basis.displacement[0].getSize(), lo, {
            "velocity": local(basis.velocity), "displacement": local(basis.displacement),
            "dbf_raw_real": local([d[0] for d in basis.raw]), "dbf_raw_imag": local([d[1] for d in basis.raw])}
    dense = basis.vectors.getMat()
    lo, _ = dense.getOwnershipRange()
    local = dense.getDenseArray().copy()
    basis.vectors.restoreMat(dense)
    return basis.vectors.getSizes()[0][1], lo, {"V": local}


def save(basis, path: str, key: str, comm, defect: float = 0.0) -> str | None:
    """Write the basis (a ReducedBasis, or a state_space.StateSpaceBasis: _columns) to `path` atomically
    (a temporary file, fsync, then rename), rank 0 writing every rank's rows in turn (memory: one
    rank's block). `defect` is the basis's own max|V^T M V - I| (state space: max|Psi^T A Psi - I|;
    load allows that much plus VERIFY_TOL). Returns None, or why it could not be written (every rank
    gets the same answer; no temporary file is left). Any other exception rank 0 meets (a bug, an h5py
    error no write foresaw) is raised on every rank (errors.from_rank0), the temporary file removed.
    Collective."""
    world = comm.tompi4py()
    n, lo, local = _columns(basis)
    state = _is_state_space(basis)
    tmp = f"{path}.tmp-{temporary_tag()}"
    error, unexpected, f, V = None, [], None, {}
    if world.rank == 0:
        try:
            check_free_space(path, 8.0 * n * sum(block.shape[1] for block in local.values()), "basis cache")
            f = h5py.File(tmp, "w", userblock_size=sealed.USERBLOCK)
            V = {name: f.create_dataset(name, shape=(n, block.shape[1]), dtype="f8") for name, block in local.items()}
            arrays = {name: np.asarray(getattr(basis, name)) for name in ARRAYS}
            if basis.complex_modes:   # a gyroscopic basis: Re and Im columns (gyroscopic_basis.py)
                arrays["constraint_columns"] = np.asarray(basis.stats["constraint_columns"], dtype=np.int64)
                arrays["complex_omega"] = np.asarray(basis.stats["complex_omega"], dtype=float)
                arrays["complex_modes"] = np.int64(basis.complex_modes)
                f.attrs["complex_modes"] = basis.complex_modes
            if state:   # varpi of each raw DBF (state_space._basis), and the form
                arrays["dbf_varpi"] = np.asarray([d[2] for d in basis.raw], dtype=float)
                f.attrs["form"] = "state_space"
            for name, value in arrays.items():
                if name != "complex_modes":
                    f.create_dataset(name, data=value)
            # V is checked on load against the operators (V^T M V = I, its frequencies); these are not
            f.attrs["arrays_sha256"] = arrays_sha256(arrays)
            f.attrs["key"] = key
            f.attrs["orthonormality_defect"] = float(defect)
            f.attrs["settings"] = json.dumps(basis.settings.key(), default=str)
            f.attrs["dbf_hpc_version"] = __version__
        except InputError:
            error = "not enough free space on its file system"
        except WRITE_ERRORS as e:
            error = write_failure(e)
        except BaseException as e:   # every rank raises it below (red team: it left the others in the bcast)
            error = type(e).__name__
            unexpected.append(e)
    for rank in range(world.size):
        start, blocks = (lo, local) if rank == 0 else (world.recv(source=rank) if world.rank == 0 else (None, None))
        if world.rank == rank and rank > 0:
            world.send((lo, local), dest=0)
        if world.rank == 0 and error is None:
            try:
                for name, block in blocks.items():
                    V[name][start:start + block.shape[0], :] = block
            except WRITE_ERRORS as e:
                error = write_failure(e)
            except BaseException as e:
                error = type(e).__name__
                unexpected.append(e)
    if world.rank == 0:
        try:
            error = _close_and_rename(f, list(V.values()), tmp, path, error)
        except BaseException as e:
            unexpected[:] = unexpected or [e]
    return from_rank0(world, error, unexpected)


def _close_and_rename(f, datasets: list, tmp: str, path: str, error: str | None) -> str | None:
    """Rank 0: finish the temporary file and move it into place, or remove it (also when it raises)."""
    done = False
    try:
        if f is not None:
            f.close()
        if error is None:
            seal(tmp)
            with open(tmp, "rb") as handle:
                os.fsync(handle.fileno())
            os.replace(tmp, path)
        done = True
    except WRITE_ERRORS as e:
        error = write_failure(e)
        park(f, *datasets)
    finally:
        if (error is not None or not done) and os.path.exists(tmp):
            os.remove(tmp)
    return error


def _read(path: str, key: str, ops: Operators, rows, settings: BasisSettings, checked: bytes,
          whole: str = "refuse"):
    """(problem or None, the small arrays, {dataset: this rank's rows}: V, or the state-space basis'
    parts (_columns)) of a cache file whose user block is `checked` (the file rank 0 checked: another
    job may have stored the entry again since, and each rank would read its own file, a mix of two
    bases). A count of modes asked (not max_frequency_hz) must be the count held, or with `whole` =
    "extend" at most it."""
    lo, hi = ops.K.getOwnershipRange()
    state = _is_state_space(settings, ops)
    try:
        with h5py.File(path, "r") as f:
            if sealed.user_block_of_open(f) != checked:
                return "was stored again by another job while this one read it", {}, None
            if f.attrs.get("key") != key:
                return "was made for other operators or settings", {}, None
            if (f.attrs.get("form") == "state_space") != state:
                return "has the wrong shape", {}, None
            arrays = {name: f[name][...] for name in ARRAYS}
            defect = float(f.attrs["orthonormality_defect"])
            if not (np.isfinite(defect) and defect >= 0.0):
                return "has the wrong shape", {}, None
            enriched = settings.strategy.count(len(rows))
            if not np.array_equal(arrays["constraint_rows"], rows):
                return "holds other constraint rows (corrupt)", {}, None
            columns = enriched
            if ops.G is not None:   # one or two real columns per constraint
                if "constraint_columns" not in f or "complex_modes" not in f.attrs:
                    return "has the wrong shape", {}, None
                if "complex_omega" not in f:   # each complex mode's frequency: a file without it is rebuilt once
                    return "was written by an older version (no complex_omega)", {}, None
                arrays["constraint_columns"] = f["constraint_columns"][...]
                arrays["complex_modes"] = int(f.attrs["complex_modes"])
                arrays["complex_omega"] = f["complex_omega"][...]
                counts = arrays["constraint_columns"]
                columns = int(counts.sum())
                if (counts.size != enriched or np.any((counts < 1) | (counts > 2))
                        or arrays["complex_omega"].size != arrays["complex_modes"]):
                    return "has the wrong shape", {}, None
            names = ("V",)
            if state:   # the velocity and displacement parts, and the raw DBFs with their varpi
                names = ("velocity", "displacement", "dbf_raw_real", "dbf_raw_imag")
                arrays["dbf_varpi"] = f["dbf_varpi"][...]
                if arrays["dbf_varpi"].size != enriched:
                    return "has the wrong shape", {}, None
            stored = dict(arrays)
            if "complex_modes" in stored:
                stored["complex_modes"] = np.int64(stored["complex_modes"])
            if f.attrs.get("arrays_sha256") != arrays_sha256(stored):
                return "fails its checksum (corrupt, or written by an older version)", {}, None
            width = arrays["omega"].size + columns
            shapes = {name: (ops.size, enriched if name.startswith("dbf_raw") else width) for name in names}
            if (arrays["enrichment_omega"].size != columns
                    or any(f[name].shape != shape for name, shape in shapes.items())
                    or any(arrays[name].size != enriched for name in ("dbf_k", "dbf_k_auto", "dbf_branch"))
                    or arrays["flexibility_exact"].size != len(rows)):
                return "has the wrong shape", {}, None
            held = arrays["omega"].size
            if ops.G is None and settings.max_frequency_hz is None and (
                    held < settings.modes or (whole == "refuse" and held != settings.modes)):
                # an entry of 0.2.3's error estimate (a repeated frequency taken whole) under a run's key
                return f"holds {held} modes, not the {settings.modes} asked", {}, None
            return None, {**arrays, "orthonormality_defect": defect}, {name: f[name][lo:hi, :] for name in names}
    except (OSError, KeyError, ValueError) as e:
        return f"cannot be read ({lock_problem(e) or type(e).__name__})", {}, None


def load(path: str, key: str, ops: Operators, settings: BasisSettings, rows,
         whole: str = "refuse") -> ReducedBasis | None:
    """The cached basis if `path` holds a valid one for `key` and `rows` on these operators, else
    None (and a line saying why). Everything it carries is checked against what is asked now: the
    key, the constraint rows, the shapes (the count of modes, `whole` as build_basis's), V^T M V = I
    and the frequencies on these operators."""
    world = ops.comm.tompi4py()
    # the seal first, on rank 0 alone: HDF5 must not parse a damaged file (it may crash the process)
    problem, checked = decided_on_rank0(world, sealed.check, path, SEAL, "this cache")
    arrays, blocks = {}, None
    if not problem:
        problem, arrays, blocks = _read(path, key, ops, np.asarray(rows, dtype=np.int64), settings, checked,
                                        whole)
    problem = next((p for p in world.allgather(problem) if p), None)
    if problem:
        _say(ops.comm, f"basis cache {path} {problem}; rebuilding it")
        return None
    if _is_state_space(settings, ops):
        basis = _state_space_basis(ops, settings, arrays, blocks, path)
        problem = _state_space_problem(basis, ops, arrays["orthonormality_defect"])
        if problem:
            _say(ops.comm, f"basis cache {path} does not match the operators ({problem}: corrupt or stale); "
                           f"rebuilding it")
            basis.destroy()
            return None
        _touch(path, world)
        return basis
    block = blocks["V"]
    r = block.shape[1]
    V = SLEPc.BV().create(comm=ops.comm)
    template = ops.K.createVecRight()
    V.setSizesFromVec(template, r)
    V.setType(SLEPc.BV.Type.SVEC)
    V.setMatrix(ops.M, False)
    for j in range(r):
        template.array[:] = block[:, j]
        V.insertVec(j, template)
    template.destroy()
    stats = {"cache": "hit", "cache_file": path}
    if ops.G is not None:
        stats.update(complex_modes=arrays["complex_modes"], constraint_columns=arrays["constraint_columns"].tolist(),
                     complex_omega=arrays["complex_omega"].tolist())
    basis = ReducedBasis(vectors=V, settings=settings, stats=stats, **{name: arrays[name] for name in ARRAYS})
    G, Kr = basis.project(ops.M), basis.project(ops.K)
    basis.set_flexibility(arrays["flexibility_exact"], Kr)
    if ops.G is None:
        # relative to each frequency, and to round-off of the largest for rigid-body modes (omega^2 at
        # 1e-7 beside 1e6 on a free-free beam: recomputed, another round-off; red team)
        stored = np.concatenate([basis.omega**2, basis.enrichment_omega**2])
        floor = VERIFY_TOL * float(np.abs(stored).max(initial=0.0))
        frequencies = np.allclose(np.diag(Kr), stored, rtol=VERIFY_TOL * 100, atol=floor)
    else:
        frequencies = _holds_complex_modes(Kr, basis.project(ops.G), basis.omega)
    # as M-orthonormal as when it was stored (many modes: SLEPc's own defect, amplified by Gram-Schmidt)
    ok = (np.all(np.isfinite(G)) and np.abs(G - np.eye(r)).max() < VERIFY_TOL + arrays["orthonormality_defect"]
          and frequencies
          and _flexibility_plausible(basis.flexibility_captured))
    if not ok:
        _say(ops.comm, f"basis cache {path} does not match the operators (corrupt or stale); rebuilding it")
        basis.destroy()
        return None
    _touch(path, world)
    return basis


def _touch(path: str, world) -> None:
    """Rank 0 marks a cache hit's file used: its modification time is its last use, what `cache clear
    --older-than` reads."""
    if world.rank == 0:
        try:
            os.utime(path)
        except OSError:   # a read-only cache serves all the same
            pass


def _state_space_basis(ops: Operators, settings: BasisSettings, arrays: dict, blocks: dict, path: str):
    """The state_space.StateSpaceBasis a checked file's arrays and this rank's rows make (its Vecs in K's
    layout, owned by it). Collective."""
    from .state_space import StateSpaceBasis

    def vecs(block):
        out = []
        for j in range(block.shape[1]):
            v = ops.K.createVecRight()
            v.array[:] = block[:, j]
            out.append(v)
        return out

    raw = [(dr, di, float(varpi)) for dr, di, varpi in zip(vecs(blocks["dbf_raw_real"]), vecs(blocks["dbf_raw_imag"]),
                                                        arrays["dbf_varpi"])]
    stats = {"cache": "hit", "cache_file": path, "complex_modes": arrays["complex_modes"],
             "constraint_columns": arrays["constraint_columns"].tolist(),
             "complex_omega": arrays["complex_omega"].tolist()}
    return StateSpaceBasis(velocity=vecs(blocks["velocity"]), displacement=vecs(blocks["displacement"]),
                           comm=ops.comm, raw=raw, settings=settings, stats=stats,
                           **{name: arrays[name] for name in ARRAYS})


def _state_space_problem(basis, ops: Operators, defect: float) -> str | None:
    """Why a state-space basis read from the cache is not the one these operators and settings make
    (None if it is), checked as build_state_space_basis made it (state_space.py), the same on every rank:
    Psi^T A Psi = I (to VERIFY_TOL beyond its stored defect); every stored omega_j an eigenfrequency of
    the reduced A_r eta' + B_r eta = 0 with the conservative B (exact for Re and Im of a complex state
    mode, as for the second-order basis); each DBF's hat-omega (Eq. 20) its <B Psi^R, Psi^I> on these
    operators; each raw DBF's state vectors [-varpi d_I; d_R], [varpi d_R; d_I] inside span Psi (what
    the error estimate's richer basis reuses: a column left out is below DROP_TOL of them); the captured
    flexibility plausible. Collective."""
    from .state_space import DROP_TOL, _local, _state_parts, conservative_state_matrix

    A_r = basis.state_energy(ops)
    if not (np.all(np.isfinite(A_r)) and np.abs(A_r - np.eye(basis.size)).max() < VERIFY_TOL + defect):
        return "Psi^T A Psi is not I"
    B_r = conservative_state_matrix(basis, ops)
    if not np.all(np.isfinite(B_r)):
        return "its reduced B is not finite"
    lam = np.linalg.eigvals(-np.linalg.solve(A_r, B_r))
    found = lam.imag[lam.imag > 0]
    if not (found.size and all(np.min(np.abs(found - w)) <= VERIFY_TOL * 100 * w for w in np.unique(basis.omega))):
        return "its reduced model lacks the stored complex frequencies"
    first, hat = basis.mode_count, []
    for count in basis.stats["constraint_columns"]:
        hat += [B_r[first + 1, first] if count == 2 else 0.0] * count
        first += count
    scale = VERIFY_TOL * 100 * float(np.abs(basis.omega).max(initial=0.0))
    if not np.allclose(hat, basis.enrichment_omega, rtol=VERIFY_TOL * 100, atol=scale):
        return "its DBF columns do not have the stored hat-omega"
    span = (_local(basis.velocity), _local(basis.displacement))   # local rows, once for all the DBFs
    for dr, di, varpi in basis.raw:
        parts = _state_parts(dr, di, varpi)
        try:
            residuals = [_residual_a_norm(ops, *p, span) for p in parts]
            norms = [_residual_a_norm(ops, *p) for p in parts]
        finally:
            for p in parts:
                destroy(*p)
        if not all(np.isfinite(residuals)) or max(residuals) > 10 * DROP_TOL * np.hypot(*norms):
            return "a DBF it reuses is not in its span"
    basis.set_flexibility(np.asarray(basis.flexibility_exact), ops)
    if not _flexibility_plausible(basis.flexibility_captured):
        return "its captured flexibility exceeds the exact one"
    return None


def _residual_a_norm(ops: Operators, v, w, span=None) -> float:
    """The A-norm of the state (v, w) less its A-projection onto span Psi (`span`: this rank's rows of
    Psi_v and Psi_w, as state_space._local gives them; None: of the state itself). Collective."""
    comm = ops.comm.tompi4py()
    v, w = v.copy(), w.copy()
    Mv, Kw = v.duplicate(), w.duplicate()
    try:
        if span is not None:
            Pv, Pw = span
            for _ in range(2):   # twice, as the Gram-Schmidt that built the basis
                ops.M.mult(v, Mv)
                ops.K.mult(w, Kw)
                c = comm.allreduce(Pv.T @ Mv.getArray(readonly=True) + Pw.T @ Kw.getArray(readonly=True))
                with v as va, w as wa:   # (get/restore: the Vecs' state moves on)
                    va -= Pv @ c
                    wa -= Pw @ c
        ops.M.mult(v, Mv)
        ops.K.mult(w, Kw)
        return float(np.sqrt(abs(v.dot(Mv) + w.dot(Kw))))
    finally:
        destroy(v, w, Mv, Kw)


def _holds_complex_modes(K_r: np.ndarray, G_r: np.ndarray, omega: np.ndarray) -> bool:
    """A gyroscopic basis holds Re and Im of its complex modes, so its reduced model q'' + G_r q' +
    K_r q = 0 has their frequencies exactly (gyroscopic_basis.py): each stored omega_j must be one of
    the reduced eigenfrequencies on the operators at hand. Not collective."""
    r = K_r.shape[0]
    if not (np.all(np.isfinite(K_r)) and np.all(np.isfinite(G_r))):
        return False
    lam = np.linalg.eigvals(np.block([[np.zeros((r, r)), np.eye(r)], [-K_r, -G_r]]))
    found = lam.imag[lam.imag > 0]
    return bool(found.size and all(np.min(np.abs(found - w)) <= VERIFY_TOL * 100 * w for w in np.unique(omega)))


def _flexibility_plausible(values: np.ndarray) -> bool:
    """A stored f_exact belongs to these operators only if no basis flexibility exceeds it
    (Rayleigh-Ritz: f_basis <= f_exact; NaN where K is singular)."""
    finite = values[np.isfinite(values)]
    return bool(np.all((finite > 0) & (finite <= 1 + 1e-6)))


def cache_path(cache_dir: str, key: str) -> str:
    return os.path.join(cache_dir, f"basis-{key[:20]}.h5")


def _prepare_directory(cache_dir: str, comm) -> str | None:
    """Rank 0 creates the cache directory; every rank learns whether it could (or raises what rank 0
    met otherwise: errors.from_rank0). Collective."""
    error, unexpected = None, []
    if comm.rank == 0:
        try:
            if os.path.exists(cache_dir) and not os.path.isdir(cache_dir):
                error = "it is a file, not a directory"
            else:
                os.makedirs(cache_dir, exist_ok=True)
                if not os.access(cache_dir, os.W_OK):
                    error = "not writable"
        except OSError as e:
            error = write_failure(e)
        except BaseException as e:   # (a bug) every rank raises it
            unexpected.append(e)
    return from_rank0(comm, error, unexpected)


def obtain_basis(ops: Operators, rows, settings: BasisSettings, fingerprint: dict, cache_dir: str | None,
                 labels=None, quiet: bool = False, whole: str = "refuse") -> ReducedBasis:
    """The basis from the cache when a valid one exists, else built (and cached if cache_dir; `whole`:
    build_basis's). A cache that cannot be written is a warning (every rank agrees; none with quiet),
    never an error. Collective."""
    check_pairs(ops, settings.modes)   # before a cache hit too: one stored before the check
    rows = np.asarray(rows, dtype=np.int64)
    gyroscopic = ops.G is not None
    if not cache_dir:
        basis = build_basis(ops, rows, settings, labels, whole)
        basis.stats["cache"] = "off"
        return basis
    key = basis_key(fingerprint, rows, settings, gyroscopic, whole)
    return _cached_or_built(ops, cache_dir, key, lambda path: load(path, key, ops, settings, rows, whole),
                            lambda: build_basis(ops, rows, settings, labels, whole), settings, quiet)


def _cached_or_built(ops: Operators, cache_dir: str, key: str, read, build, settings: BasisSettings,
                     quiet: bool = False):
    """The entry `key` of cache_dir read by read(path) (a checked basis, or None: absent, damaged or not
    this question's), else build() stored there (save). A cache that cannot be written is a warning
    (none with quiet), never an error; the stats say where the basis came from. Collective."""
    path = cache_path(cache_dir, key)
    exists = ops.comm.tompi4py().bcast(os.path.exists(path) if ops.comm.rank == 0 else None, root=0)
    if exists:
        basis = read(path)
        if basis is not None:
            _mark_used(solver_options(settings.strategy.solver_prefixes, observers=True))
            return basis
    basis = build()
    A_r = basis.state_energy(ops) if _is_state_space(basis) else basis.project(ops.M)
    defect = float(np.abs(A_r - np.eye(basis.size)).max(initial=0.0))
    try:
        error = _prepare_directory(cache_dir, ops.comm) or save(basis, path, key, ops.comm, defect)
    except BaseException:   # raised on every rank alike (errors.from_rank0): the basis is no one's
        basis.destroy()
        raise
    if error:
        if not quiet:
            warn(f"cannot write the basis cache in {cache_dir}: {error}", ops.comm)
        basis.stats["cache"] = "unwritable"
    else:
        basis.stats.update(cache="stored", cache_file=path)
    return basis


def obtain_modes(ops: Operators, count: int, fingerprint: dict, cache_dir: str | None):
    """The lowest `count` reference modes (modes.reference_modes; a ModalBasis the caller destroys; more
    where `count` ends inside a repeated frequency, up to its end),
    kept in the cache as a basis of `count` modes without enrichment or constraint rows. The error
    estimate's richer bases (accuracy.richer_models) solve 1.5 to 3 times the run's modes, which a
    run whose own basis is cached solved again at every run. The entry is a basis like any other: its
    key holds the operators, `count`, the modes_ and static_ options and the version, and it is checked
    on load (V^T M V = I, the frequencies); it holds the very numbers the solve gave, so a richer basis
    made from it is the one a solve makes, bit for bit. An odd count on a beam of two planes is its
    whole pairs' (basis.check_pairs). Solved without the cache where there is none and on a gyroscopic
    structure (its richer bases are kept whole: obtain_richer). A cache that cannot be written keeps
    nothing and says nothing: the run's own basis has warned of it, or was read from it. Collective."""
    from .basis import modes_per_frequency
    from .modes import ModalBasis, reference_modes

    if not cache_dir or ops.G is not None:
        return reference_modes(ops, count=count)
    # whole y-z pairs, as the solve extends them: build_basis refuses an odd count on a beam of two planes
    # before any solve (check_pairs), and the key of 9 is the key of 10
    count += -count % modes_per_frequency(ops)
    # a count inside a repeated frequency is extended to its end, as reference_modes does for these
    # counts (red team: the basis build refused it as a user's [basis] modes, and the estimate of a
    # symmetric structure with a cache had no richer model)
    basis = obtain_basis(ops, np.zeros(0, dtype=np.int64), BasisSettings(modes=count, enrichment="none"),
                         fingerprint, cache_dir, quiet=True, whole="extend")
    return ModalBasis(omega=basis.omega, vectors=basis.vectors)


def obtain_richer(ops: Operators, basis, count: int, fingerprint: dict, cache_dir: str | None):
    """The error estimate's richer basis of a gyroscopic structure's `basis` (basis.richer_basis: the
    complex modes 1..`count`, more where `count` ends inside a repeated frequency, and `basis`' own
    enrichment columns; either form) from the cache when a valid one exists, else built, and cached if
    cache_dir. Its key: the richer settings (`count` modes, whole="extend") and the basis it enriches
    (basis_key's richer_of: its settings and the bits of its frequencies, which a rebuild at another
    round-off changes); the load checks of a basis of its form apply. A resumed
    run's estimate is then the uninterrupted run's, bit for bit (its complex modes were solved again,
    another round-off), and a second run solves no eigenproblem for it. Without G: richer_basis (the
    real modes come from obtain_modes). A cache that cannot be written keeps nothing and says nothing,
    as obtain_modes. Collective."""
    from dataclasses import replace

    from .basis import richer_basis

    if not cache_dir or ops.G is None:
        return richer_basis(ops, basis, count)
    rows = np.asarray(basis.constraint_rows, dtype=np.int64)
    settings = replace(basis.settings, modes=count, max_frequency_hz=None)
    # the run's basis by its settings and the bits of its frequencies: a run's basis rebuilt (the cache cleared:
    # another round-off) has other columns, which the richer basis must hold (rank 0's key on every rank)
    frequencies = {name: np.asarray(getattr(basis, name), dtype=float) for name in ("omega", "enrichment_omega")}
    enriched = {"settings": basis.settings.key(), "frequencies": arrays_sha256(frequencies)}
    key = ops.comm.tompi4py().bcast(basis_key(fingerprint, rows, settings, True, "extend", richer_of=enriched), root=0)

    def read(path: str):
        rich = load(path, key, ops, settings, rows, "extend")
        if rich is not None:
            rich.settings = replace(settings, modes=rich.complex_modes)   # as built: the count taken whole
        return rich

    return _cached_or_built(ops, cache_dir, key, read, lambda: richer_basis(ops, basis, count), settings, quiet=True)


DEFAULT_DIR = "~/.cache/dbf_hpc"


# The names save() gives: basis-<20 hex of the key>.h5, and its temporary basis-....h5.tmp-<host>-<pid>
# (.tmp-<pid> before 0.2.2)
_NAME = re.compile(r"^basis-([0-9a-f]{20})\.h5(\.tmp-(?:[A-Za-z0-9._-]+-)?\d+)?$")


# A temporary file untouched this long is a killed job's (a write of 10^5 x 1000 columns takes seconds);
# a younger one may be another job's write in progress, and is kept
STALE_TEMPORARY_S = 600.0


def entries(cache_dir: str) -> list:
    """The files of the cache in `cache_dir`: path, size (bytes), modified (time), and what each holds
    (settings, dbf-hpc version, shape: V's, or a state-space basis' displacement part's, and form:
    "state_space" or "second_order"), or the problem reading it ("problem"; "foreign": a file named
    like a basis that save() did not write, which clear() never removes). Files not named as save()
    names them are not listed. Not collective."""
    out = []
    if not os.path.isdir(cache_dir):
        return out
    for name in sorted(os.listdir(cache_dir)):
        match = _NAME.match(name)
        path = os.path.join(cache_dir, name)
        if not match or not os.path.isfile(path):
            continue
        entry = {"path": path, "size": os.path.getsize(path), "modified": os.path.getmtime(path)}
        if match.group(2):
            entry.update(problem="a temporary file left by a killed job (or being written)", temporary=True)
        elif (seal_problem(path) or "").startswith("fails"):   # never parsed by HDF5 (it may crash)
            entry["problem"] = "unreadable (damaged)"
        else:
            try:
                with h5py.File(path, "r") as f:
                    # a state-space basis (save) holds its displacement part where another holds V
                    form = "state_space" if f.attrs.get("form") == "state_space" else "second_order"
                    key, V = f.attrs.get("key", ""), f.get("displacement" if form == "state_space" else "V")
                    if not (isinstance(key, str) and key[:20] == match.group(1) and isinstance(V, h5py.Dataset)
                            and V.ndim == 2):
                        entry.update(problem="not a basis this cache wrote: kept", foreign=True)
                    else:
                        entry.update(settings=f.attrs.get("settings", ""),
                                     version=f.attrs.get("dbf_hpc_version", "?"), shape=V.shape, form=form)
            except (OSError, KeyError, RuntimeError) as e:
                if refused_lock(e):      # readable where locks work: never removed for it
                    entry.update(problem=lock_problem(e), foreign=True)
                elif not (has_hdf5_signature(path) or seal_problem(path) is None):
                    entry.update(problem="not a basis this cache wrote: kept", foreign=True)
                else:
                    entry["problem"] = "unreadable (damaged)"
        out.append(entry)
    return out


def clear(cache_dir: str, older_than_days: float | None = None) -> tuple[int, int]:
    """Remove cached bases (those not used for older_than_days, if given), unreadable ones and
    temporary files left by killed jobs (untouched for STALE_TEMPORARY_S): (files removed, bytes
    freed). Only files named as save() names them, and never a readable file save() did not write.
    Not collective. Files it cannot remove (a read-only file system, no permission) are an InputError
    after the others are removed, saying how many were."""
    import time

    removed = freed = 0
    refused = []
    for entry in entries(cache_dir):
        age_s = time.time() - entry["modified"]
        if entry.get("foreign"):
            continue
        if entry.get("temporary"):
            stale = age_s > STALE_TEMPORARY_S
        else:
            stale = older_than_days is None or age_s / 86400 > older_than_days or "problem" in entry
        if stale:
            try:
                os.remove(entry["path"])
            except FileNotFoundError:   # another clear, or the writer's rename, got there first
                continue
            except OSError as e:
                refused.append(write_failure(e))
                continue
            removed, freed = removed + 1, freed + entry["size"]
    if refused:
        raise InputError(f"cannot remove {len(refused)} file(s) of the basis cache in {cache_dir} ({refused[0]}; "
                         f"removed {removed} file(s), {freed / 2**20:.3g} MiB): check the directory's "
                         f"permissions and file system")
    return removed, freed
