"""Turbulence along a span with partial correlation (issue 18): the spectral representation of a
random load per unit length with coherence exp(-|dx| / lambda), on the span's nodes, in both planes.
Each test is named by the physical fact it checks; the targets are the exact PSD and coherence."""
import math
import os
import zlib

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc
from scipy import signal

from dbf_hpc import Beam, BasisSettings, FullOrderModel, IntegratorSettings, Reductor, _romc
from dbf_hpc.errors import InputError
from dbf_hpc.excitation import MAX_COMPONENTS, MAX_COSINES, CorrelatedProcess, RandomForce, Turbulence
from dbf_hpc.schema import SECTIONS
from dbf_hpc.rom_integrator import c_core, effective_callbacks
from dbf_hpc.scene import load_scene
from dbf_hpc.structure import distributed_load

from conftest import assert_all, to_numpy


def tube(planes=2, elements=20, length=2.0):
    return Beam(length=length, E=195e9, I=2.49e-9, A=6.15e-5, rho=16000.0, elements=elements, planes=planes)


def nodal_history(load, times):
    """p(t) at the span's nodes, (nt, planes, n)."""
    X = load.process.sample(times)
    m = load.factor.shape[1]
    return np.stack([X[:, p * m:(p + 1) * m] @ load.factor.T for p in range(X.shape[1] // m)], axis=1)


BAND = (5.0, 55.0)
FS = 250.0


def long_sample(turbulence, planes=2, seconds=160.0, elements=20):
    with FullOrderModel.build(tube(planes, elements), [], turbulence, comm=PETSc.COMM_SELF) as fom:
        load = fom.force_matrix
        times = np.arange(0.0, seconds, 1.0 / FS)
        return load.points.copy(), nodal_history(load, times)


@pytest.mark.serial   # long_sample builds on COMM_SELF: the same samples on each rank (conftest)
def test_sample_psd_at_a_node_is_the_flat_target_and_its_variance_is_the_integral():
    psd = 3.0
    x, p = long_sample(Turbulence(psd, BAND, correlation_length=0.5, seed=7, components=64))
    f, S = signal.welch(p[:, 0, 7], fs=FS, nperseg=1024)
    inside = (f > BAND[0] + 2) & (f < BAND[1] - 2)
    outside = (f < BAND[0] - 2) | ((f > BAND[1] + 2) & (f < FS / 2 - 5))
    assert abs(np.mean(S[inside]) / psd - 1) < 0.05
    assert np.max(S[outside]) < 0.02 * psd
    for plane in (0, 1):   # every node, both planes: var p = int S df
        assert np.allclose(p[:, plane].var(axis=0), psd * (BAND[1] - BAND[0]), rtol=0.05)


@pytest.mark.serial   # long_sample builds on COMM_SELF: the same samples on each rank (conftest)
def test_knee_spectrum_is_flat_below_the_corner_and_falls_as_f_to_the_minus_slope_above():
    psd, corner, slope = 2.0, 20.0, 3.0
    x, p = long_sample(Turbulence(psd, BAND, 0.5, seed=3, components=128, spectrum="knee", corner_hz=corner,
                                  slope=slope), planes=1)
    f, S = signal.welch(p[:, 0, 5], fs=FS, nperseg=1024)
    target = psd * np.where(f <= corner, 1.0, (np.maximum(f, 1e-9) / corner) ** -slope)
    for lo, hi in ((7.0, 18.0), (25.0, 35.0), (40.0, 52.0)):
        band = (f > lo) & (f < hi)
        assert abs(np.mean(S[band]) / np.mean(target[band]) - 1) < 0.1, (lo, hi)


@pytest.mark.serial   # long_sample builds on COMM_SELF: the same samples on each rank (conftest)
def test_sample_coherence_between_two_nodes_is_exp_minus_distance_over_lambda_and_y_z_are_independent():
    lam = 0.5
    x, p = long_sample(Turbulence(1.0, BAND, lam, seed=11, components=64))
    i = 2
    for j in (3, 5, 8, 12):
        dx = abs(x[j] - x[i])
        target = np.exp(-dx / lam)
        rho = np.corrcoef(p[:, 0, i], p[:, 0, j])[0, 1]        # zero lag: the coherence is real
        assert abs(rho - target) < 0.05, (dx, rho, target)
        # |gamma|^2 over bins (~1 Hz) wider than df (0.78 Hz): each holds a cosine of every history
        f, C = signal.coherence(p[:, 0, i], p[:, 0, j], fs=FS, nperseg=256)
        inside = (f > BAND[0] + 2) & (f < BAND[1] - 2)
        assert abs(np.mean(C[inside]) - target**2) < 0.03, (dx, np.mean(C[inside]), target**2)
        assert abs(np.corrcoef(p[:, 0, i], p[:, 1, j])[0, 1]) < 0.05   # y and z: independent fields


def test_infinite_correlation_length_gives_one_history_times_the_uniform_load_shape(comm):
    turbulence = Turbulence(1.0, BAND, correlation_length=np.inf, seed=5, components=32, span=(0.5, 1.5))
    with FullOrderModel.build(tube(1, 40), [], turbulence, comm=comm) as fom:
        load = fom.force_matrix
        assert load.count == 1
        uniform = distributed_load(fom.operators, 0.5, 1.5)
        assert_all(np.allclose(load.rows[:, 0], uniform.getArray(), rtol=0, atol=1e-14))
        uniform.destroy()
        for t in (0.013, 0.4):
            p = load.nodal(t)
            assert np.allclose(p, p[0, 0], rtol=1e-12)     # the same value at every node of the span
            F = fom.operators.K.createVecLeft()
            F.zeroEntries()
            fom.add_loads(t, F)
            assert_all(np.allclose(F.getArray(), load.rows[:, 0] * p[0, 0], rtol=1e-12, atol=1e-15))
            F.destroy()


def loads_at(fom, times):
    out = []
    for t in times:
        F = fom.operators.K.createVecLeft()
        F.zeroEntries()
        fom.add_loads(t, F)
        out.append(to_numpy(F))
        F.destroy()
    return np.array(out)


@pytest.mark.parallel
def test_the_same_seed_gives_the_same_forces_on_one_and_two_ranks():
    turbulence = Turbulence(2.0, BAND, 0.3, seed=21, components=32, span=(0.4, 1.8))
    times = (0.0, 0.0137, 0.52)
    with FullOrderModel.build(tube(2, 30), [], turbulence, comm=PETSc.COMM_WORLD) as fom:
        two = loads_at(fom, times)
    with FullOrderModel.build(tube(2, 30), [], turbulence, comm=PETSc.COMM_SELF) as fom:
        one = loads_at(fom, times)
    assert_all(np.max(np.abs(two - one)) <= 1e-13 * np.max(np.abs(one)))
    assert_all(np.max(np.abs(one)) > 0)


def test_reduced_load_is_the_projection_of_the_full_order_load_at_every_time(comm):
    turbulence = Turbulence(1.0, BAND, 0.4, seed=2, components=32)
    with FullOrderModel.build(tube(2, 20), [], turbulence, comm=comm) as fom:
        with Reductor(fom, BasisSettings(modes=8)) as reductor:
            model = reductor.reduce()
            for t in (0.01, 0.3):
                F = fom.operators.K.createVecLeft()
                F.zeroEntries()
                fom.add_loads(t, F)
                projected = reductor.basis().dot(F)
                F.destroy()
                assert np.allclose(model.external_force(t), projected, rtol=1e-12, atol=1e-12 * np.abs(projected).max())
        assert model.force_shape.shape == (model.size, fom.force_matrix.count)


def test_reduced_and_full_order_agree_under_turbulence_before_any_contact(comm):
    from dbf_hpc.damping import Damping
    from dbf_hpc.simulate import simulate_full, simulate_reduced

    turbulence = Turbulence(1.0, (0.0, 40.0), 0.3, seed=4, components=32)
    with FullOrderModel.build(tube(2, 20), [], turbulence, damping=Damping(rayleigh_alpha=2.0), probes=[0.7],
                              comm=comm) as fom:
        with Reductor(fom, BasisSettings(modes=16)) as reductor:
            model = reductor.reduce()
        reduced = simulate_reduced(model, IntegratorSettings(t_end=0.3, dt=1e-4, sample_dt=2e-3, rtol=1e-8))
        full = simulate_full(fom, IntegratorSettings(t_end=0.3, dt=2e-5, sample_dt=2e-3, adaptive=False))
    peak = np.abs(full.probes).max()
    assert peak > 0
    assert np.abs(reduced.probes - full.probes).max() < 0.02 * peak


def test_turbulence_descriptions_refuse_bad_values_in_one_line():
    for bad in (dict(psd=0.0), dict(band=(10.0, 5.0)), dict(correlation_length=0.0), dict(components=0),
                dict(spectrum="pink"), dict(spectrum="knee", corner_hz=0.0, slope=2.0)):
        values = {"psd": 1.0, "band": (0.0, 10.0), "correlation_length": 0.2, **bad}
        with pytest.raises(InputError, match="turbulence: ") as e:
            Turbulence(**values)
        assert "\n" not in str(e.value)


def test_an_infinite_psd_corner_or_slope_is_refused_as_it_would_make_a_nan_load():
    # only the correlation length may be inf (a fully correlated load); S = inf has no finite variance
    for bad in (dict(psd=math.inf), dict(spectrum="knee", corner_hz=math.inf, slope=2.0),
                dict(spectrum="knee", corner_hz=5.0, slope=math.inf)):
        values = {"psd": 1.0, "band": (0.0, 10.0), "correlation_length": 0.2, **bad}
        with pytest.raises(InputError, match="turbulence: .* must be finite"):
            Turbulence(**values)
    assert Turbulence(1.0, (0.0, 10.0), math.inf).correlation_length == math.inf


def test_components_beyond_what_any_run_resolves_are_one_input_error_not_a_memory_error():
    # 2^16 cosines resolve the band to 1e-5 of its width; 1e9 asked for tens of GB before
    with pytest.raises(InputError, match="RandomForce components must be at most 65536"):
        RandomForce(1.0, (0.0, 10.0), components=10**9)
    with pytest.raises(InputError, match="turbulence: components must be at most 65536"):
        Turbulence(1.0, (0.0, 10.0), 0.2, components=MAX_COMPONENTS + 1)
    assert RandomForce(1.0, (0.0, 10.0), components=MAX_COMPONENTS).history().frequency.size == MAX_COMPONENTS
    # over all the histories of a Turbulence: the short correlation length of a long span needs many
    with pytest.raises(InputError, match="cosines at every step"):
        CorrelatedProcess(Turbulence(1.0, (0.0, 10.0), 1e-3, components=MAX_COMPONENTS), MAX_COSINES // MAX_COMPONENTS + 1)
    for limit in (MAX_COMPONENTS, MAX_COSINES):   # the scene reference says the same limits
        assert str(limit) in SECTIONS["excitation"][1]["components"].doc


def test_c_callbacks_take_a_load_matrix_of_one_or_two_plane_turbulence():
    from dbf_hpc import _romc

    if _romc.core is None:
        pytest.skip(_romc.why)
    for dimension in (1, 2):
        assert c_core("c", dimension=dimension) is _romc.core
        assert c_core("auto", dimension=dimension) is _romc.core
    assert c_core("python") is None


SCENE = """
[structure]
kind = "beam"
length = 2.0
elements = 20
E = 195e9
I = 2.49e-9
A = 6.15e-5
rho = 16000.0
planes = 2
[excitation]
kind = "turbulence"
psd = 1.0
band = [0.0, 40.0]
{extra}
[integrator]
t_end = 0.01
[output]
file = "out.h5"
"""


def test_turbulence_scene_takes_an_infinite_correlation_length(shared_tmp_path):
    path = os.path.join(shared_tmp_path, "inf.toml")
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "w") as f:
            f.write(SCENE.format(extra="correlation_length = inf\nspan = [0.5, 1.5]"))
    MPI.COMM_WORLD.Barrier()
    turbulence = load_scene(path).excitation()
    assert turbulence.correlation_length == np.inf and turbulence.span == (0.5, 1.5)
    with pytest.raises(InputError, match="finite"):
        load_scene(path, ["excitation.psd=inf"])


@pytest.mark.parametrize("kind, extra", [("random", "correlation_length = 0.3"), ("random", "correlation_length = inf"),
                                         ("random", 'spectrum = "knee"\ncorner_hz = 10.0\nslope = 2.0'),
                                         ("random", "slope = 2.0"), ("base", "correlation_length = 0.3\nfrequency_hz = 5.0")])
def test_turbulence_keys_on_another_kind_are_refused_not_ignored(shared_tmp_path, kind, extra):
    # kind = "random" is fully correlated with a flat PSD: a correlation length or a knee left in the
    # scene would describe a load that is not the one applied
    path = os.path.join(shared_tmp_path, f"k{zlib.crc32((kind + extra).encode())}.toml")
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "w") as f:
            f.write(SCENE.format(extra=extra).replace('kind = "turbulence"', f'kind = "{kind}"'))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match='belongs? to kind = "turbulence" and would be ignored') as e:
        load_scene(path)
    assert "\n" not in str(e.value)


def test_free_vibration_of_a_turbulence_scene_is_one_override_away(shared_tmp_path):
    # --set excitation.kind=none keeps the scene's other excitation keys (they describe no load then)
    path = os.path.join(shared_tmp_path, "free.toml")
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "w") as f:
            f.write(SCENE.format(extra='correlation_length = 0.3\nspectrum = "knee"\ncorner_hz = 10.0\nslope = 2.0'))
    MPI.COMM_WORLD.Barrier()
    assert load_scene(path, ["excitation.kind=\"none\""]).excitation().kind == "none"


