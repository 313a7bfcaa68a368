"""The structure's linear operators, as every later stage sees them.

Whatever made them (the beam model of structure.py, or matrix files through matrices.py), a
structure is: distributed K and M (and optionally C, and room for a gyroscopic G) over its free
DOFs, for base excitation the support-motion influence vector, and a map from DOF values to the
field a user looks at (w at the nodes of a beam, every DOF of a matrix model).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from petsc4py import PETSc

from .petsctools import destroy


@dataclass(frozen=True)
class FieldMap:
    """Where the reported field lives and which DOF carries it.

    positions  (F,) the field's abscissae: node x (m) on a beam, the DOF index for matrix models
    rows       (F,) global DOF row of each field point, -1 where the DOF is fixed (a support)
    moving     (F,) the support-motion share of each fixed point (1 at the moving end, else 0)
    The total field is u[rows] + r[rows] Omega(t) at free points and moving * Omega(t) at fixed ones.
    """

    positions: np.ndarray
    rows: np.ndarray
    moving: np.ndarray

    @property
    def free(self) -> np.ndarray:
        return self.rows >= 0

    def take(self, values: np.ndarray) -> np.ndarray:
        """values[rows] at the free points, 0 at the fixed ones (values: over all DOFs)."""
        out = np.zeros(self.rows.size)
        out[self.free] = np.asarray(values)[self.rows[self.free]]
        return out


@dataclass
class Operators:
    """Distributed structural operators on `comm`. K and M are symmetric, M positive definite.

    C                damping matrix, or None (Rayleigh or modal damping come from damping.py)
    G                gyroscopic matrix (skew-symmetric), or None; no solver uses it yet
    influence        r over the free DOFs: the displacement of the structure that follows a unit
                     support motion (the paper's Eq. 26 shape). Total u = u_rel + r * Omega(t).
    base_mass_load   M_(free, all) r_all: the support-motion load is -base_mass_load * Omega''(t).
                     It includes the mass coupling to the prescribed support DOF (docs/design.md).
    rigid_modes      number of zero-energy modes of (K, M); > 0 only for an unsupported structure.
    eigen_scale      a typical eigenvalue of (K, M), rad^2/s^2 (sets default solver shifts).
    mesh             the beam mesh for beam models (positions of nodes, DOF rows), else None.
    field            what snapshots show (FieldMap); every DOF when not set.
    """

    comm: PETSc.Comm
    K: PETSc.Mat
    M: PETSc.Mat
    C: Optional[PETSc.Mat] = None
    G: Optional[PETSc.Mat] = None
    influence: Optional[PETSc.Vec] = None
    base_mass_load: Optional[PETSc.Vec] = None
    rigid_modes: int = 0
    eigen_scale: float = 1.0
    mesh: Optional[object] = None
    field: Optional[FieldMap] = None

    @property
    def size(self) -> int:
        """Global number of free DOFs."""
        return self.K.getSize()[0]

    def ownership_range(self) -> tuple[int, int]:
        return self.K.getOwnershipRange()

    def field_map(self) -> FieldMap:
        if self.field is not None:
            return self.field
        n = self.size
        return FieldMap(positions=np.arange(n, dtype=float), rows=np.arange(n, dtype=np.int64), moving=np.zeros(n))

    def destroy(self) -> None:
        """Free the PETSc objects (collective on comm)."""
        destroy(self.K, self.M, self.C, self.G, self.influence, self.base_mass_load)
