"""The reduced basis of a gyroscopic structure, M u'' + (C + G) u' + K u = f + B^T N (issue 19;
Brake & Segalman 2011, Section 2, Eqs. 3-20). docs/design.md, "Gyroscopic structures", says why.

The paper works in state space, x = [u'; u] with A = [[M, 0], [0, K]] and B = [[G, K], [-K, 0]]
(Eqs. 4, 9, 10): a complex mode psi_j = psi_j^R + i psi_j^I (Eqs. 5-7) has the displacement part
phi_j = phi_j^R + i phi_j^I and the velocity part i omega_j phi_j, so both halves of the state are
spanned by the REAL displacement vectors phi_j^R, phi_j^I. The basis here is that real span, used in
the second-order form the rest of the package integrates:

    V = [Re phi_1, Im phi_1, ..., Re phi_N, Im phi_N, Re d_1, Im d_1, ..., Re d_NL, Im d_NL]

M-orthonormalized, and the reduced model M_r q'' + (C_r + G_r) q' + K_r q = ... with G_r = V^T G V
skew (rom.py, rom_integrator.py; 2 r real states for r columns). The free vibration in a mode,
u = Re(phi_j e^(i omega_j t)), stays in span V, so the Galerkin residual of a mode is zero: the
reduced model reproduces the N complex modes exactly (and adds N further ones).

- Reference modes: gyroscopic.gyroscopic_modes (SLEPc PEP), x^H M x = 1.
- DBF of constraint j (Eqs. 13-17): the first complex mode that moves at the constraint of the
  spring-perturbed problem (lambda^2 M + lambda G + K + k g g^T) x = 0 (Eq. 13), and its derivative
  in k by the paper's central difference, each end turned to the phase of x(k) (x(k)^H M x(k +- hk)
  real, the complex form of sign alignment). Its displacement part d = phi_{j,k} (Eq. 17; the
  varpi_{,k} terms are dropped as in the paper) gives the two real columns Re d, Im d. A stiffness
  "auto" is the corner of Fig. 2 in omega^2 (dbf.py), with the gyroscopic first-order slope
  d omega/dk = |g^T x|^2 / (2 omega + gamma), gamma = -i x^H G x = 2 (Re x)^T G (Im x); with G = 0
  it is the non-gyroscopic (mu - omega^2) / (g^T phi)^2.
- Gram-Schmidt (Eqs. 18-19) in the M inner product, not the A inner product of the state vectors:
  the real displacement columns are what the second-order model integrates, and for them the M
  product is the natural one (docs/design.md). A column whose M-norm is below DROP_TOL of its
  complex vector's (the imaginary part of a mode at G = 0) is left out, as is a mode column that
  Gram-Schmidt leaves almost nothing of; a DBF of which neither part survives is a breakdown error
  as in basis.py.
- hat-omega (Eq. 20): the positive root of the gyroscopic Rayleigh quotient of the DBF's complex
  vector z = Re d + i Im d, each part projected out of the modes and the earlier DBFs only (the
  complex Gram-Schmidt of Eq. 18): omega^2 (z^H M z) + omega gamma - z^H K z = 0, gamma = -i z^H G z.
  It is omega_j for an exact mode (x^H P(i omega) x = 0) and sqrt(K_r,jj) (Eq. 41) at G = 0.

The derivative is always the central difference (dbf_derivative and dbf_solver are not used: the
gyroscopic problem has one PEP solve per k); constraints are solved in groups side by side (all_dbfs).
Four PEP solves per constraint (pinned, k, k (1 +- h)), each with its own MUMPS LU (options prefix
`dbf_`: -dbf_pep_..., -dbf_st_...). Cached (cache.py: the key holds U, m_t, T or G's bytes through the
operators' fingerprint; a cached basis must still hold the complex modes' frequencies). Collective on ops.comm.
"""
from __future__ import annotations

import time

import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from .accuracy import exact_flexibility
from .basis import BREAKDOWN_TOL, BasisSettings, ReducedBasis, _basis_vectors, _check_rows
from .dbf import CENTRAL_STEP, branch_of, cluster_of, with_spring
from .enrichment import static_modes
from .errors import InputError, SolverError
from .gyroscopic import critical_speed_note, gyroscopic_modes
from .modes import counters, normalize
from .operators import Operators
from .petsctools import destroy, values_at

