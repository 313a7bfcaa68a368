"""The reduced integrator's C callbacks (dbf_hpc/_romc) against the Python reference
(rom_integrator.ReducedProblem, laws.py, recorder.py): the same laws bit for bit, the exact Jacobian
and its exact structured inverse, the same trajectory before the first impact, the same statistics,
every ARKIMEX type, and a clear line when the extension is missing."""
import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
from petsc4py import PETSc

from dbf_hpc import _romc
from dbf_hpc.errors import InputError
from dbf_hpc.laws import ConstraintLaws, law
from dbf_hpc.rom_integrator import ReducedProblem, integrate_reduced
from dbf_hpc.simulate import simulate_reduced
from dbf_hpc.timestepping import ARKIMEX_TYPES, NO_DENSE_OUTPUT, IntegratorSettings

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")
FOUR = os.path.join(ROOT, "jobs", "paper_beam_4.toml")
needs_c = pytest.mark.skipif(_romc.core is None, reason=f"{_romc.why}")
# The C callbacks against the Python ones on one reduced model: each rank would compare the same two
# integrations (the callbacks run on rank 0 alone in a run), so these are `serial` (conftest): the 2-rank
# pass keeps what is collective here, a run's checkpoint and resume with either callbacks and the
# fallback said once, by rank 0.

LAWS = [
    law("deadband", clearance=2.5e-3, k=1e6),
    law("deadband", clearance_minus=1e-3, clearance_plus=2e-3, k_minus=0.0, k_plus=3e5),        # one-sided stop
    law("deadband", clearance=-1e-3, k_minus=2e5, k_plus=1e5),                                 # interference fit
    law("power", clearance=1e-3, k_minus=0.1, k_plus=1e6, exponent_minus=3.0, exponent_plus=1.0),  # Eq. 42
    law("hertz", clearance=1e-4, k=3e9, damping="hunt_crossley", alpha=0.2),
    law("power", clearance=5e-4, k=1e9, exponent=2.5, damping="linear", c=3.0),
    law("linear", k=1e4, damping="linear", c=0.5),
    law("cubic", k=10.0, k3=1e6),
    law("table", table=[[-2e-3, 40.0], [-1e-3, 0.0], [1e-3, 0.0], [3e-3, -100.0]]),
]


def _model(path, *sets, field=False):
    from dbf_hpc.reductor import Reductor
    from dbf_hpc.scene import load_scene

    scene = load_scene(path, ["basis.cache=off", *sets])
    with scene.full_order_model() as fom, Reductor(fom, scene.basis_settings()) as reductor:
        reductor.basis()
        return reductor.reduce(field=field), scene.integrator_settings()


@pytest.fixture(scope="module")
def paper():
    return _model(PAPER, "integrator.t_end=0.2")


@pytest.fixture(scope="module")
def four():
    return _model(FOUR, "integrator.t_end=0.1", "damping.zeta=0.01")


def _problem(model, implicit=True):
    return _romc.core.Problem(model, ReducedProblem(model, implicit), implicit)


def _first_contact(result):
    touching = np.flatnonzero(np.any(result.force != 0, axis=1))
    return touching[0] if touching.size else result.time.size


@needs_c
@pytest.mark.serial
@pytest.mark.parametrize("damped", [False, True])
def test_laws_in_c_give_the_bits_of_laws_py_over_random_and_edge_states(paper, damped):
    laws = [x for x in LAWS if damped or x.damping == "none"]
    model = paper[0]
    n = len(laws)
    constraints = dataclasses.replace(model.constraints, rows=np.zeros((n, 1), dtype=np.int64),
                                      laws=ConstraintLaws(laws), labels=tuple(map(str, range(n))),
                                      positions=np.zeros(n))
    model = dataclasses.replace(model, constraints=constraints, B=np.ones((n, model.size)), r_c=np.zeros(n))
    problem, python = _problem(model), ConstraintLaws(laws)
    rng = np.random.default_rng(7)
    edges = sorted({e for x in laws for e in (-x.clearance_minus, x.clearance_plus, 0.0)}
                   | {p[0] for x in laws for p in x.table})
    states = [np.full(n, e) for e in edges] + [np.full(n, np.nextafter(e, s)) for e in edges for s in (-1, 1)]
    states += list(rng.uniform(-4e-3, 4e-3, (200, n))) + list(rng.normal(0, 1e-2, (50, n)))
    for z in states:
        v = rng.normal(0, 0.3, n)
        for c_value, py_value in zip(problem.laws(z, v), python.force_and_jacobian(z, v)):
            assert np.array_equal(c_value, py_value), (z, v, c_value, py_value)


