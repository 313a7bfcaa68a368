"""The beam model: exact Euler-Bernoulli frequencies, boundary conditions, influence vectors, layout.

Frequencies come from SLEPc on the distributed matrices (dbf_hpc.modes), compared with closed forms.
"""
import numpy as np
import pytest
from petsc4py import PETSc
from scipy.optimize import brentq

from conftest import assert_all, to_numpy
from dbf_hpc.errors import InputError
from dbf_hpc.modes import reference_modes
from dbf_hpc.structure import Beam, BeamMesh, assemble_beam

# The paper's Table 1 beam.
TABLE1 = dict(length=1.0, E=117e9, I=0.000878e-12, A=0.29e-6, rho=11800.0)


def beam(**changes):
    return Beam(**{**TABLE1, **changes})


def omegas(b, count, **kw):
    ops = assemble_beam(b, **kw)
    modes = reference_modes(ops, count=count)
    omega = modes.omega.copy()
    modes.destroy()
    ops.destroy()
    return omega


def roots(f, count, step=0.01):
    """The first `count` roots above 0.5 of a continuous f, bracketed on a fine grid."""
    x = np.arange(0.5, 4 * count + 10, step)
    fx = f(x)
    found = [brentq(f, a, b, xtol=1e-14) for a, b, fa, fb in zip(x[:-1], x[1:], fx[:-1], fx[1:])
             if np.sign(fa) != np.sign(fb)]
    return np.array(found[:count])


def beta_omega(b, beta_l):
    return np.sqrt(b.EI / b.rhoA) * (beta_l / b.length) ** 2


def test_pinned_pinned_frequencies_match_euler_bernoulli_first_ten_modes():
    b = beam(elements=200)
    n = np.arange(1, 11)
    exact = np.sqrt(b.EI / b.rhoA) * (n * np.pi / b.length) ** 2
    assert np.max(np.abs(omegas(b, 10) / exact - 1)) < 1e-6


def test_cantilever_frequencies_match_clamped_free_roots():
    beta_l = roots(lambda x: np.cos(x) + 1 / np.cosh(x), 6)
    np.testing.assert_allclose(beta_l[:4], [1.8751, 4.6941, 7.8548, 10.9955], atol=1e-4)
    b = beam(elements=120, left="clamped", right="free")
    assert np.max(np.abs(omegas(b, 6) / beta_omega(b, beta_l) - 1)) < 1e-6


def test_clamped_sliding_frequencies_match_tan_plus_tanh_roots():
    beta_l = roots(lambda x: np.sin(x) + np.cos(x) * np.tanh(x), 5)  # tan + tanh = 0
    b = beam(elements=120, left="clamped", right="sliding")
    assert np.max(np.abs(omegas(b, 5) / beta_omega(b, beta_l) - 1)) < 1e-6


def test_pinned_sliding_beam_is_half_a_pinned_beam_of_twice_the_length():
    b = beam(elements=120, right="sliding")
    n = np.arange(1, 6)
    exact = beta_omega(b, (2 * n - 1) * np.pi / 2)
    assert np.max(np.abs(omegas(b, 5) / exact - 1)) < 1e-6


def test_free_free_beam_has_two_rigid_modes_then_the_cos_cosh_roots():
    beta_l = roots(lambda x: np.cos(x) - 1 / np.cosh(x), 3)
    b = beam(elements=120, left="free", right="free")
    assert BeamMesh(b).rigid_modes() == 2
    omega = omegas(b, 5)
    assert np.all(omega[:2] < 1e-4 * omega[2])
    assert np.max(np.abs(omega[2:] / beta_omega(b, beta_l) - 1)) < 1e-6


def test_middle_support_makes_the_first_mode_that_of_one_pinned_span():
    b = beam(elements=100, supports=(0.5,))
    exact = np.sqrt(b.EI / b.rhoA) * (np.pi / 0.5) ** 2
    assert abs(omegas(b, 1)[0] / exact - 1) < 1e-7


def test_frequency_error_falls_as_h_to_the_fourth():
    b_exact = beam()
    exact = np.sqrt(b_exact.EI / b_exact.rhoA) * (3 * np.pi) ** 2
    errors = [omegas(beam(elements=ne), 3)[2] / exact - 1 for ne in (6, 12, 24)]
    assert all(e > 0 for e in errors), "consistent mass Hermite elements bound frequencies from above"
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(rates - 4) < 0.2), rates