# A real column below this fraction of its complex vector's M-norm is left out: the imaginary part
# of a mode or DBF at G = 0 is round-off (~1e-12 measured), and a physical part this small changes
# the response by less than the integrator's tolerance.
DROP_TOL = 1e-6
PREFIX = "dbf_"


# A spring above this multiple of K's diagonal entry at its row is refused (_spring_mode): the PEP with it
# loses its digits, far inside the pinned limit (dbf-hpc stiffness shows the whole curve below it).
SPRING_RATIO_MAX = 1e4


def stable_modes(ops: Operators, count: int | None = None, max_frequency_hz: float | None = None, prefix="modes_",
                 problem: str | None = None, whole: str | None = None):
    """gyroscopic_modes (`whole`: a count ending inside a repeated frequency, as there), or an
    InputError naming the first unstable mode (a basis of growing modes has no meaning): of the
    structure, or of the `problem` (words: a spring-perturbed or pinned one, which the axial speed is
    not to blame for). Collective."""
    counters["eigen_solves"] += 1
    modes = gyroscopic_modes(ops, count=count, max_frequency_hz=max_frequency_hz, prefix=prefix, whole=whole)
    if modes.unstable:
        j = modes.unstable[0]
        text = modes.describe(j)
        modes.destroy()
        if problem is not None:
            raise InputError(problem.format(text))
        raise InputError(f"the reduced basis of a gyroscopic structure needs stable modes: {text}; lower the axial "
                         f"speed below the critical speed{critical_speed_note(ops)}")
    return modes


def _mdot(M: PETSc.Mat, a: PETSc.Vec, b: PETSc.Vec) -> float:
    """a^T M b. Collective."""
    Mb = M.createVecLeft()
    M.mult(b, Mb)
    value = a.dot(Mb)
    Mb.destroy()
    return value


def _spring_mode(ops: Operators, row: int, k: float, branch: int):
    """(lambda, x_R, x_I): mode `branch` of (lambda^2 M + lambda G + K + k g g^T) x = 0 (Eq. 13),
    x^H M x = 1 (new Vecs, the caller's). Collective."""
    diagonal = ops.K.getDiagonal()
    own = abs(float(values_at(diagonal, [row])[0]))
    diagonal.destroy()
    # red team: --k 1e20 on the pipe at half its critical speed gave 547 rad/s (pinned: 438) in one process and a
    # 'flutter' blamed on the axial speed in another; 1e16 (3e6 x K_rr) was 2.6e-5 off, 1e12 (300 x) exact
    if own > 0 and k > SPRING_RATIO_MAX * own:
        raise InputError(f"a spring of k = {k:.3g} N/m at row {row} is {k / own:.1e} x K's own entry there "
                         f"({own:.3g}): above {SPRING_RATIO_MAX:g} x, the gyroscopic eigenproblem with the spring "
                         f"(Eq. 13) loses its digits to round-off, and the pinned limit is reached long before; give "
                         f"a smaller k ([basis] dbf_stiffness, or --k)")
    problem = (f"the structure with a spring of k = {k:.3g} N/m at row {row} (Eq. 13): {{}}; a spring destabilizes "
               f"only a structure that G alone holds (K not positive definite): give another k ([basis] "
               f"dbf_stiffness, or --k)")
    A = with_spring(ops.K, row, k)
    try:
        spring = Operators(comm=ops.comm, K=A, M=ops.M, G=ops.G)
        modes = stable_modes(spring, count=branch, prefix=PREFIX, problem=problem)
    finally:
        A.destroy()
    lam, xr, xi = modes.eigenvalues[branch - 1], modes.real[branch - 1], modes.imag[branch - 1]
    destroy(*modes.real[:branch - 1], *modes.imag[:branch - 1])
    return lam, xr, xi


def _pinned_frequency(ops: Operators, row: int, branch: int) -> float:
    """varpi_m with the constraint DOF fixed (k -> infinity), rad/s. Collective."""
    lo, hi = ops.K.getOwnershipRange()
    keep = np.arange(lo, hi, dtype=PETSc.IntType)
    index = PETSc.IS().createGeneral(keep[keep != row], comm=ops.comm)
    pinned = Operators(comm=ops.comm, K=ops.K.createSubMatrix(index, index), M=ops.M.createSubMatrix(index, index),
                       G=ops.G.createSubMatrix(index, index))
    try:
        modes = stable_modes(pinned, count=branch, prefix=PREFIX,
                             problem=f"the structure with the constraint DOF at row {row} pinned (k -> infinity, the "
                                     f"end of Fig. 2 and of the auto stiffness): {{}}; give [basis] dbf_stiffness as "
                                     f"a number")
        omega = float(modes.omega[branch - 1])
        modes.destroy()
    finally:
        pinned.destroy()
        index.destroy()
    return omega


