"""The reduced basis V = [phi_1..phi_N, psi_1..psi_NL] (DESIGN.md steps 1-5).

1. Reference modes on COMM_WORLD (modes.py).
2. DBF sources (dbf.py) in parallel over constraints: COMM_WORLD is split into groups, each group
   gets its own copy of K and M and takes every groups-th constraint; the derivatives are gathered
   into one distributed matrix on COMM_WORLD.
3. Gram-Schmidt in the M inner product (SLEPc BV with M as its matrix), distributed, against the
   modes and the earlier DBFs (Eqs. 18-19), M-normalization (Eq. 40), hat-omega_j (Eq. 41/20).
   A DBF that almost vanishes under orthogonalization is numerically dependent on the others: an
   error naming the constraints, never a silent bad basis.

Everything here is collective on COMM_WORLD (ops.comm).
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
from .operators import Operators

# A DBF that keeps less than this fraction of its M-norm after Gram-Schmidt is numerically dependent
# on the others: the derivatives are accurate to ~1e-11 relative (measured: the same DBF computed on
# different rank layouts), so below 1e-9 the surviving part would be mostly round-off.
BREAKDOWN_TOL = 1e-9


@dataclass(frozen=True)
class BasisSettings:
    """What determines the basis besides the operators and the constraint rows."""

    modes: int | None = 6
    max_frequency_hz: float | None = None
    dbf_stiffness: object = "auto"      # "auto" or N/m (one for all constraints)
    dbf_derivative: str = "analytic"    # or "central"
    groups: int = 0                     # constraint groups; 0: min(ranks, constraints)

    def key(self) -> dict:
        """The settings that change the basis (groups do not: same basis to round-off)."""
        return {"modes": self.modes, "max_frequency_hz": self.max_frequency_hz,
                "dbf_stiffness": self.dbf_stiffness, "dbf_derivative": self.dbf_derivative}


@dataclass
class ReducedBasis:
    """M-orthonormal basis: N reference modes then one DBF per constraint (columns of a BV)."""

    vectors: SLEPc.BV
    omega: np.ndarray            # reference modes, rad/s
    dbf_omega: np.ndarray        # hat-omega_j (Eq. 41), rad/s
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
        return self.mode_count + self.constraint_rows.size

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
        """One line per DBF whose stiffness lies far outside the transition of Fig. 2."""
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


def orthonormalize(V: SLEPc.BV, first: int, rows: np.ndarray, labels=None) -> None:
    """Gram-Schmidt of columns first.. of V in V's inner product against all earlier columns, then
    normalization with the package's sign convention (Eqs. 18-19, 40). Columns before `first` must
    be orthonormal already. Raises SolverError on breakdown, naming the constraints. Collective."""
    labels = labels or [f"row {r}" for r in rows]
    total = V.getActiveColumns()[1]
    M = V.getMatrix()[0]
    for c in range(first, total):
        j = c - first
        before = V.normColumn(c)
        if not before > 0:
            raise SolverError(f"the DBF of constraint {j + 1} ({labels[j]}) is zero; "
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
                raise SolverError(f"basis breakdown: the DBF of the constraint at {labels[j]} is numerically "
                                  f"dependent on the DBFs of the constraints at {', '.join(partners)} "
                                  f"({survived}); constraints this close act as one: merge them or move them apart")
            raise SolverError(f"basis breakdown: the DBF of the constraint at {labels[j]} is numerically "
                              f"dependent on the {first} reference modes ({survived}); the modes already "
                              f"represent it: use fewer modes or a finer mesh")
        vec = V.getColumn(c)
        normalize(vec, M)
        V.restoreColumn(c, vec)


def build_basis(ops: Operators, rows, settings: BasisSettings = BasisSettings(), labels=None) -> ReducedBasis:
    """Reference modes, one DBF per constraint row, M-orthonormalized. Collective on ops.comm."""
    rows = np.asarray(rows, dtype=np.int64)
    values, counts = np.unique(rows, return_counts=True)
    if np.any(counts > 1):
        raise InputError(f"two constraints act on the same DOF (row {values[counts > 1][0]}); "
                         f"remove the duplicate")
    if rows.size and (rows.min() < 0 or rows.max() >= ops.size):
        raise InputError(f"a constraint row is outside the structure's {ops.size} DOFs")
    t0 = time.perf_counter()
    modes = reference_modes(ops, count=settings.modes, max_frequency_hz=settings.max_frequency_hz)
    t1 = time.perf_counter()
    N, NL = modes.count, rows.size
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
    k = k_auto = branch = np.zeros(0)
    if NL:
        gathered, k, k_auto, branch = _dbf_sources(ops, rows, modes, settings)
        for j in range(NL):
            gathered.getColumnVector(j, template)
            V.insertVec(N + j, template)
        gathered.destroy()
    modes.destroy()
    template.destroy()
    t2 = time.perf_counter()
    orthonormalize(V, N, rows, labels)
    basis = ReducedBasis(vectors=V, omega=omega, dbf_omega=np.zeros(NL), dbf_k=k, dbf_branch=branch,
                         constraint_rows=rows, dbf_k_auto=k_auto, settings=settings)
    Kr = basis.project(ops.K)
    basis.dbf_omega = np.sqrt(np.clip(np.diag(Kr)[N:], 0.0, None))
    basis.stats = {"time_modes": t1 - t0, "time_dbf": t2 - t1, "time_orthogonalization": time.perf_counter() - t2}
    return basis
