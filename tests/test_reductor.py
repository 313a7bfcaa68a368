"""The reductor (reductor.py): what it projects onto the basis is what the reduced model holds, and
the reduced model is small numpy arrays, the same on every rank."""
import warnings

import numpy as np
import pytest

from conftest import assert_all, two_ranks_of
from dbf_hpc import (Beam, BaseMotion, BasisSettings, Constraint, Damping, FullOrderModel, InitialState,
                     Reductor, law)
from dbf_hpc.errors import InputError
from dbf_hpc.excitation import Harmonic
from dbf_hpc.laws import ConstraintLaws

BEAM = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=40)
STOP = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)


def test_reduced_operators_are_the_projections_and_the_mass_is_the_identity():
    # K_r is V^T K V except on the reference modes' block, which is diag(omega^2) (their Rayleigh
    # quotients; the projection's couplings there are the eigensolver's residual, below 1e-8 of
    # sqrt(K_ii K_jj)); M_r = I exactly (the projection's |V^T M V - I| is below 1e-8)
    damping = Damping(rayleigh_alpha=0.3, rayleigh_beta=2e-5)
    with FullOrderModel.build(BEAM, [STOP], BaseMotion(5e-3, 1.0), damping, probes=[0.5]) as fom, \
            Reductor(fom, BasisSettings(modes=6)) as reductor:
        rom = reductor.reduce(field=True)
        basis = reductor.basis()
        K = basis.project(fom.operators.K)
        B = basis.rows(fom.constraints.flat_rows)
        probe = basis.rows([fom.operators.mesh.w_row(0.5)])
    assert rom.size == 7
    np.testing.assert_array_equal(rom.M, np.eye(7))                   # V^T M V = I (Eq. 40)
    assert 0 <= rom.basis_info["mass_orthonormality_defect"] < 1e-12
    modes = np.diag(np.diag(K)[:6])
    d = np.sqrt(np.diag(K)[:6])
    assert np.abs(K[:6, :6] - modes).max() <= 1e-8 * np.outer(d, d).min()
    np.testing.assert_array_equal(rom.K[:6, :6], modes)                 # diag(omega^2) on the modes
    np.testing.assert_allclose(np.diag(rom.K)[:6], rom.basis_info["omega"] ** 2, rtol=1e-8)
    np.testing.assert_array_equal(rom.K[6:], K[6:])                     # the DBF's rows and column:
    np.testing.assert_array_equal(rom.K[:, 6:], K[:, 6:])               # the projection, not symmetrized
    np.testing.assert_allclose(rom.C, 0.3 * rom.M + 2e-5 * rom.K, rtol=1e-14)   # Rayleigh projects exactly
    np.testing.assert_array_equal(rom.B, B)
    np.testing.assert_array_equal(rom.probe_B, probe)
    # the moving support: r = 1 - x/L on a pinned beam moved at its left end (Eq. 26)
    np.testing.assert_allclose(rom.r_c, [0.75], rtol=1e-8)
    np.testing.assert_allclose(rom.probe_r, [0.5], rtol=1e-8)
    assert rom.field.positions.size == 41 and rom.field.support[0] == 1.0 and rom.field.support[-1] == 0.0
    np.testing.assert_allclose(rom.field.support, 1 - rom.field.positions, atol=1e-8)


def test_a_case_changes_the_law_and_the_excitation_but_not_the_operators():
    with FullOrderModel.build(BEAM, [STOP], BaseMotion(5e-3, 1.0)) as fom, \
            Reductor(fom, BasisSettings(modes=4)) as reductor:
        rom = reductor.reduce()
    spring = rom.constraints.with_laws(ConstraintLaws([law("linear", k=10.0)]))
    case = rom.with_case(constraints=spring)
    assert case.K is rom.K and case.B is rom.B
    assert case.constraints.laws.laws[0].kind == "linear" and rom.constraints.laws.laws[0].kind == "deadband"


