"""Constraint laws: Eq. 23 and Eq. 42 values, exact Jacobians and potentials, tables, contact
damping, mixing kinds, and input errors that name the constraint and the key."""
import numpy as np
import pytest

from dbf_hpc.errors import InputError
from dbf_hpc.laws import CONTACT_DAMPING, LAWS, ConstraintLaws, Law, law_from_dict

D = 1e-3  # clearance scale of the tests, m


def evaluate(law, z, v=None):
    """Force of one law at many points: one ConstraintLaws with the law repeated."""
    z = np.atleast_1d(np.asarray(z, dtype=float))
    laws = ConstraintLaws([law] * z.size)
    return laws.force(z, None if v is None else np.broadcast_to(v, z.shape))


# A law of every kind, with kinks (where finite differences are not valid) listed.
ELASTIC = {
    "deadband": (dict(law="deadband", clearance_minus=0.5 * D, clearance_plus=D, k_minus=3e5, k_plus=1e6),
                 (-0.5 * D, D)),
    "power": (dict(law="power", clearance=D, k_minus=0.1, exponent_minus=3, k_plus=1e6, exponent_plus=1),
              (-D, D)),
    "hertz": (dict(law="hertz", clearance_minus=D, clearance_plus=2 * D, k_minus=2e9, k_plus=5e9),
              (-D, 2 * D)),
    "linear": (dict(law="linear", k=1e5), ()),
    "cubic": (dict(law="cubic", k=1e4, k3=1e10), ()),
    "table": (dict(law="table", table=[[-2 * D, 400.0], [-D, 0.0], [D, 0.0], [3 * D, -900.0],
                                       [4 * D, -1000.0]]),
              (-2 * D, -D, D, 3 * D, 4 * D)),
}
ELASTIC_KINDS = tuple(k for k in LAWS if k != "friction")   # every kind with an elastic part
DAMPING = {"none": {}, "linear": dict(damping="linear", c=50.0),
           "hunt_crossley": dict(damping="hunt_crossley", alpha=0.7)}


def make(kind, damping="none", index=1):
    params, _ = ELASTIC[kind]
    return law_from_dict(index, {**params, **DAMPING[damping]})


def points_away_from(kinks, count, rng, spread=5 * D, gap=2e-5):
    z = rng.uniform(-spread, spread, size=4 * count)
    keep = np.ones(z.size, dtype=bool)
    for kink in tuple(kinks) + (0.0,):  # 0: |N| has a kink there for linear and cubic
        keep &= np.abs(z - kink) > gap
    return z[keep][:count]


def test_every_kind_and_damping_option_is_covered():
    # friction has no elastic part and takes no contact damping: tests/test_friction.py covers it
    assert set(ELASTIC) == set(LAWS) - {"friction"}
    assert set(DAMPING) == set(CONTACT_DAMPING)


def test_eq23_deadband_values_in_each_region_with_separate_stiffness_and_clearance_per_side():
    law = law_from_dict(1, dict(law="deadband", clearance_minus=2e-3, clearance_plus=1e-3,
                                k_minus=3e5, k_plus=1e6))
    z = np.array([-5e-3, -2e-3, -1e-3, 0.0, 1e-3, 1.5e-3, 4e-3])
    expected = np.array([3e5 * (-2e-3 + 5e-3), 0, 0, 0, 0, 1e6 * (1e-3 - 1.5e-3), 1e6 * (1e-3 - 4e-3)])
    np.testing.assert_allclose(evaluate(law, z), expected, rtol=1e-14, atol=1e-12)
    laws = ConstraintLaws([law] * z.size)
    np.testing.assert_array_equal(laws.in_contact(z), [True, False, False, False, False, True, True])


def test_eq42_power_law_values_on_both_sides_and_a_force_free_deadband():
    d = 0.003
    law = law_from_dict(1, dict(law="power", clearance=d, k_minus=0.1, exponent_minus=3,
                                k_plus=1e6, exponent_plus=1))
    z = np.array([-0.05, -0.01, -d - 1e-4, d + 1e-4, 0.01])
    expected = np.array([0.1 * (-d + 0.05) ** 3, 0.1 * (-d + 0.01) ** 3, 0.1 * 1e-4**3,
                         1e6 * (d - d - 1e-4), 1e6 * (d - 0.01)])
    np.testing.assert_allclose(evaluate(law, z), expected, rtol=1e-12)
    inside = np.linspace(-d, d, 101)
    assert np.all(evaluate(law, inside, v=0.3) == 0)
    assert not ConstraintLaws([law] * inside.size).in_contact(inside).any()


