"""The dbf-hpc command as users run it: under mpirun -n 2, one clear line and a non-zero exit on
bad input, never a traceback. These tests start their own mpirun (serial pass only)."""
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from conftest import tmpfs_disk
from dbf_hpc import __version__ as dbf_hpc_version

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")
pytestmark = pytest.mark.launcher


def mpi_env() -> dict:
    """Python's copy of the environment (without the variables this process's own MPI_Init set at C
    level: with them, a nested mpirun exits 1 silently), with mpirun's own notices off so that what
    is left on stderr is dbf-hpc's, and 2 ranks allowed on fewer cores."""
    return {**os.environ, "OMPI_MCA_orte_execute_quiet": "1", "OMPI_MCA_rmaps_base_oversubscribe": "1"}


def mpirun_script(script, *args, ranks=2, timeout=300):
    """A test's Python script under mpirun, this checkout first on the path: the finished process and
    the dbf-hpc lines of its stderr."""
    env = {**mpi_env(), "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(["mpirun", "-n", str(ranks), sys.executable, str(script), *map(str, args)],
                         capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env)
    return out, [line for line in out.stderr.splitlines() if line.startswith("dbf-hpc")]


def dbf_hpc(*args, ranks=2, timeout=120):
    cmd = ["mpirun", "-n", str(ranks), sys.executable, "-m", "dbf_hpc.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=mpi_env())


def dbf_hpc_alone(*args, timeout=120):
    """`dbf-hpc ARGS` as one process without mpirun, as the README runs the commands that read files
    (info, plot, cache): under `mpirun -n 1` mpirun's own start-up was most of such a call (1 to 2 s,
    about thirty calls). Tests still run them under mpirun -n 2 where the ranks are what they check
    (test_a_named_pipe_..., test_full_order_run_on_two_ranks_writes_the_common_layout)."""
    cmd = [sys.executable, "-m", "dbf_hpc.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=mpi_env())


def test_a_malformed_command_line_is_said_under_a_launcher_that_kills_at_the_first_bad_exit():
    # Only rank 0 says a usage error (it runs before MPI starts). Under a launcher that ends the job at the
    # first non-zero exit (mpirun without its grace period, srun --kill-on-bad-exit) rank 1's immediate exit
    # killed rank 0 before it printed, in about 1 of 25 tries: rank 1 now exits after it.
    for _ in range(8):
        cmd = ["mpirun", "--mca", "odls_base_sigkill_timeout", "0", "-n", "2", sys.executable, "-m", "dbf_hpc.cli",
               "run", "--no-such-flag", "x.toml"]
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT, env=mpi_env())
        lines = [line for line in out.stderr.splitlines() if line.strip()]
        assert out.returncode == 2 and len(lines) == 1, out.stderr
        assert lines[0].startswith("dbf-hpc: error: run: unrecognized arguments: --no-such-flag"), out.stderr


def test_help_and_version_print_once_under_mpirun():
    out = dbf_hpc("--help")
    assert out.returncode == 0 and out.stdout.count("usage: dbf-hpc") == 1, out.stdout   # rank 0 only
    assert "modes" in out.stdout and "basis" in out.stdout and "stiffness" in out.stdout
    out = dbf_hpc("--version")
    assert out.returncode == 0 and out.stdout.splitlines() == [f"dbf-hpc {dbf_hpc_version}"], out.stdout
    package = subprocess.run([sys.executable, "-m", "dbf_hpc", "--version"], capture_output=True, text=True,
                             timeout=60, cwd=ROOT, env=mpi_env())        # `python -m dbf_hpc` is dbf-hpc too
    assert package.returncode == 0 and package.stdout == out.stdout, package.stderr


def test_the_help_of_info_and_plot_names_the_sweep_summaries_and_partial_runs_they_read():
    # README: info reads "a run (or a sweep, or a .partial run)", plot draws "the paper's figures, or a
    # sweep's"; their --help spoke of runs only (red team)
    from dbf_hpc.cli import build_parser

    parser = build_parser()
    info, plot = (" ".join(parser.commands[name].format_help().split()) for name in ("info", "plot"))
    assert "sweep's summary" in info and ".partial" in info, info
    assert "sweep's summary" in plot and "orbits" in plot, plot


def test_the_readme_options_table_and_the_help_name_every_solver_prefix():
    # New-user pass: the README's table of options prefixes ("each solver under its prefix (table
    # below)") lacked buckling_, which --help and the "was not used" warning name.
    from dbf_hpc._petsc import SOLVER_PREFIXES
    from dbf_hpc.cli import build_parser

    readme = open(os.path.join(ROOT, "README.md")).read()
    table = set(re.findall(r"^\| `(\w+_)` \|", readme, re.M))
    helptext = " ".join(build_parser().format_help().split())
    for prefix in SOLVER_PREFIXES:
        assert prefix in table, (prefix, sorted(table))
        assert f"{prefix} (" in helptext, (prefix, helptext)


def test_a_word_the_command_does_not_take_is_named_with_that_command():
    out = dbf_hpc("run", PAPER, "--bogus")
    assert out.returncode == 2 and out.stderr.strip() == (
        "dbf-hpc: error: run: unrecognized arguments: --bogus (see dbf-hpc run --help)"), out.stderr


@pytest.mark.parametrize("argv", [[], ["bogus"], ["run"], ["run", PAPER, "--method", "xyz"],
                                  ["cache", "clear", "--older-than", "abc"], ["plot"]])
def test_a_malformed_command_line_is_one_error_line_from_one_rank(argv):
    """argparse's own contract prints a usage block, on every rank; ours is one line, exit status 2."""
    out = dbf_hpc(*argv)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2, out.stderr
    assert len(lines) == 1 and lines[0].startswith("dbf-hpc: error: ") and "--help" in lines[0], out.stderr
    assert "usage" not in out.stdout + out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize("argv, named", [
    (["run", PAPER, "-o", ""], "run: argument -o/--output: an empty name (''): give the output file, e.g. -o out.h5, "
                               "or leave -o out for the scene's [output] file"),
    (["run", PAPER, "--resume", "-o", " "], "run: argument -o/--output: an empty name (' '): give the output file"),
    (["run", ""], "run: argument scene: an empty name (''): give the scene file (TOML)"),
    (["sweep", ""], "sweep: argument SWEEP.toml: an empty name (''): give the sweep file (TOML)"),
    (["info", ""], "info: argument OUT.h5: an empty name (''): give a run's output or a sweep's summary (HDF5)"),
    (["plot", "x.h5", "-d", ""], "plot: argument -d/--directory: an empty name (''): give the folder for the PNGs"),
    (["basis", PAPER, "--xdmf", ""], "basis: argument --xdmf: an empty name (''): give a file name ending in .xdmf"),
    (["stiffness", PAPER, "-o", ""], "stiffness: argument -o/--output: an empty name (''): give the CSV file"),
    (["stiffness", PAPER, "--plot", ""], "stiffness: argument --plot: an empty name (''): give the PNG file")])
def test_an_empty_path_argument_is_one_line_naming_it_and_what_to_give(argv, named, capsys):
    # Red team: `run SCENE -o ""` wrote the scene's [output] file, and `stiffness -o ""`, `--plot ""` and
    # `basis --xdmf ""` wrote nothing, all in silence; `plot -d ""` said "cannot be made: No such file"
    from dbf_hpc.cli import build_parser

    with pytest.raises(SystemExit) as ended:
        build_parser().parse_args(argv)
    lines = capsys.readouterr().err.splitlines()
    assert ended.value.code == 2 and len(lines) == 1 and lines[0].startswith(f"dbf-hpc: error: {named}"), lines


def test_run_with_an_empty_output_name_writes_nothing_on_two_ranks(tmp_path):
    scene = tmp_path / "scene.toml"
    scene.write_text(open(PAPER).read().replace('file = "paper_beam.h5"', 'file = "default.h5"'))
    out = dbf_hpc("run", str(scene), "-o", "", "--set", "basis.cache=off", "--set", "integrator.t_end=0.01")
    assert out.returncode == 2 and out.stderr.startswith("dbf-hpc: error: run: argument -o/--output: an empty name")
    assert len(out.stderr.splitlines()) == 1, out.stderr
    assert sorted(os.listdir(tmp_path)) == ["scene.toml"]


def test_the_error_line_of_a_message_quoting_a_name_with_a_line_break_is_one_line(capsys):
    # Red team: messages quote some file names as given ("cannot write NAME: ..."); a line break in the name
    # split the command's error line in two
    from mpi4py import MPI

    from dbf_hpc.cli import _finish

    comm = MPI.COMM_WORLD.Dup()
    try:
        assert _finish(comm, "cannot write new\nline.csv: No space left on device") == 1
    finally:
        comm.Free()
    assert capsys.readouterr().err == "dbf-hpc: error: cannot write new\\nline.csv: No space left on device\n"


# A command whose rank 0 fails alone while rank 1 waits for it in the library's barrier
# (errors.wait_for_rank0, as a run's integration and the tolerance mode's candidates do)
_RANK0_FAILS_ALONE = """
import sys
from dbf_hpc import cli

def fails_on_rank0(args):
    from mpi4py import MPI
    from dbf_hpc.errors import InputError
    from dbf_hpc.errors import wait_for_rank0
    if MPI.COMM_WORLD.rank == 0:
        raise InputError("rank 0 alone refused")
    wait_for_rank0(MPI.COMM_WORLD)
    MPI.COMM_WORLD.bcast(None, root=0)

cli._info = fails_on_rank0
sys.exit(cli.main(["info", "x.h5"]))
"""


def test_an_error_on_rank_0_alone_while_rank_1_waits_in_a_barrier_ends_the_job_with_its_line(tmp_path):
    # The command's end met rank 1's barrier in errors.wait_for_rank0 (both are barriers on COMM_WORLD),
    # then rank 0 waited in allgather and rank 1 in bcast: the job hung (red team). Now rank 0's
    # barrier is on a communicator of its own: it finds rank 1 absent, prints its line and aborts.
    script = tmp_path / "rank0_fails.py"
    script.write_text(_RANK0_FAILS_ALONE)
    out, lines = mpirun_script(script, timeout=120)
    assert out.returncode != 0 and lines == ["dbf-hpc: error: (rank 0) rank 0 alone refused"], out.stderr
    assert "Traceback" not in out.stderr


_RANK0_RAISES_AS_IT_DECIDES = """
import errno, sys
from mpi4py import MPI
from dbf_hpc import cli, run
from dbf_hpc.errors import SolverError

def output_path(*args):   # rank 0 alone decides the output path for every rank (errors.decided_on_rank0)
    assert MPI.COMM_WORLD.rank == 0
    raise {raised}

run.output_path = output_path
sys.exit(cli.main(["run", sys.argv[1], "-q", "-o", sys.argv[2], "--set", "basis.cache=off"]))
"""


@pytest.mark.parametrize("raised, line", [
    ('OSError(errno.EIO, "Input/output error")',
     "dbf-hpc: internal error (OSError) on rank 0: [Errno 5] Input/output error. Set DBF_HPC_DEBUG=1 for a traceback."),
    ('KeyError("complete")',
     "dbf-hpc: internal error (KeyError) on rank 0: 'complete'. Set DBF_HPC_DEBUG=1 for a traceback."),
    ('SolverError("rank 0 gave up")', "dbf-hpc: error: rank 0 gave up")], ids=["OSError", "KeyError", "SolverError"])
def test_any_exception_on_rank_0_as_it_decides_for_every_rank_ends_the_job_with_one_line(tmp_path, raised, line):
    # Red team: errors.decided_on_rank0 passed only an InputError on to the other ranks: anything else
    # raised on rank 0 left rank 1 in the broadcast (for ever from Python; the command's 10 s wait
    # ended the job, a SolverError with "(rank 0)", the line of a rank that failed alone). Now every
    # rank raises it: a DbfError is the command's one line at once (exit 1), anything else rank 0's
    # internal error line, the job aborted (rank 1 stays quiet: its copy is rank 0's).
    script = tmp_path / "rank0_raises.py"
    script.write_text(_RANK0_RAISES_AS_IT_DECIDES.format(raised=raised))
    out, lines = mpirun_script(script, PAPER, tmp_path / "beam.h5", timeout=90)
    assert out.returncode != 0 and lines == [line], out.stderr
    assert "Traceback" not in out.stderr
    assert sorted(os.listdir(tmp_path)) == ["rank0_raises.py"], "nothing written"


def test_a_termination_signal_while_a_failed_rank_waits_for_the_others_keeps_its_error_line(tmp_path):
    # Red team: rank 0 failed alone and waited its 10 s for rank 1 (stuck in a collective call); a
    # SIGTERM then (a batch system's limit) took the command's handler, whose line "stopped by a
    # termination signal before the integration began; nothing was written" replaced the error. The
    # signal does not change the outcome: the error's line, and the job aborted.
    script = tmp_path / "rank0_fails.py"
    script.write_text(_RANK0_FAILS_ALONE.replace(
        '        raise InputError("rank 0 alone refused")',
        '        import os, signal, threading\n'
        '        threading.Timer(2.0, os.kill, (os.getpid(), signal.SIGTERM)).start()   # in the 10 s wait\n'
        '        raise InputError("rank 0 alone refused")'))
    out, lines = mpirun_script(script, timeout=120)
    assert out.returncode != 0 and lines == ["dbf-hpc: error: (rank 0) rank 0 alone refused"], out.stderr
    assert "Traceback" not in out.stderr


_RANK1_TERMINATED_IN_EIGENSOLVE = """
import os, signal, sys
from mpi4py import MPI
from dbf_hpc import cli, gyroscopic

solve = gyroscopic._solve

def terminated_on_rank_1(*args, **kwargs):   # the signal lands in gyroscopic_modes, its PEP still alive
    solved = solve(*args, **kwargs)
    if MPI.COMM_WORLD.rank == 1:
        os.kill(os.getpid(), signal.SIGTERM)
    return solved

gyroscopic._solve = terminated_on_rank_1
sys.exit(cli.main(["run", sys.argv[1], "-q", "-o", sys.argv[2], "--set", 'basis.gyroscopic_form="state_space"',
                   "--set", "basis.cache=off", "--set", "integrator.t_end=0.01"]))
"""


def test_sigterm_to_rank_1_alone_in_a_collective_basis_ends_the_job_with_one_line(tmp_path):
    # Red team: SIGTERM to rank 1 alone while the pipe's gyroscopic basis was computed (the quadratic
    # eigensolve, every rank) raised there; its cleanup (the PEP's collective MUMPS destroy) waited for
    # rank 0, which had gone on to its next collective call: the job hung for ever. A termination
    # signal outside an integration on one of several ranks prints its line and aborts the job;
    # nothing is written (the output does not exist).
    script = tmp_path / "rank1_terminated.py"
    script.write_text(_RANK1_TERMINATED_IN_EIGENSOLVE)
    out_path = tmp_path / "pipe.h5"
    out, lines = mpirun_script(script, os.path.join(ROOT, "jobs", "pipe_conveying_fluid.toml"), out_path)
    assert out.returncode != 0 and lines == [
        "dbf-hpc: error: (rank 1) stopped by a termination signal before the integration began; nothing was written: "
        "rerun to start again (the basis cache keeps what was finished)"], out.stderr
    assert "Traceback" not in out.stderr
    assert not any(os.path.exists(f"{out_path}{tail}") for tail in ("", ".partial", ".checkpoint"))


_TERMINATED_IN_THE_BASIS = """
import os, signal, sys, threading, time
from mpi4py import MPI
from dbf_hpc import basis, cli

modes = basis.reference_modes
who = sys.argv[3]

def terminated(*args, **kwargs):   # the signal lands as the reference modes are done (collective work follows)
    found = modes(*args, **kwargs)
    rank = MPI.COMM_WORLD.rank
    if who == "rank 1" and rank == 1:
        os.kill(os.getpid(), signal.SIGTERM)
    if who == "both, rank 0 twice":   # mpirun passes the batch system's signal on, which also signals rank 0
        if rank == 0:   # its second while it waits for rank 1, whose one comes later
            threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGTERM)).start()
        else:
            time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGTERM)
    return found

basis.reference_modes = terminated
sys.exit(cli.main(["run", sys.argv[1], "-q", "-o", sys.argv[2], "--set", "basis.cache=off"]))
"""


@pytest.mark.parametrize("who", ["rank 1", "both, rank 0 twice"])
def test_a_termination_signal_before_the_integration_on_two_ranks_leaves_no_lock_and_one_line(tmp_path, who):
    # Red team: SIGTERM during the basis on 2 ranks ended in MPI_Abort, which runs no `finally`: OUT.h5.lock
    # stayed beside the output (rank 0, stuck in the collective eigensolve when rank 1 alone was signalled,
    # never got to remove it). And a second signal to rank 0 while it waited for the others started a
    # barrier inside the first: the job ended 10 s later with rank 0's line instead of the common one.
    script = tmp_path / "terminated.py"
    script.write_text(_TERMINATED_IN_THE_BASIS)
    out_path = tmp_path / "beam.h5"
    out, lines = mpirun_script(script, PAPER, out_path, who)
    prefix = "(rank 1) " if who == "rank 1" else ""
    assert out.returncode != 0 and lines == [
        f"dbf-hpc: error: {prefix}stopped by a termination signal before the integration began; nothing was "
        f"written: rerun to start again (the basis cache keeps what was finished)"], out.stderr
    assert "Traceback" not in out.stderr
    assert sorted(os.listdir(tmp_path)) == ["terminated.py"], "nothing written, and no lock left"



_TERMINATED_AS_RANK0_TAKES_THE_LOCK = """
import os, signal, sys
from mpi4py import MPI
from dbf_hpc import cli, run

decided = run.decided_on_rank0

def terminated(comm, decide, *args):   # rank 1 is signalled just as rank 0 takes the output's lock
    if getattr(decide, "__name__", "") == "acquire" and MPI.COMM_WORLD.rank == 1:
        os.kill(os.getpid(), signal.SIGTERM)
    return decided(comm, decide, *args)

run.decided_on_rank0 = terminated
sys.exit(cli.main(["run", sys.argv[1], "-q", "-o", sys.argv[2], "--set", "basis.cache=off",
                   "--set", "integrator.t_end=0.01"]))
"""


def test_a_termination_signal_to_rank_1_as_rank_0_takes_the_output_lock_leaves_no_lock(tmp_path):
    # Red team: SIGTERM to rank 1 of `mpirun -n 2 dbf-hpc run` in its first seconds left OUT.h5.lock behind:
    # rank 1 learnt rank 0's lock only after rank 0 had taken it, so it stopped not knowing it, and rank 0,
    # blocked in the collective call that would have told it, was killed by mpirun before its own signal
    # handler could run. Every rank now knows the lock before rank 0 takes it, and removes it as it aborts.
    script = tmp_path / "terminated.py"
    script.write_text(_TERMINATED_AS_RANK0_TAKES_THE_LOCK)
    out_path = tmp_path / "beam.h5"
    out, lines = mpirun_script(script, PAPER, out_path)
    assert out.returncode != 0 and lines == [
        "dbf-hpc: error: (rank 1) stopped by a termination signal before the integration began; nothing was "
        "written: rerun to start again (the basis cache keeps what was finished)"], out.stderr
    assert "Traceback" not in out.stderr
    assert sorted(os.listdir(tmp_path)) == ["terminated.py"], "nothing written, and no lock left"


def test_a_termination_signal_while_the_command_still_imports_its_modules_is_no_internal_error(monkeypatch):
    # Red team: SIGTERM to rank 1 of `mpirun -n 2 dbf-hpc run` in its first seconds (under load: the
    # imports) ended the job with "internal error (ImportError) on rank 1: cannot import name
    # 'release_held_locks' from partially initialized module 'dbf_hpc.output'": the signal handler
    # (cli._terminated) imported it to remove the output locks while the command was importing that very
    # module, and the ImportError rose into the command. A module not yet made holds no lock: nothing to do.
    import types

    from dbf_hpc import cli

    half = types.ModuleType("dbf_hpc.output")   # what sys.modules holds while output.py runs its imports
    monkeypatch.setitem(sys.modules, "dbf_hpc.output", half)
    cli._release_locks()
    cli._release_locks(others=False)
    assert sys.modules["dbf_hpc.output"] is half

_TERMINATED_AT_THE_END = """
import os, signal, sys
from mpi4py import MPI
from dbf_hpc import cli, run, sweep

who, command = int(sys.argv[1]), sys.argv[2:]
module, name = (run, "_say_unsaid") if command[0] == "run" else (sweep, "_write_summary")
original = getattr(module, name)

def terminated(*args, **kwargs):   # run: the output is complete; sweep: the summary is being written
    if MPI.COMM_WORLD.rank == who:
        os.kill(os.getpid(), signal.SIGTERM)
    return original(*args, **kwargs)

setattr(module, name, terminated)
sys.exit(cli.main(command))
"""


@pytest.mark.parametrize("command,ranks,who", [("run", 1, 0), ("run", 2, 0), ("run", 2, 1), ("sweep", 2, 0)])
def test_a_termination_signal_after_the_output_is_complete_lets_the_command_end_as_it_would(tmp_path, command,
                                                                                              ranks, who):
    # Red team: a signal after the run's output was written (or while a sweep's summary was written) met
    # the command's own handler, which said "stopped ... before the integration began; nothing was
    # written" with exit 1 beside the finished output; on 2 ranks it waited 10 s and aborted the job
    # (two error lines; a sweep's summary half written). The output is the answer: the command ends as
    # it would have, exit 0, no error line.
    import h5py

    script = tmp_path / "late.py"
    script.write_text(_TERMINATED_AT_THE_END)
    out = tmp_path / "out.h5"
    if command == "run":
        args = ["run", PAPER, "-q", "-o", str(out), "--set", "integrator.t_end=0.2"]
    else:
        (tmp_path / "sweep.toml").write_text(f'scene = "{PAPER}"\noutput = "out.h5"\n[axes]\n'
                                             '"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [0.2]\n')
        args = ["sweep", str(tmp_path / "sweep.toml"), "-q"]
    done, _ = mpirun_script(script, who, *args, ranks=ranks)
    assert done.returncode == 0 and "error" not in done.stderr, done.stderr
    with h5py.File(out) as f:
        assert bool(f.attrs["complete"])
    assert not os.path.exists(f"{out}.lock") and not os.path.exists(f"{out}.partial")


def test_modes_of_the_paper_beam_are_the_euler_bernoulli_frequencies():
    out = dbf_hpc("modes", PAPER, "--set", "basis.modes=4", "-modes_eps_tol", "1e-12")
    assert out.returncode == 0, out.stderr
    rows = re.findall(r"^\s+(\d+)\s+([\d.e+-]+)\s+([\d.e+-]+)$", out.stdout, re.M)
    omega = np.array([float(r[2]) for r in rows])
    n = np.arange(1, 5)
    exact = np.sqrt(117e9 * 8.78e-16 / (11800 * 2.9e-7)) * (n * np.pi) ** 2
    assert len(rows) == 4 and np.allclose(omega, exact, rtol=1e-6)
    assert "on 2 rank(s)" in out.stdout


def test_modes_of_a_two_plane_tube_list_whole_pairs_and_say_a_cut_was_taken_whole():
    # 3 modes of a round tube end inside the second y-z pair: the summary lists both (the second in a
    # direction round-off sets, alone), and says 3 were asked and that `run` refuses them
    out = dbf_hpc("modes", os.path.join(ROOT, "jobs", "steam_generator_tube_2d.toml"), "--set", "basis.modes=3",
                  "--set", "structure.elements=40")
    assert out.returncode == 0, out.stderr
    assert "reference modes: 4 (3 asked: the repeated frequency at the cut taken whole; `run` refuses 3)" in out.stdout
    hz = np.array([float(r) for r in re.findall(r"^\s+\d+\s+([\d.e+-]+)\s+[\d.e+-]+$", out.stdout, re.M)])
    assert hz.size == 4 and np.allclose(hz[0::2], hz[1::2], rtol=1e-8), hz


def test_modes_of_a_gyroscopic_structure_say_when_its_damping_makes_one_grow(tmp_path):
    # The listed gyroscopic modes are undamped: a K held only by G (Kelvin-Tait-Chetaev) listed stable
    # modes while `run` refused the damped structure. `modes` says it too, with the growth rate that
    # the companion eigenvalues of the same system give (3.374 1/s: tests/test_gyroscopic.py).
    from conftest import write_rotor

    K, G = np.diag([-1e4, -1e4, 2e4]), np.array([[0.0, 300.0, 0.0], [-300.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    write_rotor(tmp_path, K, G, {f"r{alpha:g}.toml": f"[damping]\nrayleigh_alpha = {alpha}\n[basis]\nmodes = 3\n"
                                 for alpha in (20.0, 0.0)})
    out = dbf_hpc("modes", str(tmp_path / "r20.toml"))
    assert out.returncode == 0 and re.search(r"UNSTABLE with its damping .* growth rate 3\.374", out.stdout), out
    out = dbf_hpc("modes", str(tmp_path / "r0.toml"))
    assert out.returncode == 0 and "UNSTABLE" not in out.stdout, out


def test_modes_of_a_pipe_above_its_divergence_speed_name_the_critical_speed_pi_over_l_sqrt_ei_over_m_t():
    # The pipe conveying fluid at 200 m/s: mode 1 diverges; its critical speed is (pi / L) sqrt(EI / m_t) =
    # 156.153 m/s (L = 1.5 m, EI = 1925.36 N m^2, m_t = 0.34636 kg/m), which the listing now says.
    out = dbf_hpc("modes", os.path.join(ROOT, "jobs", "pipe_conveying_fluid.toml"), "--set",
                  "structure.axial_speed=200.0")
    exact = np.pi / 1.5 * np.sqrt(2e11 * 9.6268e-9 / 0.34636)
    speed = re.search(r"^critical speed: U_c = sqrt\(\(T \+ P_cr\) / m_t\) = ([\d.]+) m/s$", out.stdout, re.M)
    assert out.returncode == 0 and "UNSTABLE at axial speed 200 m/s: mode 1" in out.stdout, out
    assert speed and abs(float(speed.group(1)) / exact - 1) < 1e-5, out.stdout


def test_basis_is_cached_and_reused_without_eigen_solves(tmp_path):
    args = ("basis", PAPER, "--set", f"basis.cache={tmp_path}")
    first, second = dbf_hpc(*args), dbf_hpc(*args)
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    assert "cache stored" in first.stdout and "cache hit" in second.stdout
    assert "0 eigen-solves" in second.stdout
    k = re.search(r"x = 0.25 m\s+([\d.e+-]+)", first.stdout).group(1)
    assert 0.01 < float(k) < 1.0


def test_basis_of_a_state_space_scene_is_cached_and_says_it_is_a_orthonormal(tmp_path):
    # The state-space basis was not cached (every command rebuilt it), and `dbf-hpc basis` called its
    # state vectors "M-orthonormal" real columns: they are orthonormal in A = diag(M, K).
    pipe = os.path.join(ROOT, "jobs", "pipe_conveying_fluid.toml")
    args = ("basis", pipe, "--set", f"basis.cache={tmp_path}", "--set", "basis.gyroscopic_form=state_space")
    first, second = dbf_hpc(*args), dbf_hpc(*args)
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    assert "cache stored" in first.stdout and "cache hit" in second.stdout and "0 eigen-solves" in second.stdout
    for out in (first, second):
        assert "(Re and Im of the state vectors: 12 real states), A-orthonormal" in out.stdout, out.stdout
        assert "M-orthonormal" not in out.stdout, out.stdout


def test_a_solver_option_that_found_a_cached_basis_is_not_called_unused(tmp_path):
    # The option is part of the cache key, so the hit used it; red team: the hit warned that
    # -modes_eps_tol was "not used: a misspelling, or a solver this command does not run".
    args = ("basis", PAPER, "--set", f"basis.cache={tmp_path}", "-modes_eps_tol", "1e-11")
    first, second = dbf_hpc(*args), dbf_hpc(*args)
    assert first.returncode == 0 and second.returncode == 0, first.stderr + second.stderr
    assert "cache stored" in first.stdout and "cache hit" in second.stdout
    assert "was not used" not in first.stderr + second.stderr, first.stderr + second.stderr


def test_stiffness_sweep_writes_data_and_figure(tmp_path):
    csv, png = tmp_path / "sweep.csv", tmp_path / "fig2.png"
    out = dbf_hpc("stiffness", PAPER, "--k", "1e-3,1e-1,1e3", "-o", str(csv), "--plot", str(png))
    assert out.returncode == 0, out.stderr
    data = np.loadtxt(csv, delimiter=",")
    assert data.shape == (3, 3) and np.all(np.diff(data[:, 1]) > 0)
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_stiffness_of_a_two_plane_tube_sweeps_the_constraint_asked_for():
    # The two planes have the same EI: constraint 11 (x = 8.25 m) of the two-plane tube has the
    # one-plane tube's pinned frequency and auto stiffness there. It swept constraint 6 (x = 4.5 m)
    # under constraint 11's label (red team: the index ran over the y and z rows of every constraint).
    heads = []
    for scene in ("steam_generator_tube_2d.toml", "steam_generator_tube.toml"):
        out = dbf_hpc("stiffness", os.path.join(ROOT, "jobs", scene), "--constraint", "11", "--k", "1e2,1e6",
                      "--set", "structure.elements=100")
        assert out.returncode == 0, out.stderr
        heads.append(out.stdout.splitlines()[0])
    assert "spring at x = 8.25 m (y):" in heads[0] and "spring at x = 8.25 m:" in heads[1], heads
    pinned = [re.search(r"to (\S+) rad/s \(pinned\); auto stiffness (\S+) N/m", head).groups() for head in heads]
    np.testing.assert_allclose(np.array(pinned[0], dtype=float), np.array(pinned[1], dtype=float), rtol=1e-6)


@pytest.mark.parametrize("args,message", [
    (("modes", "jobs/missing.toml"), "cannot read scene"),
    (("modes", PAPER, "--set", "basis.mode=3"), "unknown key 'mode' in [basis]"),
    (("modes", PAPER, "--set", "structure.E=-5"), "E must be positive"),
    (("stiffness", PAPER, "--constraint", "3"), "the scene has 1 constraint"),
    (("stiffness", PAPER, "-o", "/nonexistent/dir/sweep.csv"), "does not exist"),
    (("stiffness", PAPER, "--k", "0:1e6:5"), "must be positive and finite"),   # not six numpy warnings first
    (("stiffness", PAPER, "--k", "1,inf"), "must be positive and finite"),
    # red team: 1e8 eigen-solves ran for what would have been eleven days
    (("stiffness", PAPER, "--k", "1e-4:1e6:100000000"), "100000000 stiffnesses, more than 10000"),
])
def test_bad_input_is_one_line_and_a_non_zero_exit(args, message):
    out = dbf_hpc(*args)
    assert out.returncode != 0
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("dbf-hpc: error:") and message in lines[0], out.stderr
    assert "Traceback" not in out.stderr + out.stdout


def test_readme_main_job_runs_the_paper_beam_on_two_ranks(tmp_path):
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "paper.h5"), "--set", f"basis.cache={tmp_path}")
    assert out.returncode == 0, out.stderr
    assert "done:" in out.stdout and (tmp_path / "paper.h5").exists()
    info = dbf_hpc_alone("info", str(tmp_path / "paper.h5"))
    assert info.returncode == 0 and "constraint 1 at 0.25" in info.stdout
    figures = tmp_path / "figs"     # made by plot (README's own command runs on a fresh clone)
    plot = dbf_hpc_alone("plot", str(tmp_path / "paper.h5"), "-d", str(figures))
    assert plot.returncode == 0, plot.stderr
    for name in ("time_histories.png", "phase.png", "forces.png", "probes.png", "snapshots.png"):
        assert (figures / name).read_bytes()[:4] == b"\x89PNG"


def test_the_slurm_script_requeued_after_its_run_finished_computes_nothing_again(tmp_path):
    # README: "--resume on a run that had already finished (a requeued batch job) computes nothing
    # again"; the shipped batch script ran without --resume, so a requeued job (and one resubmitted
    # after the time limit's checkpoint) started from t = 0 (red team). Run it as Slurm would: from
    # the submit folder, with stand-ins for scripts/setup, the venv and srun (2 ranks under mpirun).
    submit = tmp_path / "submit"
    (submit / "scripts").mkdir(parents=True)
    (submit / ".venv" / "bin").mkdir(parents=True)
    (submit / "bin").mkdir()
    (submit / "scripts" / "setup").write_text("#!/bin/sh\nexit 0\n")
    (submit / ".venv" / "bin" / "activate").write_text("")
    (submit / "bin" / "srun").write_text(f'#!/bin/sh\n[ "$1" = dbf-hpc ] || exit 99\nshift\n'
                                         f'exec mpirun -n 2 {sys.executable} -m dbf_hpc.cli "$@"\n')
    for stub in ("scripts/setup", "bin/srun"):
        os.chmod(submit / stub, 0o755)
    out = tmp_path / "run.h5"
    env = {**mpi_env(), "SLURM_SUBMIT_DIR": str(submit), "PATH": f"{submit / 'bin'}:{os.environ['PATH']}"}
    argv = ["bash", os.path.join(ROOT, "jobs", "slurm", "dbf-hpc.sbatch"), PAPER, "-o", str(out),
            "--set", "integrator.t_end=0.3", "--set", f"basis.cache={tmp_path}"]
    first = subprocess.run(argv, capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert first.returncode == 0 and out.exists(), first.stderr
    before = os.stat(out)
    again = subprocess.run(argv, capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    after = os.stat(out)
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns), \
        "the requeued job computed the finished run again"


def test_contact_jacobian_passes_petsc_jacobian_test(tmp_path):
    # A smooth law with a dashpot, so that PETSc's finite differences are themselves accurate (across
    # the kink of a deadband, or near the edge of a Hertz contact, they are not).
    text = open(PAPER).read()
    law = 'law = "cubic"\nk = 10.0\nk3 = 1e6\ndamping = "linear"\nc = 0.01\n\n'
    text = text[:text.index("law =")] + law + text[text.index("[basis]"):]
    scene = tmp_path / "cubic.toml"
    scene.write_text(text)
    out = dbf_hpc("run", str(scene), "-o", str(tmp_path / "j.h5"), "-q", "--set", "integrator.t_end=0.3",
                  "--set", f"basis.cache={tmp_path}", "-rom_snes_test_jacobian", ranks=1, timeout=300)
    assert out.returncode == 0, out.stderr
    ratios = [float(v) for v in re.findall(r"\|\|J - Jfd\|\|_F/\|\|J\|\|_F = ([\d.e+-]+)", out.stdout)]
    # finite differences of a stiff cubic carry ~1e-5 noise at worst; a wrong term gives 1e-2 or more
    assert len(ratios) > 10
    assert max(ratios) < 1e-4 and np.median(ratios) < 1e-5, (max(ratios), np.median(ratios))


def test_same_results_on_one_and_two_ranks(tmp_path):
    # Impacts amplify any difference (here the basis' round-off, 1e-10) exponentially (docs/design.md):
    # the runs must agree tightly until the first contact and statistically after it.
    import h5py

    paths = []
    for ranks in (1, 2):
        path = tmp_path / f"r{ranks}.h5"
        out = dbf_hpc("run", PAPER, "-o", str(path), "-q", "--set", "integrator.t_end=1.0",
                      "--set", "basis.cache=off", ranks=ranks)
        assert out.returncode == 0, out.stderr
        paths.append(path)
    with h5py.File(paths[0]) as a, h5py.File(paths[1]) as b:
        za, zb = a["constraints/displacement"][:, 0], b["constraints/displacement"][:, 0]
        first_contact = np.argmax(np.abs(za) >= 2.5e-3)
        assert first_contact > 100
        assert np.abs(za - zb)[:first_contact].max() < 1e-8 * np.abs(za).max()
        assert abs(np.abs(za).max() - np.abs(zb).max()) < 0.01 * 2.5e-3
        assert np.allclose(a["snapshots/w"][:2], b["snapshots/w"][:2], rtol=0, atol=1e-8 * np.abs(za).max())


@pytest.mark.parametrize("args,message", [
    (("run", PAPER, "-o", "/nonexistent/dir/out.h5"), "does not exist"),
    (("run", PAPER, "--set", "integrator.scheme=rk4"), "not an ARKIMEX type"),
    (("info", "/nonexistent.h5"), "does not exist"),
    (("run", PAPER, "--method", "full", "--set", "damping.zeta=0.02"), "modal damping"),
    (("run", PAPER, "--method", "full", "-full_ts_adapt_type", "basic"), "its own generalized-alpha loop"),
    (("run", PAPER, "--method", "full", "-full_alpha_radius", "1.5"), "lies in [0, 1]"),
    (("run", PAPER, "--method", "full", "-full_pc_type", "jacobi"), "is not exact"),
])
def test_bad_run_input_is_one_line(args, message):
    out = dbf_hpc(*args)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode != 0 and len(lines) == 1 and message in lines[0], out.stderr


@pytest.mark.parametrize("command", ["info", "plot", "run", "sweep"])
def test_a_named_pipe_given_to_a_command_is_one_line_saying_so_never_waited_on(tmp_path, command):
    # Red team: `info FIFO` and `plot FIFO` said "does not exist"; `run FIFO` and `sweep FIFO` (the scene, the
    # sweep file) waited for a writer for ever
    fifo = tmp_path / "given"
    os.mkfifo(fifo)
    out = dbf_hpc(command, str(fifo), timeout=60)
    said = (f"{str(fifo)!r} is a named pipe, not a dbf-hpc output" if command in ("info", "plot") else
            f"cannot read {'scene' if command == 'run' else 'sweep'} {str(fifo)!r}: a named pipe, not a regular file")
    assert out.returncode == 1 and out.stderr.splitlines() == [f"dbf-hpc: error: {said}" + (
        ": give a run's output or a sweep's summary" if command in ("info", "plot") else "")], out.stderr


def test_an_output_this_user_may_not_read_is_said_so_not_called_foreign_or_not_hdf5(tmp_path):
    # Red team (as user nobody): `info` on a run's output it may not read said "is not an HDF5 file", and a run
    # onto it "exists and is not a dbf-hpc output: remove it or choose another name", advice to remove
    # another user's good file
    import shutil
    import tempfile

    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to run as another user")
    shared = tempfile.mkdtemp(dir="/tmp")   # (pytest's folders are root's alone)
    try:
        os.chmod(shared, 0o777)
        out = os.path.join(shared, "theirs.h5")
        assert dbf_hpc("run", PAPER, "-o", out, *SHORT, ranks=1).returncode == 0
        os.chmod(out, 0o600)
        before = open(out, "rb").read()
        as_nobody = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-m", "dbf_hpc.cli"]
        for args, said in ((["info", out], f"{out!r} cannot be read: permission denied (ask its owner, or read it as "
                                            f"a user who may)"),
                           (["run", PAPER, "-o", out, *SHORT], f"output {out!r} exists and this user may not read it "
                                                               f"(permission denied), so whether dbf-hpc wrote it "
                                                               f"cannot be told: choose another name, or ask its owner")):
            done = subprocess.run(as_nobody + args, capture_output=True, text=True, timeout=120, cwd=ROOT, env=mpi_env())
            assert done.returncode == 1 and done.stderr.splitlines() == [f"dbf-hpc: error: {said}"], done.stderr
        assert open(out, "rb").read() == before and sorted(os.listdir(shared)) == ["theirs.h5", "theirs.xdmf"]
    finally:
        shutil.rmtree(shared)


def test_full_order_run_on_two_ranks_writes_the_common_layout(tmp_path):
    out = tmp_path / "full.h5"
    run = dbf_hpc("run", PAPER, "--method", "full", "-o", str(out), "--set", "integrator.t_end=0.01",
                  "--set", "integrator.dt=1e-4", "-full_ts_alpha_radius", "1")
    assert run.returncode == 0, run.stderr
    assert "generalized-alpha" in run.stdout and "100 steps" in run.stdout
    info = dbf_hpc("info", str(out))
    assert info.returncode == 0 and "method full" in info.stdout and "full-order model: 200 DOFs" in info.stdout


def test_a_failed_integration_on_rank_0_ends_the_job_with_advice_and_no_output(tmp_path):
    # The reduced model integrates on rank 0 alone: its failure must reach rank 1, end the job
    # with one line, and leave no file that looks complete. Explicit contact, a step far too long.
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "x.h5"), "-q", "--set", "integrator.contact=explicit",
                  "--set", "integrator.adaptive=false", "--set", "integrator.dt=1e-3", "--set", "integrator.t_end=2",
                  "--set", "basis.cache=off", timeout=60)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 1 and len(lines) == 1, out.stderr
    assert "time integration stopped" in lines[0] and 'contact = "implicit"' in lines[0]
    assert not (tmp_path / "x.h5").exists()
    import h5py

    with h5py.File(tmp_path / "x.h5.partial") as f:
        assert not f.attrs["complete"]


def _start(*args):
    cmd = ["mpirun", "-n", "2", sys.executable, "-m", "dbf_hpc.cli", *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            env=mpi_env(), start_new_session=True)


def _kill_group(process, sig):
    """Signal mpirun and each of its ranks, as a batch system does (OpenMPI puts the ranks in process
    groups of their own), and wait until every one has exited: a rank still dying holds the HDF5
    file's lock."""
    import time

    ranks = subprocess.run(["pgrep", "-P", str(process.pid)], capture_output=True, text=True).stdout.split()
    for pid in [*map(int, ranks), process.pid]:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass
    process.communicate(timeout=60)
    for pid in map(int, ranks):
        for _ in range(600):
            if not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z":
                break
            time.sleep(0.05)
        else:
            raise AssertionError(f"rank process {pid} did not exit")


def _wait_for(path, process, timeout=60):
    import time

    deadline = time.monotonic() + timeout
    while not os.path.exists(path):
        assert process.poll() is None, "the run ended before its first checkpoint"
        assert time.monotonic() < deadline
        time.sleep(0.05)


def _killed_after_a_checkpoint(target, *args):
    """Start `run PAPER -o target args` on 2 ranks and SIGKILL the whole job once its first checkpoint
    exists (a batch system's hard kill)."""
    import signal

    process = _start("run", PAPER, "-o", str(target), *args)
    _wait_for(str(target) + ".checkpoint", process)
    _kill_group(process, signal.SIGKILL)


@pytest.mark.parametrize("how", ["SIGKILL", "SIGTERM"])
def test_a_killed_run_resumes_from_its_checkpoint_to_the_uninterrupted_result(tmp_path, how):
    import signal
    import time

    import h5py

    # 20 s simulated: the rest after the first checkpoint (1 s) takes ~1.3 s of wall time, well past the
    # kill (5 s took 0.33 s on an idle machine, and the run could finish before it was killed)
    common = ("-q", "--set", "integrator.t_end=20", "--set", "output.checkpoint_dt=1",
              "--set", f"basis.cache={tmp_path}")
    reference = dbf_hpc("run", PAPER, "-o", str(tmp_path / "ref.h5"), *common)
    assert reference.returncode == 0, reference.stderr
    target = tmp_path / "run.h5"
    process = _start("run", PAPER, "-o", str(target), *common)
    _wait_for(str(target) + ".checkpoint", process)
    time.sleep(0.3)
    # SIGKILL: no chance to clean up, the last checkpoint is all there is. SIGTERM (a batch system's
    # time limit, sent to mpirun and the ranks alike): rank 0 checkpoints at the end of its step.
    _kill_group(process, signal.SIGKILL if how == "SIGKILL" else signal.SIGTERM)
    assert process.returncode != 0
    assert not target.exists() and os.path.exists(str(target) + ".partial")
    resumed = dbf_hpc("run", PAPER, "-o", str(target), "--resume", *common)
    assert resumed.returncode == 0, resumed.stderr
    assert not os.path.exists(str(target) + ".checkpoint")
    with h5py.File(tmp_path / "ref.h5") as a, h5py.File(target) as b:
        assert a["time"].shape == b["time"].shape, "no sample lost or written twice"
        for name in ("time", "constraints/displacement", "constraints/force_peak", "reduced/q", "snapshots/w",
                     "constraints/stats/impacts", "constraints/stats/force_rms"):
            np.testing.assert_allclose(b[name][:], a[name][:], rtol=1e-12, atol=1e-15, err_msg=name)
        # red team: the Newton and C-callback counts were the resumed part's, the step counts the whole run's
        counts = [{k: v for k, v in json.loads(f.attrs["solver_stats"]).items()
                   if k in ("steps", "rejected_steps", "newton_iterations", "c_counters")} for f in (a, b)]
        assert counts[0] == counts[1] and counts[0]["newton_iterations"] > 0, counts


# The killed full-order runs and their uninterrupted reference. No error estimate: it writes attributes
# only (no dataset compared below) and took two thirds of each run (a 4x shorter step over the run).
FULL_KILLED = ("-q", "--method", "full", "--set", "integrator.t_end=0.15", "--set", "integrator.dt=1e-5",
               "--set", "output.checkpoint_dt=0.01", "--set", "basis.estimate=false")


@pytest.fixture(scope="module")
def full_order_reference(tmp_path_factory):
    """The uninterrupted run of FULL_KILLED on 2 ranks, one for every way of killing it."""
    path = tmp_path_factory.mktemp("full_reference") / "ref.h5"
    reference = dbf_hpc("run", PAPER, "-o", str(path), *FULL_KILLED)
    assert reference.returncode == 0, reference.stderr
    return path


@pytest.mark.parametrize("how", ["SIGKILL", "SIGTERM", "SIGKILL before the first checkpoint"])
def test_a_killed_full_order_run_resumes_to_the_bit_identical_uninterrupted_result(tmp_path, how,
                                                                                   full_order_reference):
    # The full-order state is distributed: its checkpoint gathers it on rank 0 (the rank count is part
    # of the run's identity) and the resumed run scatters it back. Every dataset must come out bit for
    # bit as in the uninterrupted run: samples, peaks, statistics and snapshots.
    import signal
    import time

    import h5py

    common = FULL_KILLED
    target = tmp_path / "run.h5"
    process = _start("run", PAPER, "-o", str(target), *common)
    if how.endswith("checkpoint"):   # during the first steps: no checkpoint yet, the resume starts at t = 0
        _wait_for(str(target) + ".partial", process)
    else:
        _wait_for(str(target) + ".checkpoint", process)
        time.sleep(0.5)
    _kill_group(process, signal.SIGTERM if how == "SIGTERM" else signal.SIGKILL)
    assert process.returncode != 0
    assert not target.exists() and os.path.exists(str(target) + ".partial")
    assert os.path.exists(str(target) + ".checkpoint") != how.endswith("checkpoint")
    resumed = dbf_hpc("run", PAPER, "-o", str(target), "--resume", *common[1:])
    assert resumed.returncode == 0, resumed.stderr
    assert ("no usable checkpoint" in resumed.stdout) == how.endswith("checkpoint"), resumed.stdout
    assert not os.path.exists(str(target) + ".checkpoint")
    with h5py.File(full_order_reference) as a, h5py.File(target) as b:
        names = []
        a.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
        assert "constraints/stats/impacts" in names and "snapshots/w" in names and a["time"].shape == (10001,)
        for name in names:
            np.testing.assert_array_equal(b[name][()], a[name][()], err_msg=name)


def test_resuming_a_full_order_run_on_another_rank_count_is_refused(tmp_path):
    common = ("-q", "--method", "full", "--set", "integrator.t_end=0.3", "--set", "integrator.dt=1e-5",
              "--set", "output.checkpoint_dt=0.005")
    target = tmp_path / "run.h5"
    _killed_after_a_checkpoint(target, *common)
    out = dbf_hpc("run", PAPER, "-o", str(target), "--resume", *common, ranks=1)
    assert out.returncode == 1 and "ranks differ" in out.stderr, out.stderr


def test_resuming_with_a_different_scene_is_refused(tmp_path):
    common = ("-q", "--set", "integrator.t_end=3", "--set", "output.checkpoint_dt=0.25",
              "--set", f"basis.cache={tmp_path}")
    target = tmp_path / "run.h5"
    _killed_after_a_checkpoint(target, *common)
    out = dbf_hpc("run", PAPER, "-o", str(target), "--resume", *common, "--set", "constraint.clearance=1e-3")
    assert out.returncode == 1 and "written by a different scene" in out.stderr


def test_a_million_steps_keep_memory_flat_and_the_free_energy_bounded(tmp_path):
    # Undamped free vibration against an elastic stop, 10^6 fixed steps, 10^5 samples streamed to
    # disk: the process must not grow with the run, and the energy must not grow either.
    import time

    import h5py

    from dbf_hpc.laws import ConstraintLaws
    from dbf_hpc.scene import load_scene

    out = tmp_path / "long.h5"
    sets = ["excitation.kind=none", "initial.mode=2", "initial.amplitude=0.003", "constraint.k_minus=100.0",
            "constraint.k_plus=100.0", "integrator.adaptive=false", "integrator.dt=1e-4", "integrator.t_end=100.0",
            "output.sample_dt=1e-3", "output.checkpoint_dt=1000.0", f"basis.cache={tmp_path}"]
    process = _start("run", PAPER, "-o", str(out), "-q", *[a for s in sets for a in ("--set", s)])
    rss = []
    while process.poll() is None:
        ranks = subprocess.run(["pgrep", "-P", str(process.pid)], capture_output=True, text=True).stdout.split()
        total = 0
        for pid in ranks:
            try:
                status = open(f"/proc/{pid}/status").read()
                total += int(re.search(r"VmRSS:\s+(\d+)", status).group(1))
            except (OSError, AttributeError):
                pass
        if total:
            rss.append(total)
        time.sleep(0.2)   # the C callbacks run 10^6 steps in about 10 s
    assert process.returncode == 0, process.stderr.read()
    assert len(rss) > 10
    early, late = np.median(rss[len(rss) // 5: len(rss) // 5 + 3]), max(rss[-5:])
    assert late - early < 20_000, (early, late)     # kB: 10^5 samples held in memory would be ~20 MB
    with h5py.File(out) as f:
        assert f["time"].shape == (100001,)
        q, p, K, z = f["reduced/q"][:], f["reduced/qdot"][:], f["reduced/K"][:], f["constraints/displacement"][:]
        laws = ConstraintLaws([c.law for c in load_scene(PAPER, sets).constraints])
        potential = np.array([laws.potential(row).sum() for row in z])
        energy = 0.5 * np.sum(p * p, 1) + 0.5 * np.einsum("ti,ij,tj->t", q, K, q) + potential
        assert np.all(np.isfinite(energy))
        assert energy.max() <= energy[0] * (1 + 1e-3)     # L-stable ARKIMEX: energy may only decay


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere: the permission check cannot fail")
def test_an_output_directory_without_write_permission_is_one_line(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    out = dbf_hpc("run", PAPER, "-o", str(locked / "x.h5"))
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 1 and len(lines) == 1 and "is not writable" in lines[0]


def test_two_jobs_on_one_output_without_hdf5_file_locking_leave_the_first_intact(tmp_path, monkeypatch):
    # Red team: with HDF5_USE_FILE_LOCKING=FALSE (usual on Lustre and NFS) two runs on one output
    # corrupted it (complete = true with samples zeroed). The second job is refused instead.
    import h5py

    monkeypatch.setenv("HDF5_USE_FILE_LOCKING", "FALSE")
    target = tmp_path / "shared.h5"
    # The Python callbacks keep the first job running for several seconds (the C ones take 0.5 s).
    common = ("-q", "--set", "integrator.t_end=2", "--set", f"basis.cache={tmp_path}",
              "--set", "integrator.callbacks=python")
    first = _start("run", PAPER, "-o", str(target), *common)
    _wait_for(str(target) + ".partial", first)
    second = dbf_hpc("run", PAPER, "-o", str(target), *common)
    lines = [line for line in second.stderr.splitlines() if line.strip()]
    assert second.returncode == 1 and len(lines) == 1 and "being written by another job" in lines[0], second.stderr
    first.communicate(timeout=600)
    assert first.returncode == 0
    with h5py.File(target) as f:
        assert f.attrs["complete"] and f["time"].shape == (10001,)
        assert abs(abs(f["constraints/displacement"][:, 0]).max() / 2.5e-3 - 1) < 0.03


def test_a_second_job_on_an_output_being_written_is_refused_naming_the_first_job_on_1_and_2_ranks(tmp_path):
    # Red team: with HDF5's file locking on (the default), the second job's look at OUT.h5.partial, which
    # the first job holds open, failed first, as "cannot open 'OUT.h5.partial': another process has it open
    # for writing", naming neither the job nor its lock. The lock speaks first, and the first job's output
    # is left intact.
    import h5py

    target = tmp_path / "shared.h5"
    common = ("-q", "--set", "integrator.t_end=2", "--set", f"basis.cache={tmp_path}",
              "--set", "integrator.callbacks=python")
    first = _start("run", PAPER, "-o", str(target), *common)
    _wait_for(str(target) + ".partial", first)
    holder = open(f"{target}.lock").read().split()
    for ranks in (1, 2):
        second = dbf_hpc("run", PAPER, "-o", str(target), *common, ranks=ranks)
        lines = [line for line in second.stderr.splitlines() if line.strip()]
        assert first.poll() is None, "the first job ended before the second was refused: the test proves nothing"
        assert second.returncode == 1 and lines == [
            f"dbf-hpc: error: output {str(target)!r} is being written by another job (pid {holder[1]} on "
            f"{holder[0]}); wait for it, or remove {target}.lock if that job is gone"], second.stderr
    first.communicate(timeout=600)
    assert first.returncode == 0
    with h5py.File(target) as f:
        assert f.attrs["complete"] and f["time"].shape == (10001,)
        assert abs(abs(f["constraints/displacement"][:, 0]).max() / 2.5e-3 - 1) < 0.03
    assert not os.path.exists(f"{target}.lock") and not os.path.exists(f"{target}.partial")


def test_resuming_on_another_number_of_ranks_is_refused(tmp_path):
    # The basis depends on the rank layout through round-off, and the impacting beam amplifies it:
    # a resume on another layout would not continue the same run.

    common = ("-q", "--set", "integrator.t_end=3", "--set", "output.checkpoint_dt=0.25", "--set", f"basis.cache={tmp_path}")
    target = tmp_path / "run.h5"
    _killed_after_a_checkpoint(target, *common)
    out = dbf_hpc("run", PAPER, "-o", str(target), "--resume", *common, ranks=1)
    assert out.returncode == 1 and "ranks differ" in out.stderr, out.stderr


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MiB file system of its own, or a skip."""
    with tmpfs_disk(tmp_path, "3m") as mount:
        yield mount


def _fill_and_expect_one_line(disk, run):
    """Another job fills the disk under the running `run`, which must end in one line naming it."""
    with open(disk / "filler", "wb") as f:
        try:
            while True:
                f.write(b"\0" * 65536)
        except OSError:
            pass
    _, stderr = run.communicate(timeout=300)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert run.returncode == 1 and len(lines) == 1 and "No space left on device" in lines[0], stderr


def test_a_disk_too_small_or_filling_up_is_one_line_never_a_crash(small_disk):
    # Red team: a full disk gave tracebacks, then a segfault (exit 139) and a stray temp file.
    import time

    too_big = dbf_hpc("run", PAPER, "-o", str(small_disk / "big.h5"), "--set", "basis.cache=off",
                      "--set", "output.sample_dt=1e-5")
    assert too_big.returncode == 1 and "needs about" in too_big.stderr and "MiB free" in too_big.stderr
    (small_disk / "filler").write_bytes(b"\0" * (2 * 2**20))
    cache = dbf_hpc("basis", PAPER, "--set", "structure.elements=400", "--set", "basis.modes=60",
                    "--set", f"basis.cache={small_disk / 'cache'}")
    assert cache.returncode == 0 and "dbf-hpc: warning: cannot write the basis cache" in cache.stderr, cache.stderr
    (small_disk / "filler").unlink()
    # The Python callbacks keep the run going for several seconds (the C ones take 0.5 s): time for
    # another job to fill the disk while the samples stream out. No snapshots: with them the run
    # needs 1.9 MB (measured), more than this disk holds with the margin.
    run = _start("run", PAPER, "-o", str(small_disk / "out.h5"), "-q", "--set", "basis.cache=off",
                 "--set", "integrator.t_end=3", "--set", "integrator.callbacks=python", "--set", "output.snapshots=0")
    _wait_for(str(small_disk / "out.h5.partial"), run)
    time.sleep(1)
    _fill_and_expect_one_line(small_disk, run)
    assert not [p for p in os.listdir(small_disk) if ".tmp" in p]


@pytest.mark.parametrize("ranks", [1, 2])
def test_mode_shapes_and_a_stiffness_table_on_a_full_disk_are_one_line_and_leave_the_old_files(small_disk, ranks):
    # Red team: basis --xdmf on a full disk was "internal error (RuntimeError)" from h5py, then (1 rank)
    # a segfault as the failed HDF5 file was freed, with its .tmp file left behind.
    shapes = small_disk / "shapes.xdmf"
    assert dbf_hpc("basis", PAPER, "--xdmf", str(shapes), "--no-cache", ranks=ranks).returncode == 0
    before = {name: (small_disk / name).read_bytes() for name in ("shapes.h5", "shapes.xdmf")}
    with open(small_disk / "filler", "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError:
            pass
    out = dbf_hpc("stiffness", PAPER, "--k", "1:1e9:400", "-o", str(small_disk / "k.csv"), ranks=ranks)
    assert _one_line(out) and "No space left on device" in out.stderr, out.stderr
    # room for the file to open and take part of the shapes (0.2 MB): the write fails in the middle
    os.truncate(small_disk / "filler", os.path.getsize(small_disk / "filler") - 2**17)
    out = dbf_hpc("basis", PAPER, "--xdmf", str(shapes), "--no-cache", "--set", "structure.elements=300",
                  "--set", "basis.modes=30", ranks=ranks)
    assert _one_line(out) and "No space left on device" in out.stderr, out.stderr
    assert {name: (small_disk / name).read_bytes() for name in before} == before   # the old pair, whole
    assert sorted(os.listdir(small_disk)) == ["filler", "shapes.h5", "shapes.xdmf"]


_KILLED_WRITING_SHAPES = """
import os, signal, sys
from dbf_hpc import cli, xdmf

def killed(*args, **kwargs):   # the shapes' .h5 is written under its temporary name: SIGKILL, as a batch system's
    os.kill(os.getpid(), signal.SIGKILL)

xdmf.write = killed
sys.exit(cli.main(["basis", sys.argv[1], "--xdmf", sys.argv[2]]))
"""


def test_basis_xdmf_after_a_run_killed_as_it_wrote_leaves_no_temporary_file_but_a_live_writers(tmp_path):
    # Red team: `basis --xdmf` SIGKILLed while it wrote left SHAPES.h5.tmp-<pid> for good (no `finally` runs).
    # The next run removes the temporary files of its two outputs whose writer is gone from this host; a
    # live process's (another run writing now) and another host's (which cannot be told) are kept.
    import socket

    script = tmp_path / "killed.py"
    script.write_text(_KILLED_WRITING_SHAPES)
    shapes = tmp_path / "shapes.xdmf"
    out, _ = mpirun_script(script, PAPER, shapes, ranks=1)
    assert out.returncode != 0
    left = [p for p in os.listdir(tmp_path) if ".tmp-" in p]
    assert [p.split(".tmp-")[0] for p in left] == ["shapes.h5"], left    # what the kill left
    host = socket.gethostname()
    kept = [f"shapes.h5.tmp-{host}-{os.getpid()}", f"shapes.xdmf.tmp-another-host-{2**22 + 7}"]
    for name in kept:
        (tmp_path / name).write_text("being written")
    out = dbf_hpc("basis", PAPER, "--xdmf", str(shapes), ranks=1)
    assert out.returncode == 0, out.stderr
    assert sorted(os.listdir(tmp_path)) == sorted(["killed.py", "shapes.h5", "shapes.xdmf", *kept])


def test_a_full_order_run_the_disk_fills_under_stops_in_one_line_and_resumes_to_the_uninterrupted_result(
        small_disk, tmp_path):
    # The full-order reference writes from inside its integrator's callbacks; a write the full disk
    # refused ended the run on both ranks, but closed the .partial (a close after a failed write has
    # crashed HDF5) instead of parking it as the reduced run does. Either way: one line, exit 1, and a
    # rerun with room resumes to the uninterrupted run's samples bit for bit. 3 s (1501 samples): the
    # disk fills just after the first checkpoint (0.5 s), so the run has four more checkpoints and a
    # block of 1024 samples to write into it, and the resumed run writes a whole block too.
    import h5py

    common = ("-q", "--method", "full", "--set", "basis.cache=off", "--set", "integrator.t_end=3",
              "--set", "output.checkpoint_dt=0.5", "--set", "output.snapshots=0", "--set", "output.sample_dt=0.002")
    target = small_disk / "out.h5"
    run = _start("run", PAPER, "-o", str(target), *common)
    _wait_for(f"{target}.checkpoint", run)
    _fill_and_expect_one_line(small_disk, run)
    (small_disk / "filler").unlink()
    resumed = dbf_hpc("run", PAPER, "-o", str(target), "--resume", *common)
    assert resumed.returncode == 0, resumed.stderr
    whole = dbf_hpc("run", PAPER, "-o", str(tmp_path / "whole.h5"), *common)
    assert whole.returncode == 0, whole.stderr
    with h5py.File(target, "r") as a, h5py.File(tmp_path / "whole.h5", "r") as b:
        for name in ("time", "constraints/displacement", "constraints/force", "probes/displacement"):
            assert np.array_equal(a[name][()], b[name][()]), name


def test_info_reads_statistics_a_sweep_summary_and_a_partial_run(tmp_path):
    import signal

    out = tmp_path / "s.h5"
    run = dbf_hpc("run", PAPER, "-o", str(out), "-q", "--set", "integrator.t_end=1", "--set", f"basis.cache={tmp_path}")
    assert run.returncode == 0, run.stderr
    info = dbf_hpc_alone("info", str(out))
    assert re.search(r"constraint 1 at 0.25 m: .* \d+ impacts, [\d.]+/s, in contact", info.stdout), info.stdout
    process = _start("run", PAPER, "-o", str(tmp_path / "p.h5"), "-q", "--set", "integrator.t_end=20",
                     "--set", "output.checkpoint_dt=1", "--set", f"basis.cache={tmp_path}")   # killed long before its end
    _wait_for(str(tmp_path / "p.h5.checkpoint"), process)
    _kill_group(process, signal.SIGKILL)
    partial = dbf_hpc_alone("info", str(tmp_path / "p.h5"))
    assert partial.returncode == 0 and "INCOMPLETE" in partial.stdout and "--resume" in partial.stdout
    plot = dbf_hpc_alone("plot", str(tmp_path / "p.h5"), "-d", str(tmp_path / "figs"))
    assert plot.returncode == 1 and "did not finish" in plot.stderr


def test_unused_petsc_options_and_suspicious_units_draw_warnings(tmp_path):
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "w.h5"), "--set", "integrator.t_end=0.2", "--set",
                  "basis.cache=off", "--set", "structure.E=117", "--set", "constraint.clearance=1.0",
                  "--set", 'basis.gyroscopic_form="state_space"',
                  "-rom_ts_arkimex_typ", "4", "-ts_arkimex_type", "4")
    assert out.returncode == 0, out.stderr
    for expected in ("PETSc option -rom_ts_arkimex_typ was not used", "PETSc option -ts_arkimex_type was not used",
                     "the lowest elastic frequency is 8.61e-06 Hz", "never reached its stop",
                     # a form the structure cannot take (red team: it was silently not used)
                     'gyroscopic_form = "state_space" is for gyroscopic structures'):
        assert expected in out.stderr, (expected, out.stderr)   # warnings on stderr, results on stdout
    assert all(line.startswith("dbf-hpc: warning: ") for line in out.stderr.splitlines()), out.stderr
    assert "basis: 6 modes (8.606e-06 ... " in out.stdout and "warning" not in out.stdout, out.stdout


def test_an_unused_petsc_option_is_kept_in_the_output_and_said_again_by_resume_and_info(tmp_path):
    # Warnings parity: the "was not used" line was printed by the command after the run had written its
    # output, so the output's `warnings` did not hold it: `--resume` of the finished run (a requeued batch job)
    # and `dbf-hpc info` did not repeat it, and the resume warned of -modes_eps_tol, which the run had read,
    # as "not used" (nothing reads options when nothing is computed). Reduced and full-order runs alike.
    import h5py

    for method, extra, read in (("rom", (), "-modes_eps_tol"), ("full", ("--set", "integrator.dt=1e-4"),
                                                                 "-full_alpha_radius")):
        out = str(tmp_path / f"{method}.h5")
        args = ("run", PAPER, "-o", out, "--method", method, "--set", "integrator.t_end=0.01", "--set",
                "basis.modes=4", "--set", "basis.estimate=false", "--set", "output.snapshots=0", "--set",
                f"basis.cache={tmp_path}", *extra, read, "0.9" if method == "full" else "1e-11",
                "-rom_ts_arkimex_typ", "4")
        line = "dbf-hpc: warning: PETSc option -rom_ts_arkimex_typ was not used: a misspelling"
        for attempt in ("run", "resume"):
            ran = dbf_hpc(*args, *(("--resume",) if attempt == "resume" else ()))
            assert ran.returncode == 0, ran.stderr
            assert ran.stderr.count(line) == 1, (method, attempt, ran.stderr)
            assert f"{read} was not used" not in ran.stderr, (method, attempt, ran.stderr)
            assert attempt == "run" or "already complete" in ran.stdout, ran.stdout
        with h5py.File(out, "r") as f:
            stored = str(f.attrs["warnings"]).split("\n")
        assert sum(w.startswith("PETSc option -rom_ts_arkimex_typ was not used") for w in stored) == 1, stored
        info = dbf_hpc_alone("info", out)
        assert "warning: PETSc option -rom_ts_arkimex_typ was not used" in info.stdout, info.stdout


def test_the_basis_command_says_the_very_basis_warnings_a_run_says_in_its_order(tmp_path):
    # Warnings parity: `dbf-hpc basis` said the flexibility captured and the DBF stiffness lines, not the
    # lowest elastic frequency that suggests a unit slip (E in GPa given as Pa) nor a forcing above the basis'
    # modes, which `dbf-hpc run` of the same scene says: the basis command now says the run's lines in its order.
    sets = ("--set", "basis.modes=1", "--set", 'basis.enrichment="none"', "--set", "structure.E=117", "--set",
            f"basis.cache={tmp_path}")
    basis = dbf_hpc("basis", PAPER, *sets)
    ran = dbf_hpc("run", PAPER, "-o", str(tmp_path / "units.h5"), "-q", "--set", "integrator.t_end=0.01", "--set",
                  "basis.estimate=false", "--set", "output.snapshots=0", *sets)
    assert basis.returncode == 0 and ran.returncode == 0, basis.stderr + ran.stderr
    said = [line for line in basis.stderr.splitlines() if line.startswith("dbf-hpc: warning: ")]
    assert len(said) == 3 and "the lowest elastic frequency is 8.61e-06 Hz" in said[1], basis.stderr
    assert "the excitation (1 Hz) lies above the highest reference mode" in said[2], basis.stderr
    assert said == [line for line in ran.stderr.splitlines() if line in said], (said, ran.stderr)


def test_options_petsc_reads_at_its_finalize_are_not_called_unused_but_a_misspelling_is():
    # Red team: -options_left and -options_view (read by PetscFinalize, after the command's check)
    # were reported as "not used: a misspelling"; -options_left's own report must still appear.
    out = dbf_hpc("modes", PAPER, "-options_left", "-options_view", "-mdoes_eps_tol", "1e-3")
    assert out.returncode == 0, out.stderr
    assert "PETSc option -mdoes_eps_tol was not used" in out.stderr, out.stderr
    assert "-options_left was not used" not in out.stderr and "-options_view was not used" not in out.stderr, out.stderr
    assert "Option left: name:-mdoes_eps_tol" in out.stdout + out.stderr


def test_a_stop_not_reached_by_a_near_miss_draws_no_unit_warning(tmp_path):
    # New-user pass: the paper's beam to 0.1 s comes to 2.37 mm of the 2.5 mm stop; "check the
    # clearance's unit" there (and at the 2-D tube's idle plates) is a false alarm.
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "near.h5"), "--set", "integrator.t_end=0.1", "--set",
                  "basis.cache=off", ranks=1)
    assert out.returncode == 0 and "never reached" not in out.stdout + out.stderr, out.stderr
    import h5py

    with h5py.File(tmp_path / "near.h5", "r") as f:
        assert 2e-3 < np.abs(f["constraints/displacement"][:]).max() < 2.5e-3    # within a tenth, not touching


def test_a_fixed_step_that_does_not_resolve_the_impacts_draws_a_warning_and_one_that_does_not(tmp_path):
    # Red team: at k = 1e12 N/m the full-order peak force was k times a penetration set by dt (96 kN at
    # dt = 1e-5 s, 3 kN at 5e-7 s) with no word. The paper beam's chatter lasts ~15 us an impact.
    import h5py

    common = ("run", PAPER, "--method", "full")
    coarse = dbf_hpc(*common, "--set", "integrator.t_end=0.25", "-o", str(tmp_path / "coarse.h5"),
                     "--set", "constraint.k_minus=1e12", "--set", "constraint.k_plus=1e12", ranks=1)
    assert coarse.returncode == 0, coarse.stderr
    assert "the impacts of constraint 1 at x = 0.25 m last 1 fixed steps" in coarse.stderr, coarse.stderr
    # To 0.12 s, not 0.25 s: 88 impacts already (their mean 7.6 steps, as over 0.25 s), in half the
    # 2 us steps, which took 35 s of 0.25 s's measured under load. (STEPS_PER_IMPACT = 10 fails here.)
    fine = dbf_hpc(*common, "--set", "integrator.t_end=0.12", "-o", str(tmp_path / "fine.h5"),
                   "--set", "integrator.dt=2e-6", "--set", "output.sample_dt=2e-6", ranks=1)
    assert fine.returncode == 0 and "fixed steps" not in fine.stdout + fine.stderr, fine.stderr
    with h5py.File(tmp_path / "fine.h5") as f:   # it does impact, each over 5 to 10 steps
        impacts, duration = f["constraints/stats/impacts"][0], f["constraints/stats/impact_duration_mean"][0]
    assert impacts >= 10 and 5 < duration / 2e-6 < 10, (impacts, duration)


def test_cache_commands_refuse_a_bad_age_or_directory_and_clear_an_empty_one(tmp_path):
    # Red team: --older-than -1 (or nan) cleared every basis; a missing --dir listed "0 file(s)"
    (tmp_path / "file").write_text("x")
    for args, message in ((("clear", "--older-than", "-1"), "--older-than -1: give a finite number"),
                          (("clear", "--older-than", "nan"), "--older-than nan"),
                          (("list", "--dir", str(tmp_path / "missing")), "no such directory"),
                          (("clear", "--dir", str(tmp_path / "file")), "is not a directory"),
                          (("list", "--dir", ""), "give the cache directory")):
        out = dbf_hpc_alone("cache", *args)
        assert _one_line(out) and message in out.stderr, (args, out.stderr)
    out = dbf_hpc_alone("cache", "clear", "--dir", str(tmp_path), "--older-than", "0")
    assert out.returncode == 0 and "removed 0 file(s)" in out.stdout and (tmp_path / "file").exists()


def test_cache_clear_removes_only_the_files_the_cache_wrote(tmp_path):
    # Red team: `cache clear` removed any basis-* file, a user's own among them, and a temporary file
    # another job was still writing.
    import h5py

    out = dbf_hpc("basis", PAPER, "--set", "basis.modes=2", "--set", f"basis.cache={tmp_path}", ranks=1)
    assert out.returncode == 0, out.stderr
    (cached,) = [p for p in tmp_path.iterdir() if p.suffix == ".h5"]
    (tmp_path / "basis-notes.txt").write_text("mine")
    with h5py.File(tmp_path / "basis-0123456789abcdef0123.h5", "w") as f:   # named like one, not ours
        f["V"] = np.zeros((3, 1))
    (tmp_path / "basis-0123456789abcdef4567.h5").write_text("my notes")       # not even HDF5
    with h5py.File(tmp_path / "basis-0123456789abcdef89ab.h5", "w") as f:    # its key, but V a group
        f.attrs["key"] = "0123456789abcdef89ab"
        f.create_group("V")
    stale, fresh = tmp_path / f"{cached.name}.tmp-11", tmp_path / f"{cached.name}.tmp-12"
    stale_host = tmp_path / f"{cached.name}.tmp-node-7.cluster-13"   # since 0.2.2 the host is in the name
    for p in (stale, fresh, stale_host):
        p.write_bytes(b"x")
    os.utime(stale, (1e9, 1e9))
    os.utime(stale_host, (1e9, 1e9))
    listed = dbf_hpc_alone("cache", "list", "--dir", str(tmp_path))
    assert listed.returncode == 0 and "7 file(s)" in listed.stdout and "not a basis this cache wrote" in listed.stdout
    # A basis used today is not "unused for a day", however long ago it was written
    os.utime(cached, (1e9, 1e9))
    out = dbf_hpc("basis", PAPER, "--set", "basis.modes=2", "--set", f"basis.cache={tmp_path}", ranks=1)
    assert out.returncode == 0 and cached.stat().st_mtime > 1e9 + 86400, out.stdout
    out = dbf_hpc_alone("cache", "clear", "--dir", str(tmp_path), "--older-than", "1")
    assert out.returncode == 0 and "removed 2 file(s)" in out.stdout and cached.exists() and not stale.exists()
    assert not stale_host.exists()
    out = dbf_hpc_alone("cache", "clear", "--dir", str(tmp_path))
    assert out.returncode == 0 and "removed 1 file(s)" in out.stdout, out.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["basis-0123456789abcdef0123.h5", "basis-notes.txt",
                                                                 "basis-0123456789abcdef4567.h5",
                                                                 "basis-0123456789abcdef89ab.h5", fresh.name])


def test_a_file_system_that_refuses_locks_is_named_with_the_setting_that_works(tmp_path):
    # Red team: with flock failing (ENOLCK, as on some NFS mounts) a good output read as "not an HDF5
    # file", a rerun onto it advised removing it, and an empty .partial was left.
    import shutil

    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler to build the lock-refusing shim")
    source = tmp_path / "nolock.c"
    source.write_text("#include <errno.h>\nint flock(int fd, int op) { (void)fd; (void)op; errno = ENOLCK; "
                      "return -1; }\n")
    subprocess.run([compiler, "-shared", "-fPIC", "-o", str(tmp_path / "nolock.so"), str(source)], check=True)
    good = str(tmp_path / "good.h5")
    args = (PAPER, "--set", "integrator.t_end=0.01", "--set", "basis.cache=off", "-q")
    assert dbf_hpc("run", *args, "-o", good, ranks=1).returncode == 0
    env = {**mpi_env(), "LD_PRELOAD": str(tmp_path / "nolock.so")}
    for argv in (("info", good), ("run", *args, "-o", good), ("run", *args, "-o", str(tmp_path / "new.h5"))):
        out = subprocess.run([sys.executable, "-m", "dbf_hpc.cli", *argv], capture_output=True, text=True,
                             timeout=120, cwd=ROOT, env=env)
        assert _one_line(out) and "set HDF5_USE_FILE_LOCKING=FALSE" in out.stderr, (argv, out.stderr)
    assert sorted(p.name for p in tmp_path.iterdir() if "new" in p.name) == []
    out = subprocess.run([sys.executable, "-m", "dbf_hpc.cli", "run", *args, "-o", str(tmp_path / "new.h5")],
                         capture_output=True, text=True, timeout=120, cwd=ROOT,
                         env={**env, "HDF5_USE_FILE_LOCKING": "FALSE"})
    assert out.returncode == 0 and (tmp_path / "new.h5").exists(), out.stderr


def test_a_sweep_with_a_failed_case_writes_its_summary_and_exits_non_zero(tmp_path):
    # A batch job's sweep with failed cases read as a success (exit 0).
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'scene = "{PAPER}"\noutput = "s.h5"\n[[case]]\n"integrator.t_end" = 0.02\n'
                     f'[[case]]\n"integrator.t_end" = 0.02\n"integrator.scheme" = "ars443"\n')
    out = dbf_hpc("sweep", str(sweep), "-q")
    assert _one_line(out) and "1 of 2 cases failed" in out.stderr and "retries them" in out.stderr, out.stderr
    assert (tmp_path / "s.h5").exists()
    info = dbf_hpc_alone("info", str(tmp_path / "s.h5"))
    assert info.returncode == 0 and "ars443" in info.stdout, info.stdout


def test_the_installed_command_works_without_an_activated_venv(tmp_path):
    # A Jupyter kernel or `.venv/bin/dbf-hpc` from a plain shell: no PETSC_DIR, no SLEPC_DIR.
    command = os.path.join(os.path.dirname(sys.executable), "dbf-hpc")
    if not os.path.exists(command):
        pytest.skip("dbf-hpc is not installed next to this Python")
    bare = {"HOME": os.environ.get("HOME", str(tmp_path)), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([command, "modes", PAPER, "--set", "basis.modes=2"], capture_output=True, text=True,
                         env=bare, timeout=120)
    assert out.returncode == 0 and "reference modes: 2" in out.stdout, out.stderr
    api = subprocess.run([sys.executable, "-c", "import dbf_hpc; print(dbf_hpc.Beam.__name__)"],
                         capture_output=True, text=True, env=bare, timeout=120)
    assert api.returncode == 0 and api.stdout.strip() == "Beam", api.stderr


# What the second red-team pass found (issues 12 and 16): each refused in one line before any work,
# or recorded as it was asked.
SHORT = ("--set", "integrator.t_end=0.01", "-q")


def _one_line(out):
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    return out.returncode == 1 and len(lines) == 1 and lines[0].startswith("dbf-hpc: error:")


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """The finished output of `run PAPER -o run.h5 SHORT` on 2 ranks (and its ParaView file run.xdmf),
    made once for the five tests that plot it or check that other commands keep it (each ran its own,
    the same run)."""
    folder = tmp_path_factory.mktemp("short_run")
    out = dbf_hpc("run", PAPER, "-o", str(folder / "run.h5"), *SHORT)
    assert out.returncode == 0, out.stderr
    return folder


def _copy_of(short_run, folder):
    """folder/run.h5 and folder/run.xdmf, copies of the short run's (the .xdmf names run.h5 beside it)."""
    import shutil

    for name in ("run.h5", "run.xdmf"):
        shutil.copyfile(short_run / name, folder / name)
    return folder / "run.h5"


def test_a_table_figure_or_shapes_file_replaces_only_its_own_kind(tmp_path, short_run):
    # Red team: stiffness -o / --plot overwrote any file (a finished run's .h5 became a CSV), plot -d
    # replaced foreign PNGs, and basis --xdmf run.xdmf replaced the run's output run.h5.
    run_out = _copy_of(short_run, tmp_path)
    before = run_out.read_bytes()
    foreign = tmp_path / "mine.png"
    foreign.write_bytes(b"\x89PNG not a dbf-hpc figure")
    for args, kind in ((("stiffness", PAPER, "--k", "1,10", "-o", str(run_out)), "exists and is not"),
                       (("stiffness", PAPER, "--k", "1,10", "--plot", str(foreign)), "exists and is not"),
                       (("basis", PAPER, "--xdmf", str(tmp_path / "run.xdmf")),   # named for what it would replace
                        "exists and is not the mode shapes of an earlier `dbf-hpc basis --xdmf`")):
        out = dbf_hpc(*args)
        assert _one_line(out) and kind in out.stderr, (args, out.stderr)
    assert run_out.read_bytes() == before and foreign.read_bytes() == b"\x89PNG not a dbf-hpc figure"
    figures = tmp_path / "figs"
    figures.mkdir()
    (figures / "probes.png").write_bytes(b"\x89PNG mine")
    out = dbf_hpc_alone("plot", str(run_out), "-d", str(figures))
    assert _one_line(out) and "is not a dbf-hpc plot" in out.stderr
    assert (figures / "probes.png").read_bytes() == b"\x89PNG mine"
    for _ in range(2):       # its own files are replaced by a rerun
        out = dbf_hpc("stiffness", PAPER, "--k", "1,10", "-o", str(tmp_path / "k.csv"), "--plot",
                      str(tmp_path / "k.png"))
        assert out.returncode == 0, out.stderr
        out = dbf_hpc_alone("plot", str(run_out), "-d", str(tmp_path / "own"))
        assert out.returncode == 0, out.stderr


def test_a_table_figure_or_shapes_name_too_long_for_its_temporary_file_is_refused_before_any_work(tmp_path):
    # Red team: stiffness -o / --plot and basis --xdmf with a name a few bytes under the folder's limit
    # solved everything and printed the table, then failed "File name too long" at the temporary file
    # written beside it (NAME.tmp-HOST-PID[.png]). The longest temporary name decides.
    import socket

    from dbf_hpc.errors import temporary_path
    from dbf_hpc.output import LONGEST_PID

    def longest(suffix: str) -> int:   # the limit on the given name, for a suffix of the temporary file
        extra = len(os.fsencode(temporary_path("", suffix, pid=LONGEST_PID)))
        return os.pathconf(tmp_path, "PC_NAME_MAX") - extra

    assert socket.gethostname() in temporary_path("x", pid=LONGEST_PID)
    csv, png, h5 = longest(""), longest(".png"), longest("")
    for args, size in ((("stiffness", PAPER, "--k", "1,10", "-o", str(tmp_path / ("k" * (csv - 3) + ".csv"))), csv),
                       (("stiffness", PAPER, "--k", "1,10", "--plot", str(tmp_path / ("k" * (png - 3) + ".png"))),
                        png),
                       (("basis", PAPER, "--xdmf", str(tmp_path / ("s" * (h5 - 2) + ".xdmf"))), h5)):   # its .h5: h5 + 1
        out = dbf_hpc(*args)
        assert _one_line(out) and "too long for the files written beside it" in out.stderr, out.stderr
        assert f"a name of {size + 1} bytes" in out.stderr and f"give a name of at most {size} bytes" in out.stderr, \
            out.stderr
        assert "omega" not in out.stdout and "shapes" not in out.stdout, out.stdout   # nothing was solved
        assert not os.listdir(tmp_path), os.listdir(tmp_path)
    just_csv, just_png = tmp_path / ("k" * (csv - 4) + ".csv"), tmp_path / ("k" * (png - 4) + ".png")
    out = dbf_hpc("stiffness", PAPER, "--k", "1,10", "-o", str(just_csv), "--plot", str(just_png))
    assert out.returncode == 0, out.stderr
    assert just_csv.is_file() and just_png.read_bytes()[:4] == b"\x89PNG"


def test_the_paraview_file_beside_an_output_never_replaces_what_dbf_hpc_did_not_write(tmp_path):
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "run.xdmf"), *SHORT)
    assert _one_line(out) and "ends in .xdmf" in out.stderr and not os.listdir(tmp_path)
    (tmp_path / "notes.xdmf").write_text("my notes")
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "notes.h5"), *SHORT)
    assert _one_line(out) and (tmp_path / "notes.xdmf").read_text() == "my notes"
    (tmp_path / "dir.xdmf").mkdir()
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "dir.h5"), *SHORT)
    assert _one_line(out) and "directory" in out.stderr and not (tmp_path / "dir.h5").exists()
    out = dbf_hpc("basis", PAPER, "--xdmf", str(tmp_path / "shapes.h5"))
    assert _one_line(out) and "ending in .xdmf" in out.stderr
    for _ in range(2):      # dbf-hpc's own files are replaced by a rerun
        out = dbf_hpc("basis", PAPER, "--xdmf", str(tmp_path / "shapes.xdmf"))
        assert out.returncode == 0, out.stderr
    # ... but a run does not replace a basis's shapes (it did: both are dbf-hpc's HDF5 files)
    shapes = (tmp_path / "shapes.h5").read_bytes(), (tmp_path / "shapes.xdmf").read_bytes()
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "shapes.h5"), *SHORT)
    assert _one_line(out) and "mode shapes of a `dbf-hpc basis --xdmf`" in out.stderr, out.stderr
    assert ((tmp_path / "shapes.h5").read_bytes(), (tmp_path / "shapes.xdmf").read_bytes()) == shapes
    out = dbf_hpc_alone("info", str(tmp_path / "shapes.h5"))
    assert _one_line(out) and "mode shapes" in out.stderr, out.stderr
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "good.h5"), *SHORT)
    assert out.returncode == 0 and (tmp_path / "good.xdmf").exists()
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "good.h5"), *SHORT)
    assert out.returncode == 0, out.stderr