def test_mesh_puts_a_node_at_every_constraint_and_probe():
    points = [0.1234, 0.5, 0.987654, 0.25]
    mesh = BeamMesh(beam(elements=50), points)
    for p in points:
        assert mesh.x[mesh.node_at(p)] == pytest.approx(p, abs=1e-15)
    h = np.diff(mesh.x)
    assert 50 <= mesh.elements <= 54 and h.max() <= 1.0 / 50 + 1e-15  # never coarser than asked


def test_dofs_removed_by_each_boundary_condition():
    for left, right, removed in [("pinned", "pinned", 2), ("clamped", "free", 2),
                                 ("clamped", "clamped", 4), ("sliding", "free", 1), ("free", "free", 0)]:
        mesh = BeamMesh(beam(elements=10, left=left, right=right))
        assert mesh.n_free == 2 * 11 - removed


@pytest.mark.parametrize("left,right,end,shape", [
    ("pinned", "pinned", "left", lambda s: 1 - s),            # paper Eq. 26
    ("pinned", "pinned", "right", lambda s: s),
    ("clamped", "free", "left", lambda s: np.ones_like(s)),   # rigid translation of a cantilever
    ("clamped", "clamped", "left", lambda s: 1 - 3 * s**2 + 2 * s**3),  # pseudo-static, exact for cubics
])
def test_influence_vector_is_the_support_motion_consistent_with_the_supports(left, right, end, shape):
    b = beam(elements=40, left=left, right=right)
    ops = assemble_beam(b, base_end=end)
    r = to_numpy(ops.influence)
    mesh = ops.mesh
    free_w = mesh.row[:, 0] >= 0
    expected = shape(mesh.x[free_w] / b.length)
    assert np.max(np.abs(r[mesh.row[free_w, 0]] - expected)) < 1e-8
    ops.destroy()


def test_support_motion_modal_load_matches_the_paper_integral():
    # Paper Eq. 33: the modal load of y = Omega (1 - x/L) is -rho A int phi_n (1 - x/L) dx Omega''
    # = -sqrt(2 rho A L) / (n pi) Omega'' for the modes of Eq. 29.
    b = beam(elements=200)
    ops = assemble_beam(b, base_end="left")
    modes = reference_modes(ops, count=6)
    loads = []
    for i in range(6):
        col = modes.vectors.getColumn(i)
        loads.append(abs(col.dot(ops.base_mass_load)))
        modes.vectors.restoreColumn(i, col)
    n = np.arange(1, 7)
    np.testing.assert_allclose(loads, np.sqrt(2 * b.rhoA * b.length) / (n * np.pi), rtol=1e-6)
    modes.destroy()
    ops.destroy()


def test_base_excitation_needs_a_transverse_support_at_that_end():
    with pytest.raises(InputError, match="transverse support"):
        assemble_beam(beam(elements=10, left="sliding", right="clamped"), base_end="left")


@pytest.mark.parametrize("change,word", [(dict(E=-1.0), "E"), (dict(length=0.0), "length"),
                                         (dict(elements=0), "elements"), (dict(left="hinged"), "left"),
                                         (dict(supports=(1.5,)), "support")])
def test_bad_beam_parameters_are_clear_errors(change, word):
    with pytest.raises(InputError, match=word):
        beam(**change)


@pytest.mark.parametrize("change", [dict(E=1e308), dict(E=1e150), dict(E=1e-100), dict(I=1e-300), dict(rho=1e200),
                                    dict(length=1e200), dict(length=1e308), dict(tension=1e308)])
def test_a_beam_whose_frequencies_leave_double_precision_is_refused_naming_its_numbers(change):
    # omega^2 = EI / (rho A L^4) ... EI / (rho A h^4) of the mesh: red team, E = 1e308 Pa ended in "the
    # eigensolver failed (PETSc error 77) ... check M", I = 1e-300 m^4 in "the mass matrix is not positive
    # definite", length = 1e200 m in an internal OverflowError.
    with pytest.raises(InputError, match=r"^beam E, I, A, rho, length, elements \(and tension, axial_speed\) give "
                                         r"omega\^2 of .* 1/s\^2 over the mesh, outside the 1e-100 to 1e\+100"):
        beam(elements=10, **change)


def test_a_beam_far_from_any_structure_but_inside_double_precision_keeps_its_exact_frequencies():
    # E 1e80 times the paper's: the frequencies scale as sqrt(E), 1e40 times the paper beam's, and are the
    # pinned-pinned (n pi / L)^2 sqrt(EI / rho A) to the mesh's h^4 error
    b = beam(elements=40, E=117e89)
    assert_all(np.allclose(omegas(b, 3), 1e40 * omegas(beam(elements=40), 3), rtol=1e-9))
    assert_all(np.allclose(omegas(b, 3), beta_omega(b, np.pi * np.arange(1, 4)), rtol=1e-5))


