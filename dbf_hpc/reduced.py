"""The reduced nonlinear model (DESIGN.md step 6; paper Eqs. 21, 27, 32):

    q'' + D_r q' + K_r q = f_r(t) + B^T N(z, v),    z = B q + r_c Omega(t),  v = B q' + r_c Omega'(t)

q: coordinates on V = [modes, DBFs] (V^T M V = I); K_r = V^T K V; B = G^T V (the basis at the
constraint DOFs); r_c: the support-motion influence at the constraints, so the law acts on the TOTAL
displacement and velocity; f_r = -V^T (M r) Omega''(t) + V^T g_F F(t) (support motion, point force);
D_r modal or Rayleigh damping. Small and dense: every rank holds the same arrays.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from mpi4py import MPI

from .basis import ReducedBasis
from .damping import Damping
from .errors import InputError
from .laws import ConstraintLaws
from .operators import values_at


@dataclass(frozen=True)
class Harmonic:
    """a sin(2 pi f t) and its derivatives. Omega(0) = 0: a run starts with the support at rest."""

    amplitude: float = 0.0
    frequency_hz: float = 0.0

    def value(self, t):
        return self.amplitude * np.sin(2 * np.pi * self.frequency_hz * t)

    def rate(self, t):
        w = 2 * np.pi * self.frequency_hz
        return self.amplitude * w * np.cos(w * t)

    def acceleration(self, t):
        w = 2 * np.pi * self.frequency_hz
        return -self.amplitude * w * w * np.sin(w * t)


class RandomProcess:
    """Band-limited random history with a flat one-sided PSD S over [f_low, f_high] (spectral
    representation, Shinozuka): sum_k sqrt(2 S df) cos(2 pi f_k t + phi_k), f_k at the centres of
    `components` equal bins, phi_k uniform from `seed`. Its variance is exactly S (f_high - f_low);
    it is smooth, so adaptive integrators handle it, and the same seed gives the same history."""

    def __init__(self, psd: float, band, seed: int, components: int = 256):
        f_low, f_high = band
        df = (f_high - f_low) / components
        self.frequency = f_low + (np.arange(components) + 0.5) * df
        self.amplitude = np.full(components, np.sqrt(2 * psd * df))
        self.phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, components)
        self.omega = 2 * np.pi * self.frequency

    def value(self, t):
        t = np.asarray(t, dtype=float)
        return np.cos(np.multiply.outer(t, self.omega) + self.phase) @ self.amplitude


@dataclass
class ReducedModel:
    """Everything the integrator needs, as dense numpy arrays (r = basis size, N_L constraints)."""

    K: np.ndarray              # K_r (r x r)
    D: np.ndarray              # D_r (r x r)
    B: np.ndarray              # constraint rows of V (N_L x r)
    r_c: np.ndarray            # influence vector at the constraints (N_L)
    base_load: np.ndarray      # V^T M r: f_r gets -base_load * Omega''(t)
    force_shape: np.ndarray    # V^T g_F: f_r gets force_shape * F(t)
    support: Harmonic          # Omega(t)
    force: object              # F(t): Harmonic or RandomProcess (anything with value(t))
    laws: ConstraintLaws
    q0: np.ndarray             # initial coordinates (relative displacement)
    p0: np.ndarray = None      # initial velocities (default: at rest)

    @property
    def size(self) -> int:
        return self.K.shape[0]

    def external_force(self, t: float) -> np.ndarray:
        return self.force_shape * self.force.value(t) - self.base_load * self.support.acceleration(t)

    def constraint_state(self, t: float, q: np.ndarray, p: np.ndarray):
        """Total displacement and velocity at the constraints."""
        return self.B @ q + self.r_c * self.support.value(t), self.B @ p + self.r_c * self.support.rate(t)

    def energy(self, q: np.ndarray, p: np.ndarray, t: float = 0.0) -> float:
        """Kinetic + strain + contact potential (J) of the relative motion (exact for free vibration)."""
        z, _ = self.constraint_state(t, q, p)
        return 0.5 * p @ p + 0.5 * q @ self.K @ q + float(np.sum(self.laws.potential(z)))


def _plain_dot(basis: ReducedBasis, vec) -> np.ndarray:
    """V^T x in the Euclidean inner product (the BV's dotVec would use M), on every rank. Collective."""
    dense = basis.vectors.getMat()
    local = dense.getDenseArray()
    out = local.T @ vec.getArray(readonly=True)
    basis.vectors.restoreMat(dense)
    return basis.vectors.getComm().tompi4py().allreduce(out)


def build_reduced_model(basis: ReducedBasis, ops, laws: ConstraintLaws, damping: Damping,
                        support: Harmonic, force, force_row: int | None = None, force_load=None,
                        initial_mode: int = 1, initial_amplitude: float = 0.0) -> ReducedModel:
    """Project the operators onto the basis. The force F(t) acts at one DOF (force_row) or as a load
    vector (force_load, a Vec: a distributed load). Collective on the basis' communicator."""
    K = basis.project(ops.K)
    K = 0.5 * (K + K.T)
    B = basis.rows(basis.constraint_rows)
    r = basis.size
    if ops.influence is not None and support.amplitude != 0.0:
        r_c = values_at(ops.influence, basis.constraint_rows)
        base_load = _plain_dot(basis, ops.base_mass_load)
    else:
        r_c, base_load = np.zeros(basis.constraint_rows.size), np.zeros(r)
    if force_load is not None:
        force_shape = _plain_dot(basis, force_load)
    else:
        force_shape = np.zeros(r) if force_row is None else basis.rows([force_row])[0]
    if ops.C is not None:
        D = basis.project(ops.C)
        D = 0.5 * (D + D.T)
    else:
        D = damping.reduced_matrix(K)
    q0 = np.zeros(r)
    if initial_amplitude:
        if not 1 <= initial_mode <= basis.mode_count:
            raise InputError(f"[initial] mode = {initial_mode}: the basis has {basis.mode_count} reference modes")
        q0[initial_mode - 1] = initial_amplitude / _peak(basis, initial_mode - 1, ops)
    return ReducedModel(K=K, D=D, B=B, r_c=r_c, base_load=base_load, force_shape=force_shape,
                        support=support, force=force, laws=laws, q0=q0, p0=np.zeros(r))


def _peak(basis: ReducedBasis, column: int, ops) -> float:
    """max |w| of one basis vector: over the displacement DOFs of a beam, all DOFs otherwise."""
    dense = basis.vectors.getMat()
    lo, hi = dense.getOwnershipRange()
    values = dense.getDenseArray()[:, column]
    if ops.mesh is not None:
        w_rows = ops.mesh.row[:, 0]
        w_rows = w_rows[(w_rows >= lo) & (w_rows < hi)]
        values = values[w_rows - lo]
    local = float(np.abs(values).max(initial=0.0))
    basis.vectors.restoreMat(dense)
    return basis.vectors.getComm().tompi4py().allreduce(local, op=MPI.MAX)