def _align(M: PETSc.Mat, ref: tuple, x: tuple) -> None:
    """Turn the phase of x = (x_R, x_I) so that ref^H M x is real and positive. Collective."""
    a, b = ref
    c, d = x
    inner = complex(_mdot(M, a, c) + _mdot(M, b, d), _mdot(M, a, d) - _mdot(M, b, c))
    rot = np.conj(inner) / abs(inner)
    zr, zi = c.copy(), d.copy()
    c.scale(rot.real)
    c.axpy(-rot.imag, zi)
    d.scale(rot.real)
    d.axpy(rot.imag, zr)
    destroy(zr, zi)


def gyroscopic_slope(ops: Operators, row: int, omega: float, xr: PETSc.Vec, xi: PETSc.Vec) -> float:
    """d omega/dk at k = 0 of a mode x = x_R + i x_I (x^H M x = 1) under k g g^T: |g^T x|^2 / (2 omega +
    gamma), gamma = 2 x_R^T G x_I: first-order perturbation of (lambda^2 M + lambda G + K) x = 0, where
    x is its own left eigenvector (x^H P(i omega) = 0: P(i omega) is Hermitian for a skew G), so
    d lambda/dk = -|g^T x|^2 / (x^H (2 lambda M + G) x). Collective."""
    g = values_at(xr, [row])[0] ** 2 + values_at(xi, [row])[0] ** 2
    Gx = ops.G.createVecLeft()
    ops.G.mult(xi, Gx)
    gamma = 2 * xr.dot(Gx)
    Gx.destroy()
    return g / (2 * omega + gamma)


def cluster_slope(ops: Operators, row: int, omega: float, xr: list, xi: list) -> float:
    """d omega/dk at k = 0 of the branch a spring k g g^T moves out of a repeated frequency omega
    (modes x_j = x_R + i x_I, j in the cluster; one mode: gyroscopic_slope). In the cluster's span the
    first-order problem is rank one, (X^H g)(X^H g)^H v = s H v with H = X^H (2 i omega M + G) X / i
    (Hermitian), so s = (X^H g)^H H^-1 (X^H g), whatever mix of the pair the eigensolver returned
    (red team: a tube of two planes took one mix's |g^T x|^2, and the y and z rows of a support got k
    of 1.2e7 and 2.7e5 N/m). Collective."""
    c = len(xr)
    if c == 1:
        return gyroscopic_slope(ops, row, omega, xr[0], xi[0])
    gx = np.array([values_at(a, [row])[0] + 1j * values_at(b, [row])[0] for a, b in zip(xr, xi)])
    Mr, Mi, Gr, Gi = ([v.duplicate() for v in xr] for _ in range(4))
    try:
        for j in range(c):
            ops.M.mult(xr[j], Mr[j])
            ops.M.mult(xi[j], Mi[j])
            ops.G.mult(xr[j], Gr[j])
            ops.G.mult(xi[j], Gi[j])
        H = np.zeros((c, c), dtype=complex)
        for i in range(c):
            for j in range(c):
                # x_i^H A x_j = (r_i^T A r_j + s_i^T A s_j) + i (r_i^T A s_j - s_i^T A r_j), x = r + i s
                m = complex(xr[i].dot(Mr[j]) + xi[i].dot(Mi[j]), xr[i].dot(Mi[j]) - xi[i].dot(Mr[j]))
                g = complex(xr[i].dot(Gr[j]) + xi[i].dot(Gi[j]), xr[i].dot(Gi[j]) - xi[i].dot(Gr[j]))
                H[i, j] = 2 * omega * m - 1j * g
    finally:
        destroy(*Mr, *Mi, *Gr, *Gi)
    H = 0.5 * (H + H.conj().T)
    a = gx.conj()   # X^H g (g real)
    return float(np.real(a.conj() @ np.linalg.solve(H, a)))


