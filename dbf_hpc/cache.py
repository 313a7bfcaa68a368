"""Basis cache: a basis is computed once per structure, constraint set and basis settings, and reused
by every run that changes only the law, the excitation, damping or the integrator (paper,
conclusion 2).

A cache file `basis-<key>.h5` holds V (n x r), the frequencies, k_j, the constraint rows, the
settings and the full key; r is the number of columns actually present (the modes and one column
per constraint, or the modes alone for enrichment = "none"). It is written under a temporary name
and renamed when complete, so a crash never leaves a file that looks usable. On load, the key must
match and the basis must still be what it claims: V^T M V = I, and diag(V^T K V) = omega^2 for the
modes and hat-omega^2 for the other columns, on the operators at hand. Anything else (stale,
corrupt, unreadable) is reported and rebuilt, never used. The key holds the kind of enrichment and
only the settings and solver options that kind uses.

All functions are collective on ops.comm.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys

import h5py
import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from . import __version__
from .basis import STATIC_PREFIX, BasisSettings, ReducedBasis, build_basis
from .modes import FACTOR_DEFAULTS
from .operators import Operators

# Bump when the construction changes what a basis is.
ALGORITHM = "dbf-basis-3"  # 3: enrichment kinds ("dbf", "static", "none"), column count not modes + constraints
VERIFY_TOL = 1e-8


# The options prefixes of the solvers each kind of basis uses.
SOLVER_PREFIXES = {"dbf": ("modes_", "dbf_"), "static": ("modes_", STATIC_PREFIX), "none": ("modes_",)}


def solver_options(prefixes=("modes_", "dbf_")) -> dict:
    """The PETSc options under `prefixes` that can change a basis (those of the solvers it uses),
    less the defaults the eigensolvers set themselves."""
    prefixes = tuple(prefixes)
    options = PETSc.Options().getAll()
    ours = {f"{prefix}{name}": value for prefix in ("modes_", "dbf_") for name, value in FACTOR_DEFAULTS.items()}
    return {k: v for k, v in sorted(options.items())
            if k.startswith(prefixes) and ours.get(k) != str(v)}


def basis_key(fingerprint: dict, rows, settings: BasisSettings) -> str:
    """sha256 of everything that determines the basis (the options only of the solvers its kind uses)."""
    content = {"algorithm": ALGORITHM, "operators": fingerprint, "rows": [int(r) for r in rows],
               "settings": settings.key(),
               "options": solver_options(SOLVER_PREFIXES.get(settings.enrichment, ("modes_", "dbf_")))}
    return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()


def file_digest(path: str, comm) -> str:
    """sha256 of a file's bytes, read on rank 0 only. Collective."""
    digest = None
    if comm.rank == 0:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        digest = h.hexdigest()
    return comm.tompi4py().bcast(digest, root=0)


def _say(comm, message: str) -> None:
    PETSc.Sys.Print(f"dbf-hpc: {message}", comm=comm)


def save(basis: ReducedBasis, path: str, key: str, comm) -> None:
    """Write the basis to `path` atomically (temporary file, then rename)."""
    world = comm.tompi4py()
    tmp = world.bcast(f"{path}.tmp-{os.getpid()}" if world.rank == 0 else None, root=0)
    dense = basis.vectors.getMat()
    lo, hi = dense.getOwnershipRange()
    local = dense.getDenseArray().copy()
    basis.vectors.restoreMat(dense)
    n = basis.vectors.getSizes()[0][1]
    parallel_io = h5py.get_config().mpi and world.size > 1
    if parallel_io:
        f = h5py.File(tmp, "w", driver="mpio", comm=world)
    else:
        blocks = world.gather((lo, local), root=0)
        f = h5py.File(tmp, "w") if world.rank == 0 else None
    if f is not None:
        V = f.create_dataset("V", shape=(n, basis.size), dtype="f8")
        for name, value in (("omega", basis.omega), ("dbf_omega", basis.dbf_omega), ("dbf_k", basis.dbf_k),
                            ("dbf_k_auto", basis.dbf_k_auto), ("dbf_branch", basis.dbf_branch),
                            ("constraint_rows", basis.constraint_rows)):
            f.create_dataset(name, data=np.asarray(value))
        f.attrs["key"] = key
        f.attrs["settings"] = json.dumps(basis.settings.key())
        f.attrs["dbf_hpc_version"] = __version__
        if parallel_io:
            V[lo:hi, :] = local
        else:
            for start, block in blocks:
                V[start:start + block.shape[0], :] = block
        f.close()
    world.Barrier()
    if world.rank == 0:
        os.replace(tmp, path)
    world.Barrier()


