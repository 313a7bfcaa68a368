"""The paper's first-order (state-space) reduced model of a gyroscopic structure (issue 19; Brake &
Segalman 2011, Section 2, Eqs. 4-21). docs/design.md, "Gyroscopic structures", says why.

State x = [w_t; w] (Eq. 4), A x' + B x = [f; 0] with

    A = [[M, 0], [0, K]]  (Eq. 9, symmetric positive definite)
    B = [[C + G, K], [-K, 0]]  (Eq. 10 with the damping C beside G; skew when C = 0)

- Complex state modes (Eqs. 5-7): psi_j = [i omega_j phi_j; phi_j], from the PEP modes phi_j
  (gyroscopic.py): psi^R = [-omega phi^I; phi^R], psi^I = [omega phi^R; phi^I].
- State DBFs (Eqs. 13-17): the derivative in k of the spring-perturbed complex state mode,
  Psi_{j,k} = [i varpi_j phi_{j,k}; phi_{j,k}] (the varpi_{,k} terms dropped as in the paper), phi_{j,k}
  the central difference of gyroscopic_basis.dbf_columns. A static mode psi gives [0; psi] and
  [varpi psi; 0] (varpi its Rayleigh quotient), as a real DBF does.
- Real basis: the real and imaginary parts of each complex state vector, Gram-Schmidt (Eqs. 18-19)
  in the A inner product <A a, b> = a_v^T M b_v + a_w^T K b_w, each column normalized (Eq. 11), so
  Psi^T A Psi = I. Distributed: each column is a pair of PETSc Vecs (velocity part, displacement part)
  in K's layout; every product is collective. Classical Gram-Schmidt run twice ("twice is enough").
  A column below DROP_TOL of its complex vector's A-norm, or one Gram-Schmidt leaves almost nothing
  of, is left out; a DBF of which neither part survives is a breakdown error as in basis.py.
- hat-omega (Eq. 20): <B Psi^R, Psi^I> of the normalized DBF columns with the conservative B (C = 0),
  given to both columns of the DBF; it is omega_j for a mode (Eq. 11).
- Reduced model (Eq. 21 and its Galerkin projection): x = Psi eta, 2 (N + N_L) real states,

      eta' = -B_r eta + Psi_v^T (f(t) + g N(z, v)),   B_r = Psi^T B Psi,
      z = g^T Psi_w eta + r_c Omega,   v = g^T Psi_v eta + r_c Omega'

  (A_r = Psi^T A Psi is I to round-off and is factored out as the second-order integrator does with
  M_r). w = Psi_w eta is what the outputs show (constraints, probes, snapshots); the contact law's
  velocity is the velocity part Psi_v eta.

Integrated with PETSc TS ARKIMEX (options prefix `rom_`; rom_integrator.integrate_reduced): the C callbacks
(dbf_hpc/_romc, RomCtx.first: the same equations, the stage Jacobian formed densely and solved by LU
in C, samples and step statistics in C) or StateSpaceProblem's Python ones, the readable reference.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from petsc4py import PETSc

from .accuracy import captured, constraint_kinds, exact_flexibility
from .basis import BREAKDOWN_TOL, BasisSettings, _check_rows
from .constraints import ConstraintSet
from .errors import InputError, SolverError
from .excitation import Harmonic
from .operators import Operators
from .petsctools import destroy
from .rom import ReducedField, applied, case_changes, digest_of
from .timestepping import checked_by_the_integrator

# A real column below this fraction of its complex vector's A-norm is left out (gyroscopic_basis.DROP_TOL).
DROP_TOL = 1e-6
# w^T K w below -NEGATIVE_TOL (v^T M v + |w^T K w|) is negative beyond round-off: K is not positive definite.
NEGATIVE_TOL = 1e-10
FORMS = ("state_space", "second_order")


def check_form(form: str) -> None:
    if form not in FORMS:
        raise InputError(f'basis gyroscopic_form must be "state_space" or "second_order", got {form!r}')


class _StateGramSchmidt:
    """Gram-Schmidt in the A inner product (Eqs. 18-19) of state vectors (v, w). Keeps the columns
    and their A-products (M v, K w). Collective on ops.comm."""

    def __init__(self, ops: Operators):
        self.ops = ops
        self.v, self.w, self.Mv, self.Kw = [], [], [], []
        self.seconds = 0.0

    def _products(self, v, w):
        Mv, Kw = v.duplicate(), w.duplicate()
        self.ops.M.mult(v, Mv)
        self.ops.K.mult(w, Kw)
        return Mv, Kw

    def norm(self, v, w) -> float:
        Mv, Kw = self._products(v, w)
        value = _a_norm(v, w, Mv, Kw)
        destroy(Mv, Kw)
        return value

    def add(self, v, w, scale: float) -> bool:
        """Orthonormalize copies of (v, w) against the kept columns; True if kept. `scale`: the A-norm of
        its complex vector."""
        start = time.perf_counter()
        try:
            before = self.norm(v, w)
            if not before > DROP_TOL * scale:
                return False
            v, w = v.copy(), w.copy()
            for _ in range(2):
                c = [v.dot(a) + w.dot(b) for a, b in zip(self.Mv, self.Kw)]
                for cj, a, b in zip(c, self.v, self.w):
                    v.axpy(-cj, a)
                    w.axpy(-cj, b)
            Mv, Kw = self._products(v, w)
            try:
                norm = _a_norm(v, w, Mv, Kw)
            except InputError:
                destroy(v, w, Mv, Kw)
                raise
            if norm < BREAKDOWN_TOL * before:
                destroy(v, w, Mv, Kw)
                return False
            for x in (v, w, Mv, Kw):
                x.scale(1.0 / norm)
            self.v.append(v)
            self.w.append(w)
            self.Mv.append(Mv)
            self.Kw.append(Kw)
            return True
        finally:
            self.seconds += time.perf_counter() - start

    def destroy_products(self):
        destroy(*self.Mv, *self.Kw)
        self.Mv, self.Kw = [], []


def _a_norm(v, w, Mv, Kw) -> float:
    """sqrt(v^T M v + w^T K w), the A-norm of the state (v, w) (Eq. 9); an InputError where w^T K w is
    clearly negative: A is an inner product only with K positive definite, and a structure whose K is
    not (a mode that only G holds, Kelvin-Tait-Chetaev) had its mode columns dropped as zero and ended
    in an internal error (red team). Collective."""
    m, k = v.dot(Mv), w.dot(Kw)
    if k < -NEGATIVE_TOL * (m + abs(k)):
        raise InputError('[basis] gyroscopic_form = "state_space": its inner product A = diag(M, K) (Eqs. 9, 11) '
                         'needs K positive definite, and this structure\'s K is not (w^T K w < 0 on a basis vector: '
                         'a mode that only G holds); use gyroscopic_form = "second_order"')
    return float(np.sqrt(max(m + k, 0.0)))


def _state_parts(xr, xi, omega: float):
    """(psi^R, psi^I) of the complex state vector [i omega x; x] (Eqs. 6-7, 15-16): pairs of new Vecs."""
    vr, vi = xi.copy(), xr.copy()
    vr.scale(-omega)
    vi.scale(omega)
    return (vr, xr.copy()), (vi, xi.copy())


def _local(vecs) -> np.ndarray:
    """(local rows, n): the columns' local parts."""
    if not vecs:
        return np.zeros((0, 0))
    return np.column_stack([v.getArray(readonly=True) for v in vecs])