def transition(ops: Operators, row: int, modes) -> tuple:
    """(branch, omega_m, varpi_m, k_auto) of the constraint at `row`: the eigen-branch followed (the
    lowest mode that moves there, dbf.branch_of), its frequency without and with the DOF pinned, and
    the corner of Fig. 2 in omega^2 (module docstring). Collective."""
    branch, omega, slope = _branch_slope(ops, row, modes)
    # omega^2 rises by 2 omega slope k at first order; the corner of Fig. 2 in omega^2 (dbf.py)
    pinned = _pinned_frequency(ops, row, branch)
    return branch, omega, pinned, _corner(omega, pinned, slope)


def _corner(omega: float, pinned: float, slope: float) -> float:
    """The auto stiffness, or 0 (no transition) for a branch that does not stiffen (slope <= 0)."""
    return max(pinned**2 - omega**2, 0.0) / (2 * omega * slope) if slope > 0 else 0.0


def _auto_stiffness(ops: Operators, row: int, branch: int, omega: float, slope: float, stiffness) -> float:
    """k_auto, the corner of Fig. 2. When the DBF `stiffness` is a number, k_auto only serves its
    warning (far from the transition) and is 0 (none) where there is no transition: a branch that does
    not stiffen under a spring, or a structure that pinning the DOF makes unstable (a mode only G held;
    red team: a number was refused with the advice to give one). Collective."""
    if stiffness == "auto":
        return _corner(omega, _pinned_frequency(ops, row, branch), slope)
    if not slope > 0:
        return 0.0
    try:
        pinned = _pinned_frequency(ops, row, branch)
    except InputError:   # every rank: the same eigenvalues
        return 0.0
    return _corner(omega, pinned, slope)


def _branch_slope(ops: Operators, row: int, modes, stiffness="auto") -> tuple:
    """(branch, omega_m, d omega/dk) of the constraint at `row` from the reference modes; a branch that
    does not stiffen under a spring (a mode that only G holds: K is not positive definite there) has no
    auto stiffness, an error only when `stiffness` is "auto". Collective."""
    lam = modes.omega ** 2
    part = np.array([values_at(a, [row])[0] ** 2 + values_at(b, [row])[0] ** 2
                     for a, b in zip(modes.real, modes.imag)])
    branch = branch_of(part, lam)
    if branch == 0:
        raise SolverError(f"the constraint at row {row} does not move in any of the {part.size} reference modes; "
                          f"add modes or move the constraint")
    cluster = cluster_of(part, lam)
    omega = modes.omega[branch - 1]
    slope = cluster_slope(ops, row, omega, [modes.real[i] for i in cluster], [modes.imag[i] for i in cluster])
    if not slope > 0 and stiffness == "auto":   # red team: a number was refused with the same advice
        raise SolverError(f"the gyroscopic DBF at row {row}: mode {branch} does not stiffen under a spring "
                          f"(d omega/dk = {slope:.3g}); give [basis] dbf_stiffness as a number")
    return branch, float(omega), float(slope)


def stiffness_sweep(ops: Operators, row: int, stiffnesses, branch: int = 1) -> np.ndarray:
    """varpi_m(k) (rad/s) of the spring-perturbed gyroscopic problem over a list of k (the paper's
    Fig. 2). Collective."""
    out = []
    for k in stiffnesses:
        lam, xr, xi = _spring_mode(ops, row, float(k), branch)
        destroy(xr, xi)
        out.append(lam.imag)
    return np.array(out)


def dbf_columns(ops: Operators, row: int, modes, stiffness="auto"):
    """(Re d, Im d, k, k_auto, branch) of the constraint at `row`: d the central difference in k of the
    spring-perturbed complex mode (module docstring). Collective."""
    return _dbf_state(ops, row, modes, stiffness)[:5]


