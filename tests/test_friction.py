"""Coulomb friction through a law alone (issue 18): law = "friction", N = -mu F_n tanh(v / v_reg), on
a single-DOF oscillator against Den Hartog's exact free decay with dry friction and his forced
steady state without stops. Each test is named
by the physical fact it checks."""
import math

import numpy as np
import pytest

from dbf_hpc import IntegratorSettings, _romc, law, simulate_reduced
from dbf_hpc.constraints import ConstraintSet
from dbf_hpc.errors import InputError
from dbf_hpc.excitation import Harmonic
from dbf_hpc.laws import ConstraintLaws
from dbf_hpc.rom import ReducedModel
from dbf_hpc.rom_integrator import c_core


def oscillator(k, x0, friction, m=1.0):
    """m x'' + k x = N(x, x'): one DOF, the constraint on it (B = 1), no support motion or force."""
    one = np.ones((1, 1))
    constraints = ConstraintSet(rows=[[0]], laws=ConstraintLaws([friction]), labels=("dof 0",),
                                positions=np.zeros(1))
    return ReducedModel(M=m * one, C=np.zeros((1, 1)), K=k * one, B=one.copy(), r_c=np.zeros(1),
                        base_load=np.zeros(1), force_shape=np.zeros(1), constraints=constraints, support=Harmonic(),
                        force=Harmonic(), q0=np.array([x0]), p0=np.zeros(1), probe_B=np.zeros((0, 1)),
                        probe_r=np.zeros(0), basis_info={"omega": np.array([math.sqrt(k / m)]),
                                                         "enrichment_omega": np.zeros(0), "dbf_k": np.zeros(0),
                                                         "enrichment": "none"})


def coulomb_free_decay(t, omega, delta, x0):
    """Den Hartog's free decay of m x'' + k x = -F sign(x') from x0 > 0 at rest (delta = F / k): each
    half period pi / omega is a cosine about +-delta, the turning points fall by 2 delta, and the
    motion stops at the first turning point with |x| <= delta."""
    x = np.empty_like(t)
    turn, start, sign = x0, 0.0, 1.0     # sign of the centre: +delta while moving down from x > 0
    half = math.pi / omega
    stopped_at = None
    while abs(turn) > delta:
        centre = sign * delta
        inside = (t >= start) & (t < start + half)
        x[inside] = centre + (turn - centre) * np.cos(omega * (t[inside] - start))
        turn, start, sign = 2 * centre - turn, start + half, -sign
    stopped_at = start
    x[t >= stopped_at] = turn
    return x, turn, stopped_at


@pytest.mark.serial   # a one-DOF model every rank holds whole: the same integration on each rank (conftest)
@pytest.mark.parametrize("callbacks", ["python", "c"])
def test_free_decay_with_coulomb_friction_loses_4_mu_n_over_k_a_cycle_and_stops_in_the_dead_zone(callbacks):
    if callbacks == "c" and _romc.core is None:
        pytest.skip(_romc.why)
    m, omega = 1.0, 2 * math.pi
    k = m * omega**2
    mu, normal = 0.25, 4.0
    delta = mu * normal / k                       # mu N / k, m
    x0 = 10.3 * delta                             # turning points 10.3, -8.3, 6.3, -4.3, 2.3, -0.3 delta
    v_reg = 1e-6 * x0 * omega
    model = oscillator(k, x0, law("friction", normal_force=normal, mu=mu, v_reg=v_reg), m)
    result = simulate_reduced(model, IntegratorSettings(t_end=4.0, dt=1e-4, sample_dt=1e-3, rtol=1e-8, atol=1e-12,
                                                        callbacks=callbacks))
    assert result.solver["callbacks"] == callbacks
    t, x = result.time, result.displacement[:, 0]
    exact, rest, stop = coulomb_free_decay(t, omega, delta, x0)
    assert rest == pytest.approx(-0.3 * delta) and stop == pytest.approx(2.5)
    assert np.max(np.abs(x - exact)) < 0.01 * delta
    # the turning points of the numbers: one every half period, each 2 mu N / k below the previous one
    turns = [x[np.argmin(np.abs(t - n * 0.5))] for n in range(6)]
    assert np.allclose(np.abs(np.diff(np.abs(turns))), 2 * delta, atol=0.01 * delta)
    after = t > stop + 0.05
    assert np.all(np.abs(x[after]) <= delta)
    assert np.max(np.abs(result.velocity[after, 0])) < 1e-4 * x0 * omega   # stuck (a creep ~ v_reg)
    # the friction force is mu N against the sliding, below mu N when stuck
    assert np.max(np.abs(result.force[:, 0])) <= mu * normal * (1 + 1e-12)


