"""Scene files: what to simulate, in TOML with SI units, validated once here and translated into
the descriptions the core takes (structure, constraints, excitation, damping, basis and integrator
settings, initial state, output). Nothing below this module reads a scene.

The sections and keys are the contract of schema.py (rendered as docs/scene.md); an unknown
section or key is an error that lists the valid ones. Relative paths in a scene (matrix files,
output) are relative to the scene file's folder.

Reading and validating are local to the calling rank (load_scene); the commands use
load_scene_collective, which reads the file on rank 0 and broadcasts it. Building the models a
scene describes (full_order_model) is collective.
"""
from __future__ import annotations

import dataclasses
import difflib
import errno
import math
import os
import tomllib
from dataclasses import dataclass, field
from typing import Optional

from .basis import DBF_SOLVERS, ENRICHMENTS, BasisSettings
from .constraints import Constraint, check_wear_coefficient
from .damping import Damping
from .accuracy import EstimateSettings
from .errors import InputError, read_regular_file
from .excitation import BaseMotion, NoExcitation, PointForce, RandomForce, Turbulence
from .fom import DAMPING_TWICE, FullOrderModel, InitialState, check_displacement, check_stops_within_reach
from .laws import KEYS as LAW_KEYS
from .laws import KEYS_2D, LAWS_2D, default_exponent, law_from_dict
from .matrices import MatrixFiles
from .schema import CONSTRAINT, NUMBER, SECTIONS, valid_keys
from .stats import BATCHES
from .structure import BOUNDARIES, POINT_TOL, Beam
from .timestepping import CALLBACKS, IntegratorSettings

SCHEMA = {section: {name: (key.types, key.default) for name, key in keys.items()}
          for section, (_, keys) in SECTIONS.items()}


# Keys that change no number of a result, only how outputs draw it: left out of run and sweep
# identities (Scene.result_sections, file_digests)
DISPLAY_ONLY = {"structure": ("cells", "cell_type")}

# The default checkpoints (every t_end / 10 of simulated time) are written only once this much wall
# time (s) has passed since the run began or since the last one: a checkpoint costs 10-20 ms (some
# 30 HDF5 datasets and an fsync), and a short run, a parameter study's case, spent more on its nine
# checkpoints than on its integration (measured: 0.12 s against 0.02 s on the paper's beam over
# 0.05 s). A run killed loses at most this much more; a checkpoint_dt given is kept exactly.
CHECKPOINT_WALL = 1.0


@dataclass(frozen=True)
class OutputSettings:
    """[output]: the file (resolved against the scene's folder), the sample interval (s), the
    probes (x in m on a beam, DOFs of a matrix model), the snapshot count, the simulated time
    between checkpoints (s) and the least wall time between them (s): 0 when [output] checkpoint_dt
    is given, CHECKPOINT_WALL for its default."""

    file: Optional[str]
    sample_dt: float
    probes: tuple
    snapshots: int
    checkpoint_dt: float
    checkpoint_wall: float = 0.0


