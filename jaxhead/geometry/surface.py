"""Closed triangle surfaces of the nested tissue solids: extraction, repair, remeshing, checks.  [host]

:func:`extract_surfaces` turns a layered label map (see ``jaxhead.geometry.layers.make_layers``)
into one surface per nested solid (BRAIN: brain; CSF: brain+CSF; SKULL: +skull; SCALP: the whole
head), the seed paper's marching cubes + MeshLab steps (Vonach et al. 2012) done automatically:

1. ``marching cubes`` (Lewiner et al. 2003, scikit-image) at level 0.5 of the solid's mask,
   cavities filled, slightly Gaussian-smoothed (``presmooth_sigma_voxels``) against voxel
   staircases, on a zero-padded crop, mapped to world mm by the affine. Gaussian smoothing is a
   positive operator, so nested masks give nested smoothed fields and nested level sets.
2. ``repair``: keep the largest connected component, fill holes, make the winding consistent and
   outward (trimesh); everything repaired is counted in the :class:`SurfaceReport`.
3. ``smooth``: Taubin lambda|mu smoothing (Taubin 1995, SIGGRAPH), which removes the voxel
   staircase without the shrinkage of plain Laplacian smoothing.
4. ``remesh`` to a target edge length per surface: quadric decimation (Garland & Heckbert 1997,
   fast-simplification) to twice the target face count, then isotropic remeshing by edge
   split/collapse/flip and tangential relaxation with projection back onto the surface (Botsch &
   Kobbelt 2004, gpytoolbox.remesh_botsch). ``remesh="decimate"`` stops after the decimation.
5. ``gap``: surfaces are pulled apart to ``min_gap_mm`` outside in (SKULL inside SCALP, CSF inside
   SKULL, BRAIN inside CSF) by moving offending vertices of the inner surface inward along their
   normals (signed distances by AABB tree and fast winding number, gpytoolbox); the outer surface
   never moves. The gap is then checked exactly (triangle-triangle distances, manifold3d); where
   it is short although every vertex is clear (a ridge of one surface under the middle of a
   face of the other), the step is repeated with denser samples on the faces near the other
   surface (``gap_sample_density`` in the report).
6. ``checks``: every surface is watertight and edge- and vertex-manifold, consistently outward
   (positive volume), one component, without self-intersections (:func:`self_intersections`), and
   nested with the gap (:func:`surface_gap_mm`). Failure raises ValueError naming the tissue.

Edge lengths (``edge_mm``). A shell of thickness t meshed from surfaces with edges h >> t gets
flat tets (poor scaled Jacobian) unless the tetrahedraliser refines, and the field in a thin,
high-contrast shell (CSF at 1.79 S/m shunting current past the 0.018 S/m skull) is what EIT is
most sensitive to. So each surface's edge is about the thickness of the shell it bounds, giving
one to two tets across each shell (fTetWild refines locally where a shell is thinner, to keep its
AMIPS energy bounded): CSF 4 mm (subarachnoid plus sulcal CSF ~2-4 mm), SKULL 4.5 mm (skull
4-7 mm), SCALP 6 mm (scalp 5-7 mm; electrodes ~10 mm across), and BRAIN 6 mm (the inner side of
the CSF; scalp EIT's sensitivity falls off inward). This is the seed paper's adaptive meshing
(finer thin layers) at its element budget: about 300k tets for an adult head (Vonach et al. 2012,
Table 2), not more surface detail than the 1 mm voxels carry.
"""

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import equinox as eqx
import fast_simplification
import gpytoolbox
import manifold3d as m3
import numpy as np
import trimesh
from scipy import ndimage as ndi
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from ..tissue import TISSUES, Tissue, per_tissue
from ..volume import LabelMap
from .tetmesh import enclosed_volume

log = logging.getLogger(__name__)


class Surface(eqx.Module):
    """A closed, outward-oriented triangle surface in world mm.

    Arguments:
        vertices: (n_verts, 3) positions in mm (float64).
        faces: (n_faces, 3) vertex indices, counter-clockwise seen from outside.
        tissue: the Tissue whose nested solid this surface bounds on the outside
            (BRAIN: brain; CSF: brain+CSF; SKULL: +skull; SCALP: the whole head).
    """

    vertices: np.ndarray
    faces: np.ndarray
    tissue: Tissue = eqx.field(static=True)

    def __init__(self, vertices, faces, tissue):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.tissue = Tissue.parse(tissue)

    def __check_init__(self):
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"`vertices` must have shape (n_verts, 3), got {self.vertices.shape}.")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or self.faces.shape[0] == 0:
            raise ValueError(f"`faces` must have shape (n_faces, 3), n_faces >= 1; got {self.faces.shape}.")
        if self.faces.min() < 0 or self.faces.max() >= self.vertices.shape[0]:
            raise ValueError(
                f"`faces` indexes vertices {self.faces.min()}..{self.faces.max()} but there are "
                f"{self.vertices.shape[0]} vertices."
            )
        if not np.all(np.isfinite(self.vertices)):
            raise ValueError(f"{self.tissue.name} surface has NaN/Inf vertices.")


# ---------------------------------------------------------------------------------------------
# Configuration and report

_DEFAULT_EDGE_MM = {"brain": 6.0, "csf": 4.0, "skull": 4.5, "scalp": 6.0}