def test_another_law_given_as_a_plain_list_runs_on_the_same_basis_as_a_model_built_with_it():
    # Red team: the API's natural call, with_laws([law(...)]), was an AttributeError ('list' object
    # has no attribute 'n'). The paper's Eq. 42 on the deadband's basis is the model built with Eq. 42
    # from the start (the basis does not depend on the law: paper, conclusion 2), step for step.
    from dbf_hpc import IntegratorSettings, simulate_reduced
    eq42 = law("power", clearance=2.5e-3, k_minus=0.1, exponent_minus=3, k_plus=1e6, exponent_plus=1)
    runs = []
    for stop, laws in ((STOP, [eq42]), (Constraint(eq42, x=0.25), None)):
        with FullOrderModel.build(BEAM, [stop], BaseMotion(5e-3, 1.0)) as fom, \
                Reductor(fom, BasisSettings(modes=4), None) as reductor:
            rom = reductor.reduce()
        if laws is not None:
            rom = rom.with_case(constraints=rom.constraints.with_laws(laws))
        runs.append(simulate_reduced(rom, IntegratorSettings(t_end=2.0, sample_dt=1e-3)))
    # the paper's Fig. 7: past -d on the soft cubic side, held at +d by the stiff side
    assert runs[0].displacement.min() < -2.6e-3 and runs[0].displacement.max() < 2.6e-3
    np.testing.assert_allclose(runs[0].displacement, runs[1].displacement, rtol=0, atol=1e-12)
    with pytest.raises(InputError, match="2 laws for 1 constraints"):   # the project's one line, not a ValueError
        rom.constraints.with_laws([eq42, eq42])


def test_an_initial_mode_shape_starts_at_the_requested_peak_displacement():
    with FullOrderModel.build(BEAM, [STOP], initial=InitialState(mode=2, amplitude=1e-3)) as fom, \
            Reductor(fom, BasisSettings(modes=4)) as reductor:
        rom = reductor.reduce(field=True)
    w = rom.field.at(rom.q0, 0.0)
    assert_all(abs(np.abs(w).max() - 1e-3) < 1e-15 and np.count_nonzero(rom.q0) == 1)


