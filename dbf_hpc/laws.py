"""Constraint laws N(z, v) of the discrete constraints, vectorized, with exact derivatives.

Conventions (shared with the reduced model and the integrators):
- z is the TOTAL displacement at a constraint (m), v its velocity (m/s).
- N is the force ON the structure (N), restoring, with exactly the sign of Eq. 23:
      N(z) = k_minus (-d_minus - z)   for z < -d_minus
             0                        for -d_minus <= z <= d_plus
             k_plus (d_plus - z)      for z > d_plus
  The edges belong to the deadband: there N = 0, dN/dz = 0 and in_contact is False.
- power:  N = k_minus (-d_minus - z)^p_minus below, -k_plus (z - d_plus)^p_plus above (k in N/m^p).
  Eq. 42 is power with k_minus = 0.1, p_minus = 3, k_plus = 1e6, p_plus = 1, d_minus = d_plus = d_x.
  deadband is power with p = 1 on both sides; hertz is power with p = 1.5 (by default).
- linear: N = -k z.  cubic: N = -(k z + k3 z^3).  Both have no clearance and are always in contact.
  A Law stores k in k_plus (k_minus is set equal to it).
- table: piecewise-linear through (z_i, f_i), f the force on the structure, non-increasing in z
  (restoring: a rising segment is refused); beyond the ends the end segments are extended. dN/dz
  is the segment slope (at a breakpoint, the segment to the right, so at a table's upper contact
  edge the slope is the contact one, not the deadband law's 0).
- potential U: elastic N = -dU/dz. For the two-sided kinds, linear and cubic U >= 0 and U = 0 in the
  deadband; for a table U(z) = -integral_0^z N, >= 0 when its force is 0 at z = 0.
- Negative clearance is an interference fit (preload): for -d_minus > d_plus both sides push at once
  on the overlap, N = k_minus (-d_minus - z)^p_minus - k_plus (z - d_plus)^p_plus, so the force at
  z = 0 is the difference of the two preloads. The formula is the same for every clearance: each
  side contributes only where it is compressed. An interference deeper than MAX_INTERFERENCE (1 m) is
  refused: near the preload z is resolved only to 2.2e-16 x the depth (double precision).
- Contact damping, added to the elastic force only where in_contact: linear, -c v; Hunt-Crossley,
  -alpha |N_el| v (alpha in s/m). For the two-sided kinds |N_el| is the sum of the magnitudes of the
  two sides' forces (equal to |N_el| unless both sides push at once), so an interference fit still
  dissipates at its balance point. Either is dissipative: F_d v <= 0. Neither is clipped, so while the
  constraint separates either can pull (an adhesive force, N of the sign opposite to N_el): linear
  damping as soon as c |v| > |N_el| (always just before the contact ends, where N_el -> 0),
  Hunt-Crossley only at separation speeds |v| > 1 / alpha. Hunt & Crossley's alpha comes from the
  coefficient of restitution, e = 1 - (2/3) alpha v_impact, valid for alpha v small: at alpha v = 3/2
  e = 0, and within that range the separation speed keeps alpha |v| < 3/8, so it never pulls. A run
  whose alpha |v| in contact exceeds 1.5 warns (run.HUNT_CROSSLEY_MAX: the contact is overdamped, and
  its short stopping phase makes the full-order force depend on dt).
- A two-sided law may have k = 0 on one side: a one-sided stop.
- friction: Coulomb friction alone against a given normal force F_n (N), regularized over the
  sliding speed v_reg (m/s): N = -mu F_n tanh(v / v_reg), dN/dv = -(mu F_n / v_reg) sech^2(v / v_reg),
  dN/dz = 0, no potential; always in contact. It tends to the set-valued Coulomb law as v_reg -> 0
  (Den Hartog's oscillator with dry friction, tests/test_friction.py).

Use: ConstraintLaws(laws).force(z, v), .jacobian(z, v) -> (dN/dz, dN/dv) (diagonal, one entry per
constraint), .force_and_jacobian(z, v) for both in one pass, .potential(z), .in_contact(z).

Pure numpy: nothing here is collective (every rank that integrates evaluates the laws alone).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from .errors import InputError, is_number

LAWS = ("deadband", "power", "linear", "cubic", "hertz", "table", "friction")
CONTACT_DAMPING = ("none", "linear", "hunt_crossley")

_TWO_SIDED = ("deadband", "power", "hertz")
_DEFAULT_EXPONENT = {"hertz": 1.5}


def default_exponent(kind: str) -> float:
    """The exponent of a side of a `kind` law that gives none: 1.5 for hertz, else 1."""
    return _DEFAULT_EXPONENT.get(kind, 1.0)
_NUMBER_FIELDS = ("clearance_minus", "clearance_plus", "k_minus", "k_plus", "k3", "c", "alpha")


def _check_contact_damping(damping: str, c: float, alpha: float) -> None:
    """c belongs to linear contact damping, alpha to Hunt-Crossley's, each positive when used."""
    if c != 0 and damping != "linear":
        raise InputError("c applies only with damping = \"linear\"")
    if alpha != 0 and damping != "hunt_crossley":
        raise InputError("alpha applies only with damping = \"hunt_crossley\"")
    if damping == "linear" and not c > 0:
        raise InputError(f"c must be a positive number with damping = \"linear\", got {c!r}")
    if damping == "hunt_crossley" and not alpha > 0:
        raise InputError(f"alpha must be a positive number with damping = \"hunt_crossley\", got {alpha!r}")


def _quoted(names) -> str:
    return ", ".join(f'"{n}"' for n in names)


# Coulomb coefficients of real contact pairs are below about 1.5 (clean metals in vacuum reach a few);
# a larger one is a typo or a unit slip, and its stiff regularized stick crawled at 1e-13 s steps (red team)
MU_MAX = 10.0


def _check_mu(mu: float) -> None:
    if mu > MU_MAX:
        raise InputError(f"mu = {mu:g}: a Coulomb friction coefficient above {MU_MAX:g} is no contact pair's (steel on "
                         f"steel is about 0.2-0.8); give the coefficient itself, or hold the support with a stiff "
                         f"spring law instead of friction")


