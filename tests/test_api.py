"""The README's Python API example runs as written, and the objects it uses behave as the core's
tests say: the reduced model agrees with the full-order model before the first impact."""
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from conftest import assert_all, undestroyed_petsc_objects

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def readme_example() -> str:
    text = open(os.path.join(ROOT, "README.md")).read()
    section = text[text.index("## Python API"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.launcher
def test_the_readme_python_example_runs_as_written_and_the_reduced_beam_stays_at_the_stop(tmp_path):
    script = tmp_path / "example.py"
    script.write_text(readme_example())
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path,
                         timeout=600, env=dict(os.environ))
    assert out.returncode == 0, out.stderr
    found = re.search(r"max \|w\(0.25 m\)\|: ([\d.]+) mm, full order ([\d.]+) mm", out.stdout)
    assert found, out.stdout
    reduced, full = (float(v) for v in found.groups())
    assert abs(reduced - 2.5) < 0.05 and abs(full - 2.5) < 0.05, "both reach the stop at 2.5 mm and stay there"
    assert re.search(r"reduced: [1-9]\d* impacts", out.stdout), "the stop is hit"
    error = float(re.search(r"error in w: ([\d.]+)%", out.stdout).group(1)) / 100
    assert 0.01 < error < 0.15, "6 modes: 8.7 %, measured (README says so)"
    impacts = [int(v) for v in re.findall(r"(\d+) impacts", out.stdout)]
    assert impacts[1] > 10 * impacts[0], "the full model chatters (88 impacts against 1, measured)"


def test_the_example_objects_agree_with_the_full_order_model_before_the_first_impact():
    from dbf_hpc import (Beam, BaseMotion, BasisSettings, Constraint, FullOrderModel, IntegratorSettings,
                         Reductor, law, simulate_full, simulate_reduced)

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=40)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0), probes=[0.5]) as fom:
        with Reductor(fom, BasisSettings(modes=10)) as reductor:
            rom = reductor.reduce()
        truth = simulate_full(fom, IntegratorSettings(t_end=0.1, dt=1e-5, sample_dt=1e-3))
    result = simulate_reduced(rom, IntegratorSettings(t_end=0.1, sample_dt=1e-3, rtol=1e-8, atol=1e-12))
    w, w_truth = result.displacement[:, 0], truth.displacement[:, 0]
    assert_all(np.abs(w_truth).max() < 2.5e-3, "no impact before 0.1 s")
    # Before the first impact both are linear: they differ by the modal truncation (10 modes + DBF)
    # and the full model's time step.
    assert_all(np.abs(w - w_truth).max() < 1e-3 * np.abs(w_truth).max())
    assert_all(result.q.shape == (101, rom.size) and truth.q.shape == (101, 0))


@pytest.mark.parametrize("make,message", [
    (lambda api: api.Constraint("deadband", x=0.25), "Constraint law: give law"),
    (lambda api: api.Constraint(api.law("deadband", clearance=1e-3, k=1e6)), "give its place"),
    (lambda api: api.BasisSettings(modes="6"), "BasisSettings modes must be an integer"),
    (lambda api: api.BasisSettings(modes=0), "BasisSettings modes must be at least 1"),
    (lambda api: api.FullOrderModel.build(api.Beam(length=1.0, E=1e11, I=1e-12, A=1e-6, rho=8e3, elements=4),
                                          comm=3), "comm must be a petsc4py or mpi4py communicator"),
    (lambda api: api.IntegratorSettings(t_end=-1), "IntegratorSettings t_end must be above 0"),
    (lambda api: api.IntegratorSettings(t_end=1e3, sample_dt=1e-9), "1e\\+12 samples"),
    (lambda api: api.BaseMotion(amplitude="5e-3", frequency_hz=1.0), "BaseMotion amplitude must be a finite"),
    (lambda api: api.Reductor(6), "Reductor reduces a FullOrderModel"),
    (lambda api: api.simulate_reduced(None, {"t_end": 0.01}), "give IntegratorSettings"),
    (lambda api: api.simulate_reduced(None, api.IntegratorSettings(t_end=0.01), say="progress"),
     "simulate_reduced say: give a function"),
    (lambda api: api.IntegratorSettings(t_end=1, adaptive="no"), "adaptive must be True or False"),
    (lambda api: api.IntegratorSettings(t_end=1, contact="bogus"), "contact must be"),
    (lambda api: api.BasisSettings(dbf_derivative="bogus"), "dbf_derivative must be one of"),
    (lambda api: api.PointForce(amplitude=1.0, frequency_hz=1.0), "PointForce: give where it acts"),
    (lambda api: api.Harmonic(amplitude=float("nan"), frequency_hz=1.0), "Harmonic amplitude must be a finite number"),
    (lambda api: api.Harmonic(amplitude=1.0, frequency_hz=-1.0), "Harmonic frequency_hz \\(Hz\\) must be at least 0"),
    (lambda api: api.Harmonic(amplitude=1.0, frequency_hz=1.0, phase="0"), "Harmonic phase \\(rad\\) must be a finite"),
])
def test_the_python_api_refuses_a_wrong_value_where_it_is_given(make, message):
    # New-user pass: these failed later as TypeError, IndexError, AttributeError or a 7 TiB MemoryError.
    import dbf_hpc

    with pytest.raises(dbf_hpc.InputError, match=message):
        make(dbf_hpc)


