"""Reference modes: K phi = lambda M phi with SLEPc (paper Section 2.1, Eqs. 28-31).

Generalized Hermitian EPS, shift-and-invert about a target just below the spectrum, factorized by
MUMPS (Cholesky). Options prefix `modes_`: every EPS/ST/KSP/PC setting can be changed from the
command line (-modes_eps_tol, -modes_st_pc_factor_mat_solver_type, ...); the code's defaults are
set before setFromOptions, so the user's options win.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from .errors import InputError, SolverError
from .operators import Operators, direct_solver


# Options the eigensolvers set as defaults (so that MUMPS reports the inertia); they do not change
# the eigenpairs.
FACTOR_DEFAULTS = {"st_mat_mumps_icntl_13": "1", "st_mat_mumps_icntl_24": "1"}

# Eigen-solves performed by this process (lets tests and reports see that a cached basis needed none).
counters = {"eigen_solves": 0}


@dataclass
class ModalBasis:
    """M-orthonormal reference modes phi_i (columns of a distributed BV) and omega_i (rad/s)."""

    omega: np.ndarray
    vectors: SLEPc.BV

    @property
    def count(self) -> int:
        return self.omega.size

    @property
    def frequency_hz(self) -> np.ndarray:
        return self.omega / (2 * np.pi)

    def destroy(self) -> None:
        self.vectors.destroy()


def eigen_solver(ops: Operators, K: PETSc.Mat, nev: int, prefix: str, tol: float = 1e-10) -> SLEPc.EPS:
    """An EPS for the lowest `nev` eigenpairs of (K, ops.M), configured and with the user's options
    applied. Collective on K's communicator. K may differ from ops.K (spring-perturbed problems)."""
    eps = SLEPc.EPS().create(comm=K.getComm())
    eps.setOperators(K, ops.M)
    eps.setProblemType(SLEPc.EPS.ProblemType.GHEP)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
    # Shift just below the spectrum: 0 for a supported structure (K is SPD), below 0 when rigid-body
    # modes make K singular.
    eps.setTarget(-1e-3 * ops.eigen_scale if ops.rigid_modes else 0.0)
    eps.setDimensions(nev)
    eps.setTolerances(tol, 1000)
    st = eps.getST()
    st.setType(SLEPc.ST.Type.SINVERT)
    direct_solver(st.getKSP(), PETSc.PC.Type.CHOLESKY)
    eps.setOptionsPrefix(prefix)
    # MUMPS counts the negative pivots of K - sigma M (its inertia, for the check in
    # reference_modes) only with these set. They are read when the factorization is made, so they
    # stay in the options database; set only where the user has not chosen.
    options = PETSc.Options(prefix)
    for name, value in FACTOR_DEFAULTS.items():
        if not options.hasName(name):
            options.setValue(name, value)
    eps.setFromOptions()
    return eps


def eigenvalues_below_shift(eps: SLEPc.EPS) -> int | None:
    """How many eigenvalues of (K, M) lie below the EPS target, from the inertia of the factorized
    K - sigma M (Sylvester's law); None if the factorization cannot tell. Collective."""
    try:
        negative, _, _ = eps.getST().getKSP().getPC().getFactorMatrix().getInertia()
    except PETSc.Error:
        return None
    return int(negative)


def solve_lowest(eps: SLEPc.EPS, nev: int, what: str) -> tuple[np.ndarray, list]:
    """Solve and return the nev converged eigenpairs sorted by eigenvalue. Collective."""
    eps.setDimensions(nev)
    try:
        eps.solve()
    except PETSc.Error as e:
        try:  # a failed solve can leave the EPS half torn down; free it now, not at exit
            eps.destroy()
        except PETSc.Error:
            pass
        raise SolverError(f"{what}: the eigensolver failed (PETSc error {e.ierr}); check that M is positive "
                          f"definite and K symmetric positive semi-definite") from None
    counters["eigen_solves"] += 1
    nconv = eps.getConverged()
    if nconv < nev:
        raise SolverError(f"{what}: only {nconv} of {nev} eigenpairs converged; raise "
                          f"-{eps.getOptionsPrefix()}eps_max_it or loosen -{eps.getOptionsPrefix()}eps_tol")
    K, _ = eps.getOperators()
    values, vectors = [], []
    for i in range(nconv):
        x = K.createVecRight()
        values.append(complex(eps.getEigenpair(i, x)).real)
        vectors.append(x)
    order = np.argsort(values)[:nev]
    keep = [vectors[i] for i in order]
    for i in set(range(nconv)) - set(order):
        vectors[i].destroy()
    return np.asarray(values)[order], keep


