"""Reference modes: K phi = lambda M phi with SLEPc (paper Section 2.1, Eq. 2;
the beam's in Section 3.1, Eqs. 28-31).

Generalized Hermitian EPS, shift-and-invert about a target just below the spectrum, factorized by
MUMPS (Cholesky). Options prefix `modes_` (and `dbf_` for the spring-perturbed problems of dbf.py):
every EPS/ST/KSP/PC setting can be changed from the command line (-modes_eps_tol,
-modes_st_pc_factor_mat_solver_type, ...). The code's defaults are set before setFromOptions, so
the user's options win; those read at factorization time (MUMPS's inertia switches) are in the
options database only while the solver is set up and solves.

Every result is checked before it is returned (`accuracy`, `trust_check`): a beam mesh or a matrix
model too ill-conditioned for double precision is refused with one line instead of being answered
with wrong frequencies. Rounding perturbs the entries of K by a relative u = eps / 2 (in K itself, in
its factorization, in every product with it), which moves the eigenvalue of an M-normalized x by up
to about u |x|^T |K| |x|. Relative to lambda this is the `estimate` (u times the eigenvalue's
condition number). For a smooth mode of a beam of n Hermite elements it is ~ 48 u (n / beta_1 L)^4:
it grows like n^4, and scaling the DOFs (e.g. rotations by the element length) does not change it,
as it is invariant under diagonal scaling; the errors measured with such a scaling were no smaller.
Each returned eigenpair must have estimate <= TRUST_TOL and relative residual
||K x - lambda M x|| / (lambda ||M x||) <= sqrt(TRUST_TOL): the residual catches a solve that is
wrong for another reason (an inexact shift-and-invert); its floor is the rounding in K x, about the
estimate, and for a Hermitian pencil the eigenvalue error goes like the residual squared over the gap.

The solves and checks are collective on the operators' communicator.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from .errors import DbfError, InputError, Interrupted, SolverError
from .operators import Operators
from .petsctools import destroy, direct_solver, frames_released, options_defaults, release_frames

# Options the eigensolvers set as defaults (so that MUMPS reports the inertia); they do not change
# the eigenpairs.
FACTOR_DEFAULTS = {"st_mat_mumps_icntl_13": "1", "st_mat_mumps_icntl_24": "1"}

# Relative accuracy in lambda of what reference_modes returns (option -<prefix>trust_tol): the
# largest estimate accepted. Measured on Hermite beams of 100 to 4000 elements (pinned-pinned,
# clamped-free, free-free, the clamped-pinned 10 m steam generator tube) the error of lambda was at
# most 0.47 times the estimate wherever rounding outweighed the discretization error, so accepted
# eigenvalues are right to ~5e-6 (frequencies to ~2.5e-6).
# The limit is ~650 elements for the pinned-pinned paper beam, ~390 clamped-free, ~980 free-free,
# ~810 for the tube; 1e-6 would refuse the paper beam beyond ~370 elements (tests use 480).
TRUST_TOL = 1e-5
# Elements of the coarse mesh on which _element_limit measures the estimate.
COARSE_ELEMENTS = 100

# Two eigenvalues lambda = omega^2 closer than this, relative in lambda (|a - b| <= REPEATED_TOL max(|a|,
# |b|): frequencies within about half of it), are one repeated eigenvalue, whose modes are any mix of its
# eigenspace (a round tube's y and z, a square bar's two bending modes). The one quantity of every such
# decision (repeated): the cut of the reference modes (whole_count, cluster_start, the inertia window
# lam (1 +- REPEATED_TOL) of _cut_by_inertia), the DBF branch (dbf.CLUSTER_TOL), one damping ratio per
# repeated frequency (damping), the gyroscopic modes' cut (on |lambda|^2).
REPEATED_TOL = 1e-6

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


class RepeatedCut(InputError):
    """A count of reference modes that keeps part of a repeated eigenvalue's modes: `first` modes lie
    below it and `whole` take all of it (the nearest counts that keep it whole)."""

    def __init__(self, message: str, first: int, whole: int):
        super().__init__(message)
        self.first, self.whole = first, whole


def repeated(a: float, b: float) -> bool:
    """Whether the eigenvalues a and b (lambda = omega^2, not frequencies) are one repeated eigenvalue:
    |a - b| <= REPEATED_TOL max(|a|, |b|) (two zeros are). Not collective."""
    return abs(b - a) <= REPEATED_TOL * max(abs(a), abs(b))


def whole_count(values, count: int, rigid: int = 0) -> int:
    """The smallest count >= `count` of the sorted eigenvalues `values` that does not end inside a
    repeated eigenvalue (a cluster within REPEATED_TOL, or the `rigid` rigid-body modes, zero to
    round-off): `count` itself unless values[count] repeats values[count - 1]. len(values) when the
    repeated eigenvalue reaches the last value given (more may follow). Not collective."""
    lam = np.asarray(values, dtype=float)
    end = count
    while 0 < end < lam.size:
        a, b = lam[end - 1], lam[end]
        if not (end < rigid or repeated(a, b)):
            break
        end += 1
    return end


def cluster_start(values, count: int, rigid: int = 0) -> int:
    """The first index of the repeated eigenvalue (as whole_count) that values[count - 1] belongs to
    (count - 1 when it is simple). Not collective."""
    lam = np.asarray(values, dtype=float)
    start = count - 1
    while start > 0 and (start < rigid or repeated(lam[start - 1], lam[start])):
        start -= 1
    return start


def repeated_groups(values, rigid: int = 0) -> np.ndarray:
    """For each of the sorted eigenvalues `values` (repeated ones whole, as reference_modes returns
    them), the number (from 1) of the first mode of its repeated eigenvalue (whole_count's clusters,
    the `rigid` rigid-body modes one), 0 for a simple one. Not collective."""
    lam = np.asarray(values, dtype=float)
    out = np.zeros(lam.size, dtype=np.int64)
    for j in range(lam.size):
        first, end = cluster_start(lam, j + 1, rigid), whole_count(lam, j + 1, rigid)
        if end - first >= 2:
            out[j] = first + 1
    return out


def repeated_mode_refusal(values, mode: int, rigid: int = 0) -> str | None:
    """Why [initial] mode = `mode` (from 1) is refused (what follows "[initial] mode = M: "), when it
    is one of a repeated eigenvalue's modes (values: the sorted eigenvalues, repeated ones whole as
    reference_modes returns them), else None: its shape is any mix of them, chosen by round-off, so
    the reduced model (its basis's mode) and the full-order model (an eigensolve of its own) start
    from different shapes. Not collective."""
    first, end = cluster_start(values, mode, rigid), whole_count(values, mode, rigid)
    if end - first < 2:
        return None
    what = ("zero frequency, the rigid-body modes" if mode <= rigid else
            f"one repeated frequency, {np.sqrt(max(values[mode - 1], 0.0)) / (2 * np.pi):.6g} Hz")
    return (f"one of the {end - first} modes of {what} (modes {first + 1} to {end}): its "
            f"shape is any mix of them, a direction set by round-off, so the reduced and the full-order model (and "
            f"runs on other rank counts) would start from different shapes; start from a mode of a simple frequency")


def _massless_rows(M: PETSc.Mat) -> int:
    """How many diagonal entries of M are exactly 0 (massless DOFs, e.g. rotations under a lumped
    mass): each one is an infinite eigenvalue of (K, M). Collective."""
    diagonal = M.getDiagonal()
    try:
        local = int(np.count_nonzero(diagonal.getArray(readonly=True) == 0.0))
    finally:
        diagonal.destroy()
    return M.getComm().tompi4py().allreduce(local)


def shift_below_spectrum(ops: Operators) -> float:
    """The shift-and-invert target sigma below the lowest eigenvalue: 0 for a supported structure
    (K is SPD), -eigen_scale when rigid-body modes make K singular (LowestModes explains the value)."""
    return -ops.eigen_scale if ops.rigid_modes else 0.0


class LowestModes:
    """An EPS for the lowest eigenpairs of (K, ops.M), configured, with the user's options under
    `prefix`. K may differ from ops.K (spring-perturbed and pinned problems). Owns the EPS: use it
    in a `with` block. Collective on K's communicator.

    inverse: None (the ST factors K - sigma M itself), or a Python PC context whose apply(pc, x, y)
    is an exact y = (K - sigma M)^-1 x, sigma = shift_below_spectrum(ops) (the shared-factorization
    DBF path, dbf_shared.py): the ST then assembles and factors nothing, and the target and ST type
    are fixed (an option changing them is refused: the inverse would not match)."""

    def __init__(self, ops: Operators, K: PETSc.Mat, prefix: str, tol: float = 1e-10, inverse=None):
        self.prefix = prefix
        self.eps = SLEPc.EPS().create(comm=K.getComm())
        try:
            self._configure(ops, K, tol, inverse)
        except BaseException as e:   # a refused -<prefix> option, say: the EPS is ours to free (red team: leaked)
            release_frames(e)   # _configure's reference to the EPS's ST first
            self.destroy()
            raise

    def _configure(self, ops: Operators, K: PETSc.Mat, tol: float, inverse) -> None:
        eps, prefix = self.eps, self.prefix
        eps.setOperators(K, ops.M)
        eps.setProblemType(SLEPc.EPS.ProblemType.GHEP)
        eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
        # Shift below the spectrum: 0 for a supported structure (K is SPD), -eigen_scale when rigid-body
        # modes make K singular. Rounding in factoring K - sigma M moves the rigid modes' eigenvalue
        # -sigma by ~48 u (elements)^4 eigen_scale (beam), so the shift must be far enough from 0: at
        # -1e-3 eigen_scale a free-free beam lost its rigid modes (and returned wrong frequencies) beyond
        # ~800 elements, at -eigen_scale it keeps them past 4000, beyond what trust_check accepts. The
        # lowest elastic eigenvalue of a beam with rigid modes is >= 31 eigen_scale (sliding-free).
        sigma = shift_below_spectrum(ops)
        eps.setTarget(sigma)
        eps.setTolerances(tol, 1000)
        st = eps.getST()
        st.setType(SLEPc.ST.Type.SINVERT)
        direct_solver(st.getKSP(), PETSc.PC.Type.CHOLESKY)
        eps.setOptionsPrefix(prefix)
        with options_defaults(prefix, FACTOR_DEFAULTS):
            eps.setFromOptions()
        if inverse is not None:
            self._use_inverse(sigma, inverse)

    def _use_inverse(self, sigma: float, inverse) -> None:
        """Apply `inverse` as the ST's (K - sigma M)^-1 (a PCShell on the ST's KSP, implicit ST matrix)."""
        st, options = self.eps.getST(), PETSc.Options(self.prefix)
        near = lambda x: abs(complex(x).real - sigma) <= 1e-14 * max(abs(sigma), 1.0)  # noqa: E731
        if (st.getType() != SLEPc.ST.Type.SINVERT or not near(self.eps.getTarget())
                or (options.hasName("st_shift") and not near(options.getReal("st_shift")))):
            raise InputError(f"the shared-factorization DBF path needs shift-and-invert about {sigma:g} "
                             f"(-{self.prefix}eps_target, -{self.prefix}st_shift, -{self.prefix}st_type changed it); "
                             f"remove those options or use [basis] dbf_solver = \"factor\"")
        st.setShift(sigma)
        st.setMatMode(SLEPc.ST.MatMode.SHELL)
        ksp = st.getKSP()
        ksp.setType(PETSc.KSP.Type.PREONLY)
        pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(inverse)

    def solve(self, nev: int, what: str, ncv: int | None = None, least: int | None = None) -> tuple[np.ndarray, list]:
        """The nev lowest converged eigenpairs, sorted by eigenvalue (new Vecs, the caller's); ncv the
        code's default Krylov subspace size (None: SLEPc's); least (default nev): fewer converged than
        this is an error, between least and nev those converged are returned. Collective."""
        eps = self.eps
        options = PETSc.Options(self.prefix)  # keep the user's -eps_ncv, -eps_mpd (setDimensions resets them)
        eps.setDimensions(nev, options.getInt("eps_ncv", ncv or PETSc.DEFAULT),
                          options.getInt("eps_mpd", PETSc.DEFAULT))
        try:
            # MUMPS reads its inertia switches when it factors: the defaults stay for the solve.
            with options_defaults(self.prefix, FACTOR_DEFAULTS), frames_released():   # a PCShell inverse calls back
                eps.solve()
        except PETSc.Error as e:
            # red team: -modes_st_ksp_type cg was blamed on M and K alone
            raise SolverError(f"{what}: the eigensolver failed (PETSc error {e.ierr}); check that M is positive "
                              f"definite and K symmetric positive semi-definite, and check the -{self.prefix} options "
                              f"(shift-and-invert needs an exact solve: -{self.prefix}st_ksp_type preonly "
                              f"-{self.prefix}st_pc_type cholesky)") from None
        counters["eigen_solves"] += 1
        nconv = eps.getConverged()
        least = nev if least is None else least
        if nconv < least:
            nev = least
            _, M = eps.getOperators()
            n, massless = M.getSize()[0], _massless_rows(M)
            if massless and nev > n - massless:   # infinite eigenvalues: no iteration finds more
                raise InputError(f"{what}: {nev} modes asked for, but M has {massless} zero diagonal entries "
                                 f"(massless DOFs), so (K, M) has at most {n - massless} finite eigenvalues; ask for "
                                 f"fewer modes (only {nconv} converged)")
            raise SolverError(f"{what}: only {nconv} of {nev} eigenpairs converged; raise "
                              f"-{self.prefix}eps_max_it or loosen -{self.prefix}eps_tol")
        K, _ = eps.getOperators()
        values, vectors = [], []
        for i in range(nconv):
            x = K.createVecRight()
            values.append(complex(eps.getEigenpair(i, x)).real)
            vectors.append(x)
        order = np.argsort(values)[:nev]
        destroy(*(vectors[i] for i in set(range(nconv)) - set(order)))
        return np.asarray(values)[order], [vectors[i] for i in order]

    def converged_values(self) -> np.ndarray:
        """Every eigenvalue the last solve converged, sorted (often more than it was asked for). Collective."""
        return np.sort([complex(self.eps.getEigenvalue(i)).real for i in range(self.eps.getConverged())])

    def below_shift(self) -> int | None:
        """How many eigenvalues of (K, M) lie below the target, from the inertia of the factorized
        K - sigma M (Sylvester's law); None if the factorization cannot tell. Collective."""
        try:
            negative, _, _ = self.eps.getST().getKSP().getPC().getFactorMatrix().getInertia()
        except PETSc.Error:
            return None
        return int(negative)

    def destroy(self) -> None:
        try:
            self.eps.destroy()
        except PETSc.Error:  # a failed solve can leave the EPS half torn down
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.destroy()


def lowest_eigenpair(ops: Operators, K: PETSc.Mat, m: int, prefix: str, what: str, tol: float, inverse=None,
                     start: PETSc.Vec | None = None, ncv: int | None = None):
    """(lambda_m, phi_m): the m-th lowest eigenpair of (K, ops.M), phi not normalized; inverse as in
    LowestModes, start an initial vector of the Krylov space (or None), ncv as in solve. Collective."""
    with LowestModes(ops, K, prefix, tol, inverse) as solver:
        if start is not None:
            solver.eps.setInitialSpace([start])
        values, vectors = solver.solve(m, what, ncv)
    destroy(*vectors[:-1])
    return float(values[-1]), vectors[-1]


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


def _solve_reference(ops: Operators, count, max_frequency_hz, prefix: str):
    """(eigenvalues, vectors, eigenvalues below the shift, asked, seen): the `asked` lowest eigenpairs
    (`count`, or those below max_frequency_hz: on a beam of two planes whole y-z pairs), and `seen`,
    every eigenvalue the solve converged (often more than asked; _cut_by_values). Whether the cut
    falls inside a repeated eigenvalue is reference_modes' question, answered by the inertia where it
    can (_cut_by_inertia)."""
    n = ops.size
    with LowestModes(ops, ops.K, prefix) as solver:
        if count is not None:
            asked = count
            values, vectors = solver.solve(count, "reference modes")
        else:
            omega_max = 2 * np.pi * max_frequency_hz
            lam_max = omega_max * omega_max   # inf beyond double precision (a float's ** 2 raised OverflowError)
            nev = min(8, n)
            while True:
                values, vectors = solver.solve(nev, "reference modes")
                if values[-1] > lam_max or nev == n:
                    break
                destroy(*vectors)
                nev = min(2 * nev, n)
            asked = int(np.count_nonzero(values <= lam_max))
            # A beam of two planes has every frequency twice (y and z alike, equal to round-off): a cut
            # between the two keeps one in a direction set by round-off (basis.check_pairs), so keep both.
            pairs = getattr(ops.mesh, "planes", 1)
            if asked % pairs and asked < values.size:
                asked += pairs - asked % pairs
            if asked == 0:
                destroy(*vectors)
                raise InputError(f"no mode below max_frequency_hz = {max_frequency_hz} Hz "
                                 f"(the lowest is {np.sqrt(max(values[0], 0)) / (2 * np.pi):.6g} Hz)")
        below = solver.below_shift()
        seen = solver.converged_values()
    destroy(*vectors[asked:])
    return values[:asked], vectors[:asked], below, asked, seen


def _cut_by_values(ops: Operators, seen: np.ndarray, asked: int, prefix: str) -> tuple:
    """(first, whole) of the repeated eigenvalue at the cut after `asked` modes, as converged values
    show it (`seen`, sorted): the `first` eigenvalues lie below it, `whole` >= asked up to its end (rank
    0's on every rank). Where the last value seen belongs to it (or none lies beyond the cut), a solve
    for more, values only. For the rigid-body modes (zero to round-off, which the inertia cannot split)
    and where MUMPS cannot count (_cut_by_inertia gives None): a Krylov space may hold only part of a
    repeated eigenvalue. Collective."""
    n, comm, rigid = ops.size, ops.comm.tompi4py(), ops.rigid_modes
    whole = comm.bcast(whole_count(seen, asked, rigid), root=0)
    if whole >= seen.size and seen.size < n:
        try:
            with LowestModes(ops, ops.K, prefix) as solver:
                while whole >= seen.size and seen.size < n:
                    # massless DOFs may leave no more values (infinite ones)
                    more = min(max(whole + 1, 2 * seen.size), n)
                    destroy(*solver.solve(more, "reference modes beyond the cut", least=seen.size)[1])
                    if solver.eps.getConverged() <= seen.size:
                        break
                    seen = solver.converged_values()
                    whole = comm.bcast(whole_count(seen, asked, rigid), root=0)
        except Interrupted:   # a termination signal, not a check that could not be made
            raise
        except SolverError:   # the cut cannot be checked (a -modes_eps_ncv too small for more): as before
            whole = asked
    return cluster_start(seen, asked, rigid), whole


def count_below(ops: Operators, sigma: float) -> int | None:
    """How many eigenvalues of (K, M) lie below sigma: the negative pivots of K - sigma M factored by
    MUMPS (Sylvester's law of inertia; exact counts, unlike a Krylov solve, which may converge two of
    a triple eigenvalue's modes and go on to the next one: measured on three identical chains). None
    where the factorization cannot tell. Collective on ops.comm."""
    A = ops.K.duplicate(copy=True)
    ksp = PETSc.KSP().create(comm=ops.comm)
    try:
        A.axpy(-sigma, ops.M, PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        ksp.setOperators(A)
        direct_solver(ksp, PETSc.PC.Type.CHOLESKY)
        # the PC and its factor only through the KSP, no reference of ours: one that outlived the KSP
        # would park them in PETSc's garbage (petsc4py 3.18), a factor per reference_modes of a study
        ksp.getPC().setFactorSetUpSolverType()
        ksp.getPC().getFactorMatrix().setMumpsIcntl(13, 1)   # the inertia on every rank count (no ScaLAPACK root)
        ksp.getPC().getFactorMatrix().setMumpsIcntl(24, 1)   # a null pivot (sigma on an eigenvalue) is detected
        ksp.setUp()
        negative, _, _ = ksp.getPC().getFactorMatrix().getInertia()
        return int(negative)
    except PETSc.Error:
        return None
    finally:
        destroy(ksp, A)


def _cut_by_inertia(ops: Operators, values: np.ndarray, asked: int):
    """(first, whole) of the repeated eigenvalue around lam = values[asked - 1], the last of the asked
    lowest eigenvalues the solve returned: the eigenvalues below lam (1 - REPEATED_TOL) and below
    lam (1 + REPEATED_TOL), counted by count_below (rank 0's on every rank); (asked - 1, asked) where
    none is beyond the asked ones; None where the inertia is not available. A SolverError where the
    solve missed an eigenvalue below the repeated one (the returned ones are not the lowest)."""
    comm, lam = ops.comm.tompi4py(), float(values[asked - 1])
    whole = comm.bcast(count_below(ops, lam + REPEATED_TOL * abs(lam)), root=0)
    if whole is None or whole <= asked:
        return None if whole is None else (asked - 1, asked)
    first = comm.bcast(count_below(ops, lam - REPEATED_TOL * abs(lam)), root=0)
    returned = int(np.count_nonzero(values[:asked] < lam - REPEATED_TOL * abs(lam)))
    if first is not None and first != returned:
        missed = SolverError(f"reference modes: the eigensolver returned {returned} eigenvalues below "
                             f"{np.sqrt(max(lam, 0.0)) / (2 * np.pi):.6g} Hz where (K, M) has {first} (a repeated "
                             f"eigenvalue's modes missed); raise -modes_eps_ncv or tighten -modes_eps_tol")
        missed.frequency_hz = np.sqrt(np.clip(values[:asked], 0.0, None)) / (2 * np.pi)   # basis._units_hint
        raise missed
    return (returned if first is None else first), whole


def _repeated_cut(ops: Operators, lam: float, count: int, first: int, end: int) -> RepeatedCut:
    """The refusal of `count` modes that end inside the repeated eigenvalue lam of modes first + 1 to end."""
    what = ("zero frequency, the rigid-body modes" if count <= ops.rigid_modes else
            f"one repeated frequency, {np.sqrt(max(lam, 0.0)) / (2 * np.pi):.6g} Hz")
    counts = f"{first} or {end}" if first else f"{end}"
    return RepeatedCut(f"[basis] modes = {count} keeps {count - first} of the {end - first} modes of {what} (modes "
                       f"{first + 1} to {end}: any mix of their directions, so those kept lie in a direction set by "
                       f"round-off, and the reduced model changes with it); give {counts} modes, or "
                       f"max_frequency_hz", first, end)


def _absolute(A: PETSc.Mat) -> PETSc.Mat:
    """|A| entry by entry, with A's layout. Collective."""
    indptr, cols, vals = A.getValuesCSR()
    B = PETSc.Mat().createAIJ(size=A.getSizes(), csr=(indptr, cols, np.abs(vals)), comm=A.getComm())
    B.assemble()
    return B


def accuracy(ops: Operators, values, vectors) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(estimate, residual, scale) of each M-normalized eigenpair (lambda_j, x_j) of (ops.K, ops.M):
    estimate = u |x|^T |K| |x| / scale and residual = ||K x - lambda M x|| / (scale ||M x||) (module
    docstring), relative to scale = |lambda_j|, or for a rigid-body mode (lambda ~ 0) the lowest
    elastic eigenvalue among `values` (else eigen_scale). Collective; every rank gets rank 0's numbers."""
    values = np.asarray(values, dtype=float)
    elastic = values[ops.rigid_modes:]
    reference = elastic[0] if elastic.size and elastic[0] > 0 else ops.eigen_scale
    scale = np.abs(values)
    scale[:ops.rigid_modes] = np.maximum(scale[:ops.rigid_modes], reference)
    absK = _absolute(ops.K)
    t, Kx, Mx = ops.K.createVecLeft(), ops.K.createVecLeft(), ops.K.createVecLeft()
    estimate, residual = np.full(values.size, np.inf), np.full(values.size, np.inf)
    for j, (lam, x) in enumerate(zip(values, vectors)):
        x.copy(t)
        t.abs()
        absK.mult(t, Kx)
        quadratic = t.dot(Kx)                       # |x|^T |K| |x|
        ops.K.mult(x, Kx)
        ops.M.mult(x, Mx)
        Kx.axpy(-lam, Mx)
        r, m = Kx.norm(), Mx.norm()
        if scale[j] > 0:
            estimate[j] = 0.5 * np.finfo(float).eps * quadratic / scale[j]
            if m > 0:
                residual[j] = r / (scale[j] * m)
    destroy(absK, t, Kx, Mx)
    # Reductions may round differently on different ranks: take rank 0's numbers, so that every rank
    # decides alike.
    estimate, residual = ops.comm.tompi4py().bcast((estimate, residual), root=0)
    return estimate, residual, scale


def trust_check(ops: Operators, values, estimate, residual, prefix: str = "modes_") -> None:
    """Refuse eigenpairs that cannot be trusted to TRUST_TOL (module docstring), given accuracy()'s
    estimate and residual: an InputError naming the largest trustworthy mesh (beams) or the
    ill-conditioning (matrices), or a SolverError for a residual the round-off does not explain.
    Every rank takes the same path (the numbers are the same on every rank)."""
    tol = PETSc.Options(prefix).getReal("trust_tol", TRUST_TOL)
    j = int(np.argmax(estimate))
    if estimate[j] > tol:
        f = np.sqrt(max(values[j], 0.0)) / (2 * np.pi)
        cause = (f"rounding may change the eigenvalue of mode {j + 1} ({f:.6g} Hz) by up to {estimate[j]:.1e} "
                 f"relative (condition number {estimate[j] / (0.5 * np.finfo(float).eps):.1e}), more than the "
                 f"{tol:g} allowed")
        if ops.mesh is not None:
            elements = ops.mesh.beam.elements
            limit = _element_limit(ops, j + 1, estimate[j], tol, prefix)
            beam = ops.mesh.beam
            # red team: a tension of -0.99996 P_cr blamed the mesh alone, and the compression had softened mode 1
            softened = (f"; the axial compression (tension - m_t U^2 = {beam.axial_force:.6g} N) softens the lowest "
                        f"modes, the more the nearer the buckling load (or the critical speed): a compression "
                        f"farther from it also helps" if beam.axial_force < 0 else "")
            raise InputError(f"reference modes: the beam mesh is too fine for double precision: {cause}; "
                             f"use at most ~{limit} elements, not {elements} (or raise -{prefix}trust_tol){softened}")
        if estimate[j] > 1:   # the eigenvalue is zero within its own rounding
            raise InputError(f"reference modes: K is singular: eigenvalue {j + 1} ({values[j]:.3g}) is zero within "
                             f"rounding, so the structure has rigid-body modes (it is not fully supported) or a "
                             f"mechanism; apply the supports to K and M (remove the fixed DOFs)")
        raise InputError(f"reference modes: K is too ill-conditioned for double precision: {cause}; use a "
                         f"coarser model (or raise -{prefix}trust_tol)")
    j = int(np.argmax(residual))
    if residual[j] > np.sqrt(tol):
        singular = (", or K is singular (rigid-body modes: a structure not fully supported, whose factorization "
                    "at 0 is garbage): apply the supports to K and M" if ops.mesh is None and not ops.rigid_modes
                    else "")
        raise SolverError(f"reference modes: eigenpair {j + 1} has relative residual {residual[j]:.1e} "
                          f"> {np.sqrt(tol):.1e}: the eigensolver's answer is not an eigenpair of (K, M); "
                          f"check -{prefix}eps_tol (a looser stopping test than the default 1e-10) and the "
                          f"-{prefix}st_ solver options (an exact factorization is needed){singular}")


def _element_limit(ops: Operators, count: int, estimate: float, tol: float, prefix: str) -> int:
    """The largest element count of ops' beam whose lowest `count` eigenvalues pass TRUST_TOL, with
    10 % to spare: the estimate grows like elements^4. On a mesh too fine the eigenvalue itself is
    wrong (too high), so measure the estimate on a coarse mesh of the same beam (same solver options).
    Collective."""
    import dataclasses

    from .structure import assemble_beam

    elements = ops.mesh.beam.elements
    if elements > COARSE_ELEMENTS:
        coarse = assemble_beam(dataclasses.replace(ops.mesh.beam, elements=COARSE_ELEMENTS), comm=ops.comm)
        count = min(count, coarse.size)
        vectors = []
        try:
            with LowestModes(coarse, coarse.K, prefix) as solver:
                values, vectors = solver.solve(count, "reference modes of a coarse mesh")
            for x in vectors:
                normalize(x, coarse.M)
            estimate = float(np.max(accuracy(coarse, values, vectors)[0]))
            elements = COARSE_ELEMENTS
        except Interrupted:   # a termination signal, not a coarse mesh that failed
            raise
        except DbfError:
            pass    # keep the fine mesh's (optimistic) estimate
        finally:
            destroy(*vectors)
            coarse.destroy()
    return _two_digits_down(0.9 * elements * (tol / estimate) ** 0.25)


def _two_digits_down(x: float) -> int:
    """x rounded down to two significant digits (at least 1)."""
    if x < 1:
        return 1
    step = 10 ** max(int(np.floor(np.log10(x))) - 1, 0)
    return int(x // step * step)


def _check_definite(ops: Operators, values, negative, estimate, scale) -> None:
    """An InputError for an indefinite K: negative pivots, or a clearly negative eigenvalue (rigid-body
    modes are zero to round-off, up to estimate * scale)."""
    if negative:
        raise InputError(f"the stiffness matrix is not positive semi-definite ({negative} eigenvalue(s) "
                         f"below zero); check K and its boundary conditions")
    if values[0] < -(1e-8 * max(abs(values[-1]), ops.eigen_scale) + estimate[0] * scale[0]):
        raise InputError(f"the stiffness matrix is not positive semi-definite (eigenvalue {values[0]:.3g}); "
                         f"check K and its boundary conditions")


def reference_modes(ops: Operators, count: int | None = None, max_frequency_hz: float | None = None,
                    prefix: str = "modes_", whole: str = "extend") -> ModalBasis:
    """The lowest reference modes: `count` of them, or every mode below `max_frequency_hz`.

    A repeated eigenvalue (REPEATED_TOL; a round tube's y-z pairs, a square bar's bending pairs, the
    rigid-body modes) is kept whole: its modes are any mix of its eigenspace, so part of them is a
    direction set by round-off, and a reduced model on it changes with the rank count. Where `count`
    ends inside one, whole = "refuse" raises RepeatedCut (an InputError naming the frequency and the
    counts that keep it whole: the user's [basis] modes, build_basis), "extend" (the default) returns
    the modes up to its end (the estimate's richer bases; an odd count on a beam of two planes is
    rounded up to whole y-z pairs before the solve, which would otherwise find the pair cut and
    solve again). Below max_frequency_hz the repeated eigenvalue at the cutoff is kept whole.

    Collective on ops.comm. Raises SolverError if the solver converges fewer pairs than needed,
    refuses pairs that cannot be trusted to TRUST_TOL (trust_check), and an indefinite K.
    """
    if whole not in ("refuse", "extend"):
        raise ValueError(f"reference_modes whole: 'refuse' or 'extend', got {whole!r}")
    if (count is None) == (max_frequency_hz is None):
        raise InputError("give the number of modes or a maximum frequency, not both")
    n = ops.size
    if count is not None and not 1 <= count <= n:
        raise InputError(f"number of modes must be between 1 and {n} (the free DOFs), got {count}")
    if max_frequency_hz is not None and not max_frequency_hz > 0:
        raise InputError(f"max_frequency_hz must be positive, got {max_frequency_hz}")
    if count is not None and whole == "extend":   # a beam of two planes: every frequency a y-z pair, known before
        count = min(count + -count % getattr(ops.mesh, "planes", 1), n)
    values, vectors, negative, asked, seen = _solve_reference(ops, count, max_frequency_hz, prefix)
    bv = None
    try:
        for x in vectors:
            normalize(x, ops.M)
        estimate, residual, scale = accuracy(ops, values, vectors)
        # First whether double precision can answer at all: rounding in a K too ill-conditioned also
        # shows as negative pivots or eigenvalues.
        trust_check(ops, values, estimate, residual, prefix)
        _check_definite(ops, values, negative, estimate, scale)
        # then whether the cut falls inside a repeated eigenvalue (trusted pairs only: about an eigenvalue
        # of an inexact solve the counts mean nothing)
        cut = None if asked <= ops.rigid_modes else _cut_by_inertia(ops, values, asked)
        first, end = cut if cut is not None else _cut_by_values(ops, seen, asked, prefix)
        if end > asked and count is not None and whole == "refuse":
            raise _repeated_cut(ops, float(values[asked - 1]), asked, first, end)
        if end > asked:   # the modes up to the repeated eigenvalue's end, checked alike
            destroy(*vectors)
            vectors = []
            return reference_modes(ops, count=end, prefix=prefix, whole="extend")
        bv = SLEPc.BV().create(comm=ops.comm)
        bv.setSizesFromVec(vectors[0], len(vectors))
        bv.setType(SLEPc.BV.Type.SVEC)
        for j, x in enumerate(vectors):
            bv.insertVec(j, x)
    except Exception:
        destroy(bv)
        raise
    finally:
        destroy(*vectors)
    bv.setMatrix(ops.M, False)
    return ModalBasis(omega=np.sqrt(np.clip(values, 0.0, None)), vectors=bv)