@pytest.mark.parametrize("make,message", [
    (lambda api: api.PointForce(amplitude=1.0, frequency_hz=0.0, x=0.5), "PointForce frequency_hz .* must be above 0"),
    (lambda api: api.BaseMotion(amplitude=1e-3, frequency_hz=0.0), "BaseMotion frequency_hz .* must be above 0"),
    (lambda api: api.PointForce(amplitude=1.0, frequency_hz=5.0, x="0.5"), "PointForce x \\(m\\) must be a finite"),
    (lambda api: api.PointForce(amplitude=1.0, frequency_hz=5.0, x=True), "PointForce x \\(m\\) must be a finite"),
    (lambda api: api.PointForce(amplitude=1.0, frequency_hz=5.0, dof=-1), "PointForce dof must be at least 0"),
    (lambda api: api.FullOrderModel.build(api.Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=4),
                                          [], api.PointForce(amplitude=1.0, frequency_hz=5.0, dof=3)),
     "the PointForce needs x \\(m\\) on a Beam"),
])
def test_a_harmonic_load_of_no_frequency_or_of_no_place_on_the_structure_is_refused_where_it_is_given(make, message):
    # sin(2 pi 0 t) = 0: a 0 Hz force or support motion is no load at all, whatever its amplitude (a
    # scene refuses it; the API ran the structure at rest). x = "0.5" and a dof on a beam were a
    # TypeError, x = True a force at x = 1 m (red team).
    import dbf_hpc

    with pytest.raises(dbf_hpc.InputError, match=message):
        make(dbf_hpc)


@pytest.mark.parametrize("make,message", [
    (lambda d, beam: ([d.Constraint(d.law("deadband", clearance=2.5, k=1e6), x=0.25)], d.NoExcitation(), d.InitialState()),
     r"^FullOrderModel.build: constraint 1: clearance = 2.5 m is more than the beam's length \(1 m\)"),
    (lambda d, beam: ([d.Constraint(d.law("deadband", clearance_minus=1e-3, clearance_plus=3.0, k=1e6), x=0.25)],
                      d.NoExcitation(), d.InitialState()),
     r"^FullOrderModel.build: constraint 1: clearance_plus = 3 m .*, or set k_plus = 0 for a side without a stop$"),
    (lambda d, beam: ([], d.BaseMotion(amplitude=5.0, frequency_hz=20.0), d.InitialState()),
     r"^FullOrderModel.build: BaseMotion: amplitude = 5 m, the support's motion, is more than the beam's length"),
    (lambda d, beam: ([], d.NoExcitation(), d.InitialState(amplitude=3.0)),
     r"^FullOrderModel.build: InitialState: amplitude = 3 m, the peak initial displacement, is more than"),
])
def test_the_api_refuses_a_stop_or_a_motion_farther_than_the_beams_length_as_a_scene_does(make, message):
    # A linear (small-deflection) beam never moves by its own length: a stop, a support motion or an initial
    # displacement beyond it is a unit slip (2.5 mm given as 2.5). A scene refused them (scene.py); the API
    # built the model, ran it, and only warned after the run that the stop was never reached.
    import dbf_hpc

    beam = dbf_hpc.Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    constraints, excitation, initial = make(dbf_hpc, beam)
    before = undestroyed_petsc_objects()
    with pytest.raises(dbf_hpc.InputError, match=message):
        dbf_hpc.FullOrderModel.build(beam, constraints, excitation, initial=initial)
    assert undestroyed_petsc_objects() == before
    # at the length itself, and a side without a stop, it is the user's to judge
    kept = [dbf_hpc.Constraint(dbf_hpc.law("deadband", clearance=1.0, k=1e6), x=0.25),
            dbf_hpc.Constraint(dbf_hpc.law("deadband", clearance_minus=1e-3, clearance_plus=5.0, k_minus=1e6, k_plus=0.0),
                               x=0.5)]
    with dbf_hpc.FullOrderModel.build(beam, kept, initial=dbf_hpc.InitialState(amplitude=1.0)) as fom:
        assert fom.constraints.count == 2


def test_the_models_are_refused_by_the_simulation_of_the_other_kind():
    from dbf_hpc import (Beam, BaseMotion, BasisSettings, Constraint, FullOrderModel, InputError, IntegratorSettings,
                         Reductor, law, simulate_full, simulate_reduced)

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    with pytest.raises(InputError, match="a list of Constraint"):
        FullOrderModel.build(beam, stop, BaseMotion(amplitude=5e-3, frequency_hz=1.0))
    with pytest.raises(InputError, match="constraint 1 is a dict, not a Constraint"):
        FullOrderModel.build(beam, [{"x": 0.25}], BaseMotion(amplitude=5e-3, frequency_hz=1.0))
    with pytest.raises(InputError, match="constraint 1 needs x"):
        FullOrderModel.build(beam, [Constraint(stop.law, dof=5)], BaseMotion(amplitude=5e-3, frequency_hz=1.0))
    settings = IntegratorSettings(t_end=0.01)
    with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0)) as fom:
        with pytest.raises(InputError, match="Reductor settings: give BasisSettings"):
            Reductor(fom, 6)
        with pytest.raises(InputError, match="Reductor cache_dir: give a directory path"):   # a TypeError before
            Reductor(fom, BasisSettings(modes=4), cache_dir=5)
        with pytest.raises(InputError, match="simulate_reduced integrates a reduced model"):
            simulate_reduced(fom, settings)
        with Reductor(fom, BasisSettings(modes=4)) as reductor:
            rom = reductor.reduce()
        with pytest.raises(InputError, match="simulate_full integrates a FullOrderModel"):
            simulate_full(rom, settings)
        with pytest.raises(InputError, match="snapshots must be at least 0"):
            simulate_reduced(rom, settings, snapshots=-1)