@pytest.mark.parametrize("kind, extra, word", [("random", "frequency_hz = 10.0", "frequency_hz"),
                                               ("turbulence", "correlation_length = 0.3\namplitude = 3.0", "amplitude"),
                                               ("force", "x = 1.0\nfrequency_hz = 5.0\namplitude = 1.0", "psd, band")])
def test_harmonic_keys_on_a_random_load_and_spectral_keys_elsewhere_are_refused_not_ignored(shared_tmp_path, kind,
                                                                                            extra, word):
    # a random load has no single frequency or amplitude, a harmonic force no PSD: the value would be
    # silently dropped and the run would describe another load than the scene's (kind = "none" keeps
    # them: --set excitation.kind=none is the scene's free vibration)
    path = os.path.join(shared_tmp_path, f"h{zlib.crc32((kind + extra).encode())}.toml")
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "w") as f:
            f.write(SCENE.format(extra=extra).replace('kind = "turbulence"', f'kind = "{kind}"'))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=f"{word} ha(s|ve) no meaning for kind = '{kind}' and would be ignored"):
        load_scene(path)


@pytest.mark.parametrize("extra, message", [
    ("", "correlation_length"),
    ("correlation_length = 0.0", "correlation_length > 0"),
    ("correlation_length = -inf", r"correlation_length > 0 \(m; inf for a fully correlated load\), got -inf"),
    ("correlation_length = 0.3\ndirection = [1.0, 0.0]", "remove direction"),
    ("correlation_length = 0.3\nspectrum = \"knee\"", "corner_hz"),
    ("correlation_length = 0.3\nspectrum = \"pink\"", "spectrum"),
    ("correlation_length = 0.3\ncorner_hz = 10.0", "knee"),
])
def test_turbulence_scenes_refuse_incomplete_keys_in_one_line(shared_tmp_path, extra, message):
    path = os.path.join(shared_tmp_path, f"t{zlib.crc32(extra.encode())}.toml")   # hash() differs by process
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "w") as f:
            f.write(SCENE.format(extra=extra))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=message) as e:
        load_scene(path)
    assert "\n" not in str(e.value)


