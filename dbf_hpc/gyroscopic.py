"""Reference modes of a gyroscopic structure: M u'' + G u' + K u = 0 (issue 19).

Brake & Segalman 2011, Section 2 (Eqs. 3-20) write the structure in first-order (state-space) form;
with a skew-symmetric G (axial transport, structure.py) the modes are complex: u = Re(x e^(lambda t))
with the quadratic eigenproblem (lambda^2 M + lambda G + K) x = 0. While K is positive definite every
lambda = +-i omega (a conservative gyroscopic system is stable); above a critical speed K loses its
definiteness and a pair becomes real, +-sigma (divergence: the first frequency has fallen to zero),
or two pairs meet and leave the imaginary axis (flutter).

Solved with SLEPc's PEP (TOAR, real arithmetic: a complex pair is one (x_r, x_i)) by shift-and-invert
about 0, P(0) = K factored by MUMPS's LU (K may be indefinite): the eigenvalues nearest 0 are the lowest
frequencies and any divergence. Options prefix `modes_` as for the real modes (-modes_pep_tol, ...).
The problem is scaled (lambda by sqrt(||K|| / ||M||)). Each returned pair is checked: its backward
error must be below BACKWARD_TOL. With G = 0 the frequencies are the real solver's (modes.py) to 1e-10.

The solves and checks are collective on the operators' communicator.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc
from slepc4py import SLEPc

from .errors import InputError, Interrupted, SolverError
from .operators import Operators
from .petsctools import destroy, direct_solver, options_defaults

# A real part above this fraction of |lambda| is growth (the stable pairs' real parts are round-off).
UNSTABLE_TOL = 1e-6
# Largest backward error accepted for a returned eigenpair.
BACKWARD_TOL = 1e-8
# Entries of a mode within this fraction of its largest are ties for the phase (normalize_complex).
TIE_TOL = 1e-8
FACTOR_DEFAULTS = {"st_mat_mumps_icntl_24": "1"}


@dataclass
class GyroscopicModes:
    """The lowest complex modes, ascending in frequency: eigenvalues lambda_j (Im >= 0), and x_j =
    real[j] + i imag[j] normalized to x^H M x = 1, its largest entry real (new Vecs, owned here)."""

    eigenvalues: np.ndarray
    real: list = field(default_factory=list)
    imag: list = field(default_factory=list)

    @property
    def omega(self) -> np.ndarray:
        """The frequencies Im(lambda), rad/s (0 for a diverging mode)."""
        return self.eigenvalues.imag

    @property
    def frequency_hz(self) -> np.ndarray:
        return self.omega / (2 * np.pi)

    @property
    def count(self) -> int:
        return self.eigenvalues.size

    @property
    def unstable(self) -> list:
        """Indices (from 0) of the modes that grow: Re(lambda) > UNSTABLE_TOL |lambda|."""
        lam = self.eigenvalues
        return [j for j in range(lam.size) if lam[j].real > UNSTABLE_TOL * abs(lam[j])]

    def describe(self, j: int) -> str:
        """What mode j (from 0) does, in words."""
        lam = self.eigenvalues[j]
        if lam.real > UNSTABLE_TOL * abs(lam):
            kind = "divergence" if abs(lam.imag) <= UNSTABLE_TOL * abs(lam) else "flutter"
            return (f"mode {j + 1} is unstable ({kind}: lambda = {lam.real:.6g} {lam.imag:+.6g}i 1/s, "
                    f"growth rate {lam.real:.6g} 1/s)")
        return f"mode {j + 1}: {lam.imag / (2 * np.pi):.6g} Hz"

    def destroy(self) -> None:
        destroy(*self.real, *self.imag)
        self.real, self.imag = [], []


def _pep(ops: Operators, prefix: str, tol: float) -> SLEPc.PEP:
    """The configured PEP (lambda^2 M + lambda G + K) x = 0 about 0, the user's options under prefix."""
    pep = SLEPc.PEP().create(comm=ops.comm)
    try:
        pep.setOperators([ops.K, ops.G, ops.M])
        pep.setProblemType(SLEPc.PEP.ProblemType.GENERAL)
        pep.setType(SLEPc.PEP.Type.TOAR)
        pep.setWhichEigenpairs(SLEPc.PEP.Which.TARGET_MAGNITUDE)
        pep.setTarget(0.0)
        pep.setTolerances(tol, 1000)
        # Scale lambda by sqrt(||K|| / ||M||): unscaled, a beam's ||K|| >> lambda^2 ||M|| and its third and
        # fourth frequencies were 1e-7 off the real solver's at G = 0; scaled, 1e-11.
        pep.setScale(SLEPc.PEP.Scale.SCALAR)
        st = pep.getST()
        st.setType(SLEPc.ST.Type.SINVERT)
        direct_solver(st.getKSP(), PETSc.PC.Type.LU)
        pep.setOptionsPrefix(prefix)
        with options_defaults(prefix, FACTOR_DEFAULTS):
            pep.setFromOptions()
    except Exception:
        pep.destroy()
        raise
    return pep