def test_simulate_reduced_takes_every_sample_for_more_snapshots_than_samples_and_warns_once(capfd):
    # Red team: snapshots=50 over 11 samples returned 11 snapshots without a word.
    from mpi4py import MPI

    from dbf_hpc import (Beam, BaseMotion, BasisSettings, Constraint, FullOrderModel, IntegratorSettings, Reductor,
                         law, simulate_reduced)

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0)) as fom:
        with Reductor(fom, BasisSettings(modes=4)) as reductor:
            rom = reductor.reduce(field=True)
    capfd.readouterr()
    settings = IntegratorSettings(t_end=0.01, sample_dt=1e-3)
    for _ in range(2):
        result = simulate_reduced(rom, settings, snapshots=50)
        assert_all(np.array_equal(result.snapshot_time, settings.sample_times))
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert err.count("dbf-hpc: warning: simulate_reduced snapshots = 50 is more than the 11 output samples "
                         "(t_end = 0.01 s at sample_dt = 0.001 s)") == 1, err
    assert simulate_reduced(rom, settings, snapshots=11).snapshot_time.size == 11
    assert "snapshots" not in capfd.readouterr().err


def test_a_full_order_model_used_after_its_with_block_is_refused_and_its_reduced_model_lives_on():
    # New-user pass: a Reductor or simulate_full on a closed model touched freed PETSc objects: SEGV.
    from dbf_hpc import (Beam, BaseMotion, BasisSettings, Constraint, FullOrderModel, InputError, IntegratorSettings,
                         Reductor, law, simulate_full, simulate_reduced)

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0)) as fom:
        reductor = Reductor(fom, BasisSettings(modes=4))
        with reductor:
            rom = reductor.reduce()
    settings = IntegratorSettings(t_end=0.01, dt=1e-5, adaptive=False)
    for use in (lambda: Reductor(fom, BasisSettings(modes=4)), lambda: reductor.reduce(),
                lambda: simulate_full(fom, settings), lambda: fom.__enter__(), lambda: fom.size):
        with pytest.raises(InputError, match="FullOrderModel was destroyed"):
            use()
    fom.destroy()   # a second destroy does nothing
    # the reduced model holds numpy arrays only: it outlives the full-order model
    assert_all(simulate_reduced(rom, IntegratorSettings(t_end=0.01, sample_dt=1e-3)).q.shape == (11, rom.size))


@pytest.mark.parametrize("change,message", [
    ({"structure": "beam"}, "a structure is a Beam or MatrixFiles, got str"),
    ({"excitation": None}, "excitation must be NoExcitation or BaseMotion"),
    ({"damping": 0.01}, "damping must be Damping, got float"),
    ({"initial": {"amplitude": 1e-3}}, "initial must be InitialState, got dict"),
    ({"probes": [1.5]}, "probe at x = 1.5 m is outside the beam \\[0, 1\\] m"),
    ({"probes": [-0.5]}, "probe at x = -0.5 m is outside the beam"),
    ({"probes": ["a"]}, "probe x \\(m\\) must be a finite number, got 'a'"),
])
def test_full_order_model_build_refuses_a_wrong_argument_by_name(change, message):
    # New-user pass: these failed deep inside as AttributeError or ValueError, and a probe beyond the
    # end of the beam was silently extrapolated from the last element's shape functions (a point
    # off the structure has no displacement).
    from dbf_hpc import Beam, BaseMotion, Constraint, FullOrderModel, InputError, law

    args = {"structure": Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20),
            "constraints": [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)],
            "excitation": BaseMotion(amplitude=5e-3, frequency_hz=1.0), **change}
    with pytest.raises(InputError, match=message):
        FullOrderModel.build(**args)


def test_a_probe_given_as_one_number_is_one_probe_at_that_x():
    from dbf_hpc import Beam, BaseMotion, FullOrderModel

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    with FullOrderModel.build(beam, [], BaseMotion(amplitude=5e-3, frequency_hz=1.0), probes=0.5) as fom:
        assert_all(fom.probes.count == 1 and fom.probes.positions[0] == 0.5)


@pytest.mark.parametrize("make,message", [
    (lambda api: api.BaseMotion(amplitude=1e-3, frequency_hz=1.0, direction=(0.0, 0.0)), "direction must be \\(dy, dz\\)"),
    (lambda api: api.PointForce(amplitude=1.0, frequency_hz=1.0, x=0.5, direction=(0.0, 0.0, 1.0)),
     "PointForce direction must be \\(dy, dz\\)"),
    (lambda api: api.BaseMotion(amplitude=1e-3, frequency_hz=1.0, end="middle"), 'end must be "left" or "right"'),
    (lambda api: api.InitialState(mode=0, amplitude=1e-3), "InitialState mode must be at least 1"),
    (lambda api: api.InitialState(amplitude="1e-3"), "InitialState amplitude must be a finite number"),
    (lambda api: api.InitialState(velocity_direction=(0, 0)), "InitialState velocity_direction must be"),
    (lambda api: api.RandomForce(psd=-1.0, band=(1.0, 100.0)), "RandomForce psd .* must be above 0"),
    (lambda api: api.RandomForce(psd=1.0, band=(100.0, 1.0)), "RandomForce band must be .* f_low < f_high"),
    (lambda api: api.RandomForce(psd=1.0, band=(1.0, 100.0), span=(1.0, 0.0)), "span must be .* x0 < x1"),
    (lambda api: api.Turbulence(psd="1", band=(1.0, 100.0), correlation_length=0.1), "psd must be a number"),
])
def test_excitation_and_initial_state_refuse_a_wrong_value_where_it_is_given(make, message):
    # New-user pass: a zero direction gave no forcing at all, a reversed span no load, a negative PSD
    # or reversed band NaN forces (a SolverError at t = 0), a wrong end the right end.
    import dbf_hpc

    with pytest.raises(dbf_hpc.InputError, match=message):
        make(dbf_hpc)