@dataclass(frozen=True, kw_only=True)
class SurfaceConfig:
    """Settings of :func:`extract_surfaces`.

    Arguments:
        edge_mm: target edge length per surface (mm), one number or a mapping with keys brain,
            csf, skull, scalp (see the module docstring for the defaults' reasoning).
        remesh: "isotropic" (decimate, then Botsch-Kobbelt remeshing: uniform edges) or
            "decimate" (quadric decimation to the target face count only: faster, wider spread).
        remesh_iterations: Botsch-Kobbelt iterations.
        presmooth_sigma_voxels: Gaussian sigma (voxels) applied to each solid's mask before
            marching cubes; 0 = none (then the staircase is left to the Taubin step).
        taubin_iterations: Taubin steps (alternating lambda and mu, so half as many pairs).
        taubin_lambda, taubin_mu: Taubin's lambda > 0 and mu < -lambda; pass-band
            k = 1/lambda + 1/mu should be 0.01..0.1 (Taubin 1995). Defaults 0.5, -0.52: k = 0.077.
        min_gap_mm: minimum distance between consecutive surfaces. Keep it above twice the
            tetrahedraliser's envelope (fTetWild: 1e-3 x bounding-box diagonal, ~0.3 mm for a
            head) so it cannot merge the two surfaces.
        max_gap_iterations: rounds of pushing inner vertices inward before giving up.
        check_self_intersections: run :func:`self_intersections` on every final surface.
    """

    edge_mm: float | dict[str, float] = field(default_factory=lambda: dict(_DEFAULT_EDGE_MM))
    remesh: Literal["isotropic", "decimate"] = "isotropic"
    remesh_iterations: int = 3
    presmooth_sigma_voxels: float = 0.5
    taubin_iterations: int = 20
    taubin_lambda: float = 0.5
    taubin_mu: float = -0.52
    min_gap_mm: float = 0.5
    max_gap_iterations: int = 20
    check_self_intersections: bool = True

    def __post_init__(self):
        per_tissue(self.edge_mm, "edge_mm")
        if self.remesh not in ("isotropic", "decimate"):
            raise ValueError(f"`remesh` = {self.remesh!r}; choose 'isotropic' or 'decimate'.")
        for name in ("remesh_iterations", "taubin_iterations", "max_gap_iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"`{name}` must be an integer >= 0, got {v!r}.")
        if not (self.presmooth_sigma_voxels >= 0 and math.isfinite(self.presmooth_sigma_voxels)):
            raise ValueError(f"`presmooth_sigma_voxels` must be >= 0, got {self.presmooth_sigma_voxels!r}.")
        if not 0 < self.taubin_lambda < 1:
            raise ValueError(f"`taubin_lambda` must be in (0, 1), got {self.taubin_lambda!r}.")
        if not -1 < self.taubin_mu < -self.taubin_lambda:
            raise ValueError(
                f"`taubin_mu` must satisfy -1 < mu < -lambda = {-self.taubin_lambda}, got "
                f"{self.taubin_mu!r} (Taubin 1995: mu slightly more negative than -lambda).")
        if not (self.min_gap_mm >= 0 and math.isfinite(self.min_gap_mm)):
            raise ValueError(f"`min_gap_mm` must be >= 0, got {self.min_gap_mm!r}.")

    def edges(self) -> dict[Tissue, float]:
        """Target edge length per tissue (mm)."""
        return per_tissue(self.edge_mm, "edge_mm")


@dataclass(frozen=True)
class SurfaceStats:
    """What happened to one surface, and what it is.

    Arguments:
        tissue: the nested solid's tissue.
        solid_voxels: voxels of the (cavity-filled) solid; cavity_voxels: cavities filled.
        voxel_volume_mm3: solid voxels times voxel volume.
        mc_faces: marching-cubes triangles.
        components_dropped, faces_dropped: small components removed (after marching cubes
            and after remeshing together).
        hole_faces_added: faces added to close holes; faces_flipped: faces whose winding was fixed.
        gap_vertices_moved: vertices pushed inward for the gap; max_move_mm: the largest push.
        n_verts, n_faces, area_mm2, volume_mm3: the final surface.
        edge_target_mm: the target; edge_mm: (min, 5%, median, mean, 95%, max) edge lengths.
        gap_to_outer_mm: exact minimum distance to the next surface out, capped at
            max(3 mm, 2 min_gap_mm) (None for SCALP).
        self_intersections: intersecting face pairs (None if not checked).
        seconds: wall time per step.
        untangled_pairs: self-intersecting face pairs found and repaired (after remeshing and
            after the gap step, summed); untangle_rounds: local smoothing rounds they took;
            untangled_vertices: vertices moved by them.
        remesh_retries: times the surface was remeshed again at a finer edge because local
            smoothing could not remove its self-intersections.
        gap_rounds: separate -> untangle rounds the gap step took (1 when nothing was repaired).
        gap_sample_density: samples per face edge the gap step needed (1: the vertices were
            enough; 2, 4, 8: the exact gap was short with fewer, see ``_separate``).
    """

    tissue: Tissue
    solid_voxels: int
    cavity_voxels: int
    voxel_volume_mm3: float
    mc_faces: int
    components_dropped: int
    faces_dropped: int
    hole_faces_added: int
    faces_flipped: int
    gap_vertices_moved: int
    max_move_mm: float
    n_verts: int
    n_faces: int
    area_mm2: float
    volume_mm3: float
    edge_target_mm: float
    edge_mm: tuple[float, float, float, float, float, float]
    gap_to_outer_mm: float | None
    self_intersections: int | None
    seconds: Mapping[str, float]
    untangled_pairs: int = 0
    untangle_rounds: int = 0
    untangled_vertices: int = 0
    remesh_retries: int = 0
    gap_rounds: int = 1
    gap_sample_density: int = 1
    presmooth_sigma_voxels: float | None = None
    presmooth_raised: bool = False

    @property
    def n_repairs(self) -> int:
        """Components dropped + holes filled + faces flipped + self-intersections untangled +
        remesh retries + 1 if the presmoothing had to be raised."""
        return (self.components_dropped + self.hole_faces_added + self.faces_flipped
                + self.untangled_pairs + self.remesh_retries + int(self.presmooth_raised))


@dataclass(frozen=True)
class SurfaceReport:
    """Per-surface statistics of :func:`extract_surfaces` (ordered BRAIN, CSF, SKULL, SCALP)."""

    stats: Mapping[Tissue, SurfaceStats]
    min_gap_mm: float
    seconds: float

    def __getitem__(self, tissue) -> SurfaceStats:
        return self.stats[Tissue.parse(tissue)]

    def to_dict(self) -> dict:
        """A JSON-serialisable dict keyed by tissue name."""
        out = {}
        for t, s in self.stats.items():
            d = {k: getattr(s, k) for k in s.__dataclass_fields__ if k != "tissue"}
            d["edge_mm"] = dict(zip(("min", "p5", "median", "mean", "p95", "max"), s.edge_mm))
            d["seconds"] = dict(s.seconds)
            out[t.name.lower()] = d
        return {"surfaces": out, "min_gap_mm": self.min_gap_mm, "seconds": self.seconds}

    def __str__(self) -> str:
        lines = [f"extract_surfaces: {len(self.stats)} surfaces in {self.seconds:.1f} s, "
                 f"min gap {self.min_gap_mm:g} mm"]
        for t, s in self.stats.items():
            e = s.edge_mm
            gap = "-" if s.gap_to_outer_mm is None else f"{s.gap_to_outer_mm:.2f}"
            lines.append(
                f"  {t.name:<6s} {s.n_faces:>7d} faces, edge {e[2]:.2f} mm (5-95%: {e[1]:.2f}-"
                f"{e[4]:.2f}, target {s.edge_target_mm:g}), volume {s.volume_mm3 / 1e3:.1f} cm^3 "
                f"(voxels {s.voxel_volume_mm3 / 1e3:.1f}), gap to next {gap} mm")
            lines.append(
                f"         repaired: {s.components_dropped} components ({s.faces_dropped} faces) "
                f"dropped, {s.hole_faces_added} faces added to close holes, {s.faces_flipped} faces flipped, "
                f"{s.cavity_voxels} cavity voxels filled; gap: {s.gap_vertices_moved} vertices "
                f"moved (max {s.max_move_mm:.2f} mm, {s.gap_rounds} rounds"
                f"{f', {s.gap_sample_density} samples per face edge' if s.gap_sample_density > 1 else ''}"
                "); self-intersections "
                f"untangled: {s.untangled_pairs} face pairs ({s.untangle_rounds} rounds, "
                f"{s.untangled_vertices} vertices smoothed, {s.remesh_retries} finer remeshes); "
                f"left: {'-' if s.self_intersections is None else s.self_intersections}")
            if s.presmooth_raised:
                lines.append(f"         presmoothing raised to {s.presmooth_sigma_voxels:g} voxels: the "
                             "configured one's level set was not a sphere")
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Geometry helpers (public: tests and later stages use them)


def _tm(vertices, faces):

    return trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                           process=False, validate=False)


