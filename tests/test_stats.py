"""Impact statistics: exact and analytic answers for a prescribed sinusoid against elastic stops,
the identities between the statistics, non-uniform sampling, edge cases and shape errors."""
import numpy as np
import pytest

from dbf_hpc import stats
from dbf_hpc.stats import DESCRIPTIONS, STATISTICS, UNITS, impact_statistics

# stats.py is numpy on one rank's samples (no MPI, no PETSc): the 2-rank pass repeated every test on
# both ranks (6 s of it measured under load). Serial pass only (conftest).
pytestmark = pytest.mark.serial

A = 1e-3      # amplitude, m
D = 0.6e-3    # clearance, m (< A)
F = 50.0      # frequency, Hz
K = 1e6       # stop stiffness, N/m
PERIODS = 7
PER_PERIOD = 1000  # samples per period (divisible by 4: a sample at each extremum)
DT = 1 / (F * PER_PERIOD)


def uniform_times(periods=PERIODS, per_period=PER_PERIOD):
    return np.arange(periods * per_period + 1) / (per_period * F)


def jittered_times(seed=0, jitter=0.3):
    """The uniform grid with each inner sample moved by up to `jitter` of an interval; same ends."""
    t = uniform_times()
    t[1:-1] += np.random.default_rng(seed).uniform(-jitter, jitter, t.size - 2) * DT
    return t


def sine_record(t, clearance=D, two_sided=True):
    """z = A sin(2 pi F t) against an elastic stop at `clearance` (both sides or only z > 0):
    t, z, v, force as (nt, 1) columns."""
    z = A * np.sin(2 * np.pi * F * t)
    v = 2 * np.pi * F * A * np.cos(2 * np.pi * F * t)
    contact = np.abs(z) > clearance if two_sided else z > clearance
    force = np.where(contact, -K * (np.abs(z) - clearance) * np.sign(z), 0.0)
    return t, z[:, None], v[:, None], force[:, None]


def one(result):
    """The values of a one-constraint result as floats."""
    assert all(value.shape == (1,) for value in result.values())
    return {name: float(value[0]) for name, value in result.items()}


def reference(t, z, v, force, contact):
    """The definitions, written out one constraint and one sample at a time."""
    nt, nl = z.shape
    w = np.empty(nt)
    w[0], w[-1] = (t[1] - t[0]) / 2, (t[-1] - t[-2]) / 2
    w[1:-1] = (t[2:] - t[:-2]) / 2
    total = t[-1] - t[0]
    out = {name: np.zeros(nl) for name in STATISTICS}
    for j in range(nl):
        durations, run = [], None
        for i in range(nt):
            if contact[i, j]:
                run = (run or 0.0) + w[i]
            elif run is not None:
                durations.append(run)
                run = None
        if run is not None:
            durations.append(run)
        c = contact[:, j]
        out["impacts"][j] = len(durations)
        out["impact_rate"][j] = len(durations) / total
        out["contact_fraction"][j] = sum(durations) / total
        out["impact_duration_mean"][j] = np.mean(durations) if durations else 0.0
        out["impact_duration_max"][j] = max(durations) if durations else 0.0
        out["force_peak"][j] = np.max(np.abs(force[:, j]))
        out["force_rms"][j] = np.sqrt(np.sum(w * force[:, j] ** 2) / total)
        out["force_rms_contact"][j] = (np.sqrt(np.sum(w[c] * force[c, j] ** 2) / np.sum(w[c]))
                                       if c.any() else 0.0)
        out["displacement_rms"][j] = np.sqrt(np.sum(w * z[:, j] ** 2) / total)
        out["displacement_peak"][j] = np.max(np.abs(z[:, j]))
        out["impact_power_mean"][j] = np.sum(w * np.abs(force[:, j] * v[:, j])) / total
    return out


# ---- every statistic has a unit and a description ----

def test_every_statistic_has_a_unit_and_a_description_and_is_returned():
    assert set(UNITS) == set(DESCRIPTIONS) == set(STATISTICS)
    assert UNITS["impact_rate"] == "1/s" and UNITS["impact_power_mean"] == "W"
    text = DESCRIPTIONS["impact_power_mean"].lower()
    assert "|f v|" in text and "not a wear" in text
    result = impact_statistics(*sine_record(uniform_times()))
    assert tuple(result) == STATISTICS


