"""The `dbf-hpc` command: a thin front end of run.py, sweep.py, report.py, plots.py and cache.py.

    dbf-hpc run SCENE.toml [-o OUT.h5] [-q] [--resume] [--method rom|full] [--set section.key=value ...] [PETSc options]
    dbf-hpc sweep SWEEP.toml [-q] [--set ...]
    dbf-hpc info OUT.h5 | dbf-hpc plot OUT.h5 [-d DIR] [--window T0:T1]
    dbf-hpc modes SCENE.toml [--set section.key=value ...] [PETSc options]
    dbf-hpc basis SCENE.toml [--no-cache] [--xdmf SHAPES.xdmf] [--set ...] [PETSc options]
    dbf-hpc stiffness SCENE.toml [--constraint J] [--k K1,K2,...] [-o SWEEP.csv] [--plot FIG.png]
    dbf-hpc cache list|clear [--dir DIR] [--older-than DAYS]

PETSc/SLEPc options (single dash, e.g. -modes_eps_tol 1e-12 -log_view) go after the scene; each
solver reads its own prefix (modes_, dbf_, static_, buckling_, rom_, full_). Exit status: 0 on success, 1 on an
error the user can act on (one line on stderr), 2 on a malformed command line (one line on stderr),
70 on an internal error.

Every rank runs the same command, and every rank takes the same path: the subcommands are
collective on COMM_WORLD (what only rank 0 writes or prints, it decides for all), and an error on
one rank is every rank's one line (main, _finish)."""
from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import time

from . import __version__

# seconds the other ranks wait before they exit on a malformed command line, which only rank 0 says
USAGE_ERROR_GRACE_S = 2.0
# the first line of a `stiffness -o` table (a rerun replaces only such a file)
STIFFNESS_HEADER = "# k [N/m],omega [rad/s],f [Hz]"

_PETSC_OPTION = re.compile(r"^-[A-Za-z]\w+")
_NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


def split_petsc_options(argv: list[str]) -> tuple[list[str], list[str]]:
    """(our arguments, PETSc options). A PETSc option is a single-dash word longer than one letter;
    a token after it that is not an option (or is a number) is its value."""
    ours, petsc = [], []
    expecting_value = False
    for token in argv:
        if _PETSC_OPTION.match(token) and not _NUMBER.match(token):
            petsc.append(token)
            expecting_value = True
        elif expecting_value and (not token.startswith("-") or _NUMBER.match(token)):
            petsc.append(token)
            expecting_value = False
        else:
            ours.append(token)
            expecting_value = False
    return ours, petsc


def _launcher_rank() -> str:
    """This process's rank as the MPI launcher set it ("0" without a launcher): the command line is
    parsed before MPI starts."""
    return next((os.environ[v] for v in ("OMPI_COMM_WORLD_RANK", "PMIX_RANK", "PMI_RANK") if v in os.environ), "0")


class _Parser(argparse.ArgumentParser):
    """argparse with the package's error contract: a malformed command line is one line on stderr,
    `dbf-hpc: error: ...` naming the command and where its usage is, exit status 2; no usage block.
    It runs before MPI starts, so the launcher's rank variable decides who prints (rank 0 only: also
    --help and --version)."""

    commands: dict = {}   # build_parser: the subcommands' parsers by name

    def error(self, message):
        if _launcher_rank() == "0":
            command = self.prog.split(" ", 1)[1] if " " in self.prog else None
            where = f"{command}: " if command else ""
            print(f"dbf-hpc: error: {where}{message} (see {self.prog} --help)", file=sys.stderr, flush=True)
        else:   # a launcher that ends the job at the first non-zero exit (srun --kill-on-bad-exit, mpirun
            # without its grace period) could kill rank 0 before it said the line: rank 0 exits first
            time.sleep(USAGE_ERROR_GRACE_S)
        sys.exit(2)

    def _print_message(self, message, file=None):
        if _launcher_rank() == "0":
            super()._print_message(message, file)

    def parse_args(self, args=None, namespace=None):
        # argparse reports leftover words at the top level; the subcommand's parser names itself
        args, extra = self.parse_known_args(args, namespace)
        if extra:
            self.commands.get(getattr(args, "command", None), self).error(f"unrecognized arguments: {' '.join(extra)}")
        return args


