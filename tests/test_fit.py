"""Conductivity fitting recovers known tissue conductivities from noisy simulated voltages."""

import numpy as np
import pytest

from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import build_forward_model, simulate
from jaxhead.fit import fit_conductivities
from jaxhead.inverse import add_noise, noise_std
from jaxhead.protocol import adjacent, opposite
from sphere_mesh import structured_sphere_mesh

TRUE = np.array([0.3, 1.79, 0.018, 0.44])  # brain, CSF, skull, scalp (S/m)


@pytest.fixture(scope="module")
def sphere_model():
    mesh = structured_sphere_mesh(h_mm=18.0)
    pos = spread_positions(mesh, 16)
    el = place_electrodes(mesh, pos, radius_mm=8.0)
    return build_forward_model(mesh, el)


def test_recovers_conductivities_from_noisy_data(sphere_model):
    # Drives across the head send current through the brain, so all four tissues are informed.
    prot = opposite(16)
    v_true = np.asarray(simulate(sphere_model, TRUE, prot))
    std = noise_std(v_true, 0.1) + 1e-3 * np.abs(v_true).max() * 1e-3
    measured = add_noise(v_true, 0.1, seed=1)
    res = fit_conductivities(sphere_model, prot, measured, init=[0.2, 1.0, 0.03, 0.3],
                             noise_std=std)
    assert res.success
    rel = np.abs(res.sigma / TRUE - 1)
    # 0.1 % noise: each estimate within 4 standard errors of the truth, and the well-determined
    # scalp within 2 %; brain and CSF trade off inside a sphere (reported by their correlation).
    assert np.all(np.abs(res.sigma - TRUE) <= 4 * res.std_error + 1e-12), (res.sigma, res.std_error)
    assert rel[3] < 0.02
    assert res.correlation.shape == (4, 4)
    np.testing.assert_allclose(np.diag(res.correlation), 1.0, atol=1e-9)
    assert res.n_forward >= res.n_steps > 0


def test_exact_data_fit_is_exact_and_partial_fit(sphere_model):
    prot = adjacent(16)
    measured = np.asarray(simulate(sphere_model, TRUE, prot))
    # Explicit bounds on one parameter, the default (init / 1e3 .. init * 1e3) on the other.
    res = fit_conductivities(sphere_model, prot, measured, init=[0.3, 1.79, 0.01, 0.6],
                             fit=("skull", "scalp"), bounds={"skull": (0.002, 0.2)})
    np.testing.assert_allclose(res.sigma, TRUE, rtol=1e-5)
    assert res.fitted == ("skull", "scalp")


def test_fit_errors(sphere_model):
    prot = adjacent(16)
    m = np.ones(prot.rows.shape[0]) * 1e-3
    with pytest.raises(ValueError, match="> 0 S/m"):
        fit_conductivities(sphere_model, prot, m, init=[0.3, 0.0, 0.01, 0.4])
    with pytest.raises(ValueError, match="4 conductivities"):
        fit_conductivities(sphere_model, prot, m, init=[0.3, 0.01])
    with pytest.raises(ValueError, match="protocol has"):
        fit_conductivities(sphere_model, prot, m[:-1], init=TRUE)
    with pytest.raises(ValueError, match="unknown tissue"):
        fit_conductivities(sphere_model, prot, m, init=TRUE, fit=("bone",))
    with pytest.raises(ValueError, match="bounds"):
        fit_conductivities(sphere_model, prot, m, init=TRUE, fit=("skull",),
                           bounds={"scalp": (0.1, 1.0)})