@dataclass(frozen=True)
class Law:
    """One constraint's law (see the module docstring). Validated on construction.

    exponent_minus/plus default to the kind's exponent (1; hertz 1.5); they may differ from 1 only
    for power and hertz. linear and cubic take their k from k_plus (k_minus, if given, must equal
    it). All-zero stiffness is a valid, force-free law; law_from_dict insists on a law that can push
    (a stiffness, a table with a nonzero force, a friction law with mu and normal_force > 0).
    """

    kind: str = "deadband"
    clearance_minus: float = 0.0
    clearance_plus: float = 0.0
    k_minus: float = 0.0
    k_plus: float = 0.0
    exponent_minus: Optional[float] = None
    exponent_plus: Optional[float] = None
    k3: float = 0.0
    table: tuple = ()
    damping: str = "none"
    c: float = 0.0
    alpha: float = 0.0
    normal_force: float = 0.0
    mu: float = 0.0
    v_reg: float = 0.0

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        for name in ("normal_force", "mu", "v_reg"):
            value = getattr(self, name)
            if not (is_number(value) and math.isfinite(value) and value >= 0):
                raise InputError(f"{name} must be a non-negative finite number, got {value!r}")
            if value != 0 and self.kind != "friction":
                raise InputError(f"{name} applies only to a friction law (law = \"friction\")")
            put(name, float(value))
        _check_mu(self.mu)
        if self.kind == "friction" and not (self.v_reg > 0):
            raise InputError(f"v_reg must be a positive number for a friction law, got {self.v_reg!r}")

        if self.kind not in LAWS:
            raise InputError(f"law must be one of {_quoted(LAWS)}, got {self.kind!r}")
        if self.damping not in CONTACT_DAMPING:
            raise InputError(f"damping must be one of {_quoted(CONTACT_DAMPING)}, got {self.damping!r}")
        for name in _NUMBER_FIELDS:
            value = getattr(self, name)
            if not (is_number(value) and math.isfinite(value)):
                raise InputError(f"{name} must be a finite number, got {value!r}")
            put(name, float(value))
        for name in ("k_minus", "k_plus", "k3", "c", "alpha"):
            if getattr(self, name) < 0:
                raise InputError(f"{name} must be a non-negative number, got {getattr(self, name)!r}")

        default = _DEFAULT_EXPONENT.get(self.kind, 1.0)
        for name in ("exponent_minus", "exponent_plus"):
            value = getattr(self, name)
            if value is None:
                value = default
            if not (is_number(value) and math.isfinite(value) and value >= 1):
                raise InputError(f"{name} must be a number >= 1, got {value!r}")
            if value != 1 and self.kind not in ("power", "hertz"):
                raise InputError(f"{name} does not apply to a {self.kind} law (it is 1); "
                                 f"use law = \"power\"")
            put(name, float(value))

        kind = self.kind
        if kind in ("linear", "cubic"):
            if self.k_minus not in (0.0, self.k_plus):
                raise InputError(f"k_minus = {self.k_minus:g} and k_plus = {self.k_plus:g} differ; "
                                 f"a {kind} law has one k")
            put("k_minus", self.k_plus)
        for name in ("clearance_minus", "clearance_plus"):
            if getattr(self, name) != 0 and kind not in _TWO_SIDED:
                raise InputError(f"{name} does not apply to a {kind} law")
        if self.k3 != 0 and kind != "cubic":
            raise InputError(f"k3 does not apply to a {kind} law")
        if kind == "table":
            for name in ("k_minus", "k_plus"):
                if getattr(self, name) != 0:
                    raise InputError(f"{name} does not apply to a table law")
            put("table", _check_table(self.table))
        elif self.table is None or len(self.table) == 0:
            put("table", ())
        else:
            raise InputError(f"table does not apply to a {kind} law")
        _check_contact_damping(self.damping, self.c, self.alpha)
        _check_representable(self)
        _check_interference(self)


_OVERFLOW = "overflows double precision (a value beyond 1.8e308): check its units"


def _check_representable(law: "Law") -> None:
    """The constants the evaluation forms are finite numbers: k p (the slope's factor) on each acting
    side, the preload k (-clearance)^p and its slope of a negative clearance, every table slope and the
    table's integral, mu F_n / v_reg of friction. Red team: k = 1e308 with p = 2 gave k p = inf, a NaN
    slope even in the deadband, and a run that crawled at 1e-13 s; a negative clearance of -1e308 a
    NaN force; a table step of 1e-320 m an infinite slope."""
    with np.errstate(all="ignore"):
        if law.kind in _TWO_SIDED:
            for side in ("minus", "plus"):
                k, p, d = (getattr(law, f"{name}_{side}") for name in ("k", "exponent", "clearance"))
                if k == 0:
                    continue
                # the compression at z = 0 (a negative clearance: a preload), a numpy float: its power overflows
                # to inf (a Python float's raised OverflowError, an internal error for clearance = -2 m at p = 2000)
                x = np.float64(max(-d, 0.0))
                if not (np.isfinite(k * p) and np.isfinite(k * x ** p) and np.isfinite(k * p * x ** (p - 1.0))):
                    raise InputError(f"k_{side} = {k:g} with exponent_{side} = {p:g} and clearance_{side} = {d:g}: "
                                     f"the force or its slope {_OVERFLOW}")
        elif law.kind == "table":
            points = np.array(law.table, dtype=float)
            dz, df = np.diff(points[:, 0]), np.diff(points[:, 1])
            slope = df / dz
            integral = np.cumsum(0.5 * (points[1:, 1] + points[:-1, 1]) * dz)
            bad = np.flatnonzero(~(np.isfinite(dz) & np.isfinite(df) & np.isfinite(slope) & np.isfinite(integral)))
            if bad.size:
                i = int(bad[0])
                raise InputError(f"table: the segment from point {i + 1} (z = {points[i, 0]:g} m) to point {i + 2} "
                                 f"(z = {points[i + 1, 0]:g} m): its slope or the force's integral {_OVERFLOW}")
            rising = np.flatnonzero(slope > 0)
            if rising.size:   # red team: a rising segment ran, and the full-order reference's Gauss-Seidel
                # fallback (which needs N non-increasing in z) was 9.6 % off its own dt / 4 run, estimating 0.5 %
                i = int(rising[0])
                raise InputError(f"table: the segment from point {i + 1} (z = {points[i, 0]:g} m, {points[i, 1]:g} N) to "
                                 f"point {i + 2} (z = {points[i + 1, 0]:g} m, {points[i + 1, 1]:g} N) raises the force "
                                 f"with z (a negative stiffness, {slope[i]:.3g} N/m): a constraint law must be restoring, "
                                 f"the force ON the structure non-increasing in z (negative where z presses into the "
                                 f"stop above); check the forces' sign")
        elif law.kind == "friction" and not np.isfinite(law.mu * law.normal_force / law.v_reg):
            raise InputError(f"mu normal_force / v_reg = {law.mu:g} * {law.normal_force:g} / {law.v_reg:g}, the "
                             f"friction's slope at rest, {_OVERFLOW}")


