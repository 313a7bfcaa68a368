"""Scene files: what to simulate, in TOML with SI units, validated once here.

Sections and keys (the contract; unknown sections or keys are errors naming them):

    [structure]   kind = "beam" | "matrices"
                  beam:     length, elements, E, I, A, rho, left, right, supports = [x, ...]
                  matrices: stiffness, mass, damping (optional C), influence, base_mass_load (files)
    [excitation]  kind = "none" | "base" | "force" | "random", amplitude (m or N), frequency_hz,
                  end = "left" | "right" (base), x (force on a beam) or dof (force on matrices);
                  random: a distributed force per unit length on a beam, band-limited with a flat
                  one-sided PSD psd ((N/m)^2/Hz) over band = [f_low, f_high] Hz, from seed (an
                  integer: the same seed gives the same history), components (cosines), over
                  span = [x0, x1] (default the whole beam), fully correlated along the span
    [[constraint]] x (beam) or dof (matrices), law, and the law's parameters (see laws.py)
    [basis]       modes (a count) or max_frequency_hz; enrichment = "dbf" (the method, default) |
                  "static" (static attachment modes K^-1 g_j instead of DBFs) | "none" (modes
                  only), the last two as comparators; dbf_stiffness = "auto" | a number (N/m);
                  dbf_derivative = "analytic" | "central" (both for "dbf" only); groups (0: automatic);
                  cache = a directory for cached bases (default ~/.cache/dbf_hpc) or "off"
    [damping]     zeta (one ratio or a list), or rayleigh_alpha, rayleigh_beta
    [integrator]  t_end, dt, scheme, adaptive, rtol, atol, contact = "implicit" | "explicit"
    [initial]     mode, amplitude (an initial displacement in a reference mode, m)
    [output]      file, sample_dt, probes = [x, ...], snapshots (count), checkpoint_dt (simulated
                  seconds between checkpoints; default t_end / 10)

Relative paths in the scene (matrix files, output) are relative to the scene file's folder.
"""
from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field
from typing import Optional

from .damping import Damping
from .errors import InputError
from .laws import Law, law_from_dict
from .structure import BOUNDARIES, Beam

NUMBER = (int, float)

# section -> key -> (accepted types, default; REQUIRED if it must be given)
REQUIRED = object()
SCHEMA = {
    "structure": {
        "kind": (str, "beam"), "length": (NUMBER, None), "elements": (int, 100), "E": (NUMBER, None),
        "I": (NUMBER, None), "A": (NUMBER, None), "rho": (NUMBER, None), "left": (str, "pinned"),
        "right": (str, "pinned"), "supports": (list, []), "stiffness": (str, None), "mass": (str, None),
        "damping": (str, None), "influence": (str, None), "base_mass_load": (str, None),
    },
    "excitation": {
        "kind": (str, "none"), "amplitude": (NUMBER, 0.0), "frequency_hz": (NUMBER, 0.0),
        "end": (str, "left"), "x": (NUMBER, None), "dof": (int, None),
        "psd": (NUMBER, 0.0), "band": (list, []), "seed": (int, 1), "components": (int, 256), "span": (list, []),
    },
    "basis": {
        "modes": (int, None), "max_frequency_hz": (NUMBER, None), "dbf_stiffness": ((str, *NUMBER), "auto"),
        "dbf_derivative": (str, "analytic"), "groups": (int, 0), "cache": (str, "~/.cache/dbf_hpc"),
        "enrichment": (str, "dbf"),
    },
    "damping": {"zeta": ((*NUMBER, list), 0.0), "rayleigh_alpha": (NUMBER, 0.0), "rayleigh_beta": (NUMBER, 0.0)},
    "integrator": {
        "t_end": (NUMBER, 1.0), "dt": (NUMBER, 1e-4), "scheme": ((str, int), "3"), "adaptive": (bool, True),
        "rtol": (NUMBER, 1e-6), "atol": (NUMBER, 1e-9), "contact": (str, "implicit"),
    },
    "initial": {"mode": (int, 1), "amplitude": (NUMBER, 0.0)},
    "output": {
        "file": (str, None), "sample_dt": (NUMBER, None), "probes": (list, []), "snapshots": (int, 0),
        "checkpoint_dt": (NUMBER, None),
    },
}
CONSTRAINT_POSITION = {"x": NUMBER, "dof": int}


