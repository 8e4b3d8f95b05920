"""Concentric-sphere TetMeshes for tests: a fast structured one and an unstructured (fTetWild) one.

`structured_sphere_mesh` maps a Freudenthal (Kuhn) tetrahedralisation of a tensor grid on the
cube [-R, R]^3 onto the ball by x -> x |x|_inf / |x|_2. The map takes every cube surface
|x|_inf = r onto the sphere |x| = r, so with grid lines at every shell radius each tet lies in
one shell and every interface is a conforming polyhedron whose nodes lie exactly on the sphere
of that radius. It is deterministic, takes milliseconds, and its mesh size is a parameter, which
is what convergence tests need. The map is homogeneous of degree 1 with bounded distortion
(at most sqrt(3) between directions), so tet shapes do not degrade with refinement.

`tetwild_sphere_mesh` meshes nested icospheres with pytetwild (fTetWild) and labels tets by
centroid radius, for tests that want unstructured meshes like the head pipeline makes.

Both are cached per process (meshes are immutable); pass radii and labels as tuples.
"""

from __future__ import annotations

import functools

import numpy as np

from jaxhead.geometry import TetMesh, orient_tets
from jaxhead.tissue import TISSUES

#: Default shell radii in mm (brain, CSF, skull, scalp outer radii): a 96 mm head with a 4 mm
#: CSF layer, 6 mm skull and 6 mm scalp, close to the four-shell head models of the EEG
#: literature (e.g. Rush & Driscoll 1968 use ratios 0.87 / 0.92 / 1.0 for brain/skull/scalp).
RADII_MM = (80.0, 84.0, 90.0, 96.0)

# Freudenthal (Kuhn) triangulation of a cube: one tet per permutation of the axes, all sharing
# one main diagonal (conforming across cells with the same diagonal direction).
_PERMS = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))


def _axis(radii: np.ndarray, h: float) -> np.ndarray:
    """1D grid from -R to R with nodes at +-r_k and spacing <= ~h in each shell."""
    half = [0.0]
    prev = 0.0
    for r in radii:
        m = max(1, int(round((r - prev) / h)))
        half.extend(np.linspace(prev, r, m + 1)[1:])
        prev = r
    half = np.asarray(half)
    return np.r_[-half[:0:-1], half]


@functools.lru_cache(maxsize=8)
def structured_sphere_mesh(radii=RADII_MM, h_mm: float = 12.0, labels=None) -> TetMesh:
    """A concentric-shell ball mesh by mapping a cube grid onto the ball.

    Arguments:
        radii: increasing outer radii of the shells in mm (1 to 4 shells).
        h_mm: target grid spacing in mm (each shell gets >= 1 layer).
        labels: Tissue value of each shell, inside out; default TISSUES[:len(radii)] for 4
            shells (BRAIN, CSF, SKULL, SCALP); fewer shells take the outer ones (1 shell: SCALP).

    Returns:
        TetMesh with nodes in mm, centred at the origin.
    """
    radii = np.asarray(radii, dtype=np.float64)
    if radii.ndim != 1 or not 1 <= radii.size <= 4 or np.any(np.diff(radii) <= 0) or radii[0] <= 0:
        raise ValueError(f"`radii` must be 1..4 increasing positive radii, got {radii}.")
    if labels is None:
        labels = [int(t) for t in TISSUES[4 - radii.size:]]
    labels = np.asarray(labels, dtype=np.int64)
    g = _axis(radii, h_mm)
    n = g.size
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    p = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(n**3).reshape(n, n, n)
    stride = np.array([n * n, n, 1])
    ci = np.stack(np.meshgrid(*[np.arange(n - 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    # Kuhn diagonal from the cell corner nearest the centre to the farthest one (the
    # triangulation mirrored into each octant), so every tet has vertices on two different
    # |x|_inf levels and none is a flat sliver on a sphere after the map.
    neg = g[ci + 1] <= 0.0  # (n_cells, 3): cell on the negative side of each axis
    start = idx[ci[:, 0], ci[:, 1], ci[:, 2]] + (neg * stride).sum(1)
    step = np.where(neg, -stride, stride)
    tets = []
    for perm in _PERMS:
        a = step[:, perm[0]]
        b = a + step[:, perm[1]]
        c = b + step[:, perm[2]]
        tets.append(np.stack([start, start + a, start + b, start + c], axis=1))
    tets = np.concatenate(tets)
    # shell of each tet from its centroid's inf-norm in the cube (each cell lies in one shell)
    cinf = np.abs(p[tets].mean(axis=1)).max(axis=1)
    shell = np.searchsorted(radii, cinf)
    r2 = np.linalg.norm(p, axis=1)
    rinf = np.abs(p).max(axis=1)
    scale = np.divide(rinf, r2, out=np.ones_like(r2), where=r2 > 0)
    nodes = p * scale[:, None]
    tets, _ = orient_tets(nodes, tets)
    return TetMesh(nodes, tets, labels[shell])


@functools.lru_cache(maxsize=4)
def tetwild_sphere_mesh(radii=RADII_MM, edge_mm: float = 10.0, subdivisions: int = 3,
                        labels=None) -> TetMesh:
    """Nested icospheres meshed by pytetwild, tets labelled by centroid radius.

    fTetWild inserts the input triangles into the tet mesh (within its envelope, 1e-3 of the
    bounding box), so the shells are conforming up to that tolerance.
    """
    import pytetwild
    import trimesh

    radii = np.asarray(radii, dtype=np.float64)
    if labels is None:
        labels = [int(t) for t in TISSUES[4 - radii.size:]]
    labels = np.asarray(labels, dtype=np.int64)
    verts, faces, off = [], [], 0
    for r in radii:
        s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=float(r))
        verts.append(s.vertices)
        faces.append(s.faces + off)
        off += len(s.vertices)
    nodes, tets = pytetwild.tetrahedralize(
        np.vstack(verts), np.vstack(faces).astype(np.int32), edge_length_abs=edge_mm,
        simplify=False, num_threads=1)
    tets, _ = orient_tets(nodes, tets.astype(np.int64))
    rc = np.linalg.norm(nodes[tets].mean(axis=1), axis=1)
    return TetMesh(nodes, tets, labels[np.minimum(np.searchsorted(radii, rc), radii.size - 1)])