def test_friction_law_jacobian_is_exact_against_finite_differences():
    laws = ConstraintLaws([law("friction", normal_force=3.0, mu=0.4, v_reg=1e-3), law("deadband", clearance=1e-3,
                                                                                          k=1e5)])
    z = np.array([0.2, 2e-3])
    for v in (np.array([3e-4, 0.1]), np.array([-2e-3, 0.0]), np.array([0.0, 0.0])):
        force, dz, dv = laws.force_and_jacobian(z, v)
        h = 1e-9
        assert np.allclose((laws.force(z, v + [h, 0]) - laws.force(z, v - [h, 0]))[0] / (2 * h), dv[0], rtol=1e-6)
        assert dz[0] == 0.0
        assert force[0] == pytest.approx(-0.4 * 3.0 * math.tanh(v[0] / 1e-3))


def test_friction_law_keys_are_checked_in_one_line():
    with pytest.raises(InputError, match="needs mu"):
        law("friction", normal_force=1.0)
    with pytest.raises(InputError, match="normal_force"):
        law("friction", mu=0.3)
    with pytest.raises(InputError, match="applies to law = \"friction\""):
        law("deadband", clearance=1e-3, k=1e6, normal_force=2.0)
    with pytest.raises(InputError, match="no contact damping"):
        law("friction", normal_force=1.0, mu=0.3, damping="linear", c=1.0)
    assert c_core("python") is None


def den_hartog_steady_state(k, m, P0, F, omega):
    """The exact periodic motion without stops of m x'' + k x + F sign(x') = P0 cos(omega t + phi),
    two stops-free halves per period (Den Hartog 1931, solved here in closed form): with
    theta = pi omega_n / omega, D = P0 / (k - m omega^2), the half from the top (x = X, x' = 0, at
    t = 0) is x = -F/k cos(omega_n t) + B sin(omega_n t) + D cos(omega t + phi) + F/k, B = -(F/k)
    sin(theta) / (1 + cos(theta)), sin(phi) = B omega_n / (D omega), X = D cos(phi). Returns
    (X, phi, x(t) over the first half)."""
    wn = math.sqrt(k / m)
    theta = math.pi * wn / omega
    D = P0 / (k - m * omega**2)
    B = -(F / k) * math.sin(theta) / (1 + math.cos(theta))
    phi = math.asin(B * wn / (D * omega))
    X = D * math.cos(phi)

    def half(t):
        return -F / k * np.cos(wn * t) + B * np.sin(wn * t) + D * np.cos(omega * t + phi) + F / k

    return X, phi, half