# ---- sinusoid against a symmetric stop ----

def test_symmetric_stop_gives_two_impacts_per_period_at_rate_2f():
    s = one(impact_statistics(*sine_record(uniform_times())))
    assert s["impacts"] == 2 * PERIODS
    assert s["impact_rate"] == pytest.approx(2 * F, rel=1e-12)


def test_symmetric_stop_contact_fraction_is_1_minus_2_arcsin_over_pi_within_resolution():
    s = one(impact_statistics(*sine_record(uniform_times())))
    exact = 1 - (2 / np.pi) * np.arcsin(D / A)
    # Each end of an impact is within half an interval of the crossing: <= DT per impact.
    assert abs(s["contact_fraction"] - exact) <= 2 * F * DT


def test_symmetric_stop_impact_duration_is_half_period_times_contact_fraction_within_one_interval():
    s = one(impact_statistics(*sine_record(uniform_times())))
    exact = (1 / (2 * F)) * (1 - (2 / np.pi) * np.arcsin(D / A))
    assert abs(s["impact_duration_mean"] - exact) <= DT
    assert abs(s["impact_duration_max"] - exact) <= DT
    assert s["impact_duration_max"] >= s["impact_duration_mean"]


def test_displacement_rms_of_a_sinusoid_is_amplitude_over_root_2_and_peak_is_amplitude():
    s = one(impact_statistics(*sine_record(uniform_times())))
    assert s["displacement_rms"] == pytest.approx(A / np.sqrt(2), rel=1e-12)  # trapezoid: exact
    assert s["displacement_peak"] == pytest.approx(A, rel=1e-12)


def test_displacement_rms_is_about_zero_not_about_the_mean():
    t, z, v, force = sine_record(uniform_times())
    offset = 2 * A
    s = one(impact_statistics(t, z + offset, v, force))
    assert s["displacement_rms"] == pytest.approx(np.sqrt(offset ** 2 + A ** 2 / 2), rel=1e-12)
    assert s["displacement_peak"] == pytest.approx(offset + A, rel=1e-12)


def test_symmetric_stop_force_peak_and_rms_match_the_analytic_integrals():
    s = one(impact_statistics(*sine_record(uniform_times())))
    alpha = np.arcsin(D / A)
    mean_sq = (K ** 2 / np.pi) * (A ** 2 * ((np.pi - 2 * alpha) / 2 + np.sin(alpha) * np.cos(alpha))
                                  - 4 * A * D * np.cos(alpha) + D ** 2 * (np.pi - 2 * alpha))
    fraction = 1 - 2 * alpha / np.pi
    assert s["force_peak"] == pytest.approx(K * (A - D), rel=1e-12)
    assert s["force_rms"] == pytest.approx(np.sqrt(mean_sq), rel=1e-6)
    assert s["force_rms_contact"] == pytest.approx(np.sqrt(mean_sq / fraction), rel=2e-3)


def test_elastic_stop_impact_power_is_twice_peak_stored_energy_per_impact_times_impact_rate():
    # |F v| integrates to k (A-d)^2 per impact (loading plus unloading), 2 F impacts per second.
    s = one(impact_statistics(*sine_record(uniform_times())))
    assert s["impact_power_mean"] == pytest.approx(2 * F * K * (A - D) ** 2, rel=1e-4)


# ---- sinusoid against a one-sided stop ----

def test_one_sided_stop_gives_one_impact_per_period_and_contact_fraction_arccos_over_pi():
    s = one(impact_statistics(*sine_record(uniform_times(), two_sided=False)))
    fraction = np.arccos(D / A) / np.pi
    assert s["impacts"] == PERIODS
    assert s["impact_rate"] == pytest.approx(F, rel=1e-12)
    assert abs(s["contact_fraction"] - fraction) <= F * DT
    assert abs(s["impact_duration_mean"] - fraction / F) <= DT
    assert s["impact_power_mean"] == pytest.approx(F * K * (A - D) ** 2, rel=1e-4)