def normalize(x: PETSc.Vec, M: PETSc.Mat) -> None:
    """Scale x to x^T M x = 1 with a fixed sign convention (positive dot with an ascending ramp),
    so that runs on any number of ranks give the same vectors. Collective."""
    Mx = M.createVecLeft()
    M.mult(x, Mx)
    mass = x.dot(Mx)
    Mx.destroy()
    if not mass > 0:
        raise InputError(f"the mass matrix is not positive definite (x^T M x = {mass:.3g} for an eigenvector); "
                         f"check M")
    norm = np.sqrt(mass)
    lo, hi = x.getOwnershipRange()
    n = x.getSize()
    ramp = 1.0 + (np.arange(lo, hi) + 0.5) / n
    sign_dot = x.getComm().tompi4py().allreduce(float(np.dot(ramp, x.array_r)))
    x.scale((1.0 if sign_dot >= 0 else -1.0) / norm)


def reference_modes(ops: Operators, count: int | None = None, max_frequency_hz: float | None = None,
                    prefix: str = "modes_") -> ModalBasis:
    """The lowest reference modes: `count` of them, or every mode below `max_frequency_hz`.

    Collective on ops.comm. Raises SolverError if the solver converges fewer pairs than needed.
    """
    if (count is None) == (max_frequency_hz is None):
        raise InputError("give the number of modes or a maximum frequency, not both")
    n = ops.size
    if count is not None:
        if count < 1 or count > n:
            raise InputError(f"number of modes must be between 1 and {n} (the free DOFs), got {count}")
        eps = eigen_solver(ops, ops.K, count, prefix)
        values, vectors = solve_lowest(eps, count, "reference modes")
    else:
        if not max_frequency_hz > 0:
            raise InputError(f"max_frequency_hz must be positive, got {max_frequency_hz}")
        lam_max = (2 * np.pi * max_frequency_hz) ** 2
        nev = min(8, n)
        eps = eigen_solver(ops, ops.K, nev, prefix)
        while True:
            values, vectors = solve_lowest(eps, nev, "reference modes")
            if values[-1] > lam_max or nev == n:
                break
            for v in vectors:
                v.destroy()
            nev = min(2 * nev, n)
        below = int(np.count_nonzero(values <= lam_max))
        if below == 0:
            raise InputError(f"no mode below max_frequency_hz = {max_frequency_hz} Hz "
                             f"(the lowest is {np.sqrt(max(values[0], 0)) / (2 * np.pi):.6g} Hz)")
        for v in vectors[below:]:
            v.destroy()
        values, vectors = values[:below], vectors[:below]
    negative = eigenvalues_below_shift(eps)
    eps.destroy()
    if negative:
        raise InputError(f"the stiffness matrix is not positive semi-definite ({negative} eigenvalue(s) below "
                         f"zero); check K and its boundary conditions")

    bv = SLEPc.BV().create(comm=ops.comm)
    bv.setSizesFromVec(vectors[0], len(vectors))
    bv.setType(SLEPc.BV.Type.SVEC)
    for j, x in enumerate(vectors):
        normalize(x, ops.M)
        bv.insertVec(j, x)
        x.destroy()
    bv.setMatrix(ops.M, False)
    # Rigid-body modes are zero to round-off; a clearly negative eigenvalue is an indefinite K.
    if values[0] < -1e-8 * max(abs(values[-1]), ops.eigen_scale):
        raise InputError(f"the stiffness matrix is not positive semi-definite (eigenvalue {values[0]:.3g}); "
                         f"check K and its boundary conditions")
    omega = np.sqrt(np.clip(values, 0.0, None))
    return ModalBasis(omega=omega, vectors=bv)
