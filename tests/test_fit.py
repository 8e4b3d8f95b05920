"""Conductivity fitting recovers known tissue conductivities from noisy simulated voltages."""

import numpy as np
import optimistix as optx
import pytest

from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import build_forward_model, jacobian, simulate
from jaxhead.inverse.fit import LineSearchGaussNewton, fit_conductivities, fit_conductivities_batch
from jaxhead.inverse import add_noise, noise_std
from jaxhead.protocol import Protocol, pair_drive
from jaxhead.tissue import default_sigma
from sphere_mesh import structured_sphere_mesh

# Truth: the literature values (jaxhead.tissue) changed by -10..+20 %; fits start from the
# literature values, as a user would.
TRUE = default_sigma() * np.array([1.1, 0.9, 1.2, 0.95])  # brain, CSF, skull, scalp (S/m)
N_ELEC = 32


@pytest.fixture(scope="module")
def sphere_model():
    # 18 mm grid: 16k tets, every shell one or more layers thick (fast; refined spheres give
    # larger standard errors for brain and CSF, see the report in benchmarks/fit.py).
    mesh = structured_sphere_mesh(h_mm=18.0)
    el = place_electrodes(mesh, spread_positions(mesh, N_ELEC), radius_mm=10.0)
    return build_forward_model(mesh, el)


def skip_protocol(n_elec, skips=(1, 4, 8, 16)):
    """Drives (i, i + k) for every electrode i and skip k, each measured on all adjacent pairs."""
    return Protocol(np.concatenate([pair_drive(n_elec, i, (i + k) % n_elec).rows
                                    for k in skips for i in range(n_elec)]))


@pytest.fixture(scope="module")
def protocol():
    # Drives with several separations: near ones probe scalp and skull, far ones send current
    # through CSF and brain. Predicted standard errors at 0.5 % noise on this mesh (Fisher
    # matrix): brain 0.25 %, CSF 0.69 %, skull 0.06 %, scalp 0.02 %; opposite + adjacent drives
    # alone give 0.58 / 1.67 / 0.16 / 0.06 %, which misses the 2 % bar for CSF. Brain and CSF
    # stay correlated at ~ -0.995 inside a sphere.
    return skip_protocol(N_ELEC)


def test_recovers_conductivities_from_noisy_data(sphere_model, protocol):
    v_true = np.asarray(simulate(sphere_model, TRUE, protocol))
    measured = add_noise(v_true, 0.5, seed=1)  # 0.5 % per channel (the seed paper's level)
    std = noise_std(measured, 0.5)  # what a user knows: the level, applied to the data
    res = fit_conductivities(sphere_model, protocol, measured, init=default_sigma(),
                             noise_std=std)
    assert res.success and res.result == optx.RESULTS.successful
    rel = np.abs(res.sigma / TRUE - 1)
    # The bar: brain, CSF, scalp within 2 %, skull within 10 %.
    assert np.all(rel < [0.02, 0.02, 0.10, 0.02]), rel
    # Estimates within 4 standard errors of the truth (a 4-sigma event has p ~ 6e-5).
    assert np.all(np.abs(res.sigma - TRUE) <= 4 * res.std_error), (res.sigma, res.std_error)
    assert res.n_forward >= res.n_steps > 0
    np.testing.assert_allclose(np.diag(res.correlation), 1.0, atol=1e-9)
    # Gauss-Newton covariance (forward-mode AD through the solver) against the Fisher matrix
    # of the adjoint per-tissue Jacobian (reciprocity), an independent computation:
    # both are float64 with one factorisation, so they agree to ~1e-8; 1e-6 leaves margin.
    Jt = np.asarray(jacobian(sphere_model, res.sigma, protocol, per="tissue")) / std[:, None]
    cov = np.linalg.inv(Jt.T @ Jt)
    np.testing.assert_allclose(res.std_error, np.sqrt(np.diag(cov)), rtol=1e-6)
    assert res.correlation[0, 1] < -0.9  # brain and CSF trade off inside a sphere


