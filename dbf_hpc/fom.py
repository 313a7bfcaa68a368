"""The full-order model: the whole discretized structure with its constraints and loads.

    M u'' + C u' + K u = -(M r) Omega''(t) + g_F F(t) + G N(G^T u + r_c Omega(t), G^T u' + r_c Omega'(t))

u: displacement over the free DOFs relative to the support motion (paper Eqs. 26-27); r: the
influence vector of a unit support motion, r_c = G^T r; G: the unit vectors at the constraint DOFs
(constraints.py); g_F F(t): a point force or a distributed load; C: a damping matrix or Rayleigh
alpha M + beta K. The laws act on the TOTAL displacement and velocity at the constraints.

A FullOrderModel owns its PETSc objects (the operators, the load vector, a Rayleigh C) and frees
them in `destroy` (or at the end of a `with` block). It is what the full-order integrator
(fom_integrator.py) steps and what a reductor (reductor.py) projects. Everything here is collective on the model's communicator unless it says otherwise.
"""
from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .constraints import Constraint, ConstraintSet
from .damping import Damping
from .errors import InputError, check_number
from .excitation import (BaseMotion, CorrelatedProcess, NoExcitation, PointForce, RandomForce, Turbulence,
                         coherence_factor, time_functions, unit_direction)
from .laws import ConstraintLaws, PlanarLaws
from .matrices import MatrixFiles, load_operators
from .operators import Operators, PointValues
from .petsctools import destroy, petsc_comm, petsc_errors_as_one_line, values_at
from .structure import Beam, assemble_beam, distributed_load, span_node_loads


# The laws with a stop at a clearance (table, linear, cubic and friction act from z = 0)
STOP_LAWS = ("deadband", "power", "hertz", "circular", "flat_bar")


def check_displacement(value: float, length: float, where: str, what: str) -> None:
    """A displacement given (m) is at most the beam's length (m): a linear (small-deflection) beam
    carries motions far smaller than itself, and one larger is a unit slip (mm given as m). Red team:
    the paper beam's 5 mm support motion given as amplitude = 5, and an initial displacement of 3 m,
    ran to the end without a word on a 1 m beam."""
    if abs(value) > length:
        raise InputError(f"{where}: amplitude = {value:g} m, {what}, is more than the beam's length "
                         f"({length:g} m): a linear (small-deflection) beam model cannot carry it; check its "
                         f"unit (m: 5 mm is 5e-3)")


def check_stops_within_reach(constraints, length: float, name) -> None:
    """A stop farther than the beam's length (m) (on a side that has one: k > 0) is refused, as a support
    motion or an initial displacement longer than the beam is (check_displacement): a linear
    (small-deflection) beam never reaches it, and it is a unit slip (2.5 mm given as 2.5). It only drew
    the idle-stop warning after the whole run (run.idle_warnings: a linear run's result under a scene
    that describes impacts). name(i): how the message names constraint i (0-based)."""
    for i, c in enumerate(constraints):
        law = c.law
        if law.kind not in STOP_LAWS:
            continue
        one_d = hasattr(law, "k_minus")
        ks = (law.k_minus, law.k_plus) if one_d else (law.k, law.k)
        gaps = (law.clearance_minus, law.clearance_plus)
        for side, gap, k in zip(("minus", "plus"), gaps, ks):
            if k > 0 and gap > length:
                key = f"clearance_{side}" if one_d and gaps[0] != gaps[1] else "clearance"
                other = f", or set k_{side} = 0 for a side without a stop" if key != "clearance" else ""
                raise InputError(f"{name(i)}: {key} = {gap:g} m is more than the beam's length "
                                 f"({length:g} m): a linear (small-deflection) beam never reaches that stop; check its "
                                 f"unit (m: 2.5 mm is 2.5e-3){other}")


