"""Derivatives of the forward model: AD (forward and reverse) vs the adjoint Jacobian vs FD.

Everything runs under `eqx.filter_jit`. Central differences in float64 with a relative step of
1e-4: truncation error O(h^2) ~ 1e-8 relative, round-off ~ (solve error 1e-12) / h ~ 1e-8, so
the AD results must agree to ~1e-6 relative (the issue's target). AD and the adjoint Jacobian
compute the same quantity by different routes (custom_linear_solve transposition vs bilinear
forms of solved fields), so they agree to round-off (1e-10).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxhead.fem.forward import build_forward_model, jacobian, simulate
from jaxhead.protocol import adjacent
from test_fem_assembly import small_model

SIGMA = jnp.array([0.3, 1.79, 0.018, 0.44])
N_ELEC = 6
FD_RTOL = 1e-6
STEP = 1e-4


@pytest.fixture(scope="module")
def setup():
    mesh, elec = small_model(h_mm=48.0, n_elec=N_ELEC)
    model = build_forward_model(mesh, elec)
    protocol = adjacent(N_ELEC, current_a=1e-3)
    w = jnp.asarray(np.random.default_rng(0).standard_normal(protocol.n_rows))
    return mesh, elec, model, protocol, w


def central(f, x, d):
    """Central difference of f along direction d with step STEP (relative to the scales)."""
    return (f(x + STEP * d) - f(x - STEP * d)) / (2 * STEP)


def test_tissue_sigma_grad_jacfwd_adjoint_fd(setup):
    mesh, elec, model, protocol, w = setup
    sim = eqx.filter_jit(lambda m, s: simulate(m, s, protocol))
    g = eqx.filter_jit(jax.grad(lambda m, s: w @ simulate(m, s, protocol), argnums=1))(
        model, SIGMA)
    Jf = eqx.filter_jit(jax.jacfwd(lambda m, s: simulate(m, s, protocol), argnums=1))(
        model, SIGMA)
    Ja = jacobian(model, SIGMA, protocol, per="tissue")
    scale = np.abs(np.asarray(Ja)).max()
    np.testing.assert_allclose(np.asarray(Jf), np.asarray(Ja), rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(np.asarray(g), np.asarray(w @ Ja), rtol=1e-10)
    for t in range(4):
        d = jnp.zeros(4).at[t].set(SIGMA[t])  # relative step in sigma_t
        fd = central(lambda s: sim(model, s), SIGMA, d) / SIGMA[t]
        np.testing.assert_allclose(np.asarray(Ja[:, t]), np.asarray(fd), rtol=0,
                                   atol=FD_RTOL * np.abs(np.asarray(fd)).max())
        assert float(g[t]) == pytest.approx(float(w @ fd), rel=FD_RTOL)


def test_tet_sigma_adjoint_equals_ad_and_fd(setup):
    mesh, elec, model, protocol, w = setup
    s_tet = SIGMA[jnp.asarray(mesh.labels) - 1]
    Ja = jacobian(model, s_tet, protocol)
    Jr = eqx.filter_jit(jax.jacrev(lambda m, s: simulate(m, s, protocol), argnums=1))(model, s_tet)
    scale = np.abs(Ja).max()
    np.testing.assert_allclose(np.asarray(Jr), Ja, rtol=0, atol=1e-10 * scale)
    # a random direction in per-tet conductivity, relative to each tet's value
    d = s_tet * jnp.asarray(np.random.default_rng(1).standard_normal(mesh.n_tets))
    sim = eqx.filter_jit(lambda m, s: simulate(m, s, protocol))
    fd = np.asarray(central(lambda s: sim(model, s), s_tet, d))
    np.testing.assert_allclose(Ja @ np.asarray(d), fd, rtol=0, atol=FD_RTOL * np.abs(fd).max())
    _, jv = eqx.filter_jit(lambda m, s, d: jax.jvp(lambda x: simulate(m, x, protocol), (s,),
                                                   (d,)))(model, s_tet, d)
    np.testing.assert_allclose(np.asarray(jv), fd, rtol=0, atol=FD_RTOL * np.abs(fd).max())


def test_contact_impedance_derivatives(setup):
    mesh, elec, model, protocol, w = setup
    z = jnp.asarray(elec.contact_impedance_ohm_m2)
    f = eqx.filter_jit(lambda m, z: simulate(m, SIGMA, protocol, contact_impedance_ohm_m2=z))
    Jz = eqx.filter_jit(jax.jacfwd(lambda m, z: simulate(m, SIGMA, protocol,
                                                         contact_impedance_ohm_m2=z), argnums=1))(
        model, z)
    g = eqx.filter_jit(jax.grad(lambda m, z: w @ simulate(m, SIGMA, protocol,
                                                         contact_impedance_ohm_m2=z), argnums=1))(
        model, z)
    np.testing.assert_allclose(np.asarray(g), np.asarray(w @ Jz), rtol=1e-10,
                               atol=1e-12 * float(jnp.abs(g).max()))
    for l in range(N_ELEC):
        d = jnp.zeros(N_ELEC).at[l].set(z[l])
        fd = np.asarray(central(lambda x: f(model, x), z, d)) / float(z[l])
        np.testing.assert_allclose(np.asarray(Jz[:, l]), fd, rtol=0,
                                   atol=FD_RTOL * np.abs(np.asarray(Jz)).max())


def test_node_position_derivatives(setup):
    mesh, elec, model, protocol, w = setup
    x0 = jnp.asarray(mesh.nodes)
    # a smooth displacement field, ~1 mm (tets are ~30 mm, so none inverts within the step)
    d = jnp.stack([jnp.sin(x0[:, 1] / 40.0), jnp.cos(x0[:, 2] / 30.0),
                   jnp.sin(x0[:, 0] / 50.0 + 1.0)], axis=1)
    f = eqx.filter_jit(lambda m, x: w @ simulate(m, SIGMA, protocol, nodes=x))
    g = eqx.filter_jit(jax.grad(lambda m, x: w @ simulate(m, SIGMA, protocol, nodes=x),
                                argnums=1))(model, x0)
    assert g.shape == x0.shape
    fd = float(central(lambda x: f(model, x), x0, d))
    assert float(jnp.sum(g * d)) == pytest.approx(fd, rel=FD_RTOL)
    _, jv = eqx.filter_jit(lambda m, x, d: jax.jvp(
        lambda y: w @ simulate(m, SIGMA, protocol, nodes=y), (x,), (d,)))(model, x0, d)
    assert float(jv) == pytest.approx(fd, rel=FD_RTOL)
    # translating the whole mesh changes nothing: the gradient sums to zero per axis
    np.testing.assert_allclose(np.asarray(g.sum(0)), 0.0, atol=1e-8 * float(jnp.abs(g).max()))
