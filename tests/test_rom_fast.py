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
    result = simulate_reduced(model, dataclasses.replace(settings, callbacks="auto"))
    assert result.solver["callbacks"] == "python"
    warning = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(warning) == 1 and "Python callbacks" in warning[0]


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
    # arrays, and a checkpoint must hold all of it.
    import h5py
    from mpi4py import MPI

    from dbf_hpc import run as run_module
    from dbf_hpc.errors import DbfError
    from dbf_hpc.scene import load_scene

    if callbacks == "c" and _romc.core is None:
        pytest.skip(_romc.why)
    sets = ["basis.cache=off", "integrator.t_end=0.6", "output.checkpoint_dt=0.2", "output.snapshots=5",
            f"integrator.callbacks={callbacks}"]
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
