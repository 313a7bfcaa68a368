"""The recorder (recorder.py): a full-order run hands its steps and samples over in blocks; what it
writes must be what step-by-step recording writes. The per-support statistics of supports of two
directions against their closed forms."""
import numpy as np

from dbf_hpc.constraints import ConstraintSet
from dbf_hpc.excitation import Harmonic
from dbf_hpc.fom import Observation
from dbf_hpc.laws import ConstraintLaws, law
from dbf_hpc.operators import PointValues
from dbf_hpc.output import MemoryWriter
from dbf_hpc.recorder import FullRecorder, SampleRecorder
from dbf_hpc.stats import STATISTICS

from conftest import recorded_impacts


def test_blocks_of_steps_and_samples_record_what_step_by_step_recording_does():
    rng = np.random.default_rng(7)
    laws = ConstraintLaws([law("deadband", clearance=1e-3, k=1e6), law("hertz", clearance=2e-3, k=1e8,
                                                                        damping="hunt_crossley", alpha=0.5)])
    constraints = ConstraintSet(rows=np.array([[3], [9]]), laws=laws, labels=("a", "b"), positions=np.array([1., 2.]))
    support = Harmonic(1e-3, 7.0)
    r = np.array([0.3, 0.7, 0.5])           # two constraints and one probe
    steps = 3000
    t = np.arange(1, steps + 1) * 1e-5
    z = 2.5e-3 * np.sin(2 * np.pi * 40 * t[:, None] + np.array([0.0, 1.0])) + rng.normal(0, 1e-4, (steps, 2))
    v = rng.normal(0, 0.1, (steps, 2))
    # Samples: after arbitrary steps, some steps with two samples, some samples between two steps.
    sample_after = np.sort(rng.choice(steps, 400))
    x_s = rng.normal(0, 2e-3, (400, 3))
    xd_s = rng.normal(0, 0.1, (400, 3))
    t_s = t[sample_after] - 3e-6

    def total(time, x, xd, rows):
        return x + np.outer(support.value(time), r[rows]), xd + np.outer(support.rate(time), r[rows])

    one = SampleRecorder(MemoryWriter((2,), 1, 0), constraints)
    j = 0
    for i in range(steps):
        while j < 400 and sample_after[j] == i:
            zz, vv = total(t_s[j:j + 1], x_s[j:j + 1], xd_s[j:j + 1], slice(None))
            one.sample(t_s[j], zz[0, :2], vv[0, :2], zz[0, 2:])
            j += 1
        zz, vv = total(t[i:i + 1], z[i:i + 1], v[i:i + 1], slice(0, 2))
        one.step(t[i], zz[0], vv[0])

    probe = PointValues.at_rows([4.0], [12])
    observation = Observation.of(np.array([3, 9]), r[:2], probe, r[2:], support)
    blocks = FullRecorder(MemoryWriter((2,), 1, 0), constraints, observation)
    cuts = np.unique(np.concatenate(([0, steps], rng.integers(0, steps, 25), sample_after[:3])))
    for a, b in zip(cuts[:-1], cuts[1:]):
        inside = (sample_after >= a) & (sample_after < b)
        blocks.block((t[a:b], z[a:b], v[a:b]),
                     (t_s[inside], x_s[inside], xd_s[inside], sample_after[inside] - a))
    for name in ("time", "constraints/displacement", "constraints/velocity", "constraints/force",
                 "constraints/force_peak", "probes/displacement"):
        np.testing.assert_array_equal(blocks.writer.series_data(name), one.writer.series_data(name), err_msg=name)
    expected, got = one.impacts.result(), blocks.impacts.result()
    assert expected["impacts"].min() > 5, "the record has impacts"
    for name in STATISTICS:
        np.testing.assert_allclose(got[name], expected[name], rtol=1e-12, atol=1e-18, err_msg=name)
    np.testing.assert_array_equal(blocks.peak, one.peak)