@dataclass(frozen=True)
class Scene:
    """A validated scene. `sections` holds every section with defaults filled in."""

    path: str
    text: str
    sections: dict
    constraints: tuple = field(default_factory=tuple)
    overrides: tuple = ()      # the --set items applied to the file's text
    given: frozenset = frozenset()   # (section, key) of every key the file or a --set wrote, defaults excluded

    def effective(self) -> dict:
        """Every value the run uses (the file, the --set items and the defaults), JSON-ready: what an
        output records next to the file's own text."""
        return {**self.sections, "constraint": [dataclasses.asdict(c) for c in self.constraints],
                "overrides": list(self.overrides)}

    def __getitem__(self, section: str) -> dict:
        return self.sections[section]

    def with_values(self, section: str, **values) -> "Scene":
        """The same scene with some values of one section replaced (what the tolerance mode picked)."""
        sections = {name: dict(keys) for name, keys in self.sections.items()}
        sections[section].update(values)
        return dataclasses.replace(self, sections=sections)

    @property
    def is_beam(self) -> bool:
        return self["structure"]["kind"] == "beam"

    def beam(self) -> Beam:
        s = self["structure"]
        return Beam(length=float(s["length"]), E=float(s["E"]), I=float(s["I"]), A=float(s["A"]),
                    rho=float(s["rho"]), elements=s["elements"], left=s["left"], right=s["right"],
                    supports=tuple(float(x) for x in s["supports"]), planes=s["planes"],
                    axial_speed=float(s["axial_speed"]), tension=float(s["tension"]),
                    transported_mass=None if s["transported_mass"] is None else float(s["transported_mass"]))

    def structure(self):
        """The structure: a Beam, or the MatrixFiles with paths resolved against the scene's folder."""
        if self.is_beam:
            return self.beam()
        s = self["structure"]
        return MatrixFiles(**{key: self.resolve(s[key]) if s[key] else None
                              for key in ("stiffness", "mass", "damping", "influence", "base_mass_load", "nodes",
                                          "dofs", "gyroscopic", "cells")}, cell_type=s["cell_type"] or None)

    def cells_file(self) -> Optional[str]:
        """[structure] cells resolved against the scene's folder, or None."""
        cells = None if self.is_beam else self["structure"]["cells"]
        return self.resolve(cells) if cells else None

    def result_sections(self) -> dict:
        """`sections` without the keys that change no number of a result (DISPLAY_ONLY: the cells
        ParaView draws): what run and sweep identities hash, so a cells file added or changed keeps a
        checkpoint resumable and a sweep's records, and the identities of scenes without it are
        what they were before the key existed."""
        return {name: {k: v for k, v in keys.items() if k not in DISPLAY_ONLY.get(name, ())}
                for name, keys in self.sections.items()}

    def excitation(self):
        """The excitation description (excitation.py)."""
        e = self["excitation"]
        d = e["direction"] or [1.0, 0.0]
        direction = (float(d[0]) / math.hypot(*d), float(d[1]) / math.hypot(*d))
        if e["kind"] == "base":
            return BaseMotion(float(e["amplitude"]), float(e["frequency_hz"]), e["end"], direction=direction)
        if e["kind"] == "force":
            return PointForce(float(e["amplitude"]), float(e["frequency_hz"]), x=e["x"], dof=e["dof"],
                              direction=direction)
        if e["kind"] == "random":
            return RandomForce(float(e["psd"]), tuple(e["band"]), e["seed"], e["components"], tuple(e["span"]),
                               direction=direction)
        if e["kind"] == "turbulence":
            return Turbulence(float(e["psd"]), tuple(e["band"]), float(e["correlation_length"]), e["seed"],
                              e["components"], tuple(e["span"]), e["spectrum"],
                              float(e["corner_hz"] or 0.0), float(e["slope"] or 0.0))
        return NoExcitation()

    def damping(self) -> Damping:
        d = self["damping"]
        zeta = tuple(d["zeta"]) if isinstance(d["zeta"], list) else float(d["zeta"])
        return Damping(zeta=zeta, rayleigh_alpha=float(d["rayleigh_alpha"]),
                       rayleigh_beta=float(d["rayleigh_beta"]))

    def initial(self) -> InitialState:
        i = self["initial"]

        def unit(d, default):
            d = d or default
            return (float(d[0]) / math.hypot(*d), float(d[1]) / math.hypot(*d))

        return InitialState(mode=i["mode"], amplitude=float(i["amplitude"]), direction=unit(i["direction"], [1.0, 0.0]),
                            velocity=float(i["velocity"]), velocity_direction=unit(i["velocity_direction"], [0.0, 1.0]))

    def basis_settings(self):
        b = self["basis"]
        return BasisSettings(modes=b["modes"], max_frequency_hz=b["max_frequency_hz"],
                             dbf_stiffness=b["dbf_stiffness"], dbf_derivative=b["dbf_derivative"],
                             groups=b["groups"], enrichment=b["enrichment"],
                             dbf_solver=b["dbf_solver"], gyroscopic_form=b["gyroscopic_form"])

    def estimate_settings(self) -> EstimateSettings:
        b = self["basis"]
        return EstimateSettings(enabled=b["estimate"], window=b["estimate_window"], tolerance=b["tolerance"],
                                statistics_window=b["estimate_statistics_window"])

    def integrator_settings(self) -> IntegratorSettings:
        i = self["integrator"]
        return IntegratorSettings(t_end=float(i["t_end"]), dt=float(i["dt"]), scheme=i["scheme"],
                                  adaptive=i["adaptive"], rtol=float(i["rtol"]), atol=float(i["atol"]),
                                  contact=i["contact"], sample_dt=float(self.output().sample_dt),
                                  callbacks=i["callbacks"])

    def fastest_forcing_hz(self) -> float:
        """The highest frequency the excitation contains (0 for free vibration)."""
        e = self["excitation"]
        if e["kind"] in ("random", "turbulence"):
            return float(e["band"][1])
        return float(e["frequency_hz"]) if e["kind"] != "none" else 0.0

    def output(self) -> OutputSettings:
        o, t_end = self["output"], float(self["integrator"]["t_end"])
        return OutputSettings(file=self.resolve(o["file"]) if o["file"] else None,
                              sample_dt=float(o["sample_dt"] or t_end / 10000), probes=tuple(o["probes"]),
                              snapshots=o["snapshots"], checkpoint_dt=float(o["checkpoint_dt"] or t_end / 10),
                              checkpoint_wall=0.0 if o["checkpoint_dt"] else CHECKPOINT_WALL)

    def full_order_model(self, comm=None) -> FullOrderModel:
        """The full-order model this scene describes, assembled on comm (default COMM_WORLD).
        Collective."""
        return FullOrderModel.build(self.structure(), self.constraints, self.excitation(), self.damping(),
                                    self.output().probes, self.initial(), comm)

    def inputs(self) -> list:
        """(what, path) of every file this scene reads: the scene itself and its matrix files."""
        files = [("scene", os.path.abspath(self.path))]
        if not self.is_beam:
            s = self["structure"]
            files += [(f"{key} file", self.resolve(s[key])) for key in
                      ("stiffness", "mass", "damping", "influence", "base_mass_load", "nodes", "dofs", "gyroscopic",
                       "cells") if s[key]]
        return files

    def file_digests(self, comm) -> dict:
        """{path: sha256 of its bytes} of every file this scene reads besides itself (its matrix files,
        damping, influence, node map ...): a result depends on their contents. Not the cells file,
        which only draws the field (result_sections). Collective."""
        from .matrices import file_digest

        return {path: file_digest(path, comm, what.removesuffix(" file")) for what, path in self.inputs()
                if what not in ("scene", "cells file")}

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
        bare = name.strip()
        owners = [f"{owner}.{bare}" for owner, keys in SCHEMA.items() if bare in keys]
        owners += [f"constraint.{bare}"] if sep and not dot and bare in CONSTRAINT[1] else []
        if sep and not dot and owners:   # new-user pass: --set t_end=1 named no section to put it in
            raise InputError(f"--set {text!r}: expected section.key=value, here "
                             f"{' or '.join(f'--set {o}={raw.strip()}' for o in owners)}")
        raise InputError(f"--set {text!r}: expected section.key=value")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return section, key, value


