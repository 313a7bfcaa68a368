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
product, one MatMult with M) and solve small dense problems, replicated (rank 0's numbers are
broadcast, so every rank takes the same path). With V = [Phi, v_1..v_p] M-orthonormal, Gram-Schmidt
gives z = A^-1 g = V s and A^-1 M V[:, :q] = V[:, :q+1] C (T0 = Phi^T M A^-1 M Phi once per group,
N solves), so the shift-and-invert operators of all three problems,
    (A + k g g^T)^-1 M = A^-1 M - c z z^T M,   c = k / (1 + k g^T z),  c = 1 / g^T z pinned,
are known on V[:, :q], with their residual on the next vector, without K (the Rayleigh quotients
through K lose ~u ||K|| / lambda: 1e-8 on the 100-element free beams):
- mu_m: nu_m, the m-th largest eigenvalue of T - s s^T / g^T z, mu = sigma + 1/nu (the direction
  M^-1 g has nu = 0: never among the largest);
- (lambda_m(k), phi_m): the m-th eigenpair of T - c s s^T, phi = V y;
- d phi/dk: differentiating the small problem in k, (T_k - nu) y' = dc (s^T y) s - dnu y,
  y^T y' = 0, from its eigendecomposition; d = V y'. V does not depend on k, so this is exactly
  the derivative of the Ritz vector (Galerkin with phi deflated).
