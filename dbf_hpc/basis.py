"""The reduced basis V = [phi_1..phi_N, psi_1..psi_NL] (DESIGN.md steps 1-5).

1. Reference modes on COMM_WORLD (modes.py).
2. One enrichment column per constraint, of the kind `enrichment` says:
   - "dbf" (the method): DBF sources (dbf.py) in parallel over constraints: COMM_WORLD is split into
     groups, each group gets its own copy of K and M and takes every groups-th constraint; the
     derivatives are gathered into one distributed matrix on COMM_WORLD.
   - "static": the static attachment mode psi_j = K^-1 g_j (g_j the unit vector at constraint row
     j; the static correction of industrial codes, e.g. code_aster's static modes), one Cholesky
     factorization of K (MUMPS, options prefix `static_`) on COMM_WORLD and one solve per
     constraint. K must be regular: a structure with rigid-body modes is an error.
   - "none": no column: V holds the reference modes only (the truncated modal model).
   "static" and "none" are there as comparators for accuracy studies: the industry's correction and
   plain modal truncation against the DBF, with everything else the same.
3. Gram-Schmidt in the M inner product (SLEPc BV with M as its matrix), distributed, against the
   modes and the earlier columns (Eqs. 18-19), M-normalization (Eq. 40), hat-omega_j (Eq. 41/20).
   A column that almost vanishes under orthogonalization is numerically dependent on the others: an
   error naming the constraints, never a silent bad basis.

The constraint rows are kept for every kind: B = V at the constraint rows is what the reduced
model needs, with or without enrichment columns. Everything here is collective on COMM_WORLD
(ops.comm).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from .dbf import STIFFNESS_RANGE, dbf_source
from .errors import InputError, SolverError
from .modes import ModalBasis, normalize, reference_modes
from .operators import Operators, direct_solver

# A DBF that keeps less than this fraction of its M-norm after Gram-Schmidt is numerically dependent
# on the others: the derivatives are accurate to ~1e-11 relative (measured: the same DBF computed on
# different rank layouts), so below 1e-9 the surviving part would be mostly round-off.
BREAKDOWN_TOL = 1e-9
# The kinds of enrichment columns (module docstring, step 2).
ENRICHMENTS = ("dbf", "static", "none")
COLUMN_NAMES = {"dbf": "DBF", "static": "static mode"}
STATIC_PREFIX = "static_"   # options of the static attachment solve: -static_ksp_..., -static_pc_...
STATIC_BACKWARD_TOL = 1e-10  # normwise backward error of K psi = g (a backward-stable solve gives ~1e-16)


@dataclass(frozen=True)
class BasisSettings:
    """What determines the basis besides the operators and the constraint rows."""

    modes: int | None = 6
    max_frequency_hz: float | None = None
    dbf_stiffness: object = "auto"      # "auto" or N/m (one for all constraints)
    dbf_derivative: str = "analytic"    # or "central"
    groups: int = 0                     # constraint groups; 0: min(ranks, constraints)
    enrichment: str = "dbf"             # "dbf" | "static" | "none" (module docstring, step 2)

    def key(self) -> dict:
        """The settings that change the basis (groups do not: same basis to round-off; the DBF
        stiffness and derivative only for enrichment = "dbf")."""
        key = {"modes": self.modes, "max_frequency_hz": self.max_frequency_hz, "enrichment": self.enrichment}
        if self.enrichment == "dbf":
            key.update(dbf_stiffness=self.dbf_stiffness, dbf_derivative=self.dbf_derivative)
        return key


@dataclass
class ReducedBasis:
    """M-orthonormal basis: N reference modes then one enrichment column per constraint (a DBF or a
    static mode; none for enrichment = "none"), as columns of a BV. The dbf_ arrays have one entry per
    enrichment column (empty for "none"); dbf_k, dbf_k_auto and dbf_branch are zero for "static"."""

    vectors: SLEPc.BV
    omega: np.ndarray            # reference modes, rad/s
    dbf_omega: np.ndarray        # hat-omega_j (Eq. 41) of each enrichment column, rad/s
    dbf_k: np.ndarray            # k_j used for each DBF, N/m
    dbf_branch: np.ndarray       # eigen-branch m followed for each DBF (1 = first mode)
    constraint_rows: np.ndarray
    dbf_k_auto: np.ndarray       # the transition stiffness of each constraint (N/m)
    settings: BasisSettings
    stats: dict = field(default_factory=dict)

    @property
    def mode_count(self) -> int:
        return self.omega.size

    @property
    def size(self) -> int:
        """The number of basis vectors (columns of V) actually present."""
        return self.vectors.getSizes()[1]

    @property
    def enrichment(self) -> str:
        return self.settings.enrichment

    @property
    def enrichment_count(self) -> int:
        """Columns after the reference modes: one per constraint, or none."""
        return self.size - self.mode_count

    def rows(self, rows) -> np.ndarray:
        """V restricted to the given rows (len(rows) x size), on every rank: B = G^T V for the
        constraint rows. Collective."""
        return bv_rows(self.vectors, rows)

    def project(self, A: PETSc.Mat) -> np.ndarray:
        """V^T A V as a dense array on every rank (K_r for A = K). Collective."""
        projected = self.vectors.matProject(A, self.vectors)
        values = projected.getDenseArray().copy()
        projected.destroy()
        return values

    def warnings(self, labels=None) -> list:
        """One line per DBF whose stiffness lies far outside the transition of Fig. 2 (none for
        the other kinds of enrichment)."""
        if self.enrichment != "dbf":
            return []
        labels = labels or [f"row {r}" for r in self.constraint_rows]
        out = []
        for j, (k, k_auto) in enumerate(zip(self.dbf_k, self.dbf_k_auto)):
            ratio = k / k_auto if k_auto > 0 else 1.0
            if ratio > STIFFNESS_RANGE or ratio < 1 / STIFFNESS_RANGE:
                state = ("practically pinned there: the DBF derives from the pinned mode"
                         if ratio > 1 else "practically unperturbed: the DBF derives from the free mode")
                out.append(f"DBF stiffness {k:.3g} N/m at {labels[j]} is {ratio:.0e} x the transition "
                           f"({k_auto:.3g} N/m) of Fig. 2, where the method takes k; the perturbed mode is "
                           f"{state}, not from the transition. Check the result against "
                           f"dbf_stiffness = \"auto\"")
        return out

    def destroy(self) -> None:
        self.vectors.destroy()


def constraint_groups(world_size: int, n_constraints: int, requested: int = 0) -> int:
    """How many groups solve constraints side by side: as requested, else one group per rank up to
    one per constraint (each group's share differs by at most one constraint)."""
    if requested:
        if requested > world_size:
            raise InputError(f"basis groups = {requested} exceeds the {world_size} MPI ranks")
        return requested
    return max(1, min(world_size, n_constraints))


def bv_rows(bv: SLEPc.BV, rows) -> np.ndarray:
    """The given rows of all columns of a distributed BV, (len(rows) x columns), on every rank.
    Collective."""
    rows = np.asarray(rows, dtype=np.int64)
    dense = bv.getMat()
    lo, hi = dense.getOwnershipRange()
    local = dense.getDenseArray()
    out = np.zeros((rows.size, local.shape[1]))
    mine = (rows >= lo) & (rows < hi)
    out[mine] = local[rows[mine] - lo, :]
    bv.restoreMat(dense)
    return bv.getComm().tompi4py().allreduce(out)


def participation(modes: ModalBasis, rows: np.ndarray) -> np.ndarray:
    """(g_j^T phi_i)^2 for every constraint j (rows) and reference mode i: (N_L, N). Collective."""
    return bv_rows(modes.vectors, rows) ** 2


def _dbf_sources(ops: Operators, rows: np.ndarray, modes: ModalBasis, settings: BasisSettings):
    """Derivatives of all constraints, computed by groups, gathered into an n x N_L dense Mat on
    ops.comm; also k_j and the branch of each. Collective."""
    world = ops.comm.tompi4py()
    n_groups = constraint_groups(world.size, rows.size, settings.groups)
    color = world.rank * n_groups // world.size
    if n_groups == 1:
        group, group_ops = None, ops
    else:
        group = world.Split(color, world.rank)
        sub = PETSc.Comm(group)
        group_ops = Operators(comm=sub, K=ops.K.getRedundantMatrix(n_groups, sub),
                              M=ops.M.getRedundantMatrix(n_groups, sub),
                              rigid_modes=ops.rigid_modes, eigen_scale=ops.eigen_scale)
    lam = modes.omega**2
    part = participation(modes, rows)
    n = ops.size
    gathered = PETSc.Mat().createDense(size=((ops.K.getLocalSize()[0], n), (PETSc.DECIDE, rows.size)),
                                       comm=ops.comm)
    gathered.setUp()
    k, k_auto = np.zeros(rows.size), np.zeros(rows.size)
    branch = np.zeros(rows.size, dtype=np.int64)
    is_leader = (group.rank if group is not None else world.rank) == 0
    for j in range(color, rows.size, n_groups):
        src = dbf_source(group_ops, int(rows[j]), lam, part[j], settings.dbf_stiffness, settings.dbf_derivative)
        lo, hi = src.derivative.getOwnershipRange()
        gathered.setValues(np.arange(lo, hi, dtype=PETSc.IntType), [j],
                           src.derivative.array_r.reshape(-1, 1))
        if is_leader:
            k[j], k_auto[j], branch[j] = src.stiffness, src.transition, src.branch
        src.derivative.destroy()
    gathered.assemble()
    if group is not None:
        group_ops.destroy()
        if hasattr(PETSc, "garbage_cleanup"):  # PETSc >= 3.18
            PETSc.garbage_cleanup(group_ops.comm)
        group.Free()
    return gathered, world.allreduce(k), world.allreduce(k_auto), world.allreduce(branch)


def _require_regular(ops: Operators) -> None:
    """An InputError unless K is regular, as static modes need."""
    if ops.rigid_modes:
        raise InputError(f"static attachment modes need a structure without rigid-body motion; this one has "
                         f"{ops.rigid_modes} rigid-body mode(s) (K is singular): add supports or use "
                         f"[basis] enrichment = \"dbf\"")


def static_modes(ops: Operators, rows: np.ndarray) -> PETSc.Mat:
    """The static attachment modes psi_j = K^-1 g_j of all constraints (the deflection under a unit
    load at row j), as the columns of an n x N_L dense Mat on ops.comm: one Cholesky factorization
    of K (MUMPS), one solve per constraint. K must be regular. Collective."""
    _require_regular(ops)
    ksp = direct_solver(PETSc.KSP().create(comm=ops.comm), PETSc.PC.Type.CHOLESKY)
    ksp.setOperators(ops.K)
    ksp.setOptionsPrefix(STATIC_PREFIX)
    ksp.setFromOptions()
    gathered = PETSc.Mat().createDense(size=((ops.K.getLocalSize()[0], ops.size), (PETSc.DECIDE, rows.size)),
                                       comm=ops.comm)
    gathered.setUp()
    K_norm = ops.K.norm(PETSc.NormType.FROBENIUS)
    g, psi, residual = ops.K.createVecLeft(), ops.K.createVecRight(), ops.K.createVecLeft()
    lo, hi = psi.getOwnershipRange()
    for j, row in enumerate(rows):
        g.set(0.0)
        if lo <= row < hi:
            g.setValue(int(row), 1.0)
        g.assemble()
        try:
            ksp.solve(g, psi)
            solved = ksp.getConvergedReason() >= 0
        except PETSc.Error:
            solved = False
        if solved:  # normwise backward error, as for the DBF derivative (||g|| = 1)
            ops.K.mult(psi, residual)
            residual.axpy(-1.0, g)
            solved = residual.norm() / (K_norm * psi.norm() + 1.0) < STATIC_BACKWARD_TOL
        if not solved:
            for obj in (ksp, g, psi, residual, gathered):
                obj.destroy()
            raise SolverError(f"the static mode of the constraint at row {row} failed (K psi = g not solved: "
                              f"K is singular or nearly so); support the structure or use [basis] "
                              f"enrichment = \"dbf\"")
        gathered.setValues(np.arange(lo, hi, dtype=PETSc.IntType), [j], psi.array_r.reshape(-1, 1))
    gathered.assemble()
    for obj in (ksp, g, psi, residual):
        obj.destroy()
    return gathered


def orthonormalize(V: SLEPc.BV, first: int, rows: np.ndarray, labels=None, name: str = "DBF") -> None:
    """Gram-Schmidt of columns first.. of V in V's inner product against all earlier columns, then
    normalization with the package's sign convention (Eqs. 18-19, 40). Columns before `first` must
    be orthonormal already; column first + j belongs to constraint j and is called a `name` in
    errors. Raises SolverError on breakdown, naming the constraints. Collective."""
    labels = labels or [f"row {r}" for r in rows]
    total = V.getActiveColumns()[1]
    M = V.getMatrix()[0]
    for c in range(first, total):
        j = c - first
        before = V.normColumn(c)
        if not before > 0:
            raise SolverError(f"the {name} of constraint {j + 1} ({labels[j]}) is zero; "
                              f"the constraint does not move the structure")
        V.setActiveColumns(0, c)
        col = V.createVec()
        V.copyVec(c, col)
        coefficients = np.abs(V.dotVec(col)) / before
        col.destroy()
        V.setActiveColumns(0, total)
        norm, _ = V.orthogonalizeColumn(c)
        if norm < BREAKDOWN_TOL * before:
            partners = [labels[i - first] for i in np.argsort(-coefficients)
                        if i >= first and coefficients[i] > 0.1][:3]
            survived = f"{norm / before:.1e} of it survives Gram-Schmidt"
            if partners:
                raise SolverError(f"basis breakdown: the {name} of the constraint at {labels[j]} is numerically "
                                  f"dependent on the {name}s of the constraints at {', '.join(partners)} "
                                  f"({survived}); constraints this close act as one: merge them or move them apart")
            raise SolverError(f"basis breakdown: the {name} of the constraint at {labels[j]} is numerically "
                              f"dependent on the {first} reference modes ({survived}); the modes already "
                              f"represent it: use fewer modes or a finer mesh")
        vec = V.getColumn(c)
        normalize(vec, M)
        V.restoreColumn(c, vec)


def build_basis(ops: Operators, rows, settings: BasisSettings = BasisSettings(), labels=None) -> ReducedBasis:
    """Reference modes and one enrichment column per constraint row (a DBF, a static mode, or none,
    as settings.enrichment says), M-orthonormalized. Collective on ops.comm."""
    kind = settings.enrichment
    if kind not in ENRICHMENTS:
        accepted = ", ".join(f'"{e}"' for e in ENRICHMENTS)
        raise InputError(f"basis enrichment must be one of {accepted}, got {kind!r}")
    rows = np.asarray(rows, dtype=np.int64)
    values, counts = np.unique(rows, return_counts=True)
    if np.any(counts > 1):
        raise InputError(f"two constraints act on the same DOF (row {values[counts > 1][0]}); "
                         f"remove the duplicate")
    if rows.size and (rows.min() < 0 or rows.max() >= ops.size):
        raise InputError(f"a constraint row is outside the structure's {ops.size} DOFs")
    if kind == "static":
        _require_regular(ops)  # before any eigen-solve
    t0 = time.perf_counter()
    modes = reference_modes(ops, count=settings.modes, max_frequency_hz=settings.max_frequency_hz)
    t1 = time.perf_counter()
    N = modes.count
    NL = 0 if kind == "none" else rows.size   # enrichment columns
    V = SLEPc.BV().create(comm=ops.comm)
    template = ops.K.createVecRight()
    V.setSizesFromVec(template, N + NL)
    V.setType(SLEPc.BV.Type.SVEC)
    V.setMatrix(ops.M, False)
    V.setOrthogonalization(SLEPc.BV.OrthogType.CGS, SLEPc.BV.OrthogRefineType.ALWAYS)
    for i in range(N):
        modes.vectors.copyVec(i, template)
        V.insertVec(i, template)
    omega = modes.omega.copy()
    k, k_auto, branch = np.zeros(NL), np.zeros(NL), np.zeros(NL, dtype=np.int64)
    if NL:
        if kind == "dbf":
            gathered, k, k_auto, branch = _dbf_sources(ops, rows, modes, settings)
        else:
            gathered = static_modes(ops, rows)
        for j in range(NL):
            gathered.getColumnVector(j, template)
            V.insertVec(N + j, template)
        gathered.destroy()
    modes.destroy()
    template.destroy()
    t2 = time.perf_counter()
    orthonormalize(V, N, rows, labels, COLUMN_NAMES.get(kind, "DBF"))
    basis = ReducedBasis(vectors=V, omega=omega, dbf_omega=np.zeros(NL), dbf_k=k, dbf_branch=branch,
                         constraint_rows=rows, dbf_k_auto=k_auto, settings=settings)
    Kr = basis.project(ops.K)
    basis.dbf_omega = np.sqrt(np.clip(np.diag(Kr)[N:], 0.0, None))
    # time_dbf: the enrichment columns, whatever their kind
    basis.stats = {"time_modes": t1 - t0, "time_dbf": t2 - t1, "time_orthogonalization": time.perf_counter() - t2}
    return basis