def read_scene_bytes(path: str) -> bytes:
    """The scene file's bytes, or an InputError naming why they cannot be read. Red team:
    load_scene(None) was a TypeError, and load_scene(3) read file descriptor 3 and closed it."""
    name = os.fspath(path) if isinstance(path, (str, os.PathLike)) else None
    if not isinstance(name, str) or not name:
        raise InputError(f"load_scene: give the path of a scene file (a str), got {path!r}")
    try:   # a named pipe is refused, not waited on (red team: `dbf-hpc run FIFO` hung)
        return read_regular_file(name)
    except OSError as e:
        raise InputError(f"cannot read scene {path!r}: {e.strerror}{relative_to_cwd(name, e)}") from None


def relative_to_cwd(name: str, e: OSError) -> str:
    """Where a relative path that does not exist was looked for (new-user pass: `dbf-hpc run
    jobs/paper_beam.toml` from inside jobs/ said only "No such file or directory")."""
    if e.errno != errno.ENOENT or os.path.isabs(name):
        return ""
    try:
        return f" (relative to the current directory {os.getcwd()})"
    except OSError:   # the current directory was removed
        return ""


def load_scene(path: str, overrides=(), raw: bytes | None = None) -> Scene:
    """Read and validate a scene file; `overrides` are 'section.key=value' strings (--set). `raw`:
    the file's bytes, already read (load_scene_collective)."""
    raw = read_scene_bytes(path) if raw is None else raw
    try:
        text = raw.decode("utf-8")
        data = tomllib.loads(text)
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise InputError(f"{path}: not valid TOML: {e}") from None
    given, given_basis = {}, set()
    for item in overrides:
        section, key, value = parse_override(item)
        # what the file wrote where a table (or an array of tables) goes is refused as validate() would
        # refuse it: red team, [[basis]] or [constraint] with a --set on it was an internal TypeError
        if section == "constraint":
            constraints = data.get("constraint", [])
            if not isinstance(constraints, list):
                raise InputError(f"{path}: constraints are written [[constraint]] (an array of tables)")
            for i, c in enumerate(constraints):
                if not isinstance(c, dict):
                    raise InputError(f"{path}: [[constraint]] {i + 1} must be a table")
            _override_constraints(constraints, key, value, item, given)
            continue
        target = data.setdefault(section, {})
        if not isinstance(target, dict):
            raise InputError(f"{path}: [{section}] must be a table")
        if section == "basis" and isinstance(target, dict):
            # the two ways to choose the modes: one given on the command line replaces the scene's other
            other = {"modes": "max_frequency_hz", "max_frequency_hz": "modes"}.get(key)
            if other and other not in given_basis:
                target.pop(other, None)
            given_basis.add(key)
        target[key] = value
    for i, keys in given.items():
        _check_one_unit_of_k(data["constraint"][i], i, keys)
    return dataclasses.replace(validate(data, path, text), overrides=tuple(overrides))


def load_scene_collective(path: str, overrides=(), comm=None) -> Scene:
    """load_scene with the file read by rank 0 of `comm` (default COMM_WORLD) and its bytes
    broadcast: every rank validates the same scene, also when the file is edited while the job
    starts or is not readable on every node. Collective."""
    from .errors import decided_on_rank0
    from .petsctools import petsc_comm

    return load_scene(path, overrides, raw=decided_on_rank0(petsc_comm(comm, "load_scene_collective"),
                                                            read_scene_bytes, path))


def _check_one_unit_of_k(c: dict, index: int, given: set) -> None:
    """A k set on the command line for both sides of a law whose sides have different exponents would
    carry two units (N/m^p on each side): refused (Eq. 42's 0.1 N/m^3 became 1e6 N/m^3 silently)."""
    if "k" not in given or "k" not in c or c.get("law") in LAWS_2D:
        return
    # a side without an exponent has its kind's (1; hertz 1.5): Eq. 42 without exponent_plus = 1 was let through
    p = [c.get(side, c.get("exponent", default_exponent(c.get("law", "deadband")))) for side in TWO_SIDED["exponent"]]
    if all(isinstance(e, (int, float)) and not isinstance(e, bool) for e in p) and p[0] != p[1]:
        unit = ["N/m" if e == 1 else f"N/m^{e:g}" for e in p]
        raise InputError(f"--set constraint.k: constraint {index + 1}'s sides have the exponents {p[0]:g} and "
                         f"{p[1]:g}, so one k would be in {unit[0]} below and {unit[1]} above; set k_minus and "
                         f"k_plus (or one exponent for both)")


# A value on both sides and its two one-sided keys (a 1-D law takes one or the other)
TWO_SIDED = {"k": ("k_minus", "k_plus"), "clearance": ("clearance_minus", "clearance_plus"),
             "exponent": ("exponent_minus", "exponent_plus")}