@pytest.mark.serial   # a one-DOF model every rank holds whole: the same integration on each rank (conftest)
@pytest.mark.parametrize("callbacks", ["python", "c"])
def test_forced_oscillator_with_coulomb_friction_follows_den_hartogs_steady_state_without_stops(callbacks):
    if callbacks == "c" and _romc.core is None:
        pytest.skip(_romc.why)
    m, wn = 1.0, 2 * math.pi
    k = m * wn**2
    P0, F, beta = 1.0, 0.5, 0.6
    omega = beta * wn
    X, phi, half = den_hartog_steady_state(k, m, P0, F, omega)
    T = 2 * math.pi / omega
    s = np.linspace(0, T / 2, 2001)
    assert np.all(np.diff(half(s))[:-1] < 0)                  # no stop in the half: the formula holds
    assert half(T / 2) == pytest.approx(-X, rel=1e-12)
    # friction takes 5 % off the frictionless amplitude D; the test resolves 1e-3 of X
    assert X < 0.96 * P0 / (k - m * omega**2)
    model = oscillator(k, X, law("friction", normal_force=F, mu=1.0, v_reg=1e-5 * X * omega), m)
    model = model.with_case(force=Harmonic(P0, omega / (2 * math.pi), phi + math.pi / 2))
    model = type(model)(**{**model.__dict__, "force_shape": np.ones(1)})
    result = simulate_reduced(model, IntegratorSettings(t_end=2 * T, dt=1e-4, sample_dt=T / 400, rtol=1e-7,
                                                        atol=1e-11, callbacks=callbacks))
    assert result.solver["callbacks"] == callbacks
    t, x = result.time, result.displacement[:, 0]
    cycle = np.mod(t, T)
    exact = np.where(cycle <= T / 2, half(np.minimum(cycle, T / 2)), -half(np.maximum(cycle - T / 2, 0.0)))
    assert np.max(np.abs(x - exact)) < 1e-3 * X


def test_friction_mixed_with_other_laws_gives_each_law_its_own_values():
    friction = law("friction", normal_force=3.0, mu=0.4, v_reg=1e-3)
    deadband = law("deadband", clearance=1e-3, k=1e5, damping="linear", c=20.0)
    z, v = np.array([2e-3, 2e-3, 0.5]), np.array([0.01, 4e-4, -2e-4])
    mixed = ConstraintLaws([deadband, friction, friction])
    alone = [ConstraintLaws([deadband]), ConstraintLaws([friction]), ConstraintLaws([friction])]
    force, dz, dv = mixed.force_and_jacobian(z, v)
    for j, one in enumerate(alone):
        f1, z1, v1 = one.force_and_jacobian(z[j:j + 1], v[j:j + 1])
        assert (force[j], dz[j], dv[j]) == (f1[0], z1[0], v1[0])
    assert np.array_equal(mixed.force(z, v), force)
    assert np.all(mixed.in_contact(z)[1:]) and mixed.potential(z)[1] == 0.0


def test_full_order_and_reduced_model_agree_on_a_beam_held_by_friction(comm):
    from dbf_hpc import BasisSettings, Beam, Constraint, FullOrderModel, Reductor
    from dbf_hpc.excitation import PointForce
    from dbf_hpc.simulate import simulate_full

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=40)
    held = [Constraint(x=0.5, law=law("friction", normal_force=0.02, mu=0.3, v_reg=1e-4))]
    with FullOrderModel.build(beam, held, PointForce(0.05, 3.0, x=0.3), probes=[0.5], comm=comm) as fom:
        with Reductor(fom, BasisSettings(modes=10)) as reductor:
            model = reductor.reduce()
        reduced = simulate_reduced(model, IntegratorSettings(t_end=0.3, dt=1e-4, sample_dt=1e-3, rtol=1e-8))
        full = simulate_full(fom, IntegratorSettings(t_end=0.3, dt=1e-5, sample_dt=1e-3, adaptive=False))
    peak = np.abs(full.displacement).max()
    assert peak > 0
    assert np.abs(reduced.displacement - full.displacement).max() < 0.02 * peak
    # the friction force stays within mu F_n and opposes the velocity where the support slides
    sliding = np.abs(full.velocity[:, 0]) > 10 * 1e-4
    assert np.all(np.abs(full.force[:, 0]) <= 0.3 * 0.02 * (1 + 1e-12))
    assert np.all(full.force[sliding, 0] * full.velocity[sliding, 0] < 0)
