"""The labelled tetrahedral mesh type and its helpers: the package's one tet-volume formula
(`signed_volumes`, NumPy or JAX), enclosed volumes, orientation, face adjacency.  [host]"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..tissue import TISSUES, Tissue

# Local faces of a tet (P0..P3) ordered so that, for a positively oriented tet
# ((P1-P0) x (P2-P0) . (P3-P0) > 0), each face's normal points out of the tet.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def signed_volumes(nodes, tets):
    """Signed tet volumes ((P1 - P0) x (P2 - P0)) . (P3 - P0) / 6, shape (n_tets,).

    The package's one tet-volume formula (the FEM's Jacobian check, mesh volumes, the study's
    extension operator and the mesh improvement all call it; `tet_metrics` and the FEM's element
    matrices reuse the determinant they need anyway).

    Arguments:
        nodes: (n_nodes, 3) positions; the volumes are in their unit cubed (mm^3 for a TetMesh,
            m^3 for the FEM's nodes).
        tets: (n_tets, 4) node indices.

    Returns:
        (n_tets,) volumes, positive for a positively oriented tet (P3 on the side of the face
        P0 P1 P2 that its counter-clockwise normal points to), negative when two nodes are swapped.
        NumPy in, NumPy out; a JAX array (or tracer) in, JAX out (differentiable in `nodes`).
    """
    xp = jnp if isinstance(nodes, jax.Array) or isinstance(tets, jax.Array) else np
    p = xp.asarray(nodes)[xp.asarray(tets)]
    d1, d2, d3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    return xp.einsum("ij,ij->i", xp.cross(d1, d2), d3) / 6.0


def enclosed_volume(vertices, faces) -> float:
    """Signed volume enclosed by a closed triangle surface (divergence theorem).

    The sum of the signed volumes of the tets (apex, face) with the apex at the vertices' mean
    (any apex gives the same sum on a closed surface; a near one keeps the rounding small).

    Arguments:
        vertices: (n, 3) positions; faces: (m, 3) vertex indices of a closed surface.

    Returns:
        The volume in the vertices' unit cubed: positive when the faces are counter-clockwise
        seen from outside (outward normals), negative when they are all reversed.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    apex = np.full((len(F), 1), len(V))
    return float(signed_volumes(np.vstack([V, V.mean(axis=0)]), np.hstack([apex, F])).sum())


def orient_tets(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, int]:
    """Swap two nodes of every negatively oriented tet. Returns (tets, number flipped)."""
    tets = np.array(tets, copy=True)
    neg = signed_volumes(nodes, tets) < 0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    return tets, int(neg.sum())


class TetMesh(eqx.Module):
    """A labelled linear tetrahedral mesh.

    Arguments:
        nodes: (n_nodes, 3) positions in world mm (float64).
        tets: (n_tets, 4) node indices, every tet positively oriented.
        labels: (n_tets,) Tissue value of each tet (1..4: BRAIN, CSF, SKULL, SCALP).
    """

    nodes: np.ndarray
    tets: np.ndarray
    labels: np.ndarray

    def __init__(self, nodes, tets, labels):
        self.nodes = np.asarray(nodes, dtype=np.float64)
        self.tets = np.asarray(tets, dtype=np.int64)
        self.labels = np.asarray(labels, dtype=np.int64)

    def __check_init__(self):
        if self.nodes.ndim != 2 or self.nodes.shape[1] != 3:
            raise ValueError(f"`nodes` must have shape (n_nodes, 3), got {self.nodes.shape}.")
        if not np.all(np.isfinite(self.nodes)):
            raise ValueError("`nodes` contains NaN or Inf coordinates.")
        if self.tets.ndim != 2 or self.tets.shape[1] != 4:
            raise ValueError(f"`tets` must have shape (n_tets, 4), got {self.tets.shape}.")
        if self.tets.shape[0] == 0:
            raise ValueError("`tets` is empty; a TetMesh needs at least one tet.")
        if self.tets.min() < 0 or self.tets.max() >= self.nodes.shape[0]:
            raise ValueError(
                f"`tets` indexes nodes {self.tets.min()}..{self.tets.max()} but there are "
                f"{self.nodes.shape[0]} nodes; indices must be 0-based and < n_nodes."
            )
        if self.labels.shape != (self.tets.shape[0],):
            raise ValueError(
                f"`labels` has shape {self.labels.shape} but the mesh has {self.tets.shape[0]} "
                "tets; pass one Tissue label per tet."
            )
        valid = np.isin(self.labels, [int(t) for t in TISSUES])
        if not valid.all():
            bad = np.unique(self.labels[~valid])
            raise ValueError(
                f"`labels` has values {bad[:10].tolist()}; tet labels must be tissues 1..4 "
                "(BRAIN, CSF, SKULL, SCALP)."
            )
        vol = signed_volumes(self.nodes, self.tets)
        if not np.all(vol > 0):
            n_neg, n_zero = int((vol < 0).sum()), int((vol == 0).sum())
            raise ValueError(
                f"{n_neg} tets are negatively oriented and {n_zero} are degenerate; "
                "fix the orientation with `jaxhead.geometry.tetrahedralize.orient_tets(nodes, tets)` and drop "
                "zero-volume tets before building a TetMesh."
            )

    @property
    def n_nodes(self) -> int:
        return self.nodes.shape[0]

    @property
    def n_tets(self) -> int:
        return self.tets.shape[0]

    def tet_volumes(self) -> np.ndarray:
        """Tet volumes in mm^3, shape (n_tets,)."""
        return signed_volumes(self.nodes, self.tets)

    def tissue_volumes_mm3(self) -> dict[Tissue, float]:
        """Total volume of each tissue in mm^3."""
        v = np.bincount(self.labels, weights=self.tet_volumes(), minlength=len(Tissue))
        return {t: float(v[int(t)]) for t in TISSUES}

    def centroids(self) -> np.ndarray:
        """Tet centroids in mm, shape (n_tets, 3)."""
        return self.nodes[self.tets].mean(axis=1)

    def boundary_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """Faces on the mesh's outer boundary, outward oriented.

        Returns:
            faces: (n_faces, 3) node indices, counter-clockwise seen from outside.
            tet: (n_faces,) index of the tet each face belongs to.
        """
        faces, owner, _, _, boundary = face_adjacency(self.tets)
        return faces[boundary], owner[boundary]

    def interface_faces(self, inner: Tissue | str | int, outer: Tissue | str | int) -> np.ndarray:
        """Faces shared by a tet of `inner` and a tet of `outer`, oriented from inner to outer."""
        a, b = int(Tissue.parse(inner)), int(Tissue.parse(outer))
        faces, owner, i, j, _ = face_adjacency(self.tets)
        li, lj = self.labels[owner[i]], self.labels[owner[j]]
        pick_i = (li == a) & (lj == b)
        pick_j = (lj == a) & (li == b)
        return np.concatenate([faces[i[pick_i]], faces[j[pick_j]]])

    def surface_nodes(self) -> np.ndarray:
        """Indices of the nodes on the outer boundary."""
        return np.unique(self.boundary_faces()[0])


def face_adjacency(tets: np.ndarray):
    """All tet faces and which pairs of tets share one (the package's one face-matching routine).

    Arguments:
        tets: (m, 4) node indices of a conforming mesh (an interior face shared by two tets).

    Returns:
        faces: (4 m, 3) local faces (outward for positive tets); owner: (4 m,) tet of each face;
        i, j: indices into faces of the two copies of every interior face; boundary: (4 m,) bool.
    """
    tets = np.asarray(tets)
    faces = tets[:, _TET_FACES].reshape(-1, 3)
    owner = np.repeat(np.arange(len(tets)), 4)
    key = np.sort(faces, axis=1)
    n = int(faces.max()) + 1 if faces.size else 1
    if n < 1 << 21:
        # One int64 per face (three 21-bit node indices): the same order as the lexsort below,
        # several times faster; the improvement step calls this once per pass.
        k = key.astype(np.int64)
        code = (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]
        order = np.argsort(code, kind="stable")
        cs = code[order]
        same = cs[1:] == cs[:-1]
    else:
        order = np.lexsort(key.T[::-1])
        ks = key[order]
        same = np.all(ks[1:] == ks[:-1], axis=1)
    i, j = order[:-1][same], order[1:][same]
    boundary = np.ones(len(faces), dtype=bool)
    boundary[i] = False
    boundary[j] = False
    return faces, owner, i, j, boundary