def test_more_elements_than_petsc_indices_count_are_refused_not_an_allocation_failure():
    # red team: elements = 2**70 ended in numpy's "Maximum allowed size exceeded" (an internal error)
    largest = int(np.iinfo(PETSc.IntType).max)
    with pytest.raises(InputError, match=rf"^beam elements = {2**70}: .* use at most {(largest - 1) // 2 - 1} "
                                         rf"elements"):
        beam(elements=2**70)
    with pytest.raises(InputError, match=rf"use at most {(largest - 1) // 4 - 1} elements"):
        beam(elements=(largest - 1) // 2 - 1, planes=2)


@pytest.mark.parametrize("left,right", [("pinned", "pinned"), ("clamped", "free")])
@pytest.mark.parallel
def test_operators_on_two_ranks_equal_those_on_one(left, right):
    b = beam(elements=37, left=left, right=right)
    world = assemble_beam(b, comm=PETSc.COMM_WORLD, base_end="left")
    alone = assemble_beam(b, comm=PETSc.COMM_SELF, base_end="left")
    lo, hi = world.K.getOwnershipRange()
    assert_all(hi > lo, "each rank owns rows")
    same = True
    for A, B in ((world.K, alone.K), (world.M, alone.M)):
        for i in range(lo, hi):
            cols_a, vals_a = A.getRow(i)
            cols_b, vals_b = B.getRow(i)
            same &= np.array_equal(cols_a, cols_b) and np.allclose(vals_a, vals_b, rtol=1e-14, atol=0)
    for u, v in ((world.influence, alone.influence), (world.base_mass_load, alone.base_mass_load)):
        same &= np.allclose(u.getArray(), v.getArray()[lo:hi], rtol=1e-10, atol=1e-10)  # solver round-off
    assert_all(same, "distributed rows differ from the serial assembly")
    w_world = reference_modes(world, count=4).omega
    w_alone = reference_modes(alone, count=4).omega
    assert_all(np.allclose(w_world, w_alone, rtol=1e-10))
    world.destroy()
    alone.destroy()


@pytest.mark.parametrize("points", [[0.25, 0.25 + 1e-9 * 2], [0.25, 0.2500001], [0.25, 0.254], [1e-6], [1 - 1e-4]])
def test_points_closer_than_half_an_element_are_refused_naming_them(points):
    # Two stops 1 nm apart, or a stop a micrometre from a support, would make an element too short
    # to trust (the red-team found 63.6 N before any impact, and w 93 % low); they are one point or
    # an error that says what to change. At 100 elements half an element is 5 mm.
    if abs(points[-1] - points[0]) <= 1e-9 * 2 and len(points) == 2:
        points = [0.25, 0.25 + 5e-10]         # within POINT_TOL: one point, not an error
        assert BeamMesh(beam(elements=100), points).elements == 100
        return
    with pytest.raises(InputError, match="less than half an element .* at 100 elements.*use at least"):
        BeamMesh(beam(elements=100), points)


def test_a_probe_between_nodes_is_the_hermite_interpolation_and_adds_no_node():
    mesh = BeamMesh(beam(elements=10), [0.25])
    values = mesh.point_values([0.25, 0.2501, 0.33])
    assert mesh.elements == 11, "only the constraint point is a node"
    # w(x) = x^3 is represented exactly by cubic Hermite shape functions: nodal w = x^3, theta = 3 x^2
    u = np.zeros(mesh.n_free)
    free = mesh.row >= 0
    nodal = np.column_stack([mesh.x**3, 3 * mesh.x**2])
    u[mesh.row[free]] = nodal[free]
    np.testing.assert_allclose(values.take(u), np.array([0.25, 0.2501, 0.33]) ** 3, rtol=1e-13)


def test_a_probe_on_a_support_is_refused():
    mesh = BeamMesh(beam(elements=10, supports=(0.5,)))
    with pytest.raises(InputError, match="on a support"):
        mesh.point_values([0.5])


def test_axial_transport_numbers_are_checked_as_the_other_numbers_a_bool_is_no_speed():
    # axial_speed = True was a beam moving at 1 m/s, a numpy integer speed was refused, and 78 and 78.0
    # were two beams (two cache keys) of the same physics.
    base = dict(length=1.0, E=2e11, I=1e-8, A=1e-4, rho=7800.0)
    for bad in (dict(axial_speed=True), dict(tension=False), dict(transported_mass=True),
                dict(axial_speed=float("inf")), dict(transported_mass=0.0)):
        with pytest.raises(InputError, match=f"beam {next(iter(bad))} must be"):
            Beam(**base, **bad)
    assert Beam(**base, axial_speed=np.int64(3)).axial_speed == 3.0
    assert repr(Beam(**base, axial_speed=78, tension=5)) == repr(Beam(**base, axial_speed=78.0, tension=5.0))


def test_points_within_point_tol_of_each_other_in_a_chain_are_one_node_or_a_gap_that_names_both():
    # POINT_TOL (1e-9 L) makes two points one node. Measured from the node kept, not from the
    # neighbour: a chain 0.8 nm apart merged into its first point, and the third, 1.6 nm from any node,
    # was 'not a node of the beam mesh' (red team); it is a gap, named with digits that tell the two
    # points apart (they read 'x = 0.25 m and x = 0.25 m').
    assert BeamMesh(beam(elements=100), [0.25, 0.25 + 0.8e-9]).elements == 100
    with pytest.raises(InputError, match=r"x = 0.25 m and x = 0.2500000016 m are 1.6e-09 m apart, less than half"):
        BeamMesh(beam(elements=100), [0.25, 0.25 + 0.8e-9, 0.25 + 1.6e-9])
    mesh = BeamMesh(beam(elements=100), [1 - 0.4e-9, 1 - 0.8e-9])   # both within 1e-9 L of the end
    assert mesh.x[-1] == 1.0 and mesh.elements == 100 and mesh.node_at(1 - 0.8e-9) == 100


def test_a_compressed_undamped_moving_beam_solves_its_buckling_load_ei_pi2_over_l2_once(tmp_path, monkeypatch):
    # Its assembly checks the compression against P_cr = EI pi^2 / L^2 (pinned-pinned), and the run's
    # warning above the critical speed sqrt((T + P_cr) / m_t) needs P_cr again: one eigen-solve, not two.
    from mpi4py import MPI

    import dbf_hpc.structure as structure
    from dbf_hpc.run import gyroscopic_checks
    from dbf_hpc.scene import load_scene

    solved = []
    original = structure._solve_buckling_load
    monkeypatch.setattr(structure, "_solve_buckling_load",
                        lambda comm, mesh: solved.append(original(comm, mesh)) or solved[-1])
    path = MPI.COMM_WORLD.bcast(tmp_path / "compressed.toml")
    if MPI.COMM_WORLD.rank == 0:
        path.write_text('[structure]\nkind = "beam"\nlength = 1.0\nelements = 40\nE = 2e11\nI = 1e-8\nA = 1e-4\n'
                        'rho = 7800.0\naxial_speed = 10.0\ntension = -1000.0\n[excitation]\nkind = "none"\n'
                        '[initial]\namplitude = 1e-3\n[basis]\nmodes = 4\ncache = "off"\n[integrator]\nt_end = 0.002\n')
    MPI.COMM_WORLD.Barrier()
    scene = load_scene(str(path))
    with scene.full_order_model() as fom:
        gyroscopic_checks(scene, fom, "rom")
        assert fom.operators.mesh.p_cr == solved[0]
    assert len(solved) == 1, solved
    assert abs(solved[0] / (2e11 * 1e-8 * np.pi**2) - 1) < 1e-6


@pytest.mark.parametrize("change, radius", [(dict(I=8.78e-4), "55"), (dict(I=1.0, A=1e-3), "31.6")])
def test_a_section_wider_than_the_beam_is_long_is_refused_as_a_unit_slip(change, radius):
    # Red team: the paper beam's I = 0.000878 mm^4 given as 0.000878 m^4 (a radius of gyration sqrt(I / A) of
    # 55 m on a 1 m beam) ran without a word at frequencies 1e6 times the paper's: inside the omega^2 bounds.
    with pytest.raises(InputError, match=rf"^beam I = .* m\^4 and A = .* m\^2 give a section whose radius of gyration "
                                         rf"sqrt\(I / A\) = {radius} m exceeds the beam's length 1 m: .*check their units"):
        beam(elements=10, **change)
    # a stubby beam whose section is as wide as it is long is still a beam (Euler-Bernoulli's limit, not ours)
    assert beam(elements=10, I=1e-3, A=1e-3).I == 1e-3
