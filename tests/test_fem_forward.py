"""Forward model: complete-electrode-model invariants, reciprocity, scaling, grounding, errors.

Invariants and their sources:
- Electrode equation of the CEM (Somersalo, Cheney & Isaacson 1992; Vauhkonen et al. 1999):
  I_l = (1/z_l) int_{e_l} (U_l - u) dS, i.e. U_l = mean_{e_l} u + z_l I_l / |e_l|; a
  non-driving electrode reports exactly the mean of u over its area. Summing over l gives
  sum_l I_l = 0 (Kirchhoff).
- The whole ungrounded system [[A_M, A_Z], [A_Z^T, A_D]] [u; U] = [0; I], with the matrix from
  the dense reference of test_fem_assembly.
- Reciprocity of transfer impedances (Geselowitz 1971): V(drive ab, measure cd) =
  V(drive cd, measure ab), for any (even per-tet, random) conductivity.
- Scaling: sigma -> c sigma with z -> z / c multiplies the matrix by c, so voltages / c.
- Ground independence: renumbering the electrodes (so another one is grounded) leaves every
  measured voltage unchanged.
Tolerances: these identities are exact; the direct solve of matrices with condition ~1e7
leaves ~1e-9 relative error, so 1e-8 relative is used.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxhead.electrodes import Electrodes
from jaxhead.fem.forward import build_forward_model, jacobian, potentials, simulate
from jaxhead.protocol import Protocol, adjacent
from conftest import fem_solvers
from test_fem_assembly import dense_reference, small_model

SIGMA = np.array([0.3, 1.79, 0.018, 0.44])
N_ELEC = 8
RTOL = 1e-8


@pytest.fixture(scope="module")
def mesh_elec():
    return small_model(h_mm=32.0, n_elec=N_ELEC)


@pytest.fixture(scope="module")
def model(mesh_elec):
    return build_forward_model(*mesh_elec)


@pytest.fixture(scope="module")
def protocol():
    return adjacent(N_ELEC, current_a=1e-3)


def _face_means(mesh, elec, u):
    """int_{e_l} u dS / |e_l| for P1 u (exact: the face integral is area * mean of its nodes)."""
    p = mesh.nodes[elec.faces] * 1e-3
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    integral = np.bincount(elec.face_electrode, weights=area * u[elec.faces].mean(1))
    total = np.bincount(elec.face_electrode, weights=area)
    return integral / total, total


def test_electrode_equation_and_kirchhoff(mesh_elec, model):
    mesh, elec = mesh_elec
    inj = np.array([[0, 4], [1, 2], [7, 3]])
    current = 2e-3
    u, U = map(np.asarray, potentials(model, SIGMA, inj, current_a=current))
    for k, (s, t) in enumerate(inj):
        I = np.zeros(N_ELEC)
        I[s], I[t] = current, -current
        mean_u, area = _face_means(mesh, elec, u[k])
        z = elec.contact_impedance_ohm_m2
        # U_l = mean u + z_l I_l / |e_l|: exact for every electrode, the ground included
        np.testing.assert_allclose(U[k], mean_u + z * I / area, rtol=0,
                                   atol=RTOL * np.abs(U[k]).max())
        # the currents recovered from the fields sum to zero and are the injected ones
        I_rec = area * (U[k] - mean_u) / z
        np.testing.assert_allclose(I_rec, I, rtol=0, atol=RTOL * current)
        assert abs(I_rec.sum()) < RTOL * current
        # reference convention: electrode voltages sum to zero
        assert abs(U[k].sum()) < RTOL * np.abs(U[k]).max()


def test_solution_solves_the_full_ungrounded_system(mesh_elec, model):
    mesh, elec = mesh_elec
    sigma_tet = SIGMA[mesh.labels - 1]
    A = dense_reference(mesh, elec, sigma_tet)
    u, U = map(np.asarray, potentials(model, SIGMA, np.array([[2, 6]]), current_a=1e-3))
    x = np.concatenate([u[0], U[0]])
    rhs = np.zeros_like(x)
    rhs[mesh.n_nodes + 2], rhs[mesh.n_nodes + 6] = 1e-3, -1e-3
    np.testing.assert_allclose(A @ x, rhs, rtol=0, atol=RTOL * np.abs(A).max() * np.abs(x).max())


def test_reciprocity(model, mesh_elec):
    mesh, _ = mesh_elec
    sigma = 0.05 + np.random.default_rng(3).random(mesh.n_tets)  # anisotropy-free but random
    rows = np.array([[0, 3, 5, 6], [1, 5, 2, 7], [4, 6, 0, 1]])
    swapped = rows[:, [2, 3, 0, 1]]
    v = np.asarray(simulate(model, sigma, Protocol(rows, 1e-3)))
    w = np.asarray(simulate(model, sigma, Protocol(swapped, 1e-3)))
    np.testing.assert_allclose(v, w, rtol=RTOL)


def test_scaling_with_conductivity_and_current(model, mesh_elec, protocol):
    _, elec = mesh_elec
    z = elec.contact_impedance_ohm_m2
    v = np.asarray(simulate(model, SIGMA, protocol))
    c = 3.7
    vc = np.asarray(simulate(model, c * SIGMA, protocol, contact_impedance_ohm_m2=z / c))
    np.testing.assert_allclose(vc, v / c, rtol=RTOL, atol=RTOL * np.abs(v).max())
    v2 = np.asarray(simulate(model, SIGMA, Protocol(protocol.rows, 2 * protocol.current_a)))
    np.testing.assert_allclose(v2, 2 * v, rtol=RTOL, atol=RTOL * np.abs(v).max())
    # per-tissue and the equivalent per-tet conductivity are the same model
    mesh = mesh_elec[0]
    vt = np.asarray(simulate(model, SIGMA[mesh.labels - 1], protocol))
    np.testing.assert_allclose(vt, v, rtol=1e-12, atol=1e-12 * np.abs(v).max())


def test_ground_independence(mesh_elec, model, protocol):
    """Renumber the electrodes in reverse: the grounded (last) electrode changes."""
    mesh, elec = mesh_elec
    perm = np.arange(N_ELEC)[::-1]  # new index i is old electrode perm[i]
    inv = np.argsort(perm)
    flipped = Electrodes(centres=elec.centres[perm], faces=elec.faces,
                         face_electrode=inv[elec.face_electrode],
                         contact_impedance_ohm_m2=elec.contact_impedance_ohm_m2[perm])
    model2 = build_forward_model(mesh, flipped)
    v = np.asarray(simulate(model, SIGMA, protocol))
    v2 = np.asarray(simulate(model2, SIGMA, Protocol(inv[protocol.rows], protocol.current_a)))
    np.testing.assert_allclose(v2, v, rtol=RTOL, atol=RTOL * np.abs(v).max())


def test_potentials_match_simulate(model, protocol):
    pairs = protocol.rows[:, :2]
    u, U = potentials(model, SIGMA, pairs, current_a=protocol.current_a)
    r = protocol.rows
    v = np.asarray(U)[np.arange(len(r)), r[:, 2]] - np.asarray(U)[np.arange(len(r)), r[:, 3]]
    np.testing.assert_allclose(np.asarray(simulate(model, SIGMA, protocol)), v, rtol=1e-12,
                               atol=1e-15)
    # current patterns give the same fields as the pairs
    pat = np.zeros((N_ELEC, 1))
    pat[r[0, 0]], pat[r[0, 1]] = 1.0, -1.0
    u1, _ = potentials(model, SIGMA, pat, current_a=protocol.current_a)
    np.testing.assert_allclose(np.asarray(u1[0]), np.asarray(u[0]), rtol=1e-12, atol=1e-15)


def test_jit_equals_eager_and_traced_protocol(model, protocol):
    v = simulate(model, SIGMA, protocol)
    f = eqx.filter_jit(lambda m, s: simulate(m, s, protocol))
    # float64 round-off only (GPU scatter-adds sum in a different order under jit)
    np.testing.assert_allclose(np.asarray(f(model, jnp.asarray(SIGMA))), np.asarray(v),
                               rtol=1e-12, atol=1e-18)
    # rows traced: the electrode-basis path, same voltages
    g = eqx.filter_jit(simulate)
    np.testing.assert_allclose(np.asarray(g(model, jnp.asarray(SIGMA), protocol)),
                               np.asarray(v), rtol=1e-10, atol=1e-12 * float(jnp.abs(v).max()))
    # vmap over conductivities
    sig = jnp.stack([jnp.asarray(SIGMA), 2 * jnp.asarray(SIGMA)])
    vv = jax.vmap(lambda s: simulate(model, s, protocol))(sig)
    np.testing.assert_allclose(np.asarray(vv[0]), np.asarray(v), rtol=1e-12, atol=1e-15)


def test_jacobian_storage_options(model, protocol):
    J = jacobian(model, SIGMA, protocol, tile_tets=1000)
    assert isinstance(J, np.ndarray) and J.shape == (protocol.n_rows, model.n_tets)
    Jj = jacobian(model, jnp.asarray(SIGMA), protocol, tile_tets=1000)  # JAX in, JAX out
    assert isinstance(Jj, jax.Array)
    np.testing.assert_allclose(np.asarray(Jj), J, rtol=1e-12, atol=1e-13 * np.abs(J).max())
    J32 = jacobian(model, SIGMA, protocol, dtype=jnp.float32, tile_tets=1000)
    assert J32.dtype == np.float32
    np.testing.assert_allclose(J32, J, rtol=1e-6, atol=1e-6 * np.abs(J).max())
    out = np.zeros_like(J)
    J2 = jacobian(model, SIGMA, protocol, out=out, tile_tets=3500)  # a partial last tile
    assert J2 is out
    np.testing.assert_allclose(J2, J, rtol=1e-13, atol=1e-16)
    Jjit = eqx.filter_jit(lambda m, s: jacobian(m, s, protocol, tile_tets=1000))(
        model, jnp.asarray(SIGMA))
    # atol: entries 1e4 x below the largest come from cancelling products (float64 round-off
    # ~1e-16 x max; the summation order of jitted and eager code differs on GPUs)
    np.testing.assert_allclose(np.asarray(Jjit), J, rtol=1e-12, atol=1e-13 * np.abs(J).max())
    # the per-tissue sensitivity is the sum over each tissue's tets
    Jt, volts = jacobian(model, SIGMA, protocol, per="tissue", return_volts=True)
    labels = np.asarray(model.labels)
    ref = np.stack([J[:, labels == t].sum(1) for t in (1, 2, 3, 4)], axis=1)
    np.testing.assert_allclose(np.asarray(Jt), ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
    np.testing.assert_allclose(np.asarray(volts), np.asarray(simulate(model, SIGMA, protocol)),
                               rtol=1e-12, atol=1e-15)


def test_bad_inputs_raise(model, protocol, mesh_elec):
    mesh, elec = mesh_elec
    with pytest.raises(ValueError, match="sigma.*> 0"):
        simulate(model, -SIGMA, protocol)
    with pytest.raises(ValueError, match="sigma.*shape"):
        simulate(model, np.ones(3), protocol)
    with pytest.raises(ValueError, match="protocol.rows.*electrodes"):
        simulate(model, SIGMA, Protocol(np.array([[0, 1, 2, N_ELEC]]), 1e-3))
    with pytest.raises(ValueError, match="nodes.*shape"):
        simulate(model, SIGMA, protocol, nodes=mesh.nodes[:-1])
    with pytest.raises(ValueError, match="contact_impedance_ohm_m2"):
        simulate(model, SIGMA, protocol, contact_impedance_ohm_m2=-np.ones(N_ELEC))
    with pytest.raises(ValueError, match="contact_impedance_ohm_m2.*shape"):
        simulate(model, SIGMA, protocol, contact_impedance_ohm_m2=np.ones(3))
    with pytest.raises(ValueError, match="injections"):
        potentials(model, SIGMA, np.array([[0, 0]]))
    with pytest.raises(ValueError, match="sum to zero"):
        potentials(model, SIGMA, np.ones((N_ELEC, 1)))
    with pytest.raises(ValueError, match="per"):
        jacobian(model, SIGMA, protocol, per="node")
    with pytest.raises(ValueError, match="protocol"):
        simulate(model, SIGMA, np.zeros((3, 4), int))
    bad_faces = Electrodes(centres=elec.centres, faces=mesh.tets[:len(elec.faces), :3],
                           face_electrode=elec.face_electrode,
                           contact_impedance_ohm_m2=elec.contact_impedance_ohm_m2)
    with pytest.raises(ValueError, match="outer boundary"):
        build_forward_model(mesh, bad_faces)
    # traced values: checked inside jit
    f = eqx.filter_jit(lambda m, s: simulate(m, s, protocol))
    with pytest.raises(Exception, match="sigma"):
        jax.block_until_ready(f(model, -jnp.asarray(SIGMA)))
    flat = mesh.nodes.copy()
    flat[:, 2] = 0.0  # every tet flattened
    with pytest.raises(Exception, match="volume"):
        jax.block_until_ready(eqx.filter_jit(
            lambda m, x: simulate(m, SIGMA, protocol, nodes=x))(model, jnp.asarray(flat)))


@pytest.mark.parametrize("name,solver,rtol", fem_solvers(), ids=[s[0] for s in fem_solvers()])
def test_invariants_hold_for_every_solver(mesh_elec, protocol, name, solver, rtol):
    # Reciprocity (random per-tet sigma), scaling sigma -> c sigma, z -> z / c (voltages / c),
    # and agreement with the dense reference of the whole CEM system, for each solver.
    mesh, elec = mesh_elec
    model = build_forward_model(mesh, elec, solver=solver)
    sigma = 0.05 + np.random.default_rng(3).random(mesh.n_tets)
    rows = np.array([[0, 3, 5, 6], [1, 5, 2, 7], [4, 6, 0, 1]])
    v = np.asarray(simulate(model, sigma, Protocol(rows, 1e-3)))
    w = np.asarray(simulate(model, sigma, Protocol(rows[:, [2, 3, 0, 1]], 1e-3)))
    np.testing.assert_allclose(v, w, rtol=rtol, atol=rtol * np.abs(v).max())
    vc = np.asarray(simulate(model, 3.7 * sigma, Protocol(rows, 1e-3),
                             contact_impedance_ohm_m2=elec.contact_impedance_ohm_m2 / 3.7))
    np.testing.assert_allclose(vc, v / 3.7, rtol=rtol, atol=rtol * np.abs(v).max())
    # dense reference: ground electrode 0 (drop its row and column), drive 1e-3 A from 0 to 3
    A = dense_reference(mesh, elec, sigma)
    n = mesh.n_nodes
    keep = np.r_[0:n, n + 1:n + elec.contact_impedance_ohm_m2.shape[0]]
    b = np.zeros(A.shape[0])
    b[n + 3] = -1e-3  # current leaves through electrode 3; electrode 0 (ground) sources it
    U = np.zeros(elec.contact_impedance_ohm_m2.shape[0])
    U[1:] = np.linalg.solve(A[np.ix_(keep, keep)], b[keep])[n:]
    np.testing.assert_allclose(v[0], U[5] - U[6], rtol=rtol, atol=rtol * np.abs(v).max())
