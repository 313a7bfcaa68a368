"""One DBF per constraint (dbf.py): the spring-perturbed problem against the exact spring-supported
beam, the stiffness rule, and the two derivatives."""
import numpy as np
import pytest
import scipy.io
import scipy.sparse
from mpi4py import MPI
from petsc4py import PETSc

from conftest import assert_all, to_numpy
from dbf_hpc.dbf import (analytic_derivative, branch_of, central_derivative, dbf_source, participation, pinned_eigenvalue,
                         spring_eigenpair, stiffness_sweep, value_at)
from dbf_hpc.matrices import MatrixFiles, load_operators
from dbf_hpc.modes import reference_modes
from dbf_hpc.structure import Beam, assemble_beam
from exact import pinned_beam_with_intermediate_pin_omegas, spring_supported_pinned_beam_omegas

TABLE1 = dict(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0)
BEAM = Beam(**TABLE1, elements=100)
ELL = 0.25


@pytest.fixture(scope="module")
def paper():
    ops = assemble_beam(BEAM, points=[ELL])
    modes = reference_modes(ops, count=6)
    row = ops.mesh.w_row(ELL)
    yield ops, modes, row
    modes.destroy()
    ops.destroy()


def test_first_frequency_with_a_spring_matches_the_exact_spring_supported_beam(paper):
    # Transcendental equation from the paper's Eq. 36 continuity conditions (tests/exact.py).
    ops, _, row = paper
    ks = np.logspace(-4, 6, 21)
    fe = stiffness_sweep(ops, row, ks)
    exact = np.array([spring_supported_pinned_beam_omegas(BEAM.EI, BEAM.rhoA, 1.0, ELL, k)[0] for k in ks])
    assert np.max(np.abs(fe / exact - 1)) < 1e-5


def test_spring_limits_are_the_plain_beam_and_the_beam_with_an_intermediate_pin(paper):
    ops, modes, row = paper
    assert stiffness_sweep(ops, row, [1e-12])[0] == pytest.approx(modes.omega[0], rel=1e-9)
    mu = pinned_eigenvalue(ops, row, 1)
    pin = pinned_beam_with_intermediate_pin_omegas(BEAM.EI, BEAM.rhoA, 1.0, ELL, 1)[0]
    assert np.sqrt(mu) == pytest.approx(pin, rel=1e-6)


def test_auto_stiffness_is_in_the_transition_of_fig_2(paper):
    ops, modes, row = paper
    part = participation(modes, np.array([row]))[0]
    src = dbf_source(ops, row, modes.omega**2, part, "auto")
    lam0, mu = modes.omega[0] ** 2, pinned_eigenvalue(ops, row, 1)
    progress = (src.eigenvalue - lam0) / (mu - lam0)
    assert 0.3 < progress < 0.8, progress           # in the middle of the transition, not at a limit
    assert 0.01 < src.stiffness < 1.0               # the paper reads k ~ 0.1 N/m off its Fig. 2
    src.derivative.destroy()


def test_eigenvalue_derivative_is_the_squared_participation(paper):
    # d lambda / dk = (g^T phi)^2 for M-normalized phi (first-order perturbation).
    ops, _, row = paper
    k, h = 0.05, 1e-4
    lam, phi = spring_eigenpair(ops, row, k, 1)
    lam_plus, p1 = spring_eigenpair(ops, row, k * (1 + h), 1)
    lam_minus, p2 = spring_eigenpair(ops, row, k * (1 - h), 1)
    assert (lam_plus - lam_minus) / (2 * h * k) == pytest.approx(value_at(phi, row) ** 2, rel=1e-6)
    for v in (phi, p1, p2):
        v.destroy()


@pytest.mark.parametrize("k", [1e-3, 0.05, 10.0])
def test_analytic_and_central_difference_derivatives_agree(paper, k):
    ops, _, row = paper
    lam, phi = spring_eigenpair(ops, row, k, 1)
    a = analytic_derivative(ops, row, k, lam, phi)
    c = central_derivative(ops, row, k, 1, phi)
    diff = a.copy()
    diff.axpy(-1.0, c)
    assert diff.norm() / a.norm() < 1e-5
    for v in (phi, a, c, diff):
        v.destroy()


def test_branch_skips_modes_with_a_node_at_the_constraint(paper):
    ops, modes, row = paper
    part = participation(modes, np.array([row]))[0]
    assert part[3] < 1e-12 * part.max()             # l = 0.25 is a node of mode 4
    assert branch_of(part) == 1
    assert branch_of(np.array([1e-20, 3.0, 1.0])) == 2
    assert branch_of(np.zeros(3)) == 0


def test_constraint_at_a_node_of_the_first_mode_follows_the_first_branch_that_moves(shared_tmp_path):
    # Two uncoupled pinned beams, the long one first: mode 1 lives on the long beam only, so a
    # constraint on the short beam sits at a node of mode 1. Its DBF must come from the short beam's
    # own first mode (branch 2), not from the untouched mode 1.
    long_beam, short_beam = Beam(**{**TABLE1, "length": 1.3}, elements=30), Beam(**TABLE1, elements=30)
    blocks = []
    for b in (long_beam, short_beam):
        ops = assemble_beam(b, comm=PETSc.COMM_SELF, points=[ELL])
        blocks.append((ops.K.convert("dense").getDenseArray().copy(), ops.M.convert("dense").getDenseArray().copy(),
                       ops.mesh.w_row(ELL), ops.size))
        ops.destroy()
    paths = [str(shared_tmp_path / name) for name in ("K2.mtx", "M2.mtx")]
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths[0], scipy.sparse.block_diag([blocks[0][0], blocks[1][0]]).tocsr(), precision=17)
        scipy.io.mmwrite(paths[1], scipy.sparse.block_diag([blocks[0][1], blocks[1][1]]).tocsr(), precision=17)
    MPI.COMM_WORLD.Barrier()
    ops = load_operators(MatrixFiles(*paths))
    row = blocks[0][3] + blocks[1][2]
    modes = reference_modes(ops, count=4)
    part = participation(modes, np.array([row]))[0]
    src = dbf_source(ops, row, modes.omega**2, part, "auto")
    assert src.branch == 2
    omega_short = np.sqrt(short_beam.EI / short_beam.rhoA) * np.pi**2
    assert modes.omega[1] == pytest.approx(omega_short, rel=1e-6)
    assert modes.omega[1] ** 2 < src.eigenvalue < pinned_eigenvalue(ops, row, 2)
    d = to_numpy(src.derivative)
    on_long = np.abs(d[:blocks[0][3]]).max()
    assert_all(on_long < 1e-8 * np.abs(d).max(), "the DBF stays on the constrained beam")
    src.derivative.destroy()
    modes.destroy()
    ops.destroy()
