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

    from conftest import assert_all, damage_data_address
    from dbf_hpc.report import describe
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    paper = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "jobs", "paper_beam.toml")
    out = str(shared_tmp_path / "run.h5")
    run(load_scene(paper, ["integrator.t_end=0.01", "basis.estimate=false", "basis.cache=off"]), out, progress=False)
    # collective: every rank has read it before rank 0 damages it (rank 1, still reading, failed alone and the
    # job hung in the barrier below, 1 run in 4 on a loaded machine)
    assert_all(any("impacts" in line for line in describe(out)))
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


def test_info_prints_a_runs_frequencies_in_hz_its_state_count_and_each_constraints_range_and_peak_force(
        shared_tmp_path):
    # Mutation testing of report.py: `info` could print omega in rad/s as Hz, the basis's mode count as
    # its state count, constraint 1's peak force for every constraint, max w for min w, the probe's
    # largest w for its largest |w|, the second-last sample time as the end, twice the estimate as its
    # percentage: no test read its numbers.
    # Each against the output's own datasets (the A_r the run integrated gives the state count).
    import os

    import h5py

    from dbf_hpc.report import describe
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    belt = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "jobs", "moving_belt_guide.toml")
    scene = shared_tmp_path / "belt.toml"
    if MPI.COMM_WORLD.rank == 0:   # a second stop, closer than the guide's one side: two peak forces
        scene.write_text(open(belt).read() + '\n[[constraint]]\nx = 0.75\nlaw = "deadband"\nclearance = 5e-4\n'
                                              'k = 1e5\n')
    MPI.COMM_WORLD.Barrier()
    out = str(shared_tmp_path / "belt.h5")
    run(load_scene(str(scene), ["integrator.t_end=0.05", "basis.estimate=false", "basis.cache=off",
                                'basis.gyroscopic_form="state_space"']), out, progress=False)
    lines = describe(out)
    with h5py.File(out, "r") as f:
        hz = f["basis/omega"][:] / (2 * np.pi)
        states = f["reduced/M"].shape[0]
        t, z, force, w = (f[name][:] for name in ("time", "constraints/displacement", "constraints/force_peak",
                                                  "probes/displacement"))
    peak = np.abs(force).max(axis=0)
    # the checks can fail: two different peaks, the probe's largest excursion negative, rad/s is not Hz
    assert peak.size == 2 and abs(peak[0] / peak[1] - 1) > 1e-3 and np.abs(w[:, 0]).max() > w[:, 0].max()
    text = "\n".join(lines)
    assert f"8 complex modes ({hz.min():.4g} ... {hz.max():.4g} Hz), 2 DBFs; state space: {states} real states" in text, \
        text
    assert 30 < hz.min() < 50 and states == 2 * (8 + 2)   # 41 Hz, the belt's first; 2 (N + N_L) states
    assert f"samples: {t.size} from 0 to {t[-1]:g} s" in text and abs(t[-1] - 0.05) < 1e-12
    for j in range(2):
        assert (f"  constraint {j + 1} at {(0.3, 0.75)[j]:g} m: w in [{z[:, j].min():.6g}, {z[:, j].max():.6g}] m, "
                f"peak force {peak[j]:.6g} N;") in text, text
    assert f"  probe at 0.5 m: peak |w| {np.abs(w[:, 0]).max():.6g} m" in text
    # the estimate's line (written here: this run had none) gives the relative error as a percentage
    MPI.COMM_WORLD.Barrier()   # every rank has closed the file
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(out, "a") as f:
            f.attrs.update(estimated_error=0.0123, estimated_error_window=0.05, estimated_error_note="richer basis")
    MPI.COMM_WORLD.Barrier()
    assert ("  estimated error in w at the constraints: 0.0123 (1.23% of the largest |w| at any constraint) over "
            "[0, 0.05] s (richer basis)") in describe(out)


def test_info_of_a_partial_two_direction_run_bounds_the_peak_force_by_the_hypot_of_its_components(shared_tmp_path):
    # A .partial holds no statistics: a support of two directions prints max |u| and "peak |F| at most" the
    # hypot of the interval peaks of F_y and F_z (reached at different instants). Written here: the peaks
    # (-1, 4) N give 4.12 N, not the 4 N of the larger component; (3e-4, -4e-4) m gives 5e-4 m.
    import h5py

    from dbf_hpc.report import describe

    target = str(shared_tmp_path / "orbit.h5")
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(target + ".partial", "w") as f:
            f.create_dataset("time", data=[0.0, 0.1, 0.2])
            f.create_dataset("constraints/displacement", data=[[[0.0, 0.0]], [[3e-4, -4e-4]], [[1e-4, 1e-4]]])
            f.create_dataset("constraints/force_peak", data=[[[0.0, 0.0]], [[3.0, -1.0]], [[-1.0, 4.0]]])
            f.attrs["complete"] = False
    MPI.COMM_WORLD.Barrier()
    lines = describe(target)
    assert "INCOMPLETE" in lines[0] and "(3 samples up to t = 0.2 s)" in lines[0]
    assert "  constraint 1: max |u| 0.0005 m, peak |F| at most 4.12311 N" in lines, lines