def _dbf_state(ops: Operators, row: int, modes, stiffness="auto", reference=None):
    """dbf_columns and varpi_j(k), the spring-perturbed mode's frequency (rad/s), which the state-space
    DBF [i varpi d; d] (Eq. 17, state_space.py) needs. `reference`: (branch, omega, slope) from
    _branch_slope, when the modes live on another communicator (groups; modes is then unused).
    Collective on ops.comm."""
    branch, omega, slope = _branch_slope(ops, row, modes, stiffness) if reference is None else reference
    k_auto = _auto_stiffness(ops, row, branch, omega, slope, stiffness)
    k = k_auto if stiffness == "auto" else float(stiffness)
    h = CENTRAL_STEP
    vecs = []
    try:
        lam, xr, xi = _spring_mode(ops, row, k, branch)
        vecs += [xr, xi]
        ends = []
        for factor in (1 + h, 1 - h):
            _, cr, ci = _spring_mode(ops, row, k * factor, branch)
            vecs += [cr, ci]
            _align(ops.M, (xr, xi), (cr, ci))
            ends.append((cr, ci))
        dr, di = ends[0][0].copy(), ends[0][1].copy()
        dr.axpy(-1.0, ends[1][0])
        di.axpy(-1.0, ends[1][1])
        dr.scale(1.0 / (2 * h * k))
        di.scale(1.0 / (2 * h * k))
    finally:
        destroy(*vecs)
    return dr, di, k, k_auto, branch, float(lam.imag)


def all_dbfs(ops: Operators, rows: np.ndarray, modes, stiffness="auto", groups: int = 0) -> list:
    """(Re d, Im d, k, k_auto, branch, varpi) of every constraint (d, varpi as in _dbf_state; the Vecs
    on ops.comm, the caller's). The constraints are solved by groups side by side as the real DBFs
    (enrichment.py): COMM_WORLD split into `groups` (0: one per rank, at most one per constraint),
    each with its own copy of K, M, G taking every groups-th constraint (four PEP solves each); the
    branch, omega and slope come from the reference modes on ops.comm first. Collective."""
    from .enrichment import (_dense_columns, _free_group, _group_operators, constraint_groups, group_failure,
                             raise_agreed)

    world = ops.comm.tompi4py()
    NL = rows.size
    n_groups = constraint_groups(world.size, NL, groups) if NL else 1
    if n_groups == 1:
        return [_dbf_state(ops, int(r), modes, stiffness) for r in rows]
    reference = [_branch_slope(ops, int(r), modes, stiffness) for r in rows]
    color = world.rank * n_groups // world.size
    group, group_ops = _group_operators(ops, n_groups)
    group_ops.G = ops.G.getRedundantMatrix(n_groups, group_ops.comm)
    gathered = _dense_columns(ops, 2 * NL)
    scalars = np.zeros((NL, 4))   # k, k_auto, branch, varpi
    failure = mine = None
    try:
        try:
            for j in range(color, NL, n_groups):
                dr, di, k, k_auto, branch, varpi = _dbf_state(group_ops, int(rows[j]), None, stiffness, reference[j])
                lo, hi = dr.getOwnershipRange()
                index = np.arange(lo, hi, dtype=PETSc.IntType)
                gathered.setValues(index, [2 * j], dr.array_r.reshape(-1, 1))
                gathered.setValues(index, [2 * j + 1], di.array_r.reshape(-1, 1))
                destroy(dr, di)
                if group.rank == 0:
                    scalars[j] = k, k_auto, branch, varpi
        except Exception as e:   # whatever ends one group: every rank hears of it (enrichment.raise_agreed)
            failure, mine = group_failure(e, world, "modes_"), e
        raise_agreed(world, failure, mine)
        gathered.assemble()
    except Exception:
        gathered.destroy()
        raise
    finally:
        _free_group(group, group_ops)   # destroys the group's K, M and G
    scalars = world.allreduce(scalars)
    out = []
    try:
        for j in range(NL):
            dr, di = ops.K.createVecRight(), ops.K.createVecRight()
            gathered.getColumnVector(2 * j, dr)
            gathered.getColumnVector(2 * j + 1, di)
            k, k_auto, branch, varpi = scalars[j]
            out.append((dr, di, float(k), float(k_auto), int(branch), float(varpi)))
    finally:
        gathered.destroy()
    return out


def hat_omega(K_r: np.ndarray, G_r: np.ndarray, re: np.ndarray, im: np.ndarray) -> float:
    """Eq. 20 for the complex vector z = re + i im (coordinates on the basis): the positive root of
    omega^2 (z^H M_r z) + omega gamma - z^H K_r z = 0, gamma = -i z^H G_r z = 2 re^T G_r im (M_r = I),
    rad/s. For an exact complex mode it is its frequency (z^H P(i omega) z = 0)."""
    m = re @ re + im @ im
    kappa = re @ K_r @ re + im @ K_r @ im
    gamma = 2 * re @ G_r @ im
    return float((-gamma + np.sqrt(max(gamma**2 + 4 * m * kappa, 0.0))) / (2 * m))