# The deepest interference fit (negative clearance, m) a two-sided law takes. A side's compression is formed
# as edge - z, which resolves z only to 2.2e-16 x the depth near the edge (double precision): red team,
# clearance = -1e10 m on the paper's beam (k = 1e6 N/m) ran to the end with its force quantized in 2 N steps
# and w 1300 times off, and -1e100 m with no force at all (the two preloads cancel and the motion is below
# their last bit), where the exact answer is a 2 k spring. Real fits are micrometres to millimetres deep; a
# metre keeps the resolution at 2e-16 m.
MAX_INTERFERENCE = 1.0


def _check_interference(law: "Law") -> None:
    """A negative clearance on an acting side is at most MAX_INTERFERENCE deep."""
    if law.kind not in _TWO_SIDED:
        return
    for side in ("minus", "plus"):
        d = getattr(law, f"clearance_{side}")
        if getattr(law, f"k_{side}") > 0 and -d > MAX_INTERFERENCE:
            raise InputError(f"clearance_{side} = {d:g} m: an interference fit (a negative clearance) deeper than "
                             f"{MAX_INTERFERENCE:g} m is no fit's (they are micrometres to millimetres) and the law "
                             f"would resolve the displacement only to {np.spacing(-d):.2g} m there (double "
                             f"precision around the preload): check its unit and sign")


def _check_table(table) -> tuple:
    """((z0, f0), ...) as floats, >= 2 points, finite, strictly increasing z."""
    if isinstance(table, (str, bytes)) or not isinstance(table, (list, tuple, np.ndarray)):
        raise InputError(f"table must be a list of [z, force] pairs, got {table!r}")
    points = []
    for point in table:
        if (isinstance(point, (str, bytes)) or not isinstance(point, (list, tuple, np.ndarray))
                or len(point) != 2 or not all(is_number(x) and math.isfinite(x) for x in point)):
            raise InputError(f"table must be a list of [z, force] pairs of finite numbers, "
                             f"got the point {point!r}")
        points.append((float(point[0]), float(point[1])))
    if len(points) < 2:
        raise InputError(f"table must have at least 2 points, got {len(points)}")
    for i in range(1, len(points)):
        if not points[i][0] > points[i - 1][0]:
            raise InputError(f"table z values must be strictly increasing: point {i + 1} has "
                             f"z = {points[i][0]:g} after z = {points[i - 1][0]:g}")
    return tuple(points)


# Scene keys, and for each kind the keys it takes besides the damping keys.
KEYS = ("law", "clearance", "clearance_minus", "clearance_plus", "k", "k_minus", "k_plus",
        "exponent", "exponent_minus", "exponent_plus", "k3", "table", "damping", "c", "alpha", "normal_force", "mu",
        "v_reg")
_SIDED = {"clearance": ("clearance_minus", "clearance_plus"), "k": ("k_minus", "k_plus"),
          "exponent": ("exponent_minus", "exponent_plus")}
_KIND_KEYS = {
    "deadband": ("clearance", "clearance_minus", "clearance_plus", "k", "k_minus", "k_plus"),
    "power": ("clearance", "clearance_minus", "clearance_plus", "k", "k_minus", "k_plus",
              "exponent", "exponent_minus", "exponent_plus"),
    "linear": ("k", "k_minus", "k_plus"),
    "cubic": ("k", "k_minus", "k_plus", "k3"),
    "table": ("table",),
    "friction": ("normal_force", "mu", "v_reg"),
}
_KIND_KEYS["hertz"] = _KIND_KEYS["power"]


def law(kind: str = "deadband", **keys) -> Law:
    """A Law from the keys of a scene's [[constraint]] table, e.g. law("deadband", clearance=2.5e-3,
    k=1e6) or law("hertz", clearance=1e-4, k=3e9, damping="hunt_crossley", alpha=0.2). Kinds:
    deadband (the paper's Eq. 23), power (Eq. 42 is one), hertz, linear, cubic, table, friction, and
    on a beam of two planes circular and flat_bar. Units (SI, as docs/scene.md's [[constraint]]
    table): clearance m, k N/m^p for the side's exponent p (N/m for deadband, linear, circular and
    flat_bar), k3 N/m^3, table [[z (m), force (N)], ...], c N s/m, alpha s/m, normal_force N,
    v_reg m/s, angle deg. The force N(z, v) is on the structure, restoring (module docstring)."""
    return law_from_dict(None, {"law": kind, **keys})