def test_info_of_a_sweep_counts_its_failed_cases_sums_a_cases_impacts_and_names_the_support_of_the_largest_work_rate(
        shared_tmp_path):
    # _sweep_lines against a summary written here with known numbers: 3 cases, one failed; case 1's impacts
    # 2 + 5 at its two supports, its largest work rate 0.5 W at support 2 (support 1: 0.1 W, 3: NaN).
    import json

    import h5py

    from dbf_hpc.report import describe

    path = str(shared_tmp_path / "summary.h5")
    if MPI.COMM_WORLD.rank == 0:
        nan = float("nan")
        with h5py.File(path, "w") as f:
            f.attrs["sweep"] = json.dumps({"scene": "tube.toml", "parameters": ["excitation.frequency_hz"]})
            f.create_dataset("cases/status", data=["ok", "failed", "ok"])
            f.create_dataset("cases/error", data=["", "the stop was never reached", ""])
            f.create_dataset("cases/warnings", data=["", "", ""])
            f.create_dataset("cases/parameters/excitation.frequency_hz", data=[10.0, 20.0, 30.0])
            f.create_dataset("cases/stats/displacement_peak", data=[[1e-3, 2e-3, 5e-4], [nan] * 3, [1e-3] * 3])
            f.create_dataset("cases/stats/impacts", data=[[2.0, 5.0, 0.0], [nan] * 3, [1.0, 1.0, 1.0]])
            f.create_dataset("cases/stats/force_peak", data=[[3.0, 7.0, 0.0], [nan] * 3, [1.0, 1.0, 1.0]])
            f.create_dataset("cases/stats/work_rate", data=[[0.1, 0.5, nan], [nan] * 3, [0.2, 0.1, 0.3]])
            f.create_dataset("cases/stats/work_rate_ci95", data=[[0.01, 0.05, nan], [nan] * 3, [0.02, 0.01, 0.03]])
    MPI.COMM_WORLD.Barrier()
    lines = describe(path)
    assert lines[0].endswith("sweep of tube.toml, 3 cases (2 ok, 1 failed)"), lines
    assert lines[2] == ("  case 1 (frequency_hz 10): max |w| 0.002 m, 7 impacts at the 3 constraint(s) together, "
                        "peak force 7 N, max work rate 0.5 W +- 0.05 W (constraint 2)"), lines
    assert lines[3] == "  case 2 (frequency_hz 20): FAILED: the stop was never reached"
    assert lines[4].endswith("max work rate 0.3 W +- 0.03 W (constraint 3)")


@pytest.mark.parametrize("make, said", [
    ("fifo", "is a named pipe, not a dbf-hpc output: give a run's output or a sweep's summary"),
    ("directory", "is a directory, not a dbf-hpc output: give a run's output or a sweep's summary"),
    ("broken link", "is a symbolic link to a missing file, not a dbf-hpc output: give a run's output or a sweep's "
                    "summary"),
    ("file/", "ends in '/' but '{file}' is a file: give it without the '/'")])
def test_info_and_plot_on_what_is_no_regular_file_say_what_it_is_and_never_wait_on_it(shared_tmp_path, make, said):
    # Red team: `dbf-hpc info FIFO` (and plot, a directory with a .partial beside it, a device, a broken link,
    # an output given with a trailing '/') said "does not exist"
    from conftest import ends_a_hang, fifo_at

    path = str(shared_tmp_path / "out.h5")
    if make == "fifo":
        fifo_at(path)
    elif MPI.COMM_WORLD.rank == 0:
        open(path + ".partial", "w").close()   # not taken for the run's .partial when the output is there
        if make == "directory":
            (shared_tmp_path / "out.h5").mkdir()
        elif make == "broken link":
            (shared_tmp_path / "out.h5").symlink_to(shared_tmp_path / "gone.h5")
        else:
            open(path, "w").close()
    MPI.COMM_WORLD.Barrier()
    given = path + "/" if make == "file/" else path
    with ends_a_hang(60), pytest.raises(InputError) as refused:
        open_output(given)
    assert str(refused.value) == f"{given!r} " + said.format(file=path)


def test_info_on_a_character_device_says_so():
    with pytest.raises(InputError, match="^'/dev/null' is a character device, not a dbf-hpc output"):
        open_output("/dev/null")