def test_a_direction_is_only_a_direction_its_magnitude_is_the_amplitude():
    # New-user pass: direction (3, 4) moved the support, pushed the tube or displaced it 5 times the
    # amplitude (the docstrings call it a unit vector; a scene's was scaled, a script's was not).
    from dbf_hpc import BaseMotion, Beam, FullOrderModel, InitialState, PointForce

    assert BaseMotion(amplitude=1e-3, frequency_hz=1.0, direction=(3, 4)).direction == pytest.approx((0.6, 0.8))
    assert InitialState(amplitude=1e-3, direction=(0, -2)).direction == (0.0, -1.0)
    tube = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=10, planes=2)
    norms = []
    for direction in ((3.0, 4.0), (0.6, 0.8)):
        with FullOrderModel.build(tube, [], PointForce(amplitude=1.0, frequency_hz=1.0, x=0.5,
                                                       direction=direction)) as fom:
            norms.append(fom.force_load.norm())
    assert_all(abs(norms[0] - 1.0) < 1e-15 and norms[0] == norms[1], "a unit force, whatever the direction's length")


def test_a_beam_bending_in_one_plane_refuses_a_direction_or_an_initial_velocity():
    # New-user pass: both were ignored (the beam moved along y, from rest).
    from dbf_hpc import BaseMotion, Beam, FullOrderModel, InitialState, InputError

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=10)
    with pytest.raises(InputError, match="applies to a beam of two planes"):
        FullOrderModel.build(beam, [], BaseMotion(amplitude=1e-3, frequency_hz=1.0, direction=(0.0, 1.0)))
    with pytest.raises(InputError, match="applies to a beam of two planes"):
        FullOrderModel.build(beam, [], initial=InitialState(amplitude=1e-3, velocity=0.1))


def test_a_random_force_without_a_span_loads_the_whole_beam():
    # New-user pass: RandomForce's default span () was a TypeError deep inside build.
    from dbf_hpc import Beam, FullOrderModel, RandomForce

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=10)
    loads = []
    for span in ((), (0.0, 1.0)):
        with FullOrderModel.build(beam, [], RandomForce(psd=1.0, band=(1.0, 100.0), span=span)) as fom:
            loads.append(fom.force_load.sum())
    # the consistent load of a unit load per length over the free DOFs: the total minus the pinned
    # ends' shares (h / 2 each), h = 0.1 m
    assert_all(abs(loads[0] - 0.9) < 1e-12 and loads[0] == loads[1])


@pytest.mark.parametrize("change,message", [
    ({"elements": True}, "beam elements must be an integer, got True"),
    ({"length": True}, "beam length must be a finite number, got True"),
    ({"length": -1.0}, "beam length must be above 0"),
    ({"supports": 0.5}, "beam supports must be a sequence of x \\(m\\), got 0.5"),
    ({"supports": ("a",)}, "beam support x \\(m\\) must be a finite number, got 'a'"),
])
def test_a_beam_refuses_a_wrong_value_by_name(change, message):
    # New-user pass: a bool was a 1-element or 1 m beam, a bare number or a string among the supports
    # a TypeError.
    from dbf_hpc import Beam, InputError

    with pytest.raises(InputError, match=message):
        Beam(**{"length": 1.0, "E": 117e9, "I": 8.78e-16, "A": 2.9e-7, "rho": 11800.0, **change})


def test_a_beam_from_numpy_numbers_is_the_beam_from_python_numbers():
    # New-user pass: elements = np.int64(10) (from np.arange or a sweep) was refused as "must be a
    # positive integer, got 10"; an int length gave another cache key than the same float length.
    from dbf_hpc import Beam

    values = {"E": 117e9, "I": 8.78e-16, "A": 2.9e-7, "rho": 11800.0}
    assert Beam(length=np.float64(1.0), elements=np.int64(10), supports=[np.float64(0.5)], **values) == \
        Beam(length=1, elements=10, supports=(0.5,), **values)
    assert type(Beam(length=1, elements=np.int64(10), **values).elements) is int


@pytest.mark.parametrize("planes,law_keys", [(1, {"law": "deadband", "clearance": 2.5e-3, "k": 1e6}),
                                             (2, {"law": "circular", "clearance": 2.5e-3, "k": 1e6})])
def test_an_initial_mode_the_structure_does_not_have_is_refused_without_leaving_a_petsc_object(planes, law_keys):
    # Review: initial_displacement and two_plane_state made u (and u') before the eigensolve that refuses
    # the mode, and the refusal left them undestroyed (in parallel they pile up in PETSc's garbage).
    from dbf_hpc import Beam, Constraint, FullOrderModel, InitialState, InputError, law

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=10, planes=planes)
    keys = dict(law_keys)
    stop = Constraint(law(keys.pop("law"), **keys), x=0.25)
    with FullOrderModel.build(beam, [stop], initial=InitialState(mode=500, amplitude=1e-3)) as fom:
        before = undestroyed_petsc_objects()
        with pytest.raises(InputError, match=r"\[initial\] mode = 500") as refused:
            fom.initial_state()
        # the refusal's traceback (still held here) keeps every local of the frames that raised alive
        assert_all(refused.value is not None and undestroyed_petsc_objects() == before)