def to_trimesh(surface: Surface):
    """The surface as a `trimesh.Trimesh` (no processing: vertices and faces kept as they are)."""
    return _tm(surface.vertices, surface.faces)


def surface_volume_mm3(surface: Surface) -> float:
    """Signed enclosed volume in mm^3 (divergence theorem); positive for an outward surface."""
    return enclosed_volume(surface.vertices, surface.faces)


def surface_area_mm2(surface: Surface) -> float:
    """Total triangle area in mm^2."""
    p = surface.vertices[surface.faces]
    return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())


def edge_lengths(surface: Surface) -> np.ndarray:
    """Lengths (mm) of the unique undirected edges, shape (n_edges,)."""
    f = surface.faces
    n = surface.vertices.shape[0]
    a, b = f.ravel().astype(np.int64), f[:, [1, 2, 0]].ravel().astype(np.int64)
    key = _uniq(np.minimum(a, b) * n + np.maximum(a, b))
    e = np.stack([key // n, key % n], axis=1)
    return np.linalg.norm(surface.vertices[e[:, 0]] - surface.vertices[e[:, 1]], axis=1)


def _edge_stats(surface: Surface) -> tuple[float, ...]:
    L = edge_lengths(surface)
    return (float(L.min()), float(np.percentile(L, 5)), float(np.median(L)), float(L.mean()),
            float(np.percentile(L, 95)), float(L.max()))


def _uniq(x: np.ndarray, counts: bool = False):
    """Sorted unique values (and their counts) by one sort: numpy 2's hash-based np.unique is
    several times slower on the ~1e6 int64 edge keys of a 1 mm head surface."""
    x = np.sort(np.asarray(x).ravel())
    start = np.flatnonzero(np.concatenate([[True], x[1:] != x[:-1]])) if len(x) else np.zeros(0, int)
    if not counts:
        return x[start]
    return x[start], np.diff(np.append(start, len(x)))


def _edge_counts(faces: np.ndarray, n_verts: int) -> np.ndarray:
    """Number of faces on each unique undirected edge."""
    a, b = faces.ravel().astype(np.int64), faces[:, [1, 2, 0]].ravel().astype(np.int64)
    _, counts = _uniq(np.minimum(a, b) * n_verts + np.maximum(a, b), counts=True)
    return counts


def _vertex_fans(faces: np.ndarray, n_verts: int) -> np.ndarray:
    """Number of face fans (connected corner groups) around each vertex, shape (n_verts,)."""
    n_f = faces.shape[0]
    corner_vertex = faces.ravel()  # corner id = 3 f + j
    # each directed half-edge (a, b) of face f; its twin (b, a) in face g glues corners at a and b
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    ca = np.arange(3 * n_f)
    cb = (np.arange(n_f)[:, None] * 3 + np.array([1, 2, 0])).ravel()
    key = a.astype(np.int64) * n_verts + b
    twin = b.astype(np.int64) * n_verts + a
    order = np.argsort(key)
    pos = np.searchsorted(key[order], twin)
    pos = np.clip(pos, 0, len(key) - 1)
    found = key[order][pos] == twin
    g_a = ca[order][pos]  # the twin half-edge (b, a) starts at corner of b, ends at corner of a
    g_b = cb[order][pos]
    # corner at a in this face <-> corner at a in the twin face (its end corner), same for b
    rows = np.concatenate([ca[found], cb[found]])
    cols = np.concatenate([g_b[found], g_a[found]])
    graph = sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n_f, 3 * n_f))
    n_comp, comp = csgraph.connected_components(graph, directed=False)
    fans = np.zeros(n_verts, dtype=np.int64)
    # number of distinct components per vertex
    pairs = _uniq(corner_vertex.astype(np.int64) * (n_comp + 1) + comp)
    np.add.at(fans, pairs // (n_comp + 1), 1)
    return fans


@dataclass(frozen=True)
class SurfaceCheck:
    """Topology and geometry checks of one closed surface (see :func:`check_surface`)."""

    n_components: int
    boundary_edges: int  # edges with one face
    nonmanifold_edges: int  # edges with more than two faces
    nonmanifold_vertices: int  # vertices whose faces form more than one fan
    inconsistent_edges: int  # edges whose two faces traverse it in the same direction
    degenerate_faces: int  # zero-area faces
    volume_mm3: float
    self_intersections: int | None

    @property
    def ok(self) -> bool:
        """Watertight, manifold, consistently oriented, outward, one component, no intersections."""
        return (self.n_components == 1 and self.boundary_edges == 0 and self.nonmanifold_edges == 0
                and self.nonmanifold_vertices == 0 and self.inconsistent_edges == 0
                and self.degenerate_faces == 0 and self.volume_mm3 > 0
                and not self.self_intersections)

    def problems(self) -> list[str]:
        """Human-readable list of what fails."""
        out = []
        if self.n_components != 1:
            out.append(f"{self.n_components} components")
        for name in ("boundary_edges", "nonmanifold_edges", "nonmanifold_vertices",
                     "inconsistent_edges", "degenerate_faces"):
            if getattr(self, name):
                out.append(f"{getattr(self, name)} {name.replace('_', ' ')}")
        if not self.volume_mm3 > 0:
            out.append(f"enclosed volume {self.volume_mm3:.3g} mm^3 (inward or flat)")
        if self.self_intersections:
            out.append(f"{self.self_intersections} self-intersecting face pairs")
        return out


def check_surface(surface: Surface, *, self_intersection: bool = True) -> SurfaceCheck:
    """Check that a surface is one watertight, manifold, outward, non-self-intersecting shell.

    Arguments:
        surface: the surface.
        self_intersection: also count self-intersecting face pairs (:func:`self_intersections`).
    Returns:
        A SurfaceCheck; `.ok` is True when everything holds.
    """
    f = surface.faces
    n_v = surface.vertices.shape[0]
    counts = _edge_counts(f, n_v)
    directed = f.ravel().astype(np.int64) * n_v + f[:, [1, 2, 0]].ravel()
    _, dcounts = _uniq(directed, counts=True)
    inconsistent = int((dcounts > 1).sum())
    # components through shared edges
    fan_counts = _vertex_fans(f, n_v)
    used = np.zeros(n_v, dtype=bool)
    used[f.ravel()] = True
    adj = sparse.coo_matrix((np.ones(3 * len(f)), (f.ravel(), np.repeat(np.arange(len(f)), 3))),
                            shape=(n_v, len(f))).tocsr()
    vf = (adj.T @ adj).tocoo()  # faces sharing a vertex; components by vertex = by edge when manifold
    n_comp, _ = csgraph.connected_components(vf, directed=False)
    p = surface.vertices[f]
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    scale = max(float(np.ptp(surface.vertices, axis=0).max()), 1e-300)
    return SurfaceCheck(
        n_components=int(n_comp),
        boundary_edges=int((counts == 1).sum()),
        nonmanifold_edges=int((counts > 2).sum()),
        nonmanifold_vertices=int((fan_counts[used] > 1).sum()),
        inconsistent_edges=inconsistent,
        degenerate_faces=int((area2 <= 1e-12 * scale ** 2).sum()),
        volume_mm3=surface_volume_mm3(surface),
        self_intersections=len(self_intersections(surface)) if self_intersection else None,
    )


def _tri_tri_intersect(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Separating-axis test for triangle pairs, (P, 3, 3) each -> (P,) bool (True = they touch).

    Axes: both normals, the 9 edge-edge cross products (enough for non-coplanar triangles,
    Gottschalk et al. 1996 / Eberly) and the in-plane edge normals (coplanar triangles). An axis
    that separates proves disjointness; degenerate (zero) axes separate nothing.
    """
    ea = A[:, [1, 2, 0]] - A  # (P, 3, 3) edges
    eb = B[:, [1, 2, 0]] - B
    na = np.cross(ea[:, 0], ea[:, 1])
    nb = np.cross(eb[:, 0], eb[:, 1])
    axes = [na[:, None], nb[:, None],
            np.cross(ea[:, :, None], eb[:, None, :]).reshape(-1, 9, 3),
            np.cross(na[:, None], ea), np.cross(nb[:, None], eb)]
    axes = np.concatenate(axes, axis=1)  # (P, 17, 3)
    pa = np.einsum("pkd,pvd->pkv", axes, A)
    pb = np.einsum("pkd,pvd->pkv", axes, B)
    sep = (pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1))
    return ~sep.any(axis=1)


def self_intersections(surface: Surface, *, chunk: int = 200_000) -> np.ndarray:
    """Pairs of faces that intersect each other, shape (k, 2) (face indices, i < j).

    Candidate pairs are faces whose bounding spheres (about the centroid) overlap, found with a
    k-d tree; pairs sharing an edge are skipped (a fold there shows as a zero-volume dihedral,
    not here); pairs sharing one vertex are tested after shrinking both triangles by 1e-3 about
    their centroids (so the shared corner does not count). The test is the separating-axis
    theorem (:func:`_tri_tri_intersect`).

    Arguments:
        surface: the surface.
        chunk: pairs tested per vectorised batch (memory bound).
    Returns:
        (k, 2) int64 array of intersecting face pairs; empty for a clean surface.
    """
    V, F = surface.vertices, surface.faces
    P = V[F]
    c = P.mean(axis=1)
    rad = np.linalg.norm(P - c[:, None], axis=2).max(axis=1)
    tree = cKDTree(c)
    pairs = tree.query_pairs(r=2.0 * float(rad.max()) * (1 + 1e-9), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    d = np.linalg.norm(c[pairs[:, 0]] - c[pairs[:, 1]], axis=1)
    pairs = pairs[d <= (rad[pairs[:, 0]] + rad[pairs[:, 1]]) * (1 + 1e-9)]
    fa, fb = F[pairs[:, 0]], F[pairs[:, 1]]
    shared = (fa[:, :, None] == fb[:, None, :]).sum(axis=(1, 2))
    pairs, shared = pairs[shared < 2], shared[shared < 2]
    hits = []
    for s in range(0, len(pairs), chunk):
        pp, sh = pairs[s:s + chunk], shared[s:s + chunk]
        A, B = P[pp[:, 0]].copy(), P[pp[:, 1]].copy()
        one = sh == 1
        if one.any():
            A[one] = c[pp[one, 0], None] + (A[one] - c[pp[one, 0], None]) * (1 - 1e-3)
            B[one] = c[pp[one, 1], None] + (B[one] - c[pp[one, 1], None]) * (1 - 1e-3)
        # Moller (1997) early rejection: all of one triangle strictly on one side of the other's
        # plane (most neighbours on a smooth surface); then the full separating-axis test.
        keep = np.ones(len(pp), dtype=bool)
        for X, Y in ((A, B), (B, A)):
            n = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
            dist = np.einsum("pvd,pd->pv", Y - X[:, :1], n)
            keep &= ~((dist > 0).all(axis=1) | (dist < 0).all(axis=1))
        pp, A, B = pp[keep], A[keep], B[keep]
        hits.append(pp[_tri_tri_intersect(A, B)])
    out = np.concatenate(hits).astype(np.int64)
    return np.sort(out, axis=1)


def _manifold(surface: Surface):

    mesh = m3.Mesh(vert_properties=surface.vertices.astype(np.float32),
                   tri_verts=surface.faces.astype(np.uint32))
    m = m3.Manifold(mesh)
    if m.status() != m3.Error.NoError:
        raise ValueError(f"{surface.tissue.name} surface is not a valid manifold for manifold3d "
                         f"({m.status().name}).")
    return m


def surface_gap_mm(inner: Surface, outer: Surface, *, search_mm: float = 10.0) -> float:
    """Exact minimum distance between a surface and the surface enclosing it (mm).

    The inner solid must lie inside the outer one: returns 0.0 if any part of it is outside
    (the surfaces cross or touch). Uses manifold3d's triangle-triangle ``min_gap`` between the
    inner solid and (a box minus the outer solid), which is disjoint from it when nested.

    Arguments:
        inner, outer: closed outward surfaces.
        search_mm: distances above this are reported as `search_mm`.
    Returns:
        The gap in mm, in [0, search_mm].
    """

    mi, mo = _manifold(inner), _manifold(outer)
    outside = (mi - mo).volume()
    if outside > 1e-9 * max(mi.volume(), 1.0):
        return 0.0
    lo = np.minimum(inner.vertices.min(0), outer.vertices.min(0)) - 10.0
    hi = np.maximum(inner.vertices.max(0), outer.vertices.max(0)) + 10.0
    box = m3.Manifold.cube(hi - lo).translate(lo)
    return float(mi.min_gap(box - mo, float(search_mm)))


# ---------------------------------------------------------------------------------------------
# Pipeline steps


def _crop(mask: np.ndarray, margin: int) -> tuple[slice, slice, slice]:
    idx = [np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != ax))) for ax in range(3)]
    return tuple(slice(max(int(i[0]) - margin, 0), min(int(i[-1]) + margin + 1, n))
                 for i, n in zip(idx, mask.shape))


def _solid_masks(labels: np.ndarray) -> dict[Tissue, tuple[np.ndarray, int]]:
    """Cavity-filled nested solids and the number of cavity voxels filled in each.

    A cavity is a component of the complement (face-connected) that does not reach the solid's
    bounding box margin, which is outside the solid (the grid border is background).
    """
    out = {}
    for t in TISSUES:
        solid = (labels >= 1) & (labels <= int(t))
        sl = _crop(solid, 1)
        sub = np.pad(~solid[sl], 1, constant_values=True)
        lab, n = ndi.label(sub)
        filled = solid.copy()
        if n > 1:
            filled[sl] |= (lab != lab[0, 0, 0])[1:-1, 1:-1, 1:-1]
        out[t] = (filled, int(filled.sum() - solid.sum()))
    return out


def _nesting_violations(labels: np.ndarray) -> dict[Tissue, int]:
    """Voxels outside each shell's outer solid that are face neighbours of its inner solid (no
    grid edge may join a solid to the outside of the next one: the marching-cubes surfaces would
    share a vertex there)."""
    out = {}
    face = ndi.generate_binary_structure(3, 1)
    for k, t in ((1, Tissue.CSF), (2, Tissue.SKULL), (3, Tissue.SCALP)):
        inner = (labels >= 1) & (labels <= k)
        sl = _crop(inner, 2)
        outside = ~((labels[sl] >= 1) & (labels[sl] <= k + 1))
        out[t] = int((ndi.binary_dilation(inner[sl], face) & outside).sum())
    return out


def _check_layers(layers) -> None:
    """Bad input -> ValueError: not a LabelMap, empty, a tissue missing, tissue on the border.

    (The same checks as ``jaxhead.geometry.layers.check_labels``; repeated here so this module
    does not import the segmentation package.)
    """
    if not isinstance(layers, LabelMap):
        raise ValueError(f"`layers` must be a jaxhead.LabelMap, got {type(layers).__name__}; wrap "
                         "an array as LabelMap(labels, affine) and run make_layers on it.")
    lab = layers.labels
    if lab.min() < 0 or lab.max() > int(max(Tissue)):
        raise ValueError(f"`layers` has labels outside 0..{int(max(Tissue))}; use Tissue values.")
    counts = np.bincount(lab.ravel().astype(np.int64), minlength=len(Tissue))
    if not counts[1:].any():
        raise ValueError("`layers` is empty (no tissue voxels).")
    missing = [t.name for t in TISSUES if counts[int(t)] == 0]
    if missing:
        raise ValueError(f"`layers` has no {', '.join(missing)} voxels; the nested surfaces need all "
                         "four tissues (BRAIN=1, CSF=2, SKULL=3, SCALP=4).")
    border = {}
    for ax, axis in enumerate("xyz"):
        for end, tag in ((0, "0"), (-1, "max")):
            for v in np.unique(np.take(lab, end, axis=ax)):
                if v:
                    border.setdefault(Tissue(int(v)).name, []).append(f"{axis}={tag}")
    if border:
        where = "; ".join(f"{t} on {', '.join(f)}" for t, f in border.items())
        raise ValueError(
            f"`layers` has tissue on the volume border ({where}): its surface would be closed "
            "artificially there. Pad the volume with background first, e.g. "
            "`jaxhead.geometry.layers.pad_labels(labels, 4)`, and run make_layers.")


def _marching_cubes(mask: np.ndarray, affine: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:

    margin = int(math.ceil(3 * sigma)) + 2
    idx = np.argwhere(mask)
    lo, hi = idx.min(0) - margin, idx.max(0) + margin + 1
    pad_lo = np.maximum(-lo, 0)
    pad_hi = np.maximum(hi - np.array(mask.shape), 0)
    lo_c, hi_c = np.maximum(lo, 0), np.minimum(hi, mask.shape)
    sub = mask[lo_c[0]:hi_c[0], lo_c[1]:hi_c[1], lo_c[2]:hi_c[2]]
    sub = np.pad(sub, list(zip(pad_lo, pad_hi))).astype(np.float32)
    if sigma > 0:
        sub = ndi.gaussian_filter(sub, sigma, mode="constant")
    verts, faces, _, _ = marching_cubes(sub, level=0.5, allow_degenerate=False)
    ijk = verts.astype(np.float64) + lo
    xyz = ijk @ affine[:3, :3].T + affine[:3, 3]
    return xyz, faces.astype(np.int64)


#: Presmoothing factors tried, in order, until the marching-cubes surface is a sphere.
_PRESMOOTH_FACTORS = (1.0, 1.5, 2.0)


def euler_number(faces: np.ndarray) -> int:
    """Euler characteristic V - E + F of a triangle surface (2 for a sphere, 0 for a torus)."""
    F = np.asarray(faces, np.int64)
    n = int(F.max()) + 1 if F.size else 0
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [0, 2]]]), axis=1)
    return len(np.unique(F)) - len(_uniq(e[:, 0] * n + e[:, 1])) + len(F)


def _sphere_marching_cubes(mask: np.ndarray, affine: np.ndarray, sigma: float,
                           tissue: Tissue) -> tuple[np.ndarray, np.ndarray, float]:
    """Marching cubes of the presmoothed solid, whose surface must be a sphere: (V, F, sigma used).

    `make_layers` makes each solid genus 0 under both voxel-connectivity conventions, but the
    0.5 level set of the Gaussian-smoothed mask can still join two parts of the solid that lie
    one empty voxel apart (seen on a segmented MNI152 head at 1 mm: a one-voxel skull spike into
    the CSF gave the CSF surface a handle, and the mesh 8 slivers there). Stronger smoothing
    blurs such a one-voxel feature away, so sigma x 1.5 and x 2 are tried in turn; the first
    sphere is kept (logged, and reported by `extract_surfaces_reported`). If none is a sphere
    (a solid with tunnels, `LayerConfig(tunnels="keep")`), the configured sigma's surface is kept.
    """
    first = None
    for factor in _PRESMOOTH_FACTORS if sigma > 0 else (1.0,):
        V, F = _marching_cubes(mask, affine, sigma * factor)
        if euler_number(F) == 2:
            if factor != 1.0:
                log.info("%s surface: the level set at presmoothing %g voxels was not a sphere; "
                         "used %g voxels", tissue.name, sigma, sigma * factor)
            return V, F, sigma * factor
        first = first or (V, F)
    return first[0], first[1], sigma


def _face_components(F: np.ndarray, n_verts: int) -> tuple[int, np.ndarray]:
    """Connected components of faces through shared edges: (count, label per face)."""
    a, b = F.ravel().astype(np.int64), F[:, [1, 2, 0]].ravel().astype(np.int64)
    key = np.minimum(a, b) * n_verts + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    same = key[order][1:] == key[order][:-1]
    fa, fb = order[:-1][same] // 3, order[1:][same] // 3
    graph = sparse.coo_matrix((np.ones(len(fa)), (fa, fb)), shape=(len(F), len(F)))
    return csgraph.connected_components(graph, directed=False)


def _is_manifold(V: np.ndarray, F: np.ndarray) -> bool:
    """Closed, edge-manifold (2 faces per edge), vertex-manifold (one fan), consistently wound."""
    n_v = len(V)
    if not np.all(_edge_counts(F, n_v) == 2):
        return False
    directed = F.ravel().astype(np.int64) * n_v + F[:, [1, 2, 0]].ravel()
    if len(_uniq(directed)) != len(directed):
        return False
    fans = _vertex_fans(F, n_v)
    return bool(np.all(fans[_uniq(F)] == 1))


def _repair(V: np.ndarray, F: np.ndarray, tissue: Tissue, stage: str) -> tuple[np.ndarray, np.ndarray, dict]:
    """Keep the largest component, fill holes, fix winding/outwardness. Returns counts."""

    counts = {"components_dropped": 0, "faces_dropped": 0, "hole_faces_added": 0, "faces_flipped": 0}
    n_comp, comp = _face_components(F, len(V))
    if n_comp > 1:
        sizes = np.bincount(comp)
        keep = int(np.argmax(sizes))
        counts["components_dropped"] = int(n_comp - 1)
        counts["faces_dropped"] = int(len(F) - sizes[keep])
        F = F[comp == keep]
    used = _uniq(F)
    if len(used) != len(V):  # drop unreferenced vertices
        remap = np.full(len(V), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        V, F = V[used], remap[F]
    n_boundary = int((_edge_counts(F, len(V)) == 1).sum())
    tm = None
    if n_boundary:
        tm = _tm(V, F)
        before = len(tm.faces)
        trimesh.repair.fill_holes(tm)
        counts["hole_faces_added"] = int(len(tm.faces) - before)
        if not tm.is_watertight:
            raise ValueError(
                f"the {tissue.name} surface has holes after {stage} that trimesh cannot close "
                f"({n_boundary} open edges); check the label map's {tissue.name} layer with "
                "make_layers (holes, components, border) or lower `presmooth_sigma_voxels`.")
        V, F = np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int64)
    directed = F.ravel().astype(np.int64) * len(V) + F[:, [1, 2, 0]].ravel()
    if len(_uniq(directed)) != len(directed):  # some faces wound the other way
        tm = _tm(V, F)
        before = tm.faces.copy()
        trimesh.repair.fix_winding(tm)
        counts["faces_flipped"] += int((tm.faces != before).any(axis=1).sum())
        F = np.asarray(tm.faces, dtype=np.int64)
    if surface_volume_mm3(Surface(V, F, tissue)) < 0:
        F = F[:, ::-1].copy()
        counts["faces_flipped"] += len(F)
    return V, F, counts


def _taubin(V: np.ndarray, F: np.ndarray, cfg: SurfaceConfig) -> np.ndarray:

    if cfg.taubin_iterations == 0:
        return V
    tm = _tm(V, F)
    # trimesh alternates V += lamb * L V and V -= nu * L V: nu = -mu
    trimesh.smoothing.filter_taubin(tm, lamb=cfg.taubin_lambda, nu=-cfg.taubin_mu,
                                    iterations=cfg.taubin_iterations)
    return np.asarray(tm.vertices, dtype=np.float64)


def _remesh(V: np.ndarray, F: np.ndarray, edge: float, cfg: SurfaceConfig) -> tuple[np.ndarray, np.ndarray]:

    area = float(0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum())
    # faces of an equilateral mesh with edge h covering this area
    n_target = max(int(area / (math.sqrt(3) / 4 * edge ** 2)), 20)
    n_decim = n_target * (2 if cfg.remesh == "isotropic" else 1)
    if n_decim < len(F):
        Vd, Fd = fast_simplification.simplify(V.astype(np.float64), F.astype(np.int64), target_count=n_decim)
        if not _is_manifold(Vd, Fd):
            # quadric decimation without a link-condition check can pinch the surface; libigl's
            # shortest-edge decimation keeps it manifold (slower, so only as the fallback)

            Vd, Fd = gpytoolbox.decimate(V, F.astype(np.int32), num_faces=n_decim,
                                         method="shortest_edge")[:2]
        V, F = Vd, Fd
    if cfg.remesh == "isotropic" and cfg.remesh_iterations > 0:

        V, F = gpytoolbox.remesh_botsch(np.ascontiguousarray(V, dtype=np.float64),
                                        np.ascontiguousarray(F, dtype=np.int32),
                                        i=cfg.remesh_iterations, h=edge, project=True)
    return np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)


def _vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area-weighted
    n = np.zeros_like(V)
    for j in range(3):
        np.add.at(n, F[:, j], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _bary(n: int) -> np.ndarray:
    """Barycentric coordinates (g, 3) of the grid of step 1/n on a triangle."""
    return np.array([(i, j, n - i - j) for i in range(n + 1) for j in range(n + 1 - i)],
                    dtype=np.float64) / n


def _samples(V: np.ndarray, F: np.ndarray, n: int, near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points checked for the gap on the faces `near` of a triangle surface: the barycentric grid
    of step 1/n on each (n = 1: the vertices; 2: also the edge midpoints; 4: also the quarter
    points), with the face's three vertices as their owners.

    Returns (points (k, 3), owners (k, 3) vertex ids).
    """
    B = _bary(n)
    Fn = F[near].astype(np.int64)
    P = np.einsum("gc,fcx->fgx", B, V[Fn]).reshape(-1, 3)
    return P, np.repeat(Fn, len(B), axis=0)


def _separate(inner: Surface, outer: Surface, gap: float, max_iter: int,
              max_move: float, density: int = 1) -> tuple[Surface, int, float]:
    """Push inner vertices inward (along their normals) until every sample of the inner surface
    lies at least 1.1 gap inside `outer` and every sample of the outer surface at least 1.1 gap
    outside `inner`.

    The samples are the vertices (`density` 1), or the barycentric grid of step 1 / `density` on
    every face within reach of the other surface (:func:`_samples`). Returns (new inner surface,
    vertices moved, largest total move in mm). The 10% margin covers the difference between
    these point-to-surface distances and the exact surface-to-surface distance checked
    afterwards; where it does not (a ridge of one coarse surface under the middle of a face of
    the other: 0.22 mm apart with every vertex 0.55 mm clear, the ANTs head at 2 mm, BRAIN
    inside CSF), the caller separates again with denser samples. A vertex that would move more
    than `max_move` mm in total means the shell is thinner than the gap: ValueError.
    """

    V, F = inner.vertices.copy(), np.ascontiguousarray(inner.faces, dtype=np.int32)
    OV, OF = outer.vertices, np.ascontiguousarray(outer.faces, dtype=np.int32)
    outer_aabb = gpytoolbox.squared_distance_precompute(OV, OF)
    outer_fwn = gpytoolbox.fast_winding_number_precompute(OV, OF)
    target = 1.1 * gap
    if density == 1:
        owners = np.arange(len(V))[:, None].repeat(3, axis=1)
        OP = OV
    else:
        # faces within reach: a vertex closer to the other surface than the target plus the
        # longest edge of either surface (and the largest move allowed)
        reach = target + max_move + max(float(np.max(edge_lengths(inner))),
                                        float(np.max(edge_lengths(outer))))
        d_in = np.sqrt(gpytoolbox.squared_distance(V, OV, OF, use_cpp=True, cpp_aabb=outer_aabb)[0])
        d_out = np.sqrt(gpytoolbox.squared_distance(OV, V, F, use_cpp=True)[0])
        _, owners = _samples(V, F, density, (d_in[F] < reach).any(axis=1))
        OP, _ = _samples(OV, OF, density, (d_out[OF] < reach).any(axis=1))
    B = _bary(density)
    moved = np.zeros(len(V), dtype=bool)
    total = np.zeros(len(V))
    for _ in range(max_iter):
        P = V if density == 1 else np.einsum("gc,fcx->fgx", B, V[owners[::len(B)]]).reshape(-1, 3)
        sd_in = gpytoolbox.signed_distance(P, OV, OF, cpp_aabb=outer_aabb, fwn_bvh=outer_fwn)[0]
        sd_out, f_near, _ = gpytoolbox.signed_distance(OP, V, F)  # > 0 outside inner
        push = np.zeros(len(V))
        bad_in = sd_in > -target  # sd < 0 inside outer
        if bad_in.any():
            need = target + sd_in[bad_in]
            for j in range(3):
                np.maximum.at(push, owners[bad_in, j], need)
        bad_out = sd_out < target
        if bad_out.any():
            need = target - sd_out[bad_out]
            for j in range(3):
                np.maximum.at(push, F[f_near[bad_out], j], need)
        if not (bad_in.any() or bad_out.any()):
            break
        V = V - _vertex_normals(V, F) * push[:, None]
        moved |= push > 0
        total += push
        if total.max() > max_move:
            raise ValueError(
                f"the {outer.tissue.name} shell is thinner than min_gap_mm={gap:g} in places: "
                f"{int((total > max_move).sum())} {inner.tissue.name} surface vertices would have "
                f"to move more than {max_move:.2f} mm inward (up to {total.max():.2f} mm) to "
                f"keep the {inner.tissue.name} surface {gap:g} mm inside the {outer.tissue.name} "
                f"surface. Raise LayerConfig.min_thickness_mm['{outer.tissue.name.lower()}'] "
                "(make_layers) or lower SurfaceConfig.min_gap_mm.")
    return Surface(V, F, inner.tissue), int(moved.sum()), float(total.max(initial=0.0))


def _vertex_adjacency(F: np.ndarray, n_verts: int) -> sparse.csr_matrix:
    """Vertex-vertex adjacency through edges, (n_verts, n_verts) with ones."""
    a, b = F.ravel().astype(np.int64), F[:, [1, 2, 0]].ravel().astype(np.int64)
    A = sparse.coo_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])),
                          shape=(n_verts, n_verts)).tocsr()
    A.data[:] = 1.0
    return A