def _set_constraint_key(c: dict, key: str, value, given: set, item: str) -> None:
    """An override of one constraint's key (`given`: the keys earlier overrides set on it): k
    (clearance, exponent) replaces a scene's k_minus and k_plus; one side over a scene's k keeps k
    on the other side (1-D laws; a 2-D law has no sides). A side after k refines it; k after a side
    would discard that side, and is refused."""
    for both, sides in TWO_SIDED.items():
        if key == both and given & set(sides):
            raise InputError(f"--set {item!r} would discard the {'/'.join(sorted(given & set(sides)))} given before "
                             f"it for the same constraint: give {both} first, then the side that differs")
        if c.get("law") in LAWS_2D:
            continue
        if key == both:
            for side in sides:
                c.pop(side, None)
        elif key in sides and both in c:
            kept = c.pop(both)
            for side in sides:
                c.setdefault(side, kept)
    c[key] = value
    given.add(key)


def _override_constraints(constraints, key: str, value, item: str, given: dict) -> None:
    """constraint.key sets every constraint; constraint.N.key the N-th (from 1). `given` maps a
    constraint's number to the keys set on it so far."""
    index, dot, rest = key.partition(".")
    if not dot:
        for i, c in enumerate(constraints):
            _set_constraint_key(c, key, value, given.setdefault(i, set()), item)
        return
    if not index.isdigit() or not 1 <= int(index) <= len(constraints):
        raise InputError(f"--set {item!r}: constraint.N.key needs N from 1 to {len(constraints)} (the scene's "
                         f"constraints), or constraint.key for all of them")
    _set_constraint_key(constraints[int(index) - 1], rest, value, given.setdefault(int(index) - 1, set()), item)


def _check_type(where: str, key: str, value, types) -> None:
    types = types if isinstance(types, tuple) else (types,)
    if isinstance(value, bool) and bool not in types:
        raise InputError(f"{where}: {key} must be {_type_name(types)}, got {value!r}")
    if not isinstance(value, types):
        raise InputError(f"{where}: {key} must be {_type_name(types)}, got {value!r}")
    if isinstance(value, str) and "\x00" in value:   # red team: a NUL in [output] file was an internal ValueError
        raise InputError(f"{where}: {key} contains a NUL character, which no file name or name may hold; remove it")
    numbers = value if isinstance(value, list) else [value]
    if key == "correlation_length" and isinstance(value, float) and math.isinf(value):
        return   # turbulence: inf is a fully correlated load; -inf is refused as not > 0 (_check_turbulence)
    if any(isinstance(v, float) and not math.isfinite(v) for v in numbers):
        raise InputError(f"{where}: {key} must be finite, got {value!r}")


def _type_name(types) -> str:
    names = {int: "an integer", float: "a number", str: "a string", list: "a list", bool: "true or false"}
    if set(types) >= {int, float}:
        types = tuple(t for t in types if t is not int)
    return " or ".join(names[t] for t in types)


def _sections_with(key: str) -> list:
    """The sections that have `key`, as a scene writes them ("[integrator]", "[[constraint]]")."""
    owners = [f"[{section}]" for section, keys in SCHEMA.items() if key in keys]
    return owners + (["[[constraint]]"] if key in CONSTRAINT[1] else [])


def _sections(data: dict, path: str) -> dict:
    """Every section with its keys type-checked and defaults filled in."""
    if "scene" in data and ("axes" in data or "case" in data):
        raise InputError(f"{path}: is a sweep file (a base scene and its axes or cases), not a scene: run it with "
                         f"dbf-hpc sweep {path}")
    for name in data:
        if name not in SCHEMA and name != "constraint":
            if not isinstance(data[name], dict):   # a key above every section header: TOML puts it at the top
                owners = _sections_with(name)
                raise InputError(f"{path}: '{name}' is outside any section (above the first [section] line); "
                                 f"move it under {' or '.join(owners) if owners else 'its section'} "
                                 f"(sections: {', '.join(SCHEMA)}, [[constraint]])")
            raise InputError(f"{path}: unknown section [{name}] (sections: {', '.join(SCHEMA)}, [[constraint]])")
    sections = {}
    for name, keys in SCHEMA.items():
        given = data.get(name, {})
        if not isinstance(given, dict):
            raise InputError(f"{path}: [{name}] must be a table")
        for key, value in given.items():
            if key not in keys:
                # new-user pass: a key of another section (modes under [integrator]) or a near miss
                close = difflib.get_close_matches(key, keys, n=1, cutoff=0.8)
                elsewhere = [owner for owner in _sections_with(key) if owner != f"[{name}]"]
                where = (f"; did you mean '{close[0]}'?" if close else
                         f"; {key} is a key of {' and '.join(elsewhere)}" if elsewhere else "")
                raise InputError(f"{path}: unknown key '{key}' in [{name}] (valid keys: {valid_keys(name)}){where}")
            _check_type(f"{path}: [{name}]", key, value, keys[key][0])
        sections[name] = {key: given.get(key, default) for key, (_, default) in keys.items()}
    return sections


