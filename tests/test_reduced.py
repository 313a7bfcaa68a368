"""Pieces of the reduced model (rom.py, excitation.py): the random forcing process, the distributed load, and
the continuation of the state across a support jump."""
import numpy as np
import pytest

from dbf_hpc.modes import reference_modes
from dbf_hpc.excitation import Harmonic, RandomProcess
from dbf_hpc.structure import Beam, assemble_beam, distributed_load

BEAM = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=80)


@pytest.mark.serial   # numpy only: the same 400 001 samples on each rank (conftest)
def test_random_forcing_has_the_requested_variance_and_band():
    process = RandomProcess(psd=0.5, band=(2.0, 12.0), seed=7, components=400)
    assert np.sum(process.amplitude**2) / 2 == pytest.approx(0.5 * 10.0, rel=1e-12)   # S (f_high - f_low)
    assert process.frequency.min() > 2.0 and process.frequency.max() < 12.0
    t = np.linspace(0, 200, 400001)
    f = process.value(t)
    assert np.mean(f**2) == pytest.approx(5.0, rel=0.05)
    spectrum = np.abs(np.fft.rfft(f)) ** 2
    freq = np.fft.rfftfreq(t.size, t[1] - t[0])
    inside = (freq > 2.0) & (freq < 12.0)
    assert spectrum[inside].sum() > 0.999 * spectrum.sum()


def test_random_forcing_is_reproducible_from_its_seed():
    t = np.linspace(0, 1, 101)
    a, b = RandomProcess(1.0, (1, 5), 3).value(t), RandomProcess(1.0, (1, 5), 3).value(t)
    c = RandomProcess(1.0, (1, 5), 4).value(t)
    assert np.array_equal(a, b) and not np.allclose(a, c)


def test_uniform_load_projects_onto_the_modes_as_the_exact_integral():
    # phi_n = sqrt(2 / (rho A L)) sin(n pi x / L): int phi_n dx = sqrt(2 / (rho A L)) L (1 - cos n pi) / (n pi)
    ops = assemble_beam(BEAM)
    modes = reference_modes(ops, count=4)
    load = distributed_load(ops, 0.0, 1.0)
    projected = []
    for i in range(4):
        column = modes.vectors.getColumn(i)
        projected.append(abs(column.dot(load)))
        modes.vectors.restoreColumn(i, column)
    n = np.arange(1, 5)
    exact = np.sqrt(2 / (BEAM.rhoA * 1.0)) * (1 - np.cos(n * np.pi)) / (n * np.pi)
    np.testing.assert_allclose(projected, exact, atol=1e-8 * exact.max())
    load.destroy()
    modes.destroy()
    ops.destroy()


def test_harmonic_derivatives_are_consistent():
    h, t, dt = Harmonic(2e-3, 1.5), 0.37, 1e-6
    assert (h.value(t + dt) - h.value(t - dt)) / (2 * dt) == pytest.approx(h.rate(t), rel=1e-8)
    assert (h.rate(t + dt) - h.rate(t - dt)) / (2 * dt) == pytest.approx(h.acceleration(t), rel=1e-8)


def test_a_support_jump_between_cases_keeps_the_total_displacement_and_velocity_continuous():
    # z = B q + r_c Omega(t): where the support moves from (value, rate) to (new, new rate) at a case
    # boundary, the relative state must take r (old - new), r as the basis holds it (M_r^-1 V^T M r), which
    # is what sweep.py passes to support_jump. Here the basis holds r exactly: B r = r_c.
    from dbf_hpc.constraints import ConstraintSet
    from dbf_hpc.laws import ConstraintLaws, law
    from dbf_hpc.rom import ReducedModel

    M = np.diag([2.0, 3.0])
    r = np.array([0.5, -1.0])                     # the influence in basis coordinates
    B = np.array([[1.0, 0.2], [0.0, 1.0]])
    constraints = ConstraintSet(rows=[[0], [1]], laws=ConstraintLaws([law("linear", k=1.0)] * 2), labels=("a", "b"),
                                positions=np.zeros(2))
    model = ReducedModel(M=M, C=np.zeros((2, 2)), K=np.eye(2), B=B, r_c=B @ r, base_load=np.zeros(2),
                         force_shape=np.zeros(2), constraints=constraints, support=Harmonic(), force=Harmonic(),
                         q0=np.zeros(2), p0=np.zeros(2), probe_B=np.zeros((0, 2)), probe_r=np.zeros(0),
                         basis_info={}, r_q=M @ r)
    q, p = np.array([1e-3, -2e-3]), np.array([0.1, 0.3])
    (old, old_rate), (new, new_rate) = (0.3, 2.0), (-0.1, 5.0)
    dq, dp = model.support_jump(old - new, old_rate - new_rate)
    np.testing.assert_allclose(B @ (q + dq) + model.r_c * new, B @ q + model.r_c * old, rtol=0, atol=1e-15)
    np.testing.assert_allclose(B @ (p + dp) + model.r_c * new_rate, B @ p + model.r_c * old_rate, rtol=0, atol=1e-14)
