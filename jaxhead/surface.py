"""Closed triangle surfaces of the nested tissue solids.  [host]"""

import equinox as eqx
import numpy as np

from .tissue import Tissue


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
