"""The structure's linear operators, as every later stage sees them.

Whatever made them (the beam model of structure.py, or matrix files through matrices.py), a
structure is: distributed K and M (and optionally C) over its free DOFs, the rows of the DOFs the
constraints act on, and, for base excitation, the support-motion influence vector.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Optional

import numpy as np
from petsc4py import PETSc


@dataclass
class Operators:
    """Distributed structural operators on `comm`. K and M are symmetric, M positive definite.

    influence        r over the free DOFs: the displacement of the structure that follows a unit
                     support motion (the paper's Eq. 26 shape). Total u = u_rel + r * Omega(t).
    base_mass_load   M_(free, all) r_all: the support-motion load is -base_mass_load * Omega''(t).
                     It includes the mass coupling to the prescribed support DOF (DESIGN.md).
    rigid_modes      number of zero-energy modes of (K, M); > 0 only for an unsupported structure.
    eigen_scale      a typical eigenvalue of (K, M), rad^2/s^2 (sets default solver shifts).
    mesh             the beam mesh for beam models (positions of nodes, DOF rows), else None.
    """

    comm: PETSc.Comm
    K: PETSc.Mat
    M: PETSc.Mat
    C: Optional[PETSc.Mat] = None
    influence: Optional[PETSc.Vec] = None
    base_mass_load: Optional[PETSc.Vec] = None
    rigid_modes: int = 0
    eigen_scale: float = 1.0
    mesh: Optional[object] = None

    @property
    def size(self) -> int:
        """Global number of free DOFs."""
        return self.K.getSize()[0]

    def ownership_range(self) -> tuple[int, int]:
        return self.K.getOwnershipRange()

    def destroy(self) -> None:
        """Free the PETSc objects (collective on comm)."""
        for obj in (self.K, self.M, self.C, self.influence, self.base_mass_load):
            if obj is not None:
                obj.destroy()


def owned_rows(n: int, comm) -> tuple[int, int]:
    """The rows [start, end) this rank owns in PETSc's default layout of n rows. Collective."""
    n_local, _ = PETSc.Sys.splitOwnership(n, comm=comm)
    start = comm.tompi4py().exscan(n_local) or 0
    return start, start + n_local


def aij_from_owned_triplets(comm, n: int, rows, cols, values) -> PETSc.Mat:
    """An assembled n x n AIJ matrix from (row, col, value) triplets of this rank's own rows
    (duplicates are summed). Collective; no values move between ranks."""
    start, end = owned_rows(n, comm)
    rows = np.asarray(rows, dtype=np.int64)
    key, inverse = np.unique((rows - start) * n + np.asarray(cols, dtype=np.int64), return_inverse=True)
    summed = np.bincount(inverse, weights=np.asarray(values, dtype=float), minlength=key.size)
    local_row, col = np.divmod(key, n)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(local_row, minlength=end - start))])
    A = PETSc.Mat().createAIJ(size=((end - start, n), (end - start, n)),
                              csr=(indptr.astype(PETSc.IntType), col.astype(PETSc.IntType), summed),
                              comm=comm)
    A.assemble()
    return A


def direct_solver(ksp: PETSc.KSP, factorization: str = "lu") -> PETSc.KSP:
    """Configure a KSP as a direct solve by MUMPS (required in parallel): preonly + LU or Cholesky.
    Set before setFromOptions, so the user's options still win."""
    ksp.setType(PETSc.KSP.Type.PREONLY)
    pc = ksp.getPC()
    pc.setType(factorization)
    pc.setFactorSolverType("mumps")
    return ksp


@contextlib.contextmanager
def options_defaults(prefix: str, defaults: dict):
    """Put the code's `defaults` (option name -> value) under `prefix` into the options database
    where the user has not set them, for the setFromOptions calls inside the block, and take them
    out after: the user's options always win, and ours never leak into another solver. Yields the
    prefixed options, to read the effective values."""
    options = PETSc.Options(prefix)
    ours = [name for name in defaults if not options.hasName(name)]
    for name in ours:
        options.setValue(name, defaults[name])
    try:
        yield options
    finally:
        for name in ours:
            options.delValue(name)


def values_at(vec: PETSc.Vec, rows) -> np.ndarray:
    """vec[rows] on every rank. Collective."""
    lo, hi = vec.getOwnershipRange()
    rows = np.asarray(rows, dtype=np.int64)
    out = np.zeros(rows.size)
    mine = (rows >= lo) & (rows < hi)
    out[mine] = vec.getArray(readonly=True)[rows[mine] - lo]
    return vec.getComm().tompi4py().allreduce(out)