@dataclass
class StateSpaceBasis:
    """The A-orthonormal real basis of the state space (module docstring): column j is
    (velocity[j], displacement[j]), distributed Vecs in K's layout, owned here. Its interface is the
    one run.py and the reductor read from a ReducedBasis (omega, enrichment_omega, stats, ...)."""

    velocity: list
    displacement: list
    omega: np.ndarray              # the complex mode's omega_j of each mode column, rad/s
    enrichment_omega: np.ndarray   # hat-omega (Eq. 20) of each DBF column, rad/s
    dbf_k: np.ndarray
    dbf_branch: np.ndarray
    constraint_rows: np.ndarray
    dbf_k_auto: np.ndarray
    settings: BasisSettings
    comm: object = None
    raw: list = field(default_factory=list)   # (d_R, d_I, varpi) of each DBF: what a richer basis reuses
    stats: dict = field(default_factory=dict)
    flexibility_exact: np.ndarray = field(default_factory=lambda: np.zeros(0))
    flexibility_captured: np.ndarray = field(default_factory=lambda: np.zeros(0))

    form = "state_space"

    @property
    def size(self) -> int:
        return len(self.velocity)

    @property
    def mode_count(self) -> int:
        return self.omega.size

    @property
    def enrichment_count(self) -> int:
        return self.size - self.mode_count

    @property
    def enrichment(self) -> str:
        return self.settings.enrichment

    @property
    def complex_modes(self) -> int:
        return int(self.stats.get("complex_modes", 0))

    def constraint_omega(self) -> np.ndarray:
        counts = self.stats.get("constraint_columns") or []
        if not counts:
            return np.zeros(0)
        return self.enrichment_omega[np.concatenate(([0], np.cumsum(counts)[:-1])).astype(int)]

    def warnings(self, labels=None) -> list:
        labels = labels or [f"row {r}" for r in self.constraint_rows]
        return self.settings.strategy.warnings(self.dbf_k, self.dbf_k_auto, labels)

    def _rows(self, vecs, rows) -> np.ndarray:
        """The columns at the given global rows (len(rows) x n) on every rank. Collective."""
        rows = np.asarray(rows, dtype=np.int64)
        out = np.zeros((rows.size, self.size))
        if self.size:
            lo, hi = vecs[0].getOwnershipRange()
            mine = (rows >= lo) & (rows < hi)
            out[mine] = _local(vecs)[rows[mine] - lo]
        return self.comm.tompi4py().allreduce(out)

    def rows(self, rows) -> np.ndarray:
        """The displacement part Psi_w at the rows (what a field or a probe shows). Collective."""
        return self._rows(self.displacement, rows)

    def velocity_rows(self, rows) -> np.ndarray:
        """The velocity part Psi_v at the rows. Collective."""
        return self._rows(self.velocity, rows)

    def velocity_dot(self, vec: PETSc.Vec) -> np.ndarray:
        """Psi_v^T vec: a load projected onto the basis (Eq. 4's right side [f; 0]). Collective."""
        return self.comm.tompi4py().allreduce(_local(self.velocity).T @ vec.getArray(readonly=True))

    def displacement_dot(self, vec: PETSc.Vec) -> np.ndarray:
        """Psi_w^T vec. Collective."""
        return self.comm.tompi4py().allreduce(_local(self.displacement).T @ vec.getArray(readonly=True))

    def velocity_dot_rows(self, rows: np.ndarray) -> np.ndarray:
        """Psi_v^T W for W given by this rank's rows: (n, m). Collective."""
        return self.comm.tompi4py().allreduce(_local(self.velocity).T @ rows)

    def project(self, A: PETSc.Mat, left: str, right: str) -> np.ndarray:
        """Psi_left^T A Psi_right, left/right "v" (velocity) or "w" (displacement), on every rank.
        Collective."""
        parts = {"v": self.velocity, "w": self.displacement}
        products = []
        for vec in parts[right]:
            out = vec.duplicate()
            A.mult(vec, out)
            products.append(out)
        local = _local(parts[left]).T @ _local(products)
        destroy(*products)
        return self.comm.tompi4py().allreduce(local)

    def state_energy(self, ops: Operators) -> np.ndarray:
        """A_r = Psi^T A Psi (I to round-off). Collective."""
        return self.project(ops.M, "v", "v") + self.project(ops.K, "w", "w")

    def set_flexibility(self, f_exact: np.ndarray, ops: Operators) -> None:
        """The captured static flexibility of span Psi_w (accuracy.py): g^T Q Q^T g for a K-orthonormal
        Q of the displacement parts, from Psi_w^T K Psi_w (rank N + N_L at most). Collective."""
        self.flexibility_exact = np.asarray(f_exact, dtype=float)
        K_ww = self.project(ops.K, "w", "w")
        B = self.rows(self.constraint_rows)
        s, U = np.linalg.eigh(0.5 * (K_ww + K_ww.T))
        keep = s > 1e-12 * s.max() if s.size else np.zeros(0, bool)
        X = B @ U[:, keep]
        self.flexibility_captured = captured(np.sum(X**2 / s[keep], axis=1), self.flexibility_exact)

    def destroy(self) -> None:
        destroy(*self.velocity, *self.displacement, *[v for d in self.raw for v in d[:2]])
        self.velocity, self.displacement, self.raw = [], [], []