@pytest.mark.parametrize("option,value,stage", [("rom_ts_type", "nonsense", "the reduced integration"),
                                                ("modes_eps_type", "bogus", "the basis"),
                                                ("full_ksp_type", "nonexistent", "the full-order integration")])
def test_a_solver_option_petsc_refuses_reaches_the_api_caller_as_one_line_naming_it(option, value, stage):
    # Red team: an option PETSc refuses reached the Python API's caller as a bare petsc4py.PETSc.Error
    # with PETSc's multi-line traceback (the command line printed one line). Now a SolverError of one
    # line naming the stage and the option, on every rank (this test runs on each rank under mpirun:
    # a rank that did not raise would fail it), and no PETSc object left behind.
    from petsc4py import PETSc

    from conftest import petsc_options
    from dbf_hpc import (Beam, BaseMotion, BasisSettings, Constraint, FullOrderModel, IntegratorSettings, Reductor,
                         SolverError, law, simulate_full, simulate_reduced)

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    before = undestroyed_petsc_objects()
    raised = None
    with petsc_options(**{option: value}):
        try:
            with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0), probes=[0.5]) as fom:
                if option.startswith("full_"):
                    simulate_full(fom, IntegratorSettings(t_end=1e-3, dt=1e-4, sample_dt=1e-4))
                else:
                    with Reductor(fom, BasisSettings(modes=4)) as reductor:
                        rom = reductor.reduce()
                    simulate_reduced(rom, IntegratorSettings(t_end=1e-2, sample_dt=1e-3))
        except (SolverError, PETSc.Error) as e:
            raised = e
    assert_all(isinstance(raised, SolverError), f"a SolverError, not {type(raised).__name__}: {raised}")
    line = str(raised)
    assert_all("\n" not in line and line.startswith(f"{stage}: PETSc error 86 in "), line)
    assert_all(f"check the -{option.split('_')[0]}_" in line and f"(given: -{option} {value})" in line, line)
    assert_all(undestroyed_petsc_objects() == before, "the failed stage's PETSc objects were destroyed")


@pytest.mark.parametrize("kind", ["random", "turbulence"])
def test_a_distributed_load_on_a_matrix_model_is_refused_before_its_files_are_read(kind, monkeypatch):
    # Review: FullOrderModel.build loaded (and checked) K and M, possibly gigabytes, and only then
    # refused a random or turbulent load, which acts along a beam: cheap checks come first. The
    # matrix files here do not exist: the refusal must come without reading them.
    from dbf_hpc import Constraint, FullOrderModel, InputError, MatrixFiles, RandomForce, Turbulence, fom, law

    def read(*args, **kwargs):
        raise AssertionError("the matrix files were read")

    monkeypatch.setattr(fom, "load_operators", read)
    load = (RandomForce(psd=1.0, band=(1.0, 100.0)) if kind == "random" else
            Turbulence(psd=1.0, band=(1.0, 100.0), correlation_length=0.1))
    with pytest.raises(InputError, match=f"^{kind} forcing is distributed along a beam; not available for matrices$"):
        FullOrderModel.build(MatrixFiles("no_such_K.bin", "no_such_M.bin"),
                             [Constraint(law("deadband", clearance=1e-3, k=1e6), dof=3)], load)


def test_run_imported_from_the_package_runs_a_scene(tmp_path):
    # Red team: `from dbf_hpc import run` gave the module dbf_hpc.run (the import of a submodule binds
    # its name in the package), and the documented run(scene, out) raised "TypeError: 'module' object
    # is not callable". A bad output path is then the run's own one-line InputError, and nothing is
    # written.
    from dbf_hpc import InputError, load_scene, run

    scene = load_scene(os.path.join(ROOT, "jobs", "paper_beam.toml"), ["integrator.t_end=0.01", "basis.cache=off"])
    with pytest.raises(InputError, match="no_such_dir"):
        run(scene, str(tmp_path / "no_such_dir" / "out.h5"), progress=False)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("entry", ["FullOrderModel.build", "run", "load_scene_collective"])
@pytest.mark.parametrize("null", ["mpi4py", "petsc4py"])
def test_a_null_communicator_is_refused_not_read_as_comm_world(entry, null, tmp_path):
    # Red team: `comm or COMM_WORLD` read a null communicator (falsy; what MPI.Comm.Split gives a rank
    # it leaves out) as none given, and ran that rank's case collectively on COMM_WORLD, where the
    # other ranks, on cases of their own communicators, never come: a hang. Refused on the rank that
    # gave it, before any collective call.
    from mpi4py import MPI
    from petsc4py import PETSc

    from dbf_hpc import Beam, FullOrderModel, InputError, load_scene, run
    from dbf_hpc.scene import load_scene_collective

    comm = MPI.COMM_NULL if null == "mpi4py" else PETSc.COMM_NULL
    scene_file = os.path.join(ROOT, "jobs", "paper_beam.toml")
    call = {"FullOrderModel.build": lambda: FullOrderModel.build(
                Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=4), comm=comm),
            "run": lambda: run(load_scene(scene_file, ["basis.cache=off"]), str(tmp_path / "never.h5"), progress=False,
                                comm=comm),
            "load_scene_collective": lambda: load_scene_collective(scene_file, comm=comm)}[entry]
    with pytest.raises(InputError, match=f"^{entry}: comm must be a petsc4py or mpi4py communicator .* got a null "
                                         f"communicator"):
        call()
    assert not any(tmp_path.iterdir())


