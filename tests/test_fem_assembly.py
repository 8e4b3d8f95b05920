"""FEM assembly against a dense per-element loop, and its invariants.

The reference re-derives every term independently: P1 gradients from the inverse of the 4x4
matrix [1, x, y, z] of each tet (not the cross-product formula the library uses), boundary
integrals with the edge-midpoint quadrature rule (exact for the quadratic phi_a phi_b), and the
CEM blocks written out from Vauhkonen et al. (1999) into a dense matrix of all unknowns.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxhead.electrodes import place_electrodes
from jaxhead.fem.assembly import (MM_TO_M, TET_PAIRS, Pattern, face_areas, face_mass,
                                  scatter_add, scatter_plan, tet_stiffness)
from jaxhead.fem.forward import assemble, build_forward_model
from sphere_mesh import structured_sphere_mesh

# Round-off bound for sums of O(10..100) float64 terms of similar size: ~1e-13 relative.
RTOL = 1e-11


def small_model(h_mm=32.0, n_elec=6, z=0.02, seed=0):
    """A coarse 4-shell ball (radius 96 mm) with `n_elec` electrodes of radius 20 mm."""
    mesh = structured_sphere_mesh(h_mm=h_mm)
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, n_elec, endpoint=False)
    pos = np.stack([np.cos(t), np.sin(t), 0.5 + 0.1 * rng.standard_normal(n_elec)], 1)
    pos = 96.0 * pos / np.linalg.norm(pos, axis=1, keepdims=True)
    zs = z * (1.0 + 0.5 * rng.random(n_elec))  # distinct impedances catch index mix-ups
    elec = place_electrodes(mesh, pos, radius_mm=20.0, contact_impedance_ohm_m2=zs)
    return mesh, elec


def dense_reference(mesh, elec, sigma_tet):
    """The full (ungrounded) CEM matrix of nodes + electrodes by a per-element loop (SI)."""
    x = mesh.nodes * 1e-3
    n, L = mesh.n_nodes, elec.contact_impedance_ohm_m2.shape[0]
    A = np.zeros((n + L, n + L))
    for t, tet in enumerate(mesh.tets):
        M = np.hstack([np.ones((4, 1)), x[tet]])
        G = np.linalg.inv(M)[1:]  # rows: d phi_a / dx, dy, dz for a = 0..3
        vol = abs(np.linalg.det(M)) / 6.0
        A[np.ix_(tet, tet)] += sigma_tet[t] * vol * G.T @ G
    for f, l in zip(elec.faces, elec.face_electrode):
        p = x[f]
        area = 0.5 * np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]))
        # edge-midpoint rule: phi values at the three midpoints, weights area / 3
        mids = np.array([[0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]])
        mass = area / 3.0 * mids.T @ mids
        lin = area / 3.0 * mids.sum(0)
        z = elec.contact_impedance_ohm_m2[l]
        A[np.ix_(f, f)] += mass / z
        A[f, n + l] -= lin / z
        A[n + l, f] -= lin / z
        A[n + l, n + l] += area / z
    return A


@pytest.fixture(scope="module")
def mesh_elec():
    return small_model()


@pytest.fixture(scope="module")
def model(mesh_elec):
    return build_forward_model(*mesh_elec)


def test_matches_dense_loop_grounded(mesh_elec, model):
    mesh, elec = mesh_elec
    rng = np.random.default_rng(1)
    sigma = 0.1 + rng.random(mesh.n_tets)  # per-tet values exercise the scatter fully
    values = np.asarray(assemble(model, sigma))
    ref = dense_reference(mesh, elec, sigma)
    # Grounding: the last electrode's row and column are dropped (jaxhead.fem.cem).
    n = model.n_unknowns
    got = np.zeros((n, n))
    full = model.pattern
    got[np.asarray(full.rows), np.asarray(full.cols)] = values[np.asarray(full.to_upper)]
    # entries outside the library's pattern are zero in `got`, so this also checks the pattern
    np.testing.assert_allclose(got, ref[:n, :n], rtol=RTOL, atol=RTOL * np.abs(ref).max())


def test_tissue_sigma_equals_per_tet(mesh_elec, model):
    mesh, elec = mesh_elec
    s4 = np.array([0.3, 1.79, 0.018, 0.44])
    # per tissue: sum_t sigma_t K_t from precomputed K_t; per tet: the element loop. Same sums
    # in another order: equal to round-off.
    a, b = np.asarray(assemble(model, s4)), np.asarray(assemble(model, s4[mesh.labels - 1]))
    np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15 * np.abs(b).max())


def test_stiffness_annihilates_constants_and_is_psd(mesh_elec):
    mesh, _ = mesh_elec
    x = jnp.asarray(mesh.nodes) * MM_TO_M
    k = tet_stiffness(x, jnp.asarray(mesh.tets))
    i, j = mesh.tets[:, TET_PAIRS[:, 0]].ravel(), mesh.tets[:, TET_PAIRS[:, 1]].ravel()
    pattern = Pattern(mesh.n_nodes, i, j)
    order, targets = scatter_plan(pattern.locate(i, j), pattern.nnz)
    K = pattern.to_scipy(scatter_add(k.ravel(), order, targets, pattern.nnz))
    # K 1 = 0 (constants have no gradient), relative to the row scale
    assert np.abs(K @ np.ones(mesh.n_nodes)).max() < 1e-12 * np.abs(K.diagonal()).max()
    # x^T K x = int |grad x|^2 = volume for the linear field x (exact for P1)
    vol = mesh.tet_volumes().sum() * MM_TO_M**3
    for axis in range(3):
        u = mesh.nodes[:, axis] * MM_TO_M
        assert u @ (K @ u) == pytest.approx(vol, rel=1e-12)


def test_boundary_mass_sums_to_electrode_area(mesh_elec, model):
    mesh, elec = mesh_elec
    x = jnp.asarray(mesh.nodes) * MM_TO_M
    areas_m2 = np.asarray(face_areas(x, jnp.asarray(elec.faces)))
    mass = np.asarray(face_mass(jnp.asarray(areas_m2)))
    # each face's 3x3 mass matrix sums to its area: 3 diagonal + 2 x 3 off-diagonal entries
    full_sum = mass[:, [0, 3, 5]].sum(1) + 2 * mass[:, [1, 2, 4]].sum(1)
    np.testing.assert_allclose(full_sum, areas_m2, rtol=1e-14)
    per_elec = np.bincount(elec.face_electrode, weights=areas_m2)
    np.testing.assert_allclose(per_elec, elec.area_mm2(mesh.nodes) * MM_TO_M**2, rtol=1e-12)
    # and in the assembled CEM blocks: A_D[l, l] z_l = |e_l| = -sum_i A_Z[i, l] z_l
    A = model.pattern  # full pattern of the grounded matrix
    values = np.asarray(assemble(model, np.full(4, 0.3)))
    full = np.zeros((model.n_unknowns, model.n_unknowns))
    full[np.asarray(A.rows), np.asarray(A.cols)] = values[np.asarray(A.to_upper)]
    z = elec.contact_impedance_ohm_m2
    n = mesh.n_nodes
    for l in range(model.n_elec - 1):
        assert full[n + l, n + l] * z[l] == pytest.approx(per_elec[l], rel=1e-12)
        assert -full[:n, n + l].sum() * z[l] == pytest.approx(per_elec[l], rel=1e-12)


def test_full_cem_matrix_annihilates_constants(mesh_elec):
    mesh, elec = mesh_elec
    A = dense_reference(mesh, elec, np.full(mesh.n_tets, 0.44))
    assert np.abs(A @ np.ones(A.shape[0])).max() < 1e-12 * np.abs(A).max()


def test_units_are_si(mesh_elec):
    """Scaling a mesh by c scales P1 stiffness by c (it is length-linear in 3D) and areas by c^2."""
    mesh, _ = mesh_elec
    x = jnp.asarray(mesh.nodes) * MM_TO_M
    tets = jnp.asarray(mesh.tets)
    k1, k2 = tet_stiffness(x, tets), tet_stiffness(2 * x, tets)
    np.testing.assert_allclose(np.asarray(k2), 2 * np.asarray(k1), rtol=1e-12)
    # a unit cube's worth of stiffness: a regular corner tet of edge 1 mm -> 1e-3 m
    corner = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * MM_TO_M
    kc = tet_stiffness(corner, jnp.array([[0, 1, 2, 3]]))
    # K_00 = V |grad phi_0|^2 = (1/6 mm^3)(3 / mm^2) = 0.5 mm = 5e-4 m
    assert float(kc[0, 0]) == pytest.approx(5e-4, rel=1e-14)


def test_assemble_jit_and_pattern_errors(model):
    s = jnp.array([0.3, 1.79, 0.018, 0.44])
    f = jax.jit(lambda m, s: assemble(m, s))
    # Bitwise on CPU; on a GPU the scatter-add's summation order differs between jitted and
    # eager code (atomics), so allow float64 round-off.
    np.testing.assert_allclose(np.asarray(f(model, s)), np.asarray(assemble(model, s)),
                               rtol=1e-13, atol=1e-20)
    p = Pattern(4, np.array([0, 1, 2, 3, 0]), np.array([0, 1, 2, 3, 1]))
    with pytest.raises(ValueError, match="outside the sparsity pattern"):
        p.locate(np.array([0]), np.array([3]))
    with pytest.raises(ValueError, match="empty row"):
        Pattern(3, np.array([0, 1]), np.array([0, 1]))
