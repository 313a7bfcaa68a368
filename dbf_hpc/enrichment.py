"""Enrichment strategies: the columns added to the reference modes, one per constraint direction.

Each strategy computes its raw columns before Gram-Schmidt (basis.py orthonormalizes them against
the modes), and owns what belongs to it: its options prefix, the fields that enter the basis cache
key, the name of its columns, and its warnings.

- DbfEnrichment ("dbf", the method; paper Sec. 2.2, Eqs. 13-17): the derivative d phi/dk of the
  spring-perturbed mode (dbf.py), in parallel over constraints: COMM_WORLD is split into groups,
  each group gets its own copy of K and M and takes every groups-th constraint; the derivatives are
  gathered into one distributed matrix. solver "ritz" (the default): each group factors
  K - sigma M once and every constraint is a Rayleigh-Ritz problem on the reference modes plus a
  few Krylov vectors on g with it (dbf_ritz.py; ~3 solves per constraint, a block of constraints at
  a time: multi-right-hand-side solves, batched small eigenproblems); "shared": the same
  factorization, Krylov-Schur eigensolves and GMRES per constraint (dbf_shared.py, ~28 solves; the
  ritz path's fallback); "factor": three factorizations per constraint (dbf.py, the
  paper-faithful comparator). Options prefix `dbf_`.
- StaticEnrichment ("static"): the static attachment mode K^-1 g_j (the static correction of
  industrial codes, e.g. code_aster's static modes): one Cholesky factorization of K (MUMPS,
  options prefix `static_`) and one multi-right-hand-side solve per STATIC_BLOCK constraints. K must
  be regular.
- NoEnrichment ("none"): the reference modes alone (plain modal truncation).
"static" and "none" are comparators for accuracy studies, with everything else the same.

`columns` is collective on ops.comm.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc

from .dbf import STIFFNESS_RANGE, dbf_source, participation
from . import dbf_ritz
from .dbf_ritz import PREFETCH_BLOCK, RitzSolver, RitzSpace, reference_vectors
from .dbf_shared import FACTOR_AMPLIFICATION, AmplificationError, SharedFactor, SharedSolver
from .errors import DbfError, InputError, SolverError
from .modes import ModalBasis
from .operators import Operators
from .petsctools import destroy, direct_solver, refused_options_line, release_frames, unit_vector

STATIC_BACKWARD_TOL = 1e-10  # normwise backward error of K psi = g (a backward-stable solve gives ~1e-16)
STATIC_BLOCK = 64            # unit loads per multi-right-hand-side solve (memory: 3 local rows of each)


@dataclass(frozen=True)
class EnrichmentColumns:
    """Raw enrichment columns (an n x N_L dense Mat on ops.comm, or None) and, for DBFs, the
    stiffness k_j used, the transition k_auto and the eigen-branch of each (zero otherwise)."""

    matrix: PETSc.Mat | None
    k: np.ndarray
    k_auto: np.ndarray
    branch: np.ndarray


class Enrichment:
    """The interface (module docstring). Subclasses are frozen dataclasses of their parameters."""

    kind = ""
    column_name = ""        # what one column is called in messages and tables
    prefix = None           # options prefix of its solvers, None without solvers

    @property
    def solver_prefixes(self) -> tuple:
        """The options prefixes of every solver a basis of this kind uses (they enter its cache key):
        its own, the reference modes' and static_, whose Cholesky solves give every basis its stored
        f_exact (accuracy.exact_flexibility; red team: a DBF basis built under -static_ksp_max_it 1
        stored f_exact = NaN, and a run without the option reused it, its indicator lost)."""
        return tuple(dict.fromkeys(("modes_", "static_") + ((self.prefix,) if self.prefix else ())))

    def key(self) -> dict:
        """The parameters that change the columns (for the basis cache key)."""
        return {"enrichment": self.kind}

    def count(self, n_constraints: int) -> int:
        return n_constraints

    def check(self, ops: Operators) -> None:
        """An InputError if this kind cannot be built on ops (before any eigen-solve)."""

    def columns(self, ops: Operators, rows: np.ndarray, modes: ModalBasis) -> EnrichmentColumns:
        raise NotImplementedError

    def warnings(self, k: np.ndarray, k_auto: np.ndarray, labels) -> list:
        return []


def _empty(count: int) -> tuple:
    return np.zeros(count), np.zeros(count), np.zeros(count, dtype=np.int64)


@dataclass(frozen=True)
class NoEnrichment(Enrichment):
    """No enrichment column: the N reference modes alone ([basis] enrichment = "none"), a comparator
    for accuracy studies (docs/method.md)."""
    kind = "none"

    def count(self, n_constraints: int) -> int:
        return 0

    def columns(self, ops, rows, modes) -> EnrichmentColumns:
        return EnrichmentColumns(None, *_empty(0))


@dataclass(frozen=True)
class StaticEnrichment(Enrichment):
    """One static attachment mode K^-1 g_j (m/N, the deflection under a unit load at the constraint)
    per constraint where the DBF would be ([basis] enrichment = "static"): the static correction of
    industrial codes, a comparator for accuracy studies (docs/method.md). Needs K regular (no
    rigid-body modes); its solves take the options prefix static_."""
    kind = "static"
    column_name = "static mode"
    prefix = "static_"   # -static_ksp_..., -static_pc_...

    def check(self, ops: Operators) -> None:
        if ops.rigid_modes:
            raise InputError(f"static attachment modes need a structure without rigid-body motion; this one has "
                             f"{ops.rigid_modes} rigid-body mode(s) (K is singular): add supports or use "
                             f"[basis] enrichment = \"dbf\"")

    def columns(self, ops, rows, modes=None) -> EnrichmentColumns:
        return EnrichmentColumns(static_modes(ops, rows, self.prefix), *_empty(len(rows)))


@dataclass(frozen=True)
class DbfEnrichment(Enrichment):
    """stiffness: "auto" (the corner of Fig. 2) or k_j in N/m for every constraint; derivative:
    "analytic" or "central"; groups: constraint groups side by side (0: one per rank, at most one
    per constraint); solver: "ritz" or "shared" (one factorization per group) or "factor" (three per
    constraint). Groups do not enter the key: they change the DBFs by ~1e-8 (the paper's beam of 100
    elements, 9 constraints, measured), as the rank count does. The solver does: the three agree to
    ~1e-8 there (docs/method.md), not to round-off."""

    stiffness: object = "auto"
    derivative: str = "analytic"
    groups: int = 0
    solver: str = "ritz"
    kind = "dbf"
    column_name = "DBF"
    prefix = "dbf_"

    def key(self) -> dict:
        return {"enrichment": self.kind, "dbf_stiffness": self.stiffness, "dbf_derivative": self.derivative,
                "dbf_solver": self.solver}

    def columns(self, ops, rows, modes) -> EnrichmentColumns:
        return EnrichmentColumns(*_dbf_sources(ops, rows, modes, self))

    def warnings(self, k, k_auto, labels) -> list:
        """One line per DBF whose stiffness lies far outside the transition of Fig. 2."""
        out = []
        for j, (kj, kj_auto) in enumerate(zip(k, k_auto)):
            ratio = kj / kj_auto if kj_auto > 0 else 1.0
            if ratio > STIFFNESS_RANGE or ratio < 1 / STIFFNESS_RANGE:
                state = ("practically pinned there: the DBF derives from the pinned mode"
                         if ratio > 1 else "practically unperturbed: the DBF derives from the free mode")
                out.append(f"DBF stiffness {kj:.3g} N/m at {labels[j]} is {ratio:.0e} x the transition "
                           f"({kj_auto:.3g} N/m) of Fig. 2, where the method takes k; the perturbed mode is "
                           f"{state}, not from the transition. Check the result against "
                           f"dbf_stiffness = \"auto\"")
        return out


STRATEGIES = {"dbf": DbfEnrichment, "static": StaticEnrichment, "none": NoEnrichment}


def constraint_groups(world_size: int, n_constraints: int, requested: int = 0) -> int:
    """How many groups solve constraints side by side: as requested, else one group per rank up to
    one per constraint (each group's share differs by at most one constraint)."""
    if requested:
        if requested > world_size:
            # red team: a case on COMM_SELF under mpirun -n 2 read "exceeds the 1 MPI ranks"
            raise InputError(f"[basis] groups = {requested} exceeds the {world_size} MPI rank(s) of the communicator the "
                             f"basis is built on (one for a case on COMM_SELF): give at most {world_size}, or 0 for "
                             f"one group per rank")
        return requested
    return max(1, min(world_size, n_constraints))


def _dense_columns(ops: Operators, count: int) -> PETSc.Mat:
    gathered = PETSc.Mat().createDense(size=((ops.K.getLocalSize()[0], ops.size), (PETSc.DECIDE, count)),
                                       comm=ops.comm)
    gathered.setUp()
    return gathered


def _group_operators(ops: Operators, n_groups: int):
    """(mpi4py group communicator or None, the group's copy of the operators). Collective."""
    world = ops.comm.tompi4py()
    if n_groups == 1:
        return None, ops
    color = world.rank * n_groups // world.size
    group = world.Split(color, world.rank)
    sub = PETSc.Comm(group)
    K = None
    try:
        K = ops.K.getRedundantMatrix(n_groups, sub)
        M = ops.M.getRedundantMatrix(n_groups, sub)
    except BaseException:   # the copy of K and the group are this function's until it returns them
        destroy(K)
        group.Free()
        raise
    return group, Operators(comm=sub, K=K, M=M, rigid_modes=ops.rigid_modes, eigen_scale=ops.eigen_scale)


def _free_group(group, group_ops: Operators) -> None:
    if group is None:
        return
    group_ops.destroy()
    if hasattr(PETSc, "garbage_cleanup"):  # PETSc >= 3.18
        PETSc.garbage_cleanup(group_ops.comm)
    group.Free()


def group_failure(exc: Exception, world, prefix: str = "dbf_") -> tuple:
    """(is an InputError, one line) of whatever ended a constraint group's loop, for raise_agreed: a
    DbfError as it is; a PETSc error with the options of the group's solvers (-`prefix`); anything
    else (a bug) as an internal error naming its type and rank. Red team: a non-DbfError skipped
    raise_agreed, and the other groups waited in its allgather until the command's abort. The frames
    the exception passed through are released (their PETSc objects are the loop's to destroy). Not
    collective."""
    release_frames(exc)
    if isinstance(exc, DbfError):
        return isinstance(exc, InputError), str(exc)
    if isinstance(exc, PETSc.Error):
        return False, refused_options_line(exc, "the DBFs of a constraint group", (prefix,))
    text = (str(exc).splitlines() or [""])[0]
    return False, (f"internal error ({type(exc).__name__}) on rank {world.rank} in the DBFs of its constraint group"
                   f"{': ' + text if text else ''}; a bug: please report it (DBF_HPC_DEBUG=1 raises it with its "
                   f"traceback on that rank)")


def raise_agreed(world, failure, exc: Exception | None = None) -> None:
    """After the groups' loop over their constraints: the first group's failure ((is an InputError,
    message) or None, group_failure), in rank order, raised on every rank. A failed constraint ends
    its group alone; the other groups went on to the world's assembly and waited there for ever (red
    team). `exc`: this rank's own exception, raised as it is with DBF_HPC_DEBUG set (a bug's
    traceback; the other ranks raise the agreed line). Collective."""
    failure = next((f for f in world.allgather(failure) if f), None)
    if failure:
        if exc is not None and not isinstance(exc, DbfError) and os.environ.get("DBF_HPC_DEBUG"):
            raise exc
        raise (InputError if failure[0] else SolverError)(failure[1])


def _dbf_sources(ops: Operators, rows: np.ndarray, modes: ModalBasis, settings: DbfEnrichment):
    """Derivatives of all constraints, computed by groups, gathered into an n x N_L dense Mat on
    ops.comm; also k_j, k_auto and the branch of each. Collective."""
    world = ops.comm.tompi4py()
    n_groups = constraint_groups(world.size, rows.size, settings.groups)
    color = world.rank * n_groups // world.size
    group, group_ops = _group_operators(ops, n_groups)
    lam, part = modes.omega**2, participation(modes, rows)
    gathered = _dense_columns(ops, rows.size)
    k, k_auto, branch = _empty(rows.size)
    is_leader = (group.rank if group is not None else world.rank) == 0
    factor = space = None
    failure = mine = None
    try:
        try:
            # Every rank of a group takes the same path; a group with no constraint factors nothing.
            group_modes = reference_vectors(modes, group_ops, n_groups) if settings.solver == "ritz" else []
            try:
                if settings.solver in ("shared", "ritz") and color < rows.size:
                    factor = SharedFactor(group_ops)
                if factor is not None and settings.solver == "ritz":
                    space, group_modes = RitzSpace(factor, group_modes), []   # the space owns them now
            finally:
                destroy(*group_modes)
            mine = np.arange(color, rows.size, n_groups)
            lo, hi = group_ops.K.getOwnershipRange()
            local_rows = np.arange(lo, hi, dtype=PETSc.IntType)
            # the analytic derivative on the ritz path: a block of constraints at a time (RitzSpace.sources)
            blocks = space is not None and settings.derivative == "analytic" and dbf_ritz.BLOCK_SOURCES
            for start in range(0, mine.size, PREFETCH_BLOCK):
                chunk = mine[start:start + PREFETCH_BLOCK]
                served = np.zeros(0, dtype=np.int64)
                if blocks:
                    served, b, kj, kj_auto, _, d = space.sources(rows[chunk], lam, part[chunk], settings.stiffness)
                    if served.size:
                        gathered.setValues(local_rows, chunk[served].astype(PETSc.IntType), np.ascontiguousarray(d))
                        if is_leader:
                            k[chunk[served]], k_auto[chunk[served]], branch[chunk[served]] = kj, kj_auto, b
                elif space is not None:
                    space.prefetch(rows[chunk])
                for j in np.delete(chunk, served):    # one at a time (and the block's unserved)
                    src = _dbf_source(group_ops, int(rows[j]), lam, part[j], settings, factor, space)
                    gathered.setValues(local_rows, [j], src.derivative.array_r.reshape(-1, 1))
                    if is_leader:
                        k[j], k_auto[j], branch[j] = src.stiffness, src.transition, src.branch
                    src.derivative.destroy()
        except Exception as e:   # whatever ends one group: every rank hears of it (raise_agreed)
            failure, mine = group_failure(e, world), e
            # (not on an amplification refusal the factored path would take: red team, 1e7 N/m on the paper
            # beam was told "use factor" and "d phi/dk is lost in round-off" at once; factor builds it)
            if isinstance(e, SolverError) and settings.stiffness != "auto" and not (
                    isinstance(e, AmplificationError) and e.amplification <= FACTOR_AMPLIFICATION):
                # red team: dbf_stiffness = 1e300 failed with "use dbf_solver = factor", which failed with
                # "try central": d phi/dk ~ 1/k^2 is round-off there whatever the solver
                failure = (False, f"{failure[1]} (with the given [basis] dbf_stiffness = {settings.stiffness:g} "
                                  f"N/m: far from a constraint's transition, Fig. 2, d phi/dk is lost in round-off; "
                                  f"try dbf_stiffness = \"auto\")")
        raise_agreed(world, failure, mine)
        gathered.assemble()
    except Exception:
        gathered.destroy()
        raise
    finally:
        destroy(space, factor)
        _free_group(group, group_ops)
    return gathered, world.allreduce(k), world.allreduce(k_auto), world.allreduce(branch)


def _dbf_source(ops: Operators, row: int, lam, part, settings: DbfEnrichment, factor: SharedFactor | None,
                space: RitzSpace | None = None):
    """One constraint's DBF source on the group's operators: by Rayleigh-Ritz on the group's space if
    there is one, else on the shared factor if there is one, else with its own factorizations."""
    if space is not None:
        solver = RitzSolver(space, row)
    else:
        solver = SharedSolver(factor, row) if factor is not None else None
    try:
        return dbf_source(ops, row, lam, part, settings.stiffness, settings.derivative, solver)
    finally:
        destroy(solver)


def static_modes(ops: Operators, rows: np.ndarray, prefix: str = "static_") -> PETSc.Mat:
    """The static attachment modes psi_j = K^-1 g_j of all constraints (the deflection under a unit
    load at row j), as the columns of an n x N_L dense Mat on ops.comm: one Cholesky factorization
    of K (MUMPS), then STATIC_BLOCK unit loads at a time in one multi-right-hand-side solve
    (MatMatSolve: MUMPS solves a block at a fraction of the cost of as many single solves) with one
    K product for their backward errors; a factor without MatMatSolve, or a column that fails its
    check, is solved singly (and refused if it fails again). K must be regular. Collective."""
    StaticEnrichment().check(ops)
    ksp = direct_solver(PETSc.KSP().create(comm=ops.comm), PETSc.PC.Type.CHOLESKY)
    factor = gathered = psi = residual = None
    try:
        ksp.setOperators(ops.K)
        ksp.setOptionsPrefix(prefix)
        ksp.setFromOptions()   # a refused -static_ option: the KSP is still freed (red team: leaked)
        gathered = _dense_columns(ops, len(rows))
        K_norm = ops.K.norm(PETSc.NormType.FROBENIUS)
        psi, residual = ops.K.createVecRight(), ops.K.createVecLeft()
        lo, hi = psi.getOwnershipRange()
        local_rows = np.arange(lo, hi, dtype=PETSc.IntType)
        rows = np.asarray(rows, dtype=np.int64)
        single = list(range(rows.size))
        factor = _static_factor(ksp) if rows.size else None
        if factor is not None:
            single = []
            for start in range(0, rows.size, STATIC_BLOCK):
                chunk = np.arange(start, min(start + STATIC_BLOCK, rows.size))
                block, ok = _static_block(ops, factor, rows[chunk], K_norm)
                if ok.any():
                    gathered.setValues(local_rows, chunk[ok].astype(PETSc.IntType),
                                       np.ascontiguousarray(block[:, ok]))
                single.extend(chunk[~ok])
        for j in single:
            row = int(rows[j])
            g = unit_vector(residual, row)
            try:
                ksp.solve(g, psi)
                solved = ksp.getConvergedReason() >= 0
            except PETSc.Error:
                solved = False
            if solved:  # normwise backward error, as for the DBF derivative (||g|| = 1)
                ops.K.mult(psi, residual)
                residual.axpy(-1.0, g)
                solved = residual.norm() / (K_norm * psi.norm() + 1.0) < STATIC_BACKWARD_TOL
            g.destroy()
            if not solved:
                raise SolverError(f"the static mode of the constraint at row {row} failed (K psi = g not solved: "
                                  f"K is singular or nearly so); support the structure or use [basis] "
                                  f"enrichment = \"dbf\"")
            gathered.setValues(local_rows, [j], psi.array_r.reshape(-1, 1))
        gathered.assemble()
    except Exception:
        destroy(gathered)
        raise
    finally:
        # the factor is our reference to the KSP's factored K: released, not left to Python (petsc4py 3.18
        # parks a Mat whose last reference a collected wrapper held in PETSc's garbage until a collective
        # garbage_cleanup: 20 KB per basis, measured)
        destroy(factor, ksp, psi, residual)
    return gathered


def _static_factor(ksp: PETSc.KSP):
    """The factored K of a direct `ksp` for MatMatSolve (a reference the caller destroys), or None (not
    a factorization, or the set-up failed: the single solves then report the row). A factorization that failed quietly gives
    columns that fail their check. Collective."""
    try:
        ksp.setUp()
        if ksp.getPC().getType() not in (PETSc.PC.Type.CHOLESKY, PETSc.PC.Type.LU):
            return None
        return ksp.getPC().getFactorMatrix()
    except PETSc.Error:
        return None


def _static_block(ops: Operators, factor: PETSc.Mat, rows: np.ndarray, K_norm: float):
    """(psi's local rows for the unit loads at `rows`, n_local x L; which passed the backward-error
    check, the same on every rank): one MatMatSolve and one K product. Collective."""
    K, comm = ops.K, ops.comm.tompi4py()
    lo, hi = K.getOwnershipRange()
    N, L = K.getSize()[0], rows.size
    b = np.zeros((hi - lo, L), order="F")
    mine = (rows >= lo) & (rows < hi)
    b[rows[mine] - lo, np.flatnonzero(mine)] = 1.0
    x = np.zeros((hi - lo, L), order="F")
    B = PETSc.Mat().createDense(((hi - lo, N), (PETSc.DECIDE, L)), array=b, comm=ops.comm)
    X = PETSc.Mat().createDense(((hi - lo, N), (PETSc.DECIDE, L)), array=x, comm=ops.comm)
    KX = None
    try:
        B.assemble()
        X.assemble()
        try:
            factor.matSolve(B, X)
        except PETSc.Error:   # no MatMatSolve for this factor: every column singly
            return x, np.zeros(L, dtype=bool)
        KX = K.matMult(X)
        r = KX.getDenseArray() - b
        sums = np.vstack([np.einsum("ij,ij->j", r, r), np.einsum("ij,ij->j", x, x)])
        if comm.size > 1:
            sums = comm.allreduce(sums)
        with np.errstate(invalid="ignore"):
            ok = np.sqrt(sums[0]) / (K_norm * np.sqrt(sums[1]) + 1.0) < STATIC_BACKWARD_TOL
        return x, comm.bcast(ok, root=0)
    finally:
        destroy(B, X, KX)