@needs_c
@pytest.mark.serial
@pytest.mark.parametrize("arrow", [True, False])
def test_the_c_jacobian_is_the_python_jacobian_and_its_structured_inverse_is_exact(four, arrow):
    # Four constraints of the paper's beam, some in contact, Hunt-Crossley damping so that dN/dv
    # enters too; the MatShell's product against the Python dense Jacobian, and J (J^-1 x) = x, with
    # the arrow factor (the reference modes' diagonal block bordered by the 4 DBFs) and the dense one.
    model = four[0]
    laws = ConstraintLaws([law("hertz", clearance=1e-3, k=1e9, damping="hunt_crossley", alpha=0.3)] * 4)
    model = model.with_case(constraints=model.constraints.with_laws(laws))
    r = model.size
    python, fast = ReducedProblem(model, True), _problem(model)
    assert fast.arrow_modes == model.basis_info["omega"].size   # the modes' block is diagonal
    fast.arrow_modes = arrow
    assert (fast.arrow_modes > 0) == arrow
    ts = PETSc.TS().create(PETSc.COMM_SELF)
    ts.setType("arkimex")
    y, ydot = PETSc.Vec().createSeq(2 * r, comm=PETSc.COMM_SELF), PETSc.Vec().createSeq(2 * r, comm=PETSc.COMM_SELF)
    F, G = y.duplicate(), y.duplicate()
    shell = fast.shell_matrix()
    fast.attach(ts, F, G, shell, True)
    dense = PETSc.Mat().createDense((2 * r, 2 * r), comm=PETSc.COMM_SELF)
    dense.setUp()
    pc = PETSc.PC().create(PETSc.COMM_SELF)
    fast.set_pcshell(pc)
    pc.setOperators(shell)
    pc.setUp()
    rng = np.random.default_rng(3)
    x, out, back = y.duplicate(), y.duplicate(), y.duplicate()
    contacts = 0
    for trial in range(20):
        state = rng.normal(0, 1, 2 * r) * np.concatenate([np.full(r, 2e-3 / np.abs(model.B).max() / 3), np.full(r, 0.1)])
        y.setArray(state)
        t, shift = rng.uniform(0, 1), 10 ** rng.uniform(2, 5)
        ts.computeIJacobian(t, y, ydot, shift, shell, shell)
        python.ijacobian(ts, t, y, ydot, shift, dense, dense)
        contacts += np.count_nonzero(model.constraints.in_contact(model.constraint_state(t, state[:r], state[r:])[0]))
        A = dense.getDenseArray().copy()
        for _ in range(3):
            x.setArray(rng.normal(0, 1, 2 * r))
            shell.mult(x, out)
            np.testing.assert_allclose(out.getArray(), A @ x.getArray(), rtol=1e-12,
                                       atol=1e-13 * np.abs(A).max() * np.abs(x.getArray()).max())
            pc.apply(x, back)
            solution = back.getArray()
            residual = np.abs(A @ solution - x.getArray()).max()
            backward = residual / (np.abs(A).sum(axis=1).max() * np.abs(solution).max() + np.abs(x.getArray()).max())
            assert backward < 1e-12, backward   # normwise backward error: an exact solve, to round-off
    assert contacts > 10   # the Woodbury part was exercised
    for obj in (ts, y, ydot, F, G, shell, dense, pc, x, out, back):
        obj.destroy()


@needs_c
@pytest.mark.serial
def test_c_callbacks_give_the_python_trajectory_before_the_first_impact_and_the_same_statistics(paper):
    model, settings = paper
    runs = {cb: simulate_reduced(model, dataclasses.replace(settings, callbacks=cb)) for cb in ("python", "c")}
    a, b = runs["python"], runs["c"]
    assert a.solver["callbacks"] == "python" and b.solver["callbacks"] == "c" and b.solver["newton"] == "c"
    assert a.time.size == b.time.size and np.array_equal(a.time, b.time)
    k = _first_contact(a)
    assert 100 < k < a.time.size, "the run has an impact, and samples before it"
    scale = np.abs(a.displacement).max()
    assert np.abs(a.displacement[:k] - b.displacement[:k]).max() < 1e-12 * scale
    assert np.abs(a.q[:k] - b.q[:k]).max() < 1e-12 * np.abs(a.q).max()
    # after it, impacts amplify round-off: the same physics, statistically
    assert np.array_equal(a.statistics["impacts"], b.statistics["impacts"])
    np.testing.assert_allclose(b.statistics["force_peak"], a.statistics["force_peak"], rtol=1e-2)
    np.testing.assert_allclose(b.statistics["force_rms"], a.statistics["force_rms"], rtol=2e-2)
    assert abs(b.solver["steps"] - a.solver["steps"]) < 0.05 * a.solver["steps"]
    assert b.solver["rejected_steps"] <= 0.1 * b.solver["steps"]
    # the samples' forces and peaks computed in C are those the laws give
    np.testing.assert_array_equal(b.force, [model.constraints.force(z, v) for z, v in zip(b.displacement, b.velocity)])
    assert np.all(np.abs(b.force_peak) >= np.abs(b.force))