@pytest.mark.parallel
def test_each_rank_runs_its_own_scene_on_its_own_communicator_and_gets_the_answer_of_that_scene_alone(
        shared_tmp_path, capfd):
    # Task parallelism (README "Python API"): on 2 ranks each rank runs a different case of the paper's
    # beam (another stop, gap and t_end) on a communicator of its own (petsc4py's COMM_SELF, and a Split
    # of COMM_WORLD given as an mpi4py communicator, which run() took as a traceback before), both at
    # once, writing to one basis cache directory; then each runs the other rank's case. A case's
    # output must be the same bits whichever rank ran it, and beside which other case: nothing of one
    # case (a collective call, an option, a cache file) reaches the other. Each rank prints its own
    # case's progress (PETSc.Sys.Print on the case's communicator, whose rank 0 it is).
    import h5py
    from mpi4py import MPI
    from petsc4py import PETSc

    from dbf_hpc import load_scene, run

    world = MPI.COMM_WORLD
    cases = [["constraint.x=0.25", "constraint.clearance=2.5e-3", "integrator.t_end=0.12"],
             ["constraint.x=0.3", "constraint.clearance=2e-3", "integrator.t_end=0.1"]]
    cache = str(shared_tmp_path / "cache")

    def case(index, comm, tag, progress=False):
        scene = load_scene(os.path.join(ROOT, "jobs", "paper_beam.toml"),
                           cases[index] + [f"basis.cache={cache}", "output.snapshots=0"])
        out = str(shared_tmp_path / f"case{index}-{tag}.h5")
        summary = run(scene, out, progress=progress, comm=comm)
        with h5py.File(out, "r") as f:
            data = {}
            f.visititems(lambda name, obj: data.__setitem__(name, obj[...]) if isinstance(obj, h5py.Dataset) else None)
        return summary, data

    mine = world.rank % 2
    split = world.Split(world.rank, 0)
    try:
        capfd.readouterr()
        first = case(mine, PETSc.COMM_SELF, f"self-on-{world.rank}", progress=True)
        printed = capfd.readouterr().out
        other = case(1 - mine, split, f"split-on-{world.rank}")
    finally:
        split.Free()
    everything = world.allgather({mine: first, 1 - mine: other})
    assert_all("1 rank(s)" in printed and f"wrote {shared_tmp_path / f'case{mine}-self-on-{world.rank}.h5'}" in printed,
               f"rank {world.rank} did not print its own case's progress: {printed!r}")
    for index in (0, 1):
        (s0, d0), (s1, d1) = everything[0][index], everything[1][index]
        assert s0["stats"]["steps"] == s1["stats"]["steps"] and s0["final_state"] == s1["final_state"]
        assert s0["estimated_error"] == s1["estimated_error"]
        assert sorted(d0) == sorted(d1) and "time" in d0
        for name in d0:
            assert np.array_equal(d0[name], d1[name]), f"case {index + 1}: {name} differs between the ranks"
    # the two cases are different questions with different answers (the comparison could fail), and the
    # first reaches its stop
    assert everything[0][0][0]["final_state"] != everything[0][1][0]["final_state"]
    assert everything[0][0][0]["constraint_stats"]["impacts"][0] >= 1
    # two stops, two bases, each built once or shared, and the reference modes of each case's richer
    # models (cache.obtain_modes: the mesh has a node at its stop, so the two beams' modes differ), none
    # left half-written
    from dbf_hpc.cache import entries

    kinds = sorted(json.loads(e["settings"])["enrichment"] for e in entries(cache))
    assert kinds == ["dbf", "dbf", "none", "none"] and not [name for name in os.listdir(cache) if ".tmp" in name]


def test_cases_one_after_another_in_a_process_take_only_their_own_settings_and_options():
    # README "Many small cases at once": a reduced case at rtol 1e-3, one at 1e-8, one with a PETSc
    # option of its own (-rom_ts_arkimex_type 4, deleted after it), then rtol 1e-3 again: the last is
    # the first bit for bit (no rtol, step or default of the code left in the options database), and the
    # options database ends as it began.
    from petsc4py import PETSc

    from dbf_hpc import (Beam, BaseMotion, BasisSettings, Constraint, FullOrderModel, IntegratorSettings, Reductor,
                         law, simulate_reduced)

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=40)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0), comm=PETSc.COMM_SELF) as fom:
        with Reductor(fom, BasisSettings(modes=6)) as reductor:
            rom = reductor.reduce()
    options = PETSc.Options()
    before = options.getAll()

    def case(rtol):
        return simulate_reduced(rom, IntegratorSettings(t_end=0.12, sample_dt=1e-4, rtol=rtol))

    first, tight = case(1e-3), case(1e-8)
    options.setValue("rom_ts_arkimex_type", "4")
    try:
        other_scheme = case(1e-3)
    finally:
        options.delValue("rom_ts_arkimex_type")
    again = case(1e-3)
    assert np.abs(first.displacement).max() >= 2.5e-3   # the stop is reached: contact in every case
    assert tight.solver["steps"] > first.solver["steps"] and other_scheme.solver["steps"] != first.solver["steps"]
    untimed = lambda result: {k: v for k, v in result.solver.items() if k != "time_integration"}   # noqa: E731
    assert untimed(again) == untimed(first) and np.array_equal(again.displacement, first.displacement)
    assert np.array_equal(again.q, first.q) and options.getAll() == before