@dataclass(frozen=True)
class Constraint:
    """One discrete constraint: where it acts (x on a beam, dof of an external model) and its law."""

    x: Optional[float]
    dof: Optional[int]
    law: Law

    @property
    def label(self) -> str:
        return f"x = {self.x:g} m" if self.x is not None else f"dof {self.dof}"


@dataclass(frozen=True)
class Scene:
    """A validated scene. `sections` holds every section with defaults filled in."""

    path: str
    text: str
    sections: dict
    constraints: tuple = field(default_factory=tuple)

    def __getitem__(self, section: str) -> dict:
        return self.sections[section]

    @property
    def is_beam(self) -> bool:
        return self["structure"]["kind"] == "beam"

    def beam(self) -> Beam:
        s = self["structure"]
        return Beam(length=float(s["length"]), E=float(s["E"]), I=float(s["I"]), A=float(s["A"]),
                    rho=float(s["rho"]), elements=s["elements"], left=s["left"], right=s["right"],
                    supports=tuple(float(x) for x in s["supports"]))

    def damping(self) -> Damping:
        d = self["damping"]
        zeta = tuple(d["zeta"]) if isinstance(d["zeta"], list) else float(d["zeta"])
        return Damping(zeta=zeta, rayleigh_alpha=float(d["rayleigh_alpha"]),
                       rayleigh_beta=float(d["rayleigh_beta"]))

    def basis_settings(self):
        from .basis import BasisSettings

        b = self["basis"]
        return BasisSettings(modes=b["modes"], max_frequency_hz=b["max_frequency_hz"],
                             dbf_stiffness=b["dbf_stiffness"], dbf_derivative=b["dbf_derivative"],
                             groups=b["groups"], enrichment=b["enrichment"])

    def cache_dir(self):
        """The basis cache directory, or None when the scene turns caching off."""
        cache = self["basis"]["cache"]
        return None if cache == "off" else self.resolve(os.path.expanduser(cache))

    def resolve(self, path: str) -> str:
        """A path from the scene, relative to the scene file's folder."""
        return path if os.path.isabs(path) else os.path.join(os.path.dirname(os.path.abspath(self.path)), path)


def parse_override(text: str) -> tuple[str, str, object]:
    """'section.key=value' (value in TOML syntax; a bare word is a string) -> (section, key, value)."""
    name, sep, raw = text.partition("=")
    section, dot, key = name.strip().partition(".")
    if not sep or not dot or not section or not key:
        raise InputError(f"--set {text!r}: expected section.key=value")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return section, key, value