def law_from_dict(index: int | str | None, d: dict):
    """The Law of constraint `index` (as the user counts them, or the words that name it) from its
    [[constraint]] table, without its position key. Every error names the constraint and the key."""
    where = index if isinstance(index, str) else f"constraint {index}" if index is not None else "law"
    if d.get("law") in LAWS_2D:
        return circular_from_dict(where, d)
    _check_values(where, d)
    kind, damping = d.get("law", "deadband"), d.get("damping", "none")
    _check_keys(where, d, kind, damping)
    fields = {"kind": kind, "damping": damping}
    for both, sides in _SIDED.items():
        for side in sides:
            if both in d:
                fields[side] = d[both]
            elif side in d:
                fields[side] = d[side]
    for key in ("k3", "c", "alpha", "table", "normal_force", "mu", "v_reg"):
        if key in d:
            fields[key] = d[key]
    if kind == "friction":
        for key in ("normal_force", "mu"):
            if key not in d:
                raise InputError(f"{where}: a friction law needs {key}")
        zeros = [key for key in ("mu", "normal_force") if d[key] == 0]
        if zeros:
            # Refused, not taken as "frictionless": a 1-D friction law is friction alone, N = -mu F_n tanh(v / v_reg),
            # so with mu F_n = 0 it is no constraint at all, and the reduced model would still carry its DBF (a
            # basis, and results, that differ from the run without it); a frictionless support is that run
            named = " and ".join(f"{key} = 0" for key in zeros)
            raise InputError(f"{where}: {named}: a friction law (N = -mu normal_force tanh(v / v_reg)) would never "
                             f"push; give mu and normal_force positive values, or remove the constraint for a "
                             f"frictionless support")
        fields.setdefault("v_reg", DEFAULT_V_REG)
        if d.get("damping", "none") != "none":
            raise InputError(f"{where}: a friction law has no contact damping (it is all dissipation)")
    _check_stiffness(where, d, kind, fields)
    if kind in ("linear", "cubic") and "k_minus" in fields and "k_plus" not in fields:
        fields["k_plus"] = fields["k_minus"]  # a lone k_minus is the one k
    try:
        result = Law(**fields)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    if kind == "table" and all(f == 0 for _, f in result.table):
        # red team: a table of zero forces was accepted, a constraint that never pushes (and, in the reduced
        # model, a DBF for nothing), like a deadband with k = 0, which is refused
        raise InputError(f"{where}: table: every force is 0 N: the constraint would never push; give the forces "
                         f"of the contact (N on the structure), or remove the constraint")
    return result


def _check_values(where: str, d: dict) -> None:
    """Known keys, each of the right type and range."""
    for key in d:
        if key in KEYS_2D and key not in KEYS:
            raise InputError(f"{where}: {key} applies only to a flat_bar law (law = \"flat_bar\")")
        if key in ("mu", "v_reg", "normal_force") and d.get("law") != "friction":
            raise InputError(f"{where}: {key} applies to law = \"friction\" (and mu, v_reg to circular, flat_bar)")
        if key not in KEYS:
            raise InputError(f"{where}: unknown key {key!r} (known: {', '.join(KEYS)})")
    for key, value in d.items():
        if key in ("law", "damping"):
            if not isinstance(value, str):
                raise InputError(f"{where}: {key} must be a string, got {value!r}")
        elif key == "table":
            if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
                raise InputError(f"{where}: table must be a list of [z, force] pairs, got {value!r}")
        elif not is_number(value):
            raise InputError(f"{where}: {key} must be a number, got {value!r}")
        elif not math.isfinite(value):
            raise InputError(f"{where}: {key} must be a finite number, got {value!r}")
        elif key in ("k", "k_minus", "k_plus", "k3") and value < 0:
            raise InputError(f"{where}: {key} must be a non-negative number, got {value!r}")
        elif key.startswith("exponent") and value < 1:
            raise InputError(f"{where}: {key} must be a number >= 1, got {value!r}")
        elif key in ("c", "alpha") and not value > 0:
            raise InputError(f"{where}: {key} must be a positive number, got {value!r}")


def _check_keys(where: str, d: dict, kind: str, damping: str) -> None:
    """The law and damping kinds exist, and every key applies to them."""
    if kind not in LAWS:
        raise InputError(f"{where}: law must be one of {_quoted(LAWS + LAWS_2D)}, got {kind!r}")
    if damping not in CONTACT_DAMPING:
        raise InputError(f"{where}: damping must be one of {_quoted(CONTACT_DAMPING)}, got {damping!r}")
    for both, sides in _SIDED.items():
        given = [s for s in sides if s in d]
        if both in d and given:
            raise InputError(f"{where}: give either {both} or {'/'.join(sides)}, not both "
                             f"({both} and {given[0]} are set)")
    for key in d:
        if key not in ("law", "damping", "c", "alpha") and key not in _KIND_KEYS[kind]:
            takes = [k for k in LAWS if key in _KIND_KEYS[k]]
            raise InputError(f"{where}: {key} does not apply to a {kind} law "
                             f"(laws that take it: {', '.join(takes)})")
    if "c" in d and damping != "linear":
        raise InputError(f"{where}: c applies only with damping = \"linear\"")
    if "alpha" in d and damping != "hunt_crossley":
        raise InputError(f"{where}: alpha applies only with damping = \"hunt_crossley\"")
    if damping == "linear" and "c" not in d:
        raise InputError(f"{where}: damping = \"linear\" needs c (N s/m)")
    if damping == "hunt_crossley" and "alpha" not in d:
        raise InputError(f"{where}: damping = \"hunt_crossley\" needs alpha (s/m)")


def _check_stiffness(where: str, d: dict, kind: str, fields: dict) -> None:
    """A law that can push: the stiffness its kind needs is given and not all zero."""
    stiffness = [key for key in ("k", "k_minus", "k_plus", "k3") if key in d]
    if kind in _TWO_SIDED:
        if not stiffness:
            raise InputError(f"{where}: a {kind} law needs k (or k_minus and/or k_plus)")
        if fields.get("k_minus", 0) == 0 and fields.get("k_plus", 0) == 0:
            # every k given is 0: all of them named (red team: k_minus = 0 with k_plus = 0 blamed k_minus alone,
            # also when the user's last change was k_plus)
            zeros = " and ".join(f"{key} = 0" for key in stiffness)
            raise InputError(f"{where}: {zeros}: the constraint would never push; give k, k_minus or k_plus a "
                             f"positive value")
    elif kind == "linear":
        if not stiffness:
            raise InputError(f"{where}: a linear law needs k")
        if not fields.get("k_plus", fields.get("k_minus", 0)) > 0:
            raise InputError(f"{where}: {stiffness[0]} must be a positive number, got 0")
    elif kind == "cubic":
        if not stiffness:
            raise InputError(f"{where}: a cubic law needs k and/or k3")
        if fields.get("k_plus", fields.get("k_minus", 0)) == 0 and fields.get("k3", 0) == 0:
            raise InputError(f"{where}: {stiffness[0]} must be a positive number, got 0")
    elif kind == "table" and "table" not in d:
        raise InputError(f"{where}: a table law needs table = [[z, force], ...]")


