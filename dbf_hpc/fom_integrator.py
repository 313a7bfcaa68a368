"""Time integration of the full-order model (fom.py): the reference the reduced model is measured
against. Generalized-alpha with ONE factorization per step size and the contact condensed onto the
N_L constraint DOFs, in a loop of its own over distributed PETSc vectors.

    M u'' + C u' + K u = f(t) + G N(G^T u + r_c Omega(t), G^T u' + r_c Omega'(t))

The scheme is PETSc's TSALPHA2 (Chung & Hulbert 1993, in the form of Jansen, Whiting & Hulbert;
src/ts/impls/implicit/alpha/alpha2.c), with the spectral radius at infinity rho (-full_alpha_radius,
default 0.9, as -full_ts_alpha_radius before):

    a_m = (2 - rho)/(1 + rho), a_f = 1/(1 + rho), gamma = 1/2 + a_m - a_f, beta = (1 + a_m - a_f)^2 / 4

and the equation holds at the generalized mid-point t_a = t_n + a_f h:

    M A_a + C V_a + K X_a = f(t_a) + G N(G^T X_a + r_c Omega(t_a), G^T V_a + r_c Omega'(t_a))
    X_a = X0 + a_f (X1 - X0), V_a = V0 + a_f (V1 - V0), A_a = A0 + a_m (A1 - A0)

Written for the correction d to the Newmark predictor X~ = X0 + h V0 + h^2 (1/2 - beta) A0,
X1 = X~ + d, A1 = d / (beta h^2), V1 = V0 + h (1 - gamma) A0 + gamma h A1, and divided by a_f, it is
linear in d but for the contact term:

    K_eff d = b_n + G lambda,   K_eff = K + s_V C + s_A M,  s_V = gamma/(beta h),  s_A = a_m/(a_f beta h^2)
    b_n = -(1/a_f) [(1 - a_m) M A0 + C V_a0 + K X_a0 - f(t_a)],  lambda = N(z_a, v_a) / a_f
    X_a0 = X0 + a_f (h V0 + h^2 (1/2 - beta) A0),  V_a0 = V0 + a_f h (1 - gamma) A0

(A1 comes from d itself, not from the difference of nearly equal X1 - X0 - h V0, which keeps the
round-off at TSALPHA2's level.) K_eff is factored once per step size; with Y = K_eff^-1 G (N_L
solves per factorization) and the Delassus operator D = G^T Y (N_L x N_L), a step is

    1. d_free = K_eff^-1 b_n, X1 = X~ + d_free        the step's one solve
    2. y_free = G^T X1                                 N_L values (one Allreduce in parallel)
    3. if every law is force-free at the mid-point of y_free (and was at the previous step):
       lambda = 0, no law is evaluated. Otherwise Newton on the N_L unknowns y = G^T X1,
       r(y) = y - y_free - D N(z_a(y), v_a(y)) / a_f = 0, J = I - D diag(N_z + s_V N_v), with the
       laws' exact derivatives (ContactStep, ContactNewton)
    4. d += Y lambda, X1 += Y lambda                   the correction, without a solve
    5. V1, A1 from d                                   vector updates

Why a loop of its own and not PETSc TS: TS (ALPHA2 with I2Function/I2Jacobian) cannot keep one
factorization while the contact changes the Jacobian, its start procedure factors a second matrix,
it has no dense output, and its per-step machinery alone costs more than the whole step here
(docs/design.md gives the measurements).

Start: the acceleration at t = 0 from the equation of motion, M A0 = f(0) - K X0 - C V0 + G N(z0, v0)
(solved with M, options prefix full_mass_); from rest with no load and no contact force at t = 0,
A0 = 0 with no solve. This is the consistent start of Chung & Hulbert, not PETSc's (two backward
Euler half steps whose acceleration, in PETSc 3.18, is twice the backward-difference estimate).

Factorization (options prefix full_): KSP preonly + Cholesky (LU when a gyroscopic G, skew, makes
K_eff = K + s_V (C + G) + s_A M unsymmetric); on one rank PETSc's own Cholesky or LU in the natural
ordering when it keeps the fill small (a beam: its solve costs microseconds, MUMPS's hundreds of
microseconds), MUMPS otherwise; in parallel that Cholesky runs on every rank at once (PCREDUNDANT),
and an LU is always MUMPS's. Any -full_ksp_/-full_pc_ option overrides;
every factorization is checked by the residual of its N_L solves and of a load on every DOF, so an
inexact solver is an error, never a wrong result.

Samples are cubic Hermite interpolants of (u, u') between the two steps around each sample time
(third order, above the scheme's second), so output never shortens a step. Statistics go to the
caller in blocks of steps. Everything here is collective on the model's communicator; the N_L-sized
contact problem is solved on rank 0 and broadcast, so every rank takes the same branch.
"""
from __future__ import annotations

import bisect
import math
import time

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .errors import TERMINATION, WRITE_ERRORS, InputError, SolverError, WriteFailed, from_rank0, write_failure
from .fom import FullOrderModel
from .petsctools import destroy, natural_fill_is_small, options_defaults
from .timestepping import LAW_SCALES, IntegratorSettings, StepMonitor, check_outcome

# The laws whose force has a kink at a clearance (or a table's breakpoints): each contact that closes there
# sets the contact's own oscillation ringing, which a step must resolve (a linear, cubic or friction law is
# smooth: an implicit step that does not resolve a stiff spring damps it, as it should)
KINKED = ("deadband", "power", "hertz", "table", "circular", "flat_bar")
PREFIX = "full_"
WHAT = "full-order integration"
ADVICE = "reduce [integrator] dt"
NOT_FINITE = ("check the excitation, the initial state and the laws for values beyond double precision, or "
              "reduce [integrator] dt")
BLOCK = 256          # steps between control points at most (statistics handed over, checkpoints, stop)
DIFFERENT = PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN
EXACT_SOLVE = 1e-8   # relative residual a factorization's solves must reach


# -- the scheme ------------------------------------------------------------------------------------

class Alpha2:
    """Generalized-alpha parameters from rho, the spectral radius at infinity (PETSc's
    TSAlpha2SetRadius conventions)."""

    def __init__(self, rho: float = 0.9):
        self.rho = rho
        self.am = (2 - rho) / (1 + rho)
        self.af = 1 / (1 + rho)
        self.gamma = 0.5 + self.am - self.af
        self.beta = 0.25 * (1 + self.am - self.af) ** 2

    def shifts(self, h: float):
        """(s_V, s_A): dV_a/dX1 and dA_a/dX1 divided by a_f (PETSc's shift_V, shift_A)."""
        return self.gamma / (h * self.beta), self.am / (self.af * h * h * self.beta)


def options() -> dict:
    """The -full_ options the loop reads itself: the spectral radius, checked. -full_ts_* and
    -full_snes_* options (PETSc TS/SNES, which this integrator does not use) are refused by name,
    except -full_ts_alpha_radius, the old name of -full_alpha_radius."""
    opts = PETSc.Options(PREFIX)
    names = [k for k in PETSc.Options().getAll() if k.startswith(PREFIX)]
    for name in names:
        short = name[len(PREFIX):]
        if (short.startswith("ts_") or short.startswith("snes_")) and short != "ts_alpha_radius":
            raise InputError(f"-{name}: the full-order reference steps with its own generalized-alpha loop at the "
                             f"fixed step [integrator] dt, not PETSc TS/SNES; remove the option (its solver options "
                             f"are -full_ksp_*, -full_pc_*, -full_alpha_radius)")
    rho = 0.9
    for name in ("alpha_radius", "ts_alpha_radius"):
        if opts.hasName(name):
            text = opts.getString(name)
            try:
                rho = float(text)
            except ValueError:
                raise InputError(f"-full_{name} {text!r} is not a number; give the spectral radius at infinity in "
                                 f"[0, 1] (default 0.9)") from None
            if not 0.0 <= rho <= 1.0:
                raise InputError(f"-full_{name} {text}: the spectral radius at infinity lies in [0, 1] "
                                 f"(1: no numerical dissipation, 0: the most; default 0.9)")
            break
    return {"rho": rho}