def test_hertz_defaults_to_exponent_one_and_a_half():
    law = law_from_dict(1, dict(law="hertz", clearance=D, k=2e9))
    assert law.exponent_minus == law.exponent_plus == 1.5
    np.testing.assert_allclose(evaluate(law, [-3 * D, 3 * D]), [2e9 * (2 * D) ** 1.5, -2e9 * (2 * D) ** 1.5])
    assert Law(kind="hertz", k_plus=1.0).exponent_plus == 1.5  # the dataclass resolves it too


def test_linear_and_cubic_springs_have_no_deadband_and_are_always_in_contact():
    z = np.array([-2e-3, 0.0, 1e-3])
    np.testing.assert_allclose(evaluate(make("linear"), z), -1e5 * z)
    np.testing.assert_allclose(evaluate(make("cubic"), z), -(1e4 * z + 1e10 * z**3))
    for kind in ("linear", "cubic"):
        assert ConstraintLaws([make(kind)] * 3).in_contact(z).all()


@pytest.mark.parametrize("damping", CONTACT_DAMPING)
@pytest.mark.parametrize("kind", ELASTIC_KINDS)
def test_jacobian_matches_central_differences_of_the_force_in_z_and_v(kind, damping):
    rng = np.random.default_rng(7)
    z = points_away_from(ELASTIC[kind][1], 200, rng)
    v = rng.uniform(-2.0, 2.0, size=z.size)
    laws = ConstraintLaws([make(kind, damping)] * z.size)
    dz, dv = laws.jacobian(z, v)
    hz, hv = 1e-8, 1e-6
    fd_z = (laws.force(z + hz, v) - laws.force(z - hz, v)) / (2 * hz)
    fd_v = (laws.force(z, v + hv) - laws.force(z, v - hv)) / (2 * hv)
    np.testing.assert_allclose(dz, fd_z, rtol=1e-6, atol=1e-6 * np.max(np.abs(dz)))
    np.testing.assert_allclose(dv, fd_v, rtol=1e-6, atol=1e-6 * max(np.max(np.abs(dv)), 1e-12))
    force, dz2, dv2 = laws.force_and_jacobian(z, v)
    np.testing.assert_array_equal(force, laws.force(z, v))
    np.testing.assert_array_equal(dz2, dz)
    np.testing.assert_array_equal(dv2, dv)


def test_jacobian_at_the_contact_edges_is_finite_and_zero():
    for law in (make("deadband", "hunt_crossley"), make("power", "linear"), make("hertz")):
        edges = np.array([-law.clearance_minus, law.clearance_plus])
        laws = ConstraintLaws([law] * 2)
        dz, dv = laws.jacobian(edges, np.array([1.0, -1.0]))
        assert np.all(np.isfinite(dz)) and np.all(dz == 0) and np.all(dv == 0)
        assert np.all(laws.force(edges, np.ones(2)) == 0)


@pytest.mark.parametrize("kind", ELASTIC_KINDS)
def test_elastic_force_is_minus_the_derivative_of_the_potential(kind):
    rng = np.random.default_rng(3)
    z = points_away_from(ELASTIC[kind][1], 200, rng)
    laws = ConstraintLaws([make(kind)] * z.size)
    h = 1e-8
    fd = -(laws.potential(z + h) - laws.potential(z - h)) / (2 * h)
    force = laws.force(z)
    np.testing.assert_allclose(fd, force, rtol=1e-6, atol=1e-6 * np.max(np.abs(force)))


@pytest.mark.parametrize("kind", ELASTIC_KINDS)
def test_potential_is_nonnegative_and_zero_in_the_deadband(kind):
    z = np.linspace(-6 * D, 6 * D, 1201)
    laws = ConstraintLaws([make(kind)] * z.size)
    u = laws.potential(z)
    assert np.all(u >= 0)  # the test table is restoring
    assert np.all(u[~laws.in_contact(z)] == 0)