@needs_c
@pytest.mark.serial
def test_c_callbacks_record_the_hunt_crossley_alpha_v_in_contact_that_the_python_ones_do(paper):
    # run.hunt_crossley_warnings reads it from the C monitor's steps as from recorder.py's: the paper's
    # beam strikes its stop at 0.024 m/s, so alpha = 1000 s/m reaches alpha v = 24, far outside the
    # law's range (1.5), and alpha = 1 s/m stays inside it
    model, settings = paper
    settings = dataclasses.replace(settings, t_end=0.12)
    for alpha, inside in ((1000.0, False), (1.0, True)):
        hc = law("deadband", clearance=2.5e-3, k=1e6, damping="hunt_crossley", alpha=alpha)
        case = model.with_case(constraints=model.constraints.with_laws([hc]))
        a, b = (simulate_reduced(case, dataclasses.replace(settings, callbacks=cb)) for cb in ("python", "c"))
        assert b.solver["callbacks"] == "c" and a.statistics["impacts"][0] >= 1
        np.testing.assert_allclose(b.alpha_speed, a.alpha_speed, rtol=1e-6)
        assert (a.alpha_speed[0] <= 1.5) == inside, a.alpha_speed
        # at most alpha times the largest speed at the stop, and alpha |v| at the samples in contact to 1 %
        # (a sample between two steps may be a little faster than both)
        v = np.abs(a.velocity[:, 0])
        assert 0.99 * alpha * v[a.force[:, 0] != 0].max(initial=0.0) <= a.alpha_speed[0] <= alpha * v.max() * (1 + 1e-6)


@needs_c
@pytest.mark.serial
def test_the_statistics_the_c_monitor_accumulates_over_the_steps_are_those_recorder_py_makes_of_the_same_steps(paper):
    # The impact statistics, peak force, displacement peak and Hunt-Crossley alpha |v| accumulate in C over
    # the steps (rom_core.c: stats.ImpactAccumulator.add operation by operation). A Python recorder is handed
    # the state of each step of the same C run (on_step, after every step): fed the same states, the two must
    # agree to round-off in every statistic, through the paper's beam's impacts, and the probes the C
    # samples hold are w = probe_B q + probe_r Omega(t) of their own q (mutation testing: |N z| as the impact
    # power, |v| as the displacement peak, alpha v for alpha |v| passed every test; the trajectory test
    # compares two runs, whose steps differ after an impact, to 1-2 % only)
    from dbf_hpc.output import MemoryWriter
    from dbf_hpc.recorder import ReducedRecorder, Result

    model, settings = paper
    # the support's motion reversed (phase pi): the beam strikes the stop's lower side, entering it at v < 0
    hc = law("deadband", clearance=2.5e-3, k=1e6, damping="hunt_crossley", alpha=1.0)
    model = model.with_case(constraints=model.constraints.with_laws([hc]),
                            support=dataclasses.replace(model.support, phase=np.pi))
    fast, python = (ReducedRecorder(MemoryWriter(model.constraints.shape, model.probe_sample_shape, model.size), model)
                    for _ in range(2))
    steps = []

    def each_step(ts, t, q, p):
        steps.append(t)
        python.on_step(t, q, p)

    stats = integrate_reduced(model, dataclasses.replace(settings, t_end=0.2, callbacks="c"), on_step=each_step,
                              recorder=fast)
    assert stats["callbacks"] == "c"
    a, b = fast.impacts.result(), python.impacts.result()
    assert a["impacts"][0] >= 2 and len(steps) > 500   # impacts, and their contact runs ended
    assert a["impact_duration_max"][0] > 0 and a["impact_power_mean"][0] > 0
    for name in a:
        np.testing.assert_allclose(a[name], b[name], rtol=1e-10, atol=0, err_msg=name)
    np.testing.assert_allclose(fast.alpha_speed, python.alpha_speed, rtol=1e-10, atol=0)
    assert fast.alpha_speed[0] > 0
    samples = Result.from_recorder(fast, stats)
    probes = np.array([model.probes(t, q) for t, q in zip(samples.time, samples.q)])
    assert samples.time.size > 100 and np.abs(probes).max() > 0
    np.testing.assert_allclose(samples.probes, probes, rtol=0, atol=1e-13 * np.abs(probes).max())