def step_count(t_end: float, dt: float) -> tuple[int, float]:
    """(number of steps, length of the last step): steps of dt, the last one shortened to end at
    t_end (or taken as dt when t_end / dt is a whole number to a relative 1e-9)."""
    ratio = t_end / dt
    whole = round(ratio)
    if whole >= 1 and abs(ratio - whole) <= 1e-9 * max(ratio, 1.0):
        return whole, dt
    count = math.ceil(ratio)
    return count, t_end - (count - 1) * dt


# The shortest step the full-order loop takes (s). Its shifts grow as 1 / h^2: red team, t_end = dt = 1e-200 s
# (or t_end = 1e-200 s alone) ended as an internal ZeroDivisionError (h^2 underflowed to 0), and 1e-100 s as
# "the solve with K_eff ... is not finite: check K, M and C", with a half-written output. No structure moves
# on such a scale (atoms vibrate over 1e-13 s); 1e-30 s to 1e-80 s ran right, 1e-30 s keeps a margin.
MIN_STEP = 1e-30


def check_step(settings) -> None:
    """An InputError, before any work, when a step of the fixed-step loop (dt, or the last one, which
    ends at t_end) is shorter than MIN_STEP. Not collective (the settings are every rank's)."""
    steps, h_last = step_count(settings.t_end, settings.dt)
    h = min(settings.dt, h_last) if steps > 1 else h_last
    if not h >= MIN_STEP:
        raise InputError(f"--method full: a step of {h:g} s ([integrator] dt = {settings.dt:g} s over t_end = "
                         f"{settings.t_end:g} s) is below {MIN_STEP:g} s, shorter than anything a structure does, "
                         f"and the step's shifts 1 / h^2 leave double precision: give dt and t_end of at least "
                         f"{MIN_STEP:g} s")


# The reduced model's settings the full-order loop does not read, with what it does instead: a user who set one
# (a tighter rtol, another scheme, [basis] tolerance) would take it for the reference's accuracy or scheme (red
# team: --method full with rtol = 1e-9, scheme 4, contact = "explicit" and tolerance = 0.01 ran at its fixed
# step with no word). The keys that define the reduced basis ([basis] modes, enrichment, dbf_*, ...) are not
# listed: a full-order run has no basis, which no user takes for anything else, and every shipped scene sets them.
def ignored_settings(values: dict, dt: float, who: str, section: dict) -> list:
    """One line per reduced-model setting in `values` ({key: value}, the ones a user set) that the
    full-order run `who` ("--method full", "simulate_full") ignores, naming what it uses instead;
    `section` maps a key to how the user wrote it ("[integrator] rtol", "IntegratorSettings rtol")."""
    fixed = f"fixed steps of {section.get('dt', 'dt')} = {dt:g} s"
    uses = {
        "rtol": f"it takes {fixed}: halve dt to see its error (its estimate compares a step 4 times shorter)",
        "atol": f"it takes {fixed}: halve dt to see its error (its estimate compares a step 4 times shorter)",
        "max_step_scale": f"it takes {fixed}",
        "scheme": "it integrates with generalized-alpha (-full_alpha_radius)",
        "contact": "it solves the contact implicitly at every step (Newton condensed on the constraint DOFs)",
        "callbacks": "it steps in its own loop over PETSc vectors",
        "tolerance": f"its error is the step's, set by {section.get('dt', 'dt')} = {dt:g} s (the run's estimated error "
                     f"compares a step 4 times shorter)",
        "estimate_statistics_window": "it estimates no statistics error (its estimate compares w over "
                                      "estimate_window)",
    }
    out = []
    for key, value in values.items():
        if key == "adaptive":
            if value:
                out.append(f"{section[key]} = true is the reduced model's; {who} ignores it: it takes {fixed}")
            continue
        shown = f'"{value}"' if isinstance(value, str) else f"{value:g}"
        out.append(f"{section[key]} = {shown} is the reduced model's; {who} ignores it: {uses[key]}")
    return out


# -- the distributed side: rows, factorizations ----------------------------------------------------

class ConstraintRows:
    """Global rows, this rank's share of them, and their values gathered on every rank."""

    def __init__(self, vec: PETSc.Vec, rows, views: dict | None = None):
        self.views = views or {}     # Vec handle -> local array, for vectors that outlive this object
        self.rows = np.asarray(rows, dtype=np.int64)
        self.n = self.rows.size
        lo, hi = vec.getOwnershipRange()
        self.mine = np.flatnonzero((self.rows >= lo) & (self.rows < hi))
        self.local = (self.rows[self.mine] - lo).astype(np.intp)
        self.comm = vec.getComm().tompi4py()
        self.parallel = self.comm.size > 1

    def gather(self, vecs) -> np.ndarray:
        """(len(vecs), n): each Vec at the rows, on every rank (one Allreduce in parallel)."""
        if not self.parallel:
            return np.array([self._view(v)[self.local] for v in vecs])
        out = np.zeros((len(vecs), self.n))
        for i, v in enumerate(vecs):
            out[i, self.mine] = self._view(v)[self.local]
        self.comm.Allreduce(MPI.IN_PLACE, out)
        return out

    def _view(self, vec: PETSc.Vec) -> np.ndarray:
        """The local array of `vec`: the kept view of one of `views`' vectors (a Vec keeps its
        array in place for its lifetime), else a fresh one."""
        view = self.views.get(vec.handle)
        return view if view is not None else vec.getArray(readonly=True)


def factorization(A: PETSc.Mat, prefix: str, symmetric: bool = True) -> dict:
    """The default factorization of an SPD matrix (options under `prefix`): PETSc's own Cholesky in
    the natural ordering when that keeps the fill small (a beam: a solve costs microseconds), on
    every rank at once in parallel (PCREDUNDANT: MUMPS's solve of a small distributed system costs
    milliseconds); MUMPS's Cholesky otherwise, and whenever the user set a -<prefix>pc_, ksp_ or
    mat_ option (which then applies to the distributed factorization, as they expect). Collective."""
    user = any(k.startswith(tuple(prefix + p for p in ("pc_", "ksp_", "mat_"))) for k in PETSc.Options().getAll())
    if not symmetric:   # a gyroscopic K_eff (issue 19): LU, PETSc's own on one rank, else MUMPS
        # PETSc's own LU in the natural ordering only (red team: in its default nested-dissection
        # ordering, PETSc 3.18 factored a K_eff whose G adds entries outside K's pattern wrongly, 1.5e-4
        # off on a 3-DOF rotor, and the full-order reference was silently 0.4 % to 100 % wrong).
        if A.getComm().getSize() == 1 and not user and natural_fill_is_small(A):
            return {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "petsc",
                    "pc_factor_mat_ordering_type": "natural", "pc_factor_zeropivot": "0.0"}
        return {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}
    if not user and natural_fill_is_small(A):
        # PETSc's own factorization calls a pivot below 1e-12 zero (an absolute tolerance): a fine beam's
        # rotational masses are 3e-14 kg m^2 at 1000 elements. Only an exact 0 is a zero pivot here.
        native = {"pc_factor_mat_solver_type": "petsc", "pc_factor_mat_ordering_type": "natural",
                  "pc_factor_zeropivot": "0.0"}
        if A.getComm().getSize() == 1:
            return {"ksp_type": "preonly", "pc_type": "cholesky", **native}
        return {"ksp_type": "preonly", "pc_type": "redundant", "redundant_ksp_type": "preonly",
                "redundant_pc_type": "cholesky", **{f"redundant_{k}": v for k, v in native.items()}}
    return {"ksp_type": "preonly", "pc_type": "cholesky", "pc_factor_mat_solver_type": "mumps"}


