"""Linear damping of the structure: modal damping ratios or Rayleigh damping C = alpha M + beta K.

The paper's examples are undamped; real tubes have 1-3 % damping. In a reduced basis V with
V^T M V = I, modal ratios put 2 zeta_i omega_i on the diagonal (omega_i^2 = (V^T K V)_ii, so the
DBFs get hat-omega_i, Eq. 41), and Rayleigh damping projects exactly to alpha I + beta V^T K V.

Plain values and small numpy matrices: nothing here is collective.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError, is_number


# Above this a modal ratio is a typing error (1e300 overflowed 2 zeta omega and failed in the integrator as
# "reduce dt"); up to it the overdamped modes integrate (implicitly) and are tested.
ZETA_MAX = 100.0


@dataclass(frozen=True)
class Damping:
    """zeta: one ratio for every basis vector, or one per basis vector (a tuple). Or Rayleigh
    coefficients alpha (1/s) and beta (s). Not both kinds at once."""

    zeta: float | tuple = 0.0
    rayleigh_alpha: float = 0.0
    rayleigh_beta: float = 0.0

    def __post_init__(self):
        """The numbers checked once (the Python API's edge): a string, a bool, None or a nested list
        is one InputError, not a numpy traceback (red team)."""
        zeta = self.zeta
        if isinstance(zeta, (list, tuple, np.ndarray)):
            ratios = list(np.asarray(zeta, dtype=object).ravel()) if np.ndim(zeta) == 1 else None
        else:
            ratios = [zeta]
        if not ratios or not all(_real(r) and r >= 0 for r in ratios):
            raise InputError(f"damping zeta must be non-negative numbers, got {self.zeta!r}")
        ratios = np.array(ratios, dtype=float)
        if np.any(ratios > ZETA_MAX):
            raise InputError(f"damping zeta {ratios.max():g} is not a structure's (1 is critical damping; tubes "
                             f"and beams have 0.001-0.05): give ratios of at most {ZETA_MAX:g}")
        for name in ("rayleigh_alpha", "rayleigh_beta"):
            value = getattr(self, name)
            if not (_real(value) and value >= 0):
                raise InputError(f"damping {name} must be a non-negative number, got {value!r}")
        if np.any(ratios > 0) and (self.rayleigh_alpha > 0 or self.rayleigh_beta > 0):
            raise InputError("damping: give modal ratios (zeta) or Rayleigh coefficients, not both")

    @property
    def kind(self) -> str:
        if self.rayleigh_alpha > 0 or self.rayleigh_beta > 0:
            return "rayleigh"
        return "modal" if np.any(np.asarray(self.zeta) > 0) else "none"

    def ratios(self, count: int) -> np.ndarray:
        """Modal damping ratios for `count` basis vectors."""
        ratios = np.atleast_1d(np.asarray(self.zeta, dtype=float))
        if ratios.size == 1:
            return np.full(count, ratios[0])
        if ratios.size != count:
            raise InputError(f"damping zeta has {ratios.size} ratios for {count} basis vectors")
        return ratios

    def modal_coefficients(self, omega: np.ndarray, modes: int | None = None) -> np.ndarray:
        """c_i in q_i'' + c_i q_i' + omega_i^2 q_i for M-orthonormal modes of frequency omega_i; the
        first `modes` (default all) are reference modes, whose repeated frequencies take one ratio."""
        omega = np.asarray(omega, dtype=float)
        if self.kind == "rayleigh":
            return self.rayleigh_alpha + self.rayleigh_beta * omega**2
        ratios = self.ratios(omega.size)
        count = omega.size if modes is None else modes
        _check_repeated(ratios[:count], omega[:count])
        return 2.0 * ratios * omega

    def check_rayleigh(self, omega: np.ndarray) -> None:
        """An InputError when Rayleigh damping gives a reference mode (omega_i > 0, rad/s) a ratio
        alpha / (2 omega_i) + beta omega_i / 2 above ZETA_MAX, as a modal ratio would be (alpha or beta
        of 1e300 overflowed and ended as an integrator failure advising a smaller dt)."""
        omega = np.asarray(omega, dtype=float)
        omega = omega[omega > 0]
        if self.kind != "rayleigh" or not omega.size:
            return
        with np.errstate(over="ignore"):
            ratios = self.rayleigh_alpha / (2 * omega) + self.rayleigh_beta * omega / 2
        i = int(np.argmax(ratios))
        if not ratios[i] <= ZETA_MAX:
            raise InputError(f"damping rayleigh_alpha = {self.rayleigh_alpha:g} 1/s, rayleigh_beta = "
                             f"{self.rayleigh_beta:g} s give the reference mode of {omega[i] / (2 * np.pi):.4g} Hz a "
                             f"damping ratio of {ratios[i]:.3g} (1 is critical): give coefficients that keep the "
                             f"modes' ratios at most {ZETA_MAX:g}")

    def reduced_matrix(self, reduced_stiffness: np.ndarray, reduced_mass: np.ndarray | None = None,
                       modes: int | None = None) -> np.ndarray:
        """C_r for a basis with V^T K V = reduced_stiffness and V^T M V = reduced_mass (I when not
        given; modal ratios assume it) whose first `modes` vectors are reference modes (default all):
        an enrichment column is no mix of a repeated mode (two at symmetric stops share hat-omega)."""
        Kr = np.asarray(reduced_stiffness, dtype=float)
        if self.kind == "rayleigh":
            Mr = np.eye(Kr.shape[0]) if reduced_mass is None else np.asarray(reduced_mass, dtype=float)
            return self.rayleigh_alpha * Mr + self.rayleigh_beta * Kr
        return np.diag(self.modal_coefficients(np.sqrt(np.clip(np.diag(Kr), 0.0, None)), modes))


def _real(value) -> bool:
    """A finite real number, not a bool."""
    return is_number(value) and bool(np.isfinite(value))


def _check_repeated(ratios: np.ndarray, omega: np.ndarray) -> None:
    """A repeated frequency's modes are any mix of its eigenspace (a tube's y and z, turned as the
    eigensolver chose): one ratio each, or the damping depends on the load's direction (red team: zeta
    on mode 1 damped z and not y). Repeated as the reference modes count it (modes.repeated, on
    omega^2: it was 1e-6 relative in omega here, twice the modes' band)."""
    from .modes import repeated

    order = np.argsort(omega)
    w, r = omega[order], ratios[order]
    for i in range(w.size - 1):
        if repeated(w[i] ** 2, w[i + 1] ** 2) and r[i + 1] != r[i]:
            raise InputError(f"damping zeta: basis vectors {order[i] + 1} and {order[i + 1] + 1} share the frequency "
                             f"{w[i] / (2 * np.pi):.6g} Hz (a repeated mode, any mix of its directions) but have the "
                             f"ratios {r[i]:g} and {r[i + 1]:g}: give them one ratio")