def _named(give: str):
    """argparse's type for a path argument: the value as given, or a refusal naming the argument and
    what to give when it is empty or blank (red team: `run SCENE -o ""` wrote the scene's [output] file,
    `stiffness -o ""` and `basis --xdmf ""` wrote nothing, each in silence)."""
    def check(value: str) -> str:
        if not value.strip():
            raise argparse.ArgumentTypeError(f"an empty name ({value!r}): {give}")
        return value
    return check


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="dbf-hpc",
        description="Discontinuous basis functions (Brake & Segalman 2011) for structures with many "
                    "discrete nonlinear constraints, on PETSc/SLEPc. Run it under MPI: "
                    "mpirun -n 2 dbf-hpc modes jobs/paper_beam.toml",
        epilog="PETSc/SLEPc options go after the scene, e.g. -modes_eps_tol 1e-12 -log_view. "
               "Solver prefixes: modes_ (reference modes; -modes_trust_tol), dbf_ (spring-perturbed modes "
               "and DBF derivatives; dbf_shared_ on the ritz and shared paths, dbf_krylov_ on the shared path), "
               "static_ (static modes), buckling_ (a compressed or moving beam's buckling load), "
               "rom_ (the reduced model's TS and SNES, e.g. -rom_ts_arkimex_type 4), full_ (the full-order "
               "reference). The scene format: docs/scene.md.")
    parser.add_argument("--version", action="version", version=f"dbf-hpc {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    parser.commands = sub.choices    # filled as the subcommands are added
    def command(name, func, help, description):
        p = sub.add_parser(name, help=help, description=description)
        p.add_argument("scene", type=_named("give the scene file (TOML)"), help="scene file (TOML)")
        p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                       help="override a scene value, e.g. --set basis.modes=10 (repeatable)")
        p.set_defaults(func=func)
        return p

    run = command("run", _run, "run a scene: basis, reduced nonlinear dynamics, HDF5 output",
                  "Build (or reuse) the basis of modes and DBFs, integrate the reduced nonlinear model "
                  "with PETSc TS ARKIMEX, and write the HDF5 output (with --method full: the full-order "
                  "reference instead, same scene, same output layout).")
    run.add_argument("-o", "--output", metavar="OUT.h5", type=_named("give the output file, e.g. -o out.h5, or leave -o "
                                                                     "out for the scene's [output] file"),
                     help="output file (default: the scene's [output] file)")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    run.add_argument("--resume", action="store_true",
                     help="continue a killed run from its last checkpoint (OUT.h5.checkpoint); on an output "
                          "already finished for this scene and setup, compute nothing again")
    run.add_argument("--method", choices=("rom", "full"), default="rom",
                     help="rom: the reduced model (default); full: the full-order reference, the whole "
                          "finite-element model with generalized-alpha, one factorization and the contact "
                          "condensed on the constraint DOFs (options prefix full_)")
    sweep = sub.add_parser("sweep", help="a parameter study: many cases of one scene over the ranks",
                           description="Expand a sweep file (a base scene and axes or listed cases), build "
                                       "each distinct basis once, run the cases spread over the MPI ranks "
                                       "and write a summary HDF5. Rerunning resumes a killed sweep.")
    sweep.add_argument("sweep", metavar="SWEEP.toml", type=_named("give the sweep file (TOML)"))
    sweep.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    sweep.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                       help="override a value of the base scene for every case (repeatable); an axis of one "
                            "value, e.g. integrator.t_end, is replaced by a --set of the same name; another value "
                            "the sweep's cases set is refused")
    sweep.set_defaults(func=_sweep)
    info = sub.add_parser("info", help="summarize a run's (or a sweep's) HDF5 output",
                          description="Print what a run computed: scene, basis, solver statistics, "
                                      "and per constraint the extreme displacement and force. Also a "
                                      "sweep's summary (each case), and the OUT.h5.partial of a run that "
                                      "did not finish.")
    info.add_argument("output", metavar="OUT.h5", type=_named("give a run's output or a sweep's summary (HDF5)"))
    info.set_defaults(func=_info)
    plot = sub.add_parser("plot", help="the paper's figures for a run (or a sweep's), as PNG files",
                          description="Time histories, phase diagrams and forces at each constraint, "
                                      "probes, and beam snapshots (paper Figs. 4-13); on a beam of two "
                                      "planes also the supports' orbits. For a sweep's summary, the "
                                      "statistics against each varying parameter.")
    plot.add_argument("output", metavar="OUT.h5", type=_named("give a run's output or a sweep's summary (HDF5)"))
    plot.add_argument("-d", "--directory", default=".", type=_named("give the folder for the PNGs, e.g. -d figures, or "
                                                                    "leave -d out for the current one"),
                      help="where to write the PNGs (made if missing; default: .)")
    plot.add_argument("--window", metavar="T0:T1", help="time window of every figure (its samples and snapshots), "
                                                        "in s (either end may be left out, e.g. 9:)")
    plot.set_defaults(func=_plot)
    command("modes", _modes, "the structure's reference modes: a modal summary",
            "Assemble the scene's structure and print its reference modes (the [basis] modes count "
            "or max_frequency_hz).")
    basis = command("basis", _basis, "build (or reuse) the basis: modes and one DBF per constraint",
                    "Compute the reference modes and one discontinuous basis function per constraint, "
                    "in parallel over constraint groups, M-orthonormalize them, and cache the basis.")
    basis.add_argument("--no-cache", action="store_true", help="neither read nor write the basis cache")
    basis.add_argument("--xdmf", metavar="SHAPES.xdmf", type=_named("give a file name ending in .xdmf, e.g. --xdmf "
                                                                     "shapes.xdmf"), help="also write the basis vectors (modes, then the "
                       "enrichment columns) as shapes ParaView opens: SHAPES.xdmf beside SHAPES.h5")
    sweep = command("stiffness", _stiffness, "omega(k) of a constraint's spring-perturbed problem (Fig. 2)",
                    "The first frequency of the structure with a linear spring of stiffness k at one "
                    "constraint, over a range of k: the curve the DBF stiffness is chosen on (paper Fig. 2). "
                    "Marks the auto stiffness.")
    sweep.add_argument("--constraint", type=int, default=1, metavar="J",
                       help="constraint number (from 1); on a beam of two planes its y direction (the planes "
                            "have the same EI)")
    sweep.add_argument("--k", default="1e-4:1e6:41", metavar="LIST",
                       help="stiffnesses in N/m: a comma list, or START:STOP:COUNT (log-spaced); at most "
                            "10000; default 1e-4:1e6:41")
    sweep.add_argument("-o", "--output", metavar="CSV", type=_named("give the CSV file, e.g. -o stiffness.csv"),
                       help="write k, omega, f to this CSV file")
    sweep.add_argument("--plot", metavar="PNG", type=_named("give the PNG file, e.g. --plot fig2.png"),
                       help="write the Fig. 2 plot to this PNG file")
    cache = sub.add_parser("cache", help="list or clear the basis cache",
                           description="List the cached bases (what each holds, its size and age) or remove them. Only the "
                                      "files the cache wrote are touched; a temporary file is removed "
                                      "when untouched for 10 minutes (younger, another job may be "
                                      "writing it).")
    cache.add_argument("action", choices=("list", "clear"))
    cache.add_argument("--dir", default=None, help="the cache directory (default ~/.cache/dbf_hpc, as scenes use)")
    cache.add_argument("--older-than", type=float, metavar="DAYS", help="clear only bases unused for this many days")
    cache.set_defaults(func=_cache)
    return parser