def test_potential_of_an_interference_fit_is_nonnegative_and_consistent_with_the_force():
    law = law_from_dict(1, dict(law="power", clearance=-D, k_minus=2e5, k_plus=1e6, exponent=1.5))
    z = np.linspace(-4 * D, 4 * D, 801) + 1e-7
    laws = ConstraintLaws([law] * z.size)
    assert np.all(laws.potential(z) >= 0)
    h = 1e-8
    fd = -(laws.potential(z + h) - laws.potential(z - h)) / (2 * h)
    np.testing.assert_allclose(fd, laws.force(z), rtol=1e-6, atol=1e-6 * np.max(np.abs(laws.force(z))))


def test_negative_clearance_is_a_preload_both_sides_push_and_the_force_at_zero_is_their_difference():
    law = law_from_dict(1, dict(law="deadband", clearance=-D, k_minus=2e5, k_plus=1e6))
    laws = ConstraintLaws([law] * 3)
    z = np.array([-0.5 * D, 0.0, 0.5 * D])
    np.testing.assert_allclose(laws.force(z), 2e5 * (D - z) - 1e6 * (z + D))
    assert laws.force(np.zeros(3))[0] == pytest.approx(2e5 * D - 1e6 * D)
    assert laws.in_contact(z).all()
    dz, _ = laws.jacobian(z, np.zeros(3))
    np.testing.assert_allclose(dz, -(2e5 + 1e6))
    # Hunt-Crossley sees both contacts: dissipation at the balance point, where N_el = 0
    hc = law_from_dict(1, dict(law="deadband", clearance=-D, k=1e6, damping="hunt_crossley", alpha=0.5))
    assert ConstraintLaws([hc]).force(np.zeros(1), np.ones(1))[0] == pytest.approx(-0.5 * 2e6 * D)


def test_an_interference_fit_a_metre_deep_is_an_exact_two_k_spring_and_a_deeper_one_is_refused_naming_the_side():
    # Both preloads cancel and the sides' slopes add: N = -2 k z on the overlap. At 1 m depth a motion of
    # 1 um is still resolved to 1e-10 of itself; at 1e10 m the force came in 2 N steps, at 1e100 m it was 0
    k, z = 1e6, np.array([-1e-6, 3e-7, 1e-6])
    laws = ConstraintLaws([law_from_dict(1, dict(law="deadband", clearance=-1.0, k=k))] * 3)
    np.testing.assert_allclose(laws.force(z), -2 * k * z, rtol=1e-9)
    for params, side in ((dict(law="deadband", clearance=-1e10, k=k), "clearance_minus = -1e+10"),
                         (dict(law="hertz", clearance_minus=1e-3, clearance_plus=-1.5, k=k), "clearance_plus = -1.5"),
                         (dict(law="power", clearance=-1e100, k=k, exponent=1.5), "clearance_minus = -1e+100")):
        with pytest.raises(InputError) as info:
            law_from_dict(2, params)
        message = str(info.value)
        assert message.startswith(f"constraint 2: {side} m: an interference fit") and "deeper than 1 m" in message
        assert "\n" not in message
    # a side without stiffness pushes nowhere: its clearance is not a fit
    law_from_dict(3, dict(law="deadband", clearance_minus=-1e10, clearance_plus=1e-3, k_minus=0.0, k_plus=k))


def test_table_interpolates_through_its_points_and_extrapolates_with_the_end_slopes():
    points = ELASTIC["table"][0]["table"]
    law = make("table")
    zs, fs = np.array(points).T
    np.testing.assert_allclose(evaluate(law, zs), fs, atol=1e-12)
    np.testing.assert_allclose(evaluate(law, [-1.5 * D, 2 * D]), [200.0, -450.0])
    np.testing.assert_allclose(evaluate(law, [-3 * D, 6 * D]), [800.0, -1200.0])  # end slopes
    laws = ConstraintLaws([law] * 3)
    dz, _ = laws.jacobian(np.array([-D, D, 4 * D]), np.zeros(3))
    np.testing.assert_allclose(dz, [0.0, -450.0 / D, -100.0 / D])  # right-hand segment at a breakpoint


