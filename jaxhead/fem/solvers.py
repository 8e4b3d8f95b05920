"""Differentiable sparse symmetric positive definite solves with many right-hand sides.  [jax]

One verb, `linear_solve(solver, state, pattern, values, rhs)`, and solver objects for the
configuration (lineax / optimistix style):

- `Direct()`: sparse Cholesky-type factorisation on the host behind `jax.pure_callback`. The
  symbolic analysis (fill-reducing ordering) is done once per mesh in `Direct.init`; the numeric
  factor is cached against the matrix values, so all right-hand sides, the tangent solves of
  forward mode and the adjoint solves of reverse mode reuse one factorisation (the matrix is
  symmetric: the adjoint solve is the same solve). Backend: Intel MKL PARDISO (pip `pypardiso`,
  matrix type 2, real SPD, METIS nested dissection), with SciPy's SuperLU as the fallback when
  MKL is unavailable (about 30x slower on head meshes; see benchmarks/forward.py).
- `BlockCG(preconditioner=SmoothedAggregation())`: pure-JAX preconditioned conjugate gradients
  on all right-hand sides at once (one sparse mat-mat product per step, per-column step sizes),
  jit/vmap/GPU friendly. Preconditioners: `Jacobi()` and `SmoothedAggregation()`, a smoothed-
  aggregation algebraic multigrid V-cycle (Vanek, Mandel & Brezina 1996, Computing 56:179)
  whose aggregates and sparsity patterns are built once on the host and whose values are
  recomputed in JAX from the current matrix, so it adapts to any conductivity.

Derivatives never go through the solver's iterations: `jax.lax.custom_linear_solve` with
`symmetric=True` defines x' = A^{-1} (b' - A' x) and the transpose by the same solve, so for a
loss L the matrix-value cotangent is dL/dA_ij = -lambda_i x_j (lambda = A^{-1} dL/dx), summed
onto the stored (upper-triangle) entries: the adjoint formula, restricted to the pattern.

Failures are errors, never silent wrong answers: a factorisation that finds the matrix not
positive definite raises from the callback; CG that does not reach its tolerance in
`max_steps` fails through `eqx.error_if`.
"""

from __future__ import annotations

import ctypes
import logging
import threading
import weakref
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .assembly import Pattern

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Pattern arrays for JAX (the matvec that custom_linear_solve differentiates)


class PatternArrays(eqx.Module):
    """The full symmetric COO pattern as arrays, for the JAX mat-vec.

    Attributes:
        rows, cols: (nnz_full,) sorted by row.
        to_upper: (nnz_full,) stored (upper-triangle) entry of each full entry.
        diag: (n,) stored entry of each diagonal element.
        n: matrix size.
    """

    rows: np.ndarray
    cols: np.ndarray
    to_upper: np.ndarray
    diag: np.ndarray
    n: int = eqx.field(static=True)

    @classmethod
    def from_pattern(cls, pattern: Pattern) -> "PatternArrays":
        def i32(a):
            return jnp.asarray(a, dtype=jnp.int32)

        return cls(rows=i32(pattern.full_rows), cols=i32(pattern.full_cols),
                   to_upper=i32(pattern.full_to_upper), diag=i32(pattern.diag), n=pattern.n)


def matvec(p: PatternArrays, values, x):
    """A x for the symmetric matrix with stored values `values` (nnz,); x is (n,) or (n, k)."""
    v = values[p.to_upper]
    prod = v.reshape(v.shape + (1,) * (x.ndim - 1)) * x[p.cols]
    return jax.ops.segment_sum(prod, p.rows, num_segments=p.n, indices_are_sorted=True)


# ----------------------------------------------------------------------------------------------
# Solver API


class AbstractSolver(eqx.Module):
    """A way of solving A x = b for a sparse SPD A given by stored values on a fixed pattern."""

    def init(self, pattern: Pattern, values: np.ndarray):
        """Set-up done once per mesh (host): ordering, symbolic factorisation, hierarchy."""
        raise NotImplementedError

    def raw_solve(self, state, pattern: PatternArrays, values, rhs):
        """x = A^{-1} rhs, not differentiable (used inside `linear_solve`)."""
        raise NotImplementedError