#: Local smoothing of a tangled region: rounds (each grows the region by one more ring of
#: vertices) and uniform-Laplacian steps per round. A fold left by remeshing or by the gap push
#: spans a few faces; 10 steps of 0.5 on a region r rings wide relax it to the membrane spanned
#: by the fixed ring around it (the Laplacian's smoothing length ~ sqrt(steps) edges).
_UNTANGLE_ROUNDS = 6
_UNTANGLE_STEPS = 10


def _untangle(V: np.ndarray, F: np.ndarray, tissue: Tissue) -> tuple[np.ndarray, dict]:
    """Remove self-intersections by smoothing only the regions around the intersecting faces.

    Round r moves the vertices within r rings of every face found intersecting so far (uniform
    Laplacian, the ring beyond held fixed) and re-checks the whole surface with
    :func:`self_intersections`; it stops when none are left or after ``_UNTANGLE_ROUNDS``.
    Connectivity never changes, so the surface stays closed and manifold.

    Returns:
        (vertices, counts): counts has "pairs" (found at the start), "rounds", "vertices"
        (moved) and "left" (pairs still intersecting).
    """
    si = self_intersections(Surface(V, F, tissue))
    counts = {"pairs": int(len(si)), "rounds": 0, "vertices": 0, "left": int(len(si))}
    if len(si) == 0:
        return V, counts
    A = _vertex_adjacency(F, len(V))
    deg = np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1.0)
    V = V.copy()
    seed = np.zeros(len(V), dtype=bool)
    moved = np.zeros(len(V), dtype=bool)
    for r in range(1, _UNTANGLE_ROUNDS + 1):
        seed[F[si].ravel()] = True
        region = seed.copy()
        for _ in range(r):
            region |= (A @ region.astype(np.float64)) > 0
        idx = np.flatnonzero(region)
        for _ in range(_UNTANGLE_STEPS):
            avg = (A @ V)[idx] / deg[idx, None]
            V[idx] += 0.5 * (avg - V[idx])
        moved |= region
        counts["rounds"] = r
        si = self_intersections(Surface(V, F, tissue))
        if len(si) == 0:
            break
    counts["vertices"] = int(moved.sum())
    counts["left"] = int(len(si))
    log.info("%s surface: %d self-intersecting face pairs untangled by local smoothing "
             "(%d rounds, %d vertices moved, %d left)", tissue.name, counts["pairs"],
             counts["rounds"], counts["vertices"], counts["left"])
    return V, counts


