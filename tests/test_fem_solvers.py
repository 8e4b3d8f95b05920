"""Sparse SPD solvers: Direct (PARDISO, SciPy) and BlockCG against dense solves and each other.

Reference solutions come from `numpy.linalg.solve` on the dense matrix. Tolerances: a direct
factorisation of a matrix with condition number kappa loses ~kappa eps digits; for these small
FEM matrices kappa ~ 1e6-1e7, so 1e-8 relative is safe. CG stops at rtol = 1e-12 on the
residual, so its error is below kappa * 1e-12 ~ 1e-6 relative; we check 1e-6 against Direct.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxhead.fem.forward import assemble, build_forward_model
from jaxhead.fem.cem import electrode_rhs
from jaxhead.fem.solvers import (BlockCG, Direct, Jacobi, SmoothedAggregation, linear_solve,
                                 pardiso_available)
from test_fem_assembly import small_model

SIGMA = jnp.array([0.3, 1.79, 0.018, 0.44])  # the skull's 1:100 contrast makes CG work
BACKENDS = ["scipy"] + (["pardiso"] if pardiso_available() else [])


CG_RTOL = 1e-12


@pytest.fixture(scope="module")
def mesh_elec():
    return small_model(h_mm=32.0, n_elec=8)


@pytest.fixture(scope="module")
def direct_model(mesh_elec):
    return build_forward_model(*mesh_elec)


@pytest.fixture(scope="module")
def cg_models(mesh_elec):
    return {name: build_forward_model(*mesh_elec, solver=BlockCG(
        preconditioner=pre, rtol=CG_RTOL, max_steps=5000))
        for name, pre in [("jacobi", Jacobi()), ("sa-amg", SmoothedAggregation())]}


def _dense(model, values):
    p = model.pattern
    A = np.zeros((p.n, p.n))
    A[np.asarray(p.rows), np.asarray(p.cols)] = np.asarray(values)[np.asarray(p.to_upper)]
    return A


def _rhs(model):
    """Unit current into each electrode but the last, out of the last: (n_elec, n_elec - 1)."""
    n = model.n_elec
    currents = np.eye(n, n - 1)
    currents[-1] = -1.0
    return electrode_rhs(jnp.asarray(currents), n_nodes=model.n_nodes)


@pytest.mark.parametrize("backend", BACKENDS)
def test_direct_matches_dense(mesh_elec, backend):
    model = build_forward_model(*mesh_elec, solver=Direct(backend=backend))
    values = assemble(model, SIGMA)
    b = _rhs(model)
    x = linear_solve(model.solver, model.solver_state, model.pattern, values, b)
    ref = np.linalg.solve(_dense(model, values), np.asarray(b))
    np.testing.assert_allclose(np.asarray(x), ref, rtol=1e-8, atol=1e-8 * np.abs(ref).max())
    # a vector right-hand side works too and agrees
    x1 = linear_solve(model.solver, model.solver_state, model.pattern, values, b[:, 3])
    np.testing.assert_allclose(np.asarray(x1), ref[:, 3], rtol=1e-8, atol=1e-8 * np.abs(ref).max())


def test_block_cg_matches_direct_and_multigrid_beats_jacobi(direct_model, cg_models):
    values = assemble(direct_model, SIGMA)
    b = _rhs(direct_model)
    xd = linear_solve(direct_model.solver, direct_model.solver_state, direct_model.pattern,
                      values, b)
    counts = {}
    for name, model in cg_models.items():
        x, k, done = jax.jit(lambda v, b: model.solver.solve_with_stats(
            model.solver_state, model.pattern, v, b))(values, b)
        assert bool(jnp.all(done))
        counts[name] = int(k)
        np.testing.assert_allclose(np.asarray(x), np.asarray(xd), rtol=0,
                                   atol=1e-6 * float(jnp.abs(xd).max()))
    # the point of the preconditioner (REFERENCES: Jacobi-PCG ~440 iterations at 1:100)
    assert counts["sa-amg"] * 4 < counts["jacobi"], counts


def test_vmap_over_matrices_and_rhs(direct_model, cg_models):
    m = direct_model
    vals = jnp.stack([assemble(m, SIGMA), assemble(m, 2.0 * SIGMA)])
    b = _rhs(m)

    def solve(v, b):
        return linear_solve(m.solver, m.solver_state, m.pattern, v, b)

    x = jax.vmap(solve, in_axes=(0, None))(vals, b)
    # sigma * 2 -> potentials / 2 (the matrix's CEM part is not scaled, so compare solves)
    for i in range(2):
        np.testing.assert_allclose(np.asarray(x[i]), np.asarray(solve(vals[i], b)), rtol=1e-12,
                                   atol=1e-14)
    xb = jax.vmap(solve, in_axes=(None, 1), out_axes=1)(vals[0], b)
    np.testing.assert_allclose(np.asarray(xb), np.asarray(solve(vals[0], b)), rtol=1e-12,
                               atol=1e-14)
    mc = cg_models["jacobi"]
    xc = jax.jit(jax.vmap(lambda v: linear_solve(mc.solver, mc.solver_state, mc.pattern, v,
                                                 b)))(vals)
    np.testing.assert_allclose(np.asarray(xc), np.asarray(x), rtol=0,
                               atol=1e-6 * float(jnp.abs(x).max()))


def test_gradient_wrt_values_is_the_adjoint_formula(direct_model):
    """dL/dA_ij = -lambda_i x_j (both triangles onto the stored entry), lambda = A^-1 dL/dx."""
    m = direct_model
    values = assemble(m, SIGMA)
    b = _rhs(m)[:, :3]
    c = jnp.asarray(np.random.default_rng(0).standard_normal(b.shape))

    def loss(v):
        return jnp.sum(c * linear_solve(m.solver, m.solver_state, m.pattern, v, b))

    g = np.asarray(jax.grad(loss)(values))
    A = _dense(m, values)
    x = np.linalg.solve(A, np.asarray(b))
    lam = np.linalg.solve(A, np.asarray(c))  # A symmetric: the adjoint solve is a solve
    G = -lam @ x.T  # dL/dA_ij for every (i, j)
    p = m.pattern
    ref = np.zeros(m.nnz)
    np.add.at(ref, np.asarray(p.to_upper), G[np.asarray(p.rows), np.asarray(p.cols)])
    np.testing.assert_allclose(g, ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())
    # and a central finite difference on a few stored entries: step 1e-4 relative, so the
    # O(h^2) truncation (~1e-8) and the solve's round-off (~kappa eps / h ~ 1e-7) both stay
    # below the 1e-5 tolerance
    for k in np.random.default_rng(1).choice(m.nnz, 5, replace=False):
        h = 1e-4 * abs(float(values[k]))
        e = jnp.zeros(m.nnz).at[k].set(h)
        fd = (loss(values + e) - loss(values - e)) / (2 * h)
        assert float(fd) == pytest.approx(g[k], rel=1e-5, abs=1e-8 * np.abs(g).max())


def test_factor_reused_across_solves_and_backward_pass(mesh_elec):
    model = build_forward_model(*mesh_elec)
    h = model.solver_state.handle
    values = assemble(model, SIGMA)
    b = _rhs(model)
    f0 = h.n_factorisations

    def loss(v):
        return jnp.sum(linear_solve(model.solver, model.solver_state, model.pattern, v, b) ** 2)

    jax.grad(loss)(values)  # forward solve + adjoint solve: one factorisation
    jax.jacfwd(lambda s: loss(s * values))(1.0)  # same matrix again: reused
    assert h.n_factorisations - f0 == 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_direct_indefinite_matrix_is_an_error(mesh_elec, backend):
    model = build_forward_model(*mesh_elec, solver=Direct(backend=backend))
    values = assemble(model, SIGMA)
    bad = values.at[np.asarray(model.pattern.diag)[:50]].set(-1.0)  # not positive definite
    with pytest.raises(Exception, match="not positive definite|singular"):
        jax.block_until_ready(linear_solve(model.solver, model.solver_state, model.pattern,
                                           bad, _rhs(model)))


def test_cg_non_convergence_is_an_error(cg_models):
    model = cg_models["jacobi"]
    solver = BlockCG(preconditioner=Jacobi(), rtol=1e-12, max_steps=3)
    values = assemble(model, SIGMA)
    with pytest.raises(Exception, match="did not reach"):
        jax.block_until_ready(linear_solve(solver, model.solver_state, model.pattern, values,
                                           _rhs(model)))


def test_solver_arguments_are_checked():
    with pytest.raises(ValueError, match="backend"):
        Direct(backend="umfpack")
    with pytest.raises(ValueError, match="max_steps"):
        BlockCG(max_steps=0)
    with pytest.raises(ValueError, match="rtol"):
        BlockCG(rtol=0.0, atol=0.0)
    with pytest.raises(ValueError, match="theta"):
        SmoothedAggregation(theta=1.5)


def test_simulate_and_gradient_through_block_cg(direct_model, cg_models):
    """Derivatives use the same adjoint identity whichever solver runs the solves."""
    from jaxhead.fem.forward import simulate
    from jaxhead.protocol import adjacent

    protocol = adjacent(8, current_a=1e-3)

    def loss(m, s):
        return jnp.sum(simulate(m, s, protocol) ** 2)

    vg = jax.jit(jax.value_and_grad(loss, argnums=1))
    ld, gd = vg(direct_model, SIGMA)
    lc, gc = vg(cg_models["jacobi"], SIGMA)  # (the multigrid V-cycle compiles slowly)
    # CG at rtol 1e-12 on a matrix with condition ~1e7: ~1e-6 relative at worst
    assert float(lc) == pytest.approx(float(ld), rel=1e-6)
    np.testing.assert_allclose(np.asarray(gc), np.asarray(gd), rtol=1e-5,
                               atol=1e-6 * float(jnp.abs(gd).max()))
