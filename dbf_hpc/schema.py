"""The scene file's contract: every section and key, its type, default, unit and meaning.

scene.py validates against it; `reference()` renders it as docs/scene.md (a test checks that the
file is up to date, so the reference cannot drift from the code); unknown-key errors list the
valid keys from it.

Data and text only: nothing here is collective.
"""
from __future__ import annotations

from dataclasses import dataclass

NUMBER = (int, float)


@dataclass(frozen=True)
class Key:
    types: tuple
    default: object = None
    unit: str = ""
    doc: str = ""


SECTIONS = {
    "structure": ("The linear structure: a beam built here, or matrices of any FE model.", {
        "kind": Key((str,), "beam", "", '"beam" (Euler-Bernoulli, Hermite-cubic elements) or "matrices" (K, M '
                                        'from files)'),
        "length": Key(NUMBER, None, "m", "beam: length (required)"),
        "elements": Key((int,), 100, "", "beam: target number of elements (a node is added at every constraint, "
                                         "force, loaded span's end and support; probes are interpolated)"),
        "E": Key(NUMBER, None, "Pa", "beam: Young's modulus (required)"),
        "I": Key(NUMBER, None, "m^4", "beam: second moment of area (required; sqrt(I / A), the radius of "
                                             "gyration, at most the length)"),
        "A": Key(NUMBER, None, "m^2", "beam: cross-section area (required)"),
        "rho": Key(NUMBER, None, "kg/m^3", "beam: density (required)"),
        "left": Key((str,), "pinned", "", 'beam: left end, "pinned", "clamped", "free" or "sliding" (slope fixed)'),
        "right": Key((str,), "pinned", "", "beam: right end, as left"),
        "supports": Key((list,), [], "m", "beam: x of intermediate rigid supports (multi-span tubes)"),
        "planes": Key((int,), 1, "", "beam: 1 (bending in the x-y plane, w = y) or 2 (bending in two planes: per "
                                     "node y, dy/dx, z, dz/dx, the planes uncoupled with the same EI; constraints "
                                     "then take 2-D laws, law = \"circular\")"),
        "axial_speed": Key(NUMBER, 0.0, "m/s", "beam: axial transport speed U (an axially moving beam, or the flow "
                                               "speed of a pipe conveying fluid); needs w fixed at both ends. Adds "
                                               "the gyroscopic G = 2 m_t U int N^T N' dx and softens K by m_t U^2; "
                                               "above the critical speed sqrt((T + P_cr) / m_t) (P_cr the buckling "
                                               "load) K is indefinite: a run whose modes grow is refused, an "
                                               "undamped one that G alone holds is warned about"),
        "transported_mass": Key(NUMBER, None, "kg/m", "beam: mass per length moving at axial_speed (default rho A; "
                                                      "a pipe's fluid mass per length, which rho A, the whole "
                                                      "mass per length, includes: at most rho A)"),
        "tension": Key(NUMBER, 0.0, "N", "beam: axial tension T: K += (T - m_t U^2) int N'^T N' dx; negative: a "
                                         "compression, refused at or beyond the buckling load P_cr (EI pi^2 / L^2 "
                                         "pinned-pinned)"),
        "stiffness": Key((str,), None, "", "matrices: K over the free DOFs, Matrix Market (.mtx) or PETSc binary "
                                           "(required); in SI units, N/m, as M in kg: the outputs' units, the "
                                           "absolute tolerances and the friction's regularization speed are SI"),
        "mass": Key((str,), None, "", "matrices: M, as stiffness (required)"),
        "damping": Key((str,), None, "", "matrices: a damping matrix C (optional): the whole linear damping, so "
                                         "[damping] is then refused"),
        "gyroscopic": Key((str,), None, "", "matrices: a skew-symmetric gyroscopic matrix G (optional): "
                                            "M u'' + (C + G) u' + K u = f. Under base excitation the support's "
                                            "velocity loads neither C nor G (the load is -base_mass_load Omega''): "
                                            "right when the whole structure's G r is 0, e.g. a rotor's base in "
                                            "translation"),
        "influence": Key((str,), None, "", "matrices: r, the displacement under a unit support motion (.npy, .txt, "
                                           ".mtx or PETSc binary; needed for base excitation)"),
        "base_mass_load": Key((str,), None, "", "matrices: M_(free, all) r_all with the coupling to the moving "
                                                "support (default M r)"),
        "nodes": Key((str,), None, "m", "matrices: node coordinates, a text file with one node a row (1 to 3 "
                                       "columns, coordinates only: the row, from 0, is the node's number; a first "
                                       "column 0, 1, 2 ... draws a warning); with dofs, outputs show displacement "
                                       "vectors at the nodes"),
        "dofs": Key((str,), None, "", "matrices: for each free DOF (one a row, in K's order) its node (from 0) "
                                      "and direction: x, y, z, rx, ry or rz (the error estimate scales rotations, "
                                      "rad, apart from translations, m, only where this names them)"),
        "cells": Key((str,), None, "", "matrices: the mesh's cells, so that the ParaView files show the solid "
                                       "instead of points (needs nodes and dofs): one cell a row, the indices "
                                       "(from 0) of its nodes in XDMF's (VTK's) order, .npy or text; the node "
                                       "count picks the type: 2 Polyline, 3 Triangle, 4 Tetrahedron, 5 Pyramid, "
                                       "6 Wedge, 8 Hexahedron, 10 Tetrahedron_10, 20 Hexahedron_20 (cell_type "
                                       "for others). Changes no number: checkpoints and the basis cache ignore "
                                       "it; outputs record it (field_cells)"),
        "cell_type": Key((str,), None, "", "matrices: with cells, their XDMF type where the node count alone "
                                           "does not say it: Quadrilateral (4 nodes: a shell's), Triangle_6 (6), "
                                           "Quadrilateral_8 (8), or any of Polyline, Triangle, Tetrahedron, "
                                           "Pyramid, Wedge, Hexahedron, Tetrahedron_10, Hexahedron_20 with its "
                                           "node count"),
    }),
    "excitation": ("What drives the structure.", {
        "kind": Key((str,), "none", "", '"none" (free vibration), "base" (support motion), "force" (a point '
                                        'force), "random" (a fully correlated random load along a beam) or '
                                        '"turbulence" (a random load along a beam with partial correlation, '
                                        'independent in y and z with planes = 2)'),
        "amplitude": Key(NUMBER, 0.0, "m or N", "base: support displacement amplitude (on a beam at most its "
                                                    "length); force: force amplitude"),
        "frequency_hz": Key(NUMBER, 0.0, "Hz", "base, force: frequency of the sine"),
        "end": Key((str,), "left", "", 'base: the moving support of a beam, "left" or "right"'),
        "x": Key(NUMBER, None, "m", "force on a beam: where it acts"),
        "dof": Key((int,), None, "", "force on matrices: the DOF it acts on (counted from 0)"),
        "psd": Key(NUMBER, 0.0, "(N/m)^2/Hz", "random, turbulence: one-sided PSD of the force per unit length at a "
                                              "point (turbulence: its level below corner_hz)"),
        "band": Key((list,), [], "Hz", "random, turbulence: [f_low, f_high] of the PSD"),
        "seed": Key((int,), 1, "", "random, turbulence: the same seed gives the same history"),
        "components": Key((int,), 256, "", "random, turbulence: cosines of the spectral representation (per "
                                           "history), 1 to 65536; turbulence: at most 4194304 over all its "
                                           "histories"),
        "span": Key((list,), [], "m", "random, turbulence: [x0, x1] loaded, nodes of the mesh (default the whole "
                                      "beam); random: fully correlated"),
        "correlation_length": Key(NUMBER, None, "m", "turbulence: lambda of the coherence exp(-|dx| / lambda) "
                                                     "between points of the span (required; inf: fully correlated)"),
        "spectrum": Key((str,), "flat", "", 'turbulence: "flat" (S = psd) or "knee" (S = psd up to corner_hz, '
                                            'psd (f / corner_hz)^-slope above)'),
        "corner_hz": Key(NUMBER, None, "Hz", "turbulence, knee: where the PSD starts to fall"),
        "slope": Key(NUMBER, None, "1", "turbulence, knee: the exponent of the fall (S ~ f^-slope)"),
        "direction": Key((list,), [], "1", "beam of two planes: [dy, dz], the direction of the force or of the "
                                           "support motion in the y-z plane (normalized; default [1, 0])"),
    }),
    "basis": ("Reference modes and one enrichment column per constraint.", {
        "modes": Key((int,), None, "", "number of reference modes (6 if neither this nor max_frequency_hz); "
                                       "even on a beam of two planes (its frequencies come in y-z pairs), and on "
                                       "any structure not ending inside a repeated frequency (refused, naming the "
                                       "counts that keep it whole)"),
        "max_frequency_hz": Key(NUMBER, None, "Hz", "every mode below this frequency instead of a count (on a beam of two planes, whole y-z pairs)"),
        "enrichment": Key((str,), "dbf", "", '"dbf" (the method), "static" (static attachment modes K^-1 g) or '
                                             '"none" (modes alone); the last two are comparators, which read none of '
                                             'dbf_stiffness, dbf_derivative, dbf_solver and groups (given, a run '
                                             'warns)'),
        "dbf_stiffness": Key((str, *NUMBER), "auto", "N/m", 'k_j of the spring-perturbed problem: "auto" (the '
                                                             'corner of the paper\'s Fig. 2) or a number'),
        "dbf_derivative": Key((str,), "analytic", "", '"analytic" (deflated derivative solve) or "central" (the '
                                                      'paper\'s central difference)'),
        "dbf_solver": Key((str,), "ritz", "", '"ritz" (one factorization of K - sigma M per constraint group, '
                                              'Rayleigh-Ritz on the reference modes plus a few Krylov vectors per '
                                              'constraint), "shared" (the same factorization, rank-one updates and '
                                              'Krylov eigensolves per constraint) or "factor" (three factorizations '
                                              'per constraint, the paper-faithful comparator)'),
        "gyroscopic_form": Key((str,), "second_order", "", 'a gyroscopic structure\'s reduced model: '
                                                           '"second_order" (Re and Im of the complex modes and DBFs '
                                                           'as displacement columns, M-orthonormal; 2 states a '
                                                           'column) or "state_space" (the paper\'s first-order '
                                                           'form, Eqs. 4-21: state vectors orthonormal in '
                                                           'A = diag(M, K), 2 (N + N_L) states); both run the '
                                                           '[integrator] callbacks'),
        "groups": Key((int,), 0, "", "constraint groups solved side by side (0: one per rank, at most one per "
                                     "constraint)"),
        "cache": Key((str,), "~/.cache/dbf_hpc", "", 'directory of cached bases, or "off"'),
        "estimate": Key((bool,), True, "", "the a-posteriori error estimate of a run (the attribute estimated_error: "
                                           "the largest error in w at any constraint over the largest |w| at any "
                                           "constraint, each kind of DOF apart where a node map puts constraints on "
                                           "rotations and translations; without a node map every constrained DOF "
                                           "counts as a translation, so give [structure] nodes and dofs where "
                                           "constraints act on rotations): the same scene on max(2N, N + N_L) modes with the same enrichment "
                                           "(and on 1.5 times those modes where that differs by 2 % or more: the larger) "
                                           "at a 10x tighter rtol, over estimate_window (docs/accuracy.md); with "
                                           "--method full the same model at a 4x shorter step; sweeps and scenes "
                                           "without constraints do not make it"),
        "estimate_window": Key(NUMBER, None, "s", "the window [0, T] the estimate holds over (default twice the time "
                                                  "of the first impact, or t_end / 10 without one; a constraint "
                                                  "in force from the start is no impact until it lets go and "
                                                  "touches again); a run that makes no estimate (estimate = false, "
                                                  "no constraints) warns that it, as estimate_statistics_window, "
                                                  "is not used"),
        "estimate_statistics_window": Key(NUMBER, None, "s", "a long run's (t_end over 5 estimate windows) "
                                                             "statistics window [0, T]: the richer model's impact "
                                                             "statistics over it against the run's give their model "
                                                             "error (default t_end / 4; given or not, at least 20 "
                                                             "samples or the whole run; docs/accuracy.md)"),
        "tolerance": Key(NUMBER, None, "1", "the tolerance mode: the number of modes (from modes, default 4, growing "
                                            "at most twofold) and rtol (tolerance / 100) are picked so that the "
                                            "estimate over the window is below 0.75 x this relative error in w at "
                                            "the constraints; an error if it cannot be met (`run` only: `dbf-hpc "
                                            "basis` builds the first candidate; refused for a gyroscopic "
                                            "structure)"),
    }),
    "damping": ("Linear damping of the structure (none by default, as in the paper).", {
        "zeta": Key((*NUMBER, list), 0.0, "1", "modal damping ratio, 0 to 100, one for all or one per basis "
                                                "vector (a list: the run then has no error estimate, and [basis] "
                                                "tolerance refuses it)"),
        "rayleigh_alpha": Key(NUMBER, 0.0, "1/s", "C = alpha M + beta K"),
        "rayleigh_beta": Key(NUMBER, 0.0, "s", "C = alpha M + beta K"),
    }),
    "integrator": ("Time integration: the reduced model's PETSc TS ARKIMEX (options prefix rom_), the full-order "
                   "reference's generalized-alpha at the fixed step dt (options prefix full_). t_end, dt, "
                   "adaptive, rtol and atol are set here only (-rom_ts_max_time, _dt, _rtol, _atol and a contrary "
                   "-rom_ts_adapt_type are refused: the error estimate's richer run derives its own from them); "
                   "-rom_ts_arkimex_type overrides scheme.", {
        "t_end": Key(NUMBER, 1.0, "s", "end of the run"),
        "dt": Key(NUMBER, 1e-4, "s", "the fixed step, or the first step of an adaptive run (at most 10 sample "
                                     "intervals, its steps' upper limit, and at least its steps' floor; --method "
                                     "full: at least 1e-30 s, as t_end)"),
        "scheme": Key((str, int), "3", "", "the reduced model's ARKIMEX type: 1bee, a2, l2, ars122, 2c, 2d, 2e, "
                                           "prssp2, 3, bpr3, ars443, 4, 5"),
        "adaptive": Key((bool,), True, "", "adaptive steps (error control by rtol, atol) or the fixed step dt"),
        "rtol": Key(NUMBER, 1e-6, "1", "relative tolerance of the adaptive steps"),
        "atol": Key(NUMBER, 1e-9, "", "absolute tolerance (at least 1e-30) of the reduced model's adaptive "
                                      "steps, the same number for every state, in modal units, not physical ones: the second-order form's "
                                      "M-orthonormal q (m kg^(1/2), a displacement tolerance times the square root "
                                      "of the modal mass) and q' (m kg^(1/2)/s: on a column of frequency omega it "
                                      "is a displacement tolerance of atol / omega, so the velocities of the high "
                                      "columns limit the step, docs/design.md); gyroscopic_form = \"state_space\": "
                                      "the A-orthonormal states (J^(1/2), |eta|^2 twice the energy); --method full "
                                      "does not use it (fixed step dt). Small masses and displacements in SI (a MEMS "
                                      "part) make the default loose: `run` (and run.run, simulate_reduced, and a "
                                      "sweep, once naming its cases) warns where atol lets w at a constraint err by "
                                      "over 1 % of its clearance (without one, of the "
                                      "motion's scale, the initial displacement, the support's amplitude or the "
                                      "static deflection under the force), naming the atol to set"),
        "contact": Key((str,), "implicit", "", '"implicit" (with its exact Jacobian) or "explicit" (the paper\'s '
                                               'IMEX split)'),
        "callbacks": Key((str,), "auto", "", 'the reduced model\'s TS callbacks: "c" (compiled, fast), "python" '
                                             '(the reference) or "auto" (C when built, else Python with a warning)'),
    }),
    "initial": ("The state at t = 0 (at rest in relative coordinates by default).", {
        "mode": Key((int,), 1, "", "reference mode of the initial displacement, counted from 1 (not one of a "
                                   "repeated frequency's modes, whose shape round-off picks; a beam of two "
                                   "planes counts its pairs); refused, as direction and velocity_direction, "
                                   "without the amplitude or velocity it shapes (0 given is kept: at rest)"),
        "amplitude": Key(NUMBER, 0.0, "m", "peak initial displacement in that mode (on a beam at most its "
                                               "length)"),
        "direction": Key((list,), [], "1", "beam of two planes: [dy, dz], the direction of the initial "
                                           "displacement (mode counts the y-z pairs; default [1, 0])"),
        "velocity": Key(NUMBER, 0.0, "m/s", "beam of two planes: peak initial velocity in the same mode shape"),
        "velocity_direction": Key((list,), [], "1", "beam of two planes: [dy, dz] of the initial velocity "
                                                    "(default [0, 1]: across a displacement along y, a whirl)"),
    }),
    "output": ("What a run writes.", {
        "file": Key((str,), None, "", "the HDF5 output, relative to the scene's folder (or -o)"),
        "sample_dt": Key(NUMBER, None, "s", "interval of the samples from t = 0 (default t_end / 10000); t_end is "
                                            "always the last sample, the last interval shorter when sample_dt does not "
                                            "divide t_end"),
        "probes": Key((list,), [], "m", "x of the probes on a beam (DOFs for matrices): total displacement there"),
        "snapshots": Key((int,), 0, "", "field snapshots at evenly spaced times, each at an output sample: more "
                                        "than the samples are all the samples, with a warning"),
        "checkpoint_dt": Key(NUMBER, None, "s", "simulated time between checkpoints (default t_end / 10, none sooner "
                                                "than 1 s of wall time after the start or the last: a short run "
                                                "writes none)"),
    }),
}