def _cache(args) -> int:
    import datetime

    from mpi4py import MPI

    from . import cache

    from .errors import InputError

    if args.older_than is not None and not (args.older_than >= 0 and args.older_than != float("inf")):
        raise InputError(f"--older-than {args.older_than:g}: give a finite number of days >= 0")
    if args.dir is not None and not args.dir.strip():
        raise InputError("--dir '': give the cache directory (or leave --dir out for the default)")
    folder = os.path.expanduser(args.dir or cache.DEFAULT_DIR)
    if args.dir is not None and not os.path.isdir(folder):
        raise InputError(f"--dir {args.dir!r}: " + ("is not a directory" if os.path.exists(folder) else
                                                    "no such directory"))
    if MPI.COMM_WORLD.rank:
        return 0
    if args.action == "clear":
        removed, freed = cache.clear(folder, args.older_than)
        print(f"{folder}: removed {removed} file(s), {freed / 2**20:.3g} MiB")
        return 0
    found = cache.entries(folder)
    print(f"{folder}: {len(found)} file(s), {sum(e['size'] for e in found) / 2**20:.3g} MiB")
    for e in found:
        when = datetime.datetime.fromtimestamp(e["modified"]).strftime("%Y-%m-%d %H:%M")
        name = "state space Psi_v, Psi_w" if e.get("form") == "state_space" else "V"
        what = e.get("problem") or f"{name} {e['shape'][0]} x {e['shape'][1]}, dbf-hpc {e['version']}, {e['settings']}"
        print(f"  {os.path.basename(e['path'])}  {e['size'] / 2**20:8.3g} MiB  {when}  {what}")
    return 0


def _axial_speed(scene) -> str:
    """The scene's axial speed in words (a matrix model's G has no speed)."""
    return f"{scene['structure']['axial_speed']:g} m/s" if scene.is_beam else "of the given G"


def _run(args) -> int:
    from .run import run
    from .scene import load_scene_collective

    scene = load_scene_collective(args.scene, args.set)
    run(scene, args.output, progress=not args.quiet, resume=args.resume, method=args.method)
    return 0


def _info(args) -> int:
    from mpi4py import MPI

    from .report import describe

    lines = describe(args.output)    # every rank checks, so that a bad file is an error on all
    if MPI.COMM_WORLD.rank == 0:
        print("\n".join(lines))
    return 0


def _plot(args) -> int:
    from mpi4py import MPI

    from .errors import InputError, not_a_regular_file
    from .plots import parse_window, plot_run, plot_sweep
    from .report import open_output

    window = parse_window(args.window)
    f, complete = open_output(args.output)
    sweep = "cases" in f
    span = (float(f["time"][0]), float(f["time"][-1])) if not sweep and f["time"].size else None
    f.close()
    if window and sweep:   # new-user pass: it was ignored, the figures drawn whole without a word
        raise InputError(f"--window {args.window}: a sweep's summary has no time axis (its figures are against the "
                         f"swept parameters); leave --window out, or plot a case's own output (keep_outputs = true)")
    if window and span and (window[0] > span[1] or window[1] < span[0]):
        raise InputError(f"--window {args.window}: no samples there (the run spans {span[0]:g} to {span[1]:g} s)")
    if not (complete or sweep):
        raise InputError(f"{args.output!r}: the run did not finish (only its .partial file exists); "
                         f"rerun it, with --resume if it was checkpointed")
    problem = None
    if MPI.COMM_WORLD.rank == 0:
        try:
            os.makedirs(args.directory, exist_ok=True)
        except OSError as e:   # new-user pass: "-d run.h5" said "cannot be made: File exists"
            given = args.directory.rstrip(os.sep) or args.directory   # (red team: "-d run.h5/", "File exists")
            if os.path.lexists(given) and not os.path.isdir(given):
                kind = not_a_regular_file(given) or "is a file"   # (a named pipe is no file either)
                problem = (f"plot directory {args.directory!r} {kind}, not a directory: give -d a folder "
                           f"(made if missing)")
            else:
                problem = f"plot directory {args.directory!r} cannot be made: {e.strerror or e}"
    problem = MPI.COMM_WORLD.bcast(problem, root=0)
    if problem:
        raise InputError(problem)
    if MPI.COMM_WORLD.rank == 0:
        try:
            written = (plot_sweep if sweep else plot_run)(args.output, args.directory, window=window)
        except (KeyError, RuntimeError, OSError) as e:   # a dataset missing or unreadable (as `info` says it)
            if isinstance(e, OSError) and e.errno is not None:   # a figure that cannot be written: not the file
                raise
            # h5py's OSError without errno: HDF5 could not read a dataset's data ("Can't read data (addr
            # overflow ...)": a damaged data address), which was an internal error (red team)
            raise InputError(f"{args.output!r} is damaged ({str(e).splitlines()[0]})") from None
        for path in written:
            print(f"wrote {path}")
    return 0


def _sweep(args) -> int:
    from .sweep import run_sweep

    from .errors import SolverError

    result = run_sweep(args.sweep, progress=not args.quiet, overrides=args.set)
    if result["failed"]:   # the summary holds them; a batch job should not read as a success
        # the first one's cause in the line (red team: a full disk was only in the summary)
        raise SolverError(f"{result['failed']} of {result['cases']} cases failed ({result['first_failure']}): their "
                          f"errors are in {result['output']} (dbf-hpc info); rerunning the sweep retries them")
    return 0


