"""P1 finite-element assembly: sparsity built once on the host, values vectorised in JAX.  [jax]

The engine follows scikit-fem's split (Gustafsson & McBain 2020, JOSS 5:2369): the integer
topology of the global matrix (its upper-triangular CSR pattern and, for every element entry, the
index of the non-zero it adds into) is computed once with NumPy; the element values are computed
in JAX from node positions and conductivities, so derivatives with respect to both flow through a
single `segment_sum`.

Units: this module is the ONE place where geometry is converted from millimetres (the mesh's
world frame) to metres (SI physics): `MM_TO_M`. Everything it returns is SI: stiffness entries in
S, boundary masses in m^2.

Element formulas for a tet with nodes p0..p3 (positively oriented), edges e_k = p_k - p0,
det = e1 . (e2 x e3) = 6 V:
    c1 = e2 x e3,  c2 = e3 x e1,  c3 = e1 x e2,  c0 = -(c1 + c2 + c3),
    grad phi_a = c_a / det,
    K_ab = sigma V grad phi_a . grad phi_b = sigma (c_a . c_b) / (6 det).
For a triangle of area |T|: int_T phi_a phi_b dS = |T| (1 + delta_ab) / 12 and
int_T phi_a dS = |T| / 3.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

#: Millimetres to metres: the single geometry unit conversion of the FEM.
MM_TO_M = 1e-3

#: Local (a, b) index pairs with a <= b of a tet's 4x4 element matrix (upper triangle, 10).
TET_PAIRS = np.array([(a, b) for a in range(4) for b in range(a, 4)], dtype=np.int64)
#: Local (a, b) index pairs with a <= b of a triangle's 3x3 element matrix (6).
TRI_PAIRS = np.array([(a, b) for a in range(3) for b in range(a, 3)], dtype=np.int64)


def to_metres(nodes_mm):
    """Node positions in metres from millimetres (the FEM's only unit conversion)."""
    return nodes_mm * MM_TO_M


# ----------------------------------------------------------------------------------------------
# Element values (JAX, differentiable in the node positions)


def tet_geometry(nodes_m, tets):
    """Area-normal vectors and 6x volumes of tets.

    Arguments:
        nodes_m: (n_nodes, 3) node positions in metres.
        tets: (n_tets, 4) node indices.

    Returns:
        c: (n_tets, 4, 3) vectors with grad phi_a = c[:, a] / det (m^2).
        det: (n_tets,) 6 x signed volume (m^3).
    """
    p = nodes_m[tets]
    e1, e2, e3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    c1, c2, c3 = jnp.cross(e2, e3), jnp.cross(e3, e1), jnp.cross(e1, e2)
    c0 = -(c1 + c2 + c3)
    c = jnp.stack([c0, c1, c2, c3], axis=1)
    det = jnp.einsum("ij,ij->i", e1, c1)
    return c, det


def _pairs_dot(c, d):
    """(n, 10) of c_a . d_b over `TET_PAIRS` for per-tet vectors c, d: (4, n, 3) lists."""
    return jnp.stack([jnp.sum(c[a] * d[b], axis=-1) for a, b in TET_PAIRS.tolist()], axis=1)


def _edges_to_c(e1, e2, e3):
    c1, c2, c3 = jnp.cross(e2, e3), jnp.cross(e3, e1), jnp.cross(e1, e2)
    return [-(c1 + c2 + c3), c1, c2, c3]


@jax.custom_jvp
def _stiffness_from_points(p):
    """(n, 10) unit-sigma stiffness entries from tet vertex positions p (n, 4, 3) in m."""
    e1, e2, e3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    c = _edges_to_c(e1, e2, e3)
    det = jnp.sum(e1 * c[1], axis=-1)
    return _pairs_dot(c, c) / (6.0 * det[:, None])


@_stiffness_from_points.defjvp
def _stiffness_jvp(primals, tangents):
    # Written out (product rule on the cross products and det = e1 . (e2 x e3)) so that the
    # linear map, and its transpose in reverse mode, is plain element-wise arithmetic:
    # autodiff of the primal was ~30x slower on CPU.
    (p,), (dp,) = primals, tangents
    e1, e2, e3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    d1, d2, d3 = dp[:, 1] - dp[:, 0], dp[:, 2] - dp[:, 0], dp[:, 3] - dp[:, 0]
    c = _edges_to_c(e1, e2, e3)
    dc1 = jnp.cross(d2, e3) + jnp.cross(e2, d3)
    dc2 = jnp.cross(d3, e1) + jnp.cross(e3, d1)
    dc3 = jnp.cross(d1, e2) + jnp.cross(e1, d2)
    dc = [-(dc1 + dc2 + dc3), dc1, dc2, dc3]
    det = jnp.sum(e1 * c[1], axis=-1)
    ddet = jnp.sum(d1 * c[1], axis=-1) + jnp.sum(e1 * dc1, axis=-1)
    k = _pairs_dot(c, c) / (6.0 * det[:, None])
    dk = (_pairs_dot(dc, c) + _pairs_dot(c, dc)) / (6.0 * det[:, None]) \
        - k * (ddet / det)[:, None]
    return k, dk


def tet_stiffness(nodes_m, tets):
    """Unit-conductivity P1 element stiffness, upper-triangle entries in `TET_PAIRS` order.

    Arguments:
        nodes_m: (n_nodes, 3) node positions in metres.
        tets: (n_tets, 4) node indices, positively oriented.

    Returns:
        (n_tets, 10) entries int grad phi_a . grad phi_b dx in metres (S per S/m).
    """
    return _stiffness_from_points(nodes_m[tets])


def tet_field_gradients(nodes_m, tets, u):
    """Gradients of P1 fields on each tet.

    Arguments:
        nodes_m: (n_nodes, 3) node positions in metres.
        tets: (n_tets, 4) node indices.
        u: (n_nodes, n_fields) nodal values (V).

    Returns:
        (n_tets, 3, n_fields) gradients (V/m), constant on each tet.
    """
    c, det = tet_geometry(nodes_m, tets)
    cd = c / det[:, None, None]
    return sum(cd[:, a, :, None] * u[tets[:, a]][:, None, :] for a in range(4))


def face_areas(nodes_m, faces):
    """Triangle areas in m^2, shape (n_faces,)."""
    p = nodes_m[faces]
    n = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    # sqrt of a sum of squares: safe gradient for non-degenerate faces (checked at build time).
    return 0.5 * jnp.sqrt(jnp.sum(n * n, axis=1))


def face_mass(areas):
    """P1 boundary mass entries int phi_a phi_b dS, (n_faces, 6) in `TRI_PAIRS` order (m^2)."""
    w = np.where(TRI_PAIRS[:, 0] == TRI_PAIRS[:, 1], 2.0, 1.0) / 12.0
    return areas[:, None] * jnp.asarray(w)[None, :]


# ----------------------------------------------------------------------------------------------
# Sparsity pattern (host)


class Pattern:
    """Upper-triangular CSR pattern of a symmetric matrix plus its full-pattern view.  [host]

    Identity-hashed (it is static data of a ForwardModel); arrays are read-only NumPy.

    Attributes:
        n: matrix size.
        indptr, indices: (n + 1,), (nnz,) upper-triangular CSR (column indices sorted, diagonal
            included), int64.
        rows: (nnz,) row of each stored entry.
        full_rows, full_cols: (nnz_full,) COO of the full symmetric pattern, sorted by row.
        full_to_upper: (nnz_full,) stored entry of each full-pattern entry.
        diag: (n,) stored entry of each diagonal element.
    """

    def __init__(self, n: int, i: np.ndarray, j: np.ndarray):
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        key = np.unique(lo * n + hi)
        self.n = int(n)
        self.rows = key // n
        self.indices = key % n
        self.nnz = key.size
        self.indptr = np.searchsorted(self.rows, np.arange(n + 1)).astype(np.int64)
        if np.any(np.diff(self.indptr) == 0):
            raise ValueError("the pattern has an empty row: some unknown is in no element.")
        self.diag = self.indptr[:-1]
        if not np.all(self.indices[self.diag] == np.arange(n)):
            raise ValueError("the pattern lacks a diagonal entry; every unknown needs one.")
        off = np.flatnonzero(self.rows != self.indices)
        fr = np.concatenate([self.rows, self.indices[off]])
        fc = np.concatenate([self.indices, self.rows[off]])
        fu = np.concatenate([np.arange(self.nnz), off])
        order = np.lexsort((fc, fr))
        self.full_rows, self.full_cols, self.full_to_upper = fr[order], fc[order], fu[order]
        for a in (self.rows, self.indices, self.indptr, self.full_rows, self.full_cols,
                  self.full_to_upper, self.diag):
            a.flags.writeable = False
        self._key = key

    def locate(self, i, j) -> np.ndarray:
        """Stored-entry index of each (i, j) (either triangle); raises if not in the pattern."""
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        k = np.minimum(i, j) * self.n + np.maximum(i, j)
        pos = np.searchsorted(self._key, k)
        pos = np.minimum(pos, self.nnz - 1)
        if not np.all(self._key[pos] == k):
            raise ValueError("entries outside the sparsity pattern were requested.")
        return pos

    def to_scipy(self, values, full: bool = True):
        """SciPy CSR matrix from stored values (full symmetric, or upper triangle)."""

        values = np.asarray(values, dtype=np.float64)
        if not full:
            return sp.csr_matrix((values, self.indices, self.indptr), shape=(self.n, self.n))
        return sp.csr_matrix((values[self.full_to_upper], (self.full_rows, self.full_cols)),
                             shape=(self.n, self.n))


def spmv(pattern: Pattern, values, x):
    """Symmetric sparse matrix times x from stored (upper) values; x is (n,) or (n, k)."""
    v = values[pattern.full_to_upper]
    xv = x[pattern.full_cols]
    prod = v.reshape(v.shape + (1,) * (x.ndim - 1)) * xv
    return jax.ops.segment_sum(prod, pattern.full_rows, num_segments=pattern.n,
                               indices_are_sorted=True)


def scatter_plan(targets, nnz: int, complete: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Sorted segment-sum plan: where each element entry goes.  [host]

    Arguments:
        targets: (n_contrib,) stored-entry index of each contribution, in the order the
            contributions are concatenated.
        nnz: number of stored entries.
        complete: require every stored entry to receive a contribution.

    Returns:
        order: (n_contrib,) permutation sorting the contributions by target.
        sorted_targets: (n_contrib,) targets in that order (for `scatter_add`).
    """
    targets = np.asarray(targets, np.int64)
    order = np.argsort(targets, kind="stable")
    sorted_targets = targets[order]
    if complete and np.unique(sorted_targets).size != nnz:
        raise ValueError("some stored entries receive no contribution.")
    return order, sorted_targets


def scatter_add(contributions, order, sorted_targets, nnz: int):
    """Sum (n_contrib, ...) contribution values into (nnz, ...) stored entries (`scatter_plan`)."""
    return jax.ops.segment_sum(contributions[order], sorted_targets, num_segments=nnz,
                               indices_are_sorted=True)