A stage is accepted when its residual on the next vector (the Lanczos residual) is below EIGEN_TOL
relative to nu, as SLEPc's test on the other paths, and the derivative's below DERIVATIVE_TOL; then
the eigen-residual and the derivative's backward error are checked on the full operators as on the
factored path. Measuring that residual takes the next vector's solve. A stage that fails it is
tried again "closed" on all of V before that solve (_closed_stack): the newest vector v lies in the
M-complement of the lowest N modes, where A^-1 M has its spectrum in (0, theta_N], theta_N =
1 / (lambda_N - sigma) (T0's smallest eigenvalue), so with v's own unknown coefficient taken as
theta_N / 2 the residual of every Ritz pair, and of its derivative, is at most theta_N / 2 times the
pair's coefficient on v; accepted where that bound is CLOSED_FACTOR times the tolerance. This saves
the last solve of most constraints (2.90 to 2.06 solves per DBF on the 10^4-DOF beam at 100
constraints). It rests on Phi being the lowest N modes, which reference_modes checks by the inertia. A stage that does not converge within P_MAX vectors, or fails a check, falls back to
the shared path (dbf_shared.SharedSolver) for the rest of that constraint (counters).

In blocks (the default for the analytic derivative: RitzSpace.sources, PREFETCH_BLOCK constraints
at a time): every step above for all the block's constraints together. Per Krylov step one
multi-right-hand-side solve (MatMatSolve), the same CGS2 and one M product (MatMatMult) for the
constraints still unconverged; the small problems of all of them as one stack (numpy's batched
eigh); then phi = V y and d = V y' of the block with M phi and M d from M V, one K product
(MatMatMult) for the eigen-residuals and the derivatives' backward errors, normalization and the
sign in one pass. The Gram-Schmidt dots and subtractions, V y and the checks' sums run column by
column in C when the extension is built (dbf_hpc/_romc/ritz_kernels.c: rows in chunks, so the modes'
chunk stays in L1 while the columns pass, and no temporary blocks), numpy otherwise; they are
memory-bound, so what counts is how often the 10^4-10^5-row columns are swept. Each constraint's
V, coefficients and decisions are those it makes alone, so the DBFs are those of one constraint at
a time (to round-off, 1e-14-1e-12; tests at 1e-10; the C kernels and numpy agree to 1e-12). A
constraint with no moving mode, an invariant V, no convergence within P_MAX vectors or a failed
check is left to the one-at-a-time path (RitzSolver), which repeats its steps and takes the same
fallback. The central-difference derivative goes one at a time, its first PREFETCH Krylov vectors
made in blocks by RitzSpace.prefetch.

Collective on the group's communicator; the options of the shared factorization apply
(-dbf_shared_pc_factor_mat_solver_type ...).
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from . import _romc
from .dbf import DERIVATIVE_BACKWARD_TOL, EIGEN_TOL
from .dbf_shared import SharedFactor, SharedSolver, check_amplification
from .modes import normalize
from .operators import Operators
from .petsctools import destroy, unit_vector

P_MAX = 8                  # Krylov vectors per constraint before falling back to the shared path
DERIVATIVE_TOL = 1e-10     # the derivative's residual on the next vector, as EIGEN_TOL for the eigenpair
RESIDUAL_TOL = DERIVATIVE_BACKWARD_TOL  # normwise backward error of the accepted eigenpair
MODES_RESIDUAL_FACTOR = 10  # the residuals asked for are at least this times the modes' own (RitzSpace)
BREAKDOWN = 1e-10          # a Krylov vector this small after orthogonalization: V is invariant
# The closed stages' bound on A^-1 M over the modes' M-complement is theta_N times this: far above the
# modes' own error (their shift-and-invert residual, 1e-6 at most where accepted)
TAIL_MARGIN = 1.01
# A closed stage is accepted where its residual bound is this times the tolerance: a measured stage's
# residual is usually far below the tolerance when it passes (each Krylov vector shrinks it by 0.007-0.1
# on the beams), and at 1 a given stiff k (1e5 N/m, paper beam) moved the DBF by 1.2e-8 against 2e-11
CLOSED_FACTOR = 0.1
CLOSED = True              # closed stages (_closed_stack): a stage accepted without its certifying solve
# The first Krylov vectors of the constraints are made a block at a time (RitzSpace.prefetch): one
# solve with many right-hand sides costs a fraction of as many single solves (MUMPS on the 104 040-DOF
# solid: 0.27 s a solve alone, 0.044 s each in a block of 50). A DBF uses 3-4 vectors (docs/benchmarks.md).
PREFETCH = 4               # vectors per constraint made in blocks (at most P_MAX)
PREFETCH_BLOCK = 64        # constraints per block (memory: ~2 P_MAX + 6 local rows of each)
BLOCK_SOURCES = True       # the analytic DBFs of a block at once (RitzSpace.sources); False: one at a time

# The column kernels of the blocks (dbf_hpc/_romc/ritz_kernels.c) when the C extension is built; numpy
# otherwise (tests switch between them)
_kernels = _romc.core

# Work done by this process on the Ritz path (tests and benchmarks read it): constraints served (of
# them by RitzSpace.sources: "in blocks"), Krylov vectors made, stages handed to the shared path.
counters = {"constraints": 0, "in blocks": 0, "vectors": 0, "fallbacks": 0}


class RitzSpace:
    """What the constraints of a group share: the factor of A = K - sigma M, the reference modes on
    the group's communicator (owned; their local rows also as a numpy block) with M Phi and
    T0 = Phi^T M A^-1 M Phi (N solves; A^-1 M Phi is taken to lie in span Phi: the modes' own
    residual is neglected), and ||K||_F, ||M||_F for the final checks. Collective."""

    def __init__(self, factor: SharedFactor, modes: list):
        """Takes ownership of `modes` (Vecs) on success; on an error the caller still owns them."""
        self.factor, self.ops, self.sigma = factor, factor.ops, factor.sigma
        self.comm = self.ops.comm.tompi4py()
        self.Phi, self.MPhi = list(modes), []
        try:
            self._setup()
        except Exception:
            destroy(*self.MPhi)
            self.Phi, self.MPhi = [], []
            raise

    def _setup(self) -> None:
        M = self.ops.M
        for phi in self.Phi:
            self.MPhi.append(M.createVecLeft())
            M.mult(phi, self.MPhi[-1])
        n, nloc = len(self.Phi), M.getLocalSize()[1]
        # The local rows of V and M V for the constraints, one at a time: Phi's, then the Krylov vectors'
        width = n + P_MAX + 1
        self.V_local, self.MV_local = np.zeros((width, nloc)), np.zeros((width, nloc))
        self.V_local[:n] = np.array([v.array_r for v in self.Phi]).reshape(n, nloc)
        self.MV_local[:n] = np.array([v.array_r for v in self.MPhi]).reshape(n, nloc)
        self.Phi_local, self.MPhi_local = self.V_local[:n], self.MV_local[:n]
        # T0 = Phi^T M A^-1 M Phi by N solves, not diag(1 / (lambda_i - sigma)): with rigid-body modes
        # the pinned operator subtracts nearly equal terms of size 1 / (lambda_1 - sigma), and the modes'
        # own eigenvalue error (4e-9 for a rigid mode's 0) became 1e-6 in mu on the free beams.
        # A^-1 M Phi is taken to lie in span Phi: the part outside, the modes' own shift-and-invert
        # residual rho_j (relative), bounds what the Ritz residuals can reach (module docstring).
        # the N solves as one block (factor.solve_block)
        W = self.factor.solve_block(np.asfortranarray(self.MPhi_local.T)) if n else np.zeros((nloc, 0))
        self.T0 = _sum(self.comm, self.MPhi_local @ W)
        W -= self.Phi_local.T @ self.T0
        rho = (np.sqrt(np.maximum(_sum(self.comm, np.einsum("ij,ij->j", W, _mult_block(M, W))), 0.0))
               / np.abs(np.diag(self.T0))) if n else np.zeros(0)
        self.T0, self.modes_residual = self.comm.bcast(
            (0.5 * (self.T0 + self.T0.T), float(rho.max(initial=0.0))), root=0)
        # theta_N = 1 / (lambda_N - sigma), T0's smallest eigenvalue: A^-1 M on the M-complement of the
        # lowest N modes has its spectrum in (0, theta_{N+1}] within (0, theta_N] (closed stages, _closed)
        self.tail_bound = (TAIL_MARGIN * float(np.linalg.eigvalsh(self.T0)[0])) if n else None
        self.eigen_tol = max(EIGEN_TOL, MODES_RESIDUAL_FACTOR * self.modes_residual)
        self.derivative_tol = max(DERIVATIVE_TOL, MODES_RESIDUAL_FACTOR * self.modes_residual)
        self.K_norm, self.M_norm = self.ops.K.norm(PETSc.NormType.FROBENIUS), M.norm(PETSc.NormType.FROBENIUS)
        self.prefetched = {}

    def prefetch(self, rows) -> None:
        """Make the first min(PREFETCH, P_MAX) Krylov vectors of each constraint at `rows` (global rows of
        the group's operators) as blocks: per step one solve with all the rows' right-hand sides
        (factor.solve_block) and Gram-Schmidt on the block, the same arithmetic as RitzSolver._extend
        column by column (rank 0's small numbers broadcast as there). RitzSolver(space, row) takes them
        (and forgets them) instead of solving. Collective on the group."""
        depth, n = min(PREFETCH, P_MAX), len(self.Phi)
        rows = [int(r) for r in rows if int(r) not in self.prefetched]
        if depth < 1 or not rows:
            return
        M, L = self.ops.M, len(rows)
        lo, hi = M.getOwnershipRange()
        local = [(j, r - lo) for j, r in enumerate(rows) if lo <= r < hi]
        steps = {r: [] for r in rows}
        alive = np.ones(L, dtype=bool)
        rhs = np.zeros((hi - lo, L), order="F")
        for j, i in local:
            rhs[i, j] = 1.0
        V, MV = [], []                        # per step: the normalized block and M times it (local rows)
        gz = None
        for p in range(depth):
            a = self.factor.solve_block(rhs)  # A^-1 g, then A^-1 M v_p
            if p == 0:
                gz = _sum(self.comm, _at(a, local, L))     # g^T A^-1 g per constraint
            coefficients = np.zeros((n + p, L))
            for _ in range(2):                # classical Gram-Schmidt, twice, in the M inner product
                c = np.empty((n + p, L))
                c[:n] = self.MPhi_local @ a
                for k in range(p):
                    c[n + k] = np.einsum("ij,ij->j", MV[k], a)
                c = _sum(self.comm, c)
                a -= self.Phi_local.T @ c[:n]
                for k in range(p):
                    a -= V[k] * c[n + k]
                coefficients += c
            b = _mult_block(M, a)
            norm2, gx = _sum(self.comm, np.vstack([np.einsum("ij,ij->j", a, b), _at(a, local, L)]))
            norm = np.sqrt(np.maximum(norm2, 0.0))
            before = np.hypot(np.linalg.norm(coefficients, axis=0), norm)
            columns = np.vstack([coefficients, norm])
            if self.comm.size > 1:
                columns, gz, gx = self.comm.bcast((columns, gz, gx), root=0)
            ok = alive & (norm > BREAKDOWN * before)
            scale = np.where(ok, norm, 1.0)
            a /= scale
            b /= scale
            for j, r in enumerate(rows):   # views into the block (column-major): no second copy
                if alive[j]:
                    steps[r].append(_Prefetched(columns[:, j].copy(), float(gz[j]), float(gx[j] / scale[j]),
                                                a[:, j] if ok[j] else None, b[:, j] if ok[j] else None))
            alive = ok
            if not alive.any():
                break
            V.append(a)
            MV.append(b)
            rhs = np.asfortranarray(b)
        self.prefetched.update(steps)

    def sources(self, rows, reference_eigenvalues: np.ndarray, participation: np.ndarray, stiffness="auto"):
        """The DBF sources (analytic derivative) of the constraints at `rows` together, as a block
        (module docstring, "In blocks"): per Krylov step one multi-right-hand-side solve, Gram-Schmidt
        and M products for the constraints still unconverged, the small eigenproblems of all of them
        as one stack, then the checks on the full operators with one K product for the block. The
        arithmetic of RitzSolver and dbf.dbf_source constraint by constraint, so the same DBFs to
        round-off. A constraint with no moving mode, an invariant V, no convergence within P_MAX
        vectors or a failed check is not served: the caller gives it to the one-at-a-time path
        (RitzSolver), which repeats these steps and takes the same fallback.

        Returns (positions served (indices into rows), their branch, k, k_auto, lambda, and the
        derivatives' local rows (n_local x served)). Collective on the group; every decision is rank
        0's (broadcast)."""
        from .dbf import auto_stiffness, branches
        rows = np.asarray(rows, dtype=np.int64)
        L, n, comm = rows.size, len(self.Phi), self.comm
        M = self.ops.M
        lo, hi = M.getOwnershipRange()
        nloc = hi - lo
        participation = np.asarray(participation, dtype=float).reshape(L, -1)
        reference = np.asarray(reference_eigenvalues, dtype=float)
        # rigid-body eigenvalues are exactly 0 (dbf.dbf_source)
        reference = np.where(np.arange(reference.size) < self.ops.rigid_modes, 0.0, reference)
        branch, cluster = branches(participation, reference)
        width = n + P_MAX + 1
        mine = (rows >= lo) & (rows < hi)
        H = np.zeros((L, width))                       # g^T V per constraint
        H[mine, :n] = self.Phi_local[:, rows[mine] - lo].T
        H[:, :n] = _sum(comm, H[:, :n])
        C = np.zeros((L, width, width))
        C[:, :n, :n] = self.T0
        S, gz = np.zeros((L, width)), np.zeros(L)
        # stage: 0 pinned, 1 spring-perturbed, 2 done, -1 not served (the one-at-a-time path)
        stage = np.where(branch > 0, 0, -1)
        k, k_auto, lam = np.zeros(L), np.zeros(L), np.zeros(L)
        Y, DY = np.zeros((L, width)), np.zeros((L, width))
        steps = []            # per Krylov step: (constraints, their vectors' local rows, M times them)
        for p in range(P_MAX):
            act = np.flatnonzero((stage == 0) | (stage == 1))
            if not act.size:
                break
            La = act.size
            if p == 0:
                rhs = np.zeros((nloc, La), order="F")
                here = mine[act]
                rhs[rows[act][here] - lo, np.flatnonzero(here)] = 1.0
            else:
                rhs = _columns(steps[-1], act, 2)
            a = self.factor.solve_block(rhs)       # A^-1 g, then A^-1 M v_p
            local = np.flatnonzero(mine[act])
            at = np.zeros(La)
            at[local] = a[rows[act][local] - lo, local]
            if p == 0:
                gz_step = _sum(comm, at)            # g^T A^-1 g
            columns = _StepColumns(steps, act)
            coefficients = np.zeros((n + p, La))
            for _ in range(2):                 # classical Gram-Schmidt, twice, in the M inner product
                c = _sum(comm, columns.dots(self.MPhi_local, a))
                columns.subtract(self.Phi_local, c, a)   # in place, each constraint its own vectors
                coefficients += c
            b = _mult_block(M, a)
            at = np.zeros(La)                  # (a new array: _sum on one rank returns its argument)
            at[local] = a[rows[act][local] - lo, local]
            norm2, gx = _sum(comm, np.vstack([np.einsum("ij,ij->j", a, b), at]))
            columns = np.vstack([coefficients, np.sqrt(np.maximum(norm2, 0.0))])
            if comm.size > 1:       # every rank the same small problems and decisions: rank 0's numbers
                columns, gz_step, gx = comm.bcast((columns, gz_step if p == 0 else None, gx), root=0)
            norm = columns[-1]
            before = np.hypot(np.linalg.norm(columns[:-1], axis=0), norm)   # the M-norm before Gram-Schmidt
            counters["vectors"] += La
            q = n + p
            if p == 0:
                gz[act] = gz_step
                S[act, :q + 1] = columns.T
            else:
                C[act, :q + 1, q - 1] = columns.T
            ok = norm > BREAKDOWN * before
            stage[act[~ok]] = -1               # V invariant: the one-at-a-time path's special case
            scale = np.where(ok, norm, 1.0)
            a /= scale
            b /= scale
            H[act, q] = gx / scale
            steps.append((act, a, b))
            # the small problems on V[:, :q] (q = n + p: the newest vector closes them)
            moved = self._pinned_stage(np.flatnonzero(stage == 0), q, C, S, gz, branch, stage, lam)
            for j in moved:                    # mu_m known: the stiffness (dbf.dbf_source)
                k_auto[j] = auto_stiffness(lam[j], reference[branch[j] - 1], cluster[j])
                k[j] = k_auto[j] if stiffness == "auto" else float(stiffness)
            spring = np.flatnonzero(stage == 1)
            check_amplification(k[spring], gz[spring], rows[spring])
            self._spring_stage(spring, q, C, S, gz, k, branch, stage, lam, Y, DY)
            if p + 1 >= P_MAX:
                stage[(stage == 0) | (stage == 1)] = -1      # P_MAX reached: the shared path
        done = np.flatnonzero(stage == 2)
        empty = (done, branch[done], k[done], k_auto[done], lam[done], np.zeros((nloc, done.size), order="F"))
        if not done.size:
            return empty
        # phi = V y and d = V y' of the converged constraints as one block [phi d], and M [phi d] from
        # M V, as the one-at-a-time path (a MatMatMult with M instead gained nothing measurable)
        owners, coefficients = np.concatenate([done, done]), np.vstack([Y[done], DY[done]])
        XD, MXD = self._combine(owners, coefficients, steps, n, 1), self._combine(owners, coefficients, steps, n, 2)
        KXD = _mult_block(self.ops.K, XD)
        nd = done.size
        X, D, MX, MD = XD[:, :nd], XD[:, nd:], MXD[:, :nd], MXD[:, nd:]
        kd, lamd = k[done], lam[done]
        gphi = np.einsum("ij,ij->i", H[done], Y[done])           # g^T phi
        gd = np.einsum("ij,ij->i", H[done], DY[done])            # g^T d
        ramp = 1.0 + (np.arange(lo, hi) + 0.5) / M.getSize()[0]
        grow = np.where(mine[done], rows[done] - lo, -1)
        r2, x2, mass, ramp_x, rd2, d2, rhs2 = _sum(comm, _check_sums(X, D, MX, MD, KXD[:, :nd], KXD[:, nd:], lamd,
                                                                      kd, gphi, gd, grow, ramp))
        bound = self.K_norm + np.abs(kd) + np.abs(lamd) * self.M_norm
        residual = np.sqrt(r2) / (bound * np.sqrt(x2))
        backward = np.sqrt(rd2) / (bound * np.sqrt(d2) + np.sqrt(rhs2))
        accepted = (residual < RESIDUAL_TOL) & (mass > 0) & (backward < DERIVATIVE_BACKWARD_TOL)
        if comm.size > 1:
            accepted, ramp_x = comm.bcast((accepted, ramp_x), root=0)
        # the package's sign convention for phi (modes.normalize), the derivative aligned with it
        D *= np.where(ramp_x >= 0, 1.0, -1.0)
        served = done[accepted]
        counters["constraints"] += served.size
        counters["in blocks"] += served.size
        return (served, branch[served], k[served], k_auto[served], lam[served], D[:, accepted])

    def _pinned_stage(self, J, q, C, S, gz, branch, stage, lam) -> np.ndarray:
        """RitzSolver._pinned_reduced for the constraints J at size q, as one stack; the converged move
        to the spring-perturbed stage with mu_m in lam (returned: those)."""
        if not J.size:
            return J
        nu, W, beta_row = _reduced_stack(C[J], S[J], 1.0 / gz[J], q)
        m = branch[J] - 1
        y = W[np.arange(J.size), :, m]
        num = nu[np.arange(J.size), m]
        converged = np.abs(np.einsum("ij,ij->i", beta_row, y)) <= self.eigen_tol * np.abs(num)
        closing = np.flatnonzero(~converged) if self._closable() else np.zeros(0, dtype=int)
        if closing.size:      # the rest on all of V, the newest vector closed by the bound (_closed_stack)
            Jc = J[closing]
            nu, W = _closed_stack(C[Jc], S[Jc], 1.0 / gz[Jc], q, self.tail_bound)
            y = W[np.arange(Jc.size), :, m[closing]]
            num[closing] = nu[np.arange(Jc.size), m[closing]]
            converged[closing] = _closed_residual(self.tail_bound, y) <= self.eigen_tol * np.abs(num[closing])
        J = J[converged]
        stage[J] = 1
        lam[J] = self.sigma + 1.0 / num[converged]
        return J

    def _closable(self) -> bool:
        """Whether stages may be tried with the newest vector closed by the bound (_closed_stack)."""
        return CLOSED and self.tail_bound is not None

    def _spring_stage(self, J, q, C, S, gz, k, branch, stage, lam, Y, DY) -> None:
        """RitzSolver._spring_reduced for the constraints J at size q (k known), as one stack; the
        converged are done, with lambda_m(k) in lam and y, y' in Y, DY."""
        if not J.size:
            return
        kJ, gzJ = k[J], gz[J]
        c = kJ / (1.0 + kJ * gzJ)
        dc = (1.0 / (1.0 + kJ * gzJ)) ** 2   # squared after the division: no overflow at a k of 1e300 N/m

        def pairs(nu, W, J, m, c, dc, size):
            """The m-th pairs of a stack and their derivatives (RitzSolver._spring_reduced)."""
            idx = np.arange(J.size)
            y, num = W[idx, :, m], nu[idx, m]
            s = S[J, :size]
            sy = np.einsum("ij,ij->i", s, y)
            gaps = num[:, None] - nu
            gaps[idx, m] = 1.0
            coefficients = np.einsum("ikj,ik->ij", W, (-dc * sy)[:, None] * s) / gaps
            coefficients[idx, m] = 0.0
            return y, num, sy, np.einsum("ijk,ik->ij", W, coefficients)

        m = branch[J] - 1
        nu, W, beta_row = _reduced_stack(C[J], S[J], c, q)
        y, num, sy, dy = pairs(nu, W, J, m, c, dc, q)
        residual = np.abs(np.einsum("ij,ij->i", beta_row, y))
        derivative_residual = np.abs(np.einsum("ij,ij->i", beta_row, dy) - dc * S[J, q] * sy)
        converged = ((residual <= self.eigen_tol * np.abs(num))
                     & (derivative_residual <= self.derivative_tol * np.abs(num) * np.linalg.norm(dy, axis=1)))
        done, Jd, yd, dyd = [q], [J[converged]], [y[converged]], [dy[converged]]
        numd = [num[converged]]
        closing = np.flatnonzero(~converged) if self._closable() else np.zeros(0, dtype=int)
        if closing.size:      # the rest on all of V, the newest vector closed by the bound (_closed_stack)
            Jc, mc = J[closing], m[closing]
            nu, W = _closed_stack(C[Jc], S[Jc], c[closing], q, self.tail_bound)
            y, num, _, dy = pairs(nu, W, Jc, mc, c[closing], dc[closing], q + 1)
            ok = ((_closed_residual(self.tail_bound, y) <= self.eigen_tol * np.abs(num))
                  & (_closed_residual(self.tail_bound, dy) <= self.derivative_tol * np.abs(num) * np.linalg.norm(dy, axis=1)))
            done.append(q + 1)
            Jd.append(Jc[ok])
            yd.append(y[ok])
            dyd.append(dy[ok])
            numd.append(num[ok])
        for size, Jk, y, dy, num in zip(done, Jd, yd, dyd, numd):
            stage[Jk] = 2
            lam[Jk] = self.sigma + 1.0 / num
            Y[Jk] = 0.0
            DY[Jk] = 0.0
            Y[Jk, :size], DY[Jk, :size] = y, dy

    def _combine(self, owners, coefficients, steps, n: int, which: int = 1) -> np.ndarray:
        """V_j y_i for coefficient rows y_i (coefficients: m x width) of the constraints j = owners[i]
        (which = 1), or M V_j y_i (which = 2): local rows, n_local x m. The modes' part as one
        product, the Krylov vectors column by column (each its own)."""
        base = self.Phi_local if which == 1 else self.MPhi_local
        if _kernels is not None:
            pos = np.array([_positions(step[0], owners) for step in steps],
                           dtype=np.int_).reshape(len(steps), owners.size)
            return _kernels.ritz_columns_combine(base, [step[which] for step in steps], pos,
                                                 np.ascontiguousarray(coefficients[:, :n + len(steps)]))
        columns = coefficients[:, :n] @ base       # m x n_local, row-major: out (column-major) is its transpose
        out = columns.T
        for p, step in enumerate(steps):
            have, block = step[0], step[which].T
            position = np.minimum(np.searchsorted(have, owners), have.size - 1)
            d = coefficients[:, n + p]
            for i in np.flatnonzero((have[position] == owners) & (d != 0.0)):
                columns[i] += d[i] * block[position[i]]
        return out

    def destroy(self) -> None:
        destroy(*self.Phi, *self.MPhi)
        self.Phi, self.MPhi = [], []
        self.prefetched = {}


class _Prefetched:
    """One Krylov step of one constraint made by RitzSpace.prefetch: the Gram-Schmidt column (the
    coefficients on V[:, :q] and the norm), g^T A^-1 g (used on the first step), g^T v / ||v||_M, and
    the new vector's local rows and M times them (None: V was invariant)."""
    __slots__ = ("column", "gz", "h", "v", "Mv")

    def __init__(self, column, gz, h, v, Mv):
        self.column, self.gz, self.h, self.v, self.Mv = column, gz, h, v, Mv


def _columns(step, wanted: np.ndarray, which: int) -> np.ndarray:
    """The columns of a Krylov step (RitzSpace.sources: (constraints, V rows, M V rows)) for the
    constraints `wanted` (a subset of the step's, both ascending): a view when they are all."""
    have, block = step[0], step[which]
    if have.size == wanted.size:
        return block
    return np.asfortranarray(block[:, np.searchsorted(have, wanted)])


def _positions(have: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """The position of each of `wanted` in the ascending `have`, -1 where absent."""
    position = np.minimum(np.searchsorted(have, wanted), max(have.size - 1, 0))
    return np.where(have[position] == wanted, position, -1) if have.size else np.full(wanted.size, -1)


class _StepColumns:
    """The earlier Krylov steps' vectors of the constraints `act` (RitzSpace.sources: each constraint
    its own), for one step's classical Gram-Schmidt: local dot products and the subtraction, column by
    column in C (dbf_hpc/_romc/ritz_kernels.c, a column and its vectors in cache) or, without the
    extension, with numpy (the same arithmetic up to the order of the sums)."""

    def __init__(self, steps: list, act: np.ndarray):
        self.steps = steps
        if _kernels is not None:
            self.pos = np.array([np.searchsorted(step[0], act) for step in steps],
                                dtype=np.int_).reshape(len(steps), act.size)
        else:
            self.previous = [(_columns(step, act, 1), _columns(step, act, 2)) for step in steps]

    def dots(self, MPhi: np.ndarray, a: np.ndarray) -> np.ndarray:
        """The local M-inner products of a's columns with the modes and their own earlier vectors."""
        if _kernels is not None:
            return _kernels.ritz_columns_dots(MPhi, [step[2] for step in self.steps], self.pos, a)
        c = np.empty((MPhi.shape[0] + len(self.previous), a.shape[1]))
        c[:MPhi.shape[0]] = MPhi @ a
        for j, (_, Mv) in enumerate(self.previous):
            c[MPhi.shape[0] + j] = np.einsum("ij,ij->j", Mv, a)
        return c

    def subtract(self, Phi: np.ndarray, c: np.ndarray, a: np.ndarray) -> None:
        """a -= [Phi^T, own vectors] c in place."""
        if _kernels is not None:
            _kernels.ritz_columns_subtract(Phi, [step[1] for step in self.steps], self.pos, c, a)
        else:
            _subtract(a, Phi, c[:Phi.shape[0]], [v for v, _ in self.previous], c[Phi.shape[0]:])


def _check_sums(X, D, MX, MD, KX, KD, lam, k, gphi, gd, grow, ramp) -> np.ndarray:
    """The local sums of RitzSpace.sources' checks, 7 x columns: |r|^2, |phi|^2, phi^T M phi,
    ramp^T phi, |r_d|^2, |d|^2, |rhs|^2 with r = (K + k g g^T - lambda M) phi the eigen-residual and
    r_d = (K + k g g^T - lambda M) d - rhs, rhs = (g^T phi)^2 M phi - (g^T phi) g, the derivative
    equation's residual; grow: each constraint's local row of g, -1 when on another rank. In C when
    built (no temporaries), else numpy."""
    if _kernels is not None:
        return _kernels.ritz_columns_check_sums(X, D, MX, MD, KX, KD, lam, k, gphi, gd, grow, ramp)
    here = np.flatnonzero(grow >= 0)
    at_rows = grow[here]
    R = KX - lam * MX
    R[at_rows, here] += k[here] * gphi[here]
    rhs = gphi**2 * MX
    rhs[at_rows, here] -= gphi[here]
    RD = KD - lam * MD - rhs
    RD[at_rows, here] += k[here] * gd[here]
    return np.vstack([np.einsum("ij,ij->j", R, R), np.einsum("ij,ij->j", X, X), np.einsum("ij,ij->j", X, MX),
                      ramp @ X, np.einsum("ij,ij->j", RD, RD), np.einsum("ij,ij->j", D, D),
                      np.einsum("ij,ij->j", rhs, rhs)])


def _subtract(a: np.ndarray, Phi: np.ndarray, c: np.ndarray, vectors: list, d: np.ndarray) -> None:
    """a -= Phi^T c + sum_k vectors[k] * d[k] in place (a, vectors[k]: n_local x L column-major; Phi:
    N x n_local; c: N x L; d: len(vectors) x L): the Krylov part column by column (each a scaled
    vector of its own; a whole-block product would sweep memory three times). Zero coefficients
    are skipped."""
    if Phi.shape[0]:
        a -= Phi.T @ c
    columns = a.T                      # rows of the transpose: the columns, contiguous
    for v, dk in zip(vectors, d):
        vt = v.T
        for j in np.flatnonzero(dk):
            columns[j] -= dk[j] * vt[j]


def _reduced_stack(C: np.ndarray, S: np.ndarray, c: np.ndarray, q: int):
    """RitzSolver._reduced for a stack of constraints: nu (descending), W, and the residual rows."""
    T = C[:, :q, :q]
    s = S[:, :q]
    nu, W = np.linalg.eigh(0.5 * (T + T.transpose(0, 2, 1)) - c[:, None, None] * (s[:, :, None] * s[:, None, :]))
    nu, W = nu[:, ::-1], W[:, :, ::-1]
    beta_row = C[:, q, :q] - (c * S[:, q])[:, None] * s
    return nu, W, beta_row


def _closed_stack(C: np.ndarray, S: np.ndarray, c: np.ndarray, q: int, bound: float):
    """The closed stage of a stack of constraints: the projected (A^-1 - c z z^T) M on all of V[:, :q+1]
    without the solve that would give the newest vector v = V[:, q] its own column. A^-1 M v is known
    on V[:, :q] by symmetry (C[q, :q]); its coefficient on v itself, t, and what lies outside V are
    not. v lies in the M-complement of the lowest N modes, where A^-1 M has its spectrum in [0, bound]
    (bound >= 1 / (lambda_{N+1} - sigma): RitzSpace.tail_bound), so with t taken as bound / 2,
        || A^-1 M v - V T[:, q] ||_M <= bound / 2,
    and the residual of a pair (nu, V y) of T (that of the eigenproblem, and of the derivative's
    equation for d = V y') is y[q] times a vector of at most that norm (_closed_residual). z = V s lies
    in V already, so the rank-one part is exact. Returns nu (descending) and W, as _reduced_stack."""
    T = C[:, :q + 1, :q + 1].copy()
    T[:, :q, q] = T[:, q, :q]
    T[:, q, q] = 0.5 * bound
    s = S[:, :q + 1]
    nu, W = np.linalg.eigh(0.5 * (T + T.transpose(0, 2, 1)) - c[:, None, None] * (s[:, :, None] * s[:, None, :]))
    return nu[:, ::-1], W[:, :, ::-1]


def _closed_residual(bound: float, y: np.ndarray) -> np.ndarray:
    """The bound on a closed stage's residual for coefficient vectors y (the last axis: V's columns)."""
    return 0.5 * bound * np.abs(y[..., -1]) / CLOSED_FACTOR


def _at(a: np.ndarray, local, L: int) -> np.ndarray:
    """a[i_j, j] for the constraints j whose row i_j is on this rank, 0 elsewhere (length L)."""
    out = np.zeros(L)
    for j, i in local:
        out[j] = a[i, j]
    return out


def _mult_block(A: PETSc.Mat, a: np.ndarray) -> np.ndarray:
    """A a for a block of local rows a (columns: vectors), as numpy local rows: one MatMatMult of
    dense views of a and of the returned block (PETSc reuses a given dense product: no copy out).
    Collective."""
    n_local, L = a.shape
    if not L:
        return np.zeros_like(a)
    a = np.asfortranarray(a, dtype=float)
    out = np.empty((A.getLocalSize()[0], L), order="F")
    B = PETSc.Mat().createDense(((n_local, A.getSize()[1]), (PETSc.DECIDE, L)), array=a, comm=A.getComm())
    C = PETSc.Mat().createDense(((out.shape[0], A.getSize()[0]), (PETSc.DECIDE, L)), array=out, comm=A.getComm())
    try:
        B.assemble()
        C.assemble()
        A.matMult(B, C)     # into out: a dense product reuses the given matrix (no copy out)
        return out
    finally:
        destroy(B, C)


class RitzSolver:
    """The three solves of one constraint (dbf.FactorSolver's interface) by Rayleigh-Ritz on
    span{Phi, z_1..z_p} (module docstring), falling back to dbf_shared.SharedSolver. Owns its
    work vectors and the fallback solver; writes its Krylov vectors' local rows into the space's
    numpy blocks of V and M V (one BLAS call per Gram-Schmidt pass): one RitzSolver per space at a
    time.

    In the M-orthonormal basis V = [Phi, v_1, ..., v_p] (v_j: the Krylov vectors orthonormalized),
    z = A^-1 g = V s and A^-1 M V[:, :q] = V[:, :q+1] C[:q+1, :q] (the coefficients that
    Gram-Schmidt produces), so the shift-and-invert operators of the three problems,
        (A + k g g^T)^-1 M = A^-1 M - c_k z z^T M,   c_k = k / (1 + k g^T z)  (c = 1 / g^T z: pinned),
    are known on V[:, :q] with their residual on the next vector, without touching K."""

    def __init__(self, space: RitzSpace, row: int):
        self.space, self.ops, self.row = space, space.ops, row
        self.comm = space.comm
        n, width = len(space.Phi), len(space.Phi) + P_MAX + 1
        self.V, self.MV = space.V_local, space.MV_local    # the space's blocks: one solver at a time
        self.count, self.krylov = n, 0          # columns of V, Krylov vectors among them
        lo, hi = self.ops.M.getOwnershipRange()
        self.local_row = row - lo if lo <= row < hi else None
        self.h = np.zeros(width)                # g^T V
        if self.local_row is not None:
            self.h[:n] = self.V[:n, self.local_row]
        self.h[:n] = _sum(self.comm, self.h[:n])
        self.C = np.zeros((width, width))
        self.C[:n, :n] = space.T0
        self.s = np.zeros(width)
        self.gz = None
        self.exhausted = False
        self.fallback = None
        self.spring = None     # (k, lambda, y, y') of the last accepted spring-perturbed stage
        self.x, self.Mx = self.ops.M.createVecRight(), self.ops.M.createVecLeft()
        self.prefetched = space.prefetched.pop(row, [])
        counters["constraints"] += 1

    @property
    def size(self) -> int:
        """Columns of V[:, :q] on which the operators are known (the last vector only closes them,
        unless V is invariant)."""
        return self.count - 1 if self.krylov and not self.exhausted else self.count

    # -- the subspace -----------------------------------------------------------------------------

    def _extend(self) -> bool:
        """One solve: z = A^-1 g first, then A^-1 M v_p; the result orthonormalized into V. False when
        P_MAX is reached or V is invariant."""
        if self.exhausted or self.krylov >= P_MAX:
            return False
        if self.krylov < len(self.prefetched):
            return self._take(self.prefetched[self.krylov])
        x, Mx, q = self.x, self.Mx, self.count
        if self.krylov:
            Mx.array = self.MV[q - 1]
            self.space.factor.solve(Mx, x)
        else:
            g = unit_vector(x, self.row)
            try:
                self.space.factor.solve(g, x)
            finally:
                g.destroy()
        a = x.array
        gz = a[self.local_row] if self.local_row is not None else 0.0
        coefficients = np.zeros(q)
        for _ in range(2):     # classical Gram-Schmidt, twice, in the M inner product
            c = _sum(self.comm, self.MV[:q] @ a)
            a -= c @ self.V[:q]
            coefficients += c
        self.ops.M.mult(x, Mx)
        b = Mx.array_r
        norm2, gx = _sum(self.comm, np.array([a @ b, a[self.local_row] if self.local_row is not None else 0.0]))
        norm = np.sqrt(max(norm2, 0.0))
        before = np.hypot(np.linalg.norm(coefficients), norm)   # the M-norm before Gram-Schmidt
        column = np.append(coefficients, norm)
        if not self.krylov:
            gz = _sum(self.comm, np.array([gz]))[0]
        # every rank the same small problems: rank 0's numbers
        column, gz, gx = self.comm.bcast((column, gz, gx), root=0) if self.comm.size > 1 else (column, gz, gx)
        if not self.krylov:
            self.gz = gz             # g^T A^-1 g > 0 (A is SPD)
            self.s[:q + 1] = column
        else:
            self.C[:q + 1, q - 1] = column
        if not norm > BREAKDOWN * before:
            self.exhausted = True
            return False
        self.V[q], self.MV[q] = a / norm, b / norm
        self.h[q] = gx / norm
        self.count += 1
        self.krylov += 1
        counters["vectors"] += 1
        return True

    def _take(self, step: "_Prefetched") -> bool:
        """_extend with a vector made by RitzSpace.prefetch (the same numbers, no solve)."""
        q = self.count
        if not self.krylov:
            self.gz = step.gz
            self.s[:q + 1] = step.column
        else:
            self.C[:q + 1, q - 1] = step.column
        if step.v is None:
            self.exhausted = True
            return False
        self.V[q], self.MV[q], self.h[q] = step.v, step.Mv, step.h
        self.count += 1
        self.krylov += 1
        counters["vectors"] += 1
        return True

    def _vector(self, y: np.ndarray) -> PETSc.Vec:
        """V y (a new Vec)."""
        x = self.ops.M.createVecRight()
        x.array = y @ self.V[:y.size]
        return x

    def _converge(self, reduce):
        """Extend V until reduce() (the small problem on V[:, :q]: (eigenvalue, vectors, converged))
        converges; its value, or None (P_MAX reached). Collective."""
        if not self.krylov:
            self._extend()
        while True:
            result = reduce()
            if result[2]:
                return result
            if not self._extend():
                return result if self.exhausted else None   # an invariant V: the Ritz pair is exact

    def _to_fallback(self) -> SharedSolver:
        if self.fallback is None:
            counters["fallbacks"] += 1
            self.fallback = SharedSolver(self.space.factor, self.row)
        return self.fallback

    # -- the small problems -----------------------------------------------------------------------

    def _reduced(self, c: float, closed: bool = False):
        """The projected (A^-1 - c z z^T) M on V[:, :q]: its eigenvalues nu (descending) and vectors W,
        and the residual's coefficient on the next vector (a row applied to a coefficient vector).
        closed: on all of V, the newest vector's own coefficient bounded (_closed); the residual row
        is then None (the bound replaces it)."""
        if closed:
            nu, W = _closed_stack(self.C[None], self.s[None], np.array([c]), self.count - 1,
                                  self.space.tail_bound)
            return nu[0], W[0], None
        q = self.size
        T = self.C[:q, :q]
        s = self.s[:q]
        nu, W = np.linalg.eigh(0.5 * (T + T.T) - c * np.outer(s, s))
        nu, W = nu[::-1], W[:, ::-1]
        beta_row = self.C[q, :q] - c * self.s[q] * s   # A^-1 M V y's component on the next vector
        return nu, W, beta_row

    def _closable(self) -> bool:
        """Whether a stage may be tried on all of V with the newest vector closed by the bound (_closed)."""
        return CLOSED and self.space.tail_bound is not None and self.krylov > 0 and not self.exhausted

    def _pinned_reduced(self, branch: int):
        m = branch - 1
        for closed in (False, True) if self._closable() else (False,):
            nu, W, beta_row = self._reduced(1.0 / self.gz, closed)
            y = W[:, m]
            residual = _closed_residual(self.space.tail_bound, y) if closed else abs(beta_row @ y)
            converged = residual <= self.space.eigen_tol * abs(nu[m])
            if converged:
                break
        return self.space.sigma + 1.0 / nu[m], [y], converged

    def _spring_reduced(self, k: float, branch: int):
        check_amplification(k, self.gz, self.row)
        c = k / (1.0 + k * self.gz)
        dc = (1.0 / (1.0 + k * self.gz)) ** 2              # d c / dk (squared after the division: no overflow)
        m = branch - 1
        for closed in (False, True) if self._closable() else (False,):
            nu, W, beta_row = self._reduced(c, closed)
            y = W[:, m]
            s = self.s[:y.size]
            sy = s @ y
            # d/dk of (T - c s s^T) y = nu y:  (T_k - nu) y' = dc (s^T y) s - dnu y,  y^T y' = 0
            gaps = nu[m] - nu
            gaps[m] = 1.0
            coefficients = (W.T @ (-dc * sy * s)) / gaps
            coefficients[m] = 0.0
            dy = W @ coefficients
            if closed:    # both residuals lie along the newest vector's image (_closed)
                residual = _closed_residual(self.space.tail_bound, y)
                derivative_residual = _closed_residual(self.space.tail_bound, dy)
            else:
                residual = abs(beta_row @ y)
                # the derivative's residual on the next vector: (B_k y' + B_k' y) there, B_k' = -dc z z^T M
                derivative_residual = abs(beta_row @ dy - dc * self.s[y.size] * sy)
            converged = (residual <= self.space.eigen_tol * abs(nu[m])
                         and derivative_residual <= self.space.derivative_tol * abs(nu[m]) * np.linalg.norm(dy))
            if converged:
                break
        return self.space.sigma + 1.0 / nu[m], [y, dy], converged

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
                lam, (y, dy), _ = result
                phi = self._vector(y)
                if self._residual(k, lam, phi, y) < RESIDUAL_TOL:
                    normalize(phi, self.ops.M)   # the package's sign convention (y is M-normalized)
                    self.spring = (k, float(lam), y, dy)
                    return float(lam), phi
                phi.destroy()
        return self._to_fallback().eigenpair(k, branch)

    def derivative(self, k: float, lam: float, phi: PETSc.Vec) -> PETSc.Vec:
        """d phi/dk, the derivative of the Ritz vector (module docstring), sign-aligned with phi;
        checked by its backward error on the full operator. Collective."""
        if self.fallback is None and self.spring is not None and self.spring[:2] == (k, lam):
            _, _, y, dy = self.spring
            sign = 1.0 if float(_sum(self.comm, np.array([(y @ self.MV[:y.size]) @ phi.array_r]))[0]) >= 0 else -1.0
            d = self._vector(sign * dy)
            if self._derivative_backward_error(k, lam, phi, sign * y, d, sign * dy) < DERIVATIVE_BACKWARD_TOL:
                return d
            d.destroy()
        return self._to_fallback().derivative(k, lam, phi)

    # -- checks on the full operators -------------------------------------------------------------

    def _apply(self, k: float, lam: float, x: PETSc.Vec, y: np.ndarray) -> PETSc.Vec:
        """(K + k g g^T - lam M) x for x = V y (a new Vec; M x = (M V) y)."""
        r = self.ops.K.createVecLeft()
        self.ops.K.mult(x, r)
        a = r.array
        a -= lam * (y @ self.MV[:y.size])
        if self.local_row is not None:
            a[self.local_row] += k * (self.h[:y.size] @ y)
        return r

    def _norm_bound(self, k: float, lam: float) -> float:
        """||K||_F + k + |lam| ||M||_F >= ||K + k g g^T - lam M||_F."""
        return self.space.K_norm + abs(k) + abs(lam) * self.space.M_norm

    def _residual(self, k: float, lam: float, phi: PETSc.Vec, y: np.ndarray) -> float:
        """Normwise backward error of the eigenpair (lam, phi = V y) on the full operators."""
        r = self._apply(k, lam, phi, y)
        try:
            return r.norm() / (self._norm_bound(k, lam) * phi.norm())
        finally:
            r.destroy()

    def _derivative_backward_error(self, k: float, lam: float, phi: PETSc.Vec, y: np.ndarray, d: PETSc.Vec,
                                   dy: np.ndarray) -> float:
        """Normwise backward error of d = V dy in the derivative equation (dbf.derivative_system) for
        phi = V y, as on the factored path (with ||A||_F bounded by _norm_bound)."""
        r = self._apply(k, lam, d, dy)
        rhs = self.ops.M.createVecLeft()
        try:
            gphi = self.h[:y.size] @ y
            a = rhs.array
            a[:] = gphi**2 * (y @ self.MV[:y.size])
            if self.local_row is not None:
                a[self.local_row] -= gphi
            r.axpy(-1.0, rhs)
            return r.norm() / (self._norm_bound(k, lam) * d.norm() + rhs.norm())
        finally:
            destroy(r, rhs)

    def destroy(self) -> None:
        destroy(self.fallback, self.x, self.Mx)
        self.fallback = self.x = self.Mx = None


def reference_vectors(modes, group_ops: Operators, n_groups: int = 1) -> list:
    """The reference modes (a modes.ModalBasis on the world) as Vecs laid out like the group's K
    (copies, the caller's; n_groups as in enrichment.constraint_groups): each rank takes its
    group-local rows from the world BV by one scatter. Collective on the world."""
    bv, template = modes.vectors, group_ops.K.createVecRight()
    out = []
    try:
        if n_groups == 1:
            for i in range(modes.count):
                column = bv.getColumn(i)
                out.append(column.copy())
                bv.restoreColumn(i, column)
            return out
        lo, hi = template.getOwnershipRange()
        world = bv.getComm()
        column = bv.getColumn(0)
        mine = PETSc.Vec().createMPI((hi - lo, PETSc.DECIDE), comm=world)
        index = PETSc.IS().createStride(hi - lo, first=lo, step=1, comm=world)
        scatter = PETSc.Scatter().create(column, index, mine, None)
        bv.restoreColumn(0, column)
        try:
            for i in range(modes.count):
                column = bv.getColumn(i)
                scatter.scatter(column, mine, PETSc.InsertMode.INSERT_VALUES, PETSc.ScatterMode.FORWARD)
                bv.restoreColumn(i, column)
                out.append(template.duplicate())
                out[-1].array = mine.array_r
        finally:
            destroy(scatter, index, mine)
        return out
    except Exception:
        destroy(*out)
        raise
    finally:
        template.destroy()


def _sum(comm, local: np.ndarray) -> np.ndarray:
    """The sum over comm's ranks of a float64 array (a buffer reduction; none on one rank). Collective."""
    local = np.ascontiguousarray(local, dtype=float)
    if comm.size == 1:
        return local
    out = np.empty_like(local)
    comm.Allreduce(local, out)
    return out