@dataclass(frozen=True)
class InitialState:
    """The state at t = 0: at rest in relative coordinates, or displaced by `amplitude` (m, peak over
    the displacement DOFs) in reference mode `mode` (counted from 1). On a beam of two planes,
    `mode` counts the planar modes (each a y-z pair of the round tube) and the displacement is that
    shape along the unit vector `direction` (dy, dz); `velocity` (m/s, peak) starts the same shape
    moving along `velocity_direction`: across `direction`, the tube whirls in its holes."""

    mode: int = 1
    amplitude: float = 0.0
    direction: tuple = (1.0, 0.0)
    velocity: float = 0.0
    velocity_direction: tuple = (0.0, 1.0)

    def __post_init__(self):
        """Numbers checked once, the directions scaled to unit vectors (as a scene's are)."""
        object.__setattr__(self, "mode", check_number("InitialState mode", self.mode, 1, integer=True))
        for name in ("amplitude", "velocity"):
            object.__setattr__(self, name, check_number(f"InitialState {name}", getattr(self, name)))
        for name in ("direction", "velocity_direction"):
            object.__setattr__(self, name, unit_direction(f"InitialState {name}", getattr(self, name)))

    @property
    def planar(self) -> bool:
        """Whether a beam bending in one plane can start so: displaced along y, not moving."""
        return not self.velocity and self.direction == (1.0, 0.0)


EXCITATIONS = (NoExcitation, BaseMotion, PointForce, RandomForce, Turbulence)