# ---- identities between the statistics ----

@pytest.mark.parametrize("two_sided", [True, False])
def test_force_rms_squared_is_contact_fraction_times_contact_rms_squared(two_sided):
    s = one(impact_statistics(*sine_record(uniform_times(), two_sided=two_sided)))
    assert s["force_rms_contact"] >= s["force_rms"]
    assert s["force_rms"] ** 2 == pytest.approx(s["contact_fraction"] * s["force_rms_contact"] ** 2,
                                                rel=1e-12)


def test_force_rms_equals_contact_rms_when_always_in_contact():
    t, z, v, _ = sine_record(uniform_times())
    force = K * (z - 2 * A)  # never zero
    s = one(impact_statistics(t, z, v, force))
    assert s["impacts"] == 1
    assert s["contact_fraction"] == pytest.approx(1.0, rel=1e-14)
    assert s["impact_duration_max"] == pytest.approx(t[-1] - t[0], rel=1e-14)
    assert s["force_rms_contact"] == pytest.approx(s["force_rms"], rel=1e-14)


def test_impact_power_of_constant_force_and_velocity_is_their_product_times_contact_fraction():
    t = jittered_times()
    contact = (np.sin(2 * np.pi * F * t) > 0.3)[:, None]
    force = np.where(contact, -120.0, 0.0)
    v = np.full_like(force, 0.25)
    s = one(impact_statistics(t, np.zeros_like(force), v, force))
    assert s["impact_power_mean"] == pytest.approx(120.0 * 0.25 * s["contact_fraction"], rel=1e-12)
    assert s["force_rms"] == pytest.approx(120.0 * np.sqrt(s["contact_fraction"]), rel=1e-12)
    assert s["force_rms_contact"] == pytest.approx(120.0, rel=1e-12)


# ---- sampling ----

@pytest.mark.parametrize("seed", [0, 1])
def test_non_uniform_sampling_gives_the_uniform_answers_within_resolution(seed):
    t = jittered_times(seed)
    dt_max = np.diff(t).max()
    u = one(impact_statistics(*sine_record(uniform_times())))
    n = one(impact_statistics(*sine_record(t)))
    exact = 1 - (2 / np.pi) * np.arcsin(D / A)
    assert n["impacts"] == u["impacts"] == 2 * PERIODS
    assert n["impact_rate"] == u["impact_rate"]
    assert abs(n["contact_fraction"] - exact) <= 2 * F * dt_max
    assert abs(n["impact_duration_mean"] - exact / (2 * F)) <= dt_max
    assert abs(n["impact_duration_max"] - u["impact_duration_max"]) <= 2 * dt_max
    for name in ("displacement_rms", "force_rms"):  # smooth integrands: trapezoid error O(dt^2)
        assert n[name] == pytest.approx(u[name], rel=1e-6), name
    assert n["impact_power_mean"] == pytest.approx(u["impact_power_mean"], rel=1e-4)
    assert n["force_rms_contact"] == pytest.approx(u["force_rms_contact"], rel=5e-3)


def test_run_lasts_from_midpoint_before_its_first_sample_to_midpoint_after_its_last():
    t = np.array([0.0, 1.0, 3.0, 4.0, 7.0, 8.0, 10.0])
    contact = np.array([1, 0, 1, 1, 0, 1, 1], bool)[:, None]
    force = np.where(contact, 1.0, 0.0)
    s = one(impact_statistics(t, force, force, force))
    # Runs: sample 0 (starts the record), samples 2-3, samples 5-6 (ends the record).
    durations = [0.5, (4.0 + 7.0) / 2 - (1.0 + 3.0) / 2, 10.0 - (7.0 + 8.0) / 2]
    assert s["impacts"] == 3
    assert s["impact_rate"] == pytest.approx(3 / 10)
    assert s["impact_duration_mean"] == pytest.approx(np.mean(durations), rel=1e-14)
    assert s["impact_duration_max"] == pytest.approx(max(durations), rel=1e-14)
    assert s["contact_fraction"] == pytest.approx(sum(durations) / 10, rel=1e-14)