def _basis(ops: Operators, rows, settings: BasisSettings, labels, modes, raw: list | None) -> StateSpaceBasis:
    """The basis from `modes` (stable GyroscopicModes) and the DBFs: computed here (raw None) or the
    given raw DBFs (d_R, d_I, varpi) (a richer basis: no DBF recomputed). Collective."""
    from .gyroscopic_basis import all_dbfs
    from .enrichment import static_modes

    strategy = settings.strategy
    NL = rows.size if strategy.kind != "none" else 0
    gs = _StateGramSchmidt(ops)
    omega = []
    t1 = time.perf_counter()
    k, k_auto, branch = np.zeros(NL), np.zeros(NL), np.zeros(NL, dtype=np.int64)
    new_raw, groups, static, dbfs = [], [], None, []
    try:
        for j in range(modes.count):
            w_j = float(modes.omega[j])
            parts = _state_parts(modes.real[j], modes.imag[j], w_j)
            try:
                scale = np.sqrt(sum(gs.norm(*p) ** 2 for p in parts))
                for p in parts:
                    if gs.add(*p, scale):
                        omega.append(w_j)
            finally:
                destroy(*parts[0], *parts[1])
        N = len(gs.v)
        if strategy.kind == "static" and NL and raw is None:
            static = static_modes(ops, rows)
        if strategy.kind == "dbf" and raw is None:
            dbfs = all_dbfs(ops, rows, modes, strategy.stiffness, settings.groups)
        for j in range(NL):
            if raw is not None:
                dr, di, varpi = raw[j]
                dr, di = dr.copy(), di.copy()
            elif strategy.kind == "dbf":
                dr, di, k[j], k_auto[j], branch[j], varpi = dbfs[j]
                dbfs[j] = None
            else:   # a static mode psi: the state vectors [0; psi] and [varpi psi; 0] as a real DBF's
                dr = ops.K.createVecRight()
                static.getColumnVector(j, dr)
                di = dr.duplicate()
                di.zeroEntries()
                Kd = dr.duplicate()
                ops.K.mult(dr, Kd)
                stiffness = dr.dot(Kd)
                ops.M.mult(dr, Kd)
                varpi = float(np.sqrt(max(stiffness, 0.0) / Kd.dot(dr)))   # its Rayleigh quotient (any > 0 spans)
                Kd.destroy()
            new_raw.append((dr, di, varpi))
            parts = _state_parts(dr, di, varpi)
            try:
                scale = np.sqrt(sum(gs.norm(*p) ** 2 for p in parts))
                first = len(gs.v)
                for p in parts:
                    gs.add(*p, scale)
            finally:
                for p in parts:
                    destroy(*p)
            if len(gs.v) == first:
                raise SolverError(f"basis breakdown: the {strategy.column_name} of the constraint at {labels[j]} is "
                                  f"numerically dependent on the reference modes and the earlier columns; use fewer "
                                  f"modes, a finer mesh, or merge constraints this close")
            groups.append((first, len(gs.v) - first))
        gs_count = len(gs.v)
    except Exception:
        destroy(*gs.v, *gs.w, *[v for d in new_raw for v in d[:2]], *[v for d in dbfs if d is not None for v in d[:2]])
        gs.destroy_products()
        destroy(static)
        raise
    destroy(static)
    gs.destroy_products()
    t2 = time.perf_counter()
    basis = StateSpaceBasis(velocity=gs.v, displacement=gs.w, omega=np.array(omega),
                            enrichment_omega=np.zeros(gs_count - N), dbf_k=k, dbf_branch=branch, constraint_rows=rows,
                            dbf_k_auto=k_auto, settings=settings, comm=ops.comm, raw=new_raw)
    # Eq. 20 with the conservative B = [[G, K], [-K, 0]]: <B Psi^R, Psi^I> = Psi^I^T B Psi^R
    B_r = conservative_state_matrix(basis, ops)
    for first, count in groups:
        value = B_r[first + 1, first] if count == 2 else 0.0
        basis.enrichment_omega[first - N:first - N + count] = value
    basis.stats = {"time_orthogonalization": gs.seconds, "time_enrichment": t2 - t1 - gs.seconds,
                   "complex_modes": modes.count, "complex_omega": [float(w) for w in modes.omega[:modes.count]],
                   "constraint_columns": [c for _, c in groups],
                   "cache": "off"}
    t3 = time.perf_counter()
    basis.set_flexibility(exact_flexibility(ops, rows), ops)
    basis.stats["time_flexibility"] = time.perf_counter() - t3
    return basis