class EffectiveSystem:
    """K_eff = K + s_V C + s_A M for one step size, factored once (KSP, prefix full_); the columns
    Y = K_eff^-1 G and D = G^T Y. Collective."""

    def __init__(self, K, M, C, params: Alpha2, h: float, crow: ConstraintRows, symmetric_positive: bool):
        started = time.perf_counter()
        self.h = h
        self.sV, self.sA = params.shifts(h)
        self.A = self.ksp = self.factor = None
        self.Y = []
        try:
            A = K.duplicate(copy=True)
            self.A = A
            A.axpy(self.sA, M, DIFFERENT)
            if C is not None:
                A.axpy(self.sV, C, DIFFERENT)
            if symmetric_positive:   # with a gyroscopic G (skew) K_eff is not symmetric: LU
                A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
                A.setOption(PETSc.Mat.Option.SPD, True)
            self.ksp, self.factor, self.solve, self.description = _factored(
                A, factorization(A, PREFIX, symmetric_positive), PREFIX, "the step's matrix K_eff")
            self.t_factor = time.perf_counter() - started
            lo, hi = A.getOwnershipRange()
            e = A.createVecLeft()
            try:
                for r in crow.rows:
                    e.zeroEntries()
                    if lo <= r < hi:
                        e.setValue(int(r), 1.0)
                    e.assemble()
                    y = A.createVecRight()
                    self.Y.append(y)
                    self.solve(e, y)
                for r, y in zip(crow.rows, self.Y):
                    _check_exact(A, y, int(r), self.description)
                # and a load on every DOF: a factor wrong away from the constraint rows (a row
                # uncoupled from them) passes their checks
                _check_exact_dense(A, self.solve, self.description)
            finally:
                e.destroy()
            # D[i, j] = Y_j at row i: exactly what the correction X1 += Y lambda adds at the rows.
            self.D = crow.gather(self.Y).T.copy() if crow.n else np.zeros((0, 0))
        except Exception:
            self.destroy()
            raise
        self.t_setup = time.perf_counter() - started

    def destroy(self) -> None:
        destroy(self.factor, self.ksp, self.A, *self.Y)
        self.ksp = self.A = self.factor = None
        self.Y = []


def _factored(A: PETSc.Mat, defaults: dict, prefix: str, what: str):
    """(ksp, factor, solve, description): a KSP set up on A with the code's `defaults`
    (factorization()) under `prefix`, the user's options winning; our reference to its factored
    matrix, or None; the fastest exact solve it offers (the factor's MatSolve for a plain
    factorization); a description. The caller destroys factor and ksp (a factor reference Python
    drops after the KSP is gone is parked in PETSc's garbage by petsc4py 3.18: a leak in a long
    process). PETSc errors become one-line SolverErrors."""
    ksp = PETSc.KSP().create(comm=A.getComm())
    factor = None
    try:
        ksp.setOperators(A)
        with options_defaults(prefix, defaults):
            ksp.setOptionsPrefix(prefix)
            ksp.setFromOptions()
            try:
                ksp.setUp()
            except PETSc.Error as e:
                raise SolverError(f"cannot factor {what} (PETSc error {e.ierr}): check the -{prefix}ksp_/-{prefix}pc_ "
                                  f"options (a direct solver: -{prefix}pc_type cholesky or lu, "
                                  f"-{prefix}pc_factor_mat_solver_type mumps, superlu_dist or petsc on one rank)") from None
        pc = ksp.getPC()
        kind, pc_type = ksp.getType(), pc.getType()
        if kind == "preonly" and pc_type in ("lu", "cholesky"):
            factor = pc.getFactorMatrix()
            solver = pc.getFactorSolverType()
            description = f"{solver} {pc_type}"
            solve = factor.solve
        else:
            description = f"KSP {kind} + PC {pc_type}"
            if pc_type == "redundant":
                options = PETSc.Options(prefix)
                inner = (options.getString("redundant_pc_factor_mat_solver_type", defaults.get(
                         "redundant_pc_factor_mat_solver_type", "?")), options.getString(
                         "redundant_pc_type", defaults.get("redundant_pc_type", "lu")))
                description = f"{inner[0]} {inner[1]} on every rank (redundant)"

            def solve(b, x):
                ksp.solve(b, x)
                if ksp.getConvergedReason() < 0:
                    raise SolverError(f"the -{prefix}ksp_type {kind} solve with {what} did not converge (reason "
                                      f"{ksp.getConvergedReason()}); use a direct solver (-{prefix}ksp_type preonly "
                                      f"-{prefix}pc_type cholesky) or tighten -{prefix}ksp_rtol")
        return ksp, factor, solve, description
    except Exception:
        destroy(factor, ksp)
        raise


def _check_exact(A: PETSc.Mat, x: PETSc.Vec, row: int, description: str) -> None:
    """x solves A x = e_row: it must, to EXACT_SOLVE in residual (a solver that is not exact would
    give a wrong reference, not an error). Collective."""
    r = A.createVecLeft()
    try:
        A.mult(x, r)
        lo, hi = r.getOwnershipRange()
        if lo <= row < hi:
            r.setValue(row, -1.0, addv=PETSc.InsertMode.ADD_VALUES)
        r.assemble()
        residual = r.norm()
    finally:
        r.destroy()
    _refuse_inexact(residual, description, "a unit load")


def _check_exact_dense(A: PETSc.Mat, solve, description: str) -> None:
    """A solve of b = A z, z_i = 1 + (i mod 7) / 7 (every DOF loaded) returns z to EXACT_SOLVE in
    relative residual. Collective."""
    z, b, x = A.createVecRight(), A.createVecLeft(), A.createVecRight()
    try:
        lo, hi = z.getOwnershipRange()
        z.array[:] = 1.0 + (np.arange(lo, hi) % 7) / 7.0
        A.mult(z, b)
        scale = b.norm()
        solve(b, x)
        A.mult(x, z)
        z.axpy(-1.0, b)
        residual = z.norm() / scale if scale > 0 else z.norm()
    finally:
        destroy(z, b, x)
    _refuse_inexact(residual, description, "a load on every DOF")


def _refuse_inexact(residual: float, description: str, load: str) -> None:
    """A SolverError unless the relative residual of a check solve (on `load`) is finite and at most
    EXACT_SOLVE. Not collective (every rank has the same residual)."""
    if not math.isfinite(residual):
        # red team: [damping] rayleigh_alpha or rayleigh_beta = 1e300 (finite K, M) read "check K, M and C for entries
        # that are not finite", with nothing to find there
        raise SolverError(f"the solve with K_eff = K + s_V C + s_A M ({description}) is not finite: check K, M and C "
                          f"for entries that are not finite or beyond double precision once scaled by the step's "
                          f"shifts (s_V ~ 1 / dt, s_A ~ 1 / dt^2): with Rayleigh damping C = alpha M + beta K, "
                          f"[damping] rayleigh_alpha and rayleigh_beta")
    if not residual <= EXACT_SOLVE:
        raise SolverError(f"the -{PREFIX} solver ({description}) is not exact: relative residual {residual:.2e} on "
                          f"{load}; use a direct factorization (-{PREFIX}ksp_type preonly -{PREFIX}pc_type lu "
                          f"-{PREFIX}pc_factor_mat_solver_type mumps) or an iterative -{PREFIX}ksp_type with "
                          f"-{PREFIX}ksp_rtol 1e-12")


# -- the contact problem on the N_L constraint DOFs ------------------------------------------------

class FreeIntervals:
    """Where each law gives N = 0 for every velocity (a deadband with its edges, a table's zero
    run): [lo, hi] per constraint, empty (lo > hi) for laws that always push. A step whose
    mid-point lies inside every interval needs no law evaluation at all. A round hole (2-D, per
    component y, z) screens with the square inscribed in it, |y|, |z| <= c / sqrt(2); flat bars with
    the square inside their strip."""

    def __init__(self, laws):
        lo, hi = [], []
        for law in laws.laws:
            a, b = math.inf, -math.inf
            if law.kind in ("circular", "flat_bar"):
                if law.kind == "circular":
                    half = law.clearance / math.sqrt(2.0)
                else:   # the square inside the strip |u.e| <= c
                    angle = math.radians(law.angle)
                    half = law.clearance / (abs(math.cos(angle)) + abs(math.sin(angle)))
                lo += [-half, -half]
                hi += [half, half]
                continue
            if law.kind in ("deadband", "power", "hertz"):
                a = -law.clearance_minus if law.k_minus > 0 else -math.inf
                b = law.clearance_plus if law.k_plus > 0 else math.inf
            elif law.kind == "table":
                a, b = _table_zero_run(law.table)
            lo.append(a)
            hi.append(b)
        self.lo, self.hi = lo, hi
        self.any = any(a <= b for a, b in zip(lo, hi))


