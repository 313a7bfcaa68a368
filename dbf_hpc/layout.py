"""The output layout: every dataset name of a run's HDF5 file, with its unit and meaning, in one place
(README "Outputs" and docs/outputs.md describe the same contract).

Series (one row per sample) are streamed while a run goes; the rest is written when it ends.
Shapes: nt samples, N_L constraints, P probes, r basis vectors, F field points, S snapshots.

Names and units only: nothing here is collective.
"""
from __future__ import annotations

TIME = "time"
CONSTRAINT_POSITION = "constraints/position"
CONSTRAINT_CLEARANCE_MINUS = "constraints/clearance_minus"
CONSTRAINT_CLEARANCE_PLUS = "constraints/clearance_plus"
CONSTRAINT_DISPLACEMENT = "constraints/displacement"
CONSTRAINT_VELOCITY = "constraints/velocity"
CONSTRAINT_FORCE = "constraints/force"
CONSTRAINT_FORCE_PEAK = "constraints/force_peak"
CONSTRAINT_STATS = "constraints/stats"
STATISTICS_ERROR = "constraints/stats_error"
PROBE_POSITION = "probes/position"
PROBE_DISPLACEMENT = "probes/displacement"
PROBE_PEAK = "probes/peak"
BASIS_OMEGA = "basis/omega"
BASIS_ENRICHMENT_OMEGA = "basis/enrichment_omega"
BASIS_DBF_K = "basis/dbf_k"
BASIS_FLEXIBILITY_CAPTURED = "basis/flexibility_captured"
BASIS_FLEXIBILITY_EXACT = "basis/flexibility_exact"
REDUCED_Q = "reduced/q"
REDUCED_QDOT = "reduced/qdot"
REDUCED_M = "reduced/M"
REDUCED_K = "reduced/K"
REDUCED_D = "reduced/D"
REDUCED_B = "reduced/B"
SNAPSHOT_TIME = "snapshots/time"
SNAPSHOT_X = "snapshots/x"
SNAPSHOT_W = "snapshots/w"

# Streamed per sample, in this order.
SERIES = (TIME, CONSTRAINT_DISPLACEMENT, CONSTRAINT_VELOCITY, CONSTRAINT_FORCE, CONSTRAINT_FORCE_PEAK,
          PROBE_DISPLACEMENT, REDUCED_Q, REDUCED_QDOT)