def conservative_state_matrix(basis: StateSpaceBasis, ops: Operators) -> np.ndarray:
    """Psi^T [[G, K], [-K, 0]] Psi (skew to round-off). Collective."""
    K_vw = basis.project(ops.K, "v", "w")
    return basis.project(ops.G, "v", "v") + K_vw - K_vw.T


def build_state_space_basis(ops: Operators, rows, settings: BasisSettings = BasisSettings(),
                            labels=None, whole: str = "refuse") -> StateSpaceBasis:
    """The A-orthonormal state-space basis of the complex modes and one complex state DBF per
    constraint (module docstring); `whole` as in basis.build_basis. Collective on ops.comm."""
    from .gyroscopic_basis import stable_modes

    rows = np.asarray(rows, dtype=np.int64)
    _check_rows(ops, rows)
    settings.strategy.check(ops)
    labels = labels or [f"row {r}" for r in rows]
    t0 = time.perf_counter()
    modes = stable_modes(ops, count=settings.modes, max_frequency_hz=settings.max_frequency_hz, whole=whole)
    seconds = time.perf_counter() - t0
    try:
        basis = _basis(ops, rows, settings, labels, modes, None)
    finally:
        modes.destroy()
    basis.stats["time_modes"] = seconds
    return basis


def richer_state_space_basis(ops: Operators, basis: StateSpaceBasis, modes: int) -> StateSpaceBasis:
    """The complex modes 1..`modes` and basis's own DBFs (not recomputed), A-orthonormalized (the
    error estimate's richer basis, accuracy.py). Collective."""
    from .gyroscopic_basis import stable_modes

    more = stable_modes(ops, count=modes, whole="extend")   # a repeated frequency at the cut taken whole
    modes = more.count
    settings = dataclasses.replace(basis.settings, modes=modes, max_frequency_hz=None)
    labels = [f"row {r}" for r in basis.constraint_rows]
    try:
        rich = _basis(ops, basis.constraint_rows, settings, labels, more, basis.raw)
    finally:
        more.destroy()
    rich.dbf_k, rich.dbf_k_auto, rich.dbf_branch = basis.dbf_k, basis.dbf_k_auto, basis.dbf_branch
    return rich