def _table_zero_run(table) -> tuple[float, float]:
    """The longest interval where a table's force is 0 (between consecutive zero points; open-ended
    when the zero run reaches an end, since the end segments extend)."""
    z = [p[0] for p in table]
    f = [p[1] for p in table]
    best, i = (math.inf, -math.inf), 0
    while i < len(f):
        if f[i] != 0:
            i += 1
            continue
        j = i
        while j + 1 < len(f) and f[j + 1] == 0:
            j += 1
        if j > i:
            a = -math.inf if i == 0 else z[i]
            b = math.inf if j == len(f) - 1 else z[j]
            if b - a > best[1] - best[0]:
                best = (a, b)
        i = j + 1
    return best


class ContactStep:
    """The condensed contact problem of one step on the N_L constraint displacements y = G^T X1:

        r(y) = y - y_free - D N(z_a(y), v_a(y)) / a_f,   z_a = z_c + a_f y,   v_a = v_c + a_f s_V (y - x_pred)

    (x_pred: the predictor at the rows), with its exact Jacobian J = I - D diag(N_z + s_V N_v). With
    2-D laws (d = 2) y holds (y, z) per constraint and diag(...) is block diagonal, 2 x 2 blocks."""

    def __init__(self, laws, D, y_free, z_c, v_c, x_pred, af: float, sV: float):
        self.laws, self.D, self.y_free = laws, D, y_free
        self.z_c, self.v_c, self.x_pred = z_c, v_c, x_pred
        self.af, self.sV, self.afsV, self.inv_af = af, sV, af * sV, 1.0 / af

    def state(self, y):
        """(z_a, v_a) at y."""
        return self.z_c + self.af * y, self.v_c + self.afsV * (y - self.x_pred)

    def evaluate(self, y):
        """(r, lambda = N / a_f, the diagonal N_z + s_V N_v of dlambda/dy)."""
        N, Nz, Nv = self.laws.force_and_jacobian(self.z_c + self.af * y, self.v_c + self.afsV * (y - self.x_pred))
        lam = N * self.inv_af
        return y - self.y_free - self.D @ lam, lam, Nz + self.sV * Nv

    def jacobian(self, slope):
        """J = I - D diag(slope) (slope (n,), or (n, d, d) blocks for d > 1)."""
        if slope.ndim == 3:
            n, d = slope.shape[0], slope.shape[1]
            S = np.zeros((n * d, n * d))
            for j in range(n):
                S[j * d:(j + 1) * d, j * d:(j + 1) * d] = slope[j]
            return np.eye(n * d) - self.D @ S
        return np.eye(slope.size) - self.D * slope[None, :]

    def residual(self, y):
        """(r, lambda = N / a_f, J)."""
        r, lam, slope = self.evaluate(y)
        return r, lam, self.jacobian(slope)

    def force(self, y):
        return self.laws.force(*self.state(y)) / self.af


class ContactNewton:
    """Newton on a ContactStep with backtracking on ||r||_2 (Armijo 1e-4, at most 30 halvings).

    A law whose force jumps (linear contact damping switches c v on at the contact edge) may leave
    r(y) without a root, only a jump across 0; Newton then cycles. After MAX_IT iterations a
    nonlinear Gauss-Seidel sweep takes over, with a bracketed bisection per constraint: it converges
    to the root or to the jump, where lambda_j is the value inside the jump that satisfies the linear
    relation y = y_free + D lambda (the set-valued, complementarity solution). That needs a restoring
    and dissipative law (N non-increasing in z and in v), as every built-in law is. Converged when
    ||r||_inf or the Newton correction's ||dy||_inf is at most 1e-12 of the displacement scale (the
    second where r's round-off, of the order of eps |D lambda|, exceeds that). A problem it cannot solve is a SolverError."""

    MAX_IT = 20
    SWEEPS = 200

    def __init__(self, constraints=None):
        self.calls = self.iterations = self.fallbacks = self.jumps = 0
        self.constraints = constraints   # a ConstraintSet: its labels and laws name a failure
        self.step = None                 # the step (s) of the problem being solved, for a failure's line

    def solve(self, problem: ContactStep, y_start, t: float):
        """(y, lambda) with lambda = None when no constraint pushes."""
        self.calls += 1
        scale = max(float(np.abs(problem.y_free).max()), float(np.abs(y_start).max()), 1e-300)
        tol = 1e-12 * scale
        y = y_start
        r, lam, slope = problem.evaluate(y)
        norm_inf = float(np.abs(r).max())
        single = y.size == 1
        D00 = float(problem.D[0, 0]) if single else 0.0
        it = 0
        while not norm_inf <= tol:
            if not math.isfinite(norm_inf):
                raise SolverError(f"the contact force is not finite at t = {t:.6g} s; {NOT_FINITE}")
            if it == self.MAX_IT:
                y, lam = self._fallback(problem, tol, t)
                break
            it += 1
            if single:
                pivot = 1.0 - D00 * float(slope[0])
                if pivot == 0.0:
                    y, lam = self._fallback(problem, tol, t)
                    break
                dy = -r / pivot
            else:
                try:
                    dy = np.linalg.solve(problem.jacobian(slope), -r)
                except np.linalg.LinAlgError:
                    y, lam = self._fallback(problem, tol, t)
                    break
            if float(np.abs(dy).max()) <= tol:
                # the correction is below the tolerance: r is at its round-off (|D lambda| can exceed the
                # displacement scale by far, so |r| <= tol may be out of reach while y is exact)
                y = y + dy
                r, lam, slope = problem.evaluate(y)
                break
            norm = float(r @ r)
            step = 1.0
            for _ in range(30):
                trial = y + step * dy
                r_t, lam_t, slope_t = problem.evaluate(trial)
                norm_t = float(np.abs(r_t).max())
                if float(r_t @ r_t) <= (1 - 1e-4 * step) * norm or norm_t <= tol:
                    break
                step *= 0.5
            y, r, lam, slope, norm_inf = trial, r_t, lam_t, slope_t, norm_t
        self.iterations += it
        return y, (lam if lam.any() else None)

    def _fallback(self, problem: ContactStep, tol: float, t: float):
        """Nonlinear Gauss-Seidel with bracketed bisection per constraint (class docstring)."""
        self.fallbacks += 1
        D, y_free = problem.D, problem.y_free
        n = y_free.size
        y, lam = y_free.copy(), np.zeros(n)
        for _ in range(self.SWEEPS):
            change, moved = 0.0, 0
            for j in range(n):
                b = y_free[j] + D[j] @ lam - D[j, j] * lam[j]   # y_j = b + D_jj lam_j(y_j)
                trial = y.copy()

                def r_j(x):
                    trial[j] = x
                    return x - b - D[j, j] * problem.force(trial)[j]

                trial[j] = b
                end = b + D[j, j] * problem.force(trial)[j]
                lo, hi = min(b, end), max(b, end)            # r_j(lo) <= 0 <= r_j(hi)
                for _ in range(200):
                    if hi - lo <= 0.25 * tol:
                        break
                    mid = 0.5 * (lo + hi)
                    if r_j(mid) > 0:
                        hi = mid
                    else:
                        lo = mid
                x = 0.5 * (lo + hi)
                if not math.isfinite(x):
                    raise SolverError(f"the contact force is not finite at t = {t:.6g} s; {NOT_FINITE}")
                if abs(r_j(x)) > tol:
                    self.jumps += 1
                if abs(x - y[j]) > change:
                    change, moved = abs(x - y[j]), j
                y[j], lam[j] = x, (x - b) / D[j, j]
            if change <= tol:
                return y, lam
        raise SolverError(f"the contact problem at t = {t:.6g} s did not converge ({self.SWEEPS} Gauss-Seidel sweeps "
                          f"after {self.MAX_IT} Newton iterations){self._culprit(moved, change)}")

    def _culprit(self, component: int, change: float) -> str:
        """What a failed contact problem names: the constraint that moved most in the last sweep, its
        law, the step, and what to change. Red team: the line said "reduce [integrator] dt or soften the
        stops (a smaller k)" when a 2-D support's friction (mu = 5, v_reg = 1e-6 m/s) made it fail, and
        named neither the constraint nor the step."""
        step = f" (now {self.step:g} s)" if self.step else ""
        if self.constraints is None or not self.constraints.count:
            return f"; lower [integrator] dt{step}, or check {LAW_SCALES}"
        j = component // self.constraints.dimension
        law = self.constraints.laws.laws[j]
        keys = [f"{key} = {getattr(law, key):g}" for key in ("k", "k_minus", "k_plus", "mu", "normal_force", "v_reg",
                                                                "c", "alpha") if getattr(law, key, 0)]
        return (f", constraint {j + 1} ({self.constraints.labels[j]}, {law.kind}{': ' if keys else ''}"
                f"{', '.join(keys)}) moving most in the last sweep ({change:.3g} m): lower [integrator] dt{step}, or "
                f"check that law's stiffness, damping and friction regularization (k, alpha, c; mu k / v_reg or "
                f"mu normal_force / v_reg is friction's slope at rest) against the structure's scales and units")


