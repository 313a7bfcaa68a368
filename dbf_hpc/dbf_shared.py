"""The shared-factorization DBF path ([basis] dbf_solver = "shared", and the fallback of the default
"ritz" path, dbf_ritz.py; docs/design.md, "One factorization per constraint group").

The factored path (dbf.py, FactorSolver) factors three matrices per constraint: K and M without
the constraint's row (the pinned mu_m), K + k g g^T - sigma M (the shift-and-invert of Eq. 13/34)
and A_k - lambda M (the derivative of Eq. 17). All three differ from A = K - sigma M (sigma below
the spectrum: modes.shift_below_spectrum) by rank one in g, so one factorization of A serves every
constraint of a group, with z = A^-1 g (one solve per constraint) and Sherman-Morrison:

    (A + k g g^T)^-1 x = A^-1 x - k z (z^T x) / (1 + k g^T z),
    P x = A^-1 x - z (z^T x) / (g^T z)     (k -> infinity: the inverse on g^T u = 0, the pinned problem).

- the spring-perturbed eigenpair: SLEPc Krylov-Schur with shift-and-invert about sigma, the ST's
  KSP a PCShell applying (A + k g g^T)^-1 (one shared-factor solve, a dot and an axpy);
- mu_m: the same EPS on (K, M) with P: P M x = theta x, theta != 0, is exactly the pinned problem
  (g^T x = 0, (K - mu M) x parallel to g) with mu = sigma + 1/theta; the infinite eigenvalue of
  x = M^-1 g (theta = 0) is never among the lowest;
- the derivative (A_k - lambda M) phi' = rhs, phi^T M phi' = 0: GMRES, left-preconditioned by
  Q (A + k g g^T)^-1 with Q = I - phi (M phi)^T. The preconditioned operator has the eigenvalues
  1 - (lambda - sigma) / (lambda_i(k) - sigma), i != m, on the M-complement of phi (0 on phi,
  which Q removes), so a few iterations suffice; then the backward error is checked as on the
  factored path.

Collective on the group's communicator. Options prefixes: `dbf_shared_` (the factorization,
-dbf_shared_pc_factor_mat_solver_type ...), `dbf_krylov_` (the derivative's GMRES), `dbf_` (the
EPS, as on the factored path).
"""
from __future__ import annotations

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .dbf import EIGEN_TOL, PREFIX, derivative_system, refine_derivative, value_at, with_spring
from .errors import SolverError, petsc_failure
from .modes import lowest_eigenpair, normalize, shift_below_spectrum
from .operators import Operators
from .petsctools import destroy, direct_solver, natural_fill_is_small, options_defaults, unit_vector

FACTOR_PREFIX = "dbf_shared_"
KRYLOV_PREFIX = "dbf_krylov_"
KRYLOV_RTOL = 1e-13      # preconditioned residual; the backward error is checked afterwards
KRYLOV_MAX_IT = 200
EIGEN_NCV = 4            # Krylov-Schur subspace beyond the branch index: convergence is checked per restart
                         # (m + 8 took 12 solves per eigenproblem on the 10^4-DOF beam, m + 4 takes 10)

# On a one-rank group whose K - sigma M keeps its fill small in the natural ordering (a beam):
# PETSc's own sparse Cholesky in that ordering (no fill on a band; on the 10^4-DOF beam it factors in
# 1.8 ms against 8.5 ms in nested dissection, and solves as fast). A MUMPS solve costs ~6.5 ms on the
# 10^4-DOF beam whatever the arithmetic (its per-call overhead), PETSc's 0.4 ms, and each constraint
# makes several solves (docs/design.md). A 3-D mesh (the 104 040-DOF solid: bench_basis with 10 and
# 100 constraints had not finished after 13 min with PETSc's own, 7 min with MUMPS) and groups of
# several ranks use MUMPS;
# -dbf_shared_pc_factor_mat_solver_type chooses either everywhere.
# PETSc's own factorization calls a pivot below 1e-12 zero (an absolute tolerance, as
# fom_integrator.factorization says): a soft or small structure in SI units (the paper's beam with
# E 1e-11 times its own: rotational pivots 4 EI / h ~ 4e-13 N m) gave infinite solves. Only an exact
# 0 is a zero pivot here (A is SPD; solve_block refuses non-finite values).
FACTOR_DEFAULTS = {"pc_factor_mat_solver_type": "petsc", "pc_factor_mat_ordering_type": "natural",
                   "pc_factor_zeropivot": "0.0"}