@dataclass(frozen=True)
class StateSpaceModel:
    """The first-order reduced model (module docstring), dense numpy arrays, the same on every rank
    (n = 2 (N + N_L) states eta). It has the interface the recorder, the output and the run read from
    a ReducedModel, with q = eta and q' = eta' (the samples' "reduced/q" and "reduced/qdot")."""

    A: np.ndarray           # Psi^T A Psi (I to round-off)
    B_state: np.ndarray     # B_r = Psi^T B Psi
    B: np.ndarray           # g^T Psi_w: the displacement part at the constraint DOFs
    B_velocity: np.ndarray  # g^T Psi_v
    r_c: np.ndarray
    base_load: np.ndarray   # Psi_v^T M r
    force_shape: np.ndarray
    constraints: ConstraintSet
    support: Harmonic
    force: object
    q0: np.ndarray          # eta(0) = Psi^T A x(0)
    p0: np.ndarray          # eta'(0) (zeros: what the recorder reports before the first sample)
    probe_B: np.ndarray
    probe_r: np.ndarray
    basis_info: dict
    r_rate: Optional[np.ndarray] = None    # A_r^-1 Psi_v^T M r: a jump of the support's rate in eta
    r_value: Optional[np.ndarray] = None   # A_r^-1 Psi_w^T K r: a jump of its displacement
    field: Optional[ReducedField] = None
    field_points: Optional[object] = None
    probe_shape: Optional[tuple] = None
    G = None
    form = "state_space"

    def coordinates_digest(self) -> str:
        """What the reduced coordinates eta mean (ReducedModel.coordinates_digest)."""
        return digest_of(A=self.A, B_state=self.B_state, B=self.B, B_velocity=self.B_velocity, probe_B=self.probe_B,
                         r_rate=self.r_rate, r_value=self.r_value, field_V=getattr(self.field, "V", None))

    @property
    def probe_sample_shape(self) -> tuple:
        return self.probe_shape or (self.probe_B.shape[0],)

    @property
    def size(self) -> int:
        return self.A.shape[0]

    # What the output writes as reduced/M, reduced/K, reduced/D (docs/outputs.md): A_r, B_r, 0.
    @property
    def M(self) -> np.ndarray:
        return self.A

    @property
    def K(self) -> np.ndarray:
        return self.B_state

    @property
    def damping(self) -> np.ndarray:
        return np.zeros_like(self.A)

    def external_force(self, t: float) -> np.ndarray:
        return applied(self.force_shape, self.force.value(t)) - self.base_load * self.support.acceleration(t)

    def constraint_state(self, t: float, q: np.ndarray, p=None):
        """Total displacement and velocity at the constraints from the state q = eta (p is not used)."""
        return self.B @ q + self.r_c * self.support.value(t), self.B_velocity @ q + self.r_c * self.support.rate(t)

    def probes(self, t: float, q: np.ndarray) -> np.ndarray:
        return self.probe_B @ q + self.probe_r * self.support.value(t)

    def energy(self, q: np.ndarray, p=None) -> float:
        """(w_t^T M w_t + w^T K w) / 2 = eta^T A_r eta / 2, J."""
        return 0.5 * q @ self.A @ q

    def rate(self, t: float, q: np.ndarray) -> np.ndarray:
        """eta' = A_r^-1 (-B_r eta + f_r(t) + Psi_v^T g N(z, v))."""
        out = -self.B_state @ q + self.external_force(t)
        if self.B.shape[0]:
            out += self.B_velocity.T @ self.constraints.force(*self.constraint_state(t, q))
        return out if np.array_equal(self.A, np.eye(self.size)) else np.linalg.solve(self.A, out)

    def support_jump(self, value: float, rate: float) -> tuple:
        """ReducedModel.support_jump for eta (value, rate: the old support values minus the new ones):
        the relative state x = [u'; u] takes [r rate; r value], projected as the initial state is
        (eta = A_r^-1 Psi^T A x); eta' is not a state (zeros)."""
        if self.r_rate is None:
            return np.zeros(self.size), np.zeros(self.size)
        return self.r_rate * rate + self.r_value * value, np.zeros(self.size)

    def with_case(self, constraints=None, support=None, force=None, q0=None, p0=None) -> "StateSpaceModel":
        return dataclasses.replace(self, **case_changes(self, constraints, support, force, q0, p0))