def test_simulate_reduced_warns_once_where_atol_lets_w_err_by_over_a_percent_of_a_clearance(shared_tmp_path, capfd):
    # simulate_reduced says what `dbf-hpc run` says (run.loose_atol), on rank 0, once for the same line however
    # often a script calls it; an atol tight enough draws none
    import dataclasses

    from mpi4py import MPI

    from conftest import small_mass_chain
    import dbf_hpc.simulate as simulate
    from dbf_hpc import Reductor, simulate_reduced
    from dbf_hpc.scene import load_scene

    scene = load_scene(small_mass_chain(shared_tmp_path))
    settings = scene.integrator_settings()
    with scene.full_order_model() as fom, Reductor(fom, scene.basis_settings()) as reductor:
        model = reductor.reduce()
    simulate._WARNED.clear()   # an earlier test of this process may have drawn the same line (printed once)
    capfd.readouterr()
    for _ in range(2):
        simulate_reduced(model, settings)
    simulate_reduced(model, dataclasses.replace(settings, atol=1e-14))
    err = capfd.readouterr().err
    count = err.count("dbf-hpc: warning: [integrator] atol = 1e-09 (modal units")
    assert_all(count == (1 if MPI.COMM_WORLD.rank == 0 else 0), err)
    assert "atol = 1e-14" not in err


def test_simulate_full_and_reduced_warn_of_their_result_as_a_run_does_once_from_rank_0(capfd):
    # Warnings parity: `dbf-hpc run` warns after the integration of Hunt-Crossley damping beyond its range
    # (alpha |v| > 1.5) and, full order, of a contact stiffer than the step resolves; the Python API said
    # nothing of the same result. Here a stop at clearance 0 under the paper's base motion: alpha = 1000 s/m
    # reaches alpha |v| of several (full order, 2e-6 s) and 24 (6 modes), a hertz contact of 1e12 N/m rings in
    # 0.3 steps of 1e-5 s, and alpha = 1 s/m at 2e-6 s is within both. Every rank takes the same path; rank 0 prints.
    from mpi4py import MPI

    from dbf_hpc import (Beam, BaseMotion, BasisSettings, Constraint, FullOrderModel, IntegratorSettings, Reductor,
                         law, simulate_full, simulate_reduced)
    from dbf_hpc.run import HUNT_CROSSLEY_MAX

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    hunt_crossley = lambda alpha: law("deadband", clearance=0.0, k=1e6, damping="hunt_crossley", alpha=alpha)  # noqa
    cases = ((hunt_crossley(1000.0), 2e-6, True, False), (law("hertz", clearance=0.0, k=1e12), 1e-5, False, True),
             (hunt_crossley(1.0), 2e-6, False, False))
    rank0 = MPI.COMM_WORLD.rank == 0
    for stop, dt, overdamped, stiff in cases:
        with FullOrderModel.build(beam, [Constraint(stop, x=0.25)], BaseMotion(amplitude=5e-3, frequency_hz=1.0)) as fom:
            with Reductor(fom, BasisSettings(modes=6)) as reductor:
                rom = reductor.reduce()
            capfd.readouterr()
            full = simulate_full(fom, IntegratorSettings(t_end=2e-3, dt=dt, sample_dt=1e-4))
        reduced = simulate_reduced(rom, IntegratorSettings(t_end=2e-3, sample_dt=1e-4))
        err = capfd.readouterr().err
        assert_all((full.alpha_speed[0] > HUNT_CROSSLEY_MAX) == overdamped, full.alpha_speed)
        assert_all((reduced.alpha_speed[0] > HUNT_CROSSLEY_MAX) == overdamped, reduced.alpha_speed)
        hc = err.count("Hunt-Crossley damping reached alpha |v|")
        assert_all(hc == (2 if overdamped and rank0 else 0), err)
        if overdamped and rank0:   # the full-order line adds the dt dependence, as --method full's does
            assert err.count("constraint 1 at x = 0.25 m: Hunt-Crossley") == 2 and err.count("full-order force and dissipated energy depend on dt") == 1, err
        assert_all(err.count("is too stiff for dt") == (1 if stiff and rank0 else 0), err)
        if stiff and rank0:        # the advice names the field the caller sets
            assert "reduce IntegratorSettings dt to about" in err and "[integrator]" not in err, err
        assert_all(("dbf-hpc: warning" in err) == ((overdamped or stiff) and rank0), err)


def test_simulate_full_and_reduced_warn_before_the_run_of_a_step_or_samples_too_coarse_for_the_forcing(capfd):
    # Warnings parity: `dbf-hpc run` warns before any work where a fixed step takes fewer than 20 steps a period
    # of the fastest forcing, or the samples fewer than 2 (they alias it); the Python API said nothing. A force
    # at 1000 Hz, or a random force up to 1000 Hz, with steps of 1e-4 s (10 a period) and samples 1e-3 s
    # apart (1 a period): simulate_full warns of both (its steps are fixed), simulate_reduced of both with
    # fixed steps and of the samples alone with adaptive ones, naming the IntegratorSettings fields.
    import dataclasses

    from mpi4py import MPI

    import dbf_hpc.simulate as simulate
    from dbf_hpc import (Beam, BasisSettings, Constraint, FullOrderModel, IntegratorSettings, PointForce,
                         RandomForce, Reductor, law, simulate_full, simulate_reduced)

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    step = "IntegratorSettings dt = 0.0001 s takes 10 fixed steps per period of the 1000 Hz excitation"
    samples = "IntegratorSettings sample_dt = 0.001 s takes 1 samples per period of the 1000 Hz excitation"
    coarse = IntegratorSettings(t_end=5e-3, dt=1e-4, sample_dt=1e-3)
    fine = IntegratorSettings(t_end=5e-3, dt=1e-5, sample_dt=1e-4)
    warned = "dbf-hpc: warning: "
    said = lambda err: tuple(next((e for e in (step, samples) if line.startswith(warned + e)), line)  # noqa: E731
                             for line in err.splitlines() if "per period" in line)
    for excitation in (PointForce(amplitude=1e-3, frequency_hz=1000.0, x=0.5),
                       RandomForce(psd=1e-6, band=(10.0, 1000.0), seed=1)):
        with FullOrderModel.build(beam, [Constraint(law("deadband", clearance=1e-6, k=1e6), x=0.25)], excitation) \
                as fom:
            with Reductor(fom, BasisSettings(modes=6)) as reductor:
                rom = reductor.reduce()
            for settings, expected in ((coarse, (step, samples)), (fine, ())):
                capfd.readouterr()
                simulate_full(fom, settings)
                err = capfd.readouterr().err
                assert_all(said(err) == (expected if MPI.COMM_WORLD.rank == 0 else ()), err)
        for adaptive, expected in ((False, (step, samples)), (True, (samples,))):
            simulate._WARNED.clear()   # (once a process: an earlier call may have said it)
            simulate_reduced(rom, dataclasses.replace(coarse, adaptive=adaptive))
            err = capfd.readouterr().err
            assert_all(said(err) == (expected if MPI.COMM_WORLD.rank == 0 else ()), err)