def _check_structure(s: dict, where: str) -> None:
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
        if s["planes"] not in (1, 2):
            raise InputError(f"{where}: planes must be 1 or 2, got {s['planes']!r}")
        if s["transported_mass"] is not None and not s["transported_mass"] > 0:
            raise InputError(f"{where}: transported_mass must be positive, got {s['transported_mass']!r}")
        if s["axial_speed"] and not (s["left"] in ("pinned", "clamped") and s["right"] in ("pinned", "clamped")):
            raise InputError(f"{where}: axial_speed needs w fixed at both ends (left and right pinned or clamped), "
                             f"got {s['left']!r} and {s['right']!r}")
        if s["gyroscopic"] is not None:
            raise InputError(f"{where}: gyroscopic (a matrix file) is for kind = \"matrices\"; a beam's G comes from "
                             f"axial_speed")
    elif s["kind"] == "matrices":
        if s["planes"] != 1:
            raise InputError(f"{where}: planes applies to a beam; a matrix model gives its DOFs itself")
        if s["axial_speed"] or s["tension"] or s["transported_mass"] is not None:
            raise InputError(f"{where}: axial_speed, tension and transported_mass apply to a beam; a matrix model "
                             f"gives its gyroscopic matrix (gyroscopic = \"G.mtx\") and K with its tension")
        for key in ("stiffness", "mass"):
            if s[key] is None or not s[key].strip():   # red team: "" was an internal TypeError (a None path)
                got = "" if s[key] is None else f", got {s[key]!r}"
                raise InputError(f"{where}: {key} (a matrix file) is required for kind = \"matrices\"{got}")
    else:
        raise InputError(f"{where}: kind must be \"beam\" or \"matrices\", got {s['kind']!r}")
    # Any other key of the other kind would be ignored (a matrix model's supports = [0] pinned nothing)
    other = "matrices" if s["kind"] == "beam" else "beam"
    for key, (_, default) in SCHEMA["structure"].items():
        if SECTIONS["structure"][1][key].doc.startswith(f"{other}:") and s[key] != default:
            raise InputError(f"{where}: {key} applies to kind = \"{other}\" and would be ignored here" + (
                "; apply a matrix model's supports to K and M (leave the fixed DOFs out)" if key == "supports" else
                "; a matrix model's K and M hold its geometry, material and boundary conditions"
                if other == "beam" else ""))


class _Positions:
    """Checks positions on the structure: x on a beam, a DOF of a matrix model."""

    def __init__(self, structure: dict):
        self.beam = structure["kind"] == "beam"
        self.length = structure["length"]
        self.key = "x" if self.beam else "dof"

    def check(self, where: str, value) -> None:
        if self.beam:
            if not (isinstance(value, NUMBER) and not isinstance(value, bool) and 0 <= value <= self.length):
                raise InputError(f"{where}: x = {value!r} is not on the beam [0, {self.length}] m")
        elif not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            raise InputError(f"{where}: dof must be a non-negative integer, got {value!r}")


def _constraints(raw, path: str, at: _Positions, kind: str) -> tuple:
    if not isinstance(raw, list):
        raise InputError(f"{path}: constraints are written [[constraint]] (an array of tables)")
    constraints = []
    for i, c in enumerate(raw):
        where = f"{path}: [[constraint]] {i + 1}"
        if not isinstance(c, dict):
            raise InputError(f"{where} must be a table")
        other = "dof" if at.beam else "x"
        if other in c:
            raise InputError(f"{where}: use {at.key}, not {other}, on a {kind} structure")
        if at.key not in c:
            raise InputError(f"{where}: {at.key} is required")
        at.check(where, c[at.key])
        known = (at.key, *LAW_KEYS, *(k for k in KEYS_2D if k not in LAW_KEYS), "wear_coefficient")
        for key in c:
            if key not in known:
                close = difflib.get_close_matches(key, known, n=1, cutoff=0.8)
                raise InputError(f"{where}: unknown key {key!r} (keys: {', '.join(known)}; docs/scene.md says which "
                                 f"law takes which)" + (f"; did you mean '{close[0]}'?" if close else ""))
        law = law_from_dict(where, {k: v for k, v in c.items() if k not in (at.key, "wear_coefficient")})
        wear = c.get("wear_coefficient")
        if wear is not None:
            if getattr(law, "dimension", 1) != 2:
                raise InputError(f"{where}: wear_coefficient needs a 2-D law (circular, flat_bar): a planar law has "
                                 f"no sliding")
            if isinstance(wear, bool) or not isinstance(wear, NUMBER) or not (math.isfinite(wear) and wear >= 0):
                raise InputError(f"{where}: wear_coefficient must be a non-negative number (m^3/(N m)), got {wear!r}")
            wear = check_wear_coefficient(f"{where}:", wear)
        constraints.append(Constraint(law=law, x=float(c["x"]) if at.beam else None, dof=None if at.beam else c["dof"],
                                      wear_coefficient=wear))
    seen = {}
    for i, c in enumerate(constraints):
        key = round(c.x / at.length, 9) if at.beam else c.dof
        if key in seen:
            first = constraints[seen[key]]
            # apart by less than 1e-9 of the length, one node of the mesh (red team: 0.25 and 0.5 m on a 2**70 m
            # beam were "both at x = 0.5 m")
            where = (f"are both at {c.label}" if first.label == c.label else
                     f"at {first.label} and {c.label} are one point of the mesh (closer than {POINT_TOL:g} of its "
                     f"length)")
            raise InputError(f"{path}: constraints {seen[key] + 1} and {i + 1} {where}; remove one or merge their laws")
        seen[key] = i
    return tuple(constraints)


def _check_direction(e: dict, s: dict, where: str) -> None:
    d = e["direction"]
    if not d:
        return
    if s["kind"] != "beam" or s["planes"] != 2:
        raise InputError(f"{where}: direction applies to a beam of two planes ([structure] planes = 2)")
    if not (len(d) == 2 and all(isinstance(x, NUMBER) and not isinstance(x, bool) for x in d)
            and math.hypot(*d) > 0):
        raise InputError(f"{where}: direction must be [dy, dz], two numbers not both 0, got {d!r}")


