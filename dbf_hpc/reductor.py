"""The reductor: a full-order model and basis settings -> a basis -> a reduced model.

    with Reductor(fom, BasisSettings(modes=6), cache_dir) as reductor:
        rom = reductor.reduce(field=True)

The basis comes from the cache when a valid one exists (cache.py), else it is built (basis.py) and
stored. reduce() projects the operators and loads onto it (Eqs. 21, 27, 32; rom.py). Collective
on the full-order model's communicator; the reduced model it returns is the same on every rank.
"""
from __future__ import annotations

import os

import numpy as np
from petsc4py import PETSc

from .accuracy import constraint_kinds
from .basis import BasisSettings, ReducedBasis
from .cache import obtain_basis
from .errors import InputError, decided_on_rank0, warn
from .fom import FullOrderModel
from .modes import repeated_mode_refusal
from .petsctools import destroy, petsc_errors_as_one_line
from .rom import ReducedField, ReducedModel

PROJECTION_TOL = 1e-8   # relative defects of the projected M_r, K_r set to the method's exact values


def _turn(K: np.ndarray, M: np.ndarray, m: int, identity: bool):
    """(T, w, T^T K T with its modes' block diag(w)) for Reductor._turn_in_span, or None where M is not
    positive definite to working precision. Not collective."""
    r = M.shape[0]
    if identity:
        T = np.eye(r)
    else:
        try:
            T = np.linalg.inv(np.linalg.cholesky(0.5 * (M + M.T))).T
        except np.linalg.LinAlgError:
            return None
    K1 = T.T @ K @ T
    w, Q = np.linalg.eigh(0.5 * (K1[:m, :m] + K1[:m, :m].T))
    Q *= np.where(np.diag(Q) < 0.0, -1.0, 1.0)   # each mode keeps its orientation
    T[:, :m] = T[:, :m] @ Q
    if not np.all(np.isfinite(T)):
        return None
    K_turned = T.T @ K @ T
    K_turned[:m, :m] = np.diag(w)
    return T, w, K_turned