# name -> (unit, meaning)
DATASETS = {
    TIME: ("s", "sample times (nt): 0, sample_dt, 2 sample_dt, ... and t_end, always the last sample (the last "
                "interval shorter when sample_dt does not divide t_end)"),
    CONSTRAINT_POSITION: ("m or 1", "x of each constraint on a beam, or its DOF (N_L)"),
    CONSTRAINT_CLEARANCE_MINUS: ("m", "clearance below each constraint (N_L)"),
    CONSTRAINT_CLEARANCE_PLUS: ("m", "clearance above each constraint (N_L)"),
    CONSTRAINT_DISPLACEMENT: ("m", "total displacement at the constraints (nt x N_L; nt x N_L x 2, (y, z), on a beam of two planes)"),
    CONSTRAINT_VELOCITY: ("m/s", "total velocity at the constraints (nt x N_L; nt x N_L x 2, (y, z), on a beam of two planes)"),
    CONSTRAINT_FORCE: ("N", "constraint force on the structure at the samples (nt x N_L; nt x N_L x 2, (y, z), on a beam of two planes)"),
    CONSTRAINT_FORCE_PEAK: ("N", "largest-magnitude constraint force at the solver's steps since the "
                                 "previous sample (nt x N_L; nt x N_L x 2 on a beam of two "
                                 "planes, per component)"),
    PROBE_POSITION: ("m or 1", "x of each probe on a beam, or its DOF (P)"),
    PROBE_DISPLACEMENT: ("m", "total displacement at the probes (nt x P; nt x P x 2, (y, z), on a beam of two planes)"),
    PROBE_PEAK: ("m", "the largest absolute displacement at each probe over the samples (P; P x 2 per component on a "
                    "beam of two planes)"),
    BASIS_OMEGA: ("rad/s", "reference frequencies (N; a gyroscopic structure: omega_j of the complex mode of each "
                           "of its Re and Im columns)"),
    BASIS_ENRICHMENT_OMEGA: ("rad/s", "hat-omega_j of each enrichment column, Eq. 41 (N_L, or 0; a gyroscopic "
                                      "structure: Eq. 20 for each of a DBF's Re and Im columns)"),
    BASIS_DBF_K: ("N/m", "DBF stiffness k_j of each constraint, 0 for other enrichment (N_L, or 0)"),
    BASIS_FLEXIBILITY_CAPTURED: ("1", "the a-priori indicator: static flexibility at each constraint that the basis "
                                      "captures, B_j K_r^-1 B_j^T / g_j^T K^-1 g_j (N_L; 1 with static modes, NaN "
                                      "if K is singular)"),
    BASIS_FLEXIBILITY_EXACT: ("m/N", "the full model's static flexibility g_j^T K^-1 g_j at each constraint (N_L)"),
    # V^T M V = I makes V's columns kg^-1/2 (M in kg), so q = V^T M u is m kg^1/2 and B = G^T V is kg^-1/2:
    # w = B q in m (red team: the outputs said q in 1 and B in m, so q looked like a displacement)
    REDUCED_Q: ("m kg^(1/2)", "reduced coordinates q of the M-orthonormal basis, u = V q (nt x r; width 0 for a "
                              "full-order run); the columns of a repeated frequency (a round tube's y-z pairs) are "
                              "a mix of its modes that round-off chooses, other on another rank count: read "
                              "their sum of squares, or the probes, not one of them"),
    REDUCED_QDOT: ("m kg^(1/2)/s", "reduced velocities q' (nt x r; width 0 for a full-order run)"),
    REDUCED_M: ("1", "reduced mass V^T M V (r x r; I to round-off)"),
    REDUCED_K: ("1/s^2", "reduced stiffness V^T K V (r x r)"),
    REDUCED_D: ("1/s", "reduced damping C_r (r x r)"),
    REDUCED_B: ("kg^(-1/2)", "the basis at the constraint DOFs, B = G^T V: w = B q (N_L x r; 2 N_L x r, rows y_j, "
                             "z_j, on a beam of two planes)"),
    SNAPSHOT_TIME: ("s", "snapshot times (S)"),
    SNAPSHOT_X: ("m or 1", "field points: node x on a beam (twice each, y then z, on a beam of two planes), or DOF index "
                    "(F)"),
    SNAPSHOT_W: ("m", "total displacement at the field points (S x F)"),
    "snapshots/displacement": ("m", "the snapshots as displacement vectors at the nodes, one dataset (nodes x 3) "
                                    "a snapshot, for the XDMF file beside the output"),
    "snapshots/points": ("m", "node coordinates (nodes x 3): x along a beam; DOF i at (i, 0, 0) without a node map"),
    "snapshots/node": ("1", "the node of each field point (F)"),
    "snapshots/polyline": ("1", "a beam's elements as node pairs, for the XDMF file"),
    "snapshots/cells": ("1", "a matrix model's cells ([structure] cells: node indices, E x k in XDMF's order), for the "
                             "XDMF file; absent without them (the XDMF file then shows points)"),
    "snapshots/component": ("1", "the direction of each field point: 0 = x, 1 = y, 2 = z (F)"),
}

# The statistics' errors of a long reduced run (accuracy.StatisticsEstimate, docs/accuracy.md):
# per estimated statistic, these datasets (N_L each, the statistic's unit).
_ESTIMATED_UNITS = {"impact_rate": "1/s", "contact_fraction": "1", "force_rms": "N", "displacement_rms": "m",
                    "work_rate": "W"}
_ERROR_PARTS = {
    "": "its estimated error: the {0}_sampling_ci95 + |{0}_model| + {0}_window_reduced_ci95 + "
        "{0}_window_rich_ci95",
    "_sampling_ci95": "95 % confidence half-width of the run's own {0} over the whole run (batch means of the "
                      "samples; NaN with fewer than 20)",
    "_model": "the model error: the richer model's {0} minus the run's, both over the statistics window",
    "_window_reduced": "the run's {0} over the statistics window (from the samples)",
    "_window_reduced_ci95": "95 % confidence half-width of {0}_window_reduced (batch means)",
    "_window_rich": "the richer model's {0} over the statistics window (from the samples)",
    "_window_rich_ci95": "95 % confidence half-width of {0}_window_rich (batch means)",
}
for _name, _unit in _ESTIMATED_UNITS.items():
    for _suffix, _meaning in _ERROR_PARTS.items():
        DATASETS[f"{STATISTICS_ERROR}/{_name}{_suffix}"] = (
            _unit, _meaning.format(_name) + " (N_L; long reduced runs only" +
            (", supports of two directions only)" if _name == "work_rate" else ")"))