# -- the integrator --------------------------------------------------------------------------------

def _time_functions(fom: FullOrderModel):
    """(Omega, Omega', [(load vector or None for a point force, time function)]): plain-float
    functions for the loop (math.sin, not numpy: the loop calls them every step)."""
    loads = []
    value = rate = (lambda t: 0.0)                                                # noqa: E731
    if fom.moving_support:
        s = fom.support
        a, w, ph = float(s.amplitude), 2 * math.pi * float(s.frequency_hz), float(s.phase)
        value = lambda t: a * math.sin(w * t + ph)                                # noqa: E731
        rate = lambda t: a * w * math.cos(w * t + ph)                             # noqa: E731
        loads.append((fom.operators.base_mass_load, lambda t: a * w * w * math.sin(w * t + ph)))  # -Omega''
    if fom.force_load is not None or fom.force_row is not None:
        f = fom.force
        if hasattr(f, "frequency_hz"):
            a, w, ph = float(f.amplitude), 2 * math.pi * float(f.frequency_hz), float(f.phase)
            history = lambda t: a * math.sin(w * t + ph)                          # noqa: E731
        else:
            history = lambda t: float(f.value(t))                                 # noqa: E731
        loads.append((fom.force_load, history))
    if fom.force_matrix is not None:   # turbulence: the MatrixLoad fills its vector and returns 1
        loads.append((fom.force_matrix.vec, fom.force_matrix))
    return value, rate, loads


