"""Accuracy control (accuracy.py): the a-priori indicator (captured static flexibility) with every
basis, the a-posteriori estimate with every reduced run, and the tolerance mode."""
import numpy as np
import pytest

from conftest import assert_all
from dbf_hpc import BaseMotion, BasisSettings, Beam, Constraint, FullOrderModel, Reductor, law
from dbf_hpc.accuracy import basis_flexibility, exact_flexibility

BEAM = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=40)
STOPS = [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=x) for x in (0.25, 0.6)]
EI = 117e9 * 8.78e-16


def _captured(settings):
    with FullOrderModel.build(BEAM, STOPS, BaseMotion(5e-3, 1.0)) as fom, Reductor(fom, settings) as reductor:
        return reductor.basis().flexibility_captured.copy(), reductor.basis().flexibility_exact.copy()


def test_exact_flexibility_is_the_pinned_beams_closed_form_deflection():
    # A unit load at a on a pinned-pinned beam deflects it there by a^2 (L - a)^2 / (3 EI L).
    _, f_exact = _captured(BasisSettings(modes=4, enrichment="none"))
    a = np.array([0.25, 0.6])
    assert_all(np.allclose(f_exact, a**2 * (1 - a)**2 / (3 * EI), rtol=1e-8))


def test_a_basis_holding_the_static_mode_captures_all_the_flexibility_and_modes_alone_less_rising_with_n():
    static, _ = _captured(BasisSettings(modes=4, enrichment="static"))
    assert_all(np.all(np.abs(static - 1) < 1e-9))         # K^-1 g_j is in span(V): f_basis = f_exact
    alone = [_captured(BasisSettings(modes=n, enrichment="none"))[0] for n in (2, 4, 8)]
    assert_all(all(np.all(a < 1 - 1e-6) for a in alone))                        # Rayleigh-Ritz: below 1
    assert_all(np.all(alone[0] < alone[1]) and np.all(alone[1] < alone[2]))      # more modes, more of it
    dbf, _ = _captured(BasisSettings(modes=2))
    assert_all(np.all(dbf > alone[2]))     # the DBF (the method) captures more than 8 modes alone


def test_basis_flexibility_of_a_singular_reduced_stiffness_is_undefined():
    assert np.all(np.isnan(basis_flexibility(np.zeros((2, 2)), np.eye(2))))