def _refuse_ignored_turbulence_keys(e: dict, where: str) -> None:
    """The turbulence keys on another kind of load: ignored, they would describe a load the run does
    not apply (red team: kind = "random" with lambda = 0.3 m ran fully correlated)."""
    given = [key for key in ("correlation_length", "corner_hz", "slope") if e[key] is not None]
    given += ["spectrum"] if e["spectrum"] != "flat" else []
    if given:
        fully = " (a fully correlated load of a flat PSD)" if e["kind"] == "random" else ""
        verb = "belongs" if len(given) == 1 else "belong"
        raise InputError(f"{where}: {', '.join(given)} {verb} to kind = \"turbulence\" and would be ignored "
                         f"by kind = {e['kind']!r}{fully}: remove them or set kind = \"turbulence\"")


def _refuse_ignored_load_keys(e: dict, where: str) -> None:
    """A harmonic load's amplitude or frequency on a random one, or a PSD, band, seed, components or
    span on a harmonic one: ignored, they would describe a load not applied (red team; span = [-1, 5],
    components = -1 on a base excitation ran without a word). kind = "none" keeps every key:
    --set excitation.kind=none turns any scene into its free vibration."""
    harmonic = [key for key in ("amplitude", "frequency_hz") if e[key]]
    defaults = SECTIONS["excitation"][1]
    spectral = [key for key in ("psd", "band", "seed", "components", "span") if e[key] != defaults[key].default]
    ignored = harmonic if e["kind"] in ("random", "turbulence") else spectral if e["kind"] != "none" else []
    if ignored:
        verb, it = ("has", "it") if len(ignored) == 1 else ("have", "them")
        raise InputError(f"{where}: {', '.join(ignored)} {verb} no meaning for kind = {e['kind']!r} and would be "
                         f"ignored: remove {it} or set the kind that takes {it}")


def _refuse_ignored_position_keys(e: dict, where: str, at: _Positions) -> None:
    """Where a load acts, given to a load that does not take it: x or dof on anything but a force (of
    the structure's kind), end on anything but support motion. Ignored, they would describe a load not
    applied (red team: kind = "base" with x = 0.5 ran the support's motion, x read nowhere; end =
    "right" on a force likewise). kind = "none" keeps every key."""
    if e["kind"] == "none":
        return
    ignored = [key for key in ("x", "dof") if e[key] is not None and (e["kind"] != "force" or key != at.key)]
    ignored += ["end"] if e["end"] != "left" and e["kind"] != "base" else []
    if ignored:
        takes = {"x": "a force on a beam", "dof": "a force on a matrices structure", "end": "base excitation of a beam"}
        verb = "applies" if len(ignored) == 1 else "apply"
        raise InputError(f"{where}: {', '.join(ignored)} {verb} to {' and '.join(takes[k] for k in ignored)} and would "
                         f"be ignored by kind = {e['kind']!r} on a {'beam' if at.beam else 'matrices'} structure: "
                         f"remove {'it' if len(ignored) == 1 else 'them'}")


def _check_excitation(e: dict, s: dict, where: str, at: _Positions) -> None:
    _check_direction(e, s, where)
    if e["kind"] not in ("none", "base", "force", "random", "turbulence"):
        raise InputError(f"{where}: kind must be \"none\", \"base\", \"force\", \"random\" or \"turbulence\", "
                         f"got {e['kind']!r}")
    if e["kind"] == "turbulence":
        _check_turbulence(e, s, where)
    elif e["kind"] != "none":
        _refuse_ignored_turbulence_keys(e, where)
    _refuse_ignored_load_keys(e, where)
    _refuse_ignored_position_keys(e, where, at)
    if e["kind"] in ("random", "turbulence"):
        if not at.beam:
            raise InputError(f"{where}: {e['kind']} forcing is distributed along a beam; not available for matrices")
        band = e["band"]
        if not (len(band) == 2 and all(isinstance(b, NUMBER) for b in band) and 0 <= band[0] < band[1]):
            raise InputError(f"{where}: band must be [f_low, f_high] in Hz with 0 <= f_low < f_high, got {band!r}")
        if not e["psd"] > 0:
            raise InputError(f"{where}: psd must be positive ((N/m)^2/Hz), got {e['psd']!r}")
        if e["components"] < 1:
            raise InputError(f"{where}: components must be at least 1, got {e['components']}")
        span = e["span"] or [0.0, s["length"]]
        if not (len(span) == 2 and all(isinstance(v, NUMBER) for v in span) and 0 <= span[0] < span[1] <= s["length"]):
            raise InputError(f"{where}: span must be [x0, x1] within the beam, got {e['span']!r}")
        e["span"] = [float(v) for v in span]
    elif e["kind"] != "none":
        if not e["frequency_hz"] > 0:
            raise InputError(f"{where}: frequency_hz must be positive, got {e['frequency_hz']!r}")
        if e["end"] not in ("left", "right"):
            raise InputError(f"{where}: end must be \"left\" or \"right\", got {e['end']!r}")
        if e["kind"] == "force":
            if e[at.key] is None:
                raise InputError(f"{where}: a force needs its position ({at.key})")
            at.check(where, e[at.key])
        if e["kind"] == "base":
            _check_displacement(e["amplitude"], s, where, "the support's motion")
        if e["kind"] == "base" and not at.beam and s["influence"] is None:
            raise InputError(f"{where}: base excitation of a matrices structure needs [structure] influence")
        if not at.beam and e["end"] != "left":
            raise InputError(f"{where}: end applies to a beam and would be ignored here: a matrix model's support "
                             f"motion is its influence vector ([structure] influence)")