class _Group:
    """Constraints of one family; `at` selects them from the full arrays (a slice if contiguous)."""

    def __init__(self, indices):
        indices = np.asarray(indices, dtype=np.intp)
        if np.array_equal(indices, np.arange(indices[0], indices[0] + indices.size)):
            self.at = slice(int(indices[0]), int(indices[0]) + indices.size)
        else:
            self.at = indices


class _TwoSided(_Group):
    """deadband, power, hertz: N = k_m <-d_m - z>^p_m - k_p <z - d_p>^p_p, <x> = max(x, 0)."""

    def __init__(self, indices, laws):
        super().__init__(indices)
        arr = lambda name: np.array([getattr(law, name) for law in laws], dtype=float)
        self.edge_m = -arr("clearance_minus")
        self.edge_p = arr("clearance_plus")
        self.km, self.kp = arr("k_minus"), arr("k_plus")
        self.pm, self.pp = arr("exponent_minus"), arr("exponent_plus")
        self.acts_m, self.acts_p = self.km > 0, self.kp > 0
        self.linear = bool(np.all(self.pm == 1) and np.all(self.pp == 1))  # skip the powers
        self.pm1, self.pp1 = self.pm - 1.0, self.pp - 1.0
        self.km_pm, self.kp_pp = self.km * self.pm, self.kp * self.pp
        self.zero = np.zeros(len(laws))

    def _compressions(self, z):
        # in place against a stored zero array: the cheapest numpy form for small arrays
        xm = self.edge_m - z
        np.maximum(xm, self.zero, out=xm)
        xp = z - self.edge_p
        np.maximum(xp, self.zero, out=xp)
        return xm, xp

    def _sides(self, z):
        """The two sides' force magnitudes and slopes, and where each side is compressed."""
        xm, xp = self._compressions(z)
        on_m, on_p = xm > self.zero, xp > self.zero
        if self.linear:
            return self.km * xm, self.kp * xp, self.km * on_m, self.kp * on_p, on_m, on_p
        tm, tp = xm**self.pm1, xp**self.pp1  # one power per side; the mask drops 0**0 = 1 at p = 1
        return (self.km * xm * tm, self.kp * xp * tp, self.km_pm * tm * on_m, self.kp_pp * tp * on_p,
                on_m, on_p)

    def elastic(self, z):
        xm, xp = self._compressions(z)
        if self.linear:
            return self.km * xm - self.kp * xp
        return self.km * xm * xm**self.pm1 - self.kp * xp * xp**self.pp1  # as in _sides, bit for bit

    def stiffness(self, z):
        """(N, dN/dz)."""
        fm, fp, gm, gp, _, _ = self._sides(z)
        return fm - fp, -(gm + gp)

    def evaluate(self, z):
        """(N, dN/dz, |N|, d|N|/dz, contact); |N| sums the two sides' magnitudes."""
        fm, fp, gm, gp, on_m, on_p = self._sides(z)
        contact = (on_m & self.acts_m) | (on_p & self.acts_p)
        return fm - fp, -(gm + gp), fm + fp, gp - gm, contact

    def potential(self, z):
        xm, xp = self._compressions(z)
        return (self.km * xm ** (self.pm + 1.0) / (self.pm + 1.0)
                + self.kp * xp ** (self.pp + 1.0) / (self.pp + 1.0))

    def in_contact(self, z):
        return ((z < self.edge_m) & self.acts_m) | ((z > self.edge_p) & self.acts_p)


class _Polynomial(_Group):
    """linear and cubic: N = -(k z + k3 z^3), in contact everywhere."""

    def __init__(self, indices, laws):
        super().__init__(indices)
        self.k = np.array([law.k_plus for law in laws], dtype=float)
        self.k3 = np.array([law.k3 for law in laws], dtype=float)
        self.cubic = bool(np.any(self.k3 != 0))

    def evaluate(self, z):
        if self.cubic:
            z2 = z * z
            stiff = self.k + self.k3 * z2
            slope = self.k + 3.0 * self.k3 * z2
        else:
            stiff = slope = self.k
        force = -stiff * z
        return force, -slope, np.abs(force), np.sign(z) * slope, np.ones(z.shape, dtype=bool)

    def elastic(self, z):
        if self.cubic:
            return -(self.k + self.k3 * (z * z)) * z
        return -self.k * z

    def stiffness(self, z):
        if self.cubic:
            z2 = z * z
            return -(self.k + self.k3 * z2) * z, -(self.k + 3.0 * self.k3 * z2)
        return -self.k * z, -self.k

    def potential(self, z):
        z2 = z * z
        return 0.5 * self.k * z2 + 0.25 * self.k3 * z2 * z2

    def in_contact(self, z):
        return np.ones(z.shape, dtype=bool)


