"""The labelled tetrahedral mesh type and its topology helpers (orientation, face adjacency).  [host]"""

import equinox as eqx
import numpy as np

from ..tissue import TISSUES, Tissue

# Local faces of a tet (P0..P3) ordered so that, for a positively oriented tet
# ((P1-P0) x (P2-P0) . (P3-P0) > 0), each face's normal points out of the tet.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def signed_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed tet volumes in mm^3, shape (n_tets,): positive for positive orientation."""
    p = np.asarray(nodes)[np.asarray(tets)]
    d1, d2, d3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    return np.einsum("ij,ij->i", np.cross(d1, d2), d3) / 6.0


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

    def _all_faces(self) -> tuple[np.ndarray, np.ndarray]:
        faces = self.tets[:, _TET_FACES].reshape(-1, 3)
        owner = np.repeat(np.arange(self.n_tets), 4)
        return faces, owner

    def boundary_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """Faces on the mesh's outer boundary, outward oriented.

        Returns:
            faces: (n_faces, 3) node indices, counter-clockwise seen from outside.
            tet: (n_faces,) index of the tet each face belongs to.
        """
        faces, owner = self._all_faces()
        key = np.sort(faces, axis=1)
        _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        once = counts[inv.ravel()] == 1
        return faces[once], owner[once]

    def interface_faces(self, inner: Tissue | str | int, outer: Tissue | str | int) -> np.ndarray:
        """Faces shared by a tet of `inner` and a tet of `outer`, oriented from inner to outer."""
        a, b = int(Tissue.parse(inner)), int(Tissue.parse(outer))
        faces, owner = self._all_faces()
        key = np.sort(faces, axis=1)
        order = np.lexsort(key.T[::-1])
        ks = key[order]
        same = np.all(ks[1:] == ks[:-1], axis=1)
        i, j = order[:-1][same], order[1:][same]
        li, lj = self.labels[owner[i]], self.labels[owner[j]]
        pick_i = (li == a) & (lj == b)
        pick_j = (lj == a) & (li == b)
        return np.concatenate([faces[i[pick_i]], faces[j[pick_j]]])

    def surface_nodes(self) -> np.ndarray:
        """Indices of the nodes on the outer boundary."""
        return np.unique(self.boundary_faces()[0])


# ---------------------------------------------------------------------------------------------
# tetrahedralize: nested surfaces -> labelled tetrahedral mesh (fTetWild, then improvement)


def face_adjacency(tets: np.ndarray):
    """All tet faces and which pairs of tets share one.

    Returns:
        faces: (4 m, 3) local faces (outward for positive tets); owner: (4 m,) tet of each face;
        i, j: indices into faces of the two copies of every interior face; boundary: (4 m,) bool.
    """
    faces = tets[:, _TET_FACES].reshape(-1, 3)
    owner = np.repeat(np.arange(len(tets)), 4)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    ks = key[order]
    same = np.all(ks[1:] == ks[:-1], axis=1)
    i, j = order[:-1][same], order[1:][same]
    boundary = np.ones(len(faces), dtype=bool)
    boundary[i] = False
    boundary[j] = False
    return faces, owner, i, j, boundary