def _modes(args) -> int:
    from petsc4py import PETSc

    from .gyroscopic import gyroscopic_modes
    from .modes import reference_modes
    from .scene import load_scene_collective

    scene = load_scene_collective(args.scene, args.set)
    comm = PETSc.COMM_WORLD
    start = time.perf_counter()
    basis = scene["basis"]
    with scene.full_order_model(comm) as fom:
        ops = fom.operators
        assembled = time.perf_counter()
        gyroscopic = ops.G is not None
        solve = gyroscopic_modes if gyroscopic else reference_modes
        modes = solve(ops, count=basis["modes"], max_frequency_hz=basis["max_frequency_hz"], whole="extend")
        solved = time.perf_counter()
        say = PETSc.Sys.Print
        what = (f"beam, {ops.mesh.elements} Hermite-cubic elements" if ops.mesh is not None
                else f"matrices from {scene['structure']['stiffness']}")
        say(f"dbf-hpc {__version__}: {scene.path} on {comm.getSize()} rank(s)")
        say(f"structure: {what}, {ops.size} free DOFs, nonzeros K {int(ops.K.getInfo()['nz_used'])}")
        say(f"reference modes{' (gyroscopic, complex)' if gyroscopic else ''}: {modes.count}"
            + (f" below {basis['max_frequency_hz']:g} Hz" if basis["max_frequency_hz"] else "")
            + (f" ({basis['modes']} asked: the repeated frequency at the cut taken whole; `run` refuses "
               f"{basis['modes']})" if basis["modes"] and modes.count > basis["modes"] else ""))
        say(f"{'mode':>6} {'f [Hz]':>14} {'omega [rad/s]':>16}")
        for i, (f, w) in enumerate(zip(modes.frequency_hz, modes.omega)):
            say(f"{i + 1:>6} {f:>14.8g} {w:>16.8g}")
        if gyroscopic:
            for j in modes.unstable:
                say(f"UNSTABLE at axial speed {_axial_speed(scene)}: {modes.describe(j)}")
            if modes.unstable:
                from .gyroscopic import critical_speed_note
                note = critical_speed_note(ops)
                if note:
                    say(f"critical speed:{note}")
            if not modes.unstable and fom.damping.kind != "modal" and fom.damping_matrix() is not None:
                _say_damped_stability(fom, modes.count or 8, scene, say)
        say(f"time: assembly {assembled - start:.3f} s, eigensolve {solved - assembled:.3f} s")
        modes.destroy()
    return 0


def _say_damped_stability(fom, count: int, scene, say) -> None:
    """The gyroscopic modes listed are undamped; `run` also refuses a structure its damping makes
    unstable (gyroscopic.check_damped_stable): say it here too. Collective."""
    from .errors import InputError
    from .gyroscopic import check_damped_stable

    try:
        check_damped_stable(fom.operators, fom.velocity_matrix(), count, _axial_speed(scene))
        say("with its damping: no mode grows")
    except InputError as e:
        say(f"UNSTABLE {str(e).split('unstable ', 1)[-1]}")


def _basis(args) -> int:
    from mpi4py import MPI
    from petsc4py import PETSc

    from .modes import counters
    from .reductor import Reductor
    from .scene import load_scene_collective

    scene = load_scene_collective(args.scene, args.set)
    if args.xdmf:
        _check_shapes_path(args.xdmf, scene)
    comm = PETSc.COMM_WORLD
    say = PETSc.Sys.Print
    with scene.full_order_model(comm) as fom, \
            Reductor(fom, scene.basis_settings(), None if args.no_cache else scene.cache_dir(),
                     warn_basis=False) as reductor:   # _print_basis says them
        labels = fom.constraints.component_labels
        start, solves = time.perf_counter(), counters["eigen_solves"]
        basis = reductor.basis()
        elapsed = time.perf_counter() - start
        strategy = basis.settings.strategy
        say(f"dbf-hpc {__version__}: {scene.path} on {comm.getSize()} rank(s), {fom.size} DOFs")
        enriched = (f" + {basis.constraint_omega().size} {strategy.column_name}s" if strategy.column_name
                    else " (no enrichment)")
        columns = (f" (Re and Im: {basis.size} real columns)" if basis.complex_modes else "")
        normal = "M-orthonormal"
        if getattr(basis, "form", "") == "state_space":   # A = diag(M, K) (state_space.py), as `run` says
            columns, normal = f" (Re and Im of the state vectors: {basis.size} real states)", "A-orthonormal"
        say(f"basis: {basis.complex_modes or basis.mode_count} {'complex' if basis.complex_modes else 'reference'} "
            f"modes{enriched}{columns}, {normal} "
            f"({elapsed:.3f} s, {comm.tompi4py().allreduce(counters['eigen_solves'] - solves, op=MPI.MAX)} "
            f"eigen-solves on the busiest rank, cache {basis.stats.get('cache')})")
        _print_basis(say, basis, labels, fom.constraints.dimension, fom.operators.rigid_modes,
                     scene.fastest_forcing_hz())
        if args.xdmf:
            _write_shapes(args.xdmf, fom, reductor, basis)
    return 0


def _check_shapes_path(path: str, scene) -> None:
    """basis --xdmf SHAPES.xdmf: refused before any work unless SHAPES.xdmf and SHAPES.h5 may be
    written (new, or dbf-hpc's own files)."""
    from . import xdmf
    from .errors import InputError
    from .output import check_output_path, check_replaced_name, is_dbf_shapes

    if not path.endswith(".xdmf"):
        raise InputError(f"--xdmf {path!r}: give a name ending in .xdmf (its data go to the .h5 of the same name)")
    check_output_path(os.path.splitext(path)[0] + ".h5", scene.inputs(), replaceable=is_dbf_shapes,
                      kind="the mode shapes of an earlier `dbf-hpc basis --xdmf`")
    check_output_path(path, scene.inputs(), replaceable=xdmf.is_dbf_xdmf)
    for target in (os.path.splitext(path)[0] + ".h5", path):   # both written through temporary files
        check_replaced_name(target, what="--xdmf")


def _is_stiffness_table(path: str) -> bool:
    """Whether `path` is a table an earlier `stiffness -o` wrote (its first line)."""
    try:
        with open(path, encoding="ascii", errors="replace") as f:
            return f.readline().startswith(STIFFNESS_HEADER)
    except OSError:
        return False