def _pep_solve(pep: SLEPc.PEP, nev: int, prefix: str, what: str) -> None:
    """Solve for nev eigenpairs with the shift-and-invert defaults (never over the user's options); a
    failure is one SolverError naming `what`. Collective."""
    pep.setDimensions(nev, PETSc.DEFAULT, PETSc.DEFAULT)
    try:
        with options_defaults(prefix, FACTOR_DEFAULTS):
            pep.solve()
    except PETSc.Error as e:
        raise SolverError(f"{what}: the eigensolver failed (PETSc error {e.ierr}); K may be singular (the speed is "
                          f"exactly critical): move the axial speed off it") from None


def _solve(pep: SLEPc.PEP, ops: Operators, nev: int, prefix: str):
    """(eigenvalues, xr list, xi list) of the converged pairs with Im >= 0 (a real pair: the growing
    one, +sigma, only), ascending in (Im, |lambda|). Collective."""
    _pep_solve(pep, nev, prefix, "gyroscopic modes")
    values, xr, xi = [], [], []
    try:
        for i in range(pep.getConverged()):
            _take(pep, ops, i, prefix, values, xr, xi)
    except Exception:
        destroy(*xr, *xi)
        raise
    order = sorted(range(len(values)), key=lambda j: (round(values[j].imag, 12), abs(values[j])))
    return np.array([values[j] for j in order], dtype=complex), [xr[j] for j in order], [xi[j] for j in order]


def _take(pep: SLEPc.PEP, ops: Operators, i: int, prefix: str, values: list, xr: list, xi: list) -> None:
    """Append converged pair i to (values, xr, xi) if it has Im >= 0 (a real pair: lambda >= 0 only),
    after checking its backward error. Collective."""
    a, b = ops.K.createVecRight(), ops.K.createVecRight()
    lam = complex(pep.getEigenpair(i, a, b))
    error = pep.computeError(i, SLEPc.PEP.ErrorType.BACKWARD)
    tiny = UNSTABLE_TOL * abs(lam)
    keep = lam.imag > tiny or (abs(lam.imag) <= tiny and lam.real >= -tiny)
    if not keep:
        destroy(a, b)
        return
    if error > BACKWARD_TOL:
        destroy(a, b)
        raise SolverError(f"gyroscopic modes: eigenvalue {lam:.6g} has backward error {error:.1e} > {BACKWARD_TOL:g}: "
                          f"K is near singular close to a critical speed (move the speed away from it), or tighten "
                          f"-{prefix}pep_tol or check the -{prefix}st_ options")
    if abs(lam.imag) <= tiny:   # a real eigenvalue: a real eigenvector
        lam = complex(lam.real, 0.0)
        b.zeroEntries()
    values.append(lam)
    xr.append(a)
    xi.append(b)


def normalize_complex(xr: PETSc.Vec, xi: PETSc.Vec, M: PETSc.Mat) -> None:
    """Scale x = xr + i xi to x^H M x = 1 and turn its phase so that its largest entry (the lowest row
    among equals to TIE_TOL) is real and positive: the same vectors on any number of ranks. Collective."""
    lo, _ = xr.getOwnershipRange()
    world = xr.getComm().tompi4py()
    z = xr.getArray(readonly=True) + 1j * xi.getArray(readonly=True)
    # Entries within TIE_TOL of the largest are equals (a pinned-pinned travelling mode has |x| symmetric
    # about the middle: exact ties that round-off would break differently on each rank layout)
    peak = world.allreduce(float(np.abs(z).max()) if z.size else 0.0, op=MPI.MAX)
    near = np.flatnonzero(np.abs(z) >= (1 - TIE_TOL) * peak)
    row = world.allreduce(lo + int(near[0]) if near.size else np.iinfo(np.int64).max, op=MPI.MIN)
    value = complex(z[row - lo]) if lo <= row < lo + z.size else 0j
    value = world.allreduce(value)
    phase = np.conj(value) / abs(value)
    Mx = M.createVecLeft()
    mass = 0.0
    for v in (xr, xi):
        M.mult(v, Mx)
        mass += v.dot(Mx)
    Mx.destroy()
    scale = phase / np.sqrt(mass)
    a, b = xr.getArray(), xi.getArray()
    z = (a + 1j * b) * scale
    a[:], b[:] = z.real, z.imag