@needs_c
@pytest.mark.serial
@pytest.mark.parametrize("stop", ["deadband", "hertz"])
def test_the_linear_shortcut_takes_only_exact_newton_steps_on_a_stop_whose_support_is_shaken(paper, stop):
    # Piecewise-linear laws: the C Newton skips the residual of an iterate on which no constraint changed
    # side since the linearization (RomSNESSolve's linear shortcut), the stage equation being affine there.
    # The side is that of z = B q + r_c Omega(t), and on the paper's beam r_c Omega reaches 3.75 mm against
    # a 2.5 mm clearance: the run with the shortcut must be the run with every residual checked (shortcut off
    # after the first monitor call) to round-off, over the same steps (mutation testing: a side check that
    # left out r_c Omega accepted unsolved stages, 4e-5 of the peak displacement off, and passed every test).
    # A Hertz stop (p = 1.5) is not piecewise linear: the shortcut is never taken there.
    from dbf_hpc.output import MemoryWriter
    from dbf_hpc.recorder import ReducedRecorder, Result
    from dbf_hpc.rom_integrator import C_CONTEXT

    model, settings = paper
    if stop == "hertz":
        model = model.with_case(constraints=model.constraints.with_laws([law("hertz", clearance=2.5e-3, k=1e9)]))
    settings = dataclasses.replace(settings, t_end=0.2, callbacks="c")
    runs, shortcuts = [], []
    for shortcut in (True, False):
        recorder = ReducedRecorder(MemoryWriter(model.constraints.shape, model.probe_sample_shape, model.size), model)
        taken = []

        def each_step(ts, t, q, p):
            fast = ts.getAttr(C_CONTEXT)
            fast.linear_shortcut = shortcut
            taken.append(fast.counters["linear_shortcuts"])

        stats = integrate_reduced(model, settings, on_step=each_step, recorder=recorder)
        runs.append((Result.from_recorder(recorder, stats), stats))
        shortcuts.append(taken[-1])
    (a, sa), (b, sb) = runs
    assert shortcuts[0] > 100 if stop == "deadband" else shortcuts[0] == 0
    assert shortcuts[1] == 0   # with the shortcut off from the first call on
    assert a.statistics["impacts"][0] >= 2 and sa["steps"] == sb["steps"]
    assert np.abs(a.displacement - b.displacement).max() <= 1e-8 * np.abs(b.displacement).max()


@needs_c
@pytest.mark.serial
@pytest.mark.parametrize("scheme", ARKIMEX_TYPES)
def test_every_arkimex_type_runs_with_the_c_callbacks_as_with_the_python_ones(paper, scheme):
    model, settings = paper
    fixed = scheme in NO_DENSE_OUTPUT
    settings = dataclasses.replace(settings, scheme=scheme, t_end=0.02, sample_dt=1e-3, adaptive=not fixed,
                                   dt=1e-5 if fixed else settings.dt)
    a, b = (simulate_reduced(model, dataclasses.replace(settings, callbacks=cb)) for cb in ("python", "c"))
    assert b.solver["scheme"] == scheme and b.solver["callbacks"] == "c"
    assert a.solver["steps"] == b.solver["steps"]
    assert np.abs(a.q - b.q).max() < 1e-11 * np.abs(a.q).max()


@needs_c
@pytest.mark.serial
def test_petsc_newton_with_the_exact_solve_when_snes_options_are_given(paper):
    model, settings = paper
    settings = dataclasses.replace(settings, t_end=0.01, callbacks="c")
    options = PETSc.Options()
    options["rom_snes_type"] = "newtonls"
    try:
        petsc = simulate_reduced(model, settings)
    finally:
        del options["rom_snes_type"]
    ours = simulate_reduced(model, settings)
    assert petsc.solver["newton"] == "petsc" and ours.solver["newton"] == "c"
    assert np.abs(petsc.q - ours.q).max() < 1e-11 * np.abs(ours.q).max()


def test_without_the_extension_callbacks_c_is_one_clear_line_and_auto_falls_back(paper, monkeypatch, capsys):
    from dbf_hpc import rom_integrator

    monkeypatch.setattr(_romc, "core", None)
    monkeypatch.setattr(_romc, "why", "the C callbacks of the reduced integrator are not built (test)")
    monkeypatch.setattr(rom_integrator, "_warned", [])
    model, settings = paper
    settings = dataclasses.replace(settings, t_end=0.002)
    with pytest.raises(InputError, match="not built") as info:
        simulate_reduced(model, dataclasses.replace(settings, callbacks="c"))
    assert "\n" not in str(info.value)
    for _ in range(2):   # a script's loop of runs: said once a process
        result = simulate_reduced(model, dataclasses.replace(settings, callbacks="auto"))
        assert result.solver["callbacks"] == "python"
    warning = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    # once, by rank 0 (on 2 ranks, each rank calling simulate_reduced, each printed it: red team)
    from mpi4py import MPI
    assert len(warning) == (MPI.COMM_WORLD.rank == 0) and all("Python callbacks" in w for w in warning), warning