def test_simulate_reduced_warns_once_of_a_forcing_above_the_basis_as_a_run_does(capfd):
    # Warnings parity: `dbf-hpc run` warns where the excitation lies above the basis' highest reference mode
    # (run.forcing_warning: the basis cannot follow it); simulate_reduced said nothing, also of a case given
    # another force (with_case). The paper's beam on 6 modes (top 39.2 Hz) under a 100 Hz force: once a
    # process, from rank 0, naming the BasisSettings fields; a 1 Hz force draws none.
    from mpi4py import MPI

    import dbf_hpc.simulate as simulate
    from dbf_hpc import (Beam, BasisSettings, Constraint, FullOrderModel, IntegratorSettings, PointForce, Reductor,
                         law, simulate_reduced)
    from dbf_hpc.excitation import Harmonic

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    with FullOrderModel.build(beam, [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)],
                              PointForce(amplitude=1e-3, frequency_hz=1.0, x=0.5)) as fom:
        with Reductor(fom, BasisSettings(modes=6)) as reductor:
            rom = reductor.reduce()
    top = rom.basis_info["omega"].max() / (2 * np.pi)
    settings = IntegratorSettings(t_end=2e-3, sample_dt=1e-4)
    simulate._WARNED.clear()
    capfd.readouterr()
    simulate_reduced(rom, settings)
    assert_all("lies above" not in capfd.readouterr().err)
    fast = rom.with_case(force=Harmonic(1e-3, 100.0))
    for _ in range(2):
        simulate_reduced(fast, settings)
    said = [line for line in capfd.readouterr().err.splitlines() if "lies above" in line]
    expected = [f"dbf-hpc: warning: the excitation (100 Hz) lies above the highest reference mode ({top:.4g} Hz): "
                f"the basis cannot follow it; add modes (BasisSettings modes or max_frequency_hz)"]
    assert_all(said == (expected if MPI.COMM_WORLD.rank == 0 else []), said)


def test_help_of_the_package_names_every_api_name_with_its_module():
    # New-user pass: help(dbf_hpc) listed no name of the API (they load lazily, so pydoc saw only a
    # truncated "__all__ = ['BaseMotion', 'BasisSettings', 'Beam', 'Constraint', 'Const...").
    import pydoc

    import dbf_hpc

    text = pydoc.plain(pydoc.render_doc(dbf_hpc))
    listing = text[text.index("Names (module: names):"):]
    for name in dbf_hpc.__all__:
        assert re.search(rf"\b{name}\b", listing), name
    assert re.search(r"\bsimulate: simulate_reduced, simulate_full\b", listing), listing


def test_every_api_name_has_its_own_docstring_and_the_collective_entry_points_say_so():
    # New-user pass: help(NoEnrichment) and help(StaticEnrichment) showed only the dataclass's generated
    # "NoEnrichment()"; Reductor's said only that it owns its basis, and run's not that it is collective.
    import inspect

    import dbf_hpc

    for name in dbf_hpc.__all__:
        obj = getattr(dbf_hpc, name)
        doc = inspect.getdoc(obj) or ""
        assert doc and not doc.startswith(f"{name}("), (name, doc)
    assert "Collective" in inspect.getdoc(dbf_hpc.run) and "Collective" in inspect.getdoc(dbf_hpc.Reductor)
    assert "Eq. 41" in inspect.getdoc(dbf_hpc.Reductor) and "m/N" in inspect.getdoc(dbf_hpc.StaticEnrichment)


def test_the_api_docstrings_name_the_units_and_the_papers_equations_a_user_needs():
    # New-user pass: help(Beam) said only "SI units", help(law) named neither units nor Eqs. 23 / 42, and
    # help(BasisSettings) not that max_frequency_hz is in Hz or what dbf_stiffness is.
    import inspect

    import dbf_hpc

    doc = {name: inspect.getdoc(getattr(dbf_hpc, name)) for name in ("Beam", "law", "BasisSettings")}
    for words in ("E (Pa)", "I (m^4)", "A (m^2)", "rho (kg/m^3)", "length L (m)", "tension T (N)"):
        assert words in doc["Beam"], words
    for words in ("Eq. 23", "Eq. 42", "clearance m", "k N/m^p", "alpha s/m"):
        assert words in doc["law"], words
    for words in ("max_frequency_hz`, Hz", "Fig. 2", "N/m"):
        assert words in doc["BasisSettings"], words