class FullIntegrator:
    """The condensed generalized-alpha loop over a full-order model (module docstring). Owns its
    vectors and factorizations (destroy()). Collective."""

    def __init__(self, fom: FullOrderModel, rho: float):
        self.fom = fom
        ops = fom.operators
        self.K, self.M, self.C = ops.K, ops.M, fom.velocity_matrix()   # C + G with a gyroscopic G
        self.comm = fom.comm
        self.world = self.comm.tompi4py()
        self.P = Alpha2(rho)
        rows = fom.constraints.flat_rows
        self.vectors = []
        self.systems = {}
        self.unit_force = None
        try:
            X = self._vec()
            self.crow = ConstraintRows(X, rows)
            self.nl = self.crow.n
            self.X0, self.X1, self.V, self.A0, self.A1, self.W, self.B = X, *(self._vec() for _ in range(6))
            self.Wc = self._vec() if self.C is not None else None
            self.laws = fom.constraints.laws
            self.r_c = fom.influence_at(rows)
            self.free = FreeIntervals(self.laws)
            self.newton = ContactNewton(fom.constraints)
            # per constraint, the largest D_jj |dN/dz| at a step's converged contact (rank 0): the contact's stiffness
            # against the step's (contact_stiffness_warnings); laws without a clearance's kink count 0
            self.stiffness = np.zeros(self.crow.n // max(getattr(self.laws, "dimension", 1), 1))
            self.kinked = np.array([law.kind in KINKED for law in self.laws.laws], dtype=bool)
            self.value, self.rate, loads = _time_functions(fom)
            self.loads = []
            for vec, fn in loads:
                if vec is None:  # a point force: the unit vector at its row
                    vec = self.unit_force = self._vec()
                    vec.zeroEntries()
                    lo, hi = vec.getOwnershipRange()
                    if lo <= fom.force_row < hi:
                        vec.setValue(int(fom.force_row), 1.0)
                    vec.assemble()
                self.loads.append((vec, fn))
        except Exception:
            self.destroy()
            raise
        # K_eff = K + s_V C + s_A M is SPD for a dissipative C and a stable K; flagged so, MUMPS takes the
        # same Cholesky for a damping matrix and for Rayleigh damping (the residual check catches the rest).
        self.symmetric_positive = ops.G is None
        self.lam = None              # lambda of the previous step (None: no constraint pushed)
        self.factorizations = 0
        self.setup_time = 0.0
        self.loop_time = 0.0         # wall time of the steps, factorizations excluded
        self.contact_steps = self.screened = 0

    def _vec(self) -> PETSc.Vec:
        v = self.K.createVecRight()
        self.vectors.append(v)
        return v

    # -- factorizations --------------------------------------------------------------------------
    def system(self, h: float) -> EffectiveSystem:
        """K_eff for step h: factored on first use, then reused (one per step size)."""
        S = self.systems.get(h)
        if S is None:
            S = EffectiveSystem(self.K, self.M, self.C, self.P, h, self.crow, self.symmetric_positive)
            self.factorizations += 1
            self.setup_time += S.t_setup
            self.systems[h] = S
        return S

    # -- start and restart -----------------------------------------------------------------------
    def start(self, u0: PETSc.Vec, v0: PETSc.Vec) -> None:
        """X0 = u0, V = v0 and the consistent acceleration M A0 = f(0) - K X0 - C V0 + G N(z0, v0)
        (module docstring); no solve when that right-hand side is 0."""
        u0.copy(self.X0)
        v0.copy(self.V)
        B = self.B
        self.K.mult(self.X0, B)
        if self.C is not None:
            self.C.multAdd(self.V, B, B)
        B.scale(-1.0)
        for vec, fn in self.loads:
            B.axpy(fn(0.0), vec)
        if self.nl:
            x, v = self.crow.gather([self.X0, self.V])
            N = self.laws.force(x + self.r_c * self.value(0.0), v + self.r_c * self.rate(0.0))
            for j in self.crow.mine:
                B.setValue(int(self.crow.rows[j]), float(N[j]), addv=PETSc.InsertMode.ADD_VALUES)
            B.assemble()
        self.A0.zeroEntries()
        norm = B.norm()
        if norm == 0.0:
            return
        if not math.isfinite(norm):
            raise SolverError("the initial state gives a load that is not finite; check [initial] and the excitation")
        self.M.setOption(PETSc.Mat.Option.SPD, True)
        ksp, factor, solve, description = _factored(self.M, factorization(self.M, PREFIX + "mass_"),
                                                    PREFIX + "mass_", "the mass matrix M (the start)")
        self.factorizations += 1
        try:
            solve(B, self.A0)
            R = B.duplicate()
            self.M.mult(self.A0, R)
            R.axpy(-1.0, B)
            residual = R.norm() / norm
            R.destroy()
            if not residual <= EXACT_SOLVE:
                raise SolverError(f"the -{PREFIX}mass_ solver ({description}) is not exact: relative residual "
                                  f"{residual:.2e}; use a direct factorization (-{PREFIX}mass_pc_type cholesky)")
        finally:
            destroy(factor, ksp)

    def get_state(self) -> dict:
        """The integrator's state at the end of a step, for a checkpoint: the distributed vectors
        gathered on rank 0 (None elsewhere), the contact warm start, the counters. Collective."""
        def full(vec):
            scatter, whole = PETSc.Scatter.toZero(vec)
            try:
                scatter.scatter(vec, whole, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
                return whole.getArray(readonly=True).copy() if self.world.rank == 0 else None
            finally:
                destroy(scatter, whole)

        return {"X": full(self.X0), "V": full(self.V), "A": full(self.A0),
                "lam": np.zeros(self.nl) if self.lam is None else self.lam.copy(),
                "pushing": self.lam is not None,
                "counters": np.array([self.factorizations, self.contact_steps, self.screened, self.newton.calls,
                                      self.newton.iterations, self.newton.fallbacks, self.newton.jumps], dtype=np.int64),
                "stiffness": self.stiffness.copy()}

    def set_state(self, state: dict) -> None:
        """Continue from get_state's dict (arrays on rank 0; the scalars on every rank). Collective."""
        size = self.X0.getSize()
        sizes = [np.size(state[name]) for name in ("X", "V", "A")] if self.world.rank == 0 else None
        sizes = self.world.bcast(sizes, root=0)
        if sizes != [size] * 3:
            raise InputError(f"the checkpoint holds a state of {sizes[0]} DOFs, the model has {size}; remove it or "
                             f"rerun without --resume")
        for name, vec in (("X", self.X0), ("V", self.V), ("A", self.A0)):
            scatter, whole = PETSc.Scatter.toZero(vec)
            try:
                if self.world.rank == 0:
                    whole.getArray()[:] = np.asarray(state[name], dtype=float)
                scatter.scatter(whole, vec, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.REVERSE)
            finally:
                destroy(scatter, whole)
        self.lam = np.array(state["lam"], dtype=float) if bool(state["pushing"]) else None
        if "stiffness" in state and self.world.rank == 0:   # (a checkpoint written before it was kept: from 0)
            self.stiffness[:] = np.asarray(state["stiffness"], dtype=float)
        counters = [int(c) for c in state["counters"]]
        (self.factorizations, self.contact_steps, self.screened, self.newton.calls, self.newton.iterations,
         self.newton.fallbacks, self.newton.jumps) = counters

    # -- the loop ---------------------------------------------------------------------------------
    def run(self, run: "_Run", n_begin: int, n_end: int, dt: float, h: float) -> None:
        """Steps n_begin..n_end - 1, each of length h, from t = n dt (the last step of a run may be
        shorter than dt: it ends at t_end). Everything that does not change from step to step is
        hoisted; a contact-free step makes ~15 PETSc calls and no law evaluation."""
        S = self.system(h)
        started = time.perf_counter()
        P = self.P
        am, af, gamma, beta = P.am, P.af, P.gamma, P.beta
        sV = S.sV
        ib = 1.0 / (beta * h * h)
        cp = h * h * (0.5 - beta)
        inv_af = 1.0 / af
        if am != 1.0:   # B = M A0 + K (q X_a0) [+ C (q V_a0)], then B <- -(1 - a_m)/a_f B + f / a_f
            q = 1.0 / (1.0 - am)
            cb = -(1.0 - am) / af
        else:           # a_m = 1 (rho = 1/2): no mass term; B = K X_a0 [+ C V_a0], B <- -B / a_f + f / a_f
            q, cb = 1.0, -inv_af
        cw = [q, af * h * q, af * cp * q]
        cc = [q, af * h * (1 - gamma) * q]
        cx = [h, cp]
        cv = [h * (1 - gamma), h * gamma * ib]
        X, A = [self.X0, self.X1], [self.A0, self.A1]
        V, W, B, Wc = self.V, self.W, self.B, self.Wc
        vview = V.getArray(readonly=True)
        # Everything that depends on the parity p of the step: which buffer holds X0, X1, A0, A1 (d).
        parity = [(X[p], X[1 - p], A[p], A[1 - p], [X[p], V, A[p]], [V, A[p]], [A[p], A[1 - p]],
                   X[1 - p].getArray(readonly=True), A[p].getArray(readonly=True)) for p in (0, 1)]
        Kmult, Mmultadd = self.K.mult, self.M.multAdd
        Cmultadd = self.C.multAdd if self.C is not None else None
        mass_term = am != 1.0
        solve = S.solve
        loads = self.loads
        load_vec, load_fn = loads[0] if len(loads) == 1 else (None, None)
        value = self.value
        nl, crow = self.nl, self.crow
        local, mine = crow.local, crow.mine
        parallel, comm = crow.parallel, crow.comm
        D, Y = S.D, S.Y
        rc_list = self.r_c.tolist()
        lo_list, hi_list = self.free.lo, self.free.hi
        screen = self.free.any
        c0 = 1.0 - af
        lam = self.lam
        buf1 = np.zeros(nl)
        buf3 = np.zeros((3, nl))
        # The state at the rows at the start of the first step: exact, from the vectors.
        start_rows = crow.gather([X[0], V, A[0]]) if nl else np.zeros((3, 0))
        y0 = start_rows[0].tolist()
        v0, a0 = start_rows[1], start_rows[2]
        tb, zb, vb = run.tb, run.zb, run.vb
        contact_steps = screened = 0
        p = 0
        k = run.k
        steps, t_end, tol = run.steps, run.t_end, run.tol
        next_sample = run.next_sample
        last = n_end - 1
        free = True
        for n in range(n_begin, n_end):
            t = n * dt
            t_next = (n + 1) * dt if n + 1 < steps else t_end
            X0, X1, A0, Dv, w_vecs, x_vecs, v_vecs, x1view, a0view = parity[p]
            sampling = next_sample <= t_next + tol
            if sampling:
                run.before(X0, V, t, t_next)
            ta = t + af * h
            # 1. the right-hand side and the step's one solve
            W.zeroEntries()
            W.maxpy(cw, w_vecs)
            Kmult(W, B)
            if mass_term:
                Mmultadd(A0, B, B)
            if Cmultadd is not None:
                Wc.zeroEntries()
                Wc.maxpy(cc, x_vecs)
                Cmultadd(Wc, B, B)
            if load_vec is not None:
                B.axpby(load_fn(ta) * inv_af, cb, load_vec)
            else:
                B.scale(cb)
                for vec, fn in loads:
                    B.axpy(fn(ta) * inv_af, vec)
            solve(B, Dv)                                    # d_free
            X1.waxpy(1.0, X0, Dv)
            X1.maxpy(cx, x_vecs)                            # X1 = X~ + d_free
            if nl:
                # 2. the free displacement at the rows
                if parallel:
                    buf1[:] = 0.0
                    buf1[mine] = x1view[local]
                    comm.Allreduce(MPI.IN_PLACE, buf1)
                    yf = buf1.tolist()
                else:
                    yf = x1view[local].tolist()
                # 3. screen, or Newton on the N_L unknowns
                free = False
                if screen and lam is None:
                    om = value(ta)
                    free = True
                    for j in range(nl):
                        z = c0 * y0[j] + af * yf[j] + rc_list[j] * om
                        if not lo_list[j] <= z <= hi_list[j]:
                            free = False
                            break
                if free:
                    screened += 1
                else:
                    if not parallel:
                        v0, a0 = vview[local], a0view[local]
                    lam = self._contact(D, np.array(y0), np.array(yf), v0, a0, ta, h, sV, lam, t_next)
                    if lam is not None:
                        # 4. the correction: no solve
                        nz = np.flatnonzero(lam)
                        cols = [Y[j] for j in nz]
                        Dv.maxpy(lam[nz], cols)
                        if nz.size <= 2:
                            X1.maxpy(lam[nz], cols)
                        else:
                            X1.waxpy(1.0, X0, Dv)
                            X1.maxpy(cx, x_vecs)
                        contact_steps += 1
            # 5. velocity and acceleration
            V.maxpy(cv, v_vecs)                             # V1 = V~ + gamma h A1
            Dv.scale(ib)                                    # A1 = d / (beta h^2)
            p = 1 - p
            tb[k] = t_next
            if nl:
                if parallel:
                    buf3[:] = 0.0
                    buf3[0, mine] = x1view[local]
                    buf3[1, mine] = vview[local]
                    buf3[2, mine] = Dv.getArray(readonly=True)[local]
                    comm.Allreduce(MPI.IN_PLACE, buf3)
                    y0 = buf3[0].tolist()
                    v0, a0 = buf3[1].copy(), buf3[2].copy()
                    zb[k] = buf3[0]
                    vb[k] = v0
                else:
                    y0 = yf if free else x1view[local].tolist()
                    zb[k] = y0
                    vb[k] = vview[local]
            if sampling:   # samples of this step come after the steps before it (cut k)
                run.after(X1, V, t_next, k)
                next_sample = run.next_sample
            k += 1
            if k == BLOCK or n == last or (sampling and run.pending >= BLOCK):
                self.X0, self.X1, self.A0, self.A1 = X1, X0, Dv, A0
                self.lam = lam
                self.contact_steps += contact_steps
                self.screened += screened
                contact_steps = screened = 0
                run.k = k
                run.control(n + 1, t_next)
                k = run.k
        self.X0, self.X1, self.A0, self.A1 = parity[p][:4]
        self.lam = lam
        self.contact_steps += contact_steps
        self.screened += screened
        self.loop_time += time.perf_counter() - started

    def _contact(self, D, y0, yf, v0, a0, ta, h, sV, lam_prev, t):
        """lambda of one step (None when no constraint pushes), computed on rank 0 and broadcast."""
        P = self.P
        af = P.af
        world = self.world
        result, unexpected = None, []
        if world.rank == 0:
            # numpy's overflow warnings off: the state and the contact force are checked for finiteness
            # here and in the Newton loop, which end the run with one line (red team: a base amplitude of
            # 1e300 m printed "RuntimeWarning: overflow encountered in matmul" and its source lines first)
            with np.errstate(over="ignore", invalid="ignore"):
                try:
                    x_pred = y0 + h * v0 + (h * h * (0.5 - P.beta)) * a0
                    if not (math.isfinite(float(yf.sum())) and math.isfinite(float(x_pred.sum()))):
                        raise SolverError(f"the state is not finite at t = {t:.6g} s; {NOT_FINITE}")
                    z_c = (1 - af) * y0 + self.value(ta) * self.r_c
                    v_c = v0 + (af * h * (1 - P.gamma)) * a0 + self.rate(ta) * self.r_c
                    problem = ContactStep(self.laws, D, yf, z_c, v_c, x_pred, af, sV)
                    self.newton.step = h
                    y, result = self.newton.solve(problem, yf if lam_prev is None else yf + D @ lam_prev, t)
                    if result is not None:
                        self._track_stiffness(problem, y, D)
                except SolverError as e:
                    result = e
                except BaseException as e:   # (a bug) every rank raises it: errors.from_rank0
                    unexpected.append(e)
        if world.size > 1:
            result = from_rank0(world, result, unexpected)
        elif unexpected:
            raise unexpected.pop()
        if isinstance(result, SolverError):
            raise SolverError(str(result))
        return result

    def _track_stiffness(self, problem: ContactStep, y, D) -> None:
        """stiffness = max(stiffness, D_jj |dN/dz|) at a converged contact, per constraint (a support of two
        directions: its largest entry of either); NaN-free (a non-finite state ends the run elsewhere)."""
        if not self.kinked.any():
            return
        _, Nz, _ = self.laws.force_and_jacobian(*problem.state(y))
        d = np.diag(D)
        if np.ndim(Nz) == 3:   # (n, 2, 2) blocks; D's two rows per support
            ratio = np.abs(Nz).max(axis=(1, 2)) * d.reshape(-1, 2).max(axis=1)
        else:
            ratio = np.abs(Nz) * d
        ratio = np.where(self.kinked & np.isfinite(ratio), ratio, 0.0)
        np.maximum(self.stiffness, ratio, out=self.stiffness)

    def destroy(self) -> None:
        for S in self.systems.values():
            S.destroy()
        self.systems = {}
        destroy(*self.vectors)
        self.vectors = []


# -- one run: samples, blocks of steps, control points --------------------------------------------

class _Stop(Exception):
    """A stop rank 0 asked for at a control point (after its checkpoint), with its message."""


class _Run:
    """What the loop hands over: the samples (cubic Hermite between the steps around them) and the
    steps, both buffered and handed to `on_block` at the control points (every BLOCK steps, at the
    end of a run of equal steps), snapshots, progress, checkpoints, and rank 0's word on stopping
    (an output that cannot be written, a stop request). Collective: every rank takes the same
    path; the buffers live on rank 0."""

    def __init__(self, integ: FullIntegrator, settings: IntegratorSettings, monitor: StepMonitor, rows, on_block,
                 snapshot_samples, snapshot, control, steps: int):
        self.integ, self.monitor = integ, monitor
        self.on_block, self.snapshot, self.hook = on_block, snapshot, control
        self.snapshot_samples = set(int(i) for i in snapshot_samples)
        self.snapshot_list = sorted(self.snapshot_samples)
        self.t_end, self.steps = settings.t_end, steps
        self.tol = monitor.tol
        self.orow = ConstraintRows(integ.X0, rows, {v.handle: v.getArray(readonly=True)
                                                    for v in (integ.X0, integ.X1, integ.V)})
        self.world = integ.world
        nl = integ.nl
        self.tb, self.zb, self.vb = np.zeros(BLOCK), np.zeros((BLOCK, nl)), np.zeros((BLOCK, nl))
        self.k = 0
        self.samples = []           # rank 0: (t, values, rates, cut), cut = the block's steps before the sample
        self.pending = 0            # samples taken since the last hand-over
        self.start = None           # (t, values, rates) at the observed rows at the start of a sampling step
        self.prev_u = self.prev_v = None
        self.scatter = self.full = None
        self.failure, self.failed_write = None, False
        self.unexpected = []        # rank 0: what else a callback raised (_call), every rank's at the next _word
        self.t = None               # the time of the last control point

    @property
    def next_sample(self) -> float:
        m = self.monitor
        return float(m.times[m.next]) if m.next < m.times.size else math.inf

    def initial(self, t: float) -> None:
        """The samples at the start time itself (t = 0 of a new run), handed over at once."""
        X, V = self.integ.X0, self.integ.V
        values, rates = self.orow.gather([X, V])
        for index, sample, _ in self.monitor.samples_due(t):
            self._sample(index, sample, _EXACT, values, rates, values, rates, 0, X, None)
        self._hand_over()
        self._word()

    def before(self, X, V, t: float, t_next: float) -> None:
        """At the start of a step that passes a sample: the observed values at its start, and the
        field when a snapshot falls inside the step."""
        values, rates = self.orow.gather([X, V])
        self.start = (t, values, rates)
        m = self.monitor
        later = self.snapshot_list[bisect.bisect_left(self.snapshot_list, m.next):]
        if later and m.times[later[0]] <= t_next + self.tol:
            if self.prev_u is None:
                self.prev_u, self.prev_v = X.duplicate(), V.duplicate()
            X.copy(self.prev_u)
            V.copy(self.prev_v)

    def after(self, X, V, t: float, cut: int) -> None:
        """At the end of that step: its samples, after the block's first `cut` steps. A sample is
        kept as its Hermite weights and the two states; the blends are formed per block."""
        values, rates = self.orow.gather([X, V])
        t0, x0, xd0 = self.start
        h = t - t0
        for index, sample, exact in self.monitor.samples_due(t):
            if exact:
                self._sample(index, sample, _EXACT, values, rates, values, rates, cut, X, None)
                continue
            weights, rate_weights = _hermite((sample - t0) / h, h)
            a0, b0, a1, b1 = weights
            blend = (a0, b0 * h, a1, b1 * h, *rate_weights)
            self._sample(index, sample, blend, x0, xd0, values, rates, cut, X, (weights, h, V))

    def _sample(self, index, sample, blend, x0, xd0, x1, xd1, cut, X, interpolate) -> None:
        if index in self.snapshot_samples and self.snapshot is not None:
            field = self._field(X) if interpolate is None else self._interpolated_field(X, *interpolate)
            self._call(self.snapshot, index, field)
        self.pending += 1   # on every rank: the control points depend on it
        if self.world.rank == 0:
            self.samples.append((sample, blend, x0, xd0, x1, xd1, cut))

    def _hand_over(self) -> None:
        """The buffered steps and samples to on_block (rank 0), then empty buffers."""
        if self.world.rank == 0 and (self.k or self.samples) and self.on_block is not None:
            m = self.orow.n
            samples = self.samples
            J = len(samples)
            w = np.array([s[1] for s in samples]).reshape(J, 8).T[:, :, None]
            x0, xd0, x1, xd1 = (np.array([s[i] for s in samples]).reshape(J, m) for i in (2, 3, 4, 5))
            x = w[0] * x0 + w[1] * xd0 + w[2] * x1 + w[3] * xd1          # the order of the formula per sample
            xd = w[4] * x0 + w[5] * xd0 + w[6] * x1 + w[7] * xd1
            self._call(self.on_block,
                       (self.tb[:self.k].copy(), self.zb[:self.k].copy(), self.vb[:self.k].copy()),
                       (np.array([s[0] for s in samples]), x, xd, np.array([s[6] for s in samples], dtype=np.int64)))
        self.k = self.pending = 0
        self.samples = []

    def control(self, step: int, t: float) -> None:
        """A control point after `step` steps, at t."""
        integ, monitor = self.integ, self.monitor
        self.t = t
        self._hand_over()
        norm = integ.X0.norm() + integ.V.norm()
        if not math.isfinite(norm):
            raise SolverError(f"the state is not finite at t = {t:.6g} s (step {step}); {NOT_FINITE}")
        action = None
        # a termination signal on any rank stops the run here, on every rank (rank 0's hook saves first)
        if self.world.size > 1 and self.world.allreduce(TERMINATION.requested, op=MPI.LOR) and \
                self.world.rank == 0 and self.hook is not None:
            self.hook.interrupted = True
        if self.world.rank == 0 and not self.failure and self.hook is not None:
            action = self._call(self.hook.at, t, step)
        action = self._word(action)
        if action in ("save", "save and stop"):
            state = integ.get_state()
            state.update(t=t, steps=step, next_sample=monitor.next)
            if self.world.rank == 0:
                self._call(self.hook.save, state)
            self._word()
            if action == "save and stop":
                message = self.hook.stop_message(t) if self.world.rank == 0 else None
                raise _Stop(self.world.bcast(message, root=0) if self.world.size > 1 else message)
        monitor.report(step, t)

    def _word(self, action=None):
        """Rank 0's failure (an OSError in a callback, or its statistics' overflow) and action, on every
        rank; a failure ends the run. Anything else a callback raised on rank 0 is raised on every rank
        (errors.from_rank0)."""
        if self.world.size > 1:
            action, self.failure, self.failed_write = from_rank0(self.world, (action, self.failure, self.failed_write),
                                                                 self.unexpected)
        elif self.unexpected:
            raise self.unexpected.pop()
        if self.failure:
            raise (WriteFailed if self.failed_write else SolverError)(self.failure)
        return action

    def _field(self, u) -> np.ndarray | None:
        if self.scatter is None:
            self.scatter, self.full = PETSc.Scatter.toZero(u)
        self.scatter.scatter(u, self.full, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        return self.full.getArray(readonly=True).copy() if self.world.rank == 0 else None

    def _interpolated_field(self, u, weights, h, v):
        a0, b0, a1, b1 = weights
        field = self.prev_u.copy()
        field.scale(a0)
        field.axpy(b0 * h, self.prev_v)
        field.axpy(a1, u)
        field.axpy(b1 * h, v)
        values = self._field(field)
        field.destroy()
        return values

    def _call(self, callback, *args):
        """A callback on this rank; a write error (a full disk) or a SolverError (the statistics'
        overflow) becomes the run's failure, said at the next word from rank 0."""
        if self.failure:
            return None
        try:
            return callback(*args)
        except WRITE_ERRORS as exc:
            self.failure, self.failed_write = f"cannot write the output: {write_failure(exc)}", True
            return None
        except SolverError as exc:   # rank 0's statistics overflowed (stats._check_overflow): every rank's line
            self.failure, self.failed_write = str(exc), isinstance(exc, WriteFailed)
            return None
        except BaseException as exc:   # (a bug, an h5py error no write foresaw) raised on every rank by _word;
            self.failure = type(exc).__name__   # red team: on rank 0 alone, rank 1 hung
            self.unexpected.append(exc)
            return None

    def destroy(self) -> None:
        destroy(self.prev_u, self.prev_v, self.scatter, self.full)


_EXACT = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)   # the blend of a sample at the step itself


def _hermite(s: float, h: float):
    """Cubic Hermite weights (u0, h v0, u1, h v1) for the value and, divided by h, the rate at s."""
    s2, s3 = s * s, s * s * s
    value = (2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2)
    rate = ((6 * s2 - 6 * s) / h, 3 * s2 - 4 * s + 1, (-6 * s2 + 6 * s) / h, 3 * s2 - 2 * s)
    return value, rate


def _segments(first: int, steps: int, dt: float, h_last: float):
    """(begin, end, h) runs of equal steps from step `first`: steps of dt, then the last one."""
    if h_last == dt:
        return [(first, steps, dt)] if first < steps else []
    out = [(first, steps - 1, dt)] if first < steps - 1 else []
    return out + ([(max(first, steps - 1), steps, h_last)] if first < steps else [])


def integrate_full(fom: FullOrderModel, settings: IntegratorSettings, rows, on_block, snapshot_samples=(),
                   snapshot=None, say=None, control=None, resume=None) -> dict:
    """Integrate from (u(0), u'(0) = 0) at t = 0, or from a checkpoint (`resume`), to t_end with fixed
    steps [integrator] dt (the last one shortened to end at t_end), observing (u, u') at `rows`:
      on_block(steps, samples)   rank 0, in blocks (at most BLOCK steps), in order:
                                 steps = (t (k,), z (k, N_L), v (k, N_L)): u, u' at the constraint
                                 rows fom.constraints.flat_rows after each step;
                                 samples = (t (J,), x (J, m), xd (J, m), cut (J,)): u, u' at `rows`
                                 at the sample times, sample j coming after the block's first
                                 cut[j] steps (FullRecorder.block takes both)
      snapshot(i, u)             the field at the samples in `snapshot_samples` (u on rank 0, None
                                 elsewhere; called on every rank)
      control                    rank 0's hook at the control points (every BLOCK steps at most):
                                 control.at(t, steps) -> None, "save" or "save and stop";
                                 control.save(state) writes a checkpoint (FullIntegrator.get_state()
                                 with t, steps, next_sample); control.stop_message(t) is the
                                 Interrupted error's line
      resume                     such a state (the arrays on rank 0, the rest on every rank)
    Returns solver statistics (the keys of the reduced integrator's, plus factorizations and contact
    counts). An OSError in a callback on rank 0 ends the run on every rank. Collective."""

    from .errors import Interrupted

    check_step(settings)
    rho = options()["rho"]
    monitor = StepMonitor(settings.sample_times, first_sample=int(resume["next_sample"]) if resume else 0, say=say)
    steps, h_last = step_count(settings.t_end, settings.dt)
    integ = FullIntegrator(fom, rho)
    run = None
    stopped = None
    started = time.perf_counter()
    try:
        first = int(resume["steps"]) if resume else 0
        if resume:
            integ.set_state(resume)
        else:
            u, v = fom.initial_state()
            try:
                integ.start(u, v)
            finally:
                destroy(u, v)
        run = _Run(integ, settings, monitor, rows, on_block, snapshot_samples, snapshot, control, steps)
        if not resume:
            run.initial(0.0)
        try:
            for begin, end, h in _segments(first, steps, settings.dt, h_last):
                integ.run(run, begin, end, settings.dt, h)
        except _Stop as stop:
            stopped = str(stop)
        wall = time.perf_counter() - started
        final = run.t if run.t is not None else (float(resume["t"]) if resume else 0.0)
        stats = {"steps": steps if stopped is None else None, "rejected_steps": 0, "snes_failures": 0,
                 "newton_iterations": integ.newton.iterations, "factorizations": integ.factorizations,
                 "time_integration": wall, "scheme": "alpha2", "final_time": final, "adaptive": False,
                 "contact": "condensed", "dt": settings.dt, "dofs": fom.size, "alpha_radius": rho,
                 "contact_steps": integ.contact_steps, "contact_free_steps": integ.screened,
                 "contact_solves": integ.newton.calls, "contact_fallbacks": integ.newton.fallbacks,
                 "contact_stiffness": integ.stiffness.tolist(),
                 "factorization_time": integ.setup_time, "step_time": integ.loop_time,
                 "factorization": ", ".join(sorted({S.description for S in integ.systems.values()}))}
    finally:
        if run is not None:
            run.destroy()
        integ.destroy()
    if stopped is not None:
        raise Interrupted(stopped)
    check_outcome(monitor, 1, stats, settings.t_end, WHAT, ADVICE)
    return stats