@pytest.mark.launcher
def test_a_sweep_on_two_ranks_says_once_that_it_uses_the_python_callbacks(tmp_path):
    # Red team: each rank that integrated a case printed the fallback line: twice on 2 ranks. Every rank
    # decides it alike before the cases run; rank 0 says it.
    sweep = tmp_path / "fallback.toml"
    sweep.write_text(f'scene = "{PAPER}"\noutput = "fallback.h5"\n[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n'
                     f'"integrator.t_end" = [0.01]\n"basis.modes" = [4]\n"basis.cache" = ["{tmp_path}"]\n')
    env = dict(os.environ, DBF_HPC_NO_C="1", OMPI_MCA_orte_execute_quiet="1", OMPI_MCA_rmaps_base_oversubscribe="1")
    out = subprocess.run(["mpirun", "-n", "2", sys.executable, "-m", "dbf_hpc.cli", "sweep", str(sweep), "-q"],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stderr.count("DBF_HPC_NO_C is set") == 1 and "using the Python callbacks" in out.stderr, out.stderr


@pytest.mark.launcher
def test_the_command_line_says_in_one_line_that_the_c_callbacks_are_missing(tmp_path):
    env = dict(os.environ, DBF_HPC_NO_C="1")
    out = subprocess.run([sys.executable, "-m", "dbf_hpc.cli", "run", PAPER, "-o", str(tmp_path / "x.h5"), "-q",
                          "--set", "integrator.callbacks=c", "--set", "integrator.t_end=0.01",
                          "--set", f"basis.cache={tmp_path}"], capture_output=True, text=True, env=env, cwd=ROOT,
                         timeout=300)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 1 and len(lines) == 1 and "DBF_HPC_NO_C" in lines[0], out.stderr


@needs_c
@pytest.mark.serial
@pytest.mark.parametrize("mass", [1.0, 2.5])
def test_a_non_identity_reduced_mass_is_integrated_alike_by_both_callbacks(mass):
    from test_rom_integrator import oscillator

    model = oscillator(mass=mass, stiffness=4.0, spring=5.0, b=0.5)
    out = {}
    for cb in ("python", "c"):
        samples = []
        integrate_reduced(model, IntegratorSettings(t_end=1.0, sample_dt=1e-2, callbacks=cb),
                          lambda t, q, p: samples.append(q[0]))
        out[cb] = np.array(samples)
    np.testing.assert_allclose(out["c"], out["python"], rtol=0, atol=1e-15)


@pytest.mark.parametrize("callbacks", ["c", "python"])
def test_a_run_stopped_at_a_checkpoint_resumes_to_the_uninterrupted_result_bit_for_bit(shared_tmp_path, callbacks,
                                                                                       monkeypatch):
    # Both callbacks: the C monitor keeps the impact statistics and the peak force in the recorder's
    # arrays, and a checkpoint must hold all of it. No error estimate: it writes attributes only (no
    # dataset compared here) and took half of each run.
    import h5py
    from mpi4py import MPI

    from dbf_hpc import run as run_module
    from dbf_hpc.errors import DbfError
    from dbf_hpc.scene import load_scene

    if callbacks == "c" and _romc.core is None:
        pytest.skip(_romc.why)
    sets = ["basis.cache=off", "integrator.t_end=0.6", "output.checkpoint_dt=0.2", "output.snapshots=5",
            "basis.estimate=false", f"integrator.callbacks={callbacks}"]
    reference, target = str(shared_tmp_path / f"ref-{callbacks}.h5"), str(shared_tmp_path / f"cut-{callbacks}.h5")
    run_module.run(load_scene(PAPER, sets), reference, progress=False)
    original = run_module.Checkpointing.on_step

    def stop_at_the_second_checkpoint(self, ts, t, q, p):
        if t >= 0.4:
            self.interrupted = True   # as SIGTERM does
        return original(self, ts, t, q, p)

    monkeypatch.setattr(run_module.Checkpointing, "on_step", stop_at_the_second_checkpoint)
    with pytest.raises(DbfError, match="checkpointed"):
        run_module.run(load_scene(PAPER, sets), target, progress=False)
    monkeypatch.setattr(run_module.Checkpointing, "on_step", original)
    run_module.run(load_scene(PAPER, sets), target, progress=False, resume=True)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(reference) as a, h5py.File(target) as b:
            assert json_stats(a)["callbacks"] == callbacks
            for name in ("time", "constraints/displacement", "constraints/force_peak", "reduced/q", "snapshots/w",
                         *[f"constraints/stats/{k}" for k in a["constraints/stats"]]):
                assert np.array_equal(a[name][:], b[name][:]), name


def json_stats(f):
    import json

    return json.loads(f.attrs["solver_stats"])


# -- two-direction laws, friction and the load matrix (issue 18) -------------------------------------

PLANAR_LAWS = [
    ("circular", dict(clearance=1e-4, k=1e3, mu=0.3, v_reg=1e-2, damping="linear", c=0.01)),
    ("circular", dict(clearance=2e-4, k=1e5, mu=0.2)),
    ("flat_bar", dict(angle=30.0, clearance=1e-4, k=1e4, mu=0.3, damping="hunt_crossley", alpha=0.2)),
    ("flat_bar", dict(angle=90.0, clearance=0.0, k=1e4)),
]


@pytest.fixture(scope="module")
def tube2d():
    """A two-plane beam in two round holes and two pairs of flat bars (friction, both kinds of contact
    damping), under correlated turbulence (a load matrix of 22 histories)."""
    from dbf_hpc import BasisSettings, Beam, Constraint, FullOrderModel, Reductor
    from dbf_hpc.damping import Damping
    from dbf_hpc.excitation import Turbulence
    from dbf_hpc.laws import CircularLaw

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20, planes=2)
    turbulence = Turbulence(psd=1e-4, band=(0.0, 40.0), correlation_length=0.3, span=(0.5, 1.0), components=16,
                            seed=3)
    supports = [Constraint(CircularLaw(kind=kind, **keys), x=x)
                for (kind, keys), x in zip(PLANAR_LAWS, (0.2, 0.4, 0.6, 0.8))]
    with FullOrderModel.build(beam, supports, turbulence, probes=[0.5], damping=Damping(zeta=0.01),
                              comm=PETSc.COMM_SELF) as fom:
        with Reductor(fom, BasisSettings(modes=8)) as reductor:
            return reductor.reduce()


