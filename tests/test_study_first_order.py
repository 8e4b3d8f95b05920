"""First-order counterpart: host chain vs JAX AD vs FD; covariance vs a dense product; the
linearisation error falls as the amplitude squared; the second-order prediction's remainder as
its cube; measures' invariants on a small sphere."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_fem_assembly import small_model

from jaxhead.fem import build_forward_model, simulate
from jaxhead.protocol import adjacent
from jaxhead.study import (
    MeasureConfig,
    Reference,
    blob_data,
    build_morph,
    displacement_sensitivity,
    grf_covariance,
    measure,
    morph_nodes,
    first_order_summary,
    sample_grf,
    second_order_prediction,
    taylor_terms,
    voltage_covariance,
)
from jaxhead.tissue import Tissue

SIGMA = np.array([0.3, 1.79, 0.018, 0.44])


@pytest.fixture(scope="module")
def setup():
    mesh, elec = small_model(h_mm=24.0, n_elec=6)
    model = build_forward_model(mesh, elec)
    protocol = adjacent(6, current_a=1e-3)
    morph = build_morph(mesh)
    S = displacement_sensitivity(model, morph, SIGMA, protocol)
    return mesh, model, protocol, morph, S


def test_sensitivity_matches_ad_through_the_morph_and_fd(setup):
    mesh, model, protocol, morph, S = setup
    assert set(S) == {Tissue.BRAIN, Tissue.CSF, Tissue.SKULL, Tissue.SCALP}
    s = morph.interface("skull")
    f = eqx.filter_jit(lambda m, d: simulate(m, SIGMA, protocol,
                                             nodes=morph_nodes(morph, {"skull": d})))
    d0 = jnp.zeros(s.n_vertices)
    Jad = np.asarray(jax.jacrev(lambda d: f(model, d))(d0))
    np.testing.assert_allclose(S[Tissue.SKULL], Jad, rtol=0, atol=1e-9 * np.abs(Jad).max())
    e = np.random.default_rng(0).standard_normal(s.n_vertices)
    h = 1e-4
    fd = (np.asarray(f(model, h * e)) - np.asarray(f(model, -h * e))) / (2 * h)
    np.testing.assert_allclose(S[Tissue.SKULL] @ e, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


def test_voltage_covariance_equals_dense_product(setup):
    mesh, model, protocol, morph, S = setup
    s = morph.interface("csf")
    p = s.points(mesh.nodes)
    C = grf_covariance(p, 0.5, 15.0)
    dense = S[Tissue.CSF] @ C @ S[Tissue.CSF].T
    np.testing.assert_allclose(voltage_covariance(S[Tissue.CSF], p, 0.5, 15.0, block=7), dense,
                               rtol=1e-10, atol=1e-14 * np.abs(dense).max())


def test_first_order_rms_and_dof_match_monte_carlo(setup):
    """E||S d||^2 = trace(S C S^T) and Var ||S d||^2 = 2 trace((S C S^T)^2) over exact GRF draws
    (4000 Cholesky samples: the tolerances are 5 standard errors of the estimates)."""
    mesh, model, protocol, morph, S = setup
    s = morph.interface("csf")
    p = s.points(mesh.nodes)
    v = np.asarray(simulate(model, SIGMA, protocol))
    fo = first_order_summary(S[Tissue.CSF], p, 0.5, 15.0, v, np.ones_like(v))
    n = 4000
    q = np.sum((sample_grf(p, 0.5, 15.0, n_samples=n, seed=11, method="cholesky")
                @ S[Tissue.CSF].T) ** 2, axis=1)  # ||S d||^2 per draw
    ms = fo["rms_rel_voltage_change"] ** 2 * np.sum(v * v)  # predicted E||S d||^2
    dof = fo["effective_dof"]
    assert 1 <= dof <= len(v)
    rel_se = np.sqrt(2 / (n * dof))  # relative standard error of the mean of q
    assert q.mean() == pytest.approx(ms, rel=5 * rel_se)
    # variance 2 ms^2 / dof; its estimate's relative SE is at most sqrt(14 / n) (dof = 1,
    # chi^2_1: fourth central moment 60, variance 2, so (60 - 4) / (4 n))
    assert q.var(ddof=1) == pytest.approx(2 * ms**2 / dof, rel=5 * np.sqrt(14 / n))


def test_linearisation_error_is_second_order(setup):
    """||V(d) - V(0) - S d|| / ||S d|| ~ c sd: halving the amplitude halves the relative error."""
    mesh, model, protocol, morph, S = setup
    s = morph.interface("csf")
    z = sample_grf(s.points(mesh.nodes), 1.0, 25.0, seed=4)[0]
    f = eqx.filter_jit(lambda m, x: simulate(m, SIGMA, protocol, nodes=x))
    v0 = np.asarray(f(model, jnp.asarray(mesh.nodes)))
    amps = np.array([0.4, 0.2, 0.1])
    err = []
    for a in amps:
        dv = np.asarray(f(model, morph_nodes(morph, {"csf": a * z}))) - v0
        lin = S[Tissue.CSF] @ (a * z)
        err.append(np.linalg.norm(dv - lin) / np.linalg.norm(lin))
    slope = np.polyfit(np.log(amps), np.log(err), 1)[0]
    assert slope == pytest.approx(1.0, abs=0.15)


@pytest.fixture(scope="module")
def reference(setup):
    mesh, model, protocol, morph, S = setup
    return Reference(mesh, model, protocol, SIGMA, MeasureConfig(cell_mm=20.0))


def test_measures_of_the_reference_itself(reference):
    ref = reference
    blob = blob_data(ref.mesh, ref.model, ref.sigma, ref.protocol, ref.centre_mm, ref.cfg)
    m = measure(ref, ref.volts, blob)
    assert m["rel_voltage_change"] == 0 and m["voltage_change_over_noise"] == 0
    assert m["image_correlation"] == pytest.approx(1.0, abs=1e-12)
    assert m["localisation_error_mm"] == pytest.approx(ref.metrics.localisation_error_mm)
    for t in ("brain", "csf", "skull", "scalp"):
        assert abs(m[f"sigma_bias_percent_{t}"]) < 1e-3
        assert m[f"sigma_covered_{t}"] == 1.0


def test_change_over_noise_is_in_noise_units(reference):
    ref = reference
    light = Reference(ref.mesh, ref.model, ref.protocol, ref.sigma,
                      MeasureConfig(imaging=False, fit=False))
    m = measure(light, light.volts + 2.0 * light.noise_sd)
    assert m["voltage_change_over_noise"] == pytest.approx(2.0, rel=1e-12)
    assert m["rel_voltage_change"] == pytest.approx(
        2 * np.linalg.norm(light.noise_sd) / np.linalg.norm(light.volts), rel=1e-12)
    assert np.isnan(m["image_correlation"]) and np.isnan(m["sigma_bias_percent_skull"])


def test_fit_bias_of_a_scaled_skull_has_the_expected_sign(setup, reference):
    """A thicker skull (outer skull interface moved out by 1 mm) looks like a more resistive
    skull to the reference model: its fitted skull conductivity must come out lower."""
    mesh, model, protocol, morph, S = setup
    s = morph.interface("skull")
    x = morph_nodes(morph, {"skull": np.full(s.n_vertices, 1.0)})
    v = np.asarray(simulate(model, SIGMA, protocol, nodes=x))
    m = measure(reference, v, blob_data(mesh, model, SIGMA, protocol, reference.centre_mm,
                                        reference.cfg, nodes=x))
    assert m["sigma_bias_percent_skull"] < 0
    assert m["rel_voltage_change"] > 0


def test_node_gradients_by_reciprocity_equal_reverse_mode_ad(setup):
    """The reciprocity route (one solve per electrode pair) vs jax.jacrev of `simulate` in the
    node positions (one adjoint solve per row), with a drive/measurement sign mix."""
    from jaxhead.protocol import Protocol
    from jaxhead.study import node_gradients

    mesh, model, protocol, morph, S = setup
    prot = Protocol(np.array([[0, 3, 1, 2], [3, 0, 5, 4], [2, 1, 0, 5], [5, 1, 3, 2]]),
                    current_a=1e-3)
    G = node_gradients(model, SIGMA, prot, chunk_rows=3)
    f = eqx.filter_jit(lambda m, x: simulate(m, SIGMA, prot, nodes=x))
    Jad = np.asarray(jax.jacrev(lambda x: f(model, x))(jnp.asarray(mesh.nodes)))
    assert G.shape == Jad.shape == (4, mesh.n_nodes, 3)
    np.testing.assert_allclose(G, Jad, rtol=0, atol=1e-8 * np.abs(Jad).max())


@pytest.fixture(scope="module")
def morph_route(setup):
    """The csf interface's morph-route voltages V(h z) of one unit GRF field z."""
    mesh, model, protocol, morph, S = setup
    s = morph.interface("csf")
    z = sample_grf(s.points(mesh.nodes), 1.0, 25.0, seed=4)[0]
    f = eqx.filter_jit(lambda m, x: simulate(m, SIGMA, protocol, nodes=x))
    return z, lambda d: np.asarray(f(model, morph_nodes(morph, {"csf": d})))