class _Builder:
    """Gram-Schmidt in M with columns left out (module docstring): candidates are added one at a
    time; kept ones are M-orthonormal columns 0..kept-1 of a working BV. Collective."""

    def __init__(self, ops: Operators, capacity: int):
        self.ops, self.V, self.kept = ops, _basis_vectors(ops, max(capacity, 1)), 0
        self.seconds = 0.0   # spent in Gram-Schmidt

    def add(self, vec: PETSc.Vec, scale: float) -> bool:
        """Orthonormalize vec against the kept columns; True if kept. `scale`: the M-norm of its
        complex vector."""
        start = time.perf_counter()
        try:
            before = np.sqrt(max(_mdot(self.ops.M, vec, vec), 0.0))
            if not before > DROP_TOL * scale:
                return False
            V, c = self.V, self.kept
            V.insertVec(c, vec)
            norm, _ = V.orthogonalizeColumn(c)
            if norm < BREAKDOWN_TOL * before:
                return False
            col = V.getColumn(c)
            normalize(col, self.ops.M)
            V.restoreColumn(c, col)
            self.kept += 1
            return True
        finally:
            self.seconds += time.perf_counter() - start

    def coordinates(self, vec: PETSc.Vec) -> np.ndarray:
        """The M-products of vec with the kept columns (its coordinates where vec lies in their
        span). Collective."""
        self.V.setActiveColumns(0, self.kept)
        out = np.array(self.V.dotVec(vec))
        self.V.setActiveColumns(0, self.V.getSizes()[1])
        return out

    def finish(self) -> SLEPc.BV:
        out = _basis_vectors(self.ops, self.kept)
        template = self.ops.K.createVecRight()
        for j in range(self.kept):
            self.V.copyVec(j, template)
            out.insertVec(j, template)
        template.destroy()
        self.V.destroy()
        return out


def _add_modes(builder: _Builder, ops: Operators, modes) -> list:
    """Re and Im of each mode; the frequency of each kept column."""
    omega = []
    for j in range(modes.count):
        for part in (modes.real[j], modes.imag[j]):
            if builder.add(part, 1.0):
                omega.append(modes.omega[j])
    return omega