def test_one_sample_impact_lasts_one_sample_interval():
    t = np.arange(11) * 0.1
    force = np.zeros((11, 1))
    force[4] = 3.0
    s = one(impact_statistics(t, force, force, force))
    assert s["impacts"] == 1
    assert s["impact_duration_mean"] == pytest.approx(0.1, rel=1e-12)
    assert s["contact_fraction"] == pytest.approx(0.1, rel=1e-12)


# ---- contact definition ----

def test_given_in_contact_counts_zero_force_samples_and_restricts_contact_rms_to_them():
    t = np.arange(9) * 0.5
    force = np.array([0, 0, 0, 4, 4, 0, 0, 2, 0], float)[:, None]
    contact = np.array([0, 0, 1, 1, 1, 0, 0, 0, 0], bool)[:, None]  # force 2 at sample 7 is not contact
    s = one(impact_statistics(t, force, force, force, contact))
    assert s["impacts"] == 1
    assert s["contact_fraction"] == pytest.approx(1.5 / 4, rel=1e-14)
    assert s["force_rms_contact"] == pytest.approx(np.sqrt(2 * 16 / 3), rel=1e-14)
    assert s["force_rms"] == pytest.approx(np.sqrt((2 * 16 + 4) * 0.5 / 4), rel=1e-14)
    default = one(impact_statistics(t, force, force, force))
    assert default["impacts"] == 2


def test_no_contact_gives_zero_impacts_durations_and_force_statistics():
    t, z, v, _ = sine_record(uniform_times())
    s = one(impact_statistics(t, z, v, np.zeros_like(z)))
    for name in ("impacts", "impact_rate", "contact_fraction", "impact_duration_mean", "impact_duration_max",
                 "force_peak", "force_rms", "force_rms_contact", "impact_power_mean"):
        assert s[name] == 0.0, name
    assert s["displacement_rms"] == pytest.approx(A / np.sqrt(2), rel=1e-12)


# ---- several constraints, blocks, shapes ----

def test_several_constraints_give_each_constraint_its_own_values():
    records = [sine_record(uniform_times(), clearance=c, two_sided=s)
               for c, s in ((D, True), (0.2 * A, False), (2 * A, True), (-2 * A, True))]
    t = records[0][0]
    together = impact_statistics(t, *(np.hstack([r[i] for r in records]) for i in (1, 2, 3)))
    for j, record in enumerate(records):
        alone = impact_statistics(*record)
        for name in STATISTICS:
            assert together[name][j] == pytest.approx(alone[name][0], rel=1e-13, abs=0), name
    assert together["impacts"].dtype == np.int64


def test_blocked_pass_matches_the_definitions_written_out_sample_by_sample(monkeypatch):
    rng = np.random.default_rng(3)
    nt, nl = 403, 5
    t = np.cumsum(rng.uniform(0.5, 1.5, nt))
    z, v = rng.normal(size=(2, nt, nl))
    contact = rng.random((nt, nl)) < np.array([0.0, 0.1, 0.5, 0.9, 1.0])
    contact[0, 2] = contact[-1, 2] = True  # runs cut by both ends of the record
    force = np.where(contact, rng.normal(size=(nt, nl)), 0.0)
    force[5, 3] = 0.0  # zero force in contact: only the given in_contact counts it
    expected = reference(t, z, v, force, contact)
    for block in (7, 5 * 64, 10 ** 6):  # blocks of one row, of 64 rows, all rows at once
        monkeypatch.setattr(stats, "_BLOCK_VALUES", block)
        result = impact_statistics(t, z, v, force, contact)
        for name in STATISTICS:
            np.testing.assert_allclose(result[name], expected[name], rtol=1e-12, atol=0, err_msg=name)


def test_no_constraints_give_empty_arrays():
    t = uniform_times()
    empty = np.zeros((t.size, 0))
    result = impact_statistics(t, empty, empty, empty)
    assert set(result) == set(STATISTICS)
    assert all(value.shape == (0,) for value in result.values())
    assert all(value.shape == (0,) for value in impact_statistics(t[:1], empty[:1], empty[:1],
                                                                  empty[:1]).values())


