"""Morphing a reference mesh: interfaces moved along their normals, the interior by a harmonic
extension. Same topology, so the morphed head is a node array for `simulate(..., nodes=x)`.  [host set-up; jax apply]

An interface is the outer surface of the union of tissues <= t (t = BRAIN, CSF, SKULL; SCALP's is
the head's outer boundary), oriented outward, with area-weighted vertex normals. A displacement
field d_t (mm, one value per vertex of interface t, positive outward) moves every interface
vertex by d_t n; interior nodes follow the harmonic extension of the interface displacements
(Laplace's equation per coordinate with the reference mesh's P1 stiffness and the interface
nodes as Dirichlet data), the standard mesh-moving scheme (e.g. Stein, Tezduyar & Benney 2003,
J. Appl. Mech. 70:58, whose "Jacobian-based stiffening" weights each tet's stiffness by
(V_mean / V_e)^chi so small tets deform less; chi = `stiffening`).

The extension is a fixed linear map u_I = E u_B, E = -K_II^{-1} K_IB, factorised once on the
host (SciPy). `morph_nodes` applies it inside JAX through `pure_callback` with a custom VJP
(the transpose E^T y = -K_IB^T K_II^{-1} y, K_II symmetric), so voltages are differentiable with
respect to the displacement fields under `jax.grad` / `jax.jacrev`.
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..geometry import TetMesh, face_adjacency, signed_volumes, tet_metrics
from ..geometry.quality import outside_range
from ..tissue import TISSUES, Tissue


class MorphError(ValueError):
    """A morph inverted or flattened tets: the sample has no valid mesh."""


class Interface(eqx.Module):
    """One interface surface of a mesh (the outer surface of tissues <= `tissue`).

    Attributes:
        tissue: the inner tissue's value (1..4); SCALP's interface is the head's surface.
        vertices: (n_v,) mesh node index of every surface vertex.
        faces: (n_f, 3) triangles in local vertex indices, outward.
        normals: (n_v, 3) unit area-weighted vertex normals, outward.
        areas_mm2: (n_v,) a third of the area of the faces around each vertex (sums to the area).
    """

    tissue: int = eqx.field(static=True)
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    areas_mm2: np.ndarray

    @property
    def name(self) -> str:
        return Tissue(self.tissue).name.lower()

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[0]

    def points(self, nodes=None) -> np.ndarray:
        """(n_v, 3) vertex positions in mm (of `nodes`, default the reference mesh's)."""
        return np.asarray(nodes)[self.vertices]


def interface_surfaces(mesh: TetMesh) -> dict[Tissue, Interface]:
    """The mesh's interfaces: for each tissue t, the faces between tissues <= t and > t (or outside).

    Arguments:
        mesh: a TetMesh (positively oriented tets).

    Returns:
        {Tissue: Interface} for every tissue present whose surface is non-empty.
    """
    faces, owner, a, b, _ = face_adjacency(mesh.tets)
    owner_label = mesh.labels[owner]
    # label on the other side of each face (0 = outside the mesh)
    other = np.zeros(len(faces), np.int64)
    other[a], other[b] = owner_label[b], owner_label[a]
    out = {}
    for t in TISSUES:
        sel = (owner_label <= int(t)) & (other > int(t)) | ((owner_label <= int(t)) & (other == 0))
        if not sel.any():
            continue
        f = faces[sel]
        verts, local = np.unique(f, return_inverse=True)
        local = local.reshape(-1, 3)
        p = mesh.nodes[f]
        cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # 2 * area * outward unit normal
        n = np.zeros((len(verts), 3))
        for k in range(3):
            np.add.at(n, local[:, k], cross)
        norm = np.linalg.norm(n, axis=1)
        if np.any(norm == 0):
            raise ValueError(f"interface {t.name.lower()} has vertices with a zero normal "
                             "(faces cancelling); the mesh's interfaces are not manifold.")
        area = np.zeros(len(verts))
        np.add.at(area, local.ravel(), np.repeat(0.5 * np.linalg.norm(cross, axis=1) / 3.0, 3))
        out[t] = Interface(int(t), verts, local, n / norm[:, None], area)
    return out


def laplacian(nodes, tets, *, stiffening: float = 0.0) -> sp.csr_matrix:
    """P1 stiffness matrix of -div(w grad u) with per-tet weight w = (V_mean / V_e)^stiffening.

    Arguments:
        nodes: (n_nodes, 3) positions in mm; tets: (n_tets, 4) node indices.
        stiffening: Jacobian-based stiffening exponent chi (0: plain Laplacian).

    Returns:
        (n_nodes, n_nodes) symmetric positive semi-definite CSR matrix (mm; K @ 1 = 0).
    """
    x = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    p = x[tets]
    M = np.concatenate([np.ones((len(tets), 4, 1)), p], axis=2)  # rows [1, x, y, z]
    vol = np.abs(signed_volumes(x, tets))
    G = np.linalg.inv(M)[:, 1:, :]  # (n, 3, 4): gradients of the 4 barycentric functions
    w = (vol.mean() / vol) ** float(stiffening) if stiffening else np.ones(len(tets))
    Ke = (w * vol)[:, None, None] * np.einsum("nka,nkb->nab", G, G)
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    n = x.shape[0]
    return sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()


class _Extension:
    """Host factor of K_II and the coupling K_IB: u_I = -K_II^{-1} K_IB u_B (and its transpose)."""

    def __init__(self, K: sp.csr_matrix, fixed: np.ndarray, free: np.ndarray):
        self.K_ib = K[free][:, fixed].tocsc()
        self.n_free, self.n_fixed = len(free), len(fixed)
        self.lu = spla.splu(K[free][:, free].tocsc(), permc_spec="MMD_AT_PLUS_A") if len(free) else None

    def apply(self, u_b: np.ndarray) -> np.ndarray:
        """(n_fixed, k) -> (n_free, k)."""
        u_b = np.asarray(u_b, dtype=np.float64)
        if self.lu is None:
            return np.zeros((0,) + u_b.shape[1:])
        return -self.lu.solve(np.asarray(self.K_ib @ u_b))

    def transpose(self, y: np.ndarray) -> np.ndarray:
        """(n_free, k) -> (n_fixed, k): E^T y = -K_IB^T K_II^{-1} y."""
        y = np.asarray(y, dtype=np.float64)
        if self.lu is None:
            return np.zeros((self.n_fixed,) + y.shape[1:])
        return -(self.K_ib.T @ self.lu.solve(y))


class Morph(eqx.Module):
    """A reference mesh prepared for morphing (build with `build_morph`).

    Attributes:
        nodes: (n_nodes, 3) reference positions in mm; tets: (n_tets, 4).
        interfaces: {Tissue: Interface}.
        fixed: (n_fixed,) nodes on any interface (Dirichlet data of the extension).
        free: (n_free,) the other (interior) nodes.
        stiffening: the extension's stiffening exponent.
        extension: the host factorisation (static).
    """

    nodes: np.ndarray
    tets: np.ndarray
    interfaces: dict
    fixed: np.ndarray
    free: np.ndarray
    stiffening: float = eqx.field(static=True)
    extension: _Extension = eqx.field(static=True)
    ref_quality: tuple = eqx.field(static=True, default=())

    def interface(self, tissue) -> Interface:
        t = Tissue.parse(tissue)
        if t not in self.interfaces:
            raise ValueError(f"the mesh has no {t.name.lower()} interface; interfaces: "
                             f"{[k.name.lower() for k in self.interfaces]}.")
        return self.interfaces[t]


def build_morph(mesh: TetMesh, *, stiffening: float = 1.0) -> Morph:
    """Find the mesh's interfaces and factorise the harmonic extension of their displacements.

    Arguments:
        mesh: the reference TetMesh (mm).
        stiffening: Jacobian-based stiffening exponent (Stein et al. 2003; 0 plain Laplacian;
            1 makes small tets near thin layers stiffer, so they keep their shape).

    Returns:
        A Morph for `morph_nodes`.
    """
    if not isinstance(mesh, TetMesh):
        raise ValueError(f"`mesh` must be a jaxhead TetMesh, got {type(mesh).__name__}.")
    if not np.isfinite(stiffening) or stiffening < 0:
        raise ValueError(f"`stiffening` must be >= 0, got {stiffening}; 0 is the plain Laplacian.")
    surf = interface_surfaces(mesh)
    fixed = np.unique(np.concatenate([s.vertices for s in surf.values()]))
    free = np.setdiff1d(np.arange(mesh.n_nodes), fixed)
    K = laplacian(mesh.nodes, mesh.tets, stiffening=stiffening)
    return Morph(mesh.nodes.copy(), mesh.tets.copy(), surf, fixed, free, float(stiffening),
                 _Extension(K, fixed, free), _quality_counts(mesh.nodes, mesh.tets))


def _quality_counts(nodes, tets) -> tuple:
    """(n_inverted, min scaled Jacobian, n below 0.2, n with condition > 3) of a tet mesh."""
    m = {k: np.asarray(v) for k, v in tet_metrics(np.asarray(nodes, np.float64), tets).items()}
    return (int((m["jacobian"] <= 0).sum()), float(m["scaled_jacobian"].min()),
            int((m["scaled_jacobian"] < 0.2).sum()),
            int(outside_range("condition", m["condition"]).sum()))


def _callback(fn, x, n_out):
    shape = jax.ShapeDtypeStruct((n_out,) + x.shape[1:], jnp.float64)
    return jax.pure_callback(lambda a: fn(np.asarray(a)).astype(np.float64), shape, x,
                             vmap_method="sequential")


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _extend(ext: _Extension, u_b):
    return _callback(ext.apply, u_b, ext.n_free)


def _extend_fwd(ext, u_b):
    return _extend(ext, u_b), None


def _extend_bwd(ext, _, g):
    return (_callback(ext.transpose, g, ext.n_fixed),)


_extend.defvjp(_extend_fwd, _extend_bwd)


def _boundary_displacement(morph: Morph, displacement) -> jax.Array:
    """(n_fixed, 3) displacement of the interface nodes from normal displacements per interface."""
    if not isinstance(displacement, dict):
        raise ValueError("`displacement` must be a dict {tissue: (n_vertices,) mm}, got "
                         f"{type(displacement).__name__}.")
    pos = np.full(morph.nodes.shape[0], -1, np.int64)
    pos[morph.fixed] = np.arange(morph.fixed.size)
    u_b = jnp.zeros((morph.fixed.size, 3))
    for key, d in displacement.items():
        s = morph.interface(key)
        d = jnp.asarray(d, dtype=jnp.float64)
        if d.shape != (s.n_vertices,):
            raise ValueError(f"displacement of the {s.name} interface has shape {d.shape}; pass "
                             f"one value per interface vertex ({s.n_vertices},), in mm.")
        u_b = u_b.at[pos[s.vertices]].add(d[:, None] * jnp.asarray(s.normals))
    return u_b


def morph_nodes(morph: Morph, displacement) -> jax.Array:
    """Node positions of the morphed mesh (differentiable in the displacements).

    Arguments:
        morph: from `build_morph`.
        displacement: {tissue: (n_vertices,) normal displacement in mm of that interface's
            vertices, positive outward}; interfaces not given stay where they are.

    Returns:
        (n_nodes, 3) positions in mm (a JAX array), for `simulate(model, sigma, protocol,
        nodes=...)`.
    """
    u_b = _boundary_displacement(morph, displacement)
    u_i = _extend(morph.extension, u_b)
    x = jnp.asarray(morph.nodes)
    return x.at[morph.fixed].add(u_b).at[morph.free].add(u_i)


def extension_transpose(morph: Morph, y) -> np.ndarray:
    """E^T y for interior-node cotangents y (n_free, k) -> (n_fixed, k) (host; for chains)."""
    return morph.extension.transpose(np.asarray(y))


@dataclasses.dataclass(frozen=True)
class MorphQuality:
    """Quality of a morphed mesh against its reference (Verdict metrics, `tet_metrics`).

    Attributes:
        n_inverted: tets with Jacobian <= 0 (any makes the sample invalid).
        min_scaled_jacobian, ref_min_scaled_jacobian: worst scaled Jacobian, morphed and reference.
        n_below_sj_0_2, ref_n_below_sj_0_2: tets with scaled Jacobian < 0.2.
        n_condition_above_3, ref_n_condition_above_3: tets with condition number > 3.
        max_displacement_mm: the largest node displacement.
    """

    n_inverted: int
    min_scaled_jacobian: float
    ref_min_scaled_jacobian: float
    n_below_sj_0_2: int
    ref_n_below_sj_0_2: int
    n_condition_above_3: int
    ref_n_condition_above_3: int
    max_displacement_mm: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def morph_quality(morph: Morph, nodes, *, raise_on_inverted: bool = True) -> MorphQuality:
    """Tet quality of morphed nodes vs the reference; inverted tets raise `MorphError`.

    Arguments:
        morph: the Morph; nodes: (n_nodes, 3) morphed positions in mm.
        raise_on_inverted: raise MorphError when any tet has Jacobian <= 0.
    """
    x = np.asarray(nodes, dtype=np.float64)
    m = _quality_counts(x, morph.tets)
    r = morph.ref_quality or _quality_counts(morph.nodes, morph.tets)  # cached by build_morph
    q = MorphQuality(
        n_inverted=m[0], min_scaled_jacobian=m[1], ref_min_scaled_jacobian=r[1],
        n_below_sj_0_2=m[2], ref_n_below_sj_0_2=r[2],
        n_condition_above_3=m[3], ref_n_condition_above_3=r[3],
        max_displacement_mm=float(np.linalg.norm(x - morph.nodes, axis=1).max()))
    if raise_on_inverted and q.n_inverted:
        raise MorphError(
            f"the morph inverts {q.n_inverted} tets (worst scaled Jacobian "
            f"{q.min_scaled_jacobian:.3g}); the displacement is too large for the layer "
            f"thickness (max node displacement {q.max_displacement_mm:.2f} mm). Lower the "
            "amplitude, lengthen the correlation, or use the re-mesh route.")
    return q