def load(path: str, key: str, ops: Operators, settings: BasisSettings) -> ReducedBasis | None:
    """The cached basis if `path` holds a valid one for `key` on these operators, else None."""
    world = ops.comm.tompi4py()
    problem, arrays, block = None, {}, None
    lo, hi = ops.K.getOwnershipRange()
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("key") != key:
                problem = "was made for other operators or settings"
            else:
                arrays = {name: f[name][...] for name in
                          ("omega", "dbf_omega", "dbf_k", "dbf_k_auto", "dbf_branch", "constraint_rows")}
                enriched = 0 if settings.enrichment == "none" else arrays["constraint_rows"].size
                if (arrays["dbf_omega"].size != enriched
                        or f["V"].shape != (ops.size, arrays["omega"].size + enriched)):
                    problem = "has the wrong shape"
                else:
                    block = f["V"][lo:hi, :]
    except (OSError, KeyError, ValueError) as e:
        problem = f"cannot be read ({type(e).__name__})"
    problems = world.allgather(problem)
    problem = next((p for p in problems if p), None)
    if problem:
        _say(ops.comm, f"basis cache {path} {problem}; rebuilding it")
        return None
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
    basis = ReducedBasis(vectors=V, omega=arrays["omega"], dbf_omega=arrays["dbf_omega"],
                         dbf_k=arrays["dbf_k"], dbf_branch=arrays["dbf_branch"],
                         constraint_rows=arrays["constraint_rows"], dbf_k_auto=arrays["dbf_k_auto"],
                         settings=settings,
                         stats={"cache": "hit", "cache_file": path})
    G, Kr = basis.project(ops.M), basis.project(ops.K)
    N = basis.mode_count
    ok = (np.all(np.isfinite(G)) and np.abs(G - np.eye(r)).max() < VERIFY_TOL
          and np.allclose(np.diag(Kr)[:N], basis.omega**2, rtol=VERIFY_TOL * 100)
          and np.allclose(np.diag(Kr)[N:], basis.dbf_omega**2, rtol=VERIFY_TOL * 100))
    if not ok:
        _say(ops.comm, f"basis cache {path} does not match the operators (corrupt or stale); rebuilding it")
        basis.destroy()
        return None
    return basis


def obtain_basis(ops: Operators, rows, settings: BasisSettings, fingerprint: dict, cache_dir: str | None,
                 labels=None) -> ReducedBasis:
    """The basis from the cache when a valid one exists, else built (and cached if cache_dir)."""
    if not cache_dir:
        basis = build_basis(ops, rows, settings, labels)
        basis.stats["cache"] = "off"
        return basis
    key = basis_key(fingerprint, rows, settings)
    path = os.path.join(cache_dir, f"basis-{key[:20]}.h5")
    exists = ops.comm.tompi4py().bcast(os.path.exists(path) if ops.comm.rank == 0 else None, root=0)
    if exists:
        basis = load(path, key, ops, settings)
        if basis is not None:
            return basis
    basis = build_basis(ops, rows, settings, labels)
    try:
        if ops.comm.rank == 0:
            os.makedirs(cache_dir, exist_ok=True)
        ops.comm.tompi4py().Barrier()
        save(basis, path, key, ops.comm)
        basis.stats.update(cache="stored", cache_file=path)
    except OSError as e:
        print(f"dbf-hpc: warning: cannot write the basis cache in {cache_dir}: {e.strerror}", file=sys.stderr)
        basis.stats["cache"] = "unwritable"
    return basis