def load_scene(path: str, overrides=()) -> Scene:
    """Read and validate a scene file; `overrides` are 'section.key=value' strings (--set)."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise InputError(f"cannot read scene {path!r}: {e.strerror}") from None
    try:
        text = raw.decode("utf-8")
        data = tomllib.loads(text)
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise InputError(f"{path}: not valid TOML: {e}") from None
    for item in overrides:
        section, key, value = parse_override(item)
        if section == "constraint":
            for c in data.get("constraint", []):
                c[key] = value
        else:
            data.setdefault(section, {})[key] = value
    return validate(data, path, text)


def _check_type(where: str, key: str, value, types) -> None:
    types = types if isinstance(types, tuple) else (types,)
    if isinstance(value, bool) and bool not in types:
        raise InputError(f"{where}: {key} must be {_type_name(types)}, got {value!r}")
    if not isinstance(value, types):
        raise InputError(f"{where}: {key} must be {_type_name(types)}, got {value!r}")


def _type_name(types) -> str:
    names = {int: "an integer", float: "a number", str: "a string", list: "a list", bool: "true or false"}
    if set(types) >= {int, float}:
        types = tuple(t for t in types if t is not int)
    return " or ".join(names[t] for t in types)


def validate(data: dict, path: str = "<scene>", text: str = "") -> Scene:
    """Check every section and key of a parsed scene; fill in defaults."""
    for name in data:
        if name not in SCHEMA and name != "constraint":
            raise InputError(f"{path}: unknown section [{name}]")
    sections = {}
    for name, keys in SCHEMA.items():
        given = data.get(name, {})
        if not isinstance(given, dict):
            raise InputError(f"{path}: [{name}] must be a table")
        for key, value in given.items():
            if key not in keys:
                raise InputError(f"{path}: unknown key '{key}' in [{name}]")
            _check_type(f"{path}: [{name}]", key, value, keys[key][0])
        sections[name] = {key: given.get(key, default) for key, (_, default) in keys.items()}

    where = f"{path}: [structure]"
    s = sections["structure"]
    if s["kind"] == "beam":
        for key in ("length", "E", "I", "A", "rho"):
            if s[key] is None:
                raise InputError(f"{where}: {key} is required for a beam")
            if not s[key] > 0:
                raise InputError(f"{where}: {key} must be positive, got {s[key]!r}")
        for end in ("left", "right"):
            if s[end] not in BOUNDARIES:
                raise InputError(f"{where}: {end} must be one of {', '.join(BOUNDARIES)}, got {s[end]!r}")
        if s["elements"] < 1:
            raise InputError(f"{where}: elements must be at least 1, got {s['elements']}")
    elif s["kind"] == "matrices":
        for key in ("stiffness", "mass"):
            if s[key] is None:
                raise InputError(f"{where}: {key} (a matrix file) is required for kind = \"matrices\"")
    else:
        raise InputError(f"{where}: kind must be \"beam\" or \"matrices\", got {s['kind']!r}")
    beam = s["kind"] == "beam"
    position_key = "x" if beam else "dof"

    def check_position(where, value):
        if beam:
            if not (isinstance(value, NUMBER) and not isinstance(value, bool) and 0 <= value <= s["length"]):
                raise InputError(f"{where}: x = {value!r} is not on the beam [0, {s['length']}] m")
        elif not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            raise InputError(f"{where}: dof must be a non-negative integer, got {value!r}")

    for x in s["supports"]:
        check_position(f"{where} supports", x)

    constraints = []
    raw_constraints = data.get("constraint", [])
    if not isinstance(raw_constraints, list):
        raise InputError(f"{path}: constraints are written [[constraint]] (an array of tables)")
    for i, c in enumerate(raw_constraints):
        cwhere = f"{path}: [[constraint]] {i + 1}"
        if not isinstance(c, dict):
            raise InputError(f"{cwhere} must be a table")
        other = "dof" if beam else "x"
        if other in c:
            raise InputError(f"{cwhere}: use {position_key}, not {other}, on a {s['kind']} structure")
        if position_key not in c:
            raise InputError(f"{cwhere}: {position_key} is required")
        check_position(cwhere, c[position_key])
        law = law_from_dict(i + 1, {k: v for k, v in c.items() if k != position_key})
        constraints.append(Constraint(x=float(c["x"]) if beam else None,
                                      dof=None if beam else c["dof"], law=law))
    seen = {}
    for i, c in enumerate(constraints):
        key = round(c.x / s["length"], 9) if beam else c.dof
        if key in seen:
            raise InputError(f"{path}: constraints {seen[key] + 1} and {i + 1} are both at {c.label}; "
                             f"remove one or merge their laws")
        seen[key] = i

    e, where = sections["excitation"], f"{path}: [excitation]"
    if e["kind"] not in ("none", "base", "force", "random"):
        raise InputError(f"{where}: kind must be \"none\", \"base\", \"force\" or \"random\", got {e['kind']!r}")
    if e["kind"] == "random":
        if not beam:
            raise InputError(f"{where}: random forcing is distributed along a beam; not available for matrices")
        band = e["band"]
        if not (len(band) == 2 and all(isinstance(b, NUMBER) for b in band) and 0 <= band[0] < band[1]):
            raise InputError(f"{where}: band must be [f_low, f_high] in Hz with 0 <= f_low < f_high, got {band!r}")
        if not e["psd"] > 0:
            raise InputError(f"{where}: psd must be positive ((N/m)^2/Hz), got {e['psd']!r}")
        if e["components"] < 1:
            raise InputError(f"{where}: components must be at least 1, got {e['components']}")
        span = e["span"] or [0.0, s["length"]]
        if not (len(span) == 2 and 0 <= span[0] < span[1] <= s["length"]):
            raise InputError(f"{where}: span must be [x0, x1] within the beam, got {e['span']!r}")
        e["span"] = [float(v) for v in span]
    elif e["kind"] != "none":
        if not e["frequency_hz"] > 0:
            raise InputError(f"{where}: frequency_hz must be positive, got {e['frequency_hz']!r}")
        if e["end"] not in ("left", "right"):
            raise InputError(f"{where}: end must be \"left\" or \"right\", got {e['end']!r}")
        if e["kind"] == "force":
            if e[position_key] is None:
                raise InputError(f"{where}: a force needs its position ({position_key})")
            check_position(where, e[position_key])
        if e["kind"] == "base" and not beam and s["influence"] is None:
            raise InputError(f"{where}: base excitation of a matrices structure needs [structure] influence")

    b, where = sections["basis"], f"{path}: [basis]"
    if b["modes"] is not None and b["max_frequency_hz"] is not None:
        raise InputError(f"{where}: give modes or max_frequency_hz, not both")
    if b["modes"] is None and b["max_frequency_hz"] is None:
        b["modes"] = 6
    if b["modes"] is not None and b["modes"] < 1:
        raise InputError(f"{where}: modes must be at least 1, got {b['modes']}")
    if b["max_frequency_hz"] is not None and not b["max_frequency_hz"] > 0:
        raise InputError(f"{where}: max_frequency_hz must be positive, got {b['max_frequency_hz']}")
    k = b["dbf_stiffness"]
    if not (k == "auto" or (isinstance(k, NUMBER) and k > 0)):
        raise InputError(f"{where}: dbf_stiffness must be \"auto\" or a positive number (N/m), got {k!r}")
    if b["dbf_derivative"] not in ("analytic", "central"):
        raise InputError(f"{where}: dbf_derivative must be \"analytic\" or \"central\", got {b['dbf_derivative']!r}")
    if b["groups"] < 0:
        raise InputError(f"{where}: groups must be 0 (automatic) or a positive count, got {b['groups']}")
    from .basis import ENRICHMENTS  # imported here, as in Scene.basis_settings

    if b["enrichment"] not in ENRICHMENTS:
        accepted = ", ".join(f'"{e}"' for e in ENRICHMENTS)
        raise InputError(f"{where}: enrichment must be one of {accepted}, got {b['enrichment']!r}")

    i, where = sections["integrator"], f"{path}: [integrator]"
    i["scheme"] = str(i["scheme"]).lower()  # --set integrator.scheme=3 arrives as an integer
    for key in ("t_end", "dt", "rtol", "atol"):
        if not i[key] > 0:
            raise InputError(f"{where}: {key} must be positive, got {i[key]!r}")
    if i["contact"] not in ("implicit", "explicit"):
        raise InputError(f"{where}: contact must be \"implicit\" or \"explicit\", got {i['contact']!r}")

    o, where = sections["output"], f"{path}: [output]"
    for x in o["probes"]:
        check_position(f"{where} probes", x)
    if o["sample_dt"] is not None and not o["sample_dt"] > 0:
        raise InputError(f"{where}: sample_dt must be positive, got {o['sample_dt']!r}")
    if o["checkpoint_dt"] is not None and not o["checkpoint_dt"] > 0:
        raise InputError(f"{where}: checkpoint_dt must be positive, got {o['checkpoint_dt']!r}")
    if o["snapshots"] < 0:
        raise InputError(f"{where}: snapshots must be a count >= 0, got {o['snapshots']}")
    if sections["initial"]["mode"] < 1:
        raise InputError(f"{path}: [initial] mode counts from 1, got {sections['initial']['mode']}")

    scene = Scene(path=path, text=text, sections=sections, constraints=tuple(constraints))
    scene.damping()  # validates the damping section
    if beam:
        scene.beam()
    return scene