#: Finer edges (fractions of edge_mm) tried, in order, when local smoothing cannot untangle a
#: remeshed surface: a fold comes from a feature narrower than the edge (a groove or ridge a
#: voxel or two wide), which a finer remesh resolves.
_REMESH_SCALES = (1.0, 0.7, 0.5)
#: separate -> untangle rounds of the gap step before giving up.
_GAP_ROUNDS = 4
#: Samples per face edge of the gap step (:func:`_samples`), tried in order while the exact gap
#: is short: 1 (the vertices), then nested barycentric grids (each holds the one before) on the
#: faces near the other surface.
_GAP_DENSITIES = (1, 2, 4, 8)


def _add_untangle(acc: dict, u: dict) -> None:
    acc["untangled_pairs"] += u["pairs"]
    acc["untangle_rounds"] += u["rounds"]
    acc["untangled_vertices"] += u["vertices"]


def extract_surfaces_reported(layers: LabelMap, cfg: SurfaceConfig = SurfaceConfig()
                              ) -> tuple[dict[Tissue, Surface], SurfaceReport]:
    """Surfaces of the four nested solids of a layered label map, repaired, remeshed and nested.

    The steps are in this module's docstring.

    Arguments:
        layers: label map with strictly nested layers (the output of ``make_layers``): every
            BRAIN voxel's face neighbours in BRAIN/CSF, and so on out; background on the border.
        cfg: the surface settings.
    Returns:
        ({Tissue: Surface} for BRAIN, CSF, SKULL, SCALP in world mm, SurfaceReport).
    Raises:
        ValueError: bad labels (missing tissue, on the border, not nested), or a surface that
            cannot be made watertight/manifold or separated from its neighbour (names the tissue).
    """
    t_start = time.perf_counter()
    _check_layers(layers)
    if not isinstance(cfg, SurfaceConfig):
        raise ValueError(f"`cfg` must be a SurfaceConfig, got {type(cfg).__name__}.")
    labels = layers.labels
    bad = {t: n for t, n in _nesting_violations(labels).items() if n}
    if bad:
        raise ValueError(
            "`layers` is not strictly nested: " + ", ".join(
                f"{n} voxels outside the {t.name} shell touch what it should enclose"
                for t, n in bad.items())
            + "; run `jaxhead.geometry.layers.make_layers(labels)` first.")
    edges = cfg.edges()
    vox_vol = abs(float(np.linalg.det(layers.affine[:3, :3])))
    masks = _solid_masks(labels)

    surfaces: dict[Tissue, Surface] = {}
    info: dict[Tissue, dict] = {}
    for t in TISSUES:
        mask, n_cavity = masks[t]
        sec = {}
        t0 = time.perf_counter()
        V, F, sigma = _sphere_marching_cubes(mask, layers.affine, cfg.presmooth_sigma_voxels, t)
        if surface_volume_mm3(Surface(V, F, t)) < 0:  # winding convention (and det(affine) < 0)
            F = F[:, ::-1].copy()
        n_mc = len(F)
        sec["marching_cubes"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        V, F, rep1 = _repair(V, F, t, "marching cubes")
        sec["repair"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        V = _taubin(V, F, cfg)
        sec["smooth"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        unt = {"untangled_pairs": 0, "untangle_rounds": 0, "untangled_vertices": 0}
        retries = 0
        for scale in _REMESH_SCALES:
            Vr, Fr = _remesh(V, F, edges[t] * scale, cfg)
            Vr, Fr, rep2 = _repair(Vr, Fr, t, "remeshing")
            if not cfg.check_self_intersections:
                break
            Vr, u = _untangle(Vr, Fr, t)
            _add_untangle(unt, u)
            if u["left"] == 0:
                break
            if scale != _REMESH_SCALES[-1]:
                retries += 1
                log.info("%s surface: %d self-intersecting face pairs left after local smoothing; "
                         "remeshing again at edge %.2f mm", t.name, u["left"],
                         edges[t] * _REMESH_SCALES[retries])
        V, F = Vr, Fr
        sec["remesh"] = time.perf_counter() - t0
        surfaces[t] = Surface(V, F, t)
        info[t] = dict(solid_voxels=int(mask.sum()), cavity_voxels=n_cavity,
                       voxel_volume_mm3=float(mask.sum()) * vox_vol, mc_faces=n_mc,
                       **{k: rep1[k] + rep2[k] for k in rep1}, sec=sec, remesh_retries=retries,
                       presmooth_sigma_voxels=sigma, **unt)

    # Gap, outside in: only the inner surface of each pair moves (inward).
    gaps: dict[Tissue, float | None] = {Tissue.SCALP: None}
    for inner_t, outer_t in ((Tissue.SKULL, Tissue.SCALP), (Tissue.CSF, Tissue.SKULL),
                             (Tissue.BRAIN, Tissue.CSF)):
        t0 = time.perf_counter()
        # The surfaces come from strictly nested masks, so they are already apart except where
        # remeshing cut a corner (sag ~ h^2 / 8R) or smoothing moved them: a vertex needing more
        # than the gap plus half an edge means the shell itself is too thin.
        limit = cfg.min_gap_mm * 1.1 + 0.5 * edges[inner_t]
        # Pushing vertices along their normals can fold the surface where it is concave (a
        # groove narrower than the push); such folds are smoothed locally and the result is
        # separated again, until a round needs no untangling.
        n_moved, max_move = 0, 0.0
        # Vertices first; where the exact gap is still short (a ridge of one coarse surface
        # under the middle of a face of the other), again with denser samples on the faces.
        for density in _GAP_DENSITIES:
            for rnd in range(1, _GAP_ROUNDS + 1):
                new, n, mv = _separate(surfaces[inner_t], surfaces[outer_t], cfg.min_gap_mm,
                                       cfg.max_gap_iterations, limit, density)
                n_moved, max_move = n_moved + n, max(max_move, mv)
                surfaces[inner_t] = new
                if not cfg.check_self_intersections or n == 0:
                    break
                Vu, u = _untangle(new.vertices, new.faces, inner_t)
                _add_untangle(info[inner_t], u)
                if u["pairs"] == 0:
                    break
                surfaces[inner_t] = new = Surface(Vu, new.faces, inner_t)
            # search 3 mm (or 2 gaps): enough to report the typical gap, cheap for manifold3d
            gap = surface_gap_mm(new, surfaces[outer_t], search_mm=max(2 * cfg.min_gap_mm, 3.0))
            if gap >= cfg.min_gap_mm * (1 - 1e-6) and gap > 0.0:
                break
            if density != _GAP_DENSITIES[-1]:
                log.info("%s surface: %.3g mm from the %s surface after separating its vertices "
                         "(every vertex clear); separating again with %d samples per face edge",
                         inner_t.name, gap, outer_t.name, _GAP_DENSITIES[_GAP_DENSITIES.index(density) + 1])
        info[inner_t]["gap_rounds"] = rnd
        info[inner_t]["gap_sample_density"] = density
        if gap < cfg.min_gap_mm * (1 - 1e-6) or gap == 0.0:
            raise ValueError(
                f"the {inner_t.name} surface could not be kept {cfg.min_gap_mm:g} mm inside the "
                f"{outer_t.name} surface (gap {gap:.3g} mm after {cfg.max_gap_iterations} rounds, "
                f"{n_moved} vertices moved): the {outer_t.name} shell is too thin for this gap "
                f"at edge_mm={edges[inner_t]:g}. Raise LayerConfig.min_thickness_mm"
                f"['{outer_t.name.lower()}'], raise max_gap_iterations, lower edge_mm or min_gap_mm.")
        gaps[inner_t] = gap
        info[inner_t]["gap_vertices_moved"] = n_moved
        info[inner_t]["max_move_mm"] = max_move
        info[inner_t]["sec"]["gap"] = time.perf_counter() - t0
    info[Tissue.SCALP].update(gap_vertices_moved=0, max_move_mm=0.0)

    stats = {}
    for t in TISSUES:
        s = surfaces[t]
        t0 = time.perf_counter()
        chk = check_surface(s, self_intersection=cfg.check_self_intersections)
        info[t]["sec"]["checks"] = time.perf_counter() - t0
        if not chk.ok:
            raise ValueError(
                f"the {t.name} surface fails its final checks ({'; '.join(chk.problems())}); "
                f"try a finer edge_mm[{t.name.lower()!r}], more remesh_iterations, or check the "
                f"{t.name} layer of the label map.")
        d = info[t]
        stats[t] = SurfaceStats(
            tissue=t, solid_voxels=d["solid_voxels"], cavity_voxels=d["cavity_voxels"],
            voxel_volume_mm3=d["voxel_volume_mm3"], mc_faces=d["mc_faces"],
            components_dropped=d["components_dropped"], faces_dropped=d["faces_dropped"],
            hole_faces_added=d["hole_faces_added"], faces_flipped=d["faces_flipped"],
            gap_vertices_moved=d["gap_vertices_moved"], max_move_mm=d["max_move_mm"],
            n_verts=len(s.vertices), n_faces=len(s.faces), area_mm2=surface_area_mm2(s),
            volume_mm3=chk.volume_mm3, edge_target_mm=edges[t], edge_mm=_edge_stats(s),
            gap_to_outer_mm=gaps[t], self_intersections=chk.self_intersections,
            seconds=dict(d["sec"]), untangled_pairs=d["untangled_pairs"],
            untangle_rounds=d["untangle_rounds"], untangled_vertices=d["untangled_vertices"],
            remesh_retries=d["remesh_retries"], gap_rounds=d.get("gap_rounds", 1),
            gap_sample_density=d.get("gap_sample_density", 1),
            presmooth_sigma_voxels=d["presmooth_sigma_voxels"],
            presmooth_raised=d["presmooth_sigma_voxels"] != cfg.presmooth_sigma_voxels)
    report = SurfaceReport(stats=stats, min_gap_mm=cfg.min_gap_mm,
                           seconds=time.perf_counter() - t_start)
    return surfaces, report


def extract_surfaces(layers: LabelMap, cfg: SurfaceConfig = SurfaceConfig()) -> dict[Tissue, Surface]:
    """Surfaces of the four nested solids (see :func:`extract_surfaces_reported`); report logged at INFO.

    Arguments:
        layers: strictly nested label map (the output of ``make_layers``).
        cfg: the surface settings.
    Returns:
        {Tissue: Surface} for BRAIN, CSF, SKULL, SCALP, in world mm, outward, nested with the gap.
    """
    surfaces, report = extract_surfaces_reported(layers, cfg)
    log.info("%s", report)
    return surfaces