def _shape_notes(fom, basis) -> tuple:
    """(shapes/repeated, {shape index: note}, lines to print) of a real basis's shapes: the modes of a
    repeated frequency are drawn as the eigensolver returned them, any orthonormal mix of their
    eigenspace (a direction set by round-off, which another rank count may turn). (None, {}, []) for
    complex modes (their columns are Re and Im of each). Not collective."""
    import numpy as np

    from .modes import repeated_groups

    if basis.complex_modes:
        return None, {}, []
    N = basis.mode_count
    groups = np.concatenate([repeated_groups(basis.omega ** 2, fom.operators.rigid_modes),
                             np.zeros(basis.size - N, dtype=np.int64)])
    notes, lines = {}, []
    for first in np.unique(groups[groups > 0]):
        members = np.flatnonzero(groups == first)
        what = (f"shapes {members[0] + 1} to {members[-1] + 1}: one repeated frequency, "
                f"{basis.omega[members[0]] / (2 * np.pi):.6g} Hz, drawn in the directions the eigensolver returned "
                f"(any mix of them, set by round-off: another rank count may turn them)")
        lines.append(what)
        notes.update({int(j): what for j in members})
    return groups, notes, lines


def _write_shapes(path: str, fom, reductor, basis) -> None:
    """The basis vectors at the field points as an XDMF time series (step i: basis vector i + 1) and
    its HDF5 file (_check_shapes_path checked both). The modes of a repeated frequency are the basis's
    own, as the eigensolver returned them, not turned to the axes: they are the vectors a run's
    reduced q multiplies, and a symmetric structure's eigenspace may have no direction a node map
    prefers. They are marked (shapes/repeated, an XDMF note on each, a printed line). Both files are
    written to temporary files and renamed into place together: a write that fails (a full disk)
    leaves neither a partial file nor a new .h5 beside an old .xdmf, and is one DbfError on every
    rank; temporary files a killed earlier run of this host left are removed first
    (errors.remove_dead_temporaries). Collective (rank 0 writes)."""
    import h5py
    import numpy as np
    from petsc4py import PETSc

    from . import xdmf
    from .errors import WRITE_ERRORS, DbfError, park, remove_dead_temporaries, temporary_path, write_failure
    from .run import cells_attrs

    h5 = os.path.splitext(path)[0] + ".h5"
    values = reductor.field_values()
    world = PETSc.COMM_WORLD.tompi4py()
    groups, notes, lines = _shape_notes(fom, basis)
    error = None
    if world.rank == 0:
        # Red team: a full disk at the .h5 was "internal error (RuntimeError)" from h5py, then a
        # segfault as the failed file was freed (serial), with the .h5.tmp file left behind.
        # and a SIGKILL while it wrote left SHAPES.h5.tmp-<pid>: the next run removes those of dead writers
        for target in (h5, path):
            remove_dead_temporaries(target)
        tmp_h5, tmp_xdmf = temporary_path(h5), temporary_path(path)
        field = fom.operators.field_map()
        geometry = field.geometry()
        f = None
        try:
            f = h5py.File(tmp_h5, "w")
            for name, data in {**xdmf.geometry_datasets(geometry, "shapes"),
                               **xdmf.node_vectors(geometry, values.T, "shapes", "shape")}.items():
                f.create_dataset(name, data=data)
            f["shapes/omega"] = np.concatenate([basis.omega, basis.enrichment_omega])
            if groups is not None:
                f["shapes/repeated"] = groups
                f["shapes/repeated"].attrs["description"] = (
                    "per shape, the number (from 1) of the first shape of its repeated frequency, 0 for a simple "
                    "mode or an enrichment column: the shapes of one repeated frequency are any orthonormal mix "
                    "of its eigenspace, as the eigensolver returned them")
            f.attrs["dbf_hpc_version"] = __version__
            f.attrs.update(cells_attrs(field))
            f.close()
            f = None
            xdmf.write(tmp_xdmf, h5, "shapes", geometry[0], geometry[1].shape[0],
                       np.arange(1, values.shape[1] + 1), "shape", cells=geometry[4],
                       cell_type=geometry[5], notes=notes)
            os.replace(tmp_h5, h5)
            os.replace(tmp_xdmf, path)
        except (DbfError, *WRITE_ERRORS) as e:
            park(f)   # an HDF5 file whose flush failed crashes when freed (errors.PARKED)
            error = f"cannot write {path} and {h5}: " + (str(e).split(": ", 1)[-1] if isinstance(e, DbfError)
                                                          else write_failure(e))
            for tmp in (tmp_h5, tmp_xdmf):
                if os.path.exists(tmp):
                    os.remove(tmp)
    error = world.bcast(error, root=0)
    if error:
        raise DbfError(error)
    if world.rank == 0:
        print(f"wrote {path} and {h5} ({values.shape[1]} shapes)")
        for line in lines:
            print(line)


def _print_basis(say, basis, labels, dimension: int = 1, rigid_modes: int = 0, forcing_hz: float = 0.0) -> None:
    """The basis command's table, then what `dbf-hpc run` warns of the same basis, in its order
    (run.basis_warnings, and run.forcing_warning of the scene's fastest forcing, `forcing_hz`; red team:
    the unit-slip and forcing lines were missing here). Collective (rank 0 prints)."""
    from petsc4py import PETSc

    from .errors import warn
    from .run import basis_warnings, forcing_warning

    import numpy as np

    # a gyroscopic basis has Re and Im columns of each complex mode (Re alone where Im is dependent): one row per
    # complex mode, from the modes solved (np.unique of the columns' frequencies printed a pair of bit-equal
    # frequencies, a round shaft at rest, as one row under a header of N complex modes)
    omega = np.asarray(basis.stats["complex_omega"]) if basis.complex_modes else basis.omega
    say(f"{'mode':>6} {'f [Hz]':>14} {'omega [rad/s]':>16}")
    for i, w in enumerate(omega):
        say(f"{i + 1:>6} {w / (2 * 3.141592653589793):>14.8g} {w:>16.8g}")
    hat = basis.constraint_omega()
    if basis.enrichment == "static" and basis.enrichment_count:
        say(f"{'static':>6} {'constraint':>14} {'hat-omega [rad/s]':>18}")
        for j in range(hat.size):
            say(f"{j + 1:>6} {labels[j]:>14} {hat[j]:>18.8g}")
    elif basis.enrichment == "dbf" and basis.enrichment_count:
        say(f"{'DBF':>6} {'constraint':>14} {'k_j [N/m]':>12} {'branch':>7} {'hat-omega [rad/s]':>18}")
        for j in range(hat.size):
            say(f"{j + 1:>6} {labels[j]:>14} {basis.dbf_k[j]:>12.5g} {basis.dbf_branch[j]:>7d} "
                f"{hat[j]:>18.8g}")
    flex = basis.flexibility_captured
    if flex.size:
        say("static flexibility captured (f_basis / f_exact, the a-priori indicator; 1 = the basis holds K^-1 g_j):")
        say(f"{'j':>6} {'where':>14} {'captured':>10} {'f_exact (m/N)':>14}")
        for j in range(flex.size):
            say(f"{j + 1:>6} {labels[j]:>14} {flex[j]:>10.6f} {basis.flexibility_exact[j]:>14.6g}")
    for warning in [*basis_warnings(basis, labels, rigid_modes, dimension), forcing_warning(forcing_hz, basis.omega)]:
        if warning:
            warn(warning, PETSc.COMM_WORLD)
    name = basis.settings.strategy.column_name
    for key, what in (("time_modes", "modes"), ("time_enrichment", f"{name}s" if name else None),
                      ("time_orthogonalization", "orthogonalization")):
        if key in basis.stats and what:
            say(f"time {what}: {basis.stats[key]:.3f} s")