def _check_displacement(value, s: dict, where: str, what: str) -> None:
    """fom.check_displacement on a beam; matrix models have no length here: not checked."""
    if s["kind"] == "beam":
        check_displacement(value, float(s["length"]), where, what)


# A key of [initial] that only shapes the motion the other key starts (its mode and direction): given
# with that key left out, it would be ignored, the structure starting at rest
SHAPES = {"mode": ("amplitude", "velocity"), "direction": ("amplitude",), "velocity_direction": ("velocity",)}


def _refuse_ignored_initial_keys(i: dict, given: frozenset, where: str, two: bool) -> None:
    """[initial] mode, direction or velocity_direction given, and not the amplitude (velocity) they
    shape: ignored, the run starting at rest (red team: mode = 3 without amplitude ran the structure
    at rest without a word). An amplitude given as 0 is the user's word that it is at rest (a sweep's
    case, a --set turning the initial displacement off): then the shape keys are kept. `two`: a beam
    of two planes, the only structure with an initial velocity."""
    units = {"amplitude": "amplitude (m)", "velocity": "velocity (m/s)"}
    for key, moved in SHAPES.items():
        moved = tuple(m for m in moved if two or m != "velocity")
        if moved and ("initial", key) in given and not any(("initial", m) in given for m in moved):
            names = " or ".join(units[m] for m in moved)
            raise InputError(f"{where}: {key} = {i[key]!r} is given without the {' or '.join(moved)} it shapes: the "
                             f"structure would start at rest and {key} be ignored; give {names}, or remove {key}")


def _check_initial(i: dict, s: dict, where: str, given: frozenset = frozenset()) -> None:
    _check_displacement(i["amplitude"], s, where, "the peak initial displacement")
    two = s["kind"] == "beam" and s["planes"] == 2
    for key in ("direction", "velocity_direction"):
        if i[key]:
            if not two:
                raise InputError(f"{where}: {key} applies to a beam of two planes ([structure] planes = 2)")
            d = i[key]
            if not (len(d) == 2 and all(isinstance(x, NUMBER) and not isinstance(x, bool) for x in d)
                    and math.hypot(*d) > 0):
                raise InputError(f"{where}: {key} must be [dy, dz], two numbers not both 0, got {d!r}")
    if i["velocity"] and not two:
        raise InputError(f"{where}: velocity applies to a beam of two planes (elsewhere start from a displaced mode)")
    _refuse_ignored_initial_keys(i, given, where, two)


def _check_turbulence(e: dict, s: dict, where: str) -> None:
    if e["direction"]:
        raise InputError(f"{where}: turbulence acts in every plane of the beam (independent in y and z); remove "
                         f"direction")
    lam = e["correlation_length"]
    if lam is None or isinstance(lam, bool) or not lam > 0:
        raise InputError(f"{where}: turbulence needs correlation_length > 0 (m; inf for a fully correlated load), "
                         f"got {lam!r}")
    if e["spectrum"] not in ("flat", "knee"):
        raise InputError(f"{where}: spectrum must be \"flat\" or \"knee\", got {e['spectrum']!r}")
    if e["spectrum"] == "knee":
        for key in ("corner_hz", "slope"):
            if e[key] is None or not e[key] > 0:
                raise InputError(f"{where}: a knee spectrum needs {key} > 0, got {e[key]!r}")
    elif e["corner_hz"] is not None or e["slope"] is not None:
        raise InputError(f"{where}: corner_hz and slope belong to spectrum = \"knee\"; remove them or set spectrum")


def _check_basis(b: dict, where: str) -> None:
    if b["modes"] is not None and b["max_frequency_hz"] is not None:
        raise InputError(f"{where}: give modes or max_frequency_hz, not both")
    EstimateSettings(enabled=b["estimate"], window=b["estimate_window"], tolerance=b["tolerance"],
                     statistics_window=b["estimate_statistics_window"])
    if b["tolerance"] is not None and b["max_frequency_hz"] is not None:
        raise InputError(f"{where}: tolerance picks the number of modes; remove max_frequency_hz, or give the "
                         f"first candidate's modes (--set basis.modes=4 replaces it)")
    if b["modes"] is None and b["max_frequency_hz"] is None:
        b["modes"] = 4 if b["tolerance"] is not None else 6
    if b["modes"] is not None and b["modes"] < 1:
        raise InputError(f"{where}: modes must be at least 1, got {b['modes']}")
    if b["max_frequency_hz"] is not None and not b["max_frequency_hz"] > 0:
        raise InputError(f"{where}: max_frequency_hz must be positive, got {b['max_frequency_hz']}")
    k = b["dbf_stiffness"]
    if not (k == "auto" or (isinstance(k, NUMBER) and k > 0)):
        raise InputError(f"{where}: dbf_stiffness must be \"auto\" or a positive number (N/m), got {k!r}")
    if b["dbf_derivative"] not in ("analytic", "central"):
        raise InputError(f"{where}: dbf_derivative must be \"analytic\" or \"central\", got {b['dbf_derivative']!r}")
    if b["dbf_solver"] not in DBF_SOLVERS:
        raise InputError(f"{where}: dbf_solver must be \"ritz\", \"shared\" or \"factor\", got {b['dbf_solver']!r}")
    if b["gyroscopic_form"] not in ("state_space", "second_order"):
        raise InputError(f"{where}: gyroscopic_form must be \"state_space\" or \"second_order\", got "
                         f"{b['gyroscopic_form']!r}")
    if not b["cache"].strip():   # red team: "" resolved to the scene's folder, which then held the bases
        raise InputError(f"{where}: cache must be a directory or \"off\", got {b['cache']!r}")
    if b["groups"] < 0:
        raise InputError(f"{where}: groups must be 0 (automatic) or a positive count, got {b['groups']}")
    if b["enrichment"] not in ENRICHMENTS:
        accepted = ", ".join(f'"{e}"' for e in ENRICHMENTS)
        raise InputError(f"{where}: enrichment must be one of {accepted}, got {b['enrichment']!r}")