def reduce_state_space(fom, basis: StateSpaceBasis, field: ReducedField | None = None) -> StateSpaceModel:
    """Project the full-order model onto the state-space basis (module docstring). Collective."""
    ops = fom.operators
    n = basis.size
    A_r = basis.state_energy(ops)
    K_vw = basis.project(ops.K, "v", "w")
    if ops.C is not None:
        C = basis.project(ops.C, "v", "v")
    elif fom.damping.kind == "modal":
        raise InputError("[damping] zeta: modal damping ratios have no meaning for the state-space basis of a "
                         "gyroscopic structure; give rayleigh_alpha / rayleigh_beta")
    else:   # Rayleigh: Psi_v^T (alpha M + beta K) Psi_v
        C = fom.damping.reduced_matrix(basis.project(ops.K, "v", "v"), basis.project(ops.M, "v", "v"))
    B_r = C + basis.project(ops.G, "v", "v") + K_vw - K_vw.T
    rows = fom.constraints.flat_rows
    base_load = basis.velocity_dot(ops.base_mass_load) if fom.moving_support else np.zeros(n)
    if fom.force_load is not None:
        force_shape = basis.velocity_dot(fom.force_load)
    elif fom.force_row is not None:
        force_shape = basis.velocity_rows([fom.force_row])[0]
    elif fom.force_matrix is not None:
        force_shape = basis.velocity_dot_rows(fom.force_matrix.rows)
    else:
        force_shape = np.zeros(n)
    r_rate = r_value = None
    if fom.moving_support:      # the influence r in eta, as rate and as displacement (support_jump)
        Mr, Kr = ops.influence.duplicate(), ops.influence.duplicate()
        ops.M.mult(ops.influence, Mr)
        ops.K.mult(ops.influence, Kr)
        r_rate = np.linalg.solve(A_r, basis.velocity_dot(Mr))
        r_value = np.linalg.solve(A_r, basis.displacement_dot(Kr))
        destroy(Mr, Kr)
    q0 = np.zeros(n)
    if fom.initial.amplitude:   # eta(0) = Psi^T A x(0), x(0) = [u'(0); u(0)]
        u, v = fom.initial_state()
        Mv, Ku = v.duplicate(), u.duplicate()
        ops.M.mult(v, Mv)
        ops.K.mult(u, Ku)
        q0 = np.linalg.solve(A_r, basis.comm.tompi4py().allreduce(
            _local(basis.velocity).T @ Mv.getArray(readonly=True) + _local(basis.displacement).T @ Ku.getArray(
                readonly=True)))
        destroy(u, v, Mv, Ku)
    info = {"omega": basis.omega, "enrichment_omega": basis.enrichment_omega, "dbf_k": basis.dbf_k,
            "enrichment": basis.enrichment, "flexibility_captured": basis.flexibility_captured,
            "flexibility_exact": basis.flexibility_exact, "complex_modes": basis.complex_modes,
            "constraint_kinds": constraint_kinds(ops, fom.constraints), "form": "state_space"}

    def at(points):
        needed = points.needed_rows
        if not needed.size:
            return np.zeros((points.count, n))
        return points.combine(basis.rows(needed), needed)

    return StateSpaceModel(A=A_r, B_state=B_r, B=basis.rows(rows), B_velocity=basis.velocity_rows(rows),
                           r_c=fom.influence_at(rows), base_load=base_load, force_shape=force_shape,
                           constraints=fom.constraints, support=fom.support, force=fom.force, q0=q0, p0=np.zeros(n),
                           probe_B=at(fom.probes), probe_r=fom.support_share(fom.probes), basis_info=info,
                           r_rate=r_rate, r_value=r_value, field=field, field_points=ops.field_map(),
                           probe_shape=fom.probes.shape)


