"""One discontinuous basis function (DBF) per constraint: paper Section 2.2 (Eqs. 13-17) and, for the
beam, Section 3.2 (Eqs. 34-39). Orthonormalization (Eqs. 18-20, 40-41) is in basis.py.

For constraint j acting on w_j = g^T u (g: a unit vector at one DOF):

1. The spring-perturbed problem (Eq. 13/34):  (K + k g g^T) phi = lambda M phi.
   Its eigenvalues rise monotonically with k and interlace: lambda_m(k) runs from the m-th reference
   eigenvalue lambda_m(0) (no spring) to mu_m, the m-th eigenvalue with w_j pinned (k -> infinity).
   We follow the branch m of the lowest reference mode that moves at the constraint, i.e. whose
   participation (g^T phi_m)^2 is not negligible, so a constraint at a node of the first mode still
   gets a DBF (the paper's l = 0.25 is a node of mode 4; l = 0.5 of mode 2).

2. The stiffness k_j ("auto"): the corner of the paper's Fig. 2. For small k,
   lambda_m(k) ~ lambda_m(0) + k (g^T phi_m)^2 (first-order perturbation); for large k it tends to
   mu_m. The two asymptotes meet at
        k_auto = (mu_m - lambda_m(0)) / (g^T phi_m)^2,
   the middle of the transition on a log-k axis (the Table 1 beam with l = 0.25 gives k_auto of a few
   hundredths of a N/m, where the paper reads k ~ 0.1 N/m off its Fig. 2).

3. The DBF source is the derivative d phi / dk at k_j (Eq. 17; the d(varpi) phi terms are dropped as
   in the paper). Two ways, selectable:
   - "central": (phi(k (1 + h)) - phi(k (1 - h))) / (2 h k), each phi M-normalized and sign-aligned;
   - "analytic": with A = K + k g g^T and M-normalized phi, differentiating A phi = lambda M phi and
     phi^T M phi = 1 gives d lambda/dk = (g^T phi)^2 and
        (A - lambda M) phi' = -(g (g^T phi) - (g^T phi)^2 M phi),   phi^T M phi' = 0.
     A - lambda M is singular along phi only and the right side is orthogonal to phi, so we solve it
     with a direct factorization and project out the phi component (deflation), refine, then check
     the normwise backward error.

All functions here are collective on the communicator of the operators they get (a group's copy
of K and M when constraints run in parallel). Solver options prefix: `dbf_` (EPS: -dbf_eps_...,
derivative solve: -dbf_ksp_..., -dbf_pc_...).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc

from .errors import SolverError
from .modes import REPEATED_TOL, ModalBasis, bv_rows, lowest_eigenpair, normalize
from .operators import Operators
from .petsctools import destroy, direct_solver, frames_released, values_at

PREFIX = "dbf_"
# A reference mode "moves at the constraint" if (g^T phi)^2 exceeds this fraction of the largest
# (g^T phi_i)^2 over the reference modes.
PARTICIPATION_TOL = 1e-6
# A given k_j more than this factor away from the transition is outside Fig. 2's useful range.
STIFFNESS_RANGE = 1e2
# Reference eigenvalues closer than this (relative in lambda) are one repeated eigenvalue (branch_of): the
# reference modes' own (modes.REPEATED_TOL), so that a cluster here is one whole there.
CLUSTER_TOL = REPEATED_TOL
CENTRAL_STEP = 1e-3  # relative step h of the central difference in k
EIGEN_TOL = 1e-12    # tighter than the reference modes: derivatives amplify eigenvector errors
DERIVATIVE_BACKWARD_TOL = 1e-10  # a backward-stable solve gives ~1e-16
REFINEMENT_STEPS = 2


@dataclass
class DbfSource:
    """What one constraint contributes before orthogonalization (on the group's communicator)."""

    row: int
    branch: int           # 1-based index m of the eigen-branch followed
    stiffness: float      # k_j, N/m
    transition: float     # k_auto, the corner of Fig. 2 (N/m), to judge a given k_j against
    eigenvalue: float     # lambda_m(k_j), rad^2/s^2
    derivative: PETSc.Vec  # d phi / dk at k_j


def branch_of(participation: np.ndarray, eigenvalues: np.ndarray | None = None) -> int:
    """1-based index of the eigen-branch to follow, given (g^T phi_i)^2 and lambda_i of the reference
    modes i = 1..N: the lowest mode that moves at the constraint; 0 if none does.

    A repeated eigenvalue (a cluster within CLUSTER_TOL, e.g. the two bending modes of a bar with a
    square section) is one mode with a multi-dimensional eigenspace, of which the spring moves one
    direction only: the cluster's other c - 1 eigenvalues stay at lambda, the moved one rises above
    them, so the branch is the cluster's last index (and its participation the cluster's sum,
    cluster_participation). Following the first index would follow an unmoved mode (k_auto = 0, a
    zero DBF)."""
    cluster = cluster_of(participation, eigenvalues)
    return int(cluster[-1]) + 1 if cluster.size else 0


def cluster_participation(participation: np.ndarray, eigenvalues: np.ndarray | None = None) -> float:
    """(g^T P g) over the eigenspace of the branch followed (branch_of): the slope of lambda_m(k) at
    k = 0, whatever basis the eigensolver chose inside a repeated eigenvalue."""
    cluster = cluster_of(participation, eigenvalues)
    return float(participation[cluster].sum()) if cluster.size else 0.0


def branches(participation: np.ndarray, eigenvalues: np.ndarray | None = None):
    """branch_of and cluster_participation of many constraints at once: participation (N_L, N), the
    same eigenvalues for all; returns (branches (N_L,), cluster participations (N_L,))."""
    participation = np.atleast_2d(np.asarray(participation, dtype=float))
    count, n = participation.shape
    if not n or not count:
        return np.zeros(count, dtype=np.int64), np.zeros(count)
    starts = _cluster_starts(n, eigenvalues)
    sums = np.add.reduceat(participation, starts[:-1], axis=1)
    largest = sums.max(axis=1)
    moving = largest > 0
    first = np.argmax(sums > PARTICIPATION_TOL * largest[:, None], axis=1)
    return (np.where(moving, starts[first + 1], 0).astype(np.int64),
            np.where(moving, sums[np.arange(count), first], 0.0))


def _cluster_starts(n: int, eigenvalues: np.ndarray | None) -> np.ndarray:
    """The first index of each cluster of reference eigenvalues (within CLUSTER_TOL), then n."""
    if eigenvalues is None:
        return np.arange(n + 1)
    lam = np.asarray(eigenvalues, dtype=float)
    scale = np.maximum(np.abs(lam[1:]), np.abs(lam[:-1]))
    split = np.flatnonzero(np.diff(lam) > CLUSTER_TOL * np.where(scale > 0, scale, 1.0)) + 1
    return np.concatenate(([0], split, [n]))


def cluster_of(participation: np.ndarray, eigenvalues: np.ndarray | None) -> np.ndarray:
    """0-based indices of the lowest (cluster of) reference mode(s) that moves at the constraint."""
    participation = np.asarray(participation, dtype=float)
    n = participation.size
    starts = _cluster_starts(n, eigenvalues)
    sums = np.add.reduceat(participation, starts[:-1]) if n else np.zeros(0)
    if not n or sums.max() <= 0:
        return np.zeros(0, dtype=int)
    first = int(np.flatnonzero(sums > PARTICIPATION_TOL * sums.max())[0])
    return np.arange(starts[first], starts[first + 1])


def with_spring(K: PETSc.Mat, row: int, k: float) -> PETSc.Mat:
    """K + k g g^T for g the unit vector at `row` (a new matrix). Collective."""
    A = K.duplicate(copy=True)
    lo, hi = A.getOwnershipRange()
    if lo <= row < hi:
        A.setValue(row, row, k, addv=PETSc.InsertMode.ADD_VALUES)
    A.assemble()
    return A


def value_at(x: PETSc.Vec, row: int) -> float:
    """x[row] on every rank. Collective."""
    return float(values_at(x, [row])[0])


def spring_eigenpair(ops: Operators, row: int, k: float, branch: int, tol: float = EIGEN_TOL):
    """(lambda_m, phi_m) of (K + k g g^T, M), phi M-normalized with the package's sign convention."""
    A = with_spring(ops.K, row, k)
    try:
        lam, phi = lowest_eigenpair(ops, A, branch, PREFIX, f"spring-perturbed modes (k = {k:.3g} N/m at row {row})",
                                    tol)
    finally:
        A.destroy()
    normalize(phi, ops.M)
    return lam, phi


def pinned_eigenvalue(ops: Operators, row: int, branch: int) -> float:
    """mu_m: the m-th eigenvalue with the constraint DOF fixed (the k -> infinity limit). Collective."""
    lo, hi = ops.K.getOwnershipRange()
    keep = np.arange(lo, hi, dtype=PETSc.IntType)
    keep = keep[keep != row]
    index = PETSc.IS().createGeneral(keep, comm=ops.comm)
    K = M = None
    try:   # the index set and the submatrices are freed also when a submatrix or the solve fails
        K = ops.K.createSubMatrix(index, index)
        M = ops.M.createSubMatrix(index, index)
        pinned = Operators(comm=ops.comm, K=K, M=M, rigid_modes=ops.rigid_modes, eigen_scale=ops.eigen_scale)
        mu, phi = lowest_eigenpair(pinned, pinned.K, branch, PREFIX, f"pinned modes (row {row})", EIGEN_TOL)
        phi.destroy()
    finally:
        destroy(K, M, index)
    return mu


def participation(modes: ModalBasis, rows: np.ndarray) -> np.ndarray:
    """(g_j^T phi_i)^2 for every constraint j (rows) and reference mode i: (N_L, N). Collective."""
    return bv_rows(modes.vectors, rows) ** 2


def auto_stiffness(pinned: float, reference_eigenvalue: float, participation: float) -> float:
    """k_auto = (mu_m - lambda_m(0)) / (g^T phi_m)^2: where the small-k and large-k asymptotes of
    lambda_m(k) meet (the corner of the paper's Fig. 2)."""
    return max(pinned - reference_eigenvalue, 0.0) / participation


def central_derivative(ops: Operators, row: int, k: float, branch: int, phi: PETSc.Vec,
                       eigenpair=None) -> PETSc.Vec:
    """d phi/dk by the paper's central difference in k, eigenvectors sign-aligned with phi;
    eigenpair(k, branch) -> (lambda, phi) solves the spring-perturbed problem (default: factored)."""
    eigenpair = eigenpair or (lambda kk, m: spring_eigenpair(ops, row, kk, m))
    h = CENTRAL_STEP
    Mphi = ops.M.createVecLeft()
    ops.M.mult(phi, Mphi)
    ends = []
    try:
        for factor in (1 + h, 1 - h):
            _, v = eigenpair(k * factor, branch)
            ends.append(v)
            if v.dot(Mphi) < 0:
                v.scale(-1.0)
        d = ends[0].copy()
        d.axpy(-1.0, ends[1])
        d.scale(1.0 / (2 * h * k))
    finally:
        destroy(Mphi, *ends)
    return d


def derivative_system(ops: Operators, row: int, k: float, lam: float, phi: PETSc.Vec):
    """(A - lambda M, the right side -(g (g^T phi) - (g^T phi)^2 M phi), M phi) of the derivative
    equation (module docstring, step 3), A = K + k g g^T; new objects, the caller's. Collective."""
    A = with_spring(ops.K, row, k)
    A.axpy(-lam, ops.M, structure=PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
    gphi = value_at(phi, row)
    Mphi = ops.M.createVecLeft()
    ops.M.mult(phi, Mphi)
    rhs = Mphi.copy()
    rhs.scale(gphi**2)
    lo, hi = rhs.getOwnershipRange()
    if lo <= row < hi:
        rhs.setValue(row, -gphi, addv=PETSc.InsertMode.ADD_VALUES)
    rhs.assemble()
    return A, rhs, Mphi


def backward_error(A: PETSc.Mat, d: PETSc.Vec, rhs: PETSc.Vec, residual: PETSc.Vec) -> float:
    """Normwise backward error ||r|| / (||A|| ||d|| + ||rhs||) of A d = rhs. A relative residual
    ||r|| / ||rhs|| would grow with cond(A) ~ elements^4 and reject exact-to-round-off answers on
    fine meshes. Collective."""
    return residual.norm() / (A.norm(PETSc.NormType.FROBENIUS) * d.norm() + rhs.norm())


def refine_derivative(ksp: PETSc.KSP, A: PETSc.Mat, rhs: PETSc.Vec, phi: PETSc.Vec, Mphi: PETSc.Vec,
                      failed, inaccurate) -> PETSc.Vec:
    """d with (K + k g g^T - lambda M) d = rhs and phi^T M d = 0 (the deflated derivative equation,
    module docstring, step 3) by `ksp` on A with iterative refinement (A is nearly singular along
    phi): at most REFINEMENT_STEPS + 1 solves, until the backward error is below
    DERIVATIVE_BACKWARD_TOL. A failed solve raises SolverError(failed(reason)), an inaccurate result
    SolverError(inaccurate(backward error)). Collective on A's communicator; the caller owns d."""
    d, correction, residual = A.createVecRight(), A.createVecRight(), rhs.copy()
    d.set(0.0)
    try:
        for _ in range(REFINEMENT_STEPS + 1):
            with frames_released():   # a PCShell inverse calls back (dbf_shared.py)
                ksp.solve(residual, correction)
            if ksp.getConvergedReason() < 0:
                raise SolverError(failed(ksp.getConvergedReason()))
            correction.axpy(-correction.dot(Mphi), phi)  # deflate: phi^T M phi' = 0
            d.axpy(1.0, correction)
            A.mult(d, residual)
            residual.aypx(-1.0, rhs)
            backward = backward_error(A, d, rhs, residual)
            if backward < DERIVATIVE_BACKWARD_TOL:
                return d
        raise SolverError(inaccurate(backward))
    except Exception:
        d.destroy()
        raise
    finally:
        destroy(correction, residual)


def analytic_derivative(ops: Operators, row: int, k: float, lam: float, phi: PETSc.Vec) -> PETSc.Vec:
    """d phi/dk from the deflated derivative equation (module docstring, step 3), by a factorization
    of A - lambda M (LU: it is indefinite) with iterative refinement."""
    A, rhs, Mphi = derivative_system(ops, row, k, lam, phi)
    ksp = None
    try:
        ksp = direct_solver(PETSc.KSP().create(comm=ops.comm))  # A - lambda M is indefinite: LU
        ksp.setOperators(A)
        ksp.setOptionsPrefix(PREFIX)
        ksp.setFromOptions()   # a -dbf_ option PETSc refuses raises here: ksp is destroyed below
        d = refine_derivative(
            ksp, A, rhs, phi, Mphi,
            failed=lambda reason: (f"DBF derivative solve failed at row {row} ({reason}); "
                                   f"try dbf_derivative = \"central\""),
            inaccurate=lambda backward: (f"DBF derivative at row {row} is inaccurate (backward error {backward:.2e}); "
                                         f"try dbf_derivative = \"central\" or a tighter -dbf_eps_tol"))
    finally:
        destroy(ksp, A, Mphi, rhs)
    return d


class FactorSolver:
    """The three solves of one constraint, each with its own factorization (dbf_solver = "factor",
    the paper-faithful comparator): the pinned problem on K, M without the constraint's row and
    column, the spring-perturbed problem on K + k g g^T, the derivative with LU of A - lambda M.
    dbf_shared.SharedSolver has the same interface on one shared factorization."""

    def __init__(self, ops: Operators, row: int):
        self.ops, self.row = ops, row

    def pinned(self, branch: int) -> float:
        return pinned_eigenvalue(self.ops, self.row, branch)

    def eigenpair(self, k: float, branch: int):
        return spring_eigenpair(self.ops, self.row, k, branch)

    def derivative(self, k: float, lam: float, phi: PETSc.Vec) -> PETSc.Vec:
        return analytic_derivative(self.ops, self.row, k, lam, phi)

    def destroy(self) -> None:
        pass


def dbf_source(ops: Operators, row: int, reference_eigenvalues: np.ndarray, participation: np.ndarray,
               stiffness="auto", derivative: str = "analytic", solver=None) -> DbfSource:
    """The derivative d phi/dk that becomes constraint `row`'s DBF after Gram-Schmidt.

    reference_eigenvalues  lambda_i of the reference modes
    participation          (g^T phi_i)^2 of the reference modes at this constraint
    solver                 FactorSolver(ops, row) (the default), a dbf_shared.SharedSolver or a
                           dbf_ritz.RitzSolver for row (the caller destroys it)
    Returns a DbfSource whose derivative Vec is the caller's. Collective on ops.comm.
    """
    # Rigid-body eigenvalues are zero up to round-off (1e-9 rad^2/s^2 apart on a free-free beam):
    # exactly one repeated eigenvalue, which the spring moves in one direction only.
    reference_eigenvalues = np.where(np.arange(participation.size) < ops.rigid_modes, 0.0, reference_eigenvalues)
    branch = branch_of(participation, reference_eigenvalues)
    if branch == 0:
        raise SolverError(f"the constraint at row {row} does not move in any of the "
                          f"{participation.size} reference modes; add modes or move the constraint")
    solver = solver or FactorSolver(ops, row)
    k_auto = auto_stiffness(solver.pinned(branch), reference_eigenvalues[branch - 1],
                            cluster_participation(participation, reference_eigenvalues))
    k = k_auto if stiffness == "auto" else float(stiffness)
    lam, phi = solver.eigenpair(k, branch)
    try:
        if derivative == "central":
            d = central_derivative(ops, row, k, branch, phi, solver.eigenpair)
        else:
            d = solver.derivative(k, lam, phi)
    finally:
        phi.destroy()
    return DbfSource(row=row, branch=branch, stiffness=k, transition=k_auto, eigenvalue=lam, derivative=d)


def stiffness_sweep(ops: Operators, row: int, stiffnesses, branch: int = 1) -> np.ndarray:
    """omega_m(k) (rad/s) of the spring-perturbed problem over a list of k (the paper's Fig. 2)."""
    omegas = []
    for k in stiffnesses:
        lam, phi = spring_eigenpair(ops, row, float(k), branch, tol=1e-10)
        phi.destroy()
        omegas.append(np.sqrt(max(lam, 0.0)))
    return np.array(omegas)
