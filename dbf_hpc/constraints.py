"""The discrete constraints of a structure: where each acts, in how many directions, and its law.

Constraint j acts on d displacement components of the structure, w_(j,a) = u[rows[j, a]],
a = 1..d (d = 1 for a beam against a stop or a DOF of a matrix model; d = 2 for a tube moving in
two transverse directions, y and z, in a support such as a round hole: laws.PlanarLaws). G, the n x (N_L d) matrix of unit vectors at
those rows, is never formed: every operator that needs it works on the rows.

Vectors at the constraints are flat, constraint-major, of length N_L d: entry j d + a is
direction a of constraint j (for d = 1 simply one entry per constraint). The law of constraint j
maps its total displacement and velocity (d values each) to the force on the structure (d values)
and its derivatives, d x d blocks, (N_L, d, d) for all of them. The laws of laws.py have no state
(friction is regularized, a function of v); `commit`, called once per accepted step, is the hook for
a law that would (a stick point).

Nothing here is collective.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .errors import InputError, check_number
from .laws import ConstraintLaws, Law, PlanarLaws


# The largest Archard wear coefficient K_w (m^3/(N m)) a constraint takes. K_w = k / H: the dimensionless
# k is 1e-8 (mild) to 1e-2 (severe adhesive wear), the hardness H 1e7 Pa (soft polymers) or more, so no
# contact pair exceeds 1e-9; a coefficient in mm^3/(N m) given as m^3/(N m) is 1e9 times too large. Red
# team: 1.7e308 gave a wear volume of 1.6e304 m^3 in 0.05 s of the tube, a longer run inf.
WEAR_MAX = 1e-6


def check_wear_coefficient(where: str, value) -> float:
    """K_w as a float from 0 to WEAR_MAX, or one InputError naming `where`."""
    value = check_number(f"{where} wear_coefficient", value, 0.0)
    if value > WEAR_MAX:
        raise InputError(f"{where} wear_coefficient = {value:g} m^3/(N m): above {WEAR_MAX:g}, no contact pair's "
                         f"(Archard's k / H is at most about 1e-9; steam-generator tubes 1e-15 to 1e-13): give it "
                         f"in m^3/(N m), not mm^3/(N m)")
    return value


@dataclass(frozen=True)
class Constraint:
    """One discrete constraint as a user describes it: where it acts (x in m on a beam, or the DOF
    `dof` of a matrix model) and its law; with a 2-D law, optionally Archard's wear coefficient
    K_w (m^3/(N m)) for the wear volume K_w int |F_n| |v_t| dt (stats.py)."""

    law: Law
    x: Optional[float] = None
    dof: Optional[int] = None
    wear_coefficient: Optional[float] = None

    def __post_init__(self):
        from .laws import CircularLaw

        if not isinstance(self.law, (Law, CircularLaw)):
            raise InputError(f"Constraint law: give law(kind, ...) (dbf_hpc.law), got {self.law!r}")
        if (self.x is None) == (self.dof is None):
            raise InputError("Constraint: give its place, one of x (m, on a beam) or dof (a matrix model)")
        if self.x is not None:
            object.__setattr__(self, "x", check_number("Constraint x", self.x))
        else:
            object.__setattr__(self, "dof", check_number("Constraint dof", self.dof, 0, integer=True))
        if self.wear_coefficient is not None:
            object.__setattr__(self, "wear_coefficient", check_wear_coefficient("Constraint", self.wear_coefficient))

    @property
    def label(self) -> str:
        return f"x = {self.x:g} m" if self.x is not None else f"dof {self.dof}"

    @property
    def position(self) -> float:
        return float(self.x if self.x is not None else self.dof)


@dataclass(frozen=True)
class ConstraintSet:
    """N_L constraints of dimension d.

    rows       (N_L, d) global DOF rows each constraint acts on
    laws       their laws (d = 1: ConstraintLaws, one scalar law per constraint; d = 2: PlanarLaws)
    labels     how a user names each constraint in messages ("x = 0.25 m", "dof 17")
    positions  (N_L,) x (m) on a beam, the first DOF for matrix models (written to the output)
    """

    rows: np.ndarray
    laws: object
    labels: tuple
    positions: np.ndarray

    def __post_init__(self):
        rows = np.asarray(self.rows, dtype=np.int64)
        rows = rows.reshape(len(self.labels), -1 if rows.size else 1)
        object.__setattr__(self, "rows", rows)
        if rows.shape[0] and rows.shape[1] != getattr(self.laws, "dimension", 1):
            raise ValueError(f"laws of dimension {getattr(self.laws, 'dimension', 1)} for constraints on "
                             f"{rows.shape[1]} DOFs each")
        if self.laws.n != rows.shape[0]:
            raise ValueError(f"{self.laws.n} laws for {rows.shape[0]} constraints")

    @classmethod
    def empty(cls) -> "ConstraintSet":
        return cls(rows=np.zeros((0, 1), dtype=np.int64), laws=ConstraintLaws([]), labels=(),
                   positions=np.zeros(0))

    @property
    def count(self) -> int:
        """N_L."""
        return self.rows.shape[0]

    @property
    def dimension(self) -> int:
        """d: displacement components per constraint."""
        return self.rows.shape[1]

    @property
    def shape(self) -> tuple:
        """The shape of one sample of the constraints' values in an output: (N_L,) or (N_L, d)."""
        return (self.count,) if self.dimension == 1 else (self.count, self.dimension)

    @property
    def flat_rows(self) -> np.ndarray:
        """(N_L d,) the rows of G's columns, constraint-major."""
        return self.rows.ravel()

    def force(self, z, v=None) -> np.ndarray:
        """(N_L d,) force on the structure at total displacement z and velocity v (flat)."""
        return self.laws.force(z, v)

    def force_and_jacobian(self, z, v):
        """(force (N_L d,), dN/dz (N_L, d, d), dN/dv (N_L, d, d)) in one pass."""
        force, dz, dv = self.laws.force_and_jacobian(z, v)
        if self.dimension > 1:
            return force, dz, dv
        return force, dz[:, None, None], dv[:, None, None]

    def diagonal_jacobian(self, z, v):
        """(force, dN/dz, dN/dv) with the d = 1 Jacobians as flat (N_L,) diagonals: the integrators'
        fast path (d = 1 only: the blocks are 1 x 1)."""
        if self.dimension > 1:
            raise ValueError("diagonal_jacobian: the constraints are 2-D; use force_and_jacobian")
        return self.laws.force_and_jacobian(z, v)

    #: whether a law carries state that `commit` must see after every accepted step (the compiled
    #: integrator calls it only then; the laws of laws.py have none)
    stateful = False

    def commit(self, z, v) -> None:
        """Accept a step: a law with state would take it here. The laws of laws.py have none."""

    def in_contact(self, z) -> np.ndarray:
        """(N_L,) whether each constraint is in contact."""
        return self.laws.in_contact(z)

    @property
    def component_labels(self) -> list:
        """A label per flat component (the DBF columns): the constraint's, with (y) and (z) for d = 2."""
        if self.dimension == 1:
            return list(self.labels)
        return [f"{label} ({axis})" for label in self.labels for axis in "yz"]

    @property
    def clearance_minus(self) -> np.ndarray:
        return np.array([law.clearance_minus for law in self.laws.laws], dtype=float)

    @property
    def clearance_plus(self) -> np.ndarray:
        return np.array([law.clearance_plus for law in self.laws.laws], dtype=float)

    def with_laws(self, laws) -> "ConstraintSet":
        """The same constraints with other laws (a new law never needs a new basis): one law() per
        constraint, in their order, or a ConstraintLaws (PlanarLaws on a beam of two planes)."""
        from .errors import InputError

        try:   # the user's laws: a list of the wrong length or of other things is one line (red team: ValueError)
            if not hasattr(laws, "n"):
                laws = PlanarLaws(laws) if self.dimension == 2 else ConstraintLaws(laws)
            return ConstraintSet(rows=self.rows, laws=laws, labels=self.labels, positions=self.positions)
        except (TypeError, ValueError) as e:
            raise InputError(f"with_laws: {e}; give one law(...) per constraint, in their order ({self.count} of "
                             f"them)") from None