def gyroscopic_modes(ops: Operators, count: int | None = None, max_frequency_hz: float | None = None,
                     prefix: str = "modes_", tol: float = 1e-12, whole: str | None = None) -> GyroscopicModes:
    """The lowest complex modes of M u'' + G u' + K u = 0 (ops.G set): `count` of them, or every mode
    below `max_frequency_hz`, diverging and fluttering modes included (GyroscopicModes.unstable).

    A repeated frequency (|lambda|^2 within modes.REPEATED_TOL, relative: a round shaft at rest, the
    two planes of a pipe; modes.whole_count) is kept whole as modes.reference_modes keeps it: its
    modes are any mix of its eigenspace, so part of them lies in a direction set by round-off. Below
    max_frequency_hz the repeated frequency at the cutoff is always kept whole. Where `count` ends
    inside one, whole = "refuse" raises modes.RepeatedCut (the user's [basis] modes), "extend" returns
    the modes up to its end (the estimate's richer bases), None returns exactly `count` (the internal
    counts of a branch: the spring-perturbed and pinned problems, mode_state, check_stable).
    Collective on ops.comm."""
    from .modes import _repeated_cut, cluster_start, whole_count

    if ops.G is None:
        raise InputError("gyroscopic modes need a gyroscopic matrix G")
    if (count is None) == (max_frequency_hz is None):
        raise InputError("give the number of modes or a maximum frequency, not both")
    if whole not in (None, "refuse", "extend"):
        raise ValueError(f"gyroscopic_modes whole: None, 'refuse' or 'extend', got {whole!r}")
    n = ops.size
    if count is not None and not 1 <= count <= n:
        raise InputError(f"number of modes must be between 1 and {n} (the free DOFs), got {count}")
    pep = _pep(ops, prefix, tol)
    values, xr, xi = np.zeros(0, complex), [], []
    rounded = whole is not None or count is None
    try:
        nev = min(2 * count + 2 if count else 16, 2 * n)
        while True:
            destroy(*xr, *xi)
            values, xr, xi = _solve(pep, ops, nev, prefix)
            enough = (values.size >= count if count else
                      values.size and values[-1].imag > 2 * np.pi * max_frequency_hz)
            keep = count if count else int(np.count_nonzero(values.imag <= 2 * np.pi * max_frequency_hz))
            # |lambda|^2: omega^2 of a stable mode (the real modes' lambda), sigma^2 of a diverging one
            end = whole_count(np.abs(values) ** 2, keep) if rounded and enough and keep else keep
            # the repeated frequency reaches the last value converged: more may follow (one plane's mode)
            if (enough and not (rounded and keep and end >= values.size)) or nev >= 2 * n:
                break
            nev = min(2 * nev, 2 * n)
        if values.size < keep or keep == 0:
            raise SolverError(f"gyroscopic modes: only {values.size} modes converged" if count else
                              f"no mode below max_frequency_hz = {max_frequency_hz} Hz")
        if end > keep and count is not None and whole == "refuse":
            lam = np.abs(values) ** 2
            raise _repeated_cut(ops, float(lam[keep - 1]), keep, cluster_start(lam, keep), end)
        keep = end
        destroy(*xr[keep:], *xi[keep:])
        values, xr, xi = values[:keep], xr[:keep], xi[:keep]
        for a, b in zip(xr, xi):
            normalize_complex(a, b, ops.M)
    except Exception:
        destroy(*xr, *xi)
        raise
    finally:
        pep.destroy()
    return GyroscopicModes(eigenvalues=values, real=xr, imag=xi)


