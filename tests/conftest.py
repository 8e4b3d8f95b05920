"""Test entry point: float64 everywhere (FEM in float32 is wrong; see STYLE.md)."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


def fem_solvers():
    """The FEM solvers every forward-model invariant is checked with: (id, solver, rtol).

    Direct factorisations are exact to ~kappa eps (1e-8 relative on the small test matrices);
    block CG stops at a 1e-12 relative residual, so its voltages are within ~kappa 1e-12 ~ 1e-6.
    """
    from jaxhead.fem import BlockCG, Direct, Jacobi, SmoothedAggregation

    return [("direct", Direct(), 1e-8),
            ("cg-jacobi", BlockCG(preconditioner=Jacobi(), rtol=1e-12, max_steps=5000), 1e-6),
            ("cg-sa-amg", BlockCG(preconditioner=SmoothedAggregation(), rtol=1e-12, max_steps=5000), 1e-6)]