def test_second_order_remainder_is_third_order(setup, morph_route):
    """||dV - (S d + 1/2 D2V[dx, dx])|| falls as h^3 (the first-order remainder as h^2), and
    the first term is S d."""
    mesh, model, protocol, morph, S = setup
    z, V = morph_route
    v0 = V(np.zeros_like(z))
    hs = np.array([0.4, 0.2, 0.1, 0.05])
    r1, r2 = [], []
    for h in hs:
        dv = V(h * z) - v0
        p = second_order_prediction(model, morph, SIGMA, protocol, h * z, "csf")
        np.testing.assert_allclose(p["first"], S[Tissue.CSF] @ (h * z), rtol=0,
                                   atol=1e-9 * np.abs(p["first"]).max())
        np.testing.assert_allclose(p["prediction"], p["first"] + p["second"], rtol=1e-14)
        r1.append(np.linalg.norm(dv - p["first"]))
        r2.append(np.linalg.norm(dv - p["prediction"]))
    slope1 = np.polyfit(np.log(hs), np.log(r1), 1)[0]
    slope2 = np.polyfit(np.log(hs), np.log(r2), 1)[0]
    assert slope1 == pytest.approx(2.0, abs=0.1)
    assert slope2 == pytest.approx(3.0, abs=0.1)
    assert r2[-1] < 1e-2 * r1[-1]  # the second-order term carries almost all of the remainder