def test_a_planar_turbulence_scene_runs_reduced_on_the_c_callbacks_and_full_order(shared_tmp_path, comm):
    import h5py
    import json

    from dbf_hpc.run import run

    path = os.path.join(shared_tmp_path, "planar.toml")
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "w") as f:
            planar = SCENE.replace("planes = 2", "planes = 1")
            f.write(planar.format(extra="correlation_length = 0.3\nspan = [1.0, 2.0]")
                    + '[basis]\nmodes = 6\nestimate = false\n[[constraint]]\nx = 1.5\nclearance = 1e-6\nk = 1e5\n')
    MPI.COMM_WORLD.Barrier()
    scene = load_scene(path, [f"basis.cache={json.dumps(str(shared_tmp_path))}"])
    peaks = []
    for method in ("rom", "full"):
        out = os.path.join(shared_tmp_path, f"planar-{method}.h5")
        summary = run(scene, out, progress=False, comm=comm, method=method)
        peaks.append(summary["constraint_stats"]["displacement_peak"][0])
        if method == "rom":
            assert summary["stats"]["callbacks"] == effective_callbacks("auto")
            assert summary["stats"]["callbacks"] == ("python" if _romc.core is None else "c")
            if comm.getRank() == 0:
                with h5py.File(out) as f:
                    assert f["constraints/displacement"].shape[1:] == (1,)
    assert all(p > 0 for p in peaks)