CONSTRAINT = ("One table per constraint: where it acts and its law (laws.py).", {
    "x": Key(NUMBER, None, "m", "beam: position (required on a beam)"),
    "dof": Key((int,), None, "", "matrices: the DOF it acts on, counted from 0 (required for matrices)"),
    "law": Key((str,), "deadband", "", '"deadband" (Eq. 23), "power" (Eq. 42), "hertz", "linear", "cubic", '
                                       '"table", "friction" (Coulomb friction alone against a given normal force), '
                                       'or on a beam of two planes "circular" (a round hole) or "flat_bar" (two '
                                       'parallel flats)'),
    "clearance": Key(NUMBER, None, "m", "deadband, power, hertz: gap on both sides (or clearance_minus, "
                                        "clearance_plus; 0 when not given: in contact from z = 0); negative is an "
                                        "interference fit, at most 1 m deep; circular: the radial clearance (>= 0), flat_bar: the gap "
                                        "to each flat (both required); on a beam at most its length where the "
                                        "side has a stop (k > 0): a farther one is a unit slip, refused"),
    "k": Key(NUMBER, None, "N/m^p", "stiffness on both sides (or k_minus, k_plus); linear, cubic: the spring; "
                                    "required but for table and friction (cubic: k and/or k3); circular, flat_bar: "
                                    "N/m"),
    "exponent": Key(NUMBER, None, "", "power: exponent p on both sides (or exponent_minus, exponent_plus); "
                                      "hertz: 1.5"),
    "k3": Key(NUMBER, None, "N/m^3", "cubic: N = -(k z + k3 z^3)"),
    "table": Key((list,), None, "m, N", "table: [[z, force], ...], piecewise linear, the force on the structure "
                                    "non-increasing in z (restoring), not all forces 0"),
    "damping": Key((str,), "none", "", 'contact damping: "none", "linear" (-c v) or "hunt_crossley" '
                                       '(-alpha |N| v), in contact only, not clipped: while separating, '
                                       'linear damping pulls where c |v| > |N| and Hunt-Crossley where '
                                       '|v| > 1 / alpha'),
    "c": Key(NUMBER, None, "N s/m", "linear contact damping"),
    "alpha": Key(NUMBER, None, "s/m", "Hunt-Crossley contact damping: alpha = 3 (1 - e) / (2 v) for a restitution "
                                      "e at the impact speed v (Hunt & Crossley); a run whose alpha |v| in contact "
                                      "exceeds 1.5 (e = 0) warns: the law is then outside its range, and the full-order "
                                      "force depends on dt"),
    "mu": Key(NUMBER, None, "1", "circular, flat_bar: Coulomb friction coefficient (default 0, at most 10), "
                                 "F_t = -mu k (|u| - c) tanh(v_t / v_reg); friction: N = -mu normal_force "
                                 "tanh(v / v_reg) (required, > 0: mu = 0 is no constraint)"),
    "v_reg": Key(NUMBER, None, "m/s", "circular, flat_bar, friction: the sliding speed over which friction is "
                                      "regularized (default 1e-3)"),
    "normal_force": Key(NUMBER, None, "N", "friction: the given normal force F_n (required, > 0)"),
    "angle": Key(NUMBER, None, "deg", "flat_bar: the direction of the flats' normal, from y towards z (default 0: "
                                      "flats across y, sliding along z); any finite angle, taken modulo 360"),
    "wear_coefficient": Key(NUMBER, None, "m^3/(N m)", "circular, flat_bar: Archard's wear coefficient K_w (at "
                                                       "most 1e-6); "
                                                       "the output's wear_volume = K_w int |F_n| |v_t| dt (NaN "
                                                       "without it)"),
})