# Earlier names still read (outputs of dbf_hpc before the enrichment strategies).
LEGACY = {BASIS_ENRICHMENT_OMEGA: "basis/dbf_omega"}


def read(f, name: str):
    """A dataset of an open output by its current name, or by the name an older version wrote."""
    if name in f:
        return f[name]
    return f[LEGACY[name]] if name in LEGACY and LEGACY[name] in f else f[name]


def reference() -> str:
    """docs/outputs.md: every dataset of a run's output and of a sweep summary, with its unit
    (`python -m dbf_hpc.layout > docs/outputs.md`; a test checks the file is up to date)."""
    from .stats import DESCRIPTIONS_2D as DESCRIPTIONS, STATISTICS, STATISTICS_2D, UNITS_2D as UNITS

    lines = ["# Outputs: the reference", "",
             "Generated from `dbf_hpc/layout.py` (`python -m dbf_hpc.layout > docs/outputs.md`). One HDF5 file a "
             "run, written as `OUT.h5.partial` while the run goes and renamed to `OUT.h5` when complete (a crash "
             "leaves the `.partial`, never a file that looks finished; a successful rerun replaces the output). "
             "Every dataset carries `unit` and `description` attributes. Shapes: nt samples, N_L constraints, "
             "P probes, r basis vectors, F field points, S snapshots.", "",
             "| dataset | unit | meaning |", "|---|---|---|"]
    lines += [f"| `{name}` | {unit} | {meaning} |" for name, (unit, meaning) in DATASETS.items()]
    lines += [f"| `{CONSTRAINT_STATS}/{name}` | {UNITS[name]} | {DESCRIPTIONS[name]} (N_L) |" for name in STATISTICS]
    lines += [f"| `{CONSTRAINT_STATS}/{name}` | {UNITS[name]} | {DESCRIPTIONS[name]} (N_L) |"
              for name in STATISTICS_2D if name not in STATISTICS]
    lines += ["", "Root attributes: `scene` (the scene file's text), `scene_effective` (JSON: every value the "
              "run used, the `--set` items and defaults included), `scene_path`, `method` (`rom` or `full`), "
              "`basis_enrichment`, `basis_complex_modes` (a gyroscopic structure: the complex modes, two real "
              "columns each), `basis_mass_orthonormality_defect` (1, max |V^T M V - I| of the projection) and "
              "`basis_mode_coupling_defect` (1, the largest mode-mode entry of V^T K V over sqrt(K_ii K_jj)): the "
              "reduced model uses M_r = I and a diagonal mode block when they are at most 1e-8; above, the basis is "
              "turned within its span so that these hold exactly, the same Galerkin model, and "
              "`basis_turned_in_span` is true: docs/design.md), "
              "`reduced_form` (a gyroscopic structure: `second_order` or `state_space`, `[basis] "
              "gyroscopic_form`; in the state-space form `reduced/q` and `reduced/qdot` are the states eta and "
              "eta', `reduced/M` is Psi^T A Psi, `reduced/K` is B_r of eta' = -B_r eta + ..., `reduced/D` is zero "
              "and `reduced/B` is the displacement part at the constraints; docs/design.md), `field_kind` "
              "(`beam`, `nodes` or `dofs`), `field_cells`, `field_cell_nodes`, `field_cell_count` and "
              "`field_cells_sha256` (with `[structure] cells`: the XDMF cell type, the nodes of a cell, the number "
              "of cells and the sha256 of the cells file; the "
              "run identity leaves the cells out, as they change no number, and `--resume` computes an output "
              "whose cells differ again), `dbf_hpc_version`, `petsc_version`, "
              "`slepc_version`, `mpi_ranks`, `solver_stats` and `wall_times` (JSON), `initial_state`, "
              "`run_identity` (JSON: a sha256 of each part of what the run was asked and built: scene, files, "
              "basis, options, ranks, method, version; `dbf-hpc run --resume` on a finished output with the same "
              "identity computes nothing again), `warnings` (every `dbf-hpc: warning` line the run printed before its "
              "output was complete, and those it prints of its result once complete (a stop never reached, impacts a "
              "fixed step does not resolve ...) and of the command's PETSc options no solver read, one a line, empty for none: `dbf-hpc info` shows them, and "
              "`--resume` of the finished output prints them again), and `complete = true` once the run finished. A run of a scene with constraints also has its "
              "a-posteriori error estimate (docs/accuracy.md; not with `[basis] estimate = false`): "
              "`estimated_error` (1, the largest |w - w_rich| at any constraint over the largest |w_rich| at any "
              "constraint (each kind of DOF over its own where a node map puts constraints on rotations and "
              "translations: the worse), against max(2N, N + N_L) modes, and also 1.5 times those where that differs by 2 % or more (the larger "
              "difference; a reduced run), or a 4 times shorter step (a full-order run: "
              "its step's error, not its mesh's), NaN if it could not be made), `estimated_error_window` (s, "
              "the estimate holds over [0, it]) and `estimated_error_note` (how it was made, or why not). A long "
              "reduced run (t_end over 5 times `estimated_error_window`) also has its statistics' errors: the "
              "`constraints/stats_error` datasets above, `estimated_statistics_window` (s, the statistics window "
              "[0, it] of the model error) and `estimated_statistics_note`.", "",
             "On a beam of two planes (`[structure] planes = 2`, 2-D laws such as `circular`) the statistics are per "
             "support and radial: `displacement_*` of |u|, `force_*` of |F|, contact (and so the impacts) where "
             "|u| > clearance, `impact_power_mean` of |F_n v_n|, and `work_rate` = <|F_n| |v_t|> (W), the normal "
             "work rate of code_aster (Archard wear), with `work_rate_ci95` (its batch-means 95 % confidence "
             "half-width; NaN with fewer than 20 samples), and `wear_volume` = K_w T work_rate "
             "(m^3) with `wear_volume_ci95` for a constraint's `wear_coefficient` K_w (NaN without one) (runs; the "
             "Python API's Result has the work rate only).", "",
             "With snapshots, `OUT.xdmf` beside the output describes `snapshots/points` and "
             "`snapshots/displacement/NNNNNN` as a time series that ParaView (Xdmf3 reader) and meshio open: on "
             "the cells of `snapshots/cells` when the scene gives `[structure] cells` (a solid's hexahedra), a "
             "beam's polyline, else points. `dbf-hpc basis --xdmf SHAPES.xdmf` writes the basis vectors alike "
             "into `SHAPES.h5` (`shapes/points`, `shapes/cells`, `shapes/shape/NNNNNN`, `shapes/omega`, the "
             "same `field_cells` attributes). The shapes are the basis's own vectors: those of a repeated frequency "
             "(a round tube's y-z pair, a square bar's bending pair) are drawn as the eigensolver returned them, any "
             "orthonormal mix of its eigenspace (set by round-off, another on another rank count), not turned to the "
             "axes; `shapes/repeated` gives per shape the number of the first shape of its repeated frequency (0: "
             "simple mode or enrichment column; not written for complex modes), each such grid of the XDMF file "
             "carries an Information `note` saying so, and `basis --xdmf` prints a line per repeated frequency.", "",
             "A sweep summary (`dbf-hpc sweep`) holds a row per case: `cases/parameters/<section.key>` (NaN or "
             "null where a listed case leaves the base scene's value), `cases/status`, `cases/error`, "
             "`cases/wall_time` (s), `cases/warnings` (what `dbf-hpc run` warns of the case, that its result may be "
             "wrong, in its order: a coarse fixed step or sample interval, more snapshots than samples, estimate "
             "windows or DBF keys the case does not read, what the model's matrix files, form and basis "
             "draw (a flexibility captured below 99 %, a lowest frequency that suggests a unit slip ...), a forcing "
             "above the basis, a loose atol (of a clearance, or of the whole motion of a structure without one in "
             "reach) (all these but the forcing the sweep prints once for the cases they "
             "concern, before they run), a stop never reached, "
             "Hunt-Crossley damping beyond its range, impacts a fixed step does not resolve; one line each, empty "
             "for none), `cases/stats/<statistic>` (case x constraint, units as above) and "
             "`cases/probe_peak` (m, case x probe); with supports of two directions also `work_rate`, "
             "`work_rate_ci95`, `wear_volume` and `wear_volume_ci95` among the statistics.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    print(reference(), end="")