# The most stiffnesses `dbf-hpc stiffness` sweeps: each is an eigen-solve (10 ms on the paper's beam, 30 ms on
# the 2-D tube), and Fig. 2 needs a few dozen. Red team: --k 1e-4:1e6:100000000 ran for what would have been
# eleven days, with no word.
MAX_STIFFNESSES = 10000


def parse_stiffnesses(text: str):
    import numpy as np

    from .errors import InputError

    try:
        if ":" in text:
            start, stop, count = text.split(":")
            ends = np.array([float(start), float(stop)])
            if not np.all(np.isfinite(ends) & (ends > 0)):   # before log10 (numpy would warn first)
                raise InputError(f"--k {text!r}: stiffnesses must be positive and finite")
            if int(count) > MAX_STIFFNESSES:   # before logspace allocates them
                raise InputError(f"--k {text!r}: {int(count)} stiffnesses, more than {MAX_STIFFNESSES}: each is an "
                                 f"eigen-solve and the paper's Fig. 2 needs a few dozen; give at most "
                                 f"{MAX_STIFFNESSES}")
            values = np.logspace(np.log10(ends[0]), np.log10(ends[1]), int(count))
        else:
            values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise InputError(f"--k {text!r}: expected a comma list or START:STOP:COUNT") from None
    if values.size == 0 or not np.all(np.isfinite(values) & (values > 0)):
        raise InputError(f"--k {text!r}: stiffnesses must be positive and finite")
    if values.size > MAX_STIFFNESSES:
        raise InputError(f"--k: {values.size} stiffnesses, more than {MAX_STIFFNESSES}: give at most {MAX_STIFFNESSES}")
    return values


def _stiffness(args) -> int:
    import numpy as np
    from petsc4py import PETSc

    from .errors import InputError
    from .output import check_output_path, check_replaced_name
    from .scene import load_scene_collective

    scene = load_scene_collective(args.scene, args.set)
    if not 1 <= args.constraint <= len(scene.constraints):
        raise InputError(f"--constraint {args.constraint}: the scene has {len(scene.constraints)} constraint(s)")
    ks = parse_stiffnesses(args.k)
    from .plots import is_dbf_png
    for path, own, suffix in ((args.output, _is_stiffness_table, ""), (args.plot, is_dbf_png, ".png")):
        if path:
            check_output_path(path, scene.inputs(), replaceable=own)
            check_replaced_name(path, suffix)
    basis = scene["basis"]
    with scene.full_order_model(PETSc.COMM_WORLD) as fom:
        ops = fom.operators
        # the constraint's own row: flat_rows holds a two-plane beam's y and z rows constraint-major, so
        # its index J - 1 was another constraint's (red team: --constraint 11 swept constraint 6 under
        # constraint 11's label). Both planes have the same EI: the y row's curve is the z row's.
        row = int(fom.constraints.rows[args.constraint - 1][0])
        label = fom.constraints.component_labels[(args.constraint - 1) * fom.constraints.dimension]
        if ops.G is not None:   # complex modes (gyroscopic_basis.py)
            from . import gyroscopic_basis as gb

            modes = gb.stable_modes(ops, count=basis["modes"], max_frequency_hz=basis["max_frequency_hz"])
            try:
                branch, free, pinned, k_auto = gb.transition(ops, row, modes)
            finally:
                modes.destroy()
            omega_free, mu = np.zeros(branch), pinned**2
            omega_free[branch - 1] = free
            omega = gb.stiffness_sweep(ops, row, ks, branch)
        else:
            branch, omega_free, mu, k_auto, omega = _real_sweep(ops, row, basis, ks, args.constraint)
    say = PETSc.Sys.Print
    say(f"omega_{branch}(k) with a spring at {label}: from {omega_free[branch - 1]:.8g} rad/s (no spring) "
        f"to {np.sqrt(mu):.8g} rad/s (pinned); auto stiffness {k_auto:.6g} N/m")
    say(f"{'k [N/m]':>14} {'omega [rad/s]':>16} {'f [Hz]':>14}")
    for k, w in zip(ks, omega):
        say(f"{k:>14.6g} {w:>16.10g} {w / (2 * np.pi):>14.8g}")
    if PETSc.COMM_WORLD.getRank() == 0:
        if args.output:
            _write_atomically(args.output, lambda f: np.savetxt(
                f, np.column_stack([ks, omega, omega / (2 * np.pi)]), delimiter=",",
                header=f"{STIFFNESS_HEADER[2:]}   (spring at {label}; auto k = {k_auto:.6g} N/m)"))
            print(f"wrote {args.output}")
        if args.plot:
            from .plots import plot_stiffness_sweep

            plot_stiffness_sweep(args.plot, ks, omega, k_auto, label, omega_free[branch - 1], np.sqrt(mu))
            print(f"wrote {args.plot}")
    return 0