def test_an_output_records_the_values_set_on_the_command_line(tmp_path):
    import json

    import h5py

    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "set.h5"), *SHORT, "--set", "basis.modes=9",
                  "--set", "constraint.k_plus=2e6")
    assert out.returncode == 0, out.stderr
    with h5py.File(tmp_path / "set.h5") as f:
        effective = json.loads(f.attrs["scene_effective"])
    assert effective["basis"]["modes"] == 9 and effective["constraint"][0]["law"]["k_plus"] == 2e6
    assert effective["overrides"] == ["integrator.t_end=0.01", "basis.modes=9", "constraint.k_plus=2e6"]


def test_an_option_petsc_refuses_is_one_line_and_leaves_no_file(tmp_path):
    for method, option in (("rom", "-rom_pc_type"), ("full", "-full_pc_type"), ("rom", "-modes_st_type")):
        target = tmp_path / f"{method}{option}.h5"
        out = dbf_hpc("run", PAPER, "-o", str(target), *SHORT, "--method", method, option, "bogus")
        assert _one_line(out) and "bogus" in out.stderr and "cannot write" not in out.stderr, out.stderr
        assert not list(tmp_path.iterdir()), list(tmp_path.iterdir())


def test_an_integrator_option_that_would_void_the_estimate_is_refused_before_the_basis_is_built(tmp_path):
    # it was refused only when the integrator started, after the basis (minutes on a large model)
    out = dbf_hpc("run", PAPER, "-o", str(tmp_path / "r.h5"), "--set", "integrator.t_end=0.01", "-rom_ts_rtol", "0.1")
    assert _one_line(out) and "-rom_ts_rtol: set [integrator] rtol instead" in out.stderr, out.stderr
    assert "basis:" not in out.stdout and not list(tmp_path.iterdir()), out.stdout