def _check_integrator_and_output(sections: dict, path: str, at: _Positions, given: frozenset = frozenset()) -> None:
    i, where = sections["integrator"], f"{path}: [integrator]"
    i["scheme"] = str(i["scheme"]).lower()  # --set integrator.scheme=3 arrives as an integer
    for key in ("t_end", "dt", "rtol", "atol"):
        if not i[key] > 0:
            raise InputError(f"{where}: {key} must be positive, got {i[key]!r}")
    if i["contact"] not in ("implicit", "explicit"):
        raise InputError(f"{where}: contact must be \"implicit\" or \"explicit\", got {i['contact']!r}")
    if i["callbacks"] not in CALLBACKS:
        raise InputError(f"{where}: callbacks must be \"auto\", \"c\" or \"python\", got {i['callbacks']!r}")
    o, where = sections["output"], f"{path}: [output]"
    for x in o["probes"]:
        at.check(f"{where} probes", x)
    for key in ("sample_dt", "checkpoint_dt"):
        if o[key] is not None and not o[key] > 0:
            raise InputError(f"{where}: {key} must be positive, got {o[key]!r}")
    if o["sample_dt"] is None and not float(i["t_end"]) / 10000 > 0:   # red team: t_end = 5e-324 (a denormal)
        raise InputError(f"{path}: [integrator] t_end = {float(i['t_end']):g} s: its default [output] sample_dt, "
                         f"t_end / 10000, is 0 in double precision: give a longer t_end")
    _check_statistics_window(sections["basis"]["estimate_statistics_window"], float(i["t_end"]),
                             float(o["sample_dt"] or i["t_end"] / 10000), f"{path}: [basis]")
    if o["snapshots"] < 0:
        raise InputError(f"{where}: snapshots must be a count >= 0, got {o['snapshots']}")
    if sections["initial"]["mode"] < 1:
        raise InputError(f"{path}: [initial] mode counts from 1, got {sections['initial']['mode']}")
    _check_initial(sections["initial"], sections["structure"], f"{path}: [initial]", given)


def _check_statistics_window(window, t_end: float, sample_dt: float, where: str) -> None:
    """A given statistics window must hold the 2 BATCHES samples its batch-means intervals need (or
    the whole run, when that is shorter): red team, estimate_statistics_window = 1e-300 s stopped a run
    after its integration (the richer run of t_end 0, a half-written output and a checkpoint left),
    and 1e-5 s (5 samples) printed every statistic's error as "+- nan"."""
    if window is None:
        return
    least = min(2 * BATCHES * sample_dt, t_end)
    if window < least * (1 - 1e-12):
        raise InputError(f"{where}: estimate_statistics_window = {window:g} s holds fewer than the {2 * BATCHES} "
                         f"samples (sample_dt = {sample_dt:g} s) its intervals need: give at least {least:g} s, or "
                         f"leave it out (t_end / 4)")


def validate(data: dict, path: str = "<scene>", text: str = "") -> Scene:
    """Check every section and key of a parsed scene; fill in defaults."""
    sections = _sections(data, path)
    s = sections["structure"]
    _check_structure(s, f"{path}: [structure]")
    if s["kind"] == "beam":   # the beam's own checks (its numbers' scale, its supports) before positions on it
        try:                  # (red team: length = 1e308 m was "constraints 1 and 2 are both at x = 1.5 m")
            Scene(path=path, text=text, sections=sections).beam()
        except InputError as e:
            raise InputError(f"{path}: [structure]: {e}") from None
    at = _Positions(s)
    for x in s["supports"]:
        at.check(f"{path}: [structure] supports", x)
    constraints = _constraints(data.get("constraint", []), path, at, s["kind"])
    planes = s["planes"] if at.beam else 1
    for i, c in enumerate(constraints):
        d = getattr(c.law, "dimension", 1)
        if d != planes:
            raise InputError(f"{path}: [[constraint]] {i + 1}: " + (
                f"a {c.law.kind} law acts in two directions; it needs [structure] planes = 2" if d == 2 else
                f"a beam of two planes takes a 2-D law (law = \"circular\" or \"flat_bar\"), not {c.law.kind}"))
    if s["kind"] == "beam":   # matrix models have no length: the idle-stop warning after the run remains theirs
        check_stops_within_reach(constraints, float(s["length"]), lambda i: f"{path}: [[constraint]] {i + 1}")
    _check_excitation(sections["excitation"], s, f"{path}: [excitation]", at)
    _check_basis(sections["basis"], f"{path}: [basis]")
    given = frozenset((name, key) for name in SCHEMA if isinstance(data.get(name), dict) for key in data[name])
    _check_integrator_and_output(sections, path, at, given)
    scene = Scene(path=path, text=text, sections=sections, constraints=constraints, given=given)
    if scene.damping().kind != "none" and not at.beam and s["damping"]:  # (also validates the damping section)
        raise InputError(f"{path}: {DAMPING_TWICE}")
    return scene