def test_two_direction_supports_impact_power_is_normal_force_times_normal_speed_and_friction_adds_nothing():
    # A tube in a round hole with friction on a spiral always in contact: r(t) = R + a sin(W t) > c, angle w t.
    # Then |F_n| = k (r - c), v_n = r', v_t = r w, so the impact power <|F_n v_n|> is the trapezoid mean of
    # k (r - c) |r'| and the work rate that of k (r - c) r w, whatever the friction force mu k (r - c) tanh(..)
    # along t adds to |F|. The only two-direction test of the impact power had v_n = 0 (the circular orbit of
    # test_tube2d.py: 0 for any force), so recording |F| |v_n| (friction included) passed every test.
    from dbf_hpc.laws import CircularLaw, PlanarLaws

    k, c, mu, R, a, W, w = 1e6, 2e-4, 0.4, 3e-4, 5e-5, 2 * np.pi * 11.0, 2 * np.pi * 7.0
    laws = PlanarLaws([CircularLaw(clearance=c, k=k, mu=mu)])
    constraints = ConstraintSet(rows=[[0, 1]], laws=laws, labels=("a",), positions=np.zeros(1))
    t = np.cumsum(np.random.default_rng(2).uniform(0.5e-4, 1.5e-4, 4000))
    r, dr = R + a * np.sin(W * t), a * W * np.cos(W * t)
    e, et = np.column_stack((np.cos(w * t), np.sin(w * t))), np.column_stack((-np.sin(w * t), np.cos(w * t)))
    z, v = r[:, None] * e, dr[:, None] * e + (r * w)[:, None] * et
    power = np.trapz(k * (r - c) * np.abs(dr), t) / (t[-1] - t[0])
    work = np.trapz(k * (r - c) * r * w, t) / (t[-1] - t[0])
    for by_blocks in (True, False):
        stats = recorded_impacts(constraints, t, z, v, by_blocks)
        assert np.isclose(stats["impact_power_mean"][0], power, rtol=1e-10, atol=0)
        assert np.isclose(stats["work_rate"][0], work, rtol=1e-10, atol=0)
        assert stats["impacts"][0] == 1 and stats["contact_fraction"][0] == 1.0


def test_the_recorder_keeps_the_largest_hunt_crossley_alpha_v_in_contact_over_the_steps_in_blocks_as_one_by_one():
    # run.hunt_crossley_warnings reads it: alpha |v| at the steps where the law pushes, never out of contact
    rng = np.random.default_rng(3)
    alpha = 40.0
    laws = ConstraintLaws([law("deadband", clearance=1e-3, k=1e6),
                           law("hertz", clearance=2e-3, k=1e8, damping="hunt_crossley", alpha=alpha)])
    constraints = ConstraintSet(rows=np.array([[3], [9]]), laws=laws, labels=("a", "b"), positions=np.array([1., 2.]))
    steps = 2000
    t = np.arange(1, steps + 1) * 1e-5
    z = 2.5e-3 * np.sin(2 * np.pi * 40 * t[:, None] + np.array([0.0, 1.0]))
    v = rng.normal(0, 0.1, (steps, 2))
    v[np.abs(z[:, 1]) <= 2e-3, 1] *= 100.0    # faster out of contact: must not count
    one = SampleRecorder(MemoryWriter((2,), 0, 0), constraints)
    for i in range(steps):
        one.step(t[i], z[i], v[i])
    observation = Observation.of(np.array([3, 9]), np.zeros(2), PointValues.at_rows([], []), np.zeros(0),
                                 Harmonic(0.0, 1.0))
    blocks = FullRecorder(MemoryWriter((2,), 0, 0), constraints, observation)
    for a, b in ((0, 7), (7, 1000), (1000, steps)):
        blocks.block((t[a:b], z[a:b], v[a:b]), (np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, int)))
    contact = np.abs(z[:, 1]) > 2e-3
    expected = alpha * np.abs(v[contact, 1]).max()
    assert contact.sum() > 100 and expected < alpha * np.abs(v[:, 1]).max() / 10
    np.testing.assert_array_equal(one.alpha_speed, [0.0, expected])
    np.testing.assert_array_equal(blocks.alpha_speed, one.alpha_speed)
    fresh = SampleRecorder(MemoryWriter((2,), 0, 0), constraints)   # and a checkpoint keeps it
    fresh.restore(one.state())
    np.testing.assert_array_equal(fresh.alpha_speed, one.alpha_speed)
