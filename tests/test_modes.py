"""Reference modes (modes.py): by count or below a cutoff, M-normalized, and a clear error when the
eigensolver does not deliver."""
import numpy as np
import pytest
from petsc4py import PETSc

from dbf_hpc.errors import InputError, SolverError
from dbf_hpc.modes import reference_modes
from dbf_hpc.structure import Beam, assemble_beam

BEAM = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=60)
EXACT_HZ = np.sqrt(BEAM.EI / BEAM.rhoA) * (np.arange(1, 30) * np.pi) ** 2 / (2 * np.pi)


@pytest.fixture(scope="module")
def ops():
    ops = assemble_beam(BEAM)
    yield ops
    ops.destroy()


@pytest.mark.parametrize("f_max", [0.5, 5.0, 30.0])
def test_every_mode_below_the_cutoff_and_no_more(ops, f_max):
    modes = reference_modes(ops, max_frequency_hz=f_max)
    assert modes.count == np.count_nonzero(EXACT_HZ < f_max)
    assert np.all(modes.frequency_hz < f_max)
    modes.destroy()


def test_modes_are_m_normalized(ops):
    modes = reference_modes(ops, count=4)
    Mx = ops.M.createVecLeft()
    for i in range(4):
        x = modes.vectors.getColumn(i)
        ops.M.mult(x, Mx)
        assert x.dot(Mx) == pytest.approx(1.0, abs=1e-12)
        modes.vectors.restoreColumn(i, x)
    modes.destroy()


def test_too_few_converged_pairs_is_an_error_naming_the_option(ops):
    options = PETSc.Options()
    options.setValue("modes_eps_max_it", 1)
    options.setValue("modes_eps_tol", 1e-15)
    try:
        with pytest.raises(SolverError, match="eigenpairs converged; raise -modes_eps_max_it"):
            reference_modes(ops, count=20)
    finally:
        options.delValue("modes_eps_max_it")
        options.delValue("modes_eps_tol")


@pytest.mark.parametrize("kwargs,message", [(dict(count=0), "between 1 and"), (dict(max_frequency_hz=1e-3), "no mode below"),
                                            (dict(count=3, max_frequency_hz=1.0), "not both")])
def test_bad_requests_are_clear_errors(ops, kwargs, message):
    with pytest.raises(InputError, match=message):
        reference_modes(ops, **kwargs)