def _planar_scales(laws, z, v):
    """Per support, the size of each Jacobian's terms before they cancel: the friction factor
    1 - tanh^2(v_t / v_reg) loses digits where tanh is near 1, and numpy's tanh and the C library's
    differ by an ulp, so the two are compared on that scale (mu k delta / v_reg, times |v| / r in dF/du)."""
    u, w = z.reshape(-1, 2), v.reshape(-1, 2)
    r, _, curved = laws._gap_coordinate(u)
    delta = np.maximum(r - laws.gap, 0.0)
    inv_r = curved / np.where(r > 0, r, 1.0)
    speed = np.hypot(w[:, 0], w[:, 1])
    friction = laws.mu * laws.k * delta / laws.v_reg
    sz = laws.k * (1 + laws.alpha * speed) + (laws.k * delta + laws.c * speed) * inv_r + friction * (1 + speed * inv_r)
    sv = laws.c + laws.alpha * laws.k * delta + friction
    return sz, sv


@needs_c
@pytest.mark.serial
def test_two_direction_and_friction_laws_in_c_agree_with_laws_py_to_round_off(tube2d, paper):
    # circular and flat_bar with friction and contact damping: random states in and out of contact, the
    # axis (u = 0), the edge of contact (|u| = c); values to 1e-13 of the largest force, the 2 x 2 blocks
    # to 1e-12 of each block's term scale (_planar_scales)
    model = tube2d
    laws = model.constraints.laws
    problem = _problem(model)
    rng = np.random.default_rng(11)
    gaps = np.repeat(laws.gap, 2)
    edge = [np.concatenate([[g, 0.0] for g in laws.gap]), np.concatenate([[0.0, -g] for g in laws.gap])]
    states = [np.zeros(8)] + edge + list(rng.normal(0, 1.5, (400, 8)) * np.maximum(gaps, 1e-4))
    worst = 0.0
    for z in states:
        v = rng.normal(0, 1e-2, 8) * rng.choice([0.0, 1e-2, 1.0, 30.0])
        (N, Nz, Nv), (N0, Nz0, Nv0) = problem.laws(z, v), laws.force_and_jacobian(z, v)
        sz, sv = _planar_scales(laws, z, v)
        assert Nz.shape == Nz0.shape == (4, 2, 2)
        assert np.abs(N - N0).max() <= 1e-13 * max(np.abs(N0).max(), 1e-300)
        assert np.all(np.abs(Nz - Nz0).max(axis=(1, 2)) <= 1e-12 * sz), (z, v)
        assert np.all(np.abs(Nv - Nv0).max(axis=(1, 2)) <= 1e-12 * sv), (z, v)
        worst = max(worst, (np.abs(Nz - Nz0).max(axis=(1, 2)) / sz).max())
    assert np.count_nonzero([np.any(laws.in_contact(z)) for z in states]) > 100
    # law = "friction" (d = 1) among the scalar laws: the same, on the scale mu F_n / v_reg of dN/dv
    scalar = LAWS[:1] + [law("friction", normal_force=3.0, mu=0.4, v_reg=1e-3),
                         law("friction", normal_force=0.5, mu=0.2)]
    n = len(scalar)
    constraints = dataclasses.replace(paper[0].constraints, rows=np.zeros((n, 1), dtype=np.int64),
                                      laws=ConstraintLaws(scalar), labels=tuple(map(str, range(n))),
                                      positions=np.zeros(n))
    one = dataclasses.replace(paper[0], constraints=constraints, B=np.ones((n, paper[0].size)), r_c=np.zeros(n))
    problem, python = _problem(one), ConstraintLaws(scalar)
    slip = np.array([x.mu * x.normal_force / (x.v_reg or 1.0) for x in scalar])
    for z in rng.uniform(-4e-3, 4e-3, (200, n)):
        v = rng.normal(0, 1e-2, n) * rng.choice([0.0, 1e-2, 1.0, 30.0])
        (N, Nz, Nv), (N0, Nz0, Nv0) = problem.laws(z, v), python.force_and_jacobian(z, v)
        assert np.array_equal(Nz, Nz0)
        assert np.all(np.abs(N - N0) <= 1e-15 * np.abs(N0).max())
        assert np.all(np.abs(Nv - Nv0) <= 1e-13 * (np.abs(Nv0) + slip))


