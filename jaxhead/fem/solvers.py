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
import ctypes.util
import glob
import logging
import os
import sys
import threading
import weakref
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse.linalg as spla

from .assembly import Pattern

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Pattern arrays for JAX (the matvec that custom_linear_solve differentiates)


#: Rows longer than this keep their first `ell_width` entries in the ELL block and the rest in
#: a small COO overflow (the electrode unknowns' rows: one entry per node under the electrode).
LONG_ROW = 64


class Ell(eqx.Module):
    """A sparse matrix's pattern for fast mat-vecs in JAX: ELLPACK block plus COO overflow.

    A scatter over all non-zeros (segment_sum) is slow in XLA on CPU; instead every row's first
    `width` entries are gathered and reduced in an (n_rows, width) block (padding points at a
    zero value), and the entries beyond (only rows longer than `LONG_ROW`) are summed by a
    small segment-sum.

    Attributes:
        cols, vals: (n_rows, width) column and value index of each row's entries (padding:
            column 0, value index `nnz`, which reads 0).
        ovf_rows, ovf_cols, ovf_vals: (n_ovf,) the overflow entries.
        n_rows, nnz: rows and length of the values array.
    """

    cols: jax.Array
    vals: jax.Array
    ovf_rows: jax.Array
    ovf_cols: jax.Array
    ovf_vals: jax.Array
    n_rows: int = eqx.field(static=True)
    nnz: int = eqx.field(static=True)

    @classmethod
    def from_coo(cls, rows, cols, val_idx, n_rows: int, nnz: int) -> "Ell":
        """From COO entries sorted by row; val_idx says which value each entry reads."""
        rows, cols, val_idx = (np.asarray(a, np.int64) for a in (rows, cols, val_idx))
        starts = np.searchsorted(rows, np.arange(n_rows + 1))
        length = np.diff(starts)
        # width: the longest row among all but the 0.1 % longest (and <= LONG_ROW), so the few
        # long rows (electrodes, coarse aggregates) overflow instead of widening every row
        width = max(1, int(min(np.percentile(length, 99.9, method="lower"), LONG_ROW)))
        pos = np.arange(rows.size) - starts[rows]
        inside = pos < width
        ell_cols = np.zeros((n_rows, width), np.int32)
        ell_vals = np.full((n_rows, width), nnz, np.int32)
        ell_cols[rows[inside], pos[inside]] = cols[inside]
        ell_vals[rows[inside], pos[inside]] = val_idx[inside]
        out = ~inside

        def i32(a):
            return jnp.asarray(a, dtype=jnp.int32)

        return cls(cols=i32(ell_cols), vals=i32(ell_vals), ovf_rows=i32(rows[out]),
                   ovf_cols=i32(cols[out]), ovf_vals=i32(val_idx[out]), n_rows=n_rows,
                   nnz=nnz)

    def apply(self, values, x):
        """M x for values (nnz,) and x (n_cols,) or (n_cols, k)."""
        v = jnp.concatenate([values, jnp.zeros((1,), values.dtype)])
        vec = x.ndim == 1
        x2 = x[:, None] if vec else x
        V = v[self.vals]  # one gather, so the transpose (values' cotangent) is one scatter
        y = jnp.zeros((self.n_rows, x2.shape[1]), jnp.result_type(values, x))
        for k in range(self.cols.shape[1]):  # unrolled: one fused gather-multiply-add
            y = y + V[:, k, None] * x2[self.cols[:, k]]
        y = y + jax.ops.segment_sum(v[self.ovf_vals][:, None] * x2[self.ovf_cols],
                                    self.ovf_rows, num_segments=self.n_rows,
                                    indices_are_sorted=True)
        return y[:, 0] if vec else y


class PatternArrays(eqx.Module):
    """The symmetric matrix pattern as arrays for JAX: mat-vec plan and index maps.

    Attributes:
        ell: the full symmetric pattern as an `Ell` over the stored (upper) values.
        diag: (n,) stored entry of each diagonal element.
        rows, cols, to_upper: (nnz_full,) the full COO pattern (sorted by row).
        n, nnz: matrix size and number of stored entries.
    """

    ell: Ell
    diag: jax.Array
    rows: jax.Array
    cols: jax.Array
    to_upper: jax.Array
    n: int = eqx.field(static=True)
    nnz: int = eqx.field(static=True)

    @classmethod
    def from_pattern(cls, pattern: Pattern) -> "PatternArrays":
        def i32(a):
            return jnp.asarray(a, dtype=jnp.int32)

        rows, cols, up = pattern.full_rows, pattern.full_cols, pattern.full_to_upper
        return cls(ell=Ell.from_coo(rows, cols, up, pattern.n, pattern.nnz),
                   diag=i32(pattern.diag), rows=i32(rows), cols=i32(cols), to_upper=i32(up),
                   n=pattern.n, nnz=pattern.nnz)


