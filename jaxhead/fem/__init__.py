"""Differentiable complete-electrode-model FEM: assembly, solvers, forward model, Jacobian."""

from .assembly import MM_TO_M
from .forward import (
                      ForwardModel,
                      assemble,
                      build_forward_model,
                      jacobian,
                      jacobian_cells,
                      potentials,
                      simulate,
)
from .solvers import (
                      AbstractSolver,
                      BlockCG,
                      Direct,
                      Jacobi,
                      SmoothedAggregation,
                      linear_solve,
                      pardiso_available,
)

__all__ = [
    "MM_TO_M",
    "AbstractSolver",
    "BlockCG",
    "Direct",
    "ForwardModel",
    "Jacobi",
    "SmoothedAggregation",
    "assemble",
    "build_forward_model",
    "jacobian",
    "jacobian_cells",
    "linear_solve",
    "pardiso_available",
    "potentials",
    "simulate",
]