@needs_c
@pytest.mark.serial
def test_the_c_jacobian_of_two_direction_laws_is_the_python_jacobian_and_its_structured_inverse_is_exact(tube2d):
    # the 2 x 2 blocks in the MatShell's product and in Woodbury's capacitance (friction makes them
    # unsymmetric), against the Python dense Jacobian; J (J^-1 x) = x
    model = tube2d
    r = model.size
    python, fast = ReducedProblem(model, True), _problem(model)
    ts = PETSc.TS().create(PETSc.COMM_SELF)
    ts.setType("arkimex")
    y, ydot = PETSc.Vec().createSeq(2 * r, comm=PETSc.COMM_SELF), PETSc.Vec().createSeq(2 * r, comm=PETSc.COMM_SELF)
    F, G = y.duplicate(), y.duplicate()
    shell = fast.shell_matrix()
    fast.attach(ts, F, G, shell, True)
    dense = PETSc.Mat().createDense((2 * r, 2 * r), comm=PETSc.COMM_SELF)
    dense.setUp()
    pc = PETSc.PC().create(PETSc.COMM_SELF)
    fast.set_pcshell(pc)
    pc.setOperators(shell)
    pc.setUp()
    rng = np.random.default_rng(4)
    x, out, back, Fc, Fp = (y.duplicate() for _ in range(5))
    contacts = 0
    for trial in range(30):
        z = rng.normal(0, 3e-4, 8)
        q = np.linalg.lstsq(model.B, z, rcond=None)[0]
        p = np.linalg.lstsq(model.B, rng.normal(0, 1e-2, 8), rcond=None)[0]
        state = np.concatenate([q, p])
        y.setArray(state)
        ydot.setArray(rng.normal(0, 1, 2 * r))
        t, shift = rng.uniform(0, 1), 10 ** rng.uniform(2, 5)
        ts.computeIJacobian(t, y, ydot, shift, shell, shell)
        python.ijacobian(ts, t, y, ydot, shift, dense, dense)
        ts.computeIFunction(t, y, ydot, Fc, imex=True)   # F alone (imex=False subtracts G)
        python.ifunction(ts, t, y, ydot, Fp)
        np.testing.assert_allclose(Fc.getArray(), Fp.getArray(), rtol=0, atol=1e-12 * np.abs(Fp.getArray()).max())
        contacts += np.count_nonzero(model.constraints.in_contact(model.constraint_state(t, q, p)[0]))
        A = dense.getDenseArray().copy()
        for _ in range(3):
            x.setArray(rng.normal(0, 1, 2 * r))
            shell.mult(x, out)
            np.testing.assert_allclose(out.getArray(), A @ x.getArray(), rtol=1e-12,
                                       atol=1e-12 * np.abs(A).max() * np.abs(x.getArray()).max())
            pc.apply(x, back)
            solution = back.getArray()
            residual = np.abs(A @ solution - x.getArray()).max()
            backward = residual / (np.abs(A).sum(axis=1).max() * np.abs(solution).max() + np.abs(x.getArray()).max())
            assert backward < 1e-12, backward
    assert contacts > 30   # the 2 x 2 Woodbury blocks were exercised
    for obj in (ts, y, ydot, F, G, shell, dense, pc, x, out, back, Fc, Fp):
        obj.destroy()


@needs_c
@pytest.mark.serial
def test_the_load_matrix_forcing_in_c_is_the_python_forcing_of_the_turbulence_histories(tube2d):
    # X(t) by Horner's rule over the equally spaced frequencies against excitation.CorrelatedProcess's
    # cosines, times V^T W: to 1e-13 of the force at times up to 100 s
    model = tube2d
    r = model.size
    assert model.force_shape.shape == (r, 22)
    _check_c_forcing(model, np.concatenate([[0.0], np.random.default_rng(2).uniform(0, 100.0, 50)]))


def _check_c_forcing(model, times) -> None:
    """The C right-hand side's velocity rows at state 0 (the forcing) equal ReducedProblem.forcing to 1e-13
    of the force (times t: relative max(1, t)), and its displacement rows are 0, at each of `times`."""
    r = model.size
    python, fast = ReducedProblem(model, True), _problem(model)
    ts = PETSc.TS().create(PETSc.COMM_SELF)
    y = PETSc.Vec().createSeq(2 * r, comm=PETSc.COMM_SELF)
    F, G, shell, out = y.duplicate(), y.duplicate(), fast.shell_matrix(), y.duplicate()
    fast.attach(ts, F, G, shell, True)
    y.set(0.0)
    for t in times:
        ts.computeRHSFunction(t, y, out)
        reference = python.forcing(t)
        assert not np.any(out.getArray()[:r])
        assert np.abs(out.getArray()[r:] - reference).max() <= 1e-13 * np.abs(reference).max() * max(1.0, t), t
    for obj in (ts, y, F, G, shell, out):
        obj.destroy()