def build_gyroscopic_basis(ops: Operators, rows, settings: BasisSettings = BasisSettings(), labels=None,
                           whole: str = "refuse") -> ReducedBasis:
    """The reduced basis of a gyroscopic structure (module docstring): Re/Im of the complex modes and
    of one complex DBF per constraint ("dbf"), or one static mode K^-1 g ("static"), or none. `whole`:
    settings.modes ending inside a repeated frequency is refused or extended (basis.build_basis).
    Collective on ops.comm."""
    strategy = settings.strategy
    rows = np.asarray(rows, dtype=np.int64)
    _check_rows(ops, rows)
    strategy.check(ops)
    labels = labels or [f"row {r}" for r in rows]
    t0 = time.perf_counter()
    modes = stable_modes(ops, count=settings.modes, max_frequency_hz=settings.max_frequency_hz, whole=whole)
    t1 = time.perf_counter()
    NL = rows.size if strategy.kind != "none" else 0
    builder = _Builder(ops, 2 * modes.count + 2 * NL)
    k, k_auto, branch = np.zeros(NL), np.zeros(NL), np.zeros(NL, dtype=np.int64)
    groups, static, dbfs = [], None, []
    try:
        omega = _add_modes(builder, ops, modes)
        N = builder.kept
        if strategy.kind == "static" and NL:
            static = static_modes(ops, rows)
        dbfs = all_dbfs(ops, rows, modes, strategy.stiffness, settings.groups) if strategy.kind == "dbf" else []
        for j in range(NL):
            if strategy.kind == "dbf":
                dr, di, k[j], k_auto[j], branch[j], _ = dbfs[j]
                dbfs[j] = None
                parts = [dr, di]
            else:
                parts = [ops.K.createVecRight()]
                static.getColumnVector(j, parts[0])
            try:
                scale = np.sqrt(sum(_mdot(ops.M, p, p) for p in parts))
                first = builder.kept
                for p in parts:
                    builder.add(p, scale)
                # z = Re d + i Im d, each projected out of the earlier columns only (the complex
                # Gram-Schmidt of Eq. 18): its coordinates on this constraint's new columns
                z = [builder.coordinates(p)[first:] for p in parts] if builder.kept > first else []
            finally:
                destroy(*parts)
            if builder.kept == first:
                raise SolverError(f"basis breakdown: the {strategy.column_name} of the constraint at {labels[j]} is "
                                  f"numerically dependent on the reference modes and the earlier columns; use fewer "
                                  f"modes, a finer mesh, or merge constraints this close")
            groups.append((first, z))
        t2 = time.perf_counter()
        V = builder.finish()
    except Exception:
        builder.V.destroy()
        raise
    finally:
        destroy(static, *[v for d in dbfs if d is not None for v in d[:2]])
        n_complex, complex_omega = modes.count, [float(w) for w in modes.omega[:modes.count]]
        modes.destroy()
    basis = ReducedBasis(vectors=V, omega=np.array(omega), enrichment_omega=np.zeros(V.getSizes()[1] - N), dbf_k=k,
                         dbf_branch=branch, constraint_rows=rows, dbf_k_auto=k_auto, settings=settings)
    K_r, G_r = basis.project(ops.K), basis.project(ops.G)
    for first, z in groups:
        cols = slice(first, first + z[0].size)
        value = hat_omega(K_r[cols, cols], G_r[cols, cols], z[0], z[1] if len(z) > 1 else np.zeros(z[0].size))
        basis.enrichment_omega[cols.start - N:cols.stop - N] = value
    t3 = time.perf_counter()
    basis.set_flexibility(exact_flexibility(ops, rows), K_r)
    # Gram-Schmidt runs column by column between the DBF solves: its time is taken out of theirs
    basis.stats = {"time_modes": t1 - t0, "time_enrichment": t2 - t1 - builder.seconds,
                   "time_orthogonalization": builder.seconds + t3 - t2,
                   # the complex modes solved (np.unique of the columns' frequencies counted a pair of
                   # bit-equal frequencies, a round shaft at rest, once: the estimate's richer model had fewer)
                   "time_flexibility": time.perf_counter() - t3, "complex_modes": n_complex,
                   # each complex mode's frequency (rad/s) once: basis.omega has one per kept column, Re and Im
                   # of a mode, or Re alone where Im is dependent (a mode at rest): `dbf-hpc basis` prints these
                   "complex_omega": complex_omega,
                   "constraint_columns": [z[0].size for _, z in groups]}
    return basis


def richer_gyroscopic_basis(ops: Operators, basis: ReducedBasis, modes: int) -> ReducedBasis:
    """The complex modes 1..`modes` (more where `modes` ends inside a repeated frequency, up to its end)
    and basis's own enrichment columns, M-orthonormalized (what basis.richer_basis is for the error
    estimate). Collective."""
    from dataclasses import replace

    more = stable_modes(ops, count=modes, whole="extend")
    modes = more.count
    complex_omega = [float(w) for w in more.omega[:modes]]
    first = basis.mode_count
    builder = _Builder(ops, 2 * modes + basis.enrichment_count)
    template = ops.K.createVecRight()
    try:
        omega = _add_modes(builder, ops, more)
        for j in range(basis.enrichment_count):
            basis.vectors.copyVec(first + j, template)
            if not builder.add(template, 1.0):
                raise SolverError("no richer basis: an enrichment column is held by the richer modes")
        V = builder.finish()
    except Exception:
        builder.V.destroy()
        raise
    finally:
        destroy(more, template)
    settings = replace(basis.settings, modes=modes, max_frequency_hz=None)
    # what a gyroscopic basis carries (build_gyroscopic_basis), so that the cache can keep it (cache.obtain_richer)
    stats = {"cache": "off", "complex_modes": modes, "complex_omega": complex_omega,
             "constraint_columns": list(basis.stats["constraint_columns"])}
    rich = ReducedBasis(vectors=V, omega=np.array(omega), enrichment_omega=basis.enrichment_omega.copy(),
                        dbf_k=basis.dbf_k, dbf_branch=basis.dbf_branch, constraint_rows=basis.constraint_rows,
                        dbf_k_auto=basis.dbf_k_auto, settings=settings, stats=stats)
    rich.set_flexibility(basis.flexibility_exact, rich.project(ops.K))
    return rich
