"""report.py: what `dbf-hpc info` and `plot` say of a file that is dbf-hpc's but not a run's output."""
import glob

import numpy as np
import pytest
from mpi4py import MPI

from dbf_hpc import BaseMotion, BasisSettings, Beam, Constraint, FullOrderModel, Reductor, law
from dbf_hpc.checkpoint import Checkpoint, identity
from dbf_hpc.errors import InputError
from dbf_hpc.report import open_output


def test_a_checkpoint_given_to_info_is_named_a_checkpoint_and_the_run_output_to_give_instead(shared_tmp_path):
    # New-user pass: `dbf-hpc info OUT.h5.checkpoint` said only "is not a dbf-hpc output".
    path = str(shared_tmp_path / "run.h5.checkpoint")
    if MPI.COMM_WORLD.rank == 0:
        Checkpoint(path, identity(scene="x")).write({"q": np.zeros(3), "t": 0.5})
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError) as refused:
        open_output(path)
    assert str(refused.value) == (f"{path!r} is a run's checkpoint (its state, not its samples): give the run's "
                                  f"output, {path[:-len('.checkpoint')]!r}")


def test_a_cached_basis_given_to_info_is_named_a_cached_basis(shared_tmp_path):
    cache = str(shared_tmp_path / "cache")
    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=10)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0)) as fom:
        with Reductor(fom, BasisSettings(modes=2), cache_dir=cache) as reductor:
            reductor.reduce()
    stored = glob.glob(f"{cache}/basis-*.h5")
    assert len(stored) == 1, stored
    with pytest.raises(InputError, match="is a cached basis, not a run: `dbf-hpc cache list` describes it$"):
        open_output(stored[0])


def test_an_output_whose_statistics_cannot_be_read_is_named_damaged_not_an_internal_error(shared_tmp_path):
    # Red team (bytes flipped across a finished output's metadata): where the file opens but a dataset's
    # data address points past its end, `dbf-hpc info` ended in "internal error (OSError) on rank 0: Can't
    # read data (addr overflow ...)". It is one line naming the file damaged.
    import os

    from conftest import damage_data_address
    from dbf_hpc.report import describe
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    paper = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "jobs", "paper_beam.toml")
    out = str(shared_tmp_path / "run.h5")
    run(load_scene(paper, ["integrator.t_end=0.01", "basis.estimate=false", "basis.cache=off"]), out, progress=False)
    assert any("impacts" in line for line in describe(out))
    if MPI.COMM_WORLD.rank == 0:
        damage_data_address(out, "constraints/stats/impacts")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"is damaged \(Can't read data \(addr overflow"):
        describe(out)


def test_an_output_whose_root_links_cannot_be_read_is_named_damaged_by_info_and_plot(shared_tmp_path):
    # Red team: an output whose root group's link names cannot be read (its local heap damaged) opens, and
    # the look at what it holds raised h5py's RuntimeError: "internal error (RuntimeError) on rank 0: Unable
    # to get link info (bad local heap signature)" from `info` and `plot` (both open it with open_output).
    import os

    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    paper = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "jobs", "paper_beam.toml")
    out = shared_tmp_path / "run.h5"
    run(load_scene(paper, ["integrator.t_end=0.01", "basis.estimate=false", "basis.cache=off"]), str(out),
        progress=False)
    if MPI.COMM_WORLD.rank == 0:
        data = out.read_bytes()
        at = data.index(b"HEAP")   # the root group's local heap, the file's first
        out.write_bytes(data[:at] + b"XXXX" + data[at + 4:])
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"is damaged \(Unable to get link info \(bad local heap signature"):
        open_output(str(out))