class _Table(_Group):
    """Piecewise-linear tables, padded to a common length so one call handles them all."""

    def __init__(self, indices, laws):
        super().__init__(indices)
        width = max(len(law.table) for law in laws)
        rows = len(laws)
        self.z = np.full((rows, width), np.inf)  # +inf pads never count as "z_j <= z"
        f = np.zeros((rows, width))
        self.last = np.array([len(law.table) - 2 for law in laws], dtype=np.intp)  # last segment
        for i, law in enumerate(laws):
            points = np.array(law.table)
            self.z[i, :len(points)] = points[:, 0]
            f[i, :len(points)] = points[:, 1]
        self.rows = np.arange(rows)
        slope = np.zeros((rows, width))
        start = np.zeros((rows, width))  # integral of N from 0 to z_j
        for i, law in enumerate(laws):
            m = len(law.table)
            zi, fi = self.z[i, :m], f[i, :m]
            slope[i, :m - 1] = np.diff(fi) / np.diff(zi)
            slope[i, m - 1] = slope[i, m - 2]
            start[i, 1:m] = np.cumsum(0.5 * (fi[1:] + fi[:-1]) * np.diff(zi))
        self.f, self.slope, self.start = f, slope, start
        segment = self._segment(np.zeros(rows))
        start -= self._integral(np.zeros(rows), segment)[:, None]  # shift the origin to z = 0

    def _segment(self, z):
        count = np.count_nonzero(self.z <= z[:, None], axis=1)
        return np.minimum(np.maximum(count - 1, 0), self.last)

    def _integral(self, z, s):
        dz = z - self.z[self.rows, s]
        return (self.start[self.rows, s]
                + dz * (self.f[self.rows, s] + 0.5 * self.slope[self.rows, s] * dz))

    def evaluate(self, z):
        force, slope = self.stiffness(z)
        return force, slope, np.abs(force), np.sign(force) * slope, force != 0

    def elastic(self, z):
        return self.stiffness(z)[0]

    def stiffness(self, z):
        s = self._segment(z)
        slope = self.slope[self.rows, s]
        return self.f[self.rows, s] + slope * (z - self.z[self.rows, s]), slope

    def potential(self, z):
        return -self._integral(z, self._segment(z))

    def in_contact(self, z):
        return self.elastic(z) != 0


class _Friction(_Group):
    """friction: no force from z (its velocity part is ConstraintLaws'), always in contact."""

    def __init__(self, indices, laws):
        super().__init__(indices)

    def evaluate(self, z):
        zero = np.zeros(z.shape)
        return zero, zero, zero.copy(), zero.copy(), np.ones(z.shape, dtype=bool)

    def elastic(self, z):
        return np.zeros(z.shape)

    def stiffness(self, z):
        return np.zeros(z.shape), np.zeros(z.shape)

    def potential(self, z):
        return np.zeros(z.shape)

    def in_contact(self, z):
        return np.ones(z.shape, dtype=bool)


class ConstraintLaws:
    """The laws of all constraints, evaluated vectorized: one pass per family of kinds, with the
    parameters gathered into arrays once here. Arrays in and out have shape (n,)."""

    def __init__(self, laws: Sequence[Law]):
        self.laws = tuple(laws)
        for i, law in enumerate(self.laws):
            if not isinstance(law, Law):
                raise TypeError(f"constraint {i + 1}: expected a Law, got {type(law).__name__}")
        self.n = len(self.laws)
        families = {"two_sided": (_TwoSided, _TWO_SIDED), "polynomial": (_Polynomial, ("linear", "cubic")),
                    "table": (_Table, ("table",)), "friction": (_Friction, ("friction",))}
        self._groups = []
        for cls, kinds in families.values():
            members = [i for i, law in enumerate(self.laws) if law.kind in kinds]
            if members:
                self._groups.append(cls(members, [self.laws[i] for i in members]))
        self._single = len(self._groups) == 1 and isinstance(self._groups[0].at, slice) \
            and self._groups[0].at == slice(0, self.n)  # no gather/scatter needed
        self.c = np.array([law.c for law in self.laws], dtype=float)
        self.alpha = np.array([law.alpha for law in self.laws], dtype=float)
        self._damped = bool(np.any(self.c > 0) or np.any(self.alpha > 0))
        self._hunt_crossley = bool(np.any(self.alpha > 0))
        self._minus_c = -self.c
        # friction: N += -mu F_n tanh(v / v_reg), the one law whose force is nonlinear in v
        self._slip = np.array([law.mu * law.normal_force for law in self.laws], dtype=float)
        self._v_reg = np.array([law.v_reg if law.kind == "friction" else 1.0 for law in self.laws], dtype=float)
        self.friction = bool(np.any(self._slip > 0))

    def _friction(self, v):
        """(N, dN/dv) of the friction laws (zeros elsewhere)."""
        x = np.asarray(v, dtype=float) / self._v_reg
        th = np.tanh(x)
        return -self._slip * th, -(self._slip / self._v_reg) * (1.0 - th * th)

    def _gather(self, z, method, parts=1, dtype=float):
        """Call `method` of every group on its share of z; `parts` arrays, the last of `dtype`."""
        if self._single:
            return getattr(self._groups[0], method)(z)
        out = [np.empty(self.n) for _ in range(parts - 1)] + [np.empty(self.n, dtype=dtype)]
        for g in self._groups:
            values = getattr(g, method)(z[g.at])
            for target, part in zip(out, values if parts > 1 else (values,)):
                target[g.at] = part
        return out if parts > 1 else out[0]

    def _z(self, z):
        z = np.asarray(z, dtype=float)
        if z.shape != (self.n,):
            raise ValueError(f"expected {self.n} constraint displacements, got shape {z.shape}")
        return z

    def force_and_jacobian(self, z, v):
        """(N, dN/dz, dN/dv) in one pass; the Jacobians are diagonal, one entry per constraint."""
        z = self._z(z)
        if self.friction:
            force, dz, dv = self._without_friction(z, v)
            f, g = self._friction(v)
            return force + f, dz, dv + g
        return self._without_friction(z, v)

    def _without_friction(self, z, v):
        if not self._damped:
            force, dz = self._gather(z, "stiffness", parts=2)
            return force, dz, np.zeros(self.n)
        force, dz, mag, dmag, contact = self._gather(z, "evaluate", parts=5, dtype=bool)
        v = np.asarray(v, dtype=float)
        dv = self._minus_c * contact
        if self._hunt_crossley:
            a = self.alpha * contact
            dv -= a * mag
            dz = dz - a * dmag * v
        return force + dv * v, dz, dv  # the damping force is linear in v

    def force(self, z, v=None) -> np.ndarray:
        """N on the structure; v = None leaves out contact damping and friction."""
        z = self._z(z)
        if v is not None and self.friction:
            return self._without_friction_force(z, v) + self._friction(v)[0]
        return self._without_friction_force(z, v)

    def _without_friction_force(self, z, v):
        if v is None or not self._damped:
            return self._gather(z, "elastic")
        force, _, mag, _, contact = self._gather(z, "evaluate", parts=5, dtype=bool)
        c = self._minus_c * contact
        if self._hunt_crossley:
            c -= self.alpha * contact * mag
        return force + c * np.asarray(v, dtype=float)

    def jacobian(self, z, v=None) -> tuple:
        """(dN/dz, dN/dv), diagonal: one entry per constraint."""
        if v is None:
            v = np.zeros(self.n)
        return self.force_and_jacobian(z, v)[1:]

    def potential(self, z) -> np.ndarray:
        """U (J) with elastic N = -dU/dz, U = 0 at z = 0 for tables, U >= 0 for the other kinds."""
        return self._gather(self._z(z), "potential")

    def in_contact(self, z) -> np.ndarray:
        """Where the elastic force is nonzero: outside the deadband on a side with k > 0; always for
        linear and cubic; where the tabulated force is nonzero for tables."""
        return self._gather(self._z(z), "in_contact", dtype=bool)