def test_second_derivative_matches_central_differences(setup, morph_route):
    """D2V[dx, dx] vs (V(h z) + V(-h z) - 2 V(0)) / h^2 (truncation O(h^2), h = 1e-2 mm)."""
    mesh, model, protocol, morph, S = setup
    z, V = morph_route
    h = 1e-2
    fd = (V(h * z) + V(-h * z) - 2 * V(np.zeros_like(z))) / h**2
    p = second_order_prediction(model, morph, SIGMA, protocol, z, "csf")
    np.testing.assert_allclose(2 * p["second"], fd, rtol=0, atol=1e-5 * np.abs(fd).max())


def test_second_order_term_is_even_and_zero_at_zero(setup, morph_route):
    mesh, model, protocol, morph, S = setup
    z, _ = morph_route
    zero = second_order_prediction(model, morph, SIGMA, protocol, np.zeros_like(z), "csf")
    assert all(np.all(v == 0) for v in zero.values())
    p, m = (second_order_prediction(model, morph, SIGMA, protocol, s * z, "csf")
            for s in (0.3, -0.3))
    scale = np.abs(p["second"]).max()
    assert scale > 0
    np.testing.assert_allclose(m["second"], p["second"], rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(m["first"], -p["first"], rtol=0,
                               atol=1e-12 * np.abs(p["first"]).max())
    # homogeneous of degree 2: doubling d quadruples the term (to the rounding of
    # dx = x(d) - x0, eps |x0| / |dx| ~ 1e-13 relative, squared into the term)
    q = second_order_prediction(model, morph, SIGMA, protocol, 0.6 * z, "csf")
    np.testing.assert_allclose(q["second"], 4 * p["second"], rtol=0, atol=1e-9 * scale)


def test_taylor_terms_bad_input(setup):
    mesh, model, protocol, morph, S = setup
    with pytest.raises(ValueError, match="dx.*shape"):
        taylor_terms(model, SIGMA, protocol, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        taylor_terms(model, SIGMA, protocol, np.full((mesh.n_nodes, 3), np.nan))
