"""The Rayleigh-Ritz DBF path ([basis] dbf_solver = "ritz"; docs/design.md, "One factorization per
constraint group").

Every vector a DBF needs lies, to high accuracy, in a small subspace: the N reference modes Phi
(M-orthonormal, Phi^T K Phi = diag lambda_i) plus a rational Krylov sequence on g at the shared
shift sigma (A = K - sigma M, factored once per group: dbf_shared.SharedFactor),

    V = span{Phi, z_1, ..., z_p},   z_1 = A^-1 g,  z_{j+1} = A^-1 M z_j.

Why: the spring-perturbed and the pinned eigenvectors are both (K - lambda M)^-1 g up to scale
(lambda = lambda_m(k), or mu_m with g^T x = 0), i.e. sum_i phi_i (phi_i^T g) / (lambda_i - lambda).
Phi carries the modes i <= N exactly; for the tail i > N,
    1 / (lambda_i - lambda) = sum_j (lambda - sigma)^j / (lambda_i - sigma)^(j+1),
a Neumann series whose j-th term is z_{j+1} minus its part on Phi, so the error after p vectors
falls like ((lambda - sigma) / (lambda_{N+1} - sigma))^p (on the Table 1 beam with 6 modes and
branch 1, ~(2/7)^4 = 0.007 per vector). The derivative d phi/dk differentiates (K - lambda M)^-1 g
in lambda: the squared resolvent, the same series with a factor (j + 1): the same subspace.

Per constraint: extend V one Krylov vector at a time (one shared-factor solve, CGS2 in the M inner
product, one MatMult with K and one with M), and solve small dense problems on V, replicated on
every rank (rank 0's numbers are broadcast, so every rank takes the same path):
- mu_m: the m-th eigenvalue of V^T K V on the coefficients with h^T y = 0 (h = V^T g);
- (lambda_m(k), phi_m): the m-th eigenpair of V^T K V + k h h^T;
- d phi/dk: differentiating the small problem, (H_k - theta) y' = -(h (h^T y) - (h^T y)^2 y),
  y^T y' = 0, from its eigendecomposition; d = V y'. The subspace does not depend on k, so this
  is exactly the derivative of the Ritz vector (Galerkin with phi deflated).
A stage is accepted when one more vector changes its eigenvalue by less than EIGEN_CHANGE_TOL
(relative to lambda - sigma) and its M-normalized vector and derivative by less than
VECTOR_CHANGE_TOL (the accepted iterate, one vector further, is ~0.007 times better still); then
the eigen-residual and the derivative's backward error are checked on the full operators as on
the factored path. A stage that does not converge within P_MAX vectors, or fails a check, falls
back to the shared path (dbf_shared.SharedSolver) for the rest of that constraint (counters).

Collective on the group's communicator; the options of the shared factorization apply
(-dbf_shared_pc_factor_mat_solver_type ...).
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from .dbf import DERIVATIVE_BACKWARD_TOL, value_at
from .dbf_shared import SharedFactor, SharedSolver
from .modes import normalize
from .petsctools import destroy, unit_vector

P_MAX = 8                  # Krylov vectors per constraint before falling back to the shared path
EIGEN_CHANGE_TOL = 1e-10   # change of the Ritz value, relative to lambda - sigma
VECTOR_CHANGE_TOL = 1e-9   # change of the M-normalized Ritz vector and of the derivative (relative)
RESIDUAL_TOL = DERIVATIVE_BACKWARD_TOL  # normwise backward error of the accepted eigenpair
BREAKDOWN = 1e-10          # a Krylov vector this small after orthogonalization: V is invariant

# Work done by this process on the Ritz path (tests and benchmarks read it): constraints served,
# Krylov vectors made, stages handed to the shared path.
counters = {"constraints": 0, "vectors": 0, "fallbacks": 0}


class RitzSpace:
    """What the constraints of a group share: the factor of A = K - sigma M, the reference modes on
    the group's communicator with M Phi and Phi^T K Phi, and ||K||_F, ||M||_F. Owns the mode Vecs
    (given) and the factor if `own_factor`. Collective."""

    def __init__(self, factor: SharedFactor, modes: list, eigenvalues: np.ndarray):
        self.factor, self.ops, self.sigma = factor, factor.ops, factor.sigma
        K, M = self.ops.K, self.ops.M
        self.Phi, self.MPhi = list(modes), []
        for phi in self.Phi:
            self.MPhi.append(M.createVecLeft())
            M.mult(phi, self.MPhi[-1])
        # Phi^T K Phi = diag(lambda_i), the reference modes taken as exact eigenpairs: a Rayleigh
        # quotient through K loses ~u ||K|| / lambda (5e-9 on the 100-element free beams), the
        # shift-and-invert eigenvalues do not.
        self.eigenvalues = np.asarray(eigenvalues, dtype=float)
        self.H0 = np.diag(self.eigenvalues)
        self.K_norm, self.M_norm = K.norm(PETSc.NormType.FROBENIUS), M.norm(PETSc.NormType.FROBENIUS)

    def destroy(self) -> None:
        destroy(*self.Phi, *self.MPhi)
        self.Phi, self.MPhi = [], []


class RitzSolver:
    """The three solves of one constraint (dbf.FactorSolver's interface) by Rayleigh-Ritz on
    span{Phi, z_1..z_p} (module docstring), falling back to dbf_shared.SharedSolver. Owns its
    Krylov vectors and the fallback solver."""

    def __init__(self, space: RitzSpace, row: int):
        self.space, self.ops, self.row = space, space.ops, row
        self.comm = self.ops.comm.tompi4py()
        n = len(space.Phi)
        self.V, self.MV, self.own = list(space.Phi), list(space.MPhi), []
        self.H = np.zeros((n + P_MAX, n + P_MAX))
        self.H[:n, :n] = space.H0
        lo, hi = self.ops.K.getOwnershipRange()
        local = np.array([phi.getArray(readonly=True)[row - lo] if lo <= row < hi else 0.0 for phi in space.Phi])
        self.h = np.zeros(n + P_MAX)
        self.h[:n] = self.comm.allreduce(local)
        self.exhausted = False
        self.fallback = None
        self.spring = None     # (k, branch, theta, y, y') of the last accepted spring-perturbed stage
        counters["constraints"] += 1

    @property
    def size(self) -> int:
        return len(self.V)

    # -- the subspace -----------------------------------------------------------------------------

    def _extend(self) -> bool:
        """Add one Krylov vector (one solve); False when P_MAX is reached or V is invariant."""
        if self.exhausted or len(self.own) >= P_MAX:
            return False
        factor, M, K = self.space.factor, self.ops.M, self.ops.K
        x = M.createVecRight()
        g = unit_vector(x, self.row) if not self.own else None
        try:
            factor.solve(g if g is not None else self.MV[-1], x)
        finally:
            destroy(g)
        Mx = M.createVecLeft()
        M.mult(x, Mx)
        before = np.sqrt(max(x.dot(Mx), 0.0))
        for _ in range(2):     # classical Gram-Schmidt, twice, in the M inner product
            x.maxpy(-np.asarray(_dots(x, self.MV)), self.V)
        M.mult(x, Mx)
        norm = np.sqrt(max(x.dot(Mx), 0.0))
        if not norm > BREAKDOWN * before:
            self.exhausted = True
            destroy(x, Mx)
            return False
        x.scale(1.0 / norm)
        Mx.scale(1.0 / norm)
        Kx = K.createVecLeft()
        K.mult(x, Kx)
        q, n = self.size, len(self.space.Phi)
        # K phi_i = lambda_i M phi_i (RitzSpace): the Phi rows without K's rounding
        column = np.concatenate((self.space.eigenvalues * _dots(x, self.space.MPhi),
                                 _dots(Kx, self.V[n:]), [Kx.dot(x)]))
        Kx.destroy()
        gx = value_at(x, self.row)
        column, gx = self.comm.bcast((column, gx), root=0)   # every rank the same small problems
        self.H[:q + 1, q] = self.H[q, :q + 1] = column
        self.h[q] = gx
        self.V.append(x)
        self.MV.append(Mx)
        self.own.append(x)
        counters["vectors"] += 1
        return True

    def _vector(self, y: np.ndarray) -> PETSc.Vec:
        """V y (a new Vec)."""
        x = self.ops.M.createVecRight()
        x.set(0.0)
        x.maxpy(y[:self.size], self.V)
        return x

    def _converge(self, reduce):
        """Extend V until reduce() (on the current V: (eigenvalue, [coefficient vectors])) changes by
        less than the tolerances; its last value, or None (P_MAX reached). Collective."""
        if not self.own:
            self._extend()
        previous = reduce()
        while self._extend():
            current = reduce()
            if _close(previous, current, self.space.sigma):
                return current
            previous = current
        return previous if self.exhausted else None   # an invariant V: the Ritz pair is exact

    def _to_fallback(self) -> SharedSolver:
        if self.fallback is None:
            counters["fallbacks"] += 1
            self.fallback = SharedSolver(self.space.factor, self.row)
        return self.fallback

    # -- the small problems -----------------------------------------------------------------------

    def _pinned_reduced(self, branch: int):
        q = self.size
        h = self.h[:q]
        basis, _ = np.linalg.qr(h.reshape(-1, 1), mode="complete")
        Q = basis[:, 1:]              # the coefficients with h^T y = 0
        theta, W = np.linalg.eigh(Q.T @ self.H[:q, :q] @ Q)
        return theta[branch - 1], [Q @ W[:, branch - 1]]

    def _spring_reduced(self, k: float, branch: int):
        q = self.size
        h = self.h[:q]
        theta, W = np.linalg.eigh(self.H[:q, :q] + k * np.outer(h, h))
        m = branch - 1
        y = W[:, m]
        hy = h @ y
        rhs = -(h * hy - hy**2 * y)
        gaps = theta - theta[m]
        gaps[m] = 1.0
        coefficients = (W.T @ rhs) / gaps
        coefficients[m] = 0.0          # y^T y' = 0
        return theta[m], [y, W @ coefficients]

    # -- the interface ----------------------------------------------------------------------------

    def pinned(self, branch: int) -> float:
        """mu_m, the m-th eigenvalue of the pinned problem. Collective."""
        if self.fallback is None:
            result = self._converge(lambda: self._pinned_reduced(branch))
            if result is not None:
                return float(result[0])
        return self._to_fallback().pinned(branch)

    def eigenpair(self, k: float, branch: int):
        """(lambda_m, phi_m) of (K + k g g^T, M), phi M-normalized as on the factored path. Collective."""
        self.spring = None
        if self.fallback is None:
            result = self._converge(lambda: self._spring_reduced(k, branch))
            if result is not None:
                theta, (y, dy) = result
                phi = self._vector(y)
                if self._residual(k, theta, phi) < RESIDUAL_TOL:
                    normalize(phi, self.ops.M)   # the package's sign convention (y is M-normalized)
                    self.spring = (k, branch, float(theta), y, dy)
                    return float(theta), phi
                phi.destroy()
        return self._to_fallback().eigenpair(k, branch)

    def derivative(self, k: float, lam: float, phi: PETSc.Vec) -> PETSc.Vec:
        """d phi/dk, the derivative of the Ritz vector (module docstring), sign-aligned with phi;
        checked by its backward error on the full operator. Collective."""
        if self.fallback is None and self.spring is not None and self.spring[0] == k and self.spring[2] == lam:
            _, _, _, y, dy = self.spring
            sign = 1.0 if float(np.dot(np.asarray(_dots(phi, self.MV[:y.size])), y)) >= 0 else -1.0
            d = self._vector(sign * dy)
            if self._derivative_backward_error(k, lam, phi, d) < DERIVATIVE_BACKWARD_TOL:
                return d
            d.destroy()
        return self._to_fallback().derivative(k, lam, phi)

    # -- checks on the full operators -------------------------------------------------------------

    def _apply(self, k: float, lam: float, x: PETSc.Vec) -> PETSc.Vec:
        """(K + k g g^T - lam M) x (a new Vec)."""
        K, M = self.ops.K, self.ops.M
        r, Mx = K.createVecLeft(), M.createVecLeft()
        K.mult(x, r)
        M.mult(x, Mx)
        r.axpy(-lam, Mx)
        Mx.destroy()
        gx = value_at(x, self.row)
        lo, hi = r.getOwnershipRange()
        if lo <= self.row < hi:
            r.setValue(self.row, k * gx, addv=PETSc.InsertMode.ADD_VALUES)
        r.assemble()
        return r

    def _norm_bound(self, k: float, lam: float) -> float:
        """||K||_F + k + |lam| ||M||_F >= ||K + k g g^T - lam M||_F."""
        return self.space.K_norm + abs(k) + abs(lam) * self.space.M_norm

    def _residual(self, k: float, lam: float, phi: PETSc.Vec) -> float:
        r = self._apply(k, lam, phi)
        try:
            return r.norm() / (self._norm_bound(k, lam) * phi.norm())
        finally:
            r.destroy()

    def _derivative_backward_error(self, k: float, lam: float, phi: PETSc.Vec, d: PETSc.Vec) -> float:
        r = self._apply(k, lam, d)
        rhs = self.ops.M.createVecLeft()
        try:
            gphi = value_at(phi, self.row)
            self.ops.M.mult(phi, rhs)
            rhs.scale(gphi**2)
            lo, hi = rhs.getOwnershipRange()
            if lo <= self.row < hi:
                rhs.setValue(self.row, -gphi, addv=PETSc.InsertMode.ADD_VALUES)
            rhs.assemble()
            r.axpy(-1.0, rhs)
            return r.norm() / (self._norm_bound(k, lam) * d.norm() + rhs.norm())
        finally:
            destroy(r, rhs)

    def destroy(self) -> None:
        destroy(self.fallback, *self.own, *self.MV[len(self.space.Phi):])
        self.V, self.MV, self.own, self.fallback = [], [], [], None


def _dots(x: PETSc.Vec, vectors: list) -> np.ndarray:
    """[v^T x for v in vectors] on every rank, one reduction (petsc4py 3.18 has no Vec.mDot). Collective."""
    local = x.array_r
    out = np.array([np.dot(v.array_r, local) for v in vectors])
    return x.getComm().tompi4py().allreduce(out) if x.getComm().getSize() > 1 else out


def _close(previous, current, sigma: float) -> bool:
    """Whether two successive (eigenvalue, [coefficient vectors]) agree to the tolerances; the
    vectors are compared up to sign, the shorter padded with zeros."""
    (a, xs), (b, ys) = previous, current
    if not abs(a - b) <= EIGEN_CHANGE_TOL * abs(b - sigma):
        return False
    sign = None
    for x, y in zip(xs, ys):     # the first is the eigenvector: its sign is the derivative's too
        x = np.pad(x, (0, y.size - x.size))
        sign = sign or (1.0 if float(np.dot(x, y)) >= 0 else -1.0)
        x = sign * x
        if not np.linalg.norm(x - y) <= VECTOR_CHANGE_TOL * max(np.linalg.norm(y), 1e-300):
            return False
    return True