TWO_PLANE_SUPPORTS = """[basis]
modes = 8
estimate = false
[output]
checkpoint_dt = 0.01
snapshots = 4
[[constraint]]
x = 0.7
law = "circular"
clearance = 2e-6
k = 2e4
mu = 0.3
[[constraint]]
x = 1.5
law = "flat_bar"
angle = 30.0
clearance = 2e-6
k = 2e4
mu = 0.3
"""


# The Python callbacks' case is serial (conftest) where the C callbacks are built: the callbacks differ only
# in rank 0's integration, and the [c] case takes the same collective path (the run, its checkpoint, the
# refused and the good resume) on 2 ranks in 0.5 s; the Python one took 12.6 s of the 2-rank pass in CI.
@pytest.mark.parametrize("callbacks", [pytest.param("python", marks=() if _romc.core is None else pytest.mark.serial),
                                       "c"])
def test_a_two_plane_run_under_turbulence_stopped_at_a_checkpoint_resumes_to_the_uninterrupted_result(
        shared_tmp_path, callbacks, monkeypatch):
    """The turbulence histories are not stored in the checkpoint: they are sums of cosines whose
    phases come from the seed, regenerated on resume (excitation.CorrelatedProcess). The resumed run
    is the uninterrupted one bit for bit, and a resume with another seed or PSD (other histories) is
    refused by the checkpoint's scene key. To 0.03 s: both supports touch within 2.3 ms, so the
    checkpoint at 0.02 s carries their contact and sliding, and any bit lost there shows at once."""
    import h5py
    import json

    from dbf_hpc import run as run_module
    from dbf_hpc.errors import DbfError

    if callbacks == "c" and _romc.core is None:
        pytest.skip(_romc.why)

    path = os.path.join(shared_tmp_path, "resume2d.toml")
    if MPI.COMM_WORLD.rank == 0:
        with open(path, "w") as f:
            f.write(SCENE.format(extra="correlation_length = 0.3\nspan = [1.0, 2.0]\nseed = 7")
                    .replace("t_end = 0.01", "t_end = 0.03")
                    .replace("psd = 1.0", "psd = 4.0").replace('[output]\nfile = "out.h5"\n', "")
                    + TWO_PLANE_SUPPORTS)
    MPI.COMM_WORLD.Barrier()
    sets = [f"basis.cache={json.dumps(str(shared_tmp_path))}", f"integrator.callbacks={callbacks}"]
    reference, target = (os.path.join(shared_tmp_path, f"{name}-2d-{callbacks}.h5") for name in ("ref", "cut"))
    run_module.run(load_scene(path, sets), reference, progress=False)
    original = run_module.Checkpointing.on_step

    def stop_at_the_second_checkpoint(self, ts, t, q, p):
        if t >= 0.02:
            self.interrupted = True   # as SIGTERM does
        return original(self, ts, t, q, p)

    monkeypatch.setattr(run_module.Checkpointing, "on_step", stop_at_the_second_checkpoint)
    with pytest.raises(DbfError, match="checkpointed"):
        run_module.run(load_scene(path, sets), target, progress=False)
    monkeypatch.setattr(run_module.Checkpointing, "on_step", original)
    for change in ("excitation.seed=8", "excitation.psd=1.1"):
        with pytest.raises(InputError, match="written by a different scene or setup \\(scene differs\\)"):
            run_module.run(load_scene(path, sets + [change]), target, progress=False, resume=True)
    summary = run_module.run(load_scene(path, sets), target, progress=False, resume=True)
    assert summary["stats"]["final_time"] == pytest.approx(0.03)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(reference) as a, h5py.File(target) as b:
            assert json.loads(a.attrs["solver_stats"])["callbacks"] == callbacks
            assert json.loads(b.attrs["solver_stats"])["callbacks"] == callbacks
            assert a["constraints/displacement"].shape[1:] == (2, 2)
            assert np.all(a["constraints/stats/work_rate"][:] > 0)     # both supports slide under friction
            for name in ("time", "constraints/displacement", "constraints/force", "constraints/force_peak",
                         "reduced/q", "snapshots/w", *[f"constraints/stats/{k}" for k in a["constraints/stats"]]):
                assert np.array_equal(a[name][:], b[name][:], equal_nan=True), name
    assert_all(True)