def _real_sweep(ops, row: int, basis, ks, constraint: int) -> tuple:
    """(branch, omega of the reference modes, mu, k_auto, omega(k)) of a structure without G (dbf.py)."""
    import numpy as np

    from .dbf import (auto_stiffness, branch_of, cluster_participation, participation, pinned_eigenvalue,
                      stiffness_sweep)
    from .errors import InputError
    from .modes import reference_modes

    modes = reference_modes(ops, count=basis["modes"], max_frequency_hz=basis["max_frequency_hz"], whole="refuse")
    part = participation(modes, np.array([row]))[0]
    omega_free = modes.omega
    modes.destroy()
    lam_free = np.where(np.arange(part.size) < ops.rigid_modes, 0.0, omega_free ** 2)   # as dbf.dbf_source
    branch = branch_of(part, lam_free)
    if branch == 0:
        raise InputError(f"constraint {constraint} does not move in any reference mode")
    mu = pinned_eigenvalue(ops, row, branch)
    k_auto = auto_stiffness(mu, omega_free[branch - 1] ** 2, cluster_participation(part, lam_free))
    return branch, omega_free, mu, k_auto, stiffness_sweep(ops, row, ks, branch)


def _write_atomically(path: str, write) -> None:
    from .errors import replacing

    with replacing(path) as tmp, open(tmp, "w") as f:
        write(f)


def _finish(comm, failure: str | None) -> int:
    """The end of every run, on every rank: agree on the outcome, then exit alike.

    All ranks meet in a non-blocking barrier on `comm`, a communicator of its own (a duplicate of
    COMM_WORLD that nothing else uses: a rank waiting in another barrier never meets this one). A rank
    that succeeded waits as long as it takes (rank 0 may still be writing). A rank that failed waits
    10 s: if the others do not arrive, they are stuck in a collective call this rank will never make,
    so it prints its error and aborts the job. When all arrive, the first failing rank prints its one
    line and every rank exits 1. A termination signal meanwhile does not change the outcome (red
    team: one during a failed rank's 10 s took the command's handler, whose line replaced the error
    with "stopped ... before the integration began; nothing was written"): a rank that succeeded
    and is signalled waits 10 s more for the others, then aborts the job as a failed one does.
    """
    from .errors import one_line, termination_signals

    signalled, previous = [], {}
    try:
        for signum in termination_signals():
            previous[signum] = signal.signal(signum, lambda number, frame: signalled.append(time.monotonic()))
    except ValueError:  # not the main thread
        pass
    try:
        request = comm.Ibarrier()
        deadline = time.monotonic() + 10.0
        while not request.Test():
            now = time.monotonic()
            if (failure and now > deadline) or (signalled and now > signalled[0] + 10.0):
                cause = failure or "stopped by a termination signal while the other ranks had not ended"
                print(f"dbf-hpc: error: (rank {comm.rank}) {one_line(cause)}", file=sys.stderr, flush=True)
                _abort(comm, 1)
            time.sleep(0.005)
        failures = comm.allgather(failure)
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)
    first = next((i for i, f in enumerate(failures) if f), None)
    if first is None:
        return 0
    if comm.rank == first:
        print(f"dbf-hpc: error: {one_line(failure)}", file=sys.stderr, flush=True)
    return 1


def _warn_unused(comm, said=()) -> None:
    """One warning per PETSc option of the command (petsctools.command_option_names) no solver read, but
    those the command has said already (`said`: `dbf-hpc run` says them itself and stores them in its
    output, run.unused_option_lines). Collective."""
    from .errors import warn
    from .petsctools import command_option_names, unused_option_warning, unused_options

    for name in unused_options(command_option_names(), comm):
        message = unused_option_warning(name)
        if message not in said:
            warn(message, comm)


TERMINATED = ("stopped by a termination signal before the integration began; nothing was written: rerun to start "
              "again (the basis cache keeps what was finished)")
# A sweep stopped before its cases ran: the records of an earlier run of it stay (red team: it said
# "nothing was written" beside them)
TERMINATED_SWEEP = ("stopped by a termination signal before this sweep's cases began; the cases recorded before are "
                    "kept: rerun the same command to go on (the basis cache keeps what was finished)")
_COMMAND = None   # the command main runs (the line _terminated prints)
# A communicator of its own for the ranks signalled outside an integration (_terminated; made in main)
_SIGNALLED = None
_STOPPING = False   # _terminated is under way on this rank (several ranks: it ends in an abort)


def _terminated(signum, frame):
    """SIGTERM outside an integration (a batch system's time limit during the basis, say): stop with
    one line instead of dying silently. On one rank, errors.Interrupted. On several, the exception
    would leave this rank alone at an arbitrary point of collective work (red team: SIGTERM to rank 1
    alone during a gyroscopic basis raised in its eigensolve, whose cleanup, a collective MUMPS
    destroy, then waited for ever while rank 0 waited in its next collective call: the job hung). So
    the ranks stop where they are: they meet in a non-blocking barrier on a communicator of their own,
    as cli._finish does; when every rank was signalled (a batch system's limit), rank 0 prints the line,
    else after 10 s this rank prints it with its number; then the job aborts. A rank that mpirun
    signals as it ends the job after another rank's error is killed within those 10 s, silently.
    Nothing is written before the integration but the basis cache (a temporary file, then a rename)."""
    from .errors import TERMINATION, Interrupted

    global _STOPPING
    if TERMINATION.finished:   # the output is complete on every rank: the command ends at once (red team:
        return                 # it said "nothing was written", exit 1, and on 2 ranks aborted after 10 s)
    world = _SIGNALLED
    line = TERMINATED_SWEEP if _COMMAND == "sweep" else TERMINATED
    if world is None or world.size == 1:
        raise Interrupted(line)
    # a second signal while this rank waits below (a batch system signals mpirun, which passes it on, and
    # the ranks; Ctrl-C pressed again) would start a second barrier inside the first, which the other
    # ranks' one signal never meets: 10 s more and the job ended as if they had not been signalled (red team)
    if _STOPPING:
        return
    _STOPPING = True
    # the job ends here whatever the others do (or mpirun, ending it, kills this rank): rank 0's output
    # lock goes now, where no `finally` will run (red team: OUT.h5.lock was left beside the output);
    # another rank removes rank 0's just before it aborts the job (_abort), not while rank 0 may go on
    _release_locks(others=False)
    request = world.Ibarrier()
    deadline = time.monotonic() + 10.0
    while not request.Test():
        if time.monotonic() > deadline:
            print(f"dbf-hpc: error: (rank {world.rank}) {line}", file=sys.stderr, flush=True)
            _abort(world, 1)
        time.sleep(0.005)
    if world.rank == 0:
        print(f"dbf-hpc: error: {line}", file=sys.stderr, flush=True)
    world.Barrier()   # the line before the abort
    _abort(world, 1)


