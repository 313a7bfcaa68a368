"""The structure's linear operators, as every later stage sees them.

Whatever made them (the beam model of structure.py, or matrix files through matrices.py), a
structure is: distributed K and M (and optionally C, and room for a gyroscopic G) over its free
DOFs, for base excitation the support-motion influence vector, and a map from DOF values to the
field a user looks at (w at the nodes of a beam, every DOF of a matrix model).

The Operators hold distributed PETSc objects on their communicator `comm`: freeing them is collective
on it; PointValues is plain numpy and not collective.
"""
from __future__ import annotations

from dataclasses import dataclass, field as dataclass_field
from typing import Optional

import numpy as np
from petsc4py import PETSc

from .petsctools import destroy


@dataclass(frozen=True)
class PointValues:
    """The displacement at points of the structure as a combination of DOF values:

        w_p = sum_k weights[p, k] u_total[rows[p, k]] + moving[p] Omega(t)

    positions  (P,) the points' abscissae: x (m) on a beam, the DOF index for matrix models
    rows       (P, m) global DOF rows (-1: a fixed DOF or no entry; it contributes nothing)
    weights    (P, m) the weights (1 for a node's w; a beam element's Hermite shape functions
               between nodes, so that asking for a value never adds a node to the model)
    moving     (P,) the share of the support motion carried by fixed DOFs (the moving end's w)
    cells      (E, k) a matrix model's cells for the XDMF files (node indices, XDMF node order), or
               None (points); cell_type their XDMF type; cells_sha256 the bytes of the file they
               came from, which outputs record
    The field of a snapshot is the PointValues of every node; probes are PointValues too.
    """

    positions: np.ndarray
    rows: np.ndarray
    weights: np.ndarray
    moving: np.ndarray
    kind: str = "dofs"
    node: Optional[np.ndarray] = None
    component: Optional[np.ndarray] = None
    coordinates: Optional[np.ndarray] = None
    components: int = 1     # values per point: 2 on a beam of two planes (y, z), point-major
    cells: Optional[np.ndarray] = None
    cell_type: str = ""
    cells_sha256: str = ""

    @property
    def shape(self) -> tuple:
        """The shape of one sample of these values in an output: (P,) or (P, components)."""
        return (self.count,) if self.components == 1 else (self.count // self.components, self.components)

    @classmethod
    def at_rows(cls, positions, rows, moving=None, **where) -> "PointValues":
        """One DOF per point, weight 1 (a node's w, or a DOF of a matrix model). `where` (kind, node,
        component, coordinates, cells) says where the points are in space (for the field's output)."""
        rows = np.asarray(rows, dtype=np.int64).reshape(-1, 1)
        return cls(positions=np.asarray(positions, dtype=float), rows=rows, weights=np.ones(rows.shape),
                   moving=np.zeros(rows.shape[0]) if moving is None else np.asarray(moving, dtype=float), **where)

    def geometry(self) -> tuple:
        """(kind, node coordinates (nodes x 3), node of each point, component of each point: 0 = x,
        1 = y, 2 = z, cells (E x k node indices) or None, their XDMF type or ""): what a field output
        needs to place the values in space. A beam is along x with w along y; a matrix model without
        a node map puts DOF i at (i, 0, 0), its value along x."""
        n = self.count
        if self.node is not None:
            return self.kind, self.coordinates, self.node, self.component, self.cells, self.cell_type
        xyz = np.zeros((n, 3))
        xyz[:, 0] = self.positions
        return self.kind, xyz, np.arange(n), np.full(n, 1 if self.kind == "beam" else 0), None, ""

    @property
    def count(self) -> int:
        return self.rows.shape[0]

    @property
    def needed_rows(self) -> np.ndarray:
        """The distinct DOF rows the values depend on (sorted)."""
        return np.unique(self.rows[self.rows >= 0])

    def combine(self, values_at: np.ndarray, needed: np.ndarray) -> np.ndarray:
        """The weighted sums from the values at the rows `needed` (values_at[i] belongs to
        needed[i]; the trailing axes, e.g. basis columns, are kept); the support part not included."""
        values_at = np.asarray(values_at)
        index = np.searchsorted(needed, np.maximum(self.rows, 0))
        picked = values_at[index]                                  # (P, m, ...)
        mask = (self.weights * (self.rows >= 0)).reshape(self.rows.shape + (1,) * (values_at.ndim - 1))
        return (picked * mask).sum(axis=1)

    def take(self, values: np.ndarray) -> np.ndarray:
        """The weighted sums from all DOF values (the support part not included)."""
        needed = self.needed_rows
        return self.combine(np.asarray(values)[needed], needed) if needed.size else np.zeros(self.count)


@dataclass
class Operators:
    """Distributed structural operators on `comm`. K and M are symmetric, M positive definite.

    C                damping matrix, or None (Rayleigh or modal damping come from damping.py)
    G                gyroscopic matrix (skew-symmetric), or None: axial transport (issue 19); the
                     gyroscopic modes (gyroscopic.py), the reduced basis (gyroscopic_basis.py) and
                     the full-order reference use it
    influence        r over the free DOFs: the displacement of the structure that follows a unit
                     support motion (the paper's Eq. 26 shape). Total u = u_rel + r * Omega(t).
    base_mass_load   M_(free, all) r_all: the support-motion load is -base_mass_load * Omega''(t).
                     It includes the mass coupling to the prescribed support DOF (docs/design.md).
    rigid_modes      number of zero-energy modes of (K, M); > 0 only for an unsupported structure.
    eigen_scale      a typical eigenvalue of (K, M), rad^2/s^2 (sets default solver shifts).
    mesh             the beam mesh for beam models (positions of nodes, DOF rows), else None.
    field            what snapshots show (PointValues of the nodes); every DOF when not set.
    flexibility      g_j^T K^-1 g_j of constraint rows once solved (accuracy.exact_flexibility), keyed
                     by the rows: the tolerance mode's candidate bases factor K for it once.
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
    field: Optional[PointValues] = None
    rotations: Optional[np.ndarray] = None   # the rows a node map names rx, ry or rz; None without a node map
    flexibility: dict = dataclass_field(default_factory=dict, repr=False)

    @property
    def size(self) -> int:
        """Global number of free DOFs."""
        return self.K.getSize()[0]

    def ownership_range(self) -> tuple[int, int]:
        return self.K.getOwnershipRange()

    def field_map(self) -> PointValues:
        if self.field is not None:
            return self.field
        n = self.size
        return PointValues.at_rows(np.arange(n, dtype=float), np.arange(n))

    def destroy(self) -> None:
        """Free the PETSc objects (collective on comm)."""
        destroy(self.K, self.M, self.C, self.G, self.influence, self.base_mass_load)