def test_a_psd_whose_load_peak_overflows_double_precision_is_refused_naming_psd():
    # The peak of a history, every cosine at its crest, is components sqrt(2 psd df); red team: psd = 1e308
    # gave numpy's overflow warning and a first-step failure naming neither psd nor the load
    for make in (lambda psd: RandomForce(psd, (0.0, 1000.0)), lambda psd: Turbulence(psd, (0.0, 1000.0), 0.2)):
        with pytest.raises(InputError, match=r"psd = 1e\+308 over the band 0 to 1000 Hz: the load's peak overflows"):
            make(1e308)
    history = RandomForce(1e250, (0.0, 1000.0)).history()   # large but representable: still a load
    assert np.isfinite(history.value(np.array([0.0, 0.1]))).all()


@pytest.mark.parametrize("lam", [5.0, 50.0])
def test_the_coherence_factor_keeps_every_points_psd_exactly_and_its_coherence_to_the_variance_dropped(lam):
    # H H^T ~ Gamma = exp(-|dx| / lambda) from the leading eigenvectors holding VARIANCE_KEPT of the trace, each
    # row then rescaled: diag(H H^T) = 1 exactly (every node keeps the target PSD) and every coherence within the
    # dropped share. Planted bug it catches: the rows not rescaled (each node's PSD 0.1 % low, which the 5 %
    # sample-PSD tests cannot see).
    from dbf_hpc.excitation import VARIANCE_KEPT, coherence_factor

    x = np.linspace(0.0, 2.0, 41)
    gamma = Turbulence(1.0, BAND, lam, seed=1).coherence(x)
    H = coherence_factor(gamma)
    np.testing.assert_allclose(np.diag(H @ H.T), 1.0, rtol=0, atol=1e-14)
    assert np.abs(H @ H.T - gamma).max() < 4 * (1 - VARIANCE_KEPT)   # measured 2.2e-3 at lambda = 5 m
    assert H.shape[1] < x.size          # a well correlated field: fewer histories than nodes (34 and 9 of 41)


