"""Euler-Bernoulli beam by Hermite-cubic finite elements, assembled as distributed PETSc AIJ matrices.

DOFs per node: w (transverse displacement, m) and theta = dw/dx (rad). With `planes = 2` the beam
bends in two planes: per node (y, dy/dx, z, dz/dx), in this order, two uncoupled copies of the
planar beam with the same EI (a tube's section is round); a planar beam's w is y. Boundary conditions remove
DOFs (they are not penalised), so K and M are over the free DOFs only, numbered node by node: rank
p owns a contiguous stretch of the beam and assembles only the elements touching its rows.

Boundary conditions at each end:
    pinned   w = 0               clamped  w = 0, theta = 0
    free     (none)              sliding  theta = 0 (a guided end: no slope, no shear)
Intermediate rigid supports pin w = 0 at interior points (multi-span tubes). With two planes every
condition holds in both planes.

Axial transport and tension (issue 19; the gyroscopic form of Brake & Segalman 2011, Section 2,
Eqs. 3-20, with C -> C + G): a beam moving axially at speed U (or a pipe conveying fluid at U) with
transported mass m_t per length and tension T obeys

    rho A w_tt + 2 m_t U w_xt + (m_t U^2 - T) w_xx + EI w_xxxx = 0,

which the same Hermite elements turn into M q'' + G q' + K q = 0 with
    G = 2 m_t U int N^T N' dx  (its skew-symmetric part: exact when w is fixed at both ends)
    K = K_bending + (T - m_t U^2) int N'^T N' dx   (tension stiffens, transport softens).
With U = 0 there is no G; with U = 0 and T = 0, K is the bending stiffness alone, bit for bit.

Assembly is collective on the communicator it is given (default COMM_WORLD); each rank assembles its
own rows.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc
from slepc4py import SLEPc

from .errors import InputError, SolverError, check_number
from .operators import Operators, PointValues
from .petsctools import aij_from_owned_triplets, destroy, direct_solver, owned_rows, petsc_comm

W, THETA = 0, 1
BOUNDARIES = {"pinned": (W,), "clamped": (W, THETA), "free": (), "sliding": (THETA,)}
# Points closer than this (relative to the length) are the same node.
POINT_TOL = 1e-9
# The squared circular frequencies (1/s^2) a beam's mesh may span (Beam._check_scale): far outside
# any structure's in SI units, inside what the eigen-solves' double precision holds.
OMEGA2_RANGE = (1e-100, 1e100)
# A compression -T within this fraction of the buckling load is the buckling load (K singular to round-off).
BUCKLING_TOL = 1e-9


@dataclass(frozen=True)
class Beam:
    """A uniform Euler-Bernoulli beam, SI units: length L (m), Young's modulus E (Pa), second moment of
    area I (m^4), cross-section area A (m^2), density rho (kg/m^3); the paper's Table 1 beam is
    Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0). `elements` is the target count
    (see beam_mesh); left, right: "pinned", "clamped", "free" or "sliding"; supports: x (m) of
    intermediate rigid supports; planes: 1, or 2 (bending in y and z); axial_speed U (m/s),
    transported_mass m_t (kg/m, default rho A) and tension T (N): an axially moving beam or a pipe
    conveying fluid (the gyroscopic G; docs/scene.md [structure] says what is refused)."""

    length: float
    E: float
    I: float
    A: float
    rho: float
    elements: int = 100
    left: str = "pinned"
    right: str = "pinned"
    supports: tuple = ()
    planes: int = 1
    axial_speed: float = 0.0                 # U, m/s
    transported_mass: float | None = None    # m_t, kg/m (None: rho A)
    tension: float = 0.0                     # T, N

    def __post_init__(self):
        """Checked once, the numbers stored as float and int (a numpy scalar or an int length is
        the same beam, with the same cache key, as a scene's float); a bool is not a number."""
        put = object.__setattr__
        for name in ("length", "E", "I", "A", "rho"):
            put(self, name, check_number(f"beam {name}", getattr(self, name), 0.0, above=True))
        put(self, "elements", check_number("beam elements", self.elements, 1, integer=True))
        if isinstance(self.planes, bool) or self.planes not in (1, 2):
            raise InputError(f"beam planes must be 1 or 2, got {self.planes!r}")
        put(self, "planes", int(self.planes))
        # red team: elements = 2**70 ended in numpy's "Maximum allowed size exceeded" (an internal error)
        most = (int(np.iinfo(PETSc.IntType).max) - 1) // (2 * self.planes) - 1
        if self.elements > most:
            raise InputError(f"beam elements = {self.elements}: 2 DOFs a node in {self.planes} plane(s) are more than "
                             f"PETSc's indices count ({np.iinfo(PETSc.IntType).max}); use at most {most} elements")
        for end in ("left", "right"):
            if not isinstance(getattr(self, end), str) or getattr(self, end) not in BOUNDARIES:
                raise InputError(f"beam {end} boundary must be one of {', '.join(BOUNDARIES)}, "
                                 f"got {getattr(self, end)!r}")
        if isinstance(self.supports, (str, bytes)) or not np.iterable(self.supports):
            raise InputError(f"beam supports must be a sequence of x (m), got {self.supports!r}")
        put(self, "supports", tuple(check_number("beam support x (m)", x) for x in self.supports))
        for x in self.supports:
            if not 0 < x < self.length:
                raise InputError(f"intermediate support at x = {x} m is not inside the beam (0, {self.length})")
        self._check_transport()
        self._check_scale()
        self._check_section()

    def _check_section(self) -> None:
        """The section's radius of gyration sqrt(I / A) is below the length: a beam's section is smaller than
        the beam is long (Euler-Bernoulli theory wants it far smaller). Red team: I given in mm^4 as m^4 (the
        paper's 0.000878), a radius of gyration of 55 m on a 1 m beam, ran without a word at frequencies
        1e6 times the paper's; inside the omega^2 bounds of _check_scale, as every unit slip is."""
        with np.errstate(all="ignore"):
            radius = float(np.sqrt(np.float64(self.I) / self.A))
        if radius > self.length:
            raise InputError(f"beam I = {self.I:g} m^4 and A = {self.A:g} m^2 give a section whose radius of "
                             f"gyration sqrt(I / A) = {radius:.3g} m exceeds the beam's length {self.length:g} m: no "
                             f"beam is wider than it is long (Euler-Bernoulli theory wants a slender one); check "
                             f"their units (I in m^4, A in m^2: 1 mm^4 = 1e-12 m^4, 1 mm^2 = 1e-6 m^2)")

    def _check_scale(self) -> None:
        """omega^2 of the mesh, (EI / h^4 + |T - m_t U^2| / h^2) / (rho A) from the whole length to half
        an element (beam_mesh's shortest), within 1e-100 ... 1e100 1/s^2, where the double-precision
        eigen-solves and element matrices work. Red team: E = 1e308 Pa failed in the eigensolver ("PETSc
        error 77 ... check M"), I = 1e-300 m^4 as "the mass matrix is not positive definite", length =
        1e200 m in an internal OverflowError; an E or rho in the wrong unit is far inside these bounds."""
        with np.errstate(all="ignore"):
            EI, rhoA = np.float64(self.E) * self.I, np.float64(self.rho) * self.A
            axial = abs(self.tension - (self.transported_mass or rhoA) * np.float64(self.axial_speed) ** 2)
            h = np.float64(self.length) / (2 * self.elements)
            lowest = (EI / np.float64(self.length) ** 4 + axial / np.float64(self.length) ** 2) / rhoA
            highest = (EI / h ** 4 + axial / h ** 2) / rhoA
        if not (OMEGA2_RANGE[0] <= lowest and highest <= OMEGA2_RANGE[1]):
            raise InputError(f"beam E, I, A, rho, length, elements (and tension, axial_speed) give omega^2 of "
                             f"{lowest:.3g} to {highest:.3g} 1/s^2 over the mesh, outside the {OMEGA2_RANGE[0]:g} to "
                             f"{OMEGA2_RANGE[1]:g} that double-precision solves handle: check their units (SI: Pa, "
                             f"m^4, m^2, kg/m^3, m)")

    def _check_transport(self) -> None:
        # check_number, as the other numbers: a bool is not a speed (True was taken as 1 m/s), a numpy
        # integer is one (it was refused), and 78 and 78.0 are the same beam and cache key
        put = object.__setattr__
        for name in ("axial_speed", "tension"):
            put(self, name, check_number(f"beam {name}", getattr(self, name)))
        if self.transported_mass is not None:
            put(self, "transported_mass", check_number("beam transported_mass", self.transported_mass, 0.0, above=True))
        m_t = self.transported_mass
        if m_t is not None and m_t > self.rho * self.A * (1 + 1e-12):
            raise InputError(f"beam transported_mass {m_t:g} kg/m exceeds rho A = {self.rho * self.A:g} kg/m, the "
                             f"whole mass per length, which includes it (a pipe: rho A = pipe + fluid)")
        if self.axial_speed and any(W not in BOUNDARIES[getattr(self, end)] for end in ("left", "right")):
            raise InputError(f"an axially moving beam (axial_speed = {self.axial_speed} m/s) needs w fixed at both "
                             f"ends (pinned or clamped), got left = {self.left!r}, right = {self.right!r}: with a free "
                             f"end the transport does work (a cantilevered pipe flutters) and is not modelled")

    @property
    def EI(self) -> float:
        return self.E * self.I

    @property
    def rhoA(self) -> float:
        return self.rho * self.A

    @property
    def m_t(self) -> float:
        """The transported mass per length, kg/m (rho A unless given)."""
        return self.rhoA if self.transported_mass is None else float(self.transported_mass)

    @property
    def axial_force(self) -> float:
        """T - m_t U^2 (N): the coefficient of the geometric stiffness int N'^T N' dx."""
        return self.tension - self.m_t * self.axial_speed**2

    @property
    def eigen_scale(self) -> float:
        """EI / (rho A L^4): the beam's natural eigenvalue scale, rad^2/s^2."""
        return self.EI / (self.rhoA * self.length**4)


class BeamMesh:
    """Nodes of a beam mesh and its free-DOF numbering; the same small arrays on every rank.

    x      node positions (m), increasing, with a node at every requested point
    row    (nodes, 2 planes) global row of (w, theta) at each node (two planes: y, y', z, z'), -1
           where the DOF is fixed
    """

    def __init__(self, beam: Beam, points=()):
        self.beam = beam
        self.planes = beam.planes
        self.per_node = 2 * beam.planes
        self.x = _mesh_nodes(beam.length, beam.elements, [*points, *beam.supports])
        fixed = np.zeros((self.x.size, self.per_node), dtype=bool)
        for plane in range(self.planes):
            fixed[0, [2 * plane + d for d in BOUNDARIES[beam.left]]] = True
            fixed[-1, [2 * plane + d for d in BOUNDARIES[beam.right]]] = True
            for s in beam.supports:
                fixed[self.node_at(s), 2 * plane + W] = True
        self.fixed = fixed
        self.row = np.full(fixed.shape, -1, dtype=np.int64)
        self.row[~fixed] = np.arange(np.count_nonzero(~fixed))
        self.free_dofs = np.flatnonzero(~fixed.ravel())  # node-major DOF index of each row
        self.p_cr = None   # the buckling load (N), once buckling_load has solved it

    @property
    def elements(self) -> int:
        return self.x.size - 1

    @property
    def n_free(self) -> int:
        return self.free_dofs.size

    def node_at(self, x: float) -> int:
        """Index of the node at position x; an InputError if there is none."""
        i = int(np.argmin(np.abs(self.x - x)))
        if abs(self.x[i] - x) > POINT_TOL * self.beam.length:
            raise InputError(f"x = {x} m is not a node of the beam mesh")
        return i

    def _moving(self, moving_end: str | None) -> np.ndarray:
        moving = np.zeros(self.x.size)
        if moving_end is not None:
            moving[0 if moving_end == "left" else -1] = 1.0
        return moving

    def field_map(self, moving_end: str | None = None, direction=(1.0, 0.0)) -> PointValues:
        """w at every node; the fixed w of the `moving_end` support follows the support motion. Two
        planes: (y, z) at every node, node-major, the support moving along `direction` (dy, dz)."""
        if self.planes == 1:
            return PointValues.at_rows(self.x, self.row[:, W], self._moving(moving_end), kind="beam")
        moving = self._moving(moving_end)
        nodes = np.repeat(np.arange(self.x.size), 2)
        xyz = np.zeros((self.x.size, 3))
        xyz[:, 0] = self.x
        return PointValues.at_rows(self.x[nodes], self.row[:, [W, 2 + W]].ravel(),
                                   (moving[:, None] * np.asarray(direction, dtype=float)[None, :]).ravel(),
                                   kind="beam", node=nodes, component=np.tile([1, 2], self.x.size),
                                   coordinates=xyz)

    def point_values(self, xs, moving_end: str | None = None, direction=(1.0, 0.0)) -> PointValues:
        """w at arbitrary points from the Hermite shape functions of the element holding each (a
        node's own w at a node): asking for a value never changes the mesh. A point on a fixed w
        (a support) is an InputError. Two planes: (y, z) at each point, point-major (2 P values)."""
        if self.planes == 2:
            one = self._plane_values(xs, moving_end, 0)
            two = self._plane_values(xs, moving_end, 2)
            direction = np.asarray(direction, dtype=float)
            rows = np.stack([one.rows, two.rows], axis=1).reshape(-1, one.rows.shape[1])
            weights = np.stack([one.weights, two.weights], axis=1).reshape(rows.shape)
            moving = np.stack([one.moving * direction[0], two.moving * direction[1]], axis=1).ravel()
            return PointValues(positions=np.repeat(one.positions, 2), rows=rows, weights=weights, moving=moving,
                               components=2)
        return self._plane_values(xs, moving_end, 0)

    def _plane_values(self, xs, moving_end, offset: int) -> PointValues:
        xs = np.asarray(xs, dtype=float).reshape(-1)
        moving_nodes = self._moving(moving_end)
        rows, weights, moving = np.full((xs.size, 4), -1, np.int64), np.zeros((xs.size, 4)), np.zeros(xs.size)
        for p, x in enumerate(xs):
            e = int(np.clip(np.searchsorted(self.x, x, side="right") - 1, 0, self.elements - 1))
            h = self.x[e + 1] - self.x[e]
            s = (x - self.x[e]) / h
            if min(abs(s), abs(1 - s)) * h <= POINT_TOL * self.beam.length:
                node = e if abs(s) < abs(1 - s) else e + 1
                if self.fixed[node, W]:
                    raise InputError(f"probe at x = {x:g} m is on a support (a fixed DOF); move it")
                e, s = (node, 0.0) if node < self.elements else (node - 1, 1.0)
            shape = (1 - 3 * s**2 + 2 * s**3, h * (s - 2 * s**2 + s**3), 3 * s**2 - 2 * s**3, h * (s**3 - s**2))
            dofs = [(e, W + offset), (e, THETA + offset), (e + 1, W + offset), (e + 1, THETA + offset)]
            for k, ((node, dof), weight) in enumerate(zip(dofs, shape)):
                rows[p, k], weights[p, k] = self.row[node, dof], weight
                if dof == W + offset and self.fixed[node, dof]:
                    moving[p] += weight * moving_nodes[node]
        return PointValues(positions=xs, rows=rows, weights=weights, moving=moving)

    def w_row(self, x: float, plane: int = 0) -> int:
        """Row of the displacement DOF at x (of plane 0 = y or 1 = z), or -1 if w is fixed there."""
        return int(self.row[self.node_at(x), 2 * plane + W])

    def can_rotate(self) -> bool:
        """Whether the supports allow a rigid rotation w = a + b x, b != 0 (no slope held, w held at one
        point at most): a rigid motion that a compression does work on."""
        return not self.fixed[:, THETA].any() and np.count_nonzero(self.fixed[:, W]) < 2

    def rigid_modes(self) -> int:
        """Number of rigid-body motions w = a + b x that the supports allow (0, 1 or 2)."""
        conditions = [[1.0, xi] for xi in self.x[self.fixed[:, W]]]
        conditions += [[0.0, 1.0]] * int(np.count_nonzero(self.fixed[:, THETA]))
        if not conditions:
            return 2 * self.planes
        scaled = np.array(conditions) / [1.0, self.beam.length]
        return (2 - np.linalg.matrix_rank(scaled)) * self.planes


def _mesh_nodes(length: float, elements: int, points) -> np.ndarray:
    """Nodes over [0, length]: at least `elements` elements (one more per extra point at most),
    near-uniform, a node at every point. Points that coincide to POINT_TOL are one point; points
    (or a point and an end) closer than half an element would make an element too short to trust:
    an InputError that says so."""
    for p in points:
        if not 0 <= p <= length:
            raise InputError(f"x = {p} m is outside the beam [0, {length}] m")
    kept = []
    # A point within POINT_TOL of the last point kept is that point; measured from the point kept, not
    # from its neighbour: a chain of points 0.8e-9 L apart merged into its first, and the third, 1.6e-9 L
    # from any node, was refused as 'not a node of the beam mesh' (red team)
    for p in np.unique(np.concatenate([[0.0, length], np.asarray(points, dtype=float)])):
        if not kept or p - kept[-1] > POINT_TOL * length:
            kept.append(p)
    breaks = np.array(kept)
    breaks[-1] = length   # the end, or a point within POINT_TOL of it
    half = 0.5 * length / elements
    gaps = np.diff(breaks)
    if gaps.size and gaps.min() < half:
        i = int(np.argmin(gaps))
        a, b = breaks[i], breaks[i + 1]
        # 12 digits: two points 1e-9 m apart read as two numbers, not 'x = 0.25 m and x = 0.25 m'
        what = (f"x = {b:.12g} m is {b - a:.3g} m from the left end" if i == 0 else
                f"x = {a:.12g} m is {b - a:.3g} m from the right end" if i == gaps.size - 1 else
                f"x = {a:.12g} m and x = {b:.12g} m are {b - a:.3g} m apart")
        raise InputError(f"{what}, less than half an element ({half:.3g} m at {elements} elements): "
                         f"make them one point, move them apart, or use at least "
                         f"{int(np.ceil(0.5 * length / (b - a)))} elements")
    pieces = [breaks[:1]]
    for a, b in zip(breaks[:-1], breaks[1:]):
        n = max(1, int(np.ceil((b - a) / length * elements - 1e-9)))   # elements (b - a) overflowed at 1e308 m
        pieces.append(np.linspace(a, b, n + 1)[1:])
    return np.concatenate(pieces)


def element_matrices(h: np.ndarray, EI: float, rhoA: float):
    """Hermite-cubic stiffness and consistent mass for elements of lengths h: two (ne, 4, 4) arrays.

    Element DOFs: (w1, theta1, w2, theta2).
    """
    h = np.asarray(h, dtype=float)[:, None, None]
    one = np.ones_like(h)
    k = np.block([[12 * one, 6 * h, -12 * one, 6 * h],
                  [6 * h, 4 * h**2, -6 * h, 2 * h**2],
                  [-12 * one, -6 * h, 12 * one, -6 * h],
                  [6 * h, 2 * h**2, -6 * h, 4 * h**2]]) * (EI / h**3)
    m = np.block([[156 * one, 22 * h, 54 * one, -13 * h],
                  [22 * h, 4 * h**2, 13 * h, -3 * h**2],
                  [54 * one, 13 * h, 156 * one, -22 * h],
                  [-13 * h, -3 * h**2, -22 * h, 4 * h**2]]) * (rhoA * h / 420.0)
    return k, m


def transport_matrices(h: np.ndarray, axial_force: float, m_t_U: float):
    """Hermite-cubic geometric stiffness axial_force * int N'^T N' dx and gyroscopic
    m_t_U * int (N^T N' - N'^T N) dx (the skew part of 2 m_t U int N^T N' dx) for elements of
    lengths h: two (ne, 4, 4) arrays, DOFs (w1, theta1, w2, theta2)."""
    h = np.asarray(h, dtype=float)[:, None, None]
    one, zero = np.ones_like(h), np.zeros_like(h)
    s = np.block([[36 * one, 3 * h, -36 * one, 3 * h],
                  [3 * h, 4 * h**2, -3 * h, -h**2],
                  [-36 * one, -3 * h, 36 * one, -3 * h],
                  [3 * h, -h**2, -3 * h, 4 * h**2]]) * (axial_force / (30.0 * h))
    g = np.block([[zero, 6 * h, 30 * one, -6 * h],
                  [-6 * h, zero, 6 * h, -h**2],
                  [-30 * one, -6 * h, zero, 6 * h],
                  [6 * h, h**2, -6 * h, zero]]) * (m_t_U / 30.0)
    return s, g


def planes_element(mats: np.ndarray, planes: int) -> np.ndarray:
    """Element matrices (ne, 4, 4) of one plane -> (ne, 4 planes, 4 planes) in the element's DOF
    order (node 1: y, y', z, z'; node 2: the same): the planes uncoupled."""
    if planes == 1:
        return mats
    out = np.zeros((mats.shape[0], 8, 8))
    for plane in range(2):
        local = np.array([0, 1, 4, 5]) + 2 * plane
        out[:, local[:, None], local[None, :]] = mats
    return out


def _assemble(comm, mesh: BeamMesh, element_mats, fixed_values=None):
    """Assemble element matrices into a distributed AIJ over the free DOFs. Collective.

    Each rank takes only the elements touching its own rows and only its own rows of them, so no
    off-rank values move. With `fixed_values` (one value per node DOF), also returns the owned part
    of A_(free, fixed) @ fixed_values as a Vec.
    """
    n = mesh.n_free
    rstart, rend = owned_rows(n, comm)
    if rend > rstart:
        owned_nodes = mesh.free_dofs[[rstart, rend - 1]] // mesh.per_node
        first, last = max(owned_nodes[0] - 1, 0), min(owned_nodes[1], mesh.elements - 1)
    else:
        first, last = 0, -1
    elems = np.arange(first, last + 1)
    per = mesh.per_node
    all_dofs = per * elems[:, None] + np.arange(2 * per)[None, :]
    rows = mesh.row.ravel()[all_dofs]
    mats = planes_element(element_mats(mesh.x[elems + 1] - mesh.x[elems]), mesh.planes)

    ri = np.broadcast_to(rows[:, :, None], mats.shape)
    cj = np.broadcast_to(rows[:, None, :], mats.shape)
    take = (ri >= rstart) & (ri < rend) & (cj >= 0)
    A = aij_from_owned_triplets(comm, n, ri[take], cj[take], mats[take])
    if fixed_values is None:
        return A
    f = fixed_values[all_dofs] * (rows < 0)
    contrib = np.einsum("eij,ej->ei", mats, f)
    mine = (rows >= rstart) & (rows < rend)
    coupling = A.createVecLeft()
    coupling.array[:] = np.bincount(rows[mine] - rstart, weights=contrib[mine], minlength=rend - rstart)
    return A, coupling


def assemble_beam(beam: Beam, comm=None, points=(), base_end: str | None = None, direction=(1.0, 0.0)) -> Operators:
    """Assemble K and M of `beam` on `comm` (default COMM_WORLD). Collective.

    points    positions that must be nodes (constraints, probes)
    base_end  "left" or "right": also compute the support-motion influence vector for base
              excitation of that end's transverse support (see influence_vector).
    direction (dy, dz), a unit vector: the direction the support moves on a beam of two planes
    """
    comm = petsc_comm(comm, "assemble_beam")
    mesh = BeamMesh(beam, points)

    def stiffness(h):
        k = element_matrices(h, beam.EI, beam.rhoA)[0]
        if beam.axial_force:   # T = m_t U^2 = 0: the bending stiffness alone, bit for bit
            k = k + transport_matrices(h, beam.axial_force, 0.0)[0]
        return k

    def mass(h):
        return element_matrices(h, beam.EI, beam.rhoA)[1]

    if beam.tension < 0:   # only a compression can buckle the beam
        if mesh.can_rotate():
            # red team: pinned-free under -1000 N, --method full swung w to 20 m on a 1 m beam without a word
            raise InputError(f"beam tension = {beam.tension:g} N compresses a beam free to rotate as a rigid body "
                             f"(left = {beam.left!r}, right = {beam.right!r}, {len(beam.supports)} support(s)): any "
                             f"compression tips it over (the buckling load is 0) and the linear beam grows without "
                             f"bound; give tension >= 0, or ends and supports that hold its rotation")
        held = mesh
        if mesh.rigid_modes():
            # free to translate only (a sliding end, no w held): w + c costs nothing in either stiffness, so the
            # beam with its sliding end clamped buckles at the same load (red team: free-sliding at -2 P_cr swung
            # to 1e19 m under --method full)
            end = "left" if beam.left == "sliding" else "right"
            held = BeamMesh(dataclasses.replace(beam, **{end: "clamped"}), points)
        check_not_buckled(beam, buckling_load(comm, held))
    if base_end is None:
        ops = Operators(comm=comm, K=_assemble(comm, mesh, stiffness), M=_assemble(comm, mesh, mass), mesh=mesh,
                        rigid_modes=mesh.rigid_modes(), eigen_scale=beam.eigen_scale, field=mesh.field_map())
        if beam.axial_speed:
            try:
                ops.G = _assemble(comm, mesh, lambda h: transport_matrices(h, 0.0, beam.m_t * beam.axial_speed)[1])
            except Exception:
                ops.destroy()
                raise
        return ops
    if beam.axial_speed:
        raise InputError("base excitation of an axially moving beam (axial_speed != 0) is not modelled yet: the "
                         "support's velocity would load the gyroscopic term; use a force or axial_speed = 0")
    if base_end not in ("left", "right"):
        raise InputError(f"base excitation end must be 'left' or 'right', got {base_end!r}")
    node = 0 if base_end == "left" else mesh.elements
    if not mesh.fixed[node, W]:
        raise InputError(f"base excitation at the {base_end} end needs a transverse support there "
                         f"(pinned or clamped), but it is {getattr(beam, base_end)}")
    if mesh.rigid_modes():
        raise InputError("base excitation needs a structure without rigid-body modes; "
                         "add supports or use boundary conditions that restrain it")
    support = np.zeros(mesh.fixed.size)
    for plane in range(beam.planes):
        support[mesh.per_node * node + 2 * plane + W] = direction[plane] if beam.planes == 2 else 1.0
    K, k_coupling = _assemble(comm, mesh, stiffness, support)
    M, m_coupling = _assemble(comm, mesh, mass, support)
    ops = Operators(comm=comm, K=K, M=M, mesh=mesh, rigid_modes=0, eigen_scale=beam.eigen_scale,
                    field=mesh.field_map(base_end, direction))
    try:
        ops.influence, ops.base_mass_load = influence_vector(K, M, k_coupling, m_coupling)
    except Exception:
        ops.destroy()
        raise
    finally:
        destroy(k_coupling, m_coupling)
    return ops


def buckling_load(comm, mesh: BeamMesh) -> float:
    """P_cr (N): the least compressive axial force -T at which the beam's K = K_bending + T int N'^T N' dx
    loses its definiteness, the lowest P of K_bending x = P int N'^T N' dx x (EI pi^2 / L^2 pinned-pinned,
    4 EI pi^2 / L^2 clamped-clamped), solved as the largest 1/P of int N'^T N' dx x = (1/P) K_bending x
    (SLEPc GHEP, K_bending positive definite: the mesh has no rigid-body motion). Options prefix
    `buckling_`. Solved once per mesh, kept in mesh.p_cr: a compressed moving beam's assembly checks
    it and the run's critical speed needs it again. Collective."""
    if mesh.p_cr is None:
        mesh.p_cr = _solve_buckling_load(comm, mesh)
    return mesh.p_cr


def _solve_buckling_load(comm, mesh: BeamMesh) -> float:
    """buckling_load's eigen-solve. Collective."""
    beam = mesh.beam
    Kb = _assemble(comm, mesh, lambda h: element_matrices(h, beam.EI, beam.rhoA)[0])
    Kg = _assemble(comm, mesh, lambda h: transport_matrices(h, 1.0, 0.0)[0])
    eps = SLEPc.EPS().create(comm=comm)
    try:
        eps.setOperators(Kg, Kb)
        eps.setProblemType(SLEPc.EPS.ProblemType.GHEP)
        eps.setWhichEigenpairs(SLEPc.EPS.Which.LARGEST_REAL)
        eps.setDimensions(1, PETSc.DEFAULT, PETSc.DEFAULT)
        eps.setTolerances(1e-12, 1000)
        direct_solver(eps.getST().getKSP(), PETSc.PC.Type.CHOLESKY)
        eps.setOptionsPrefix("buckling_")
        eps.setFromOptions()
        eps.solve()
        theta = eps.getEigenvalue(0).real if eps.getConverged() else 0.0
    except PETSc.Error as e:
        raise SolverError(f"the buckling load of the beam: the eigensolver failed (PETSc error {e.ierr}); check the "
                          f"-buckling_ options") from None
    finally:
        destroy(eps, Kb, Kg)
    if not theta > 0:
        raise SolverError("the buckling load of the beam: the eigensolver did not converge; check the -buckling_ "
                          "options")
    return 1.0 / theta


def check_not_buckled(beam: Beam, load: float) -> None:
    """An InputError if the beam's tension is a compression at or beyond its buckling load `load` (N):
    K is then not positive definite and the linear model grows without bound at any axial speed (no
    critical speed is left to stay below)."""
    if beam.tension + load <= BUCKLING_TOL * load:
        raise InputError(f"beam tension = {beam.tension:g} N is a compression at or beyond the beam's buckling load "
                         f"P_cr = {load:.6g} N (EI pi^2 / L^2 pinned-pinned): K is not positive definite and the "
                         f"linear beam grows without bound at any axial speed; give a tension above {-load:.6g} N")


def critical_speed(beam: Beam, load: float) -> float:
    """U_c (m/s) at which K = K_bending + (T - m_t U^2) int N'^T N' dx becomes singular, sqrt((T + P_cr) /
    m_t) with P_cr = `load` the buckling load: sqrt((EI (pi / L)^2 + T) / m_t) pinned-pinned, the
    divergence speed of a pipe conveying fluid or a moving beam (0 if the beam is buckled)."""
    return float(np.sqrt(max(beam.tension + load, 0.0) / beam.m_t))


def influence_vector(K, M, k_coupling, m_coupling):
    """Quasi-static influence vector of a unit support motion, and its mass load. Collective.

    r_free solves K_ff r_free = -K_(free,support): the structure's static displacement when the
    support moves by one metre. Where the supports allow a rigid motion (the paper's pinned-pinned
    beam, Eq. 26: r = 1 - x/L) this is exactly that motion; otherwise it is the standard pseudo-static
    shape. The load of the moving support is -(M_ff r_free + M_(free,support)) Omega''.
    """
    ksp = direct_solver(PETSc.KSP().create(comm=K.getComm()), PETSc.PC.Type.CHOLESKY)
    ksp.setOperators(K)
    r = K.createVecRight()
    rhs = k_coupling.copy()
    rhs.scale(-1.0)
    try:
        ksp.solve(rhs, r)
        if ksp.getConvergedReason() < 0:
            r.destroy()
            raise InputError("the influence vector solve failed: the stiffness matrix is singular")
    finally:
        destroy(ksp, rhs)
    load = M.createVecLeft()
    M.mult(r, load)
    load.axpy(1.0, m_coupling)
    return r, load


def distributed_load(ops: Operators, x0: float, x1: float, direction=(1.0, 0.0)) -> PETSc.Vec:
    """Consistent nodal loads of a unit uniform load per length (1 N/m) on [x0, x1] (nodes of the
    mesh): (h/2, h^2/12, h/2, -h^2/12) per element; on a beam of two planes along `direction`
    (dy, dz). Collective."""
    mesh = ops.mesh
    load = ops.K.createVecLeft()
    lo, hi = load.getOwnershipRange()
    first, last = mesh.node_at(x0), mesh.node_at(x1)
    elems = np.arange(first, last)
    h = mesh.x[elems + 1] - mesh.x[elems]
    values = np.column_stack([h / 2, h**2 / 12, h / 2, -h**2 / 12])
    per = mesh.per_node
    if mesh.planes == 2:
        values = np.column_stack([values[:, :2] * direction[0], values[:, :2] * direction[1],
                                  values[:, 2:] * direction[0], values[:, 2:] * direction[1]])
    rows = mesh.row.ravel()[per * elems[:, None] + np.arange(2 * per)[None, :]]
    mine = (rows >= lo) & (rows < hi)
    load.array[:] = np.bincount(rows[mine] - lo, weights=values[mine], minlength=hi - lo)
    return load


def span_node_loads(ops: Operators, x0: float, x1: float) -> tuple:
    """The consistent nodal loads of a load per unit length that is linear between the nodes of
    [x0, x1] (the hat function of each node, cut at the span's ends): per element of length h, a
    unit value at its first node gives (7h/20, h^2/20, 3h/20, -h^2/30), at its second (3h/20,
    h^2/30, 7h/20, -h^2/20) (exact integrals of the Hermite cubics times the hats; together
    distributed_load's uniform load). Returns (x of the span's nodes (n,), this rank's rows of the
    load matrix (local rows x planes n): column p n + i is node i's hat in plane p). Not collective."""
    mesh = ops.mesh
    lo, hi = ops.ownership_range()
    first, last = mesh.node_at(x0), mesh.node_at(x1)
    nodes = np.arange(first, last + 1)
    n = nodes.size
    out = np.zeros((hi - lo, mesh.planes * n))
    for e in range(first, last):
        h = mesh.x[e + 1] - mesh.x[e]
        hats = {e - first: (7 * h / 20, h**2 / 20, 3 * h / 20, -h**2 / 30),
                e + 1 - first: (3 * h / 20, h**2 / 30, 7 * h / 20, -h**2 / 20)}
        for i, (wa, ta, wb, tb) in hats.items():
            for plane in range(mesh.planes):
                for node, dof, value in ((e, 0, wa), (e, 1, ta), (e + 1, 0, wb), (e + 1, 1, tb)):
                    row = mesh.row[node, 2 * plane + dof]
                    if lo <= row < hi:
                        out[row - lo, plane * n + i] += value
    return mesh.x[nodes].copy(), out
