"""The morph route and surface GRFs: analytic sphere morphs, identity, transposes and FD derivatives."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sphere_mesh import RADII_MM, structured_sphere_mesh
from test_fem_assembly import small_model

from jaxhead.fem import build_forward_model, simulate
from jaxhead.protocol import adjacent
from jaxhead.study import (
    MorphError,
    build_morph,
    grf_covariance,
    interface_surfaces,
    laplacian,
    morph_nodes,
    morph_quality,
    sample_grf,
)


@pytest.fixture(scope="module")
def sphere():
    mesh = structured_sphere_mesh(h_mm=8.0)
    return mesh, build_morph(mesh)


def test_laplacian_invariants(sphere):
    mesh, _ = sphere
    K = laplacian(mesh.nodes, mesh.tets)
    n = mesh.n_nodes
    assert abs(K - K.T).max() < 1e-12 * abs(K).max()
    np.testing.assert_allclose(K @ np.ones(n), 0.0, atol=1e-10 * abs(K).max())
    # a linear field has zero Laplacian at interior nodes (P1 reproduces linears exactly)
    lin = mesh.nodes @ np.array([0.3, -1.2, 0.7])
    interior = np.setdiff1d(np.arange(n), mesh.surface_nodes())
    np.testing.assert_allclose((K @ lin)[interior], 0.0, atol=1e-9 * abs(K).max() * 100)
    # energy of a linear field g.x is |g|^2 times the mesh volume
    g = np.array([0.3, -1.2, 0.7])
    assert lin @ K @ lin == pytest.approx(g @ g * mesh.tet_volumes().sum(), rel=1e-10)


def test_interfaces_of_spheres_lie_on_their_spheres(sphere):
    mesh, morph = sphere
    surf = interface_surfaces(mesh)
    assert [int(t) for t in surf] == [1, 2, 3, 4]
    for t, r in zip(surf, RADII_MM):
        p = surf[t].points(mesh.nodes)
        np.testing.assert_allclose(np.linalg.norm(p, axis=1), r, rtol=1e-12)
        # outward: normals point away from the centre; areas sum to the polyhedron's area
        assert np.all(np.einsum("ij,ij->i", surf[t].normals, p) > 0)
        assert surf[t].areas_mm2.sum() == pytest.approx(4 * np.pi * r**2, rel=0.02)


def test_zero_displacement_is_identity(sphere):
    mesh, morph = sphere
    s = morph.interface("csf")
    x = morph_nodes(morph, {"csf": np.zeros(s.n_vertices)})
    np.testing.assert_array_equal(np.asarray(x), mesh.nodes)
    x = morph_nodes(morph, {})
    np.testing.assert_array_equal(np.asarray(x), mesh.nodes)


@pytest.mark.parametrize("h_mm", [8.0, 4.0])
def test_constant_normal_displacement_scales_the_sphere(h_mm):
    """Brain sphere r -> r + c: vertex radii and the brain's volume match the analytic values.

    The vertex normals of an inscribed polyhedron deviate from the radial direction by
    O(h / r), so |x + c n| = r + c - O(c (h / r)^2); the brain volume ratio follows
    ((r + c) / r)^3 to the same order. Tolerances: 2 (h / r)^2 relative to c.
    """
    mesh = structured_sphere_mesh(h_mm=h_mm)
    morph = build_morph(mesh)
    r, c = RADII_MM[0], 1.5
    s = morph.interface("brain")
    x = np.asarray(morph_nodes(morph, {"brain": np.full(s.n_vertices, c)}))
    radius = np.linalg.norm(x[s.vertices], axis=1)
    tol = 2 * (h_mm / r) ** 2 * c
    np.testing.assert_allclose(radius, r + c, atol=tol)
    q = morph_quality(morph, x)
    assert q.n_inverted == 0 and q.max_displacement_mm == pytest.approx(c, rel=1e-12)
    vol = lambda nodes: np.sum(  # noqa: E731
        np.einsum("ij,ij->i", np.cross(*(nodes[mesh.tets[:, k]] - nodes[mesh.tets[:, 0]]
                                         for k in (1, 2)), axis=1),
                  nodes[mesh.tets[:, 3]] - nodes[mesh.tets[:, 0]])[mesh.labels == 1]) / 6
    ratio = vol(x) / vol(mesh.nodes)
    assert ratio == pytest.approx(((r + c) / r) ** 3, abs=3 * tol / r)
    # total volume is unchanged (only an inner interface moved)
    assert mesh.tet_volumes().sum() == pytest.approx(
        float(np.sum(np.abs(np.asarray(jnp.linalg.det(jnp.asarray(
            x[mesh.tets[:, 1:]] - x[mesh.tets[:, :1]]))))) / 6), rel=1e-12)


def test_large_displacement_inverts_and_is_an_error(sphere):
    mesh, morph = sphere
    s = morph.interface("brain")
    x = morph_nodes(morph, {"brain": np.full(s.n_vertices, 6.0)})  # CSF is 4 mm thick
    with pytest.raises(MorphError, match="inverts"):
        morph_quality(morph, x)


def test_bad_displacement_shape_names_the_interface(sphere):
    _, morph = sphere
    with pytest.raises(ValueError, match="skull interface"):
        morph_nodes(morph, {"skull": np.zeros(3)})
    with pytest.raises(ValueError, match="background|tissue"):
        morph_nodes(morph, {"bone": np.zeros(3)})


def test_extension_vjp_is_the_transpose(sphere):
    _, morph = sphere
    rng = np.random.default_rng(1)
    ext = morph.extension
    a = rng.standard_normal((ext.n_fixed, 3))
    b = rng.standard_normal((ext.n_free, 3))
    assert np.sum(ext.apply(a) * b) == pytest.approx(np.sum(a * ext.transpose(b)), rel=1e-10)
    s = morph.interface("skull")
    d = jnp.asarray(rng.standard_normal(s.n_vertices))
    w = jnp.asarray(rng.standard_normal((morph.nodes.shape[0], 3)))
    f = lambda dd: jnp.sum(w * morph_nodes(morph, {"skull": dd}))  # noqa: E731 (linear in d)
    g = jax.grad(f)(d)
    e = jnp.asarray(rng.standard_normal(s.n_vertices))
    assert float(g @ e) == pytest.approx(float(f(e) - f(0 * e)), rel=1e-10)


def test_voltage_gradient_wrt_displacement_matches_finite_differences():
    mesh, elec = small_model(h_mm=24.0, n_elec=6)
    model = build_forward_model(mesh, elec)
    protocol = adjacent(6, current_a=1e-3)
    morph = build_morph(mesh)
    s = morph.interface("csf")
    rng = np.random.default_rng(0)
    w = jnp.asarray(rng.standard_normal(protocol.n_rows))
    sigma = jnp.array([0.3, 1.79, 0.018, 0.44])
    f = eqx.filter_jit(lambda m, d: w @ simulate(m, sigma, protocol,
                                                 nodes=morph_nodes(morph, {"csf": d})))
    d0 = jnp.asarray(0.3 * rng.standard_normal(s.n_vertices))
    g = jax.grad(lambda d: f(model, d))(d0)
    e = jnp.asarray(rng.standard_normal(s.n_vertices))
    h = 1e-4  # mm: central differences, truncation O(h^2), round-off ~1e-12 / h
    fd = (f(model, d0 + h * e) - f(model, d0 - h * e)) / (2 * h)
    assert float(g @ e) == pytest.approx(float(fd), rel=1e-6)


# --- GRF -----------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["cholesky", "fourier"])
def test_grf_sample_covariance_matches_the_kernel(method):
    """Sample covariance of n samples: each entry's sd is <= sd^2 sqrt(2 / n); check 5 sd."""
    rng = np.random.default_rng(3)
    p = rng.uniform(-30, 30, (40, 3))
    sd, ell, n = 0.7, 20.0, 4000
    z = sample_grf(p, sd, ell, n_samples=n, seed=5, method=method, n_features=500)
    C = grf_covariance(p, sd, ell)
    S = z.T @ z / n
    assert np.abs(S - C).max() < 5 * sd**2 * np.sqrt(2 / n)
    np.testing.assert_allclose(z.mean(0), 0, atol=5 * sd / np.sqrt(n))


def test_grf_seeded_zero_amplitude_and_bad_input():
    p = np.random.default_rng(0).uniform(-10, 10, (10, 3))
    np.testing.assert_array_equal(sample_grf(p, 1.0, 5.0, seed=2), sample_grf(p, 1.0, 5.0, seed=2))
    assert not np.array_equal(sample_grf(p, 1.0, 5.0, seed=2), sample_grf(p, 1.0, 5.0, seed=3))
    np.testing.assert_array_equal(sample_grf(p, 0.0, 5.0), 0.0)
    with pytest.raises(ValueError, match="sd_mm.*-1"):
        sample_grf(p, -1.0, 5.0)
    with pytest.raises(ValueError, match="correlation_mm"):
        sample_grf(p, 1.0, 0.0)


def test_grf_correlation_length_sets_smoothness():
    """Neighbour correlation of samples: exp(-d^2 / 2 l^2) for points a distance d apart."""
    p = np.array([[0.0, 0, 0], [5.0, 0, 0]])
    z = sample_grf(p, 1.0, 10.0, n_samples=20000, seed=1)
    assert np.corrcoef(z.T)[0, 1] == pytest.approx(np.exp(-25 / 200), abs=0.02)