@pytest.mark.parametrize("lam", [0.05, 0.5, 5.0, 50.0])
def test_the_coherence_factors_histories_hold_the_kept_share_of_the_loads_variance_and_are_the_fewest_that_do(lam):
    # The load's variance over the span is trace(Gamma); the field generated from H holds the part of it in
    # H's column space, trace(P Gamma) (P the orthogonal projector onto span H). It must be at least
    # VARIANCE_KEPT, with no history to spare: the best one history fewer (Gamma's leading eigenvectors) holds
    # less. Planted bug this catches, which the coherence test above does not: one history too few (the
    # dropped share just above 0.1 %, each coherence still within 4 times it).
    from dbf_hpc.excitation import VARIANCE_KEPT, coherence_factor

    x = np.linspace(0.0, 2.0, 41)
    gamma = Turbulence(1.0, BAND, lam, seed=1).coherence(x)
    H = coherence_factor(gamma)
    Q, _ = np.linalg.qr(H)
    held = np.trace(Q.T @ gamma @ Q) / np.trace(gamma)
    assert held >= VARIANCE_KEPT, (lam, held)
    best_fewer = np.sort(np.linalg.eigvalsh(gamma))[::-1][:H.shape[1] - 1].sum() / np.trace(gamma)
    assert best_fewer < VARIANCE_KEPT, (lam, H.shape[1], best_fewer)