# k g^T A^-1 g above this is refused on the shared and ritz paths: their rank-one (Sherman-Morrison)
# updates subtract k/(1 + k g^T A^-1 g) terms that cancel as k grows, and the DBF loses about
# 1e-16 x this amplification to round-off while every backward error still passes. Red team, the
# paper's 4-stop beam (g^T A^-1 g = 83 to 187 m/N) against the factored path, which gives the same DBFs
# to 2e-10 from 1e6 to 1e14 N/m: 1.6e-9 at k = 1e7 N/m (amplification 8e8), 1.5e-7 at 1e8 (8e9),
# 1.6e-4 at 1e10 (8e11), silently. "auto" puts k at the transition (an amplification of order 1-100).
AMPLIFICATION_LIMIT = 1e9
# The factored path's DBFs agreed to 2e-10 up to 1e14 N/m on the paper's 4-stop beam (k g^T A^-1 g up
# to 2e16); beyond, the refusal also says that d phi/dk is round-off on any path (enrichment.py).
FACTOR_AMPLIFICATION = 1e16


class AmplificationError(SolverError):
    """check_amplification's refusal: the DBF stiffness given is too large for the rank-one update
    (the remedy is a smaller [basis] dbf_stiffness or dbf_solver = "factor", not "auto" alone);
    `amplification` is k g^T A^-1 g."""

    def __init__(self, message: str, amplification: float):
        super().__init__(message)
        self.amplification = amplification


def check_amplification(k, gz, rows) -> None:
    """AmplificationError if k g^T A^-1 g > AMPLIFICATION_LIMIT for any of the constraints (k, gz, rows
    arrays or scalars alike), naming the largest k the rank-one update takes there. Not collective:
    every rank of the group holds the same k and gz."""
    a = np.atleast_1d(np.asarray(k, dtype=float) * np.asarray(gz, dtype=float))
    over = np.flatnonzero(np.isfinite(a) & (a > AMPLIFICATION_LIMIT))
    if over.size:
        j = over[0]
        row = int(np.atleast_1d(rows)[j])
        kj, gj = float(np.atleast_1d(k)[j]), float(np.atleast_1d(gz)[j])
        raise AmplificationError(
            f"DBF at row {row}: k g^T (K - sigma M)^-1 g = {a[j]:.3g} (k = {kj:.3g} N/m) is above "
            f"{AMPLIFICATION_LIMIT:g}, where the shared factorization's rank-one update loses the DBF to "
            f"round-off; give [basis] dbf_stiffness at most {AMPLIFICATION_LIMIT / gj:.3g} N/m (or \"auto\") "
            f"or use [basis] dbf_solver = \"factor\"", float(a[j]))


# Work done by this process on the shared path (tests and benchmarks read it).
counters = {"factorizations": 0, "solves": 0}