def test_a_checkpoint_of_the_c_callbacks_is_not_resumed_with_the_python_ones(tmp_path):
    target = tmp_path / "cb.h5"
    common = ("--set", "integrator.t_end=20", "--set", "output.checkpoint_dt=0.01", "-q")
    _killed_after_a_checkpoint(target, *common)
    env = {**mpi_env(), "DBF_HPC_NO_C": "1"}
    out = subprocess.run(["mpirun", "-n", "2", sys.executable, "-m", "dbf_hpc.cli", "run", PAPER, "-o", str(target),
                          "--resume", *common], capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    lines = [line for line in out.stderr.splitlines() if line.strip() and "warning" not in line]
    assert out.returncode == 1 and len(lines) == 1 and "callbacks differ)" in lines[0], out.stderr


def test_info_on_a_partial_file_names_it_and_its_checkpoint(tmp_path):
    target = tmp_path / "part.h5"
    _killed_after_a_checkpoint(target, "--set", "integrator.t_end=20", "--set", "output.checkpoint_dt=0.01", "-q")
    for name in (target, f"{target}.partial"):
        out = dbf_hpc_alone("info", str(name))
        assert out.returncode == 0 and f"{target}.partial: INCOMPLETE" in out.stdout, out.stdout
        assert "a checkpoint exists" in out.stdout and ".partial.partial" not in out.stdout
        assert "constraint 1:" in out.stdout and "at 0:" not in out.stdout


def test_a_plot_window_without_samples_is_refused(tmp_path, short_run):
    run_out = _copy_of(short_run, tmp_path)
    for window in ("0.1:0.05", "5:6", "nan:1", "a:b", "0.01"):   # "0.01": which end?
        out = dbf_hpc_alone("plot", str(run_out), "-d", str(tmp_path / "figs"), "--window", window)
        assert _one_line(out), (window, out.stderr)


def test_a_plot_directory_that_is_a_file_is_refused_saying_so_and_the_file_is_kept(tmp_path, short_run):
    # New-user pass: "plot run.h5 -d run.h5" said "cannot be made: File exists".
    run_out = _copy_of(short_run, tmp_path)
    before = run_out.read_bytes()
    out = dbf_hpc_alone("plot", str(run_out), "-d", str(run_out))
    assert _one_line(out) and "is a file, not a directory" in out.stderr, out.stderr
    assert run_out.read_bytes() == before
    # red team: with a trailing '/' it said "cannot be made: File exists"; a named pipe "is a file"
    out = dbf_hpc_alone("plot", str(run_out), "-d", f"{run_out}/")
    assert _one_line(out) and f"{str(run_out) + '/'!r} is a file, not a directory" in out.stderr, out.stderr
    os.mkfifo(tmp_path / "pipe")
    out = dbf_hpc_alone("plot", str(run_out), "-d", str(tmp_path / "pipe"))
    assert _one_line(out) and "is a named pipe, not a directory: give -d a folder" in out.stderr, out.stderr
    assert run_out.read_bytes() == before



def test_a_run_whose_snapshot_data_cannot_be_read_is_plotted_as_one_line_naming_it_damaged(tmp_path):
    # Red team: an output that opens but whose snapshots' data address points past its end (damage to its
    # layout message) ended `dbf-hpc plot` in "internal error (OSError) on rank 0: Can't read data (addr
    # overflow ...)". It is the line a damaged file gets, as in `info`.
    from conftest import damage_data_address

    run_out = tmp_path / "w.h5"
    assert dbf_hpc("run", PAPER, "-o", str(run_out), "--set", "basis.estimate=false", *SHORT, ranks=1).returncode == 0
    damage_data_address(str(run_out), "snapshots/w")
    out = dbf_hpc_alone("plot", str(run_out), "-d", str(tmp_path / "figs"))
    assert _one_line(out) and "is damaged (Can't read data (addr overflow" in out.stderr, out.stderr

def test_a_plot_window_on_a_sweep_summary_is_refused_not_ignored(tmp_path):
    # New-user pass: `plot SUMMARY.h5 --window 1:2` drew the whole figures without a word.
    sweep = tmp_path / "s.toml"
    sweep.write_text(f'scene = "{PAPER}"\noutput = "s.h5"\n[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n'
                     '"integrator.t_end" = [0.01]\n')
    assert dbf_hpc("sweep", str(sweep), "-q", "--set", f"basis.cache={tmp_path}", ranks=1).returncode == 0
    out = dbf_hpc_alone("plot", str(tmp_path / "s.h5"), "-d", str(tmp_path / "figs"), "--window", "0:0.005")
    assert _one_line(out) and "a sweep's summary has no time axis" in out.stderr, out.stderr
    assert not (tmp_path / "figs").exists()
    assert dbf_hpc_alone("plot", str(tmp_path / "s.h5"), "-d", str(tmp_path / "figs")).returncode == 0


def test_a_windowed_plot_writes_beside_the_whole_run_figures_never_over_them(tmp_path, short_run):
    run_out = _copy_of(short_run, tmp_path)
    figs = tmp_path / "figs"
    assert dbf_hpc_alone("plot", str(run_out), "-d", str(figs)).returncode == 0
    whole = (figs / "time_histories.png").read_bytes()
    out = dbf_hpc_alone("plot", str(run_out), "-d", str(figs), "--window", "0.005:")
    assert out.returncode == 0, out.stderr
    windowed = sorted(p.name for p in figs.glob("*-*s.png"))
    assert {"time_histories_0.005-0.01s.png", "phase_0.005-0.01s.png", "forces_0.005-0.01s.png",
            "snapshots_0.005-0.01s.png"} <= set(windowed), windowed    # the snapshots too (they ignored it)
    assert (figs / "time_histories.png").read_bytes() == whole


def test_plot_of_an_output_with_a_dataset_missing_is_one_line_naming_it_damaged(tmp_path, short_run):
    # Red team: a finished run's file with one dataset gone (the solid's snapshot vectors, edited by
    # hand or cut short by a full disk) was "internal error (KeyError)" in plot; info already said
    # "is damaged". The velocities at the constraints are what the phase diagrams read.
    import h5py

    target = _copy_of(short_run, tmp_path)
    with h5py.File(target, "a") as f:
        del f["constraints/velocity"]
    out = dbf_hpc_alone("plot", str(target), "-d", str(tmp_path / "figs"))
    assert _one_line(out) and "is damaged" in out.stderr and "constraints/velocity" not in out.stdout, out.stderr
    assert "internal error" not in out.stderr


def test_a_checkpoint_is_not_resumed_in_a_basis_rebuilt_with_its_repeated_modes_turned(tmp_path):
    # Red team: a tube's modes come in pairs of one frequency; the pair's orientation depends on the
    # rank layout. A run on 1 rank used a basis cached by a 2-rank run; after the cache was cleared
    # the resume rebuilt it on 1 rank and continued q in it: the motion moved into the other plane.
    import signal

    scene = tmp_path / "pair.toml"
    scene.write_text('[structure]\nkind = "beam"\nlength = 1.0\nelements = 30\nE = 2e11\nI = 1e-9\nA = 1e-4\n'
                     'rho = 8000.0\nplanes = 2\n[[constraint]]\nx = 0.3\nlaw = "circular"\nclearance = 1.0\n'
                     'k = 1e6\n[initial]\nmode = 4\namplitude = 1e-4\ndirection = [1.0, 0.0]\n[basis]\nmodes = 10\n'
                     f'estimate = false\ncache = "{tmp_path / "cache"}"\n[integrator]\nt_end = 100.0\n[output]\n'
                     'sample_dt = 1e-3\ncheckpoint_dt = 0.5\n')
    seed = dbf_hpc("run", str(scene), "-q", "-o", str(tmp_path / "seed.h5"), "--set", "integrator.t_end=0.01")
    assert seed.returncode == 0, seed.stderr
    target = tmp_path / "pair.h5"
    process = subprocess.Popen(["mpirun", "-n", "1", sys.executable, "-m", "dbf_hpc.cli", "run", str(scene), "-q",
                                "-o", str(target)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               cwd=ROOT, env=mpi_env(), start_new_session=True)   # the 2-rank basis, cached
    _wait_for(f"{target}.checkpoint", process)
    _kill_group(process, signal.SIGTERM)
    assert dbf_hpc_alone("cache", "clear", "--dir", str(tmp_path / "cache")).returncode == 0
    out = dbf_hpc("run", str(scene), "-q", "-o", str(target), "--resume", ranks=1)
    assert _one_line(out) and "(coordinates differ; the basis was rebuilt since" in out.stderr, out.stderr


def test_a_report_piped_into_head_ends_quietly(tmp_path):
    # Red team: `dbf-hpc modes ... | head -1` ended in PETSc's signal handler (SIGPIPE) with its
    # debugger advice and an MPI_ABORT notice.
    cmd = f"{sys.executable} -m dbf_hpc.cli modes {PAPER} | head -1"
    out = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=120, cwd=ROOT, env=mpi_env())
    assert out.stdout.startswith("dbf-hpc ") and out.stderr == "", out.stderr


def test_a_commands_petsc_options_hold_for_that_command_only(capsys):
    # Red team: cli.main called twice in one process (a study script) ran the second command with the
    # first one's -modes_eps_tol, and dropped its own options with an "unused" warning. A command's
    # solver options now go in for its duration and the values from before come back.
    from petsc4py import PETSc

    from conftest import petsc_options
    from dbf_hpc.cli import main
    before = PETSc.Options().getAll()
    assert main(["modes", PAPER, "--set", "basis.modes=4", "-modes_eps_tol", "1e-9", "-modes_eps_conv_abs"]) == 0
    assert "was not used" not in capsys.readouterr().err        # the eigensolver read both
    assert PETSc.Options().getAll() == before
    with petsc_options(modes_eps_tol=1e-11):
        assert main(["modes", PAPER, "--set", "basis.modes=4", "-modes_eps_tol", "1e-9"]) == 0
        assert PETSc.Options().getString("modes_eps_tol") == "1e-11"
    assert PETSc.Options().getAll() == before


def test_the_programs_solver_options_reach_petsc_finalization_options_left_and_log_view(tmp_path):
    # Red team: a command's solver options were taken back when it ended, also at the end of the
    # program itself, so PETSc's finalization reported on a database without them: -options_left said
    # "There are no unused options." of a misspelled -modes_ option, and -log_view's option table
    # listed none of the solver options the run used. The program's options stay to its end.
    out = dbf_hpc("modes", PAPER, "--set", "basis.modes=4", "-modes_eps_tol", "1e-9", "-modes_eps_tolerance", "3",
                  "-modes_eps_target", "-1", "-options_left", "-options_view")
    assert out.returncode == 0, out.stderr
    assert "Option left: name:-modes_eps_tolerance value: 3" in out.stdout, out.stdout[-2000:]
    assert "There are no unused options" not in out.stdout
    table = out.stdout[out.stdout.index("#PETSc Option Table entries:"):]
    assert "-modes_eps_tol 1e-9" in table and "-modes_eps_target -1" in table, table
    assert "PETSc option -modes_eps_tolerance was not used" in out.stderr   # dbf-hpc's own line too


_ENVIRONMENT_OPTION = """
from dbf_hpc.cli import main
code = main(["modes", {paper!r}, "--set", "basis.modes=4", "-modes_eps_tol", "1e-9", "-modes_eps_view"])
from petsc4py import PETSc
print("after:", PETSc.Options().getString("modes_eps_tol"), code)
"""


def test_a_petsc_options_environment_value_comes_back_after_a_command_that_overrode_it(tmp_path):
    # Red team: the first command of a process (PETSc started with its options) took its solver
    # options back by deleting them, so a PETSC_OPTIONS value of the same name was gone for every later
    # command of the process. The command line still wins while the command runs (as in PETSc).
    script = tmp_path / "environment_option.py"
    script.write_text(_ENVIRONMENT_OPTION.format(paper=PAPER))
    env = {**mpi_env(), "PETSC_OPTIONS": "-modes_eps_tol 1e-11",
           "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=ROOT,
                         env=env)
    assert out.returncode == 0, out.stderr
    assert re.search(r"^\s*tolerance: 1e-09$", out.stdout, re.M), out.stdout[:3000]   # the command's value
    assert "after: 1e-11 0" in out.stdout, out.stdout[-500:]                           # the environment's again


@pytest.mark.parametrize("form", ["second_order", "state_space"])
def test_basis_prints_one_row_per_complex_mode_also_for_a_pair_of_bit_equal_frequencies(form):
    # a round shaft at rest, its two planes exactly alike: modes 2 and 3 share omega to the bit, and the table
    # printed np.unique of the columns' frequencies, 2 rows under "3 complex modes"
    from dbf_hpc.basis import BasisSettings, build_basis
    from dbf_hpc.cli import _print_basis
    from test_gyroscopic import shaft_at_rest

    ops, exact = shaft_at_rest(0.0)
    try:
        basis = build_basis(ops, [], BasisSettings(modes=3, enrichment="none", gyroscopic_form=form))
        try:
            lines = []
            _print_basis(lines.append, basis, [])
        finally:
            basis.destroy()
    finally:
        ops.destroy()
    rows = [line.split() for line in lines[1:] if line.split() and line.split()[0].isdigit()]
    assert [int(r[0]) for r in rows] == [1, 2, 3]
    np.testing.assert_allclose([float(r[1]) for r in rows], exact[:3], rtol=1e-7)