def critical_speed_note(ops: Operators) -> str:
    """For an axially moving beam, ' U_c = sqrt((T + P_cr) / m_t) = ... m/s': the speed at which its K
    becomes singular, sqrt((T + P_cr) / m_t) (structure.critical_speed; (pi / L) sqrt(EI / m_t) for a
    pinned-pinned pipe without tension), where the first frequency falls to zero. '' for a matrix
    model (its G has no speed). Collective."""
    from .structure import buckling_load, critical_speed

    beam = getattr(ops.mesh, "beam", None)
    if beam is None or not beam.axial_speed:
        return ""
    speed = critical_speed(beam, buckling_load(ops.comm, ops.mesh))
    return f" U_c = sqrt((T + P_cr) / m_t) = {speed:.6g} m/s"


def check_stable(ops: Operators, count: int, speed: str, prefix: str = "modes_") -> None:
    """An InputError naming the first unstable mode among the lowest `count` complex modes (divergence
    or flutter) at the axial `speed` (words), and the critical speed of a beam: a linear model that
    grows without bound has no steady response to run. Within ~1e-4 of the critical speed, the
    SolverError of a near-singular K, with the critical speed. Collective."""
    try:
        modes = gyroscopic_modes(ops, count=min(count, ops.size), prefix=prefix)
    except Interrupted:   # a termination signal is not a near-singular K
        raise
    except SolverError as e:
        note = critical_speed_note(ops)
        raise SolverError(f"{e}; the critical speed is{note}" if note else str(e)) from None
    try:
        unstable = [modes.describe(j) for j in modes.unstable]
    finally:
        modes.destroy()
    if unstable:
        raise InputError(f"the structure is unstable at axial speed {speed}: {unstable[0]}; lower the axial speed "
                         f"below the critical speed{critical_speed_note(ops)} (or raise the tension)")


def check_damped_stable(ops: Operators, damped: PETSc.Mat, count: int, speed: str, prefix: str = "modes_") -> None:
    """An InputError if M u'' + `damped` u' + K u = 0 (damped = C + G) has a growing mode among the
    `count` of smallest |lambda|: a structure whose K is not positive definite can be held by its
    gyroscopic forces alone (all undamped lambda = +-i omega, check_stable passes), and damping then
    destroys that stability (Kelvin-Tait-Chetaev): the run would grow without bound. Collective."""
    pep = _pep(Operators(comm=ops.comm, K=ops.K, M=ops.M, G=damped), prefix, 1e-12)
    try:
        _pep_solve(pep, min(2 * count + 2, 2 * ops.size), prefix, "gyroscopic modes with damping")
        worst = None
        for i in range(pep.getConverged()):
            lam = complex(pep.getEigenpair(i))
            if lam.real > UNSTABLE_TOL * abs(lam) and pep.computeError(i, SLEPc.PEP.ErrorType.BACKWARD) <= BACKWARD_TOL:
                worst = lam if worst is None or lam.real > worst.real else worst
    finally:
        pep.destroy()
    if worst is not None:
        raise InputError(f"the structure is unstable with its damping at axial speed {speed}: a mode grows (lambda = "
                         f"{worst.real:.6g} {abs(worst.imag):+.6g}i 1/s, growth rate {worst.real:.6g} 1/s) though the "
                         f"undamped one does not: K is not positive definite and only the gyroscopic forces held it, "
                         f"which damping undoes; lower the axial speed below the critical speed"
                         f"{critical_speed_note(ops)} (or stiffen K)")


def mode_state(ops: Operators, mode: int, prefix: str = "modes_") -> tuple:
    """(u, v): the free vibration of complex mode `mode` (from 1) at t = 0, u = Re x, v = Re(lambda x)
    (x normalized as in normalize_complex; new Vecs, the caller's). A mode of a repeated frequency is
    refused as for the real modes (modes.repeated_mode_refusal: its shape is a mix set by round-off,
    another on another rank count). Collective."""
    from .modes import repeated_mode_refusal

    modes = gyroscopic_modes(ops, count=mode, prefix=prefix, whole="extend")
    refusal = repeated_mode_refusal(np.abs(modes.eigenvalues) ** 2, mode)   # the same values on every rank
    if refusal:
        modes.destroy()
        raise InputError(refusal)
    try:
        lam = modes.eigenvalues[mode - 1]
        u, v = modes.real[mode - 1].copy(), modes.real[mode - 1].copy()
        v.scale(lam.real)
        v.axpy(-lam.imag, modes.imag[mode - 1])
    finally:
        modes.destroy()
    return u, v