@needs_c
@pytest.mark.serial
@pytest.mark.parametrize("history", ["harmonic", "random", "one_component_turbulence"])
def test_the_forcing_in_c_is_the_python_forcing_of_every_kind_of_load_history(paper, history):
    # f(t) = force_shape F(t) - base_load Omega''(t) on the paper's beam (a shaken support) with a harmonic
    # force, a random one (RandomProcess: a sum of cosines, which no other C test ran) and a load matrix of
    # one-component turbulence histories (one frequency each: C sums the cosines, not Horner's ladder),
    # against ReducedProblem.forcing to 1e-13 of the force at times up to 100 s (mutation testing: a sine
    # for a cosine in either sum passed every test)
    from dbf_hpc.excitation import CorrelatedProcess, Harmonic, RandomProcess, Turbulence

    model = paper[0]
    r = model.size
    rng = np.random.default_rng(5)
    if history == "harmonic":
        force, shape = Harmonic(amplitude=2.0, frequency_hz=3.0, phase=0.4), rng.normal(0, 1, r)
    elif history == "random":
        force, shape = RandomProcess(psd=1.0, band=(1.0, 50.0), seed=5, components=64), rng.normal(0, 1, r)
    else:
        force = CorrelatedProcess(Turbulence(psd=1.0, band=(2.0, 30.0), correlation_length=0.3, components=1), 3)
        shape = rng.normal(0, 1, (r, 3))
    model = dataclasses.replace(model, force=force, force_shape=shape)
    assert np.any(model.base_load) and model.support.amplitude > 0   # Omega'' enters too
    _check_c_forcing(model, np.concatenate([[0.0], rng.uniform(0, 100.0, 50)]))


@needs_c
@pytest.mark.serial
def test_c_callbacks_follow_the_python_trajectory_of_a_two_plane_beam_under_turbulence_with_friction(tube2d):
    # The same fixed steps: the C and Python callbacks differ by round-off in the laws and the
    # forcing, which contacts amplify (3e-9 of the peak after 0.06 s, measured); the statistics the
    # C monitor accumulates (radial quantities, work rate) are those of recorder.py
    settings = IntegratorSettings(t_end=0.03, dt=2e-5, adaptive=False, sample_dt=1e-3)
    a, b = (simulate_reduced(tube2d, dataclasses.replace(settings, callbacks=cb)) for cb in ("python", "c"))
    assert a.solver["callbacks"] == "python" and b.solver["callbacks"] == "c" and b.solver["newton"] == "c"
    assert a.displacement.shape == b.displacement.shape == (31, 4, 2)
    assert a.statistics["impacts"][:3].sum() >= 3 and np.all(a.statistics["work_rate"][1:] > 0)   # three slide
    peak = np.abs(a.displacement).max()
    assert np.abs(a.displacement - b.displacement).max() <= 1e-7 * peak
    assert np.abs(a.force_peak - b.force_peak).max() <= 1e-6 * np.abs(a.force_peak).max()
    np.testing.assert_array_equal(a.statistics["impacts"], b.statistics["impacts"])
    for name in a.statistics:
        np.testing.assert_allclose(b.statistics[name], a.statistics[name], rtol=1e-6, atol=0, err_msg=name)
    laws_force = [tube2d.constraints.force(z, v) for z, v in zip(b.displacement.reshape(31, -1),
                                                                 b.velocity.reshape(31, -1))]
    np.testing.assert_allclose(b.force.reshape(31, -1), laws_force, rtol=0, atol=1e-13 * np.abs(b.force).max())


@needs_c
@pytest.mark.serial
def test_c_callbacks_record_the_normal_alpha_v_of_a_two_direction_support_that_the_python_ones_do(tube2d):
    # The third support (flat bars, Hunt-Crossley alpha = 0.2 s/m) is the only damped one: alpha |v.n| over
    # the steps in contact, the same in C as in recorder.py, 0 at the others
    settings = IntegratorSettings(t_end=0.03, dt=2e-5, adaptive=False, sample_dt=1e-3)
    a, b = (simulate_reduced(tube2d, dataclasses.replace(settings, callbacks=cb)) for cb in ("python", "c"))
    assert b.solver["callbacks"] == "c" and a.statistics["impacts"][2] >= 1
    assert a.alpha_speed[2] > 0 and np.array_equal(a.alpha_speed[[0, 1, 3]], np.zeros(3))
    np.testing.assert_allclose(b.alpha_speed, a.alpha_speed, rtol=1e-6, atol=0)