class Reductor:
    """Reduces a FullOrderModel: `settings` picks N reference modes, K phi = omega^2 M phi, and one
    enrichment column per constraint: a DBF (the method), the derivative d phi / dk at k_j of the first
    mode of the spring-perturbed structure K + k_j g_j g_j^T (paper Eqs. 13-17 and 34-39, k_j "auto" the
    corner of Fig. 2; dbf.py), or a static mode K^-1 g_j, or none; Gram-Schmidt in M (Eqs. 18-19, 40),
    hat-omega_j from Eq. 41. basis() builds it, reduce() projects the model onto it (a ReducedModel of
    numpy arrays). cache_dir: a directory of cached bases, read and written (None: always built, never
    cached; the command line's default is ~/.cache/dbf_hpc). Collective on the full-order model's
    communicator, as are basis() and reduce(). Owns the basis it obtains (destroyed with the reductor,
    destroy() or the end of its with block). As basis() obtains it, says what `dbf-hpc run` says of it
    (warnings(): a DBF stiffness far outside Fig. 2's transition, a static flexibility captured below 99 %,
    a lowest elastic frequency that suggests a unit slip), from rank 0 of the model's communicator
    (errors.warn, as simulate_reduced says its lines), unless warn_basis is False.
    """

    def __init__(self, fom: FullOrderModel, settings: BasisSettings = BasisSettings(), cache_dir: str | None = None,
                 basis: ReducedBasis | None = None, warn_basis: bool = True):
        """With `basis`, that basis (already built, e.g. basis.richer_basis; the reductor owns it, and says
        nothing of it). warn_basis False: basis() says nothing (the front ends that say the lines themselves,
        after their progress line: run.run, the sweep, `dbf-hpc basis`; the tolerance mode's candidates)."""
        if not isinstance(fom, FullOrderModel):
            raise InputError(f"Reductor reduces a FullOrderModel (FullOrderModel.build), got {type(fom).__name__}")
        if not isinstance(settings, BasisSettings):
            raise InputError(f"Reductor settings: give BasisSettings(...), got {settings!r}")
        fom.operators   # an InputError for a destroyed model
        if cache_dir is not None and not isinstance(cache_dir, (str, os.PathLike)):
            raise InputError(f"Reductor cache_dir: give a directory path (str) or None, got {cache_dir!r}")
        if not isinstance(warn_basis, (bool, np.bool_)):
            raise InputError(f"Reductor warn_basis: give True or False, got {warn_basis!r}")
        self.fom, self.settings, self.cache_dir = fom, settings, cache_dir
        self._basis, self._warn_basis = basis, bool(warn_basis)

    @petsc_errors_as_one_line("the basis", ("modes_", "dbf_", "static_"))
    def basis(self) -> ReducedBasis:
        """The basis (obtained once, and its warnings() said then, unless warn_basis is False). Collective."""
        if self._basis is None:
            fom = self.fom
            self._basis = obtain_basis(fom.operators, fom.constraints.flat_rows, self.settings, fom.fingerprint,
                                       self.cache_dir, fom.constraints.component_labels)
            if self._warn_basis:
                for message in self.warnings():
                    warn(message, fom.comm)
        return self._basis

    def warnings(self) -> list:
        """What `dbf-hpc run` warns of this basis whatever the forcing (run.basis_warnings: the same lines,
        the same order). Collective (it obtains the basis); the list is the same on every rank."""
        from .run import basis_warnings

        fom = self.fom
        return basis_warnings(self.basis(), fom.constraints.component_labels, fom.operators.rigid_modes,
                              fom.constraints.dimension)

    @petsc_errors_as_one_line("Reductor.reduce", ("modes_", "dbf_", "static_"))
    def reduce(self, field: bool = False) -> ReducedModel:
        """Project the full-order model onto the basis. With field, also the basis at the field
        points, for snapshots. Collective."""
        if not isinstance(field, (bool, np.bool_)):   # "no" would be truthy
            raise InputError(f"Reductor.reduce field: give True or False, got {field!r}")
        fom, basis = self.fom, self.basis()
        if getattr(basis, "form", "") == "state_space":   # the paper's first-order form (state_space.py)
            from .state_space import reduce_state_space
            return reduce_state_space(fom, basis, self._field() if field else None)
        ops = fom.operators
        K, M = basis.project(ops.K), basis.project(ops.M)
        structure = self._clean_projection(basis, K, M) if ops.G is None else {}
        if ops.C is None:
            fom.damping.check_rayleigh(basis.omega)
        C = basis.project(ops.C) if ops.C is not None else fom.damping.reduced_matrix(K, M, basis.mode_count)
        G = basis.project(ops.G) if ops.G is not None else None
        rows = fom.constraints.flat_rows
        base_load = basis.dot(ops.base_mass_load) if fom.moving_support else np.zeros(basis.size)
        if fom.force_load is not None:
            force_shape = basis.dot(fom.force_load)
        elif fom.force_row is not None:
            force_shape = basis.rows([fom.force_row])[0]
        elif fom.force_matrix is not None:   # (r, m): V^T W, the load shapes in basis coordinates
            force_shape = basis.dot_rows(fom.force_matrix.rows)
        else:
            force_shape = np.zeros(basis.size)
        with np.errstate(over="ignore", invalid="ignore"):   # a non-finite start is refused below, in one line
            q0, p0 = self._initial_coordinates()
        if not (np.isfinite(q0).all() and np.isfinite(p0).all()):   # the same on every rank (allreduced)
            # red team: amplitude = 1e308 m printed numpy's overflow warning, then "the state is not finite at
            # t = 0 s (step 0); reduce [integrator] dt or rtol", which no dt changes
            initial = self.fom.initial
            raise InputError(f"[initial] amplitude = {initial.amplitude:g} m, velocity = {initial.velocity:g} m/s: "
                             f"the initial state in the basis is beyond double precision; give a displacement and "
                             f"velocity of this structure's size")
        r_q = np.zeros(basis.size)
        if fom.moving_support:
            Mr = ops.M.createVecLeft()
            try:
                ops.M.mult(ops.influence, Mr)
                r_q = basis.dot(Mr)
            finally:
                Mr.destroy()
        info = {"omega": basis.omega, "enrichment_omega": basis.enrichment_omega, "dbf_k": basis.dbf_k,
                "enrichment": basis.enrichment, "flexibility_captured": basis.flexibility_captured,
                "flexibility_exact": basis.flexibility_exact, "complex_modes": basis.complex_modes,
                "constraint_kinds": constraint_kinds(ops, fom.constraints), **structure}
        return ReducedModel(M=M, C=C, K=K, G=G, B=basis.rows(rows), r_c=fom.influence_at(rows), base_load=base_load,
                            force_shape=force_shape, constraints=fom.constraints, support=fom.support,
                            force=fom.force, q0=q0, p0=p0, probe_B=self._basis_at(fom.probes),
                            probe_r=fom.support_share(fom.probes), basis_info=info, r_q=r_q,
                            field=self._field() if field else None, field_points=ops.field_map(),
                            probe_shape=fom.probes.shape)

    @staticmethod
    def _clean_projection(basis: ReducedBasis, K: np.ndarray, M: np.ndarray) -> dict:
        """The reduced model the method defines (Eqs. 21, 27): on an M-orthonormal basis M_r = I, and
        on its reference modes K_r = diag(omega^2), the Rayleigh quotients. The projections carry
        the eigensolver's and the Gram-Schmidt's residuals instead (measured: mode-mode couplings up
        to 5e-10 of sqrt(K_ii K_jj), |M_r - I| up to 1e-10); below PROJECTION_TOL they are set to their
        exact values in place, which gives the stage solve its structure (a diagonal mode block
        bordered by the enrichment columns: rom_core.c). Larger defects (a fine beam mesh, where
        V^T K V carries the round-off of an ill-conditioned K: 1e-7 on a tube of 800 elements) turn
        the basis within its own span (_turn_in_span): the same Galerkin model, with that structure
        exactly. Returns the defects found on the basis as built (basis_info). Collective."""
        m = basis.mode_count
        defect_M = float(np.abs(M - np.eye(M.shape[0])).max(initial=0.0))
        diagonal = np.abs(np.diag(K)[:m])
        # a rigid-body mode's K_ii is round-off: measured against the round-off of the largest, so that
        # its couplings count as large (kept) unless they are round-off too; never a unit-dependent floor
        d = np.sqrt(np.maximum(diagonal, np.finfo(float).eps * diagonal.max(initial=0.0)))
        off = K[:m, :m] - np.diag(np.diag(K)[:m])
        scale = np.outer(d, d)
        defect_K = float((np.abs(off) / np.where(scale > 0, scale, 1.0)).max(initial=0.0))
        if defect_M <= PROJECTION_TOL:
            M[...] = np.eye(M.shape[0])
        if defect_K <= PROJECTION_TOL:
            K[:m, :m] = np.diag(np.diag(K)[:m])
        turned = max(defect_M, defect_K) > PROJECTION_TOL and Reductor._turn_in_span(basis, K, M)
        return {"mass_orthonormality_defect": defect_M, "mode_coupling_defect": defect_K, "turned_in_span": turned}

    @staticmethod
    def _turn_in_span(basis: ReducedBasis, K: np.ndarray, M: np.ndarray) -> bool:
        """V <- V T with T = L^-T Q: L L^T = M_r (Cholesky; L^-T is upper triangular, so a mode column
        stays in the modes' span and an enrichment column gains only earlier columns: Gram-Schmidt in
        the reduced M inner product), then Q the eigenvectors of the modes' block of L^-1 K_r L^-T
        (Rayleigh-Ritz on the modes' span: their Ritz values are the new omega^2). The span is the
        same, so is the Galerkin model (K_r -> T^T K_r T, M_r -> I); only the coordinates change, to
        ones where M_r = I and the mode block is diagonal, exactly: the structured stage solve, not the
        dense one (measured: 2.26 s against 0.46 s of integration on a tube of 112 vectors at 800
        elements, one CLI run each). In place on V, K, M and basis.omega; False (nothing changed) where
        M_r is not positive definite to working precision. Collective (the same T on every rank:
        K and M are allreduced projections)."""
        m, r = basis.mode_count, M.shape[0]
        identity = np.array_equal(M, np.eye(r))   # the usual case: only the modes' block turns (n m^2 flops)
        # rank 0's numbers on every rank, as the DBFs' small problems (dbf_ritz): LAPACK on unlike nodes
        # may differ in the last bits, and each rank turns its own rows of V
        comm = basis.vectors.getComm().tompi4py()

        def turned():
            try:
                return _turn(K, M, m, identity)
            except (np.linalg.LinAlgError, ValueError):   # eigh did not converge: kept as projected, on every rank
                return None

        turn = decided_on_rank0(comm, turned)   # anything else it raises (a bug), every rank raises
        if turn is None:
            return False
        T, w, K_turned = turn
        k = m if identity else r                      # T = blockdiag(Q, I) when M_r = I
        Tm = PETSc.Mat().createDense((k, k), comm=PETSc.COMM_SELF)
        active = basis.vectors.getActiveColumns()
        try:
            Tm.setUp()
            Tm.getDenseArray()[...] = T[:k, :k]
            Tm.assemble()
            basis.vectors.setActiveColumns(0, k)
            basis.vectors.multInPlace(Tm, 0, k)
        finally:
            basis.vectors.setActiveColumns(*active)
            Tm.destroy()
        K[...] = K_turned
        M[...] = np.eye(r)
        basis.omega = np.sqrt(np.clip(w, 0.0, None))
        return True

    def _initial_coordinates(self) -> tuple:
        """(q(0), q'(0)): zero, or the initial amplitude (m, peak over the field) in a reference mode;
        on a beam of two planes the M-projections V^T M u(0), V^T M u'(0) of fom.two_plane_state (the
        planar mode lies in the span of the basis' modes, so the projection is exact); on a gyroscopic
        structure the M-projection of the full-order model's start (the free vibration of a complex
        mode, whose real and imaginary parts the basis holds: exact). Collective."""
        basis, initial = self.basis(), self.fom.initial
        q0, p0 = np.zeros(basis.size), np.zeros(basis.size)
        mesh = self.fom.operators.mesh
        if mesh is not None and mesh.planes == 2:
            if not (initial.amplitude or initial.velocity):
                return q0, p0
            if not 1 <= 2 * initial.mode <= basis.mode_count:
                raise InputError(f"[initial] mode = {initial.mode}: a beam of two planes counts its modes in y-z "
                                 f"pairs; the basis has {basis.mode_count // 2} pairs")
            u, v = self.fom.two_plane_state()
            Mx = None
            try:   # freed also on an error
                Mx = u.duplicate()
                out = []
                for vec in (u, v):
                    self.fom.operators.M.mult(vec, Mx)
                    out.append(basis.dot(Mx))
            finally:
                destroy(u, v, Mx)
            return out[0], out[1]
        if initial.amplitude and self.fom.operators.G is not None:
            u, v = self.fom.initial_state()
            try:
                q0, p0 = basis.vectors.dotVec(u), basis.vectors.dotVec(v)   # V^T M u (the BV's inner product is M)
            finally:
                destroy(u, v)
        elif initial.amplitude:
            if not 1 <= initial.mode <= basis.mode_count:
                raise InputError(f"[initial] mode = {initial.mode}: the basis has {basis.mode_count} reference modes")
            refusal = repeated_mode_refusal(basis.omega ** 2, initial.mode, self.fom.operators.rigid_modes)
            if refusal:   # the basis holds whole repeated frequencies (modes.reference_modes): the same on every rank
                raise InputError(f"[initial] mode = {initial.mode}: {refusal}")
            column = self._basis_at(self.fom.operators.field_map())[:, initial.mode - 1]
            q0[initial.mode - 1] = initial.amplitude / np.abs(column).max()
        return q0, p0

    def _basis_at(self, points) -> np.ndarray:
        """(P, r) the basis at PointValues (combined as the points combine DOF values)."""
        needed = points.needed_rows
        if not needed.size:
            return np.zeros((points.count, self.basis().size))
        return points.combine(self.basis().rows(needed), needed)

    def field_values(self) -> np.ndarray:
        """(F, r) the basis vectors at the field points (mode shapes for a plot or ParaView). Collective."""
        return self._basis_at(self.fom.operators.field_map())

    def _field(self) -> ReducedField:
        field = self.fom.operators.field_map()
        return ReducedField(positions=field.positions, V=self._basis_at(field), support=self.fom.field_support())

    def destroy(self) -> None:
        if self._basis is not None:
            self._basis.destroy()
            self._basis = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.destroy()