class SharedFactor:
    """A = K - sigma M factored once (Cholesky; SPD as sigma lies below the spectrum) on ops.comm
    (FACTOR_DEFAULTS: which factorization). Owns A and its KSP. Collective."""

    def __init__(self, ops: Operators):
        self.ops, self.sigma = ops, shift_below_spectrum(ops)
        self.A, self.ksp = ops.K.duplicate(copy=True), None
        try:
            if self.sigma:
                self.A.axpy(-self.sigma, ops.M, structure=PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
            self.ksp = direct_solver(PETSc.KSP().create(comm=ops.comm), PETSc.PC.Type.CHOLESKY)
            self.ksp.setOperators(self.A)
            self.ksp.setOptionsPrefix(FACTOR_PREFIX)
            native = ops.comm.getSize() == 1 and natural_fill_is_small(self.A)
            with options_defaults(FACTOR_PREFIX, FACTOR_DEFAULTS if native else {}):
                self.ksp.setFromOptions()
                self.ksp.setUp()     # the factorization
            # PETSc's own factor has no MatMatSolve of its own: the generic one took 0.20 ms a column on
            # the 10^4-DOF beam, its MatSolve one column at a time 0.15 ms (solve_block)
            self.column_solves = (self.ksp.getPC().getFactorSolverType() == "petsc"
                                  and self.ksp.getType() == PETSc.KSP.Type.PREONLY)
            counters["factorizations"] += 1
        except PETSc.Error as e:
            self.destroy()
            raise SolverError(f"the shared DBF factorization of K - sigma M (sigma = {self.sigma:g}) failed "
                              f"({petsc_failure(e)}); check the -{FACTOR_PREFIX} options and K and M, or use "
                              f"[basis] dbf_solver = \"factor\"") from None
        except Exception:
            self.destroy()
            raise

    def solve(self, x: PETSc.Vec, y: PETSc.Vec) -> None:
        """y = A^-1 x. Collective."""
        self.ksp.solve(x, y)
        counters["solves"] += 1
        if self.ksp.getConvergedReason() < 0:
            raise SolverError(f"a solve with the shared DBF factorization failed (KSP reason "
                              f"{self.ksp.getConvergedReason()}); check the -{FACTOR_PREFIX} options (an exact "
                              f"solve is needed: -{FACTOR_PREFIX}ksp_type preonly -{FACTOR_PREFIX}pc_type cholesky)")

    def solve_block(self, b: np.ndarray) -> np.ndarray:
        """A^-1 b for a block of local rows b (n_local x L, one right-hand side per column), as numpy
        local rows: one MatMatSolve with the factor (MUMPS solves a block at a fraction of the cost of as
        many single solves); PETSc's own factor (one rank) column by column with its MatSolve, faster than
        its generic MatMatSolve; column by column with the KSP where the factor has none. Collective."""
        n_local, L = b.shape
        N = self.A.getSize()[0]
        comm = self.ops.comm
        # B and X are views of numpy blocks (column-major): no copies in or out
        b = np.asfortranarray(b, dtype=float)
        out = np.empty((n_local, L), order="F")
        if self.column_solves:
            self._column_solves(b, out)
            return out
        B = PETSc.Mat().createDense(((n_local, N), (PETSc.DECIDE, L)), array=b, comm=comm)
        X = PETSc.Mat().createDense(((n_local, N), (PETSc.DECIDE, L)), array=out, comm=comm)
        try:
            B.assemble()
            X.assemble()
            try:
                self.ksp.getPC().getFactorMatrix().matSolve(B, X)
            except PETSc.Error:   # the same decision on every rank: the factor's type
                x, y = self.A.createVecRight(), self.A.createVecLeft()
                try:
                    for j in range(L):
                        x.array = b[:, j]
                        self.ksp.solve(x, y)
                        out[:, j] = y.array_r
                finally:
                    destroy(x, y)
        finally:
            destroy(B, X)
        counters["solves"] += L
        # every rank's rows (red team: a solve that overflowed in one rank's rows, an uncoupled part of
        # the structure, was that rank's error alone, and the others went on into the group's next
        # collective call: the job hung)
        if not comm.tompi4py().allreduce(bool(np.isfinite(out).all()), op=MPI.LAND):
            raise SolverError("a block solve with the shared DBF factorization gave non-finite values")
        return out

    def _column_solves(self, b: np.ndarray, out: np.ndarray) -> None:
        """out = A^-1 b column by column with the factor's MatSolve (b, out: column-major, placed in
        Vecs, no copies). One rank (PETSc's own factor)."""
        x, y = self.A.createVecRight(), self.A.createVecLeft()
        factor = self.ksp.getPC().getFactorMatrix()
        try:
            for j in range(b.shape[1]):
                x.placeArray(b[:, j])
                y.placeArray(out[:, j])
                try:
                    factor.solve(x, y)
                finally:
                    x.resetArray()
                    y.resetArray()
        finally:
            destroy(x, y)
        counters["solves"] += b.shape[1]
        if not np.isfinite(out).all():
            raise SolverError("a block solve with the shared DBF factorization gave non-finite values")

    def destroy(self) -> None:
        destroy(self.ksp, self.A)


class SpringInverse:
    """(A + k g g^T)^-1 by Sherman-Morrison, or P (k = inf, the pinned problem), optionally followed
    by Q = I - phi (M phi)^T: a Python PC context (apply) for the EPS's ST and the derivative's
    GMRES. Owns z = A^-1 g (one solve). Collective."""

    def __init__(self, factor: SharedFactor, row: int):
        self.factor, self.row = factor, row
        self.z = factor.A.createVecRight()
        g = unit_vector(self.z, row)
        try:
            factor.solve(g, self.z)
        except Exception:
            self.z.destroy()
            raise
        finally:
            g.destroy()
        self.gz = value_at(self.z, row)   # g^T A^-1 g > 0 (A is SPD)
        self.phi = self.Mphi = None
        self.set_stiffness(np.inf)

    def set_stiffness(self, k: float) -> None:
        self.coefficient = 1.0 / self.gz if np.isinf(k) else k / (1.0 + k * self.gz)

    def deflate(self, phi: PETSc.Vec | None, Mphi: PETSc.Vec | None) -> None:
        """Project out phi along M phi after each apply (None: no projection). Borrowed, not owned."""
        self.phi, self.Mphi = phi, Mphi

    def apply(self, pc, x: PETSc.Vec, y: PETSc.Vec) -> None:
        self.factor.solve(x, y)
        y.axpy(-self.coefficient * self.z.dot(x), self.z)
        if self.phi is not None:
            y.axpy(-y.dot(self.Mphi), self.phi)

    def free(self) -> None:
        """Destroy z (not `destroy`: petsc4py calls a context's destroy(pc) with each PC it served)."""
        destroy(self.z)


class SharedSolver:
    """The three solves of one constraint (dbf.FactorSolver's interface) on a SharedFactor: no
    factorization, one solve for z, then one solve per Krylov step. Owns its SpringInverse."""

    def __init__(self, factor: SharedFactor, row: int):
        self.factor, self.ops, self.row = factor, factor.ops, row
        self.inverse = SpringInverse(factor, row)

    def pinned(self, branch: int) -> float:
        """mu_m, the m-th eigenvalue of the pinned problem. Collective."""
        self.inverse.set_stiffness(np.inf)
        mu, phi = lowest_eigenpair(self.ops, self.ops.K, branch, PREFIX,
                                   f"pinned modes (row {self.row}, shared factorization)", EIGEN_TOL,
                                   self.inverse, None, branch + EIGEN_NCV)
        phi.destroy()
        return mu

    def eigenpair(self, k: float, branch: int):
        """(lambda_m, phi_m) of (K + k g g^T, M), phi M-normalized as on the factored path. Collective."""
        check_amplification(k, self.inverse.gz, self.row)
        Kk = with_spring(self.ops.K, self.row, k)
        self.inverse.set_stiffness(k)
        try:
            lam, phi = lowest_eigenpair(self.ops, Kk, branch, PREFIX,
                                        f"spring-perturbed modes (k = {k:.3g} N/m at row {self.row}, shared "
                                        f"factorization)", EIGEN_TOL, self.inverse, None, branch + EIGEN_NCV)
        finally:
            Kk.destroy()
        normalize(phi, self.ops.M)
        return lam, phi

    def derivative(self, k: float, lam: float, phi: PETSc.Vec) -> PETSc.Vec:
        """d phi/dk from the deflated derivative equation by preconditioned GMRES (module docstring)."""
        check_amplification(k, self.inverse.gz, self.row)
        A, rhs, Mphi = derivative_system(self.ops, self.row, k, lam, phi)
        self.inverse.set_stiffness(k)
        self.inverse.deflate(phi, Mphi)
        ksp = None
        try:
            ksp = _krylov(A, self.inverse)
            d = refine_derivative(
                ksp, A, rhs, phi, Mphi,
                failed=lambda reason: (f"DBF derivative at row {self.row}: GMRES preconditioned by the shared "
                                       f"factorization did not converge ({reason}, {ksp.getIterationNumber()} "
                                       f"iterations); use [basis] dbf_solver = \"factor\""),
                inaccurate=lambda backward: (f"DBF derivative at row {self.row} is inaccurate (backward error "
                                             f"{backward:.2e}) on the shared factorization; use [basis] "
                                             f"dbf_solver = \"factor\""))
        finally:
            self.inverse.deflate(None, None)
            destroy(ksp, A, rhs, Mphi)
        return d

    def destroy(self) -> None:
        self.inverse.free()


def _krylov(A: PETSc.Mat, inverse: SpringInverse) -> PETSc.KSP:
    """GMRES on A, left-preconditioned by `inverse` (a PCShell), user options under dbf_krylov_."""
    ksp = PETSc.KSP().create(comm=A.getComm())
    try:
        ksp.setOperators(A)
        ksp.setType(PETSc.KSP.Type.GMRES)
        ksp.setTolerances(rtol=KRYLOV_RTOL, atol=0.0, max_it=KRYLOV_MAX_IT)
        ksp.setOptionsPrefix(KRYLOV_PREFIX)
        ksp.setFromOptions()   # a -dbf_krylov_ option PETSc refuses raises here
        pc = ksp.getPC()   # after setFromOptions: the shared path is this preconditioner
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(inverse)
    except Exception:
        ksp.destroy()
        raise
    return ksp