def _release_locks(others: bool = True) -> None:
    """Remove the output locks this process holds (output.HELD; rank 0's), and with `others` those
    rank 0 holds (OutputLock.expect): before an abort, which runs no `finally`. Called from the signal
    handler (_terminated), it imports nothing: a SIGTERM while the command still imported dbf_hpc.output
    (its first seconds, under load) had the handler's import find the module half made, and the
    ImportError, raised into that import, ended the job as an "internal error (ImportError)" (red
    team). A module not yet imported holds no lock."""
    release = getattr(sys.modules.get(f"{__package__}.output"), "release_held_locks", None)
    if release is None:
        return
    try:
        release(others)
    except Exception:   # the abort must happen whatever the file system says
        pass


def _abort(comm, code: int) -> None:
    """comm.Abort(code), this process's output locks removed first."""
    _release_locks()
    comm.Abort(code)


def _quiet_write_failures(unraisable) -> None:
    """sys.unraisablehook: after a write failed (a full disk), h5py frees each of its objects with the
    same error, printed as "Exception ignored" with a traceback (thousands, measured). The failure
    itself is reported once, as the command's error line; anything else goes to the default hook."""
    if not _is_write_failure(unraisable.exc_value):
        sys.__unraisablehook__(unraisable)


def _quiet_write_failures_printed(kind, value, tb) -> None:
    """sys.excepthook: Cython prints the same errors of h5py's deallocations through it first."""
    if not _is_write_failure(value):
        sys.__excepthook__(kind, value, tb)


def _is_write_failure(exc) -> bool:
    return isinstance(exc, RuntimeError) and "write failed" in str(exc)


def main(argv=None) -> int:
    program = argv is None   # the program's own command line, not a call from Python (command_options)
    argv = list(sys.argv[1:] if argv is None else argv)
    sys.unraisablehook, sys.excepthook = _quiet_write_failures, _quiet_write_failures_printed
    ours, petsc_options = split_petsc_options(argv)
    args = build_parser().parse_args(ours)

    from . import _petsc

    at_start = _petsc.init(_petsc.startup_options(petsc_options))   # the solvers' go in per command
    # `dbf-hpc info OUT.h5 | head` ends quietly, as other commands do, not in PETSc's signal handler
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    from mpi4py import MPI
    from petsc4py import PETSc

    from .errors import TERMINATION, DbfError, one_line, petsc_failure, recording, termination_signals
    from .petsctools import command_options

    comm = MPI.COMM_WORLD
    # _finish's own communicator: its barrier on COMM_WORLD met a rank still waiting in one of the
    # library's (errors.wait_for_rank0) after rank 0 failed alone, and the job hung (red team)
    ending = comm.Dup()
    global _SIGNALLED, _COMMAND
    _COMMAND = args.command
    if _SIGNALLED is None:   # once a process (main runs many times in the tests)
        _SIGNALLED = comm.Dup()
    TERMINATION.finished = False
    for signum in termination_signals():   # SIGTERM, and Ctrl-C; integrations and sweeps install their own
        signal.signal(signum, _terminated)
    try:
        with command_options(petsc_options, at_start, keep=program), recording() as said:
            args.func(args)
            failure = None
            _warn_unused(PETSc.COMM_WORLD, said)
    except DbfError as e:
        failure = str(e)
    except PETSc.Error as e:  # most often an option PETSc refused: one line, the ranks agree as on a DbfError
        if os.environ.get("DBF_HPC_DEBUG"):
            raise
        given = [t for t in petsc_options if t.startswith("-")]
        failure = petsc_failure(e) + (f"; check the PETSc options given ({' '.join(given)})" if given else "")
    except Exception as e:  # a bug: say it in one line and end every rank
        if os.environ.get("DBF_HPC_DEBUG"):
            raise
        origin = getattr(e, "dbf_hpc_origin", None)
        if comm.size > 1 and origin is not None and origin != comm.rank:
            # a copy of rank `origin`'s exception (errors.decided_on_rank0, agreed): that rank prints its
            # line and aborts the job; this one says it only if that has not happened within 10 s
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                time.sleep(0.05)
        print(f"dbf-hpc: internal error ({type(e).__name__}) on rank {comm.rank}: {one_line(e)}. Set DBF_HPC_DEBUG=1 "
              f"for a traceback.",
              file=sys.stderr, flush=True)
        if comm.size > 1:
            _abort(comm, 70)
        ending.Free()
        return 70
    code = _finish(ending, failure)
    ending.Free()   # collective; main runs many times in one process (the tests)
    from .errors import PARKED

    if comm.allreduce(len(PARKED), op=MPI.SUM):
        _exit_without_teardown(comm, code)
    return code


def _exit_without_teardown(comm, code: int) -> None:
    """After a failed HDF5 write (errors.park), leave without freeing h5py's objects, which would
    crash in HDF5 1.10. MPI_Finalize is skipped too: the MPI build of HDF5 closes its files then
    (and crashed there, measured). Every rank meets in a barrier, then exits with the code."""
    sys.stdout.flush()
    sys.stderr.flush()
    comm.Barrier()
    os._exit(code)


if __name__ == "__main__":
    sys.exit(main())