def test_single_sample_has_zero_rate_and_duration_and_its_own_values():
    z, v, force = np.array([[2.0, -1.0]]), np.array([[3.0, 1.0]]), np.array([[-5.0, 0.0]])
    result = impact_statistics([1.0], z, v, force)
    np.testing.assert_array_equal(result["impacts"], [1, 0])
    np.testing.assert_array_equal(result["contact_fraction"], [1.0, 0.0])
    for name in ("impact_rate", "impact_duration_mean", "impact_duration_max"):
        np.testing.assert_array_equal(result[name], [0.0, 0.0])
    np.testing.assert_array_equal(result["force_rms"], [5.0, 0.0])
    np.testing.assert_array_equal(result["force_rms_contact"], [5.0, 0.0])
    np.testing.assert_array_equal(result["displacement_rms"], [2.0, 1.0])
    np.testing.assert_array_equal(result["impact_power_mean"], [15.0, 0.0])


@pytest.mark.parametrize("case", ["t_2d", "t_empty", "t_not_increasing", "z_1d", "z_rows", "v_shape",
                                  "force_shape", "in_contact_shape"])
def test_mismatched_shapes_and_bad_times_raise_value_error(case):
    t = np.linspace(0, 1, 5)
    z = np.zeros((5, 2))
    args = dict(t=t, z=z, v=z, force=z, in_contact=None)
    args.update({
        "t_2d": dict(t=t[:, None]),
        "t_empty": dict(t=t[:0], z=z[:0], v=z[:0], force=z[:0]),
        "t_not_increasing": dict(t=t[[0, 1, 1, 3, 4]]),
        "z_1d": dict(z=z[:, 0], v=z[:, 0], force=z[:, 0]),
        "z_rows": dict(z=z[:4]),
        "v_shape": dict(v=z[:, :1]),
        "force_shape": dict(force=z.T),
        "in_contact_shape": dict(in_contact=np.zeros((5, 3), bool)),
    }[case])
    with pytest.raises(ValueError):
        impact_statistics(**args)


def test_accumulator_over_steps_equals_the_statistics_of_the_same_points():
    # The run feeds the solver's steps one by one (memory stays flat); it must agree with the
    # array definition on the same points, including non-uniform steps.
    from dbf_hpc.stats import ImpactAccumulator

    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.5e-4, 1.5e-4, 20000))
    A, d, k = np.array([3e-3, 1e-3, 2e-3]), np.array([2.5e-3, 2e-3, 1.5e-3]), 1e6
    z = A * np.sin(2 * np.pi * 1.3 * t[:, None] + np.array([0.0, 0.4, 1.0]))
    v = np.gradient(z, t, axis=0)
    force = np.where(np.abs(z) > d, -k * (np.abs(z) - d) * np.sign(z), 0.0)
    expected = impact_statistics(t, z, v, force)
    acc = ImpactAccumulator(3)
    for i in range(t.size):
        acc.add(t[i], z[i], v[i], force[i])
    got = acc.result()
    for name in STATISTICS:
        np.testing.assert_allclose(got[name], expected[name], rtol=1e-10, atol=1e-15, err_msg=name)


def test_accumulating_blocks_of_steps_equals_adding_them_one_by_one():
    # The full-order integrator hands its steps over in blocks of any length (cut by samples and
    # checkpoints); the statistics must not depend on where the blocks are cut.
    from dbf_hpc.stats import ImpactAccumulator

    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.5e-4, 1.5e-4, 5000))
    A, d, k = np.array([3e-3, 1e-3, 2e-3]), np.array([2.5e-3, 2e-3, 1.5e-3]), 1e6
    z = A * np.sin(2 * np.pi * 1.3 * t[:, None] + np.array([0.0, 0.4, 1.0]))
    z[100:103, 0] = 2.7e-3   # a few one-step impacts and a contact at a block boundary
    v = np.gradient(z, t, axis=0)
    force = np.where(np.abs(z) > d, -k * (np.abs(z) - d) * np.sign(z), 0.0)
    one = ImpactAccumulator(3)
    for i in range(t.size):
        one.add(t[i], z[i], v[i], force[i])
    blocks = ImpactAccumulator(3)
    cuts = np.unique(np.concatenate(([0, 1, 2, 101, 102, t.size], rng.integers(0, t.size, 60))))
    for a, b in zip(cuts[:-1], cuts[1:]):
        blocks.add_block(t[a:b], z[a:b], v[a:b], force[a:b])
    expected, got = one.result(), blocks.result()
    for name in STATISTICS:
        np.testing.assert_allclose(got[name], expected[name], rtol=1e-12, atol=1e-18, err_msg=name)
    state = blocks.state()
    for name in ("run", "duration_max", "contact_time"):
        np.testing.assert_allclose(state[name], one.state()[name], rtol=1e-12, atol=1e-18, err_msg=name)