# ---------------------------------------------------------------------------------------------------
# Time integration: PETSc TS ARKIMEX on y = eta (the C callbacks, or these Python ones: the reference)


class StateSpaceProblem:
    """The TS callbacks of eta' = A_r^-1 (-B_r eta + f_r(t) + B_v^T N(z, v)) in Python (the C ones,
    rom_core.c with RomCtx.first, take Bs, Bvt and the loads from here and compute the same):

        F(t, y, y') = y' + B_r y - B_v^T N(z, v)    implicit (contact implicit by default)
        G(t, y)     = f_r(t)                           explicit (forcing; the contact with contact = "explicit")
        dF/dy + shift dF/dy' = shift I + B_r - B_v^T (N_z B_w + N_v B_v)

    (all with A_r^-1 applied once)."""

    def __init__(self, model: StateSpaceModel, implicit_contact: bool):
        self.model = model
        self.implicit_contact = implicit_contact and model.B.shape[0] > 0
        self.r = n = model.size
        identity = np.array_equal(model.A, np.eye(n))
        solve = (lambda X: X) if identity else (lambda X: np.linalg.solve(model.A, X))
        self.Bs, self.Bvt = solve(model.B_state), solve(model.B_velocity.T)
        self.force_shape, self.base_load = solve(model.force_shape), solve(model.base_load)
        self.eye = np.eye(n)

    def contact(self, t, q):
        z, v = self.model.constraint_state(t, q)
        return self.Bvt @ self.model.constraints.force(z, v)

    def forcing(self, t) -> np.ndarray:
        m = self.model
        return applied(self.force_shape, m.force.value(t)) - self.base_load * m.support.acceleration(t)

    def coordinates(self, t, state, copy: bool = True):
        """(eta, eta') of a state vector's array (rom_integrator._Monitor): eta' from the equation."""
        q = state.copy()
        return q, self.rate(t, q)

    def commit(self, t, q, p) -> None:
        """The laws' state after an accepted step."""
        self.model.constraints.commit(*self.model.constraint_state(t, q))

    def rate(self, t, q) -> np.ndarray:
        out = -self.Bs @ q + self.forcing(t)
        if self.model.B.shape[0]:
            out += self.contact(t, q)
        return out

    @checked_by_the_integrator
    def ifunction(self, ts, t, y, ydot, f):
        q = y.getArray(readonly=True)
        out = f.getArray()
        out[:] = ydot.getArray(readonly=True) + self.Bs @ q
        if self.implicit_contact:
            out -= self.contact(t, q)

    @checked_by_the_integrator
    def ijacobian(self, ts, t, y, ydot, shift, J, P):
        m = self.model
        a = P.getDenseArray()
        a[:] = shift * self.eye + self.Bs
        if self.implicit_contact:
            q = y.getArray(readonly=True)
            z, v = m.constraint_state(t, q)
            d = m.constraints.dimension
            if d == 1:
                _, dz, dv = m.constraints.diagonal_jacobian(z, v)
                a -= self.Bvt @ (dz[:, None] * m.B + dv[:, None] * m.B_velocity)
            else:
                _, dz, dv = m.constraints.force_and_jacobian(z, v)
                n = self.r
                a -= self.Bvt @ (np.einsum("jab,jbr->jar", dz, m.B.reshape(-1, d, n)).reshape(-1, n)
                                 + np.einsum("jab,jbr->jar", dv, m.B_velocity.reshape(-1, d, n)).reshape(-1, n))
        P.assemble()
        if J != P:
            J.assemble()
        return True

    @checked_by_the_integrator
    def rhsfunction(self, ts, t, y, g):
        out = g.getArray()
        out[:] = self.forcing(t)
        if not self.implicit_contact and self.model.B.shape[0]:
            out += self.contact(t, y.getArray(readonly=True))
