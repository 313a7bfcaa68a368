"""The reduced basis V = [phi_1..phi_N, psi_1..psi_NL] (docs/design.md, the pipeline steps 1-5).

1. Reference modes on the operators' communicator (modes.py).
2. One enrichment column per constraint, of the strategy BasisSettings names (enrichment.py): a DBF
   (the method), a static attachment mode, or none (the modes alone).
3. Gram-Schmidt in the M inner product (SLEPc BV with M as its matrix), distributed, against the
   modes and the earlier columns (Eqs. 18-19), M-normalization (Eq. 40), hat-omega_j (Eq. 41/20).
   A column that almost vanishes under orthogonalization is numerically dependent on the others: an
   error naming the constraints, never a silent bad basis.

The constraint rows are kept for every kind: B = V at the constraint rows is what the reduced
model needs, with or without enrichment columns. Everything here is collective on ops.comm.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass, field, replace

import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from .accuracy import basis_flexibility, captured, exact_flexibility
from .enrichment import STRATEGIES, DbfEnrichment, Enrichment
from .errors import InputError, Interrupted, SolverError, check_number
from .modes import bv_rows, normalize, reference_modes, whole_count
from .operators import Operators
from .petsctools import destroy

# A DBF that keeps less than this fraction of its M-norm after Gram-Schmidt is numerically dependent
# on the others: the derivatives are accurate to ~1e-11 relative (measured: the same DBF computed on
# different rank layouts), so below 1e-9 the surviving part would be mostly round-off.
BREAKDOWN_TOL = 1e-9
ENRICHMENTS = tuple(STRATEGIES)
DBF_SOLVERS = ("ritz", "shared", "factor")


@dataclass(frozen=True)
class BasisSettings:
    """What determines the basis besides the operators and the constraint rows: the reference modes
    (a count `modes`, or every mode below `max_frequency_hz`, Hz) and the enrichment with its
    parameters: "dbf" (the method: dbf_stiffness k_j, "auto" for the corner of the paper's Fig. 2 or
    N/m for every constraint; dbf_derivative and dbf_solver, docs/method.md), "static" or "none"
    (comparators). gyroscopic_form: a gyroscopic structure's reduced model, "second_order" or the
    paper's first-order "state_space" (Eqs. 4-21). docs/scene.md's [basis] table has each key."""

    modes: int | None = 6
    max_frequency_hz: float | None = None
    dbf_stiffness: object = "auto"      # "auto" or N/m (one for all constraints)
    dbf_derivative: str = "analytic"    # or "central"
    groups: int = 0                     # constraint groups; 0: min(ranks, constraints)
    enrichment: str = "dbf"             # "dbf" | "static" | "none" (enrichment.py)
    dbf_solver: str = "ritz"            # "ritz" | "shared" (one factorization per group) | "factor" (three per constraint)
    gyroscopic_form: str = "second_order"   # a gyroscopic structure's reduced model: "second_order" | "state_space"

    def __post_init__(self):
        if self.modes is not None:
            object.__setattr__(self, "modes", check_number("BasisSettings modes", self.modes, 1, integer=True))
        if self.max_frequency_hz is not None:
            object.__setattr__(self, "max_frequency_hz", check_number("BasisSettings max_frequency_hz",
                                                                      self.max_frequency_hz, 0.0, above=True))
        if self.modes is None and self.max_frequency_hz is None:
            raise InputError("BasisSettings: give modes or max_frequency_hz")
        object.__setattr__(self, "groups", check_number("BasisSettings groups", self.groups, 0, integer=True))
        for name, accepted in (("enrichment", tuple(STRATEGIES)), ("dbf_solver", DBF_SOLVERS),
                               ("dbf_derivative", ("analytic", "central")),
                               ("gyroscopic_form", ("second_order", "state_space"))):
            if getattr(self, name) not in accepted:
                quoted = ", ".join(f'"{a}"' for a in accepted)
                raise InputError(f"BasisSettings {name} must be one of {quoted}, got {getattr(self, name)!r}")
        if self.dbf_stiffness != "auto":
            object.__setattr__(self, "dbf_stiffness", check_number("BasisSettings dbf_stiffness (N/m, or \"auto\")",
                                                                   self.dbf_stiffness, 0.0, above=True))

    @property
    def strategy(self) -> Enrichment:
        """The enrichment strategy these settings name (enrichment.py; __post_init__ checked the names)."""
        if self.enrichment == "dbf":
            return DbfEnrichment(self.dbf_stiffness, self.dbf_derivative, self.groups, self.dbf_solver)
        return STRATEGIES[self.enrichment]()

    def key(self) -> dict:
        """The settings that change the basis (groups do not: the same span to the DBFs' accuracy, ~1e-8
        on the paper's beam of 100 elements, measured; the DBF stiffness, derivative and solver only for
        DBFs)."""
        return {"modes": self.modes, "max_frequency_hz": self.max_frequency_hz, **self.strategy.key()}


@dataclass
class ReducedBasis:
    """M-orthonormal basis: N reference modes then the enrichment columns (one per constraint, or
    none), as columns of a BV. enrichment_omega holds hat-omega_j of each enrichment column;
    dbf_k, dbf_k_auto and dbf_branch the stiffness, transition and branch of each DBF (zero where a
    column is not a DBF); flexibility_exact and flexibility_captured the a-priori indicator of each
    constraint (accuracy.py)."""

    vectors: SLEPc.BV
    omega: np.ndarray              # reference modes, rad/s
    enrichment_omega: np.ndarray   # hat-omega_j (Eq. 41) of each enrichment column, rad/s
    dbf_k: np.ndarray              # k_j used for each DBF, N/m
    dbf_branch: np.ndarray         # eigen-branch m followed for each DBF (1 = first mode)
    constraint_rows: np.ndarray
    dbf_k_auto: np.ndarray         # the transition stiffness of each constraint (N/m)
    settings: BasisSettings
    stats: dict = field(default_factory=dict)
    flexibility_exact: np.ndarray = field(default_factory=lambda: np.zeros(0))     # g_j^T K^-1 g_j, m/N
    flexibility_captured: np.ndarray = field(default_factory=lambda: np.zeros(0))  # f_basis / f_exact, 1

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

    @property
    def complex_modes(self) -> int:
        """The complex modes of a gyroscopic basis (two columns each, Re and Im; gyroscopic_basis.py),
        0 for a basis of real modes."""
        return int(self.stats.get("complex_modes", 0))

    def constraint_omega(self) -> np.ndarray:
        """hat-omega of each constraint's enrichment: enrichment_omega, or on a gyroscopic basis (one
        or two columns per constraint) the value of each constraint's first column."""
        counts = self.stats.get("constraint_columns")
        if counts is None:
            return self.enrichment_omega
        if not counts:
            return np.zeros(0)
        return self.enrichment_omega[np.concatenate(([0], np.cumsum(counts)[:-1])).astype(int)]

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

    def dot(self, vec: PETSc.Vec) -> np.ndarray:
        """V^T vec (the plain dot, not the M inner product) on every rank: a load projected onto the
        basis. Collective."""
        dense = self.vectors.getMat()
        out = dense.getDenseArray().T @ vec.getArray(readonly=True)
        self.vectors.restoreMat(dense)
        return self.vectors.getComm().tompi4py().allreduce(out)

    def dot_rows(self, rows: np.ndarray) -> np.ndarray:
        """V^T W for a matrix W given by this rank's rows (local rows x m, K's layout): (r, m) on
        every rank. Collective."""
        dense = self.vectors.getMat()
        out = dense.getDenseArray().T @ rows
        self.vectors.restoreMat(dense)
        return self.vectors.getComm().tompi4py().allreduce(out)

    def warnings(self, labels=None) -> list:
        """One line per DBF whose stiffness lies far outside the transition of Fig. 2."""
        labels = labels or [f"row {r}" for r in self.constraint_rows]
        return self.settings.strategy.warnings(self.dbf_k, self.dbf_k_auto, labels)

    def set_flexibility(self, f_exact: np.ndarray, K_r: np.ndarray) -> None:
        """Store f_exact (m/N) and the captured flexibility f_basis / f_exact with f_basis from this
        basis's own K_r = V^T K V (accuracy.py). Collective."""
        self.flexibility_exact = np.asarray(f_exact, dtype=float)
        self.flexibility_captured = captured(basis_flexibility(K_r, self.rows(self.constraint_rows)),
                                             self.flexibility_exact)

    def destroy(self) -> None:
        self.vectors.destroy()


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
            raise SolverError(f"the {name} at {labels[j]} is zero; "
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


def name_rows(message: str, rows, labels) -> str:
    """A solver's "at row R" (a DOF row, which the user never wrote) named by the constraint at that row
    as the scene gives it (labels: x = 0.25 m, dof 12), the row kept in brackets (red team: "DBF at row
    49" for a stop the scene placed at x). Not collective."""
    if labels is None:
        return message
    names = {int(r): str(label) for r, label in zip(np.ravel(rows), labels)}

    def named(match):
        row = int(match.group(2))
        if row not in names:
            return match.group(0)
        return f"{'constraint' if match.group(1) else 'at the constraint'} at {names[row]} (row {row})"

    return re.sub(r"\b(constraint )?at row (\d+)", named, message)


def _check_rows(ops: Operators, rows: np.ndarray) -> None:
    values, counts = np.unique(rows, return_counts=True)
    if np.any(counts > 1):
        raise InputError(f"two constraints act on the same DOF (row {values[counts > 1][0]}); "
                         f"remove the duplicate")
    if rows.size and (rows.min() < 0 or rows.max() >= ops.size):
        raise InputError(f"a constraint row is outside the structure's {ops.size} DOFs")


def _basis_vectors(ops: Operators, count: int) -> SLEPc.BV:
    V = SLEPc.BV().create(comm=ops.comm)
    template = ops.K.createVecRight()
    V.setSizesFromVec(template, count)
    template.destroy()
    V.setType(SLEPc.BV.Type.SVEC)
    V.setMatrix(ops.M, False)
    V.setOrthogonalization(SLEPc.BV.OrthogType.CGS, SLEPc.BV.OrthogRefineType.ALWAYS)
    return V


def _insert_columns(V: SLEPc.BV, first: int, source, count: int, ops: Operators) -> None:
    """Copy `count` columns of a BV or a dense Mat into V from column `first` on."""
    template = ops.K.createVecRight()
    for j in range(count):
        if isinstance(source, SLEPc.BV):
            source.copyVec(j, template)
        else:
            source.getColumnVector(j, template)
        V.insertVec(first + j, template)
    template.destroy()


# A lowest frequency below this is more likely a unit mistake (E in GPa given as Pa) than a structure.
SUSPICIOUS_HZ = 1e-3


def _units_hint(ops: Operators, frequency_hz) -> str:
    """What to check when an enrichment solve fails on a structure whose lowest elastic frequency is
    below SUSPICIOUS_HZ (red team: K and M files swapped failed as "GMRES did not converge; use
    dbf_solver = factor", the units warning printed only after a basis), else ""."""
    elastic = np.asarray(frequency_hz)[ops.rigid_modes:]
    if elastic.size and elastic[0] < SUSPICIOUS_HZ:
        return (f"; the lowest elastic frequency is {elastic[0]:.3g} Hz: check the structure's units (SI: N/m "
                f"and kg), and that the stiffness and mass are not swapped")
    return ""


def build_basis(ops: Operators, rows, settings: BasisSettings = BasisSettings(), labels=None,
                whole: str = "refuse") -> ReducedBasis:
    """Reference modes and the enrichment columns settings.strategy makes (one per constraint row,
    or none), M-orthonormalized. With a gyroscopic G, the real basis of the complex modes and DBFs
    (gyroscopic_basis.py). `whole`: a settings.modes that ends inside a repeated frequency is refused
    (a user's count) or extended to its end ("extend": the estimate's richer modes, cache.obtain_modes);
    modes.reference_modes. Collective on ops.comm."""
    if settings.max_frequency_hz is None and not 1 <= settings.modes <= ops.size:   # named by its key (AX)
        raise InputError(f"[basis] modes = {settings.modes}: the structure has {ops.size} free DOFs; give 1 to "
                         f"{ops.size} modes, fewer where constraints add enrichment columns")
    check_pairs(ops, settings.modes)
    if ops.G is not None:
        from .state_space import build_state_space_basis, check_form
        check_form(settings.gyroscopic_form)
        if settings.gyroscopic_form == "state_space":
            return build_state_space_basis(ops, rows, settings, labels, whole)
        from .gyroscopic_basis import build_gyroscopic_basis
        return build_gyroscopic_basis(ops, rows, settings, labels, whole)
    strategy = settings.strategy
    rows = np.asarray(rows, dtype=np.int64)
    _check_rows(ops, rows)
    strategy.check(ops)  # before any eigen-solve
    t0 = time.perf_counter()
    try:
        modes = reference_modes(ops, count=settings.modes, max_frequency_hz=settings.max_frequency_hz,
                                whole=whole)
    except SolverError as exc:   # modes that are not the lowest (modes._cut_by_inertia): K and M swapped, say
        if hasattr(exc, "frequency_hz"):
            exc.args = (str(exc) + _units_hint(ops, exc.frequency_hz),)
        raise
    t1 = time.perf_counter()
    N, NL = modes.count, strategy.count(rows.size)
    if NL and N >= ops.size:
        # red team: a single-DOF mass-spring with a stop ended in a ZeroDivisionError (2 ranks) or an
        # eigensolver failure blaming M and K (1 rank) inside the DBF solve
        destroy(modes)
        raise InputError(f"the {N} reference modes span all {ops.size} DOFs of the structure: an enrichment column "
                         f"would depend on them; set [basis] enrichment = \"none\" (the modes are then exact)"
                         + (" or use fewer modes" if ops.size > 1 else ""))
    V = _basis_vectors(ops, N + NL)
    columns = None
    try:
        _insert_columns(V, 0, modes.vectors, N, ops)
        columns = strategy.columns(ops, rows, modes)
        if NL:
            _insert_columns(V, N, columns.matrix, NL, ops)
        t2 = time.perf_counter()
        orthonormalize(V, N, rows, labels, strategy.column_name or "column")
    except SolverError as exc:   # every rank's (enrichment.raise_agreed), with the same modes
        V.destroy()
        hint = None if isinstance(exc, Interrupted) else _units_hint(ops, modes.frequency_hz)
        exc.args = (name_rows(str(exc), rows, labels) + (hint or ""),)   # the same exception, its type kept
        raise
    except Exception:
        V.destroy()
        raise
    finally:
        destroy(modes, columns.matrix if columns is not None else None)
    basis = ReducedBasis(vectors=V, omega=modes.omega.copy(), enrichment_omega=np.zeros(NL), dbf_k=columns.k,
                         dbf_branch=columns.branch, constraint_rows=rows, dbf_k_auto=columns.k_auto,
                         settings=settings)
    try:
        K_r = basis.project(ops.K)
        basis.enrichment_omega = np.sqrt(np.clip(np.diag(K_r)[N:], 0.0, None))
        t3 = time.perf_counter()
        basis.set_flexibility(exact_flexibility(ops, rows), K_r)   # Cholesky solves of K: may be refused
    except Exception:
        basis.destroy()
        raise
    basis.stats = {"time_modes": t1 - t0, "time_enrichment": t2 - t1,
                   "time_orthogonalization": t3 - t2, "time_flexibility": time.perf_counter() - t3}
    return basis


def modes_per_frequency(ops: Operators) -> int:
    """2 on a beam of two planes (y and z bend alike: every frequency twice), else 1."""
    return getattr(ops.mesh, "planes", 1)


def check_pairs(ops: Operators, count: int | None) -> None:
    """A beam of two planes has every frequency twice (y and z bend alike): an odd count of modes keeps
    one of the last pair, in a y-z direction the eigensolver picks by round-off, so the reduced model
    changed with the rank count (red team: the 2-D tube at 3 modes, 39 % apart at 0.2 s on 1 and 2
    ranks; 4e-10 at 4 modes). An InputError before any eigen-solve."""
    if count is not None and count % modes_per_frequency(ops):
        raise InputError(f"[basis] modes = {count} on a beam of two planes: each frequency is a pair (y and z), and "
                         f"an odd count keeps one of the last pair in a direction set by round-off; give an even "
                         f"count ({' or '.join(str(n) for n in sorted({max(count - 1, 2), count + 1}))}) or "
                         f"max_frequency_hz")


def richer_basis(ops: Operators, basis: ReducedBasis, modes: int, labels=None, reference=None) -> ReducedBasis:
    """The reference modes 1..`modes` (more than basis has; more where `modes` ends inside a repeated
    frequency, up to its end) and basis's own enrichment columns,
    M-orthonormalized: span(basis) lies inside the result's span, so the difference between the two
    reduced models measures what the missing modes change (the error estimate, accuracy.py). No
    enrichment is recomputed; the indicator is carried over (f_exact) and recomputed (captured).
    `reference`: the reference modes already solved (a ModalBasis of at least `modes`, kept: the
    estimate's two richer bases share one eigensolve), else they are solved here. Collective on ops.comm."""
    if getattr(basis, "form", "") == "state_space":
        from .state_space import richer_state_space_basis
        return richer_state_space_basis(ops, basis, modes)
    if ops.G is not None:
        from .gyroscopic_basis import richer_gyroscopic_basis
        return richer_gyroscopic_basis(ops, basis, modes)
    rows = basis.constraint_rows
    N, NL = basis.mode_count, basis.enrichment_count
    if reference is not None and reference.count < modes:
        raise ValueError(f"richer_basis: {reference.count} reference modes given for {modes}")
    # a repeated frequency at the cut is taken whole (modes.whole_count): part of it is a direction set
    # by round-off (red team: the 2-D tube's second richer model at 15 modes kept one of a y-z pair)
    more = reference if reference is not None else reference_modes(ops, count=modes)
    modes = whole_count(more.omega ** 2, modes, ops.rigid_modes) if modes < more.count else more.count
    V = _basis_vectors(ops, modes + NL)
    try:
        _insert_columns(V, 0, more.vectors, modes, ops)
        template = ops.K.createVecRight()
        for j in range(NL):
            basis.vectors.copyVec(N + j, template)
            V.insertVec(modes + j, template)
        template.destroy()
        orthonormalize(V, modes, rows, labels, basis.settings.strategy.column_name or "column")
    except Exception:
        V.destroy()
        raise
    finally:
        if reference is None:
            destroy(more)
    settings = replace(basis.settings, modes=modes, max_frequency_hz=None)
    rich = ReducedBasis(vectors=V, omega=more.omega[:modes].copy(), enrichment_omega=np.zeros(NL), dbf_k=basis.dbf_k,
                        dbf_branch=basis.dbf_branch, constraint_rows=rows, dbf_k_auto=basis.dbf_k_auto,
                        settings=settings, stats={"cache": "off"})
    try:
        K_r = rich.project(ops.K)
        rich.enrichment_omega = np.sqrt(np.clip(np.diag(K_r)[modes:], 0.0, None))
        rich.set_flexibility(basis.flexibility_exact, K_r)
    except Exception:
        rich.destroy()
        raise
    return rich