# -- two-dimensional laws: a tube in a support of two directions (y, z) ----------------------------

LAWS_2D = ("circular", "flat_bar")
KEYS_2D = ("law", "clearance", "k", "mu", "v_reg", "damping", "c", "alpha", "angle")
DEFAULT_V_REG = 1e-3


@dataclass(frozen=True)
class CircularLaw:
    """A round hole of radial clearance c around a tube (two directions, y and z). u = (y, z) the
    total displacement, v its velocity, r = |u|, n = u / r, t = (-n_z, n_y), v_n = v.n, v_t = v.t,
    delta = r - c. In contact (delta > 0) the force on the tube is

        F = -(k delta + F_d) n - mu k delta tanh(v_t / v_reg) t

    with the contact damping F_d of the 1-D laws along the normal (linear: c v_n; Hunt-Crossley:
    alpha k delta v_n), and Coulomb friction regularized over the velocity scale v_reg (m/s),
    proportional to the elastic normal force k delta. Out of contact (r <= c) F = 0.

    kind = "flat_bar": two parallel flats at `angle` (degrees from y) around the tube, a gap c on each
    side along their normal e = (cos angle, sin angle): the same law with r = |u.e|, n = sign(u.e) e
    (a deadband along e, sliding along the flats). Any finite angle; it is kept modulo 360 deg (exactly,
    so that a large angle is the direction it names)."""

    clearance: float = 0.0
    k: float = 0.0
    mu: float = 0.0
    v_reg: float = DEFAULT_V_REG
    damping: str = "none"
    c: float = 0.0
    alpha: float = 0.0
    kind: str = "circular"
    angle: float = 0.0
    dimension = 2

    def __post_init__(self):
        if self.kind not in LAWS_2D:
            raise InputError(f"a 2-D law is one of {_quoted(LAWS_2D)}, got {self.kind!r}")
        if self.angle != 0 and self.kind != "flat_bar":
            raise InputError("angle applies only to a flat_bar law")
        for name in ("clearance", "k", "mu", "v_reg", "c", "alpha", "angle"):
            value = getattr(self, name)
            if not (is_number(value) and math.isfinite(value)):
                raise InputError(f"{name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        # the normal's direction modulo a turn, reduced exactly (fmod is exact): radians() of a large angle
        # rounds away its remainder (1e20 deg gave a normal at 108 deg instead of 280 deg)
        object.__setattr__(self, "angle", math.fmod(self.angle, 360.0))
        for name in ("clearance", "mu", "c", "alpha"):
            if getattr(self, name) < 0:
                raise InputError(f"{name} must be a non-negative number, got {getattr(self, name)!r}")
        _check_mu(self.mu)
        if not self.k > 0:
            raise InputError(f"k must be a positive number, got {self.k!r}")
        if not self.v_reg > 0:
            raise InputError(f"v_reg must be a positive number (m/s), got {self.v_reg!r}")
        if self.damping not in CONTACT_DAMPING:
            raise InputError(f"damping must be one of {_quoted(CONTACT_DAMPING)}, got {self.damping!r}")
        _check_contact_damping(self.damping, self.c, self.alpha)

    @property
    def clearance_minus(self) -> float:
        return self.clearance

    @property
    def clearance_plus(self) -> float:
        return self.clearance


def circular_from_dict(where: str, d: dict) -> CircularLaw:
    """A CircularLaw from a [[constraint]] table (without its position key)."""
    for key, value in d.items():
        if key not in KEYS_2D:
            takes = " (a key of the 1-D laws)" if key in KEYS else ""
            raise InputError(f"{where}: {key} does not apply to a circular law{takes} (keys: {', '.join(KEYS_2D)})")
        if key not in ("law", "damping") and not (is_number(value) and math.isfinite(value)):
            raise InputError(f"{where}: {key} must be a finite number, got {value!r}")
    for key, unit in (("clearance", "m, the radial clearance" if d.get("law") != "flat_bar" else "m, the gap to each "
                       "flat"), ("k", "N/m")):
        if key not in d:
            raise InputError(f"{where}: a {d.get('law', 'circular')} law needs {key} ({unit})")
    damping = d.get("damping", "none")
    if damping == "linear" and "c" not in d:
        raise InputError(f"{where}: damping = \"linear\" needs c (N s/m)")
    if damping == "hunt_crossley" and "alpha" not in d:
        raise InputError(f"{where}: damping = \"hunt_crossley\" needs alpha (s/m)")
    if "angle" in d and d.get("law") != "flat_bar":
        raise InputError(f"{where}: angle applies only to a flat_bar law")
    try:
        return CircularLaw(kind=d["law"], **{k: v for k, v in d.items() if k != "law"})
    except InputError as e:
        raise InputError(f"{where}: {e}") from None


class PlanarLaws:
    """The 2-D laws of all constraints, vectorized. Flat arrays of length 2 n in and out
    (constraint-major: y_j, z_j); Jacobians as (n, 2, 2) blocks. The same interface as
    ConstraintLaws where it makes sense (force, force_and_jacobian, potential, in_contact), plus
    `radial`: the per-support quantities the statistics read."""

    dimension = 2

    def __init__(self, laws):
        self.laws = tuple(laws)
        for i, law in enumerate(self.laws):
            if not isinstance(law, CircularLaw):
                raise TypeError(f"constraint {i + 1}: expected a CircularLaw, got {type(law).__name__}")
        self.n = len(self.laws)
        arr = lambda name: np.array([getattr(law, name) for law in self.laws], dtype=float)  # noqa: E731
        self.gap, self.k, self.mu, self.v_reg = arr("clearance"), arr("k"), arr("mu"), arr("v_reg")
        self.c, self.alpha = arr("c"), arr("alpha")
        self.flat = np.array([law.kind == "flat_bar" for law in self.laws], dtype=bool)
        self.any_flat = bool(self.flat.any())
        angle = np.radians(arr("angle"))
        self.e = np.column_stack((np.cos(angle), np.sin(angle)))   # the flats' normal

    def _split(self, z, v):
        z = np.asarray(z, dtype=float)
        if z.shape != (2 * self.n,):
            raise ValueError(f"expected {2 * self.n} constraint displacements (y, z each), got shape {z.shape}")
        u = z.reshape(self.n, 2)
        w = np.zeros_like(u) if v is None else np.asarray(v, dtype=float).reshape(self.n, 2)
        return u, w

    def _gap_coordinate(self, u):
        """(r, n, the curvature factor): r = |u| and n = u / |u| in a round hole, r = |u.e| and
        n = sign(u.e) e between flat bars; the factor 1 (round: dn/du = t t^T / r) or 0 (flat)."""
        r = np.hypot(u[..., 0], u[..., 1])
        safe = np.where(r > 0, r, 1.0)
        n = u / safe[..., None]
        n[r == 0] = (1.0, 0.0)
        if not self.any_flat:
            return r, n, 1.0
        along = np.einsum("...ja,ja->...j", u, self.e)
        flat = np.broadcast_to(self.flat, r.shape)
        r = np.where(flat, np.abs(along), r)
        side = np.where(along < 0, -1.0, 1.0)
        n = np.where(flat[..., None], side[..., None] * self.e, n)
        return r, n, (~self.flat).astype(float)

    def _kinematics(self, u, w):
        r, n, curved = self._gap_coordinate(u)
        contact = r > self.gap
        inv_r = curved / np.where(r > 0, r, 1.0)   # 1 / r of dn/du = t t^T / r; 0 between flat bars
        t = np.column_stack((-n[:, 1], n[:, 0]))
        vn, vt = np.einsum("ja,ja->j", w, n), np.einsum("ja,ja->j", w, t)
        delta = np.where(contact, r - self.gap, 0.0)
        return r, inv_r, contact, n, t, vn, vt, delta

    def force(self, z, v=None) -> np.ndarray:
        """F on the structure (flat, 2 n); v = None leaves out damping and friction."""
        u, w = self._split(z, v)
        r, _, contact, n, t, vn, vt, delta = self._kinematics(u, w)
        normal = self.k * delta
        if v is not None:
            normal = normal + contact * (self.c * vn + self.alpha * self.k * delta * vn)
            tangent = self.mu * self.k * delta * np.tanh(vt / self.v_reg)
        else:
            tangent = np.zeros(self.n)
        return (-(normal[:, None] * n) - tangent[:, None] * t).ravel()

    def force_and_jacobian(self, z, v):
        """(F flat (2 n,), dF/du (n, 2, 2), dF/dv (n, 2, 2)): exact derivatives (docs/method.md)."""
        u, w = self._split(z, v)
        r, inv_r, contact, n, t, vn, vt, delta = self._kinematics(u, w)
        k, on = self.k, contact.astype(float)
        nn, tt = np.einsum("ja,jb->jab", n, n), np.einsum("ja,jb->jab", t, t)
        nt, tn = np.einsum("ja,jb->jab", n, t), np.einsum("ja,jb->jab", t, n)
        inv_r = on * inv_r
        s = lambda a: a[:, None, None]  # noqa: E731
        # elastic: -k delta n
        dz = -s(k * on) * nn - s(k * delta * inv_r) * tt
        dv = np.zeros_like(dz)
        # damping along the normal: -(c + alpha k delta) v_n n
        cd = on * (self.c + self.alpha * k * delta)
        dz -= s(cd * vt * inv_r) * nt + s(cd * vn * inv_r) * tt + s(on * self.alpha * k * vn) * nn
        dv -= s(cd) * nn
        # friction: -mu k delta tanh(v_t / v_reg) t
        tau = np.tanh(vt / self.v_reg)
        dtau = (1.0 - tau * tau) / self.v_reg
        mk = self.mu * k
        dz -= s(mk * on * tau) * tn - s(mk * delta * dtau * vn * inv_r) * tt - s(mk * delta * tau * inv_r) * nt
        dv -= s(mk * delta * dtau) * tt
        normal = k * delta + cd * vn
        force = -(normal[:, None] * n) - (mk * delta * tau)[:, None] * t
        return force.ravel(), dz, dv

    def potential(self, z) -> np.ndarray:
        u, _ = self._split(z, None)
        delta = np.maximum(self._gap_coordinate(u)[0] - self.gap, 0.0)
        return 0.5 * self.k * delta * delta

    def in_contact(self, z) -> np.ndarray:
        """(n,) |u| > clearance (flat bars: |u.e| > clearance)."""
        u, _ = self._split(z, None)
        return self._gap_coordinate(u)[0] > self.gap

    def radial(self, z, v, force):
        """Per support, from flat (k, 2 n) arrays: |u|, the normal velocity v.n, |F|, the normal
        force magnitude |F.n|, the sliding speed |v.t| and contact (|u| > c), each (k, n)."""
        k = np.asarray(z).shape[0]
        u, w, f = (np.asarray(a, dtype=float).reshape(k, self.n, 2) for a in (z, v, force))
        gap, n, _ = self._gap_coordinate(u)
        r = np.hypot(u[..., 0], u[..., 1])
        vn = np.einsum("kja,kja->kj", w, n)
        vt = n[..., 0] * w[..., 1] - n[..., 1] * w[..., 0]
        fn = np.abs(np.einsum("kja,kja->kj", f, n))
        return r, vn, np.hypot(f[..., 0], f[..., 1]), fn, np.abs(vt), gap > self.gap