@pytest.mark.parametrize("start", [dict(amplitude=1e308), dict(amplitude=-1e308), dict(velocity=1e308)])
def test_an_initial_state_beyond_double_precision_is_refused_naming_the_initial_section(start, shared_tmp_path):
    # u(0) = amplitude x a mode shape of peak 1, projected with M: past 1e308 m it is inf. Red team: numpy's
    # overflow warning, then "the state is not finite at t = 0 s (step 0); reduce [integrator] dt or rtol".
    # A beam refuses a displacement longer than itself when it is built (fom.check_displacement): the
    # displacements go to a matrix model (no length), the velocity to the beam of two planes.
    from conftest import twin_chains
    from dbf_hpc.matrices import MatrixFiles

    twin_chains(shared_tmp_path, copies=1)[0].destroy()   # one chain: distinct frequencies
    chain = MatrixFiles(str(shared_tmp_path / "K.mtx"), str(shared_tmp_path / "M.mtx"))
    tube = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=40, planes=2)
    structure, stop = ((tube, Constraint(law("circular", clearance=2.5e-3, k=1e6), x=0.25)) if "velocity" in start else
                       (chain, Constraint(law("deadband", clearance=1e-3, k=1e6), dof=3)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # no RuntimeWarning on the way to the one line
        with FullOrderModel.build(structure, [stop], initial=InitialState(mode=1, **start)) as fom, \
                Reductor(fom, BasisSettings(modes=4)) as reductor:
            with pytest.raises(InputError, match=r"^\[initial\] amplitude = .* m, velocity = .* m/s: the initial "
                                                 r"state in the basis is beyond double precision"):
                reductor.reduce()
    with FullOrderModel.build(chain, [Constraint(law("deadband", clearance=1e-3, k=1e6), dof=3)],
                              initial=InitialState(mode=1, amplitude=1e300)) as fom, \
            Reductor(fom, BasisSettings(modes=4)) as reductor:
        assert_all(np.isfinite(reductor.reduce().q0).all())   # large, finite: the integration's to judge
    if "amplitude" in start:   # on the beam: refused as a unit slip before anything is built
        with pytest.raises(InputError, match=r"^FullOrderModel.build: InitialState: amplitude = .* m, the peak initial "
                                             r"displacement, is more than the beam's length \(1 m\)"):
            FullOrderModel.build(tube, [Constraint(law("circular", clearance=2.5e-3, k=1e6), x=0.25)],
                                 initial=InitialState(mode=1, **start))


def test_reduce_refuses_a_field_flag_that_is_not_a_bool():
    # the API edge: field="no" was truthy, so it projected the field points it was asked not to
    with FullOrderModel.build(BEAM, [STOP]) as fom, Reductor(fom, BasisSettings(modes=4)) as reductor:
        with pytest.raises(InputError, match=r"^Reductor.reduce field: give True or False, got 'no'$"):
            reductor.reduce(field="no")
        assert reductor.reduce(field=False).field is None


def same_galerkin_model(K0, M0, B0, K1, M1, B1):
    """Two reduced models of one span in two coordinate systems (K1 = T^T K0 T, M1 = T^T M0 T, B1 = B0 T)
    have the same generalized eigenvalues and the same receptance B (K - w^2 M)^-1 B^T at the
    constraints, static, below the first eigenvalue and between two: to round-off, 100 eps times the
    condition number of the matrix solved (the eigenvalues: 100 r eps ||K||). K0's antisymmetric part is the projection's round-off (K
    is symmetric; 1e-8 of sqrt(K_ii K_jj) on a fine tube), which a diagonal mode block drops: the
    reference is K0's symmetric part."""
    from scipy.linalg import eigh

    eps = np.finfo(float).eps
    K0 = 0.5 * (K0 + K0.T)
    lam0, lam1 = eigh(K0, M0, eigvals_only=True), eigh(K1, M1, eigvals_only=True)
    # eigenvalues to a backward error of r eps ||K|| (100 times: round-off)
    np.testing.assert_allclose(lam1, lam0, rtol=0, atol=100 * eps * len(lam0) * np.linalg.cond(M0) * np.abs(lam0).max())
    for w2 in (0.0, 0.5 * lam0[0], 0.5 * (lam0[1] + lam0[2])):
        h0 = B0 @ np.linalg.solve(K0 - w2 * M0, B0.T)
        h1 = B1 @ np.linalg.solve(K1 - w2 * M1, B1.T)
        np.testing.assert_allclose(h1, h0, rtol=0, atol=100 * eps * np.linalg.cond(K0 - w2 * M0) * np.abs(h0).max())


def test_projection_defects_above_the_tolerance_are_kept_in_a_basis_turned_within_its_span():
    # a reduced model is cleaned only of the eigensolver's and Gram-Schmidt's residuals, never of a
    # real coupling: a 1e-2 mode-mode coupling and a 1e-2 mass defect stay in the model (its
    # eigenvalues and receptance at the constraint), which the basis turned within its span (V T,
    # the constraint's row of V too) carries with M_r = I and a diagonal mode block exactly, the
    # structure the stage solve uses
    from dbf_hpc.reductor import PROJECTION_TOL

    with FullOrderModel.build(BEAM, [STOP]) as fom, Reductor(fom, BasisSettings(modes=4)) as reductor:
        basis = reductor.basis()
        K, M = basis.project(fom.operators.K), basis.project(fom.operators.M)
        rows = fom.constraints.flat_rows
        B0 = basis.rows(rows)
        K[0, 1] = K[1, 0] = 1e-2 * np.sqrt(K[0, 0] * K[1, 1])
        M[2, 2] += 1e-2
        M[1, 4] = M[4, 1] = 1e-2
        K0, M0 = K.copy(), M.copy()
        defects = Reductor._clean_projection(basis, K, M)
        B1 = basis.rows(rows)
        omega = basis.omega
    assert defects["mode_coupling_defect"] > PROJECTION_TOL and defects["mass_orthonormality_defect"] > PROJECTION_TOL
    assert defects["turned_in_span"]
    np.testing.assert_array_equal(M, np.eye(5))
    np.testing.assert_array_equal(K[:4, :4], np.diag(np.diag(K)[:4]))
    np.testing.assert_allclose(np.diag(K)[:4], omega ** 2, rtol=1e-14)   # the modes' Ritz values are their omega
    same_galerkin_model(K0, M0, B0, K, M, B1)


def test_a_fine_tube_mesh_is_reduced_in_turned_coordinates_to_the_same_galerkin_model_with_its_structure():
    # On a tube of 800 elements V^T K V carries the round-off of an ill-conditioned K: the reference
    # modes couple at ~1e-7 of sqrt(K_ii K_jj), above PROJECTION_TOL, and the reduced model fell to
    # dense stage solves (5x the integration time at 112 vectors). Turned within its span, the basis
    # gives the same model (eigenvalues, receptance at the supports), M-orthonormal as the reduced
    # model says, with M_r = I and the diagonal mode block exactly
    from dbf_hpc.reductor import PROJECTION_TOL
    from dbf_hpc.scene import load_scene

    scene = load_scene("jobs/steam_generator_tube.toml", ["structure.elements=800"])
    with scene.full_order_model() as fom, Reductor(fom, scene.basis_settings()) as reductor:
        basis = reductor.basis()
        K0, M0 = basis.project(fom.operators.K), basis.project(fom.operators.M)
        B0 = basis.rows(fom.constraints.flat_rows)
        rom = reductor.reduce()
        turned_M = basis.project(fom.operators.M)
    m = basis.mode_count
    assert rom.basis_info["mode_coupling_defect"] > PROJECTION_TOL and rom.basis_info["turned_in_span"]
    np.testing.assert_array_equal(rom.M, np.eye(rom.size))
    np.testing.assert_array_equal(rom.K[:m, :m], np.diag(np.diag(rom.K)[:m]))
    assert np.abs(turned_M - np.eye(rom.size)).max() < 1e-10         # V T is M-orthonormal: M_r = I is true
    same_galerkin_model(K0, M0, B0, rom.K, rom.M, rom.B)


def test_a_fine_two_plane_tube_turned_within_its_span_is_one_model_alone_and_on_every_rank(comm):
    # The 2-D tube of 800 elements: its modes come in y-z pairs of one frequency (any mix of y and z, as
    # the eigensolver chose on each rank count) and couple at 1e-7 by round-off, so the basis is turned
    # within its span (Rayleigh-Ritz on the modes' block mixes each pair again). Whatever mix, it is the
    # Galerkin model of the projection (eigenvalues, receptance at the supports), with 2 % modal damping
    # on every mode of a pair alike, and integrated at fixed steps it moves the supports as the model
    # built on rank 0 alone does (measured: 1.1e-9 of the largest |w| over 0.05 s on 2 ranks, 48 vectors).
    from mpi4py import MPI
    from petsc4py import PETSc

    from dbf_hpc import IntegratorSettings, simulate_reduced
    from dbf_hpc.scene import load_scene

    scene = load_scene("jobs/steam_generator_tube_2d.toml", ["structure.elements=800", "basis.cache=off",
                                                             "basis.max_frequency_hz=60"])
    settings = IntegratorSettings(t_end=0.05, dt=1e-4, sample_dt=1e-3, adaptive=False, callbacks="auto")

    def reduced(on):
        with scene.full_order_model(on) as fom, Reductor(fom, scene.basis_settings()) as reductor:
            basis = reductor.basis()
            K0, M0 = basis.project(fom.operators.K), basis.project(fom.operators.M)
            B0 = basis.rows(fom.constraints.flat_rows)
            return K0, M0, B0, reductor.reduce()

    K0, M0, B0, rom = reduced(comm)
    omega = rom.basis_info["omega"]
    assert rom.basis_info["turned_in_span"] and rom.basis_info["mode_coupling_defect"] > 1e-8
    np.testing.assert_allclose(omega[0::2], omega[1::2], rtol=1e-6)         # whole y-z pairs, turned alike
    np.testing.assert_allclose(np.diag(rom.C)[:omega.size], 2 * 0.02 * omega, rtol=1e-12)
    same_galerkin_model(K0, M0, B0, rom.K, rom.M, rom.B)
    w = simulate_reduced(rom, settings).displacement
    alone = None
    if MPI.COMM_WORLD.rank == 0:
        alone = simulate_reduced(reduced(PETSc.COMM_SELF)[3], settings).displacement
    alone = MPI.COMM_WORLD.bcast(alone, root=0)
    assert_all(np.abs(w - alone).max() < 1e-7 * np.abs(alone).max(), np.abs(w - alone).max() / np.abs(alone).max())


def test_a_failed_projection_of_the_support_load_frees_its_mass_product(monkeypatch, capfd):
    # Review: reduce() made M r (the support's inertia load) and destroyed it only after projecting it,
    # so a failure there left the Vec behind (in parallel: in PETSc's garbage). The failure reaches the
    # caller as one SolverError line.
    from petsc4py import PETSc

    from conftest import petsc_garbage, undestroyed_petsc_objects
    from dbf_hpc.basis import ReducedBasis
    from dbf_hpc.errors import SolverError

    real = ReducedBasis.dot
    with FullOrderModel.build(BEAM, [STOP], BaseMotion(5e-3, 1.0)) as fom, \
            Reductor(fom, BasisSettings(modes=4)) as reductor:
        reductor.basis()

        def dot(self, vec):
            if vec is not fom.operators.base_mass_load:   # M r, after the base load's projection
                raise PETSc.Error(55)
            return real(self, vec)

        monkeypatch.setattr(ReducedBasis, "dot", dot)
        PETSc.garbage_cleanup()
        before = undestroyed_petsc_objects()
        with pytest.raises(SolverError, match=r"^Reductor.reduce: PETSc error 55"):
            reductor.reduce()
        assert_all(undestroyed_petsc_objects() == before, "M r was destroyed")
        assert petsc_garbage(capfd) == 0, "nothing was left in PETSc's garbage"


@pytest.mark.parametrize("change,message", [
    ({"q0": [1e-4]}, r"with_case q0: give 5 finite reduced coordinates .*got \[0.0001\]"),
    ({"p0": [np.nan] * 5}, r"with_case p0: give 5 finite reduced coordinates"),
    ({"q0": "abc"}, r"with_case q0: give 5 finite"),
    ({"support": "x"}, r"with_case support: give a Harmonic"),
    ({"force": 3.0}, r"with_case force: give a force history"),
    ({"force": Harmonic}, r"with_case force: give a force history"),
    ({"constraints": "deadband"}, r"with_case constraints: give the model's own constraints"),
])
def test_a_case_refuses_a_start_or_an_excitation_the_model_cannot_take_in_one_line(change, message):
    # Red team: q0 = [1e-4] on a basis of 5 was broadcast to all 5 coordinates (a silent wrong start),
    # and a support or force of another type failed in the integration as AttributeError or TypeError.
    with FullOrderModel.build(BEAM, [STOP], BaseMotion(5e-3, 1.0)) as fom, \
            Reductor(fom, BasisSettings(modes=4)) as reductor:
        rom = reductor.reduce()
    assert rom.size == 5
    with pytest.raises(InputError, match=message):
        rom.with_case(**change)


@pytest.mark.parametrize("laws,message", [([], "0 laws for 1 constraints"), (["deadband"], "constraint 1: expected a Law, got str"),
                                          ([law("linear", k=1.0)] * 2, "2 laws for 1 constraints")])
def test_other_laws_of_the_wrong_count_or_kind_are_one_input_error(laws, message):
    # Red team: with_laws([]) raised a bare ValueError and with_laws(["deadband"]) a TypeError
    with FullOrderModel.build(BEAM, [STOP], BaseMotion(5e-3, 1.0)) as fom:
        with pytest.raises(InputError, match=f"with_laws: {message}; give one law\\(...\\) per constraint"):
            fom.constraints.with_laws(laws)


def test_an_initial_mode_of_a_repeated_frequency_is_refused_by_both_models(shared_tmp_path):
    # Two identical chains: mode 1 is any mix of the chains' first modes. The full-order model took the
    # mix of its own eigensolve and the reduced model its basis's: on 2 ranks they started one at
    # -9.3e-5 m, the other at +4.7e-4 m on the second chain (1 rank: -3.8e-4 m for both). Both refuse it,
    # naming the pair; mode 4 too (the second of its pair, which no count of modes cuts).
    from conftest import twin_chains
    from dbf_hpc.matrices import MatrixFiles

    twin_chains(shared_tmp_path)[0].destroy()
    files = MatrixFiles(str(shared_tmp_path / "K.mtx"), str(shared_tmp_path / "M.mtx"))
    stop = Constraint(law("deadband", clearance=1e-3, k=1e6), dof=3)
    for mode, pair in ((1, "modes 1 to 2"), (4, "modes 3 to 4")):
        with FullOrderModel.build(files, [stop], initial=InitialState(mode=mode, amplitude=1e-3)) as fom:
            with pytest.raises(InputError, match=rf"\[initial\] mode = {mode}: one of the 2 modes of one repeated "
                                                 rf"frequency, .* Hz \({pair}\): its shape is any mix of them"):
                fom.initial_state()
            with Reductor(fom, BasisSettings(modes=4)) as reductor, \
                    pytest.raises(InputError, match=rf"\[initial\] mode = {mode}: one of the 2 modes .*\({pair}\)"):
                reductor.reduce()



def test_the_support_motion_in_the_basis_is_each_modes_participation_in_the_rigid_rotation_of_a_pinned_beam(comm):
    # The left support of the pinned-pinned beam moves: r = 1 - x/L (w) and -1/L (the slopes). Per M-orthonormal
    # mode phi_i = sqrt(2 / m) sin(i pi x / L) (m = rho A L) its inertia load is rho A int phi_i (1 - x/L) dx =
    # sqrt(2 m) / (i pi) (the cubic elements hold r: exact up to the FE mode shape). r_q is V^T M r over the free
    # DOFs alone (what support_jump turns into the relative state), here against r written out node by node, not
    # the influence solve. Planted bug it catches: the reductor leaving r_q at zero (a sweep's support jump then
    # broke the continuity of the total displacement and velocity).
    with FullOrderModel.build(BEAM, [STOP], BaseMotion(5e-3, 1.0), comm=comm) as fom, \
            Reductor(fom, BasisSettings(modes=6)) as reductor:
        rom = reductor.reduce()
        mesh, M = fom.operators.mesh, fom.operators.M
        r, Mr = M.createVecRight(), M.createVecLeft()
        lo, hi = r.getOwnershipRange()
        for node, x in enumerate(mesh.x):
            for dof, value in ((mesh.row[node, 0], 1 - x / BEAM.length), (mesh.row[node, 1], -1 / BEAM.length)):
                if lo <= dof < hi:
                    r.setValue(dof, value)
        r.assemble()
        M.mult(r, Mr)
        r_q = reductor.basis().dot(Mr)
        r.destroy(), Mr.destroy()
    mass = BEAM.rho * BEAM.A * BEAM.length
    np.testing.assert_allclose(np.abs(rom.base_load[:6]), np.sqrt(2 * mass) / (np.pi * np.arange(1, 7)), rtol=1e-5)
    np.testing.assert_allclose(rom.r_q, r_q, rtol=1e-8, atol=1e-10 * np.abs(r_q).max())


def test_a_reductor_says_the_very_lines_a_run_says_of_its_basis_once_from_rank_0(shared_tmp_path, capfd):
    # Warnings parity: `dbf-hpc run` warns of its basis (run.basis_warnings; here 1 mode without enrichment
    # captures 87.6 % of the stop's static flexibility: accuracy.flexibility_warning); the Python API's
    # Reductor said nothing of it. It now says the run's very line as it obtains the basis, once, from rank 0
    # of the model's communicator; warn_basis=False (the front ends that say it themselves) says nothing.
    import os

    from mpi4py import MPI
    from petsc4py import PETSc

    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    paper = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "jobs", "paper_beam.toml")
    scene = load_scene(paper, ['basis.enrichment="none"', "basis.modes=1", "basis.estimate=false",
                               "integrator.t_end=0.01", 'basis.cache="off"', "output.snapshots=0"])
    ran = run(scene, str(shared_tmp_path / "flexibility.h5"), progress=False)
    capfd.readouterr()
    with scene.full_order_model(PETSc.COMM_WORLD) as fom:
        with Reductor(fom, scene.basis_settings()) as reductor:
            reductor.basis()
            reductor.reduce()
        with Reductor(fom, scene.basis_settings(), warn_basis=False) as quiet:
            quiet.reduce()
    err = capfd.readouterr().err
    said = [line[len("dbf-hpc: warning: "):] for line in err.splitlines() if line.startswith("dbf-hpc: warning: ")]
    if MPI.COMM_WORLD.rank == 0:
        assert len(said) == 1 and said[0].startswith("the basis captures ") and said[0] in ran["warnings"], \
            (said, ran["warnings"])
    else:
        assert said == [], said


# Rank 0 of a 2-rank Reductor (the Python API) meets an exception no check foresaw as it computes the turn
# within the basis' span (Reductor._turn_in_span: rank 0's numbers for every rank), which every basis takes
# here (PROJECTION_TOL below any defect); every rank says what it raised
_UNEXPECTED_AS_RANK_0_TURNS = """
from mpi4py import MPI
from dbf_hpc import Beam, BasisSettings, Constraint, FullOrderModel, Reductor, law
from dbf_hpc import reductor

rank = MPI.COMM_WORLD.rank
reductor.PROJECTION_TOL = -1.0
def refuse(*args, **kwargs):
    raise FloatingPointError("rank 0's turn refused")
if rank == 0:
    reductor._turn = refuse
beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
def act():
    with FullOrderModel.build(beam, [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)]) as fom:
        with Reductor(fom, BasisSettings(modes=4)) as r:
            r.reduce()


every_rank_says(act)
"""


@pytest.mark.launcher
def test_an_unexpected_error_while_rank_0_turns_the_basis_within_its_span_is_raised_on_every_rank():
    # Red team: rank 0 computes the turn and broadcasts it; a LinAlgError or ValueError (eigh did not
    # converge) was every rank's "not turned", and anything else (a bug) left rank 0 alone with it and the
    # other ranks waiting in the broadcast for ever (the Python API does not abort as `python -m mpi4py`
    # does). Now every rank raises it, rank 0 its own and rank 1 a copy naming rank 0.
    out = two_ranks_of(_UNEXPECTED_AS_RANK_0_TURNS)
    assert out.returncode == 0, f"exit {out.returncode} (124: a rank waited for ever)\n{out.stdout}{out.stderr}"
    assert out.stdout.splitlines() == ["rank 0: FloatingPointError: rank 0's turn refused (origin None)",
                                       "rank 1: FloatingPointError: rank 0's turn refused (origin 0)"], out.stdout