def test_table_potential_is_exact_for_a_two_segment_table():
    # N = 2 - z on [-1, 0] ... (0, 2) -> (2, -2): slope -2 on [0, 2]; (-1, 3) -> (0, 2): slope -1
    law = Law(kind="table", table=((-1.0, 3.0), (0.0, 2.0), (2.0, -2.0)))
    laws = ConstraintLaws([law] * 5)
    z = np.array([-2.0, -1.0, 0.5, 2.0, 3.0])
    # U(z) = -int_0^z N: for z > 0, N = 2 - 2z -> U = -(2z - z^2); for z < 0, N = 2 - z -> U = -(2z - z^2/2)
    expected = np.array([-(2 * -2.0 - 4.0 / 2), -(2 * -1.0 - 1.0 / 2), -(1.0 - 0.25), -(4.0 - 4.0),
                         -(6.0 - 9.0)])
    np.testing.assert_allclose(laws.potential(z), expected, rtol=1e-14, atol=1e-14)


def test_a_table_reproducing_a_deadband_equals_the_deadband_law():
    deadband = law_from_dict(1, dict(law="deadband", clearance_minus=0.5 * D, clearance_plus=D,
                                     k_minus=3e5, k_plus=1e6, damping="linear", c=20.0))
    table = law_from_dict(2, dict(law="table", damping="linear", c=20.0,
                                  table=[[-1.5 * D, 300.0], [-0.5 * D, 0.0], [D, 0.0], [2 * D, -1000.0]]))
    z = np.linspace(-5 * D, 5 * D, 1001)
    v = np.linspace(-1, 1, z.size)
    a, b = ConstraintLaws([deadband] * z.size), ConstraintLaws([table] * z.size)
    scale = 1e6 * 5 * D
    np.testing.assert_allclose(b.force(z, v), a.force(z, v), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(b.potential(z), a.potential(z), rtol=1e-10, atol=1e-15)
    np.testing.assert_array_equal(b.in_contact(z), a.in_contact(z))
    # off the kinks: at z = d_plus the table takes the right-hand slope, the deadband law 0
    off = np.all(np.abs(z[:, None] - np.array([-0.5 * D, D])) > 1e-9, axis=1)
    for x, y in zip(b.jacobian(z, v), a.jacobian(z, v)):
        np.testing.assert_allclose(x[off], y[off], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("damping", ("linear", "hunt_crossley"))
@pytest.mark.parametrize("kind", ("deadband", "power", "hertz", "table"))
def test_contact_damping_is_zero_in_the_deadband_even_with_velocity(kind, damping):
    law = make(kind, damping)
    z = np.linspace(-0.45 * D, 0.9 * D, 51)  # inside every test law's deadband
    v = np.full(z.size, 3.0)
    laws = ConstraintLaws([law] * z.size)
    assert np.all(laws.force(z, v) == 0)
    dz, dv = laws.jacobian(z, v)
    assert np.all(dz == 0) and np.all(dv == 0)


@pytest.mark.parametrize("damping", ("linear", "hunt_crossley"))
def test_contact_damping_acts_in_contact_and_dissipates(damping):
    law = make("deadband", damping)
    z = np.array([-3 * D, -3 * D, 3 * D, 3 * D])
    v = np.array([-1.0, 1.0, -1.0, 1.0])
    laws = ConstraintLaws([law] * 4)
    damping_force = laws.force(z, v) - laws.force(z)
    assert np.all(damping_force * v < 0)
    if damping == "linear":
        np.testing.assert_allclose(damping_force, -50.0 * v)
    else:
        np.testing.assert_allclose(damping_force, -0.7 * np.abs(laws.force(z)) * v)


def test_mixed_laws_in_one_object_give_the_same_values_as_each_alone():
    rng = np.random.default_rng(11)
    laws = [make(kind, damping, index=i) for i, (kind, damping) in
            enumerate([(k, d) for d in CONTACT_DAMPING for k in ELASTIC_KINDS][::-1])]
    laws = [laws[i] for i in rng.permutation(len(laws))]  # kinds interleaved
    together = ConstraintLaws(laws)
    for _ in range(5):
        z = rng.uniform(-5 * D, 5 * D, size=len(laws))
        v = rng.uniform(-1, 1, size=len(laws))
        force, dz, dv = together.force_and_jacobian(z, v)
        u, contact = together.potential(z), together.in_contact(z)
        for i, law in enumerate(laws):
            alone = ConstraintLaws([law])
            f1, dz1, dv1 = alone.force_and_jacobian(z[i:i + 1], v[i:i + 1])
            assert (force[i], dz[i], dv[i]) == (f1[0], dz1[0], dv1[0])
            assert u[i] == alone.potential(z[i:i + 1])[0]
            assert contact[i] == alone.in_contact(z[i:i + 1])[0]


def test_scene_keys_map_to_the_law_fields():
    law = law_from_dict(1, dict(law="deadband", clearance=D, k=1e6))
    assert law == Law(kind="deadband", clearance_minus=D, clearance_plus=D, k_minus=1e6, k_plus=1e6)
    assert law_from_dict(1, dict(law="linear", k=5)) == Law(kind="linear", k_minus=5.0, k_plus=5.0)
    law = law_from_dict(1, dict(law="table", table=[[0, 1], [1, 0]]))
    assert law.table == ((0.0, 1.0), (1.0, 0.0))
    assert law_from_dict(1, dict(k_plus=1e6)).k_minus == 0  # one-sided stop


@pytest.mark.parametrize("params, key", [
    (dict(k=1e6, stiffness=3), "stiffness"),
    (dict(law="spring", k=1e6), "law"),
    (dict(law="deadband", k_plus=-1), "k_plus"),
    (dict(law="deadband", k=-1), "k"),
    (dict(law="power", k=1, exponent_minus=0.5), "exponent_minus"),
    (dict(law="table", table=[[0, 0], [1, 1], [1, 2]]), "table"),
    (dict(law="table", table=[[0, 0]]), "table"),
    (dict(clearance=D, clearance_minus=D, k=1), "clearance"),
    (dict(k=1, k_plus=2), "k_plus"),
    (dict(k="1e6"), "k"),
    (dict(k=float("nan")), "k"),
    (dict(law="deadband", k=1, k3=5), "k3"),
    (dict(law="deadband", k=1, exponent=2), "exponent"),
    (dict(law="linear", k=1, clearance=D), "clearance"),
    (dict(law="deadband", clearance=D), "k"),
    (dict(k=1, damping="viscous"), "damping"),
    (dict(k=1, damping="linear"), "c"),
    (dict(k=1, c=3), "c"),
    (dict(k=1, damping="hunt_crossley", alpha=-1), "alpha"),
    (dict(law="friction", normal_force=10.0, mu=1e30, v_reg=1e-3), "mu"),   # crawled at 1e-13 s steps
])
def test_bad_input_raises_one_line_naming_the_constraint_and_the_key(params, key):
    with pytest.raises(InputError) as info:
        law_from_dict(4, params)
    message = str(info.value)
    assert message.startswith("constraint 4: ") and "\n" not in message
    assert key in message


@pytest.mark.parametrize("params, named", [
    (dict(k_minus=0.0, k_plus=0.0), "k_minus = 0 and k_plus = 0"),
    (dict(k_plus=0.0, k_minus=0.0), "k_minus = 0 and k_plus = 0"),
    (dict(k=0.0), "k = 0"),
    (dict(k_plus=0.0), "k_plus = 0"),
])
def test_a_two_sided_law_that_can_never_push_names_every_zero_stiffness(params, named):
    # A stop with no stiffness on either side exerts no force. Red team: the moving belt's guide
    # (k_minus = 0, one-sided) with --set constraint.k_plus=0 said "k_minus must be a positive number,
    # got 0", naming the key the user had not touched.
    with pytest.raises(InputError, match=rf"^constraint 2: {named}: the constraint would never push; give k, "
                                         r"k_minus or k_plus a positive value$"):
        law_from_dict(2, dict(law="deadband", clearance=D, **params))
    assert law_from_dict(2, dict(law="deadband", clearance=D, k_minus=0.0, k_plus=2e5)).k_plus == 2e5


def test_law_dataclass_validates_too():
    with pytest.raises(InputError, match="k_plus"):
        Law(k_plus=-1)
    with pytest.raises(InputError, match="law must be one of"):
        Law(kind="spring")
    with pytest.raises(InputError, match="table"):
        Law(kind="table", table=((1.0, 0.0), (0.0, 1.0)))


def test_a_two_direction_support_refuses_a_friction_coefficient_no_contact_pair_has():
    # Red team: mu = 1e30 on the tube's supports ran (its regularized stick at 1e-13 s steps, an ETA of
    # minutes for 0.1 s); 10 is still accepted (some clean metal pairs exceed 1).
    from dbf_hpc.laws import CircularLaw

    assert CircularLaw(clearance=2e-4, k=1e6, mu=10.0).mu == 10.0
    with pytest.raises(InputError, match="mu = 1e\\+30: a Coulomb friction coefficient above 10"):
        CircularLaw(clearance=2e-4, k=1e6, mu=1e30)


@pytest.mark.parametrize("params, key", [
    # k p = inf: the slope's factor was inf, the slope NaN even in the deadband, and a run crawled at 1e-13 s
    (dict(law="power", clearance=D, k=1e308, exponent=2), "k_minus = 1e+308"),
    # the preload k (-clearance) = inf: N(0) = inf - inf = NaN
    (dict(law="deadband", clearance=-1e308, k=1e6), "clearance_minus = -1e+308"),
    # the preload's power beyond double precision: 2**2000 (was an OverflowError, an internal error)
    (dict(law="power", clearance=-2.0, k=1.0, exponent=2000), "clearance_minus = -2"),
    (dict(law="power", clearance_plus=-1e10, clearance_minus=0.0, k=1.0, exponent=100), "clearance_plus = -1e+10"),
    # a table step of 1e-320 m: an infinite slope
    (dict(law="table", table=[[0.0, 0.0], [1e-320, 1.0]]), "table: the segment from point 1"),
    # a force range beyond double precision: slope and integral overflow
    (dict(law="table", table=[[-1e308, 1e308], [1e308, -1e308]]), "table: the segment from point 1"),
    # mu F_n / v_reg = inf: the friction's slope at rest
    (dict(law="friction", normal_force=1e308, mu=10.0, v_reg=1e-300), "v_reg"),
])
def test_a_law_whose_force_or_slope_overflows_double_precision_is_refused_naming_the_key(params, key):
    # A finite value for every key is not enough: the constants the evaluation forms must be finite too,
    # else the force or its slope is NaN or inf where the law is well defined (at z = 0, in free flight)
    with pytest.raises(InputError) as info:
        law_from_dict(4, params)
    message = str(info.value)
    assert message.startswith("constraint 4: ") and "\n" not in message
    assert key in message and "overflows double precision" in message


def test_large_but_representable_laws_are_accepted_and_evaluate_to_finite_numbers():
    # the overflow check refuses only what does not fit: stiff laws, long tables, fast friction run
    laws = [law_from_dict(1, dict(law="power", clearance=D, k=1e300, exponent=3)),
            law_from_dict(2, dict(law="deadband", clearance=-1e-3, k=1e300)),
            law_from_dict(3, dict(law="table", table=[[-1e100, 1e100], [1e100, -1e100]])),
            law_from_dict(4, dict(law="friction", normal_force=1e6, mu=0.5, v_reg=1e-200))]
    z = np.array([0.0, 0.0, 0.0, 0.0])
    force, dz, dv = ConstraintLaws(laws).force_and_jacobian(z, np.zeros(4))
    assert np.all(np.isfinite(force)) and np.all(np.isfinite(dz)) and np.all(np.isfinite(dv))
    assert force[1] == 0.0 and dz[1] == -2e300   # both preloads of 1e297 N cancel; both sides' slopes add


def test_contact_damping_pulls_only_where_documented_while_separating():
    # Hunt-Crossley N = N_el (1 + alpha v) above the stop: restoring (N <= 0) for separation speeds below
    # 1 / alpha, adhesive (N > 0) above; linear damping pulls once c |v| exceeds |N_el|. Never while
    # approaching. docs/method.md and docs/scene.md say so.
    alpha, c = 0.7, 50.0
    hc = law_from_dict(1, dict(law="hertz", clearance=D, k=3e9, damping="hunt_crossley", alpha=alpha))
    z = np.full(3, 1.5 * D)
    v = np.array([-0.9 / alpha, -1.1 / alpha, 3.0])   # separating slower, faster than 1 / alpha; approaching
    force = ConstraintLaws([hc] * 3).force(z, v)
    assert force[0] < 0 and force[1] > 0 and force[2] < 0
    elastic = ConstraintLaws([hc]).force(z[:1])[0]
    assert np.allclose(force, elastic * (1 + alpha * v), rtol=1e-14)
    lin = law_from_dict(1, dict(law="deadband", clearance=D, k=1e6, damping="linear", c=c))
    n_el = 1e6 * 1e-6   # 1 N at 1 um past the stop
    force = ConstraintLaws([lin] * 3).force(np.full(3, D + 1e-6), np.array([-0.9, -1.1, 0.5]) * n_el / c)
    assert force[0] < 0 and force[1] > 0 and force[2] < 0
    # the same below the stop, mirrored
    force = ConstraintLaws([hc] * 2).force(np.full(2, -1.5 * D), np.array([0.9, 1.1]) / alpha)
    assert force[0] > 0 and force[1] < 0


@pytest.mark.parametrize("kind", ["circular", "flat_bar"])
def test_a_two_direction_support_without_a_stiffness_or_a_gap_is_refused_naming_its_own_law_and_unit(kind):
    # New-user pass: a flat_bar without k said "a circular law needs k", another law than the one
    # written, and neither said the unit. A support with no stiffness or no gap has no force law.
    with pytest.raises(InputError, match=rf"^\[\[constraint\]\] 1: a {kind} law needs k \(N/m\)$"):
        law_from_dict("[[constraint]] 1", {"law": kind, "clearance": 1e-4, "mu": 0.3})
    with pytest.raises(InputError, match=rf"^\[\[constraint\]\] 1: a {kind} law needs clearance \(m, the "):
        law_from_dict("[[constraint]] 1", {"law": kind, "k": 1e6})


@pytest.mark.parametrize("table, segment", [
    ([[-1e-3, 0.0], [1e-3, 0.0], [2e-3, 50.0]], "point 2 (z = 0.001 m, 0 N) to point 3 (z = 0.002 m, 50 N)"),
    # a stop whose forces were given as the force on the stop (the sign flipped): rising on both sides
    ([[-2e-3, -40.0], [-1e-3, 0.0], [1e-3, 0.0], [3e-3, 100.0]], "point 1 (z = -0.002 m, -40 N)"),
])
def test_a_table_whose_force_rises_with_z_is_refused_naming_the_segment_as_a_negative_stiffness(table, segment):
    # A table is the force ON the structure: restoring, non-increasing in z. A rising segment is a negative
    # stiffness, whose contact problem the full-order reference's Gauss-Seidel fallback cannot solve (red
    # team: it ran 9.6 % off its own dt / 4 run while estimating 0.5 %); flat segments (a deadband) stay
    with pytest.raises(InputError) as info:
        law_from_dict(2, dict(law="table", table=table))
    message = str(info.value)
    assert message.startswith(f"constraint 2: table: the segment from {segment}") and "\n" not in message
    assert "negative stiffness" in message and "restoring" in message
    flat = law_from_dict(2, dict(law="table", table=[[-1e-3, 0.0], [1e-3, 0.0], [2e-3, -50.0]]))
    assert ConstraintLaws([flat]).force(np.array([1.5e-3]), np.zeros(1))[0] == pytest.approx(-25.0)


@pytest.mark.parametrize("params, named", [
    (dict(law="table", table=[[-1e-3, 0.0], [0.0, 0.0], [1e-3, 0.0]]), "table: every force is 0 N"),
    (dict(law="table", table=[[0.0, -0.0], [1e-3, 0.0]]), "table: every force is 0 N"),
    (dict(law="friction", normal_force=10.0, mu=0.0), "mu = 0"),
    (dict(law="friction", normal_force=0.0, mu=0.3), "normal_force = 0"),
    (dict(law="friction", normal_force=0.0, mu=0.0), "mu = 0 and normal_force = 0"),
])
def test_a_table_of_zero_forces_or_a_friction_law_without_friction_never_pushes_and_is_refused(params, named):
    # A law whose force is 0 everywhere is no constraint (and would cost the reduced model a DBF for nothing),
    # refused like a deadband with k = 0; a frictionless 1-D friction support is the run without the constraint.
    with pytest.raises(InputError, match=rf"^constraint 3: {named}.*would never push.*remove the constraint"):
        law_from_dict(3, params)
    # one nonzero force, or any positive mu F_n, is a law that pushes
    assert law_from_dict(3, dict(law="table", table=[[0.0, 0.0], [1e-3, -1.0]])).table[1] == (1e-3, -1.0)
    assert law_from_dict(3, dict(law="friction", normal_force=1e-6, mu=1e-6)).mu == 1e-6