def matvec(p: PatternArrays, values, x):
    """A x for the symmetric matrix with stored values `values` (nnz,); x is (n,) or (n, k)."""
    return p.ell.apply(values, x)


def matvecs(p: PatternArrays, values, x):
    """A_t x for several matrices on one pattern: values (m, nnz) -> (m, n[, k]).

    Several mat-vecs of the same x in one XLA computation share (CSE, or hoist out of a loop)
    the gathers of x, which XLA then materialises: ~30x slower on CPU than one mat-vec. A
    zero that XLA cannot prove zero (min(loop index, 0)) in the column indices keeps each
    loop iteration's gathers its own.
    """
    def one(t, v):
        q = eqx.tree_at(lambda q: q.ell.cols, p, p.ell.cols + jnp.minimum(t, 0))
        return matvec(q, v, x)

    return jax.lax.map(lambda tv: one(*tv), (jnp.arange(values.shape[0]), values))


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

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, n: int, threads: int | None):
        self._fn = _mkl_pardiso()
        self.threads = threads
        self._threads()
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

    def _threads(self):
        if self.threads is not None:
            _mkl_set_pardiso_threads(self.threads)

    def factor(self, values: np.ndarray) -> None:
        self._threads()
        self._data = np.ascontiguousarray(values, dtype=np.float64)
        b = np.zeros((self.n, 1))
        err = self._call(22, self._data, b, b.copy())
        if err != 0:
            raise _factor_error(err, "PARDISO")

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        self._threads()
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

        a = self.pattern.to_scipy(values).tocsc()
        try:
            # Diagonal pivots only (threshold 0) with a symmetric ordering: then
            # P A P^T = L U = L D L^T-like with D = diag(U), and A is positive definite iff
            # every pivot is > 0 (Sylvester's law of inertia).
            self._lu = spla.splu(a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
        except RuntimeError as e:  # "Factor is exactly singular"
            raise _factor_error(str(e), "SuperLU") from None
        d = self._lu.U.diagonal()
        if (not np.array_equal(self._lu.perm_r, self._lu.perm_c)
                or not np.all(np.isfinite(d)) or np.any(d <= 0)):
            raise _factor_error("non-positive pivot", "SuperLU")

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
        if not values.any():
            # An all-zero matrix is never an FEM system (the diagonal is > 0 for sigma > 0). It is
            # the placeholder that optimistix's trust-region solvers (LevenbergMarquardt, Dogleg)
            # evaluate in their first step and then mask out; raising there would abort a valid
            # fit. Return zeros for it; every other singular matrix still raises below.
            return np.zeros(batch + rhs.shape[-2:], dtype=np.float64)
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
        _MKL.append(lib)
    return _MKL[0]


def _mkl_set_pardiso_threads(n: int) -> None:
    """Threads MKL uses for PARDISO only (MKL_Domain_Set_Num_Threads, MKL_DOMAIN_PARDISO = 4)."""
    _mkl_pardiso()
    _MKL[1].MKL_Domain_Set_Num_Threads(ctypes.c_int(int(n)), ctypes.c_int(4))


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
        threads: PARDISO threads (None: MKL's default, all cores). On a machine shared with
            other jobs, 1 avoids OpenMP threads spinning against each other.
    """

    backend: Literal["auto", "pardiso", "scipy"] = eqx.field(static=True, default="auto")
    threads: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.backend not in ("auto", "pardiso", "scipy"):
            raise ValueError(
                f"`Direct.backend` = {self.backend!r}; use 'auto', 'pardiso' or 'scipy'.")
        if self.threads is not None and int(self.threads) < 1:
            raise ValueError(f"`Direct.threads` must be >= 1 or None, got {self.threads}.")

    def init(self, pattern: Pattern, values: np.ndarray | None = None) -> DirectState:
        try:  # the factorisation runs on the host through jax.pure_callback
            jax.devices("cpu")
        except RuntimeError as e:
            raise ValueError(
                "Direct() solves on the host through jax.pure_callback, which needs JAX's CPU "
                f"platform, but JAX_PLATFORMS={os.environ.get('JAX_PLATFORMS')!r} leaves it "
                "out: add it (e.g. JAX_PLATFORMS=cuda,cpu) or use BlockCG() on the "
                "accelerator.") from e
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
            backend = _MKLPardiso(pattern.indptr, pattern.indices, pattern.n, self.threads)
        else:
            backend = _ScipyLU(pattern)
        return DirectState(DirectHandle(backend, pattern.n, pattern.nnz))

    def raw_solve(self, state: DirectState, pattern: PatternArrays, values, rhs):
        vec = rhs.ndim == 1
        b = rhs[:, None] if vec else rhs
        x = jax.pure_callback(state.handle.solve, jax.ShapeDtypeStruct(b.shape, b.dtype),
                              values, b, vmap_method="expand_dims")
        return x[:, 0] if vec else x


# ----------------------------------------------------------------------------------------------
# Pure-JAX preconditioned conjugate gradients on many right-hand sides


def _diag(pattern: PatternArrays, values):
    return values[pattern.diag]


class Jacobi(eqx.Module):
    """Diagonal (Jacobi) preconditioner: M^{-1} r = r / diag(A)."""

    def init(self, pattern: Pattern, values: np.ndarray):
        return None

    def build(self, state, pattern: PatternArrays, values):
        d = _diag(pattern, values)

        def apply(r):
            return r / d.reshape(d.shape + (1,) * (r.ndim - 1))

        return apply


class _Coarsening(eqx.Module):
    """Index plans of one multigrid level (fixed patterns; values recomputed in JAX).

    Level matrices are stored as full COO sorted by row: a_rows, a_cols (nnz_a,).
    Prolongator P (n_f x n_c): pattern p_rows, p_cols (nnz_p,), values from the level matrix:
        P = T - omega D^{-1} A T,  T[i, agg(i)] = 1
    (Vanek, Mandel & Brezina 1996, eq. 3.4): `pt_target` (n_f,) puts T's ones,
    `pa_target` (nnz_a,) puts a_ij into entry (i, agg(j)).
    Coarse matrix A_c = P^T (A P): `ap_a, ap_p -> ap_target` for B = A P (entries b_rows,
    b_cols) and `pb_p, pb_b -> pb_target` for P^T B, whose pattern is the next level's.
    Mat-vec plans (`Ell`): `a_ell` for this level's matrix (over its COO values), `p_ell`
    for P and `pt_ell` for P^T (over P's values); `a_diag` (n_f,) the diagonal's entries.
    """

    a_ell: Ell
    p_ell: Ell
    pt_ell: Ell
    a_diag: jax.Array
    p_rows: jax.Array
    p_cols: jax.Array
    pt_target: jax.Array
    pa_target: jax.Array
    ap_a: jax.Array
    ap_p: jax.Array
    ap_target: jax.Array
    b_rows: jax.Array
    pb_p: jax.Array
    pb_b: jax.Array
    pb_target: jax.Array
    c_rows: jax.Array
    c_cols: jax.Array
    n_fine: int = eqx.field(static=True)
    n_coarse: int = eqx.field(static=True)
    nnz_p: int = eqx.field(static=True)
    nnz_b: int = eqx.field(static=True)
    nnz_c: int = eqx.field(static=True)


def _csr_starts(rows: np.ndarray, n: int) -> np.ndarray:
    return np.searchsorted(rows, np.arange(n + 1))


def _product_plan(a_rows, a_cols, b_rows, b_cols, n_b, n_out_cols):
    """Pattern and index plan of C = A B for COO A and row-sorted COO B.  [host]

    Returns (ia, ib, target, c_rows, c_cols): c[target[k]] += a[ia[k]] * b[ib[k]].
    """
    starts = _csr_starts(b_rows, n_b)
    counts = (starts[1:] - starts[:-1])[a_cols]
    ia = np.repeat(np.arange(a_rows.size), counts)
    offs = np.arange(ia.size) - np.repeat(np.cumsum(counts) - counts, counts)
    ib = np.repeat(starts[:-1][a_cols], counts) + offs
    key = a_rows[ia].astype(np.int64) * n_out_cols + b_cols[ib]
    uniq, target = np.unique(key, return_inverse=True)
    return ia, ib, target.ravel(), uniq // n_out_cols, uniq % n_out_cols


def _aggregate(n: int, rows: np.ndarray, cols: np.ndarray, vals: np.ndarray,
               theta: float) -> np.ndarray:
    """Standard aggregation on the strong graph |a_ij| >= theta sqrt(a_ii a_jj).  [host]

    Vanek, Mandel & Brezina 1996, Sec. 3 (the three passes of pyamg's `standard_aggregation`).
    Returns agg (n,): aggregate of each unknown, 0..n_agg-1.
    """
    d = np.zeros(n)
    on = rows == cols
    d[rows[on]] = vals[on]
    off = ~on
    strong = off & (np.abs(vals) >= theta * np.sqrt(np.abs(d[rows] * d[cols])))
    sr, sc = rows[strong], cols[strong]
    starts = _csr_starts(sr, n)
    nbrs = [sc[starts[i]:starts[i + 1]] for i in range(n)]
    agg = np.full(n, -1, dtype=np.int64)
    n_agg = 0
    for i in range(n):  # pass 1: roots whose whole strong neighbourhood is free
        if agg[i] >= 0:
            continue
        nb = nbrs[i]
        if nb.size and np.all(agg[nb] < 0):
            agg[i] = n_agg
            agg[nb] = n_agg
            n_agg += 1
    first = agg.copy()
    for i in np.flatnonzero(agg < 0):  # pass 2: join a neighbouring pass-1 aggregate
        nb = nbrs[i]
        nb = nb[first[nb] >= 0]
        if nb.size:
            agg[i] = first[nb[0]]
    for i in np.flatnonzero(agg < 0):  # pass 3: the rest aggregate with their free neighbours
        if agg[i] >= 0:
            continue
        nb = nbrs[i]
        nb = nb[agg[nb] < 0]
        agg[i] = n_agg
        agg[nb] = n_agg
        n_agg += 1
    return agg


def _spectral_bound(rows, cols, vals, d, n):
    """Gershgorin bound of rho(D^{-1} A): max_i sum_j |a_ij| / a_ii."""
    return jnp.max(jax.ops.segment_sum(jnp.abs(vals), rows, num_segments=n,
                                       indices_are_sorted=True) / d)


def _coarse_values(lev: _Coarsening, rows, cols, vals, n):
    """Prolongator values and coarse matrix values of one level (JAX)."""
    on = rows == cols
    d = jax.ops.segment_sum(jnp.where(on, vals, 0.0), rows, num_segments=n,
                            indices_are_sorted=True)
    omega = 4.0 / (3.0 * _spectral_bound(rows, cols, vals, d, n))
    p = jnp.zeros(lev.nnz_p, vals.dtype).at[lev.pt_target].add(1.0)
    p = p.at[lev.pa_target].add(-omega * vals / d[rows])
    b = jax.ops.segment_sum(vals[lev.ap_a] * p[lev.ap_p], lev.ap_target, num_segments=lev.nnz_b)
    c = jax.ops.segment_sum(p[lev.pb_p] * b[lev.pb_b], lev.pb_target, num_segments=lev.nnz_c)
    return p, c


_coarse_values_jit = eqx.filter_jit(_coarse_values)


class SmoothedAggregation(eqx.Module):
    """Smoothed-aggregation algebraic multigrid V-cycle as a CG preconditioner.

    Set-up on the host, once per mesh: strength of connection and aggregates from the matrix
    at the build-time conductivities, and the index plans of every prolongator and Galerkin
    product. Per solve, in JAX: prolongator values P = (I - omega D^{-1} A) T with
    omega = 4 / (3 rho), rho the Gershgorin bound of D^{-1} A (Vanek, Mandel & Brezina 1996),
    coarse matrices P^T A P, a dense Cholesky factor on the coarsest level, and a symmetric
    V-cycle with damped-Jacobi smoothing (same sweeps before and after, so the preconditioner
    is symmetric positive definite, as CG needs).

    Arguments:
        theta: strength threshold on |a_ij| / sqrt(a_ii a_jj) (0.08: Vanek et al. 1996), halved
            per level.
        max_coarse: stop coarsening at this many unknowns (solved densely).
        max_levels: at most this many levels.
        sweeps: damped-Jacobi sweeps before and after the coarse correction.
    """

    theta: float = eqx.field(static=True, default=0.08)
    max_coarse: int = eqx.field(static=True, default=400)
    max_levels: int = eqx.field(static=True, default=8)
    sweeps: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        if not 0 <= self.theta < 1:
            raise ValueError(f"`theta` must be in [0, 1), got {self.theta}.")
        if self.max_coarse < 1 or self.max_levels < 1 or self.sweeps < 1:
            raise ValueError("`max_coarse`, `max_levels` and `sweeps` must be >= 1.")

    def init(self, pattern: Pattern, values: np.ndarray):
        values = np.asarray(values, dtype=np.float64)
        rows, cols = pattern.full_rows, pattern.full_cols
        vals = values[pattern.full_to_upper]
        n = pattern.n
        levels = []
        theta = self.theta
        while n > self.max_coarse and len(levels) + 1 < self.max_levels:
            agg = _aggregate(n, rows, cols, vals, theta)
            nc = int(agg.max()) + 1
            if nc >= n:  # no coarsening possible
                break
            # P pattern: T's (i, agg(i)) and A T's (i, agg(j)).
            key_t = np.arange(n) * nc + agg
            key_a = rows * nc + agg[cols]
            uniq, inv = np.unique(np.concatenate([key_t, key_a]), return_inverse=True)
            inv = inv.ravel()
            p_rows, p_cols = uniq // nc, uniq % nc
            ap_a, ap_p, ap_t, b_rows, b_cols = _product_plan(rows, cols, p_rows, p_cols, n, nc)
            # P^T B: P^T entries (p_cols, p_rows) times B rows (sorted by row).
            order = np.argsort(p_cols, kind="stable")
            pb_pt, pb_b, pb_t, c_rows, c_cols = _product_plan(
                p_cols[order], p_rows[order], b_rows, b_cols, n, nc)
            pb_p = order[pb_pt]
            i32 = lambda a: jnp.asarray(a, dtype=jnp.int32)  # noqa: E731
            lev = _Coarsening(
                a_ell=Ell.from_coo(rows, cols, np.arange(rows.size), n, rows.size),
                p_ell=Ell.from_coo(p_rows, p_cols, np.arange(p_rows.size), n, p_rows.size),
                pt_ell=Ell.from_coo(p_cols[order], p_rows[order], order, nc, p_rows.size),
                a_diag=i32(np.flatnonzero(rows == cols)), p_rows=i32(p_rows), p_cols=i32(p_cols), pt_target=i32(inv[:n]),
                pa_target=i32(inv[n:]), ap_a=i32(ap_a), ap_p=i32(ap_p), ap_target=i32(ap_t),
                b_rows=i32(b_rows), pb_p=i32(pb_p), pb_b=i32(pb_b), pb_target=i32(pb_t),
                c_rows=i32(c_rows), c_cols=i32(c_cols), n_fine=n, n_coarse=nc,
                nnz_p=p_rows.size, nnz_b=b_rows.size, nnz_c=c_rows.size)
            levels.append(lev)
            # Host values of the next level (for its aggregation) with the same formulas.
            vals = np.asarray(_coarse_values_jit(lev, jnp.asarray(rows), jnp.asarray(cols),
                                                 jnp.asarray(vals), n)[1])
            rows, cols, n = c_rows, c_cols, nc
            theta = theta / 2
        logger.info("SmoothedAggregation: %d levels, sizes %s", len(levels) + 1,
                    [lv.n_fine for lv in levels] + [n])
        return tuple(levels)

    def build(self, state, pattern: PatternArrays, values):
        levels = state
        rows, cols, n = pattern.rows, pattern.cols, pattern.n
        vals = values[pattern.to_upper]  # level 0 as full COO values
        ops = []
        for lev in levels:
            p, c = _coarse_values(lev, rows, cols, vals, n)
            d = vals[lev.a_diag]
            rho = jnp.max(lev.a_ell.apply(jnp.abs(vals), jnp.ones(n)) / d)  # Gershgorin
            ops.append((lev, vals, p, (4.0 / (3.0 * rho)) / d))
            rows, cols, vals, n = lev.c_rows, lev.c_cols, c, lev.n_coarse
        dense = jnp.zeros((n, n), vals.dtype).at[rows, cols].add(vals)
        chol = jax.scipy.linalg.cho_factor(dense, lower=True)
        sweeps = self.sweeps

        def vcycle(level, r):
            if level == len(ops):
                return jax.scipy.linalg.cho_solve(chol, r)
            lev, vals_l, p, w = ops[level]
            w = w[:, None]
            x = w * r
            for _ in range(sweeps - 1):
                x = x + w * (r - lev.a_ell.apply(vals_l, x))
            xc = vcycle(level + 1, lev.pt_ell.apply(p, r - lev.a_ell.apply(vals_l, x)))
            x = x + lev.p_ell.apply(p, xc)
            for _ in range(sweeps):
                x = x + w * (r - lev.a_ell.apply(vals_l, x))
            return x

        def apply(r):
            vec = r.ndim == 1
            out = vcycle(0, r[:, None] if vec else r)
            return out[:, 0] if vec else out

        return apply


def pcg(A, M, b, *, rtol: float, atol: float, max_steps: int):
    """Preconditioned CG on the columns of b at once (each column its own step sizes).

    Arguments:
        A, M: callables (n, k) -> (n, k): the SPD matrix and preconditioner.
        b: (n, k) right-hand sides.
        rtol, atol: stop a column when ||r|| <= max(rtol ||b||, atol).
        max_steps: iteration limit.

    Returns:
        x (n, k), steps (number of iterations), converged (k,) bool.
    """
    bnorm = jnp.linalg.norm(b, axis=0)
    tol = jnp.maximum(rtol * bnorm, atol)
    x = jnp.zeros_like(b)
    r = b
    z = M(r)
    p = z
    rz = jnp.sum(r * z, axis=0)
    done = jnp.linalg.norm(r, axis=0) <= tol

    def cond(s):
        k, x, r, p, rz, done = s
        return (k < max_steps) & ~jnp.all(done)

    def body(s):
        k, x, r, p, rz, done = s
        Ap = A(p)
        pAp = jnp.sum(p * Ap, axis=0)
        alpha = jnp.where(done, 0.0, rz / jnp.where(done, 1.0, pAp))
        x = x + alpha * p
        r = r - alpha * Ap
        done = done | (jnp.linalg.norm(r, axis=0) <= tol)
        z = M(r)
        rz_new = jnp.sum(r * z, axis=0)
        beta = jnp.where(done, 0.0, rz_new / jnp.where(rz == 0, 1.0, rz))
        p = z + beta * p
        return k + 1, x, r, p, rz_new, done

    k, x, r, p, rz, done = jax.lax.while_loop(cond, body, (0, x, r, p, rz, done))
    return x, k, done


class CGState(eqx.Module):
    """What `BlockCG.init` returns: the preconditioner's host-built plans."""

    preconditioner: object


class BlockCG(AbstractSolver):
    """Preconditioned conjugate gradients on all right-hand sides at once, in pure JAX.

    Runs under jit and vmap and on GPU. One sparse mat-mat product per step for all columns;
    each column has its own step sizes (simultaneous CG rather than O'Leary's block Krylov,
    which needs rank deflation). Stops when every column has ||r|| <= max(rtol ||b||, atol);
    otherwise raises through `eqx.error_if`.

    Arguments:
        preconditioner: `SmoothedAggregation()` (default) or `Jacobi()`.
        rtol, atol: residual tolerances (relative to ||b||, absolute).
        max_steps: iteration limit.
    """

    preconditioner: eqx.Module = eqx.field(static=True,
                                           default_factory=lambda: SmoothedAggregation())
    rtol: float = eqx.field(static=True, default=1e-10)
    atol: float = eqx.field(static=True, default=0.0)
    max_steps: int = eqx.field(static=True, default=2000)

    def __check_init__(self):
        if not (self.rtol >= 0 and self.atol >= 0 and self.rtol + self.atol > 0):
            raise ValueError(f"BlockCG needs rtol, atol >= 0, not both 0; got {self.rtol}, "
                             f"{self.atol}.")
        if self.max_steps < 1:
            raise ValueError(f"`max_steps` must be >= 1, got {self.max_steps}.")

    def init(self, pattern: Pattern, values: np.ndarray) -> CGState:
        return CGState(self.preconditioner.init(pattern, values))

    def solve_with_stats(self, state: CGState, pattern: PatternArrays, values, rhs):
        """(x, steps, converged) without raising; for diagnostics and benchmarks."""
        vec = rhs.ndim == 1
        b = rhs[:, None] if vec else rhs
        M = self.preconditioner.build(state.preconditioner, pattern, values)
        x, k, done = pcg(lambda v: matvec(pattern, values, v), M, b, rtol=self.rtol,
                         atol=self.atol, max_steps=self.max_steps)
        return (x[:, 0] if vec else x), k, done

    def raw_solve(self, state: CGState, pattern: PatternArrays, values, rhs):
        x, k, done = self.solve_with_stats(state, pattern, values, rhs)
        x = eqx.error_if(
            x, ~jnp.all(done),
            f"BlockCG did not reach rtol={self.rtol} in max_steps={self.max_steps}: raise "
            "max_steps, loosen rtol, or use Direct(); a singular or indefinite matrix (sigma "
            "<= 0, inverted tets) also stalls CG.")
        return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)),
                            "BlockCG produced NaN/Inf: the FEM matrix is singular or invalid.")
