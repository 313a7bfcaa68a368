"""The reduced model (docs/design.md; paper Eqs. 21, 27, 32):

    M_r q'' + (C_r + G_r) q' + K_r q = f_r(t) + B^T N(z, v),   z = B q + r_c Omega(t),  v = B q' + r_c Omega'(t)

q: coordinates on V = [modes, enrichment columns] (V^T M V = I, so M_r is I to round-off);
K_r = V^T K V, C_r = V^T C V (or modal / Rayleigh damping, damping.py), G_r = V^T G V (gyroscopic,
skew: gyroscopic_basis.py; None without G); B = G^T V (the basis at the constraint DOFs); r_c: the support-motion influence
at the constraints, so the law acts on the TOTAL displacement and velocity;
f_r(t) = -V^T (M r) Omega''(t) + V^T g_F F(t), or with turbulence V^T W X(t) (W: m load shapes, X(t):
their m histories; excitation.CorrelatedProcess). None of the matrices is symmetrized: what the
projection gives is what is integrated.

A ReducedModel is small and holds numpy arrays only, the same on every rank: it can be handed to
any rank (a sweep's cases run side by side) and integrated there (rom_integrator.py). Its field
part (V at the points a snapshot shows) is present only when snapshots are asked for.

Nothing here is collective: the projection that makes a ReducedModel is (reductor.py).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .constraints import ConstraintSet
from .excitation import Harmonic


def applied(shape: np.ndarray, value) -> np.ndarray:
    """A load shape times its history: (r,) times a number, or (r, m) times an (m,) vector."""
    return shape * value if shape.ndim == 1 else shape @ value


@dataclass(frozen=True)
class ReducedField:
    """What reconstructs the field a snapshot shows from q: w = V_f q + s Omega(t)."""

    positions: np.ndarray   # (F,) x (m) of a beam's nodes, or DOF indices
    V: np.ndarray           # (F, r) the basis at the field points (0 at fixed DOFs)
    support: np.ndarray     # (F,) the influence r (and the moving support's 1) at the field points

    def at(self, q: np.ndarray, omega: float) -> np.ndarray:
        return self.V @ q + self.support * omega


def case_changes(model, constraints=None, support=None, force=None, q0=None, p0=None) -> dict:
    """What with_case changes (the arguments that are not None), checked against `model` (a
    ReducedModel or a state_space.StateSpaceModel): the same constraints (model.constraints.with_laws),
    a Harmonic support motion and a force history (a Harmonic checks its numbers), and a finite start
    of the model's size. Red team: q0 = [1e-4] on a basis of 4 was broadcast to every coordinate, and a
    support or force of another type failed deep in the integration (AttributeError, TypeError)."""
    from .errors import InputError

    changes = {}
    if constraints is not None:
        if not isinstance(constraints, ConstraintSet) or not np.array_equal(constraints.rows, model.constraints.rows):
            raise InputError(f"with_case constraints: give the model's own constraints with other laws "
                             f"(model.constraints.with_laws([...])), got {type(constraints).__name__}")
        changes["constraints"] = constraints
    if support is not None:
        if not isinstance(support, Harmonic):   # whose numbers it checks itself
            raise InputError(f"with_case support: give a Harmonic(amplitude (m), frequency_hz, phase), got {support!r}")
        changes["support"] = support
    if force is not None:
        if isinstance(force, type) or not callable(getattr(force, "value", None)):
            raise InputError(f"with_case force: give a force history (a Harmonic, N), got {force!r}")
        changes["force"] = force
    for name, value in (("q0", q0), ("p0", p0)):
        if value is None:
            continue
        try:
            array = np.array(value, dtype=float)
        except (TypeError, ValueError):
            array = None
        if array is None or array.shape != (model.size,) or not np.all(np.isfinite(array)):
            raise InputError(f"with_case {name}: give {model.size} finite reduced coordinates (one per basis vector), "
                             f"got {value!r}")
        changes[name] = array
    return changes


def digest_of(**arrays) -> str:
    """sha256 of the named arrays that are not None (a model's coordinates_digest)."""
    from .checkpoint import arrays_sha256

    return arrays_sha256({name: value for name, value in arrays.items() if value is not None})


@dataclass(frozen=True)
class ReducedModel:
    """Everything the integrator and the output need, as dense numpy arrays (r = basis size,
    N_L d constraint components, P probes). See the module docstring for the equations.

    basis_info   what the output records about the basis: omega, enrichment_omega, dbf_k (arrays)
                 and enrichment (its kind)
    r_q          V^T M r: the influence vector projected onto the basis (zeros without support
                 motion), to keep the total state continuous when the support motion jumps
                 (support_jump, sweep.py)
    field        what reconstructs snapshots (ReducedField, only when asked for), field_points where
                 the field's values are (operators.PointValues, for the output's geometry)
    """

    M: np.ndarray
    C: np.ndarray
    K: np.ndarray
    B: np.ndarray
    r_c: np.ndarray
    base_load: np.ndarray
    force_shape: np.ndarray
    constraints: ConstraintSet
    support: Harmonic
    force: object
    q0: np.ndarray
    p0: np.ndarray
    probe_B: np.ndarray
    probe_r: np.ndarray
    basis_info: dict
    r_q: Optional[np.ndarray] = None
    G: Optional[np.ndarray] = None
    field: Optional[ReducedField] = None
    field_points: Optional[object] = None
    probe_shape: Optional[tuple] = None

    def coordinates_digest(self) -> str:
        """sha256 of what the reduced coordinates q mean: the reduced mass and stiffness (and G), the
        basis at the constraints, probes and field points, and the influence on the basis. Two models
        with one digest map a state q to the same physical state; a basis rebuilt with a repeated
        frequency's modes in another orientation (another rank layout) has the same cache key but not
        the same digest. Damping, laws and loads are not part of it: a continuation may change them."""
        return digest_of(M=self.M, K=self.K, B=self.B, probe_B=self.probe_B, r_q=self.r_q, G=self.G,
                         field_V=getattr(self.field, "V", None))

    @property
    def probe_sample_shape(self) -> tuple:
        """The shape of one sample of the probes: (P,), or (P, 2) (y, z) on a beam of two planes."""
        return self.probe_shape or (self.probe_B.shape[0],)

    @property
    def size(self) -> int:
        return self.K.shape[0]

    @property
    def damping(self) -> np.ndarray:
        """C_r + G_r: everything that multiplies q'."""
        return self.C if self.G is None else self.C + self.G

    def external_force(self, t: float) -> np.ndarray:
        """f_r(t)."""
        return applied(self.force_shape, self.force.value(t)) - self.base_load * self.support.acceleration(t)

    def constraint_state(self, t: float, q: np.ndarray, p: np.ndarray):
        """Total displacement and velocity at the constraints (flat, N_L d)."""
        return self.B @ q + self.r_c * self.support.value(t), self.B @ p + self.r_c * self.support.rate(t)

    def probes(self, t: float, q: np.ndarray) -> np.ndarray:
        """Total displacement at the probes."""
        return self.probe_B @ q + self.probe_r * self.support.value(t)

    def energy(self, q: np.ndarray, p: np.ndarray) -> float:
        """Kinetic plus strain energy of the linear part, (p^T M p + q^T K q) / 2, J (relative
        coordinates; the constraints' potential is not included: constraints.laws.potential(z))."""
        return 0.5 * (p @ self.M @ p + q @ self.K @ q)

    def support_jump(self, value: float, rate: float) -> tuple:
        """(dq, dp) that keep the total displacement and velocity continuous at a case boundary (a
        sweep's continuation) where the support's displacement and rate change: `value` (m) and `rate`
        (m/s) are the old values minus the new ones (minus the jump, as sweep.py passes them), and the
        relative state takes r times them, r as the basis holds it (M_r^-1 V^T M r)."""
        if self.r_q is None or not np.any(self.r_q):
            return np.zeros(self.size), np.zeros(self.size)
        r = np.linalg.solve(self.M, self.r_q)
        return r * value, r * rate

    def with_case(self, constraints: ConstraintSet | None = None, support: Harmonic | None = None, force=None,
                  q0=None, p0=None) -> "ReducedModel":
        """The same reduced operators with another law, excitation history or initial state (what
        the cases of a sweep change; none of it needs a new basis)."""
        return dataclasses.replace(self, **case_changes(self, constraints, support, force, q0, p0))