def linear_solve(solver: AbstractSolver, state, pattern: PatternArrays, values, rhs):
    """Differentiable solve of A(values) x = rhs for symmetric positive definite A.

    Arguments:
        solver: a solver object (`Direct()`, `BlockCG(...)`).
        state: what `solver.init` returned for this pattern.
        pattern: the pattern's arrays (`PatternArrays.from_pattern`).
        values: (nnz,) stored upper-triangle values of A.
        rhs: (n,) or (n, k) right-hand sides.

    Returns:
        x with the shape of rhs. Derivatives with respect to `values` and `rhs` (forward and
        reverse mode) use the adjoint identity, never the solver's internals.
    """
    values_c = jax.lax.stop_gradient(values)

    def mv(x):
        return matvec(pattern, values, x)

    def solve(_mv, b):
        return solver.raw_solve(state, pattern, values_c, b)

    return jax.lax.custom_linear_solve(mv, rhs, solve, symmetric=True)


# ----------------------------------------------------------------------------------------------
# Direct: host factorisation behind pure_callback


class _MKLPardiso:
    """Intel MKL PARDISO for one sparsity pattern: real SPD (mtype 2), upper CSR, 0-based.

    Phases (Intel oneMKL reference, `pardiso`): 11 analysis (METIS ordering + symbolic
    factorisation, once), 22 numeric factorisation (per matrix values), 33 solve, -1 release.
    """

    name = "pardiso"

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int):
        self._fn = _mkl_pardiso()
        self.pt = np.zeros(64, dtype=np.int64)
        self.iparm = np.zeros(64, dtype=np.int32)
        self.iparm[0] = 1     # user-supplied iparm
        self.iparm[1] = 2     # METIS nested-dissection ordering
        self.iparm[7] = 0     # iterative refinement only if pivots were perturbed
        self.iparm[9] = 8     # pivot perturbation 1e-8 (never triggered for SPD)
        self.iparm[17] = -1   # report nnz of the factor
        self.iparm[34] = 1    # zero-based indexing
        self.n = int(n)
        self.indptr = np.ascontiguousarray(indptr, dtype=np.int32)
        self.indices = np.ascontiguousarray(indices, dtype=np.int32)
        dummy = np.ones(self.indices.size)
        self._call(11, dummy, np.zeros((self.n, 1)), np.zeros((self.n, 1)))
        self.factor_nnz = int(self.iparm[17])
        self._finalizer = weakref.finalize(self, _MKLPardiso._release, self._fn, self.pt, self.n)

    def _call(self, phase, data, b, x):
        err = ctypes.c_int32(0)
        i32p = ctypes.POINTER(ctypes.c_int32)
        f64p = ctypes.POINTER(ctypes.c_double)
        nrhs = 1 if b.ndim == 1 else b.shape[1]
        self._fn(self.pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
                 ctypes.byref(ctypes.c_int32(1)), ctypes.byref(ctypes.c_int32(1)),
                 ctypes.byref(ctypes.c_int32(2)), ctypes.byref(ctypes.c_int32(phase)),
                 ctypes.byref(ctypes.c_int32(self.n)), data.ctypes.data_as(f64p),
                 self.indptr.ctypes.data_as(i32p), self.indices.ctypes.data_as(i32p),
                 None, ctypes.byref(ctypes.c_int32(nrhs)), self.iparm.ctypes.data_as(i32p),
                 ctypes.byref(ctypes.c_int32(0)), b.ctypes.data_as(f64p),
                 x.ctypes.data_as(f64p), ctypes.byref(err))
        return err.value

    @staticmethod
    def _release(fn, pt, n):
        err = ctypes.c_int32(0)
        zero = np.zeros(1)
        idx = np.zeros(2, np.int32)
        fn(pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), ctypes.byref(ctypes.c_int32(1)),
           ctypes.byref(ctypes.c_int32(1)), ctypes.byref(ctypes.c_int32(2)),
           ctypes.byref(ctypes.c_int32(-1)), ctypes.byref(ctypes.c_int32(n)),
           zero.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
           idx.ctypes.data_as(ctypes.POINTER(ctypes.c_int32)),
           idx.ctypes.data_as(ctypes.POINTER(ctypes.c_int32)), None,
           ctypes.byref(ctypes.c_int32(1)), np.zeros(64, np.int32).ctypes.data_as(
               ctypes.POINTER(ctypes.c_int32)), ctypes.byref(ctypes.c_int32(0)),
           zero.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
           zero.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), ctypes.byref(err))

    def factor(self, values: np.ndarray) -> None:
        self._data = np.ascontiguousarray(values, dtype=np.float64)
        b = np.zeros((self.n, 1))
        err = self._call(22, self._data, b, b.copy())
        if err != 0:
            raise _factor_error(err, "PARDISO")

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        b = np.asfortranarray(rhs, dtype=np.float64)
        x = np.zeros_like(b, order="F")
        err = self._call(33, self._data, b, x)
        if err != 0:
            raise RuntimeError(f"PARDISO solve failed with error {err}.")
        return np.ascontiguousarray(x)