def test_exact_data_fit_is_exact_and_partial_fit(sphere_model, protocol):
    measured = np.asarray(simulate(sphere_model, TRUE, protocol))
    init = TRUE * np.array([1.0, 1.0, 0.6, 1.4])
    # Explicit bounds on one parameter, the default (init / 1e3 .. init * 1e3) on the other;
    # the Gauss-Newton line-search solver instead of the default Levenberg-Marquardt.
    res = fit_conductivities(sphere_model, protocol, measured, init=init,
                             fit=("skull", "scalp"), bounds={"skull": (0.002, 0.2)},
                             solver=LineSearchGaussNewton(rtol=1e-8, atol=1e-8))
    # Noise-free data: the optimum is the truth up to the solver's tolerance (rtol 1e-6 in
    # log-parameters) and float64 round-off.
    np.testing.assert_allclose(res.sigma, TRUE, rtol=1e-5)
    assert res.fitted == ("skull", "scalp")
    np.testing.assert_array_equal(res.sigma[:2], init[:2])  # unfitted stay at init


def test_fit_errors(sphere_model, protocol):
    m = np.ones(protocol.n_rows) * 1e-3
    with pytest.raises(ValueError, match="> 0 S/m"):
        fit_conductivities(sphere_model, protocol, m, init=[0.3, 0.0, 0.01, 0.4])
    with pytest.raises(ValueError, match="> 0 S/m"):
        fit_conductivities(sphere_model, protocol, m, init=[0.3, -1.0, 0.01, 0.4])
    with pytest.raises(ValueError, match="4 conductivities"):
        fit_conductivities(sphere_model, protocol, m, init=[0.3, 0.01])
    with pytest.raises(ValueError, match="protocol has"):
        fit_conductivities(sphere_model, protocol, m[:-1], init=TRUE)
    with pytest.raises(ValueError, match="fit_conductivities_batch"):
        fit_conductivities(sphere_model, protocol, np.stack([m, m]), init=TRUE)
    with pytest.raises(ValueError, match="n_batch, n_rows"):
        fit_conductivities_batch(sphere_model, protocol, m, init=TRUE)
    with pytest.raises(ValueError, match="unknown tissue"):
        fit_conductivities(sphere_model, protocol, m, init=TRUE, fit=("bone",))
    with pytest.raises(ValueError, match="twice"):
        fit_conductivities(sphere_model, protocol, m, init=TRUE, fit=("skull", "skull"))
    with pytest.raises(ValueError, match="noise_std"):
        fit_conductivities(sphere_model, protocol, m, init=TRUE, noise_std=0.0)
    with pytest.raises(ValueError, match="bounds"):
        fit_conductivities(sphere_model, protocol, m, init=TRUE, fit=("skull",),
                           bounds={"scalp": (0.1, 1.0)})
    with pytest.raises(ValueError, match="0 < lo < init"):
        fit_conductivities(sphere_model, protocol, m, init=TRUE, fit=("skull",),
                           bounds={"skull": (0.1, 1.0)})


@pytest.mark.slow
def test_batch_equals_loop(sphere_model, protocol):
    # vmapped optimistix solve over noise realisations == one fit per realisation.
    v_true = np.asarray(simulate(sphere_model, TRUE, protocol))
    data = np.stack([add_noise(v_true, 0.5, seed=s) for s in (2, 3)])
    std = noise_std(v_true, 0.5)
    batch = fit_conductivities_batch(sphere_model, protocol, data, init=default_sigma(),
                                     noise_std=std)
    for b, m in zip(batch, data):
        one = fit_conductivities(sphere_model, protocol, m, init=default_sigma(), noise_std=std)
        # Same iterations up to round-off in the batched linear algebra; the solver stops at
        # rtol 1e-6, so estimates agree to well below that.
        np.testing.assert_allclose(b.sigma, one.sigma, rtol=1e-6)
        np.testing.assert_allclose(b.std_error, one.std_error, rtol=1e-6)


def test_failure_is_data_with_throw_false(sphere_model, protocol):
    # Two steps cannot converge: with throw=False the status says so instead of raising.
    measured = np.asarray(simulate(sphere_model, TRUE, protocol))
    res = fit_conductivities(sphere_model, protocol, measured, init=default_sigma(), max_steps=2,
                             throw=False)
    assert res.result == optx.RESULTS.nonlinear_max_steps_reached and not res.success
    with pytest.raises(Exception, match="maximum number of steps"):
        fit_conductivities(sphere_model, protocol, measured, init=default_sigma(), max_steps=2)