class FullOrderModel:
    """A structure, its constraints, excitation, damping, probes and initial state (module docstring).

    operators    the distributed K, M (C) with the influence vector and field map
    constraints  ConstraintSet (rows, laws, labels)
    excitation   the description (excitation.py); support and force are its time functions
    force_row    the DOF of a point force, or None; force_load the Vec of a distributed one, or None
    force_matrix turbulence (excitation.Turbulence): a MatrixLoad, the load matrix W whose columns
                 the histories of `force` (a CorrelatedProcess, value(t) a vector) multiply, or None
    probes       the displacement at the probes (PointValues: a DOF of a matrix model, or a beam's
                 Hermite interpolation between nodes: a probe never adds a node)
    fingerprint  what identifies the operators (for the basis cache)
    """

    def __init__(self, operators: Operators, constraints: ConstraintSet, excitation, damping: Damping,
                 probes: PointValues, initial: InitialState, fingerprint: dict,
                 force_row: int | None = None, force_load: PETSc.Vec | None = None,
                 force_matrix: "MatrixLoad | None" = None):
        self._operators, self.constraints, self.excitation = operators, constraints, excitation
        self.damping, self.initial, self.fingerprint = damping, initial, fingerprint
        self.probes = probes
        self.force_row, self.force_load, self.force_matrix = force_row, force_load, force_matrix
        self.support, self.force = time_functions(excitation)
        if force_matrix is not None:
            self.force = force_matrix.process
        self._C = self._CG = None

    # -- construction -------------------------------------------------------------------------
    @classmethod
    @petsc_errors_as_one_line("FullOrderModel.build")
    def build(cls, structure, constraints=(), excitation=NoExcitation(), damping: Damping = Damping(),
              probes=(), initial: InitialState = InitialState(), comm=None) -> "FullOrderModel":
        """Assemble or load the operators of `structure` (a Beam or MatrixFiles) and place the
        constraints (Constraint descriptions), loads and probes on them. Collective on comm
        (a petsc4py or mpi4py communicator, default COMM_WORLD). Bad placements are InputErrors,
        and nothing is leaked."""
        comm = petsc_comm(comm, "FullOrderModel.build")
        if not isinstance(structure, (Beam, MatrixFiles)):
            raise InputError(f"FullOrderModel.build: a structure is a Beam or MatrixFiles, got {type(structure).__name__}")
        for name, value, kinds in (("excitation", excitation, EXCITATIONS), ("damping", damping, (Damping,)),
                                   ("initial", initial, (InitialState,))):
            if not isinstance(value, kinds):
                raise InputError(f"FullOrderModel.build: {name} must be {' or '.join(k.__name__ for k in kinds)}, "
                                 f"got {type(value).__name__}")
        probes = _probe_places(structure, probes)
        if isinstance(constraints, Constraint) or not isinstance(constraints, (list, tuple)):
            raise InputError(f"FullOrderModel.build: give the constraints as a list of Constraint, got "
                             f"{type(constraints).__name__}")
        constraints = tuple(constraints)
        on_beam = isinstance(structure, Beam)
        for j, c in enumerate(constraints):
            if not isinstance(c, Constraint):
                raise InputError(f"FullOrderModel.build: constraint {j + 1} is a {type(c).__name__}, not a Constraint")
            if (c.x is None) == on_beam:
                raise InputError(f"FullOrderModel.build: constraint {j + 1} needs {'x (m)' if on_beam else 'dof'} "
                                 f"on a {type(structure).__name__}")
        if excitation.kind == "force" and (excitation.x is None) == on_beam:   # a TypeError before (red team)
            raise InputError(f"FullOrderModel.build: the PointForce needs {'x (m)' if on_beam else 'dof'} on a "
                             f"{type(structure).__name__}")
        planes = structure.planes if isinstance(structure, Beam) else 1
        _check_dimensions(constraints, planes)
        if isinstance(structure, MatrixFiles) and structure.damping and damping.kind != "none":
            raise InputError(DAMPING_TWICE)
        if excitation.kind in ("random", "turbulence") and not isinstance(structure, Beam):   # before the files are read
            raise InputError(f"{excitation.kind} forcing is distributed along a beam; not available for matrices")
        if planes == 1 and (getattr(excitation, "direction", (1.0, 0.0)) != (1.0, 0.0) or not initial.planar):
            raise InputError("FullOrderModel.build: a direction (dy, dz) or an initial velocity applies to a beam of "
                             "two planes (Beam(planes=2)); this structure moves along one direction only")
        if isinstance(structure, Beam):   # what a scene refuses (scene.py), the API refuses too
            check_stops_within_reach(constraints, structure.length, lambda i: f"FullOrderModel.build: constraint {i + 1}")
            if excitation.kind == "base":
                check_displacement(excitation.amplitude, structure.length, "FullOrderModel.build: BaseMotion",
                                   "the support's motion")
            check_displacement(initial.amplitude, structure.length, "FullOrderModel.build: InitialState",
                               "the peak initial displacement")
            ops = _beam_operators(structure, constraints, excitation, comm)
            beam = dataclasses.asdict(structure)
            if planes == 1:
                del beam["planes"]   # the cache keys of planar beams stay what they were
            for key, default in (("axial_speed", 0.0), ("transported_mass", None), ("tension", 0.0)):
                if beam[key] == default:
                    del beam[key]    # nor do those of beams without axial transport or tension
            fingerprint = {"beam": beam, "nodes": hashlib.sha256(ops.mesh.x.tobytes()).hexdigest()}
        else:   # MatrixFiles (checked above)
            ops = load_operators(structure, comm)
            fingerprint = None
        force_load = force_matrix = None
        try:
            if fingerprint is None:
                fingerprint = structure.fingerprint(comm)
            rows = [_row(ops, c.x, c.dof, f"constraint at {c.label}") for c in constraints]
            _distinct(rows, constraints)
            laws = [c.law for c in constraints]
            rows = np.asarray(rows, dtype=np.int64).reshape(-1, 1)
            if planes == 2:
                rows = np.column_stack([rows[:, 0], [_row(ops, c.x, None, f"constraint at {c.label}", plane=1)
                                                     for c in constraints]]).astype(np.int64)
            constraint_set = ConstraintSet(rows=rows.reshape(len(constraints), planes),
                                           laws=PlanarLaws(laws) if planes == 2 else ConstraintLaws(laws),
                                           labels=tuple(c.label for c in constraints),
                                           positions=np.array([c.position for c in constraints], dtype=float))
            probes = _probes(ops, probes, excitation)
            force_row = None
            if excitation.kind == "force" and planes == 2:
                force_load = _point_load(ops, excitation)
            elif excitation.kind == "force":
                force_row = _row(ops, excitation.x, excitation.dof, "the force")
            elif excitation.kind == "random":
                force_load = distributed_load(ops, *(excitation.span or (0.0, structure.length)),
                                              direction=excitation.direction)
            elif excitation.kind == "turbulence":
                force_matrix = MatrixLoad.turbulence(ops, excitation)
            if excitation.kind == "base" and ops.influence is None:
                raise InputError("base excitation of a matrices structure needs [structure] influence")
            return cls(ops, constraint_set, excitation, damping, probes, initial, fingerprint, force_row, force_load,
                       force_matrix)
        except Exception:
            destroy(force_load)
            if force_matrix is not None:
                force_matrix.destroy()
            ops.destroy()
            raise

    # -- what the integrators and the reductor read -------------------------------------------
    @property
    def operators(self) -> Operators:
        """The distributed operators; an InputError once the model is destroyed (its PETSc objects are
        gone: using them would crash the process). Not collective."""
        if self._operators is None:
            raise InputError("this FullOrderModel was destroyed (its with block has closed, or destroy() was "
                             "called): use it inside the with block, or build it again")
        return self._operators

    @property
    def comm(self):
        return self.operators.comm

    @property
    def size(self) -> int:
        return self.operators.size

    @property
    def moving_support(self) -> bool:
        """Whether the support moves (and so r Omega(t) enters the loads and the laws)."""
        return self.operators.influence is not None and self.support.amplitude != 0.0

    def influence_at(self, rows) -> np.ndarray:
        """r at the given rows (zeros without support motion), on every rank."""
        rows = np.asarray(rows, dtype=np.int64)
        return values_at(self.operators.influence, rows) if self.moving_support else np.zeros(rows.size)

    def support_share(self, points: PointValues) -> np.ndarray:
        """(P,) the support motion's share of the displacement at `points`: r combined as the
        points combine u, plus the moving support's fixed DOF; zeros without support motion. The
        total is points.take(u) + support_share(points) Omega(t). On every rank."""
        if not self.moving_support:
            return np.zeros(points.count)
        needed = points.needed_rows
        return points.combine(self.influence_at(needed), needed) + points.moving

    def field_support(self) -> np.ndarray:
        """support_share of the field a user sees (the nodes of a beam, every DOF of a matrix model)."""
        return self.support_share(self.operators.field_map())

    def damping_matrix(self) -> PETSc.Mat | None:
        """C: the given matrix, or Rayleigh alpha M + beta K (built once, owned here). Modal damping
        has no sparse full-order form: an InputError."""
        ops = self.operators
        if ops.C is not None:
            return ops.C
        if self.damping.kind == "modal":
            raise InputError("--method full: modal damping ([damping] zeta) has no sparse full-order counterpart; "
                             "give Rayleigh coefficients ([damping] rayleigh_alpha, rayleigh_beta) or a damping matrix")
        if self.damping.kind == "none":
            return None
        if self._C is None:
            self._C = ops.M.duplicate(copy=True)
            self._C.scale(self.damping.rayleigh_alpha)
            self._C.axpy(self.damping.rayleigh_beta, ops.K, PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        return self._C

    def add_loads(self, t: float, F: PETSc.Vec, scale: float = 1.0) -> None:
        """F += scale * (external load at t): -(M r) Omega''(t) + g_F F(t). Not collective."""
        ops = self.operators
        if self.moving_support:
            F.axpy(-scale * self.support.acceleration(t), ops.base_mass_load)
        if self.force_load is not None:
            F.axpy(scale * float(self.force.value(t)), self.force_load)
        if self.force_row is not None:
            lo, hi = F.getOwnershipRange()
            if lo <= self.force_row < hi:
                F.getArray()[self.force_row - lo] += scale * float(self.force.value(t))
        if self.force_matrix is not None:
            F.getArray()[:] += scale * self.force_matrix.local(t)

    def initial_state(self) -> tuple:
        """(u(0), u'(0)): on a beam of two planes two_plane_state(); on a gyroscopic structure (G set)
        with an amplitude the free vibration of complex mode `initial.mode` (gyroscopic.mode_state),
        `initial.amplitude` m peak in u; otherwise initial_displacement() and u'(0) = 0. New Vecs, the
        caller's. Collective."""
        try:
            return self._initial_state()
        except InputError as e:   # "number of modes must be between 1 and 80" named no [initial] (red team)
            raise InputError(f"[initial] mode = {self.initial.mode}: {e}") from None

    def _initial_state(self) -> tuple:
        if self.operators.mesh is not None and self.operators.mesh.planes == 2:
            return self.two_plane_state()
        if self.operators.G is None or not self.initial.amplitude:
            u = self.initial_displacement()
            v = u.duplicate()
            v.zeroEntries()
            return u, v
        from .gyroscopic import mode_state

        u, v = mode_state(self.operators, self.initial.mode)
        try:
            scale = self.initial.amplitude / field_peak(self.operators, u)
            u.scale(scale)
            v.scale(scale)
        except BaseException:
            destroy(u, v)
            raise
        return u, v

    def two_plane_state(self) -> tuple:
        """(u(0), u'(0)) on a beam of two planes: planar mode `initial.mode` as a shape phi (peak 1 in
        w), u = amplitude (dy phi_y + dz phi_z), u' = velocity (ey phi_y + ez phi_z). New Vecs, the
        caller's. Collective."""
        init = self.initial
        # the planar mode first: a mode the basis does not have is an InputError with no Vec made yet
        y, z = planar_mode(self.operators, init.mode) if init.amplitude or init.velocity else (None, None)
        u, v = self.operators.K.createVecLeft(), self.operators.K.createVecLeft()
        try:
            u.zeroEntries()
            v.zeroEntries()
            if y is not None:
                for vec, scale, (dy, dz) in ((u, init.amplitude, init.direction), (v, init.velocity,
                                                                                init.velocity_direction)):
                    vec.axpy(scale * dy, y)
                    vec.axpy(scale * dz, z)
        except BaseException:
            destroy(u, v)
            raise
        finally:
            if y is not None:
                destroy(y, z)
        return u, v

    def velocity_matrix(self) -> PETSc.Mat | None:
        """C + G (built once, owned here): what multiplies u' in the full-order equations; the damping
        matrix alone (or None) without G."""
        C, G = self.damping_matrix(), self.operators.G
        if G is None:
            return C
        if self._CG is None:
            self._CG = G.duplicate(copy=True)
            if C is not None:
                self._CG.axpy(1.0, C, PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
        return self._CG

    def initial_displacement(self) -> PETSc.Vec:
        """u(0): zero, or `initial.amplitude` m peak (over the field's DOFs) in reference mode
        `initial.mode`."""
        from .modes import reference_modes, repeated_mode_refusal

        # the modes first: an [initial] mode the structure does not have is an InputError with no Vec made yet
        modes = reference_modes(self.operators, count=self.initial.mode) if self.initial.amplitude else None
        if modes is not None:   # the modes of a repeated frequency taken whole (reference_modes)
            refusal = repeated_mode_refusal(modes.omega ** 2, self.initial.mode, self.operators.rigid_modes)
            if refusal:
                modes.destroy()
                raise InputError(refusal)
        u = self.operators.K.createVecRight()
        u.zeroEntries()
        if modes is None:
            return u
        try:
            modes.vectors.copyVec(self.initial.mode - 1, u)
            u.scale(self.initial.amplitude / field_peak(self.operators, u))
        except Exception:
            u.destroy()
            raise
        finally:
            modes.destroy()
        return u

    def destroy(self) -> None:
        """Free the PETSc objects (a second call does nothing); the model cannot be used after it.
        Collective."""
        if self._operators is None:
            return
        destroy(self._C, self._CG, self.force_load)
        if self.force_matrix is not None:
            self.force_matrix.destroy()
        self._operators.destroy()
        self._operators = self._C = self._CG = self.force_load = self.force_matrix = None

    def __enter__(self):
        self.operators   # a destroyed model is refused here, not at its first use
        return self

    def __exit__(self, *exc):
        self.destroy()


class MatrixLoad:
    """A load W X(t): a few load shapes (the columns of W, n x m) times their histories X(t) (a
    process whose value(t) is an (m,) vector). Each rank holds its rows of W as a dense numpy block
    (`rows`, local rows x m: small, and applying it is not collective). `vec` is a Vec of K's
    layout that __call__(t) fills with W X(t) and then returns 1.0, so that the full-order loop
    takes it as one more (vector, time function) load (fom_integrator.py)."""

    def __init__(self, rows: np.ndarray, process, vec: PETSc.Vec, points: np.ndarray, factor: np.ndarray):
        self.rows, self.process, self.vec = rows, process, vec
        self.points, self.factor = points, factor     # the span's nodes, and H (H H^T ~ coherence)

    @classmethod
    def turbulence(cls, ops: Operators, turbulence) -> "MatrixLoad":
        """The load of an excitation.Turbulence on a beam: p = H X(t) at the span's nodes (H from
        excitation.coherence_factor, one factor for both planes; X independent histories, those of
        the z plane after those of y), W = L blockdiag(H, H) with L the consistent hat loads
        (structure.span_node_loads). Not collective (every rank builds the same H and X)."""
        points, L = span_node_loads(ops, *(turbulence.span or (ops.mesh.x[0], ops.mesh.x[-1])))
        H = coherence_factor(turbulence.coherence(points))
        n, m, planes = points.size, H.shape[1], ops.mesh.planes
        rows = np.hstack([L[:, p * n:(p + 1) * n] @ H for p in range(planes)])
        return cls(rows, CorrelatedProcess(turbulence, planes * m), ops.K.createVecLeft(), points, H)

    @property
    def count(self) -> int:
        """m, the number of histories."""
        return self.rows.shape[1]

    def local(self, t: float) -> np.ndarray:
        """This rank's rows of W X(t)."""
        return self.rows @ self.process.value(t)

    def nodal(self, t: float) -> np.ndarray:
        """p(t) at the span's nodes, (planes, n) in N/m (what the tests compare with the target)."""
        X = self.process.value(t).reshape(-1, self.factor.shape[1])
        return X @ self.factor.T

    def __call__(self, t: float) -> float:
        self.vec.getArray()[:] = self.local(t)
        return 1.0

    def destroy(self) -> None:
        destroy(self.vec)
        self.vec = None


class Observation:
    """What a recorder needs from a full-order state: the DOF rows to gather (the constraints', then
    those the probes combine), and from their values and rates the total displacement and velocity
    at the constraints and the total displacement at the probes. Not collective once built."""

    def __init__(self, fom: FullOrderModel):
        rows = fom.constraints.flat_rows
        self._set(rows, fom.influence_at(rows), fom.probes, fom.support_share(fom.probes), fom.support)

    @classmethod
    def of(cls, constraint_rows, r_c, probes: PointValues, probe_share, support) -> "Observation":
        """From its parts: r at the constraint rows, the probes and their support share (fom.py)."""
        observation = cls.__new__(cls)
        observation._set(np.asarray(constraint_rows), np.asarray(r_c, dtype=float), probes,
                         np.asarray(probe_share, dtype=float), support)
        return observation

    def _set(self, constraint_rows, r_c, probes, probe_share, support):
        self.probes, self.needed = probes, probes.needed_rows
        self.rows = np.concatenate([constraint_rows, self.needed]).astype(np.int64)
        self.nc = constraint_rows.size
        self.r_c, self.probe_share, self.support = r_c, probe_share, support

    def totals(self, t: float, values: np.ndarray, rates: np.ndarray):
        """(z, v, probe displacement) from u and u' at self.rows."""
        omega, rate, nc = self.support.value(t), self.support.rate(t), self.nc
        z, v = values[:nc] + self.r_c * omega, rates[:nc] + self.r_c * rate
        probe = self.probes.combine(values[nc:], self.needed) if self.needed.size else np.zeros(self.probes.count)
        return z, v, probe + self.probe_share * omega

    def constraint_totals(self, t: np.ndarray, values: np.ndarray, rates: np.ndarray):
        """Blocks of steps: t (k,), u and u' (k, >= N_L) at self.rows -> total z, v (k, N_L)."""
        nc = self.nc
        if not np.any(self.r_c):
            return values[:, :nc], rates[:, :nc]
        return (values[:, :nc] + np.outer(self.support.value(t), self.r_c),
                rates[:, :nc] + np.outer(self.support.rate(t), self.r_c))

    def block_totals(self, t: np.ndarray, values: np.ndarray, rates: np.ndarray):
        """Blocks of samples: t (J,), u and u' (J, len(self.rows)) -> total z, v (J, N_L) and the
        probes' total displacement (J, P)."""
        z, v = self.constraint_totals(t, values, rates)
        if self.needed.size:
            probe = self.probes.combine(values[:, self.nc:].T, self.needed).T
        else:
            probe = np.zeros((t.size, self.probes.count))
        return z, v, probe + np.outer(self.support.value(t), self.probe_share)


def planar_mode(ops: Operators, mode: int) -> tuple:
    """(phi_y, phi_z): planar mode `mode` (counted from 1) of a beam of two planes as a shape in y
    and the same shape in z, peak |w| = 1. The eigensolver returns any orthonormal pair of each y-z
    eigenspace; the pair's member with the larger y part, cut to its y rows, is the planar mode
    (the planes are uncoupled). Collective."""
    from .modes import reference_modes

    mesh = ops.mesh
    modes = reference_modes(ops, count=2 * mode)
    y_rows, z_rows = mesh.row[:, :2].ravel(), mesh.row[:, 2:].ravel()
    keep = y_rows >= 0           # the same DOFs are fixed in both planes
    y_rows, z_rows = y_rows[keep], z_rows[keep]
    lo, hi = ops.ownership_range()
    world = ops.comm.tompi4py()
    best, best_norm = None, -1.0
    for i in (2 * mode - 2, 2 * mode - 1):
        vec = ops.K.createVecLeft()
        modes.vectors.copyVec(i, vec)
        values = np.zeros(y_rows.size)
        mine = (y_rows >= lo) & (y_rows < hi)
        values[mine] = vec.getArray(readonly=True)[y_rows[mine] - lo]
        values = world.allreduce(values, op=MPI.SUM)
        vec.destroy()
        if np.linalg.norm(values) > best_norm:
            best, best_norm = values, np.linalg.norm(values)
    modes.destroy()
    peak = np.abs(best[_w_positions(mesh)]).max()
    shapes = []
    for rows in (y_rows, z_rows):
        vec = ops.K.createVecLeft()
        vec.zeroEntries()
        mine = (rows >= lo) & (rows < hi)
        vec.getArray()[rows[mine] - lo] = best[mine] / peak
        shapes.append(vec)
    return tuple(shapes)


def _w_positions(mesh) -> np.ndarray:
    """Among the free y DOFs in node order (w, dw/dx per node), the positions of the w's."""
    rows = mesh.row[:, :2]
    dof = np.broadcast_to(np.arange(2), rows.shape)
    return np.flatnonzero(dof[rows >= 0] == 0)


def field_peak(ops: Operators, u: PETSc.Vec) -> float:
    """max |u| over the DOFs of the field a user sees (w at the nodes of a beam, all DOFs of a
    matrix model). Collective."""
    lo, hi = u.getOwnershipRange()
    rows = ops.field_map().rows
    rows = rows[(rows >= lo) & (rows < hi)]
    local = float(np.abs(u.getArray(readonly=True)[rows - lo]).max(initial=0.0))
    return ops.comm.tompi4py().allreduce(local, op=MPI.MAX)


def _probe_places(structure, probes) -> tuple:
    """The probes as given to build, checked: x in m within a beam (a probe outside it would be
    extrapolated from the end element's shape functions), or DOF indices of a matrix model (their
    range is checked against the loaded matrices)."""
    if isinstance(probes, (str, bytes)) or not np.iterable(probes):
        probes = (probes,)
    out = []
    for p in probes:
        if isinstance(structure, Beam):
            x = check_number("FullOrderModel.build probe x (m)", p)
            if not 0 <= x <= structure.length:
                raise InputError(f"FullOrderModel.build: probe at x = {x:g} m is outside the beam [0, "
                                 f"{structure.length:g}] m")
            out.append(x)
        else:
            out.append(check_number("FullOrderModel.build probe dof", p, 0, integer=True))
    return tuple(out)


def _probes(ops: Operators, probes, excitation) -> PointValues:
    """The probes' PointValues: interpolated on a beam (no node added), a DOF of a matrix model."""
    if ops.mesh is not None:
        return ops.mesh.point_values(probes, excitation.end if excitation.kind == "base" else None,
                                     getattr(excitation, "direction", (1.0, 0.0)))
    for p in probes:
        if not 0 <= int(p) < ops.size:
            raise InputError(f"probe dof {int(p)} is outside the {ops.size} DOFs of the matrices")
    return PointValues.at_rows(np.asarray(probes, dtype=float), np.asarray(probes, dtype=np.int64))


def _beam_operators(beam: Beam, constraints, excitation, comm) -> Operators:
    points = [c.x for c in constraints]
    if excitation.kind == "force":
        points.append(excitation.x)
    elif excitation.kind in ("random", "turbulence"):
        points.extend(excitation.span)
    return assemble_beam(beam, comm, points=points, base_end=excitation.end if excitation.kind == "base" else None,
                         direction=getattr(excitation, "direction", (1.0, 0.0)))


# The reduced and full-order models take the damping matrix and ignore modal or Rayleigh damping beside it.
DAMPING_TWICE = ("a damping matrix ([structure] damping) and modal or Rayleigh damping ([damping] zeta, "
                 "rayleigh_alpha, rayleigh_beta) were both given, and only the matrix would act: give one (add "
                 "alpha M + beta K to the matrix yourself)")


def _check_dimensions(constraints, planes: int) -> None:
    """A beam of two planes takes 2-D laws only (circular, flat_bar), any other structure 1-D laws only."""
    for i, c in enumerate(constraints):
        d = getattr(c.law, "dimension", 1)
        if d == 2 and planes != 2:
            raise InputError(f"constraint {i + 1} ({c.label}): a {c.law.kind} law acts in two directions; it needs "
                             f"a beam bending in two planes ([structure] planes = 2)")
        if d == 1 and planes == 2:
            raise InputError(f"constraint {i + 1} ({c.label}): a beam of two planes takes 2-D laws "
                             f"(law = \"circular\" or \"flat_bar\"), not {c.law.kind}")


def _point_load(ops: Operators, excitation) -> PETSc.Vec:
    """A unit point force along `direction` (dy, dz) at x on a beam of two planes. Collective."""
    load = ops.K.createVecLeft()
    load.zeroEntries()
    lo, hi = load.getOwnershipRange()
    for plane in range(2):
        row = _row(ops, excitation.x, None, "the force", plane=plane)
        if lo <= row < hi:
            load.getArray()[row - lo] += excitation.direction[plane]
    return load


def _row(ops: Operators, x, dof, what: str, plane: int = 0) -> int:
    """The row of w at x (a beam; plane 1: z) or of `dof` (a matrix model); an InputError on a fixed
    DOF or outside the structure."""
    if ops.mesh is not None:
        row = ops.mesh.w_row(x, plane)
        if row < 0:
            raise InputError(f"{what} acts on a fixed DOF: it is on a support; move it or remove it")
        return row
    if not 0 <= dof < ops.size:
        raise InputError(f"{what} is outside the {ops.size} DOFs of the matrices")
    return int(dof)


def _distinct(rows, constraints) -> None:
    seen = {}
    for i, row in enumerate(rows):
        if row in seen:
            raise InputError(f"constraints {seen[row] + 1} and {i + 1} act on the same DOF "
                             f"({constraints[seen[row]].label} and {constraints[i].label}); remove one or merge their laws")
        seen[row] = i