class _ScipyLU:
    """SciPy SuperLU fallback (no symbolic reuse; COLAMD-type ordering on A + A^T)."""

    name = "scipy"

    def __init__(self, pattern: Pattern):
        self.pattern = pattern
        self.factor_nnz = -1

    def factor(self, values: np.ndarray) -> None:
        import scipy.sparse.linalg as spla

        a = self.pattern.to_scipy(values).tocsc()
        try:
            self._lu = spla.splu(a, permc_spec="MMD_AT_PLUS_A",
                                 options={"SymmetricMode": True})
        except RuntimeError as e:  # "Factor is exactly singular"
            raise _factor_error(str(e), "SuperLU") from None
        d = self._lu.U.diagonal()
        if not np.all(np.isfinite(d)) or np.any(d == 0):
            raise _factor_error("zero pivot", "SuperLU")

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._lu.solve(np.asarray(rhs, dtype=np.float64))


def _factor_error(code, who) -> ValueError:
    return ValueError(
        f"{who} could not factorise the FEM matrix (error {code}): it is singular or not "
        "positive definite. Check that every conductivity and contact impedance is finite "
        "and > 0, that node positions keep every tet positively oriented, and that every "
        "mesh node belongs to a tet.")


class DirectHandle:
    """Host-side state of `Direct` for one pattern: backend, cached factor, lock.

    Identity-hashed, so it can be a static field of a ForwardModel.
    """

    def __init__(self, backend, n: int, nnz: int):
        self.backend = backend
        self.n, self.nnz = n, nnz
        self._lock = threading.Lock()
        self._values: np.ndarray | None = None
        self.n_factorisations = 0
        self.n_solves = 0

    def _ensure_factor(self, values: np.ndarray) -> None:
        if self._values is not None and np.array_equal(values, self._values):
            return
        if not np.all(np.isfinite(values)):
            raise ValueError(
                "the FEM matrix has NaN or Inf entries; check sigma, contact impedance and "
                "node positions for NaN/Inf or zeros.")
        self._values = None
        self.backend.factor(values)
        self._values = values.copy()
        self.n_factorisations += 1

    def solve(self, values: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """Solve for every batch of (values (..., nnz), rhs (..., n, k)), broadcasting batches."""
        values = np.asarray(values, dtype=np.float64)
        rhs = np.asarray(rhs, dtype=np.float64)
        batch = np.broadcast_shapes(values.shape[:-1], rhs.shape[:-2])
        k = rhs.shape[-1]
        vb = values.reshape(-1, self.nnz)
        out = np.empty(batch + rhs.shape[-2:], dtype=np.float64)
        with self._lock:
            if vb.shape[0] == 1:
                # One matrix: all right-hand sides of all batches in one multi-RHS solve.
                self._ensure_factor(vb[0])
                rb = np.broadcast_to(rhs, batch + rhs.shape[-2:]).reshape(-1, self.n, k)
                cols = np.moveaxis(rb, 0, 1).reshape(self.n, -1)
                x = self.backend.solve(cols).reshape(self.n, -1, k)
                out[...] = np.moveaxis(x, 1, 0).reshape(out.shape)
                self.n_solves += cols.shape[1]
            else:
                vfull = np.broadcast_to(values, batch + values.shape[-1:]).reshape(-1, self.nnz)
                rfull = np.broadcast_to(rhs, batch + rhs.shape[-2:]).reshape(-1, self.n, k)
                flat = out.reshape(-1, self.n, k)
                for i in range(vfull.shape[0]):
                    self._ensure_factor(vfull[i])
                    flat[i] = self.backend.solve(rfull[i])
                    self.n_solves += k
        if not np.all(np.isfinite(out)):
            raise ValueError("the direct solve returned NaN/Inf: the FEM matrix is singular.")
        return out


_MKL: list = []


def _mkl_pardiso():
    """The ctypes `pardiso` function of MKL's runtime library (shipped by pip `pypardiso`).

    Looked up once: $PYPARDISO_MKL_RT, then the system's library path, then the environment's
    lib/ folder (where the `mkl` wheel puts libmkl_rt). pypardiso's own search globs the
    whole environment recursively (~0.5 s), so it is not used.
    """
    if not _MKL:
        import ctypes.util
        import glob
        import os
        import sys

        found = [os.environ.get("PYPARDISO_MKL_RT"), ctypes.util.find_library("mkl_rt")]
        for base in (sys.prefix, sys.base_prefix):
            found += sorted(glob.glob(os.path.join(base, "lib", "libmkl_rt.so*")))
            found += sorted(glob.glob(os.path.join(base, "Library", "bin", "mkl_rt*.dll")))
        lib = None
        for path in filter(None, found):
            try:
                lib = ctypes.CDLL(path)
                break
            except OSError:
                continue
        if lib is None:
            raise OSError("MKL runtime library (libmkl_rt) not found; `pip install pypardiso` "
                          "or set PYPARDISO_MKL_RT to its path.")
        fn = lib.pardiso
        i32p = ctypes.POINTER(ctypes.c_int32)
        fn.argtypes = [ctypes.POINTER(ctypes.c_int64), i32p, i32p, i32p, i32p, i32p,
                       ctypes.c_void_p, i32p, i32p, i32p, i32p, i32p, i32p,
                       ctypes.c_void_p, ctypes.c_void_p, i32p]
        fn.restype = None
        _MKL.append(fn)
    return _MKL[0]


def pardiso_available() -> bool:
    """Whether Intel MKL PARDISO (pip `pypardiso`) can be loaded."""
    try:
        _mkl_pardiso()
        return True
    except Exception:  # ImportError, OSError when mkl_rt is missing
        return False


class DirectState(eqx.Module):
    """What `Direct.init` returns: the host handle as static (identity-hashed) data."""

    handle: DirectHandle = eqx.field(static=True)


class Direct(AbstractSolver):
    """Sparse direct solver on the host (CPU default), factor reused for every solve.

    Arguments:
        backend: "auto" (PARDISO if `pypardiso` loads, else SciPy), "pardiso" or "scipy".
    """

    backend: Literal["auto", "pardiso", "scipy"] = eqx.field(static=True, default="auto")

    def __check_init__(self):
        if self.backend not in ("auto", "pardiso", "scipy"):
            raise ValueError(
                f"`Direct.backend` = {self.backend!r}; use 'auto', 'pardiso' or 'scipy'.")

    def init(self, pattern: Pattern, values: np.ndarray | None = None) -> DirectState:
        name = self.backend
        if name == "auto":
            name = "pardiso" if pardiso_available() else "scipy"
            if name == "scipy":
                logger.info("pypardiso (MKL) not available; Direct uses SciPy SuperLU "
                            "(much slower on large meshes; `pip install pypardiso`).")
        if name == "pardiso":
            if not pardiso_available():
                raise ValueError("Direct(backend='pardiso') needs `pip install pypardiso` "
                                 "(Intel MKL); or use backend='auto'/'scipy'.")
            backend = _MKLPardiso(pattern.indptr, pattern.indices, pattern.n)
        else:
            backend = _ScipyLU(pattern)
        return DirectState(DirectHandle(backend, pattern.n, pattern.nnz))

    def raw_solve(self, state: DirectState, pattern: PatternArrays, values, rhs):
        vec = rhs.ndim == 1
        b = rhs[:, None] if vec else rhs
        x = jax.pure_callback(state.handle.solve, jax.ShapeDtypeStruct(b.shape, b.dtype),
                              values, b, vmap_method="expand_dims")
        return x[:, 0] if vec else x