def test_work_rate_is_the_time_mean_of_a_linear_work_series_by_steps_by_blocks_and_across_a_checkpoint():
    # The work rate of supports of two directions, <|F_n| |v_t|>, is the trapezoid mean of the series the
    # recorder hands over; for a series linear in t, a + b t, the trapezoid is exact: a + b (t_0 + t_end) / 2,
    # on any steps. The unit tests had only constant series (the forced orbit of test_tube2d.py), on which a
    # rectangle rule (a mutation: 0.5 dt (w_prev + w) -> dt w) gives the same number, and survived them.
    from dbf_hpc.stats import ImpactAccumulator

    rng = np.random.default_rng(7)
    t = 0.2 + np.cumsum(rng.uniform(0.5e-3, 1.5e-3, 4001))
    a, b = np.array([3.0, 0.0, 1e-3]), np.array([-2.0, 5.0, 0.0])
    work = a + b * t[:, None]
    exact = a + b * (t[0] + t[-1]) / 2
    z, v, force = np.full((t.size, 3), 1e-3), np.zeros((t.size, 3)), np.zeros((t.size, 3))
    one = ImpactAccumulator(3, work=True)
    for i in range(t.size):
        one.add(t[i], z[i], v[i], force[i], work=work[i])
    np.testing.assert_allclose(one.result()["work_rate"], exact, rtol=1e-12, atol=0)
    cuts = np.unique(np.concatenate(([0, 1, 2, 2000, t.size], rng.integers(0, t.size, 30))))
    blocks = ImpactAccumulator(3, work=True)
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        if lo == 2000:   # a checkpoint between two blocks: the accumulator resumes from its state
            blocks = ImpactAccumulator.from_state(blocks.state())
        blocks.add_block(t[lo:hi], z[lo:hi], v[lo:hi], force[lo:hi], work=work[lo:hi])
    np.testing.assert_allclose(blocks.result()["work_rate"], exact, rtol=1e-12, atol=0)


def test_statistics_whose_squares_overflow_are_refused_in_one_line_and_a_state_not_finite_is_left_to_the_integrator():
    # F^2 of a finite 1e200 N force is inf: the RMS force would be inf. Red team: numpy's "overflow encountered
    # in multiply" with its source lines, before the run's own line. The accumulator names the constraint and
    # the time, numpy says nothing; a NaN or inf state is the integrators' to name ("the state is not finite").
    import warnings

    from dbf_hpc.errors import SolverError

    t = np.array([0.0, 1e-3, 2e-3])
    z = np.zeros((3, 2))
    force = np.array([[0.0, 0.0], [0.0, 1e200], [0.0, 0.0]])
    for block in (True, False):
        acc = stats.ImpactAccumulator(2)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(SolverError, match=r"^the statistics of constraint 2 overflow at t = 0.001 s: its force "
                                                  r"\(1e\+200 N\) .* beyond double precision; check the excitation"):
                if block:
                    acc.add_block(t, z, z, force)
                else:
                    for i in range(3):
                        acc.add(t[i], z[i], z[i], force[i])
    acc = stats.ImpactAccumulator(2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        acc.add_block(t, z, z, np.where(force > 0, np.inf, force))   # not finite: no line from here
        acc.add_block(t + 1.0, z, z, 1e150 * np.ones((3, 2)))         # large, its square finite: kept
    assert np.isinf(acc.f2[1]) and np.isfinite(acc.f2[0])
