"""errors.py: what every rank agrees on. An exception one rank raises while it decides for all
(decided_on_rank0) or reads its own share (agreed) is raised on every rank, as the same exception: a
user's error is every rank's one line, and a bug ends the job on every rank instead of leaving the
others waiting in a collective call."""
import errno

import pytest
from mpi4py import MPI

from conftest import assert_all, ends_a_hang
from dbf_hpc.errors import InputError, SolverError, agreed, decided_on_rank0
from dbf_hpc.modes import RepeatedCut

RAISED_ON_RANK_0 = [OSError(errno.EIO, "Input/output error"), FileNotFoundError(errno.ENOENT, "No such file", "x.h5"),
                    ValueError("a value rank 0 could not parse"), KeyError("attrs"), SolverError("rank 0 gave up"),
                    RepeatedCut("6 modes cut a repeated frequency", 5, 7)]


@pytest.mark.parametrize("raised", RAISED_ON_RANK_0, ids=lambda e: type(e).__name__)
def test_any_exception_rank_0_raises_as_it_decides_is_raised_on_every_rank_as_the_same_one(raised):
    # Red team: decided_on_rank0 passed an InputError on, and nothing else: an OSError, ValueError or
    # KeyError on rank 0 left the other ranks waiting in its broadcast for ever.
    def decide():
        raise raised

    with ends_a_hang(60):
        with pytest.raises(type(raised)) as caught:
            decided_on_rank0(MPI.COMM_WORLD, decide)
    e = caught.value
    assert_all(type(e) is type(raised) and str(e) == str(raised), f"{type(e).__name__}: {e}")
    assert_all(getattr(e, "errno", None) == getattr(raised, "errno", None)
               and getattr(e, "filename", None) == getattr(raised, "filename", None))
    if isinstance(raised, RepeatedCut):   # its own attributes too (basis.py reads them)
        assert_all((e.first, e.whole) == (5, 7))
    # rank 0 raises its own (its traceback); the others a copy that names the rank that raised it
    assert_all((e is raised) == (MPI.COMM_WORLD.rank == 0))
    assert_all(MPI.COMM_WORLD.rank == 0 or e.dbf_hpc_origin == 0)


def test_a_value_rank_0_decides_is_every_ranks():
    assert_all(decided_on_rank0(MPI.COMM_WORLD, lambda: ("decided", MPI.COMM_WORLD.rank)) == ("decided", 0))


@pytest.mark.parallel
def test_an_exception_on_rank_1_alone_as_every_rank_reads_is_raised_on_every_rank():
    # agreed: each rank reads its own share; an OSError on rank 1 alone left rank 0 in the next
    # collective call (only an InputError was shared)
    def work():
        if MPI.COMM_WORLD.rank == 1:
            raise OSError(errno.EIO, "rank 1 could not read its rows")
        return "read"

    with ends_a_hang(60):
        with pytest.raises(OSError, match="rank 1 could not read its rows") as caught:
            agreed(MPI.COMM_WORLD, work)
    assert_all(MPI.COMM_WORLD.rank == 1 or caught.value.dbf_hpc_origin == 1)


@pytest.mark.parallel
def test_the_first_failing_rank_in_rank_order_is_the_one_every_rank_raises():
    def work():
        raise InputError(f"rank {MPI.COMM_WORLD.rank} refused")

    with pytest.raises(InputError, match="^rank 0 refused$"):
        agreed(MPI.COMM_WORLD, work)


def test_a_recording_inside_another_that_holds_the_same_messages_ends_itself_and_the_outer_keeps_recording():
    # recording() removed its list with list.remove, which compares by ==: an inner recording ending with the
    # outer one's messages (both empty) removed the outer list, which then missed every later warning, and its
    # own end raised ValueError (red team: a rerun sweep whose pending cases were all refused before their basis
    # ended in "internal error (ValueError) on rank 0: list.remove(x): x not in list")
    from dbf_hpc.errors import recorded, recording, warn

    with recording() as outer:
        with recording() as inner:
            pass
        warn("after the inner one", MPI.COMM_WORLD)
        assert recorded() == ["after the inner one"]
    assert outer == ["after the inner one"] and inner == [] and recorded() == []
    with recording() as outer:
        warn("both", MPI.COMM_WORLD)
        with recording() as inner:
            warn("inner", MPI.COMM_WORLD)
        assert recorded() == ["both", "inner"]
    assert outer == ["both", "inner"] and inner == ["inner"] and recorded() == []


@pytest.mark.launcher   # starts the command as a process of its own (not under the 2-rank pass's mpirun)
def test_a_control_character_quoted_in_an_error_line_is_written_as_an_escape_not_raw(tmp_path):
    # Red team: a scene key "ze\u0000ta" (a TOML escape) was refused as "unknown key 'ze<NUL>ta' in [damping]",
    # the NUL byte written raw to stderr (and an escape sequence would reach the terminal); a line break was
    # already written as \n
    import subprocess
    import sys

    from dbf_hpc.errors import one_line
    from test_run import PAPER

    assert one_line("a\x00b\nc\rd\te\x1b[31m\x7f") == "a\\x00b\\nc\\rd\te\\x1b[31m\\x7f"
    scene = tmp_path / "nul.toml"
    scene.write_text(open(PAPER).read().replace("[integrator]", '[damping]\n"ze\\u0000ta" = 0.01\n\n[integrator]'))
    ended = subprocess.run([sys.executable, "-m", "dbf_hpc", "run", str(scene), "-o", str(tmp_path / "o.h5")],
                           capture_output=True, timeout=120)
    assert ended.returncode != 0 and b"\x00" not in ended.stderr, ended.stderr
    assert ended.stderr.decode().splitlines() == [f"dbf-hpc: error: {scene}: unknown key 'ze\\x00ta' in [damping] "
                                                  f"(valid keys: zeta, rayleigh_alpha, rayleigh_beta); did you "
                                                  f"mean 'zeta'?"], ended.stderr