def unit_of(name: str) -> str:
    """The unit of a scene value 'section.key' (or 'constraint.N.key'), '' where it has none."""
    section, _, key = name.partition(".")
    key = key.rpartition(".")[2]
    keys = CONSTRAINT[1] if section == "constraint" else SECTIONS.get(section, ("", {}))[1]
    entry = keys.get(key) or keys.get(key.replace("_minus", "").replace("_plus", ""))
    return entry.unit if entry is not None and entry.unit not in ("", "1") else ""


def valid_keys(section: str) -> str:
    keys = CONSTRAINT[1] if section == "constraint" else SECTIONS[section][1]
    return ", ".join(keys)


def _table(keys: dict) -> list:
    lines = ["| key | type | default | unit | meaning |", "|---|---|---|---|---|"]
    names = {int: "integer", float: "number", str: "string", list: "list", bool: "boolean"}
    for name, key in keys.items():
        types = key.types if not set(key.types) >= {int, float} else tuple(t for t in key.types if t is not int)
        default = "" if key.default is None else f"`{key.default!r}`".replace("'", '"')
        lines.append(f"| `{name}` | {' or '.join(names[t] for t in types)} | {default} | {key.unit} | {key.doc} |")
    return lines


def reference() -> str:
    """docs/scene.md: the scene reference, generated from this module."""
    lines = ["# Scene files: the reference", "",
             "Generated from `dbf_hpc/schema.py` (`python -m dbf_hpc.schema > docs/scene.md`); a test checks "
             "that this file is up to date. A scene is TOML with SI units. Relative paths are taken relative to "
             "the scene file's folder. DOFs count from 0. Any value can be overridden on the command line with "
             "`--set section.key=value` (TOML syntax; `--set constraint.key=value` sets every constraint, "
             "`--set constraint.2.key=value` the second one; `k`, `clearance` or `exponent` set that way "
             "replaces the scene's two sides (`k_minus`/`k_plus`, ...), one side set over a scene's `k` keeps "
             "`k` on the other, and a side given after `k` refines it, while `k` after a side is refused, "
             "as is one `k` for sides of different exponents, whose units differ; `basis.modes` replaces the "
             "scene's `max_frequency_hz`, and the other way round).", ""]
    for section, (doc, keys) in SECTIONS.items():
        lines += [f"## [{section}]", "", doc, "", *_table(keys), ""]
    lines += ["## [[constraint]]", "", CONSTRAINT[0] + " Keys with a side (`clearance`, `k`, `exponent`) also "
              "exist as `_minus` and `_plus` versions for the two sides.", "", *_table(CONSTRAINT[1]), ""]
    lines += ["## Example: the paper's beam (jobs/paper_beam.toml)", "", "```toml",
              *open(_example()).read().strip().splitlines(), "```", ""]
    return "\n".join(lines)


def _example() -> str:
    import os

    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "jobs", "paper_beam.toml")


if __name__ == "__main__":
    print(reference(), end="")
