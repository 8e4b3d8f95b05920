"""Electrodes on the scalp: the Electrodes type and placement on a TetMesh.  [host]

An electrode is a disc of the scalp: the outer-boundary faces of the mesh whose centroids lie
within ``radius_mm`` (Euclidean distance in 3D, restricted to the faces edge-connected to the
face under the centre, so a disc never jumps across a fold of the surface) of the electrode centre
projected onto the scalp. For the radii used in EIT (a few mm on a head of radius ~90 mm) the
Euclidean and geodesic distances differ by < 0.1 % (chord vs arc: r^3 / (24 R^2)).
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import numpy as np

from .mesh import TetMesh

#: Default contact impedance in Ohm m^2 (see `place_electrodes`).
DEFAULT_CONTACT_IMPEDANCE_OHM_M2 = 1e-2


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


class Electrodes(eqx.Module):
    """Electrodes as patches of the mesh's outer boundary (complete electrode model).

    Arguments:
        centres: (n_elec, 3) electrode centres in world mm, on the scalp surface.
        faces: (n_eface, 3) int64 node indices of the mesh boundary faces under the electrodes,
            counter-clockwise seen from outside (as `TetMesh.boundary_faces`).
        face_electrode: (n_eface,) int64 electrode index 0..n_elec-1 of each face.
        contact_impedance: (n_elec,) contact impedance in Ohm m^2 (float64, > 0).
        names: electrode names, one per electrode.
        face_areas_mm2: optional (n_eface,) face areas in mm^2 at placement time, so that
            `area_mm2()` works without the mesh.
    """

    centres: np.ndarray
    faces: np.ndarray
    face_electrode: np.ndarray
    contact_impedance: np.ndarray
    names: tuple[str, ...] = eqx.field(static=True, default=())
    face_areas_mm2: np.ndarray | None = None

    def __init__(self, centres, faces, face_electrode, contact_impedance, names=(),
                 face_areas_mm2=None):
        self.centres = np.asarray(centres, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.face_electrode = np.asarray(face_electrode, dtype=np.int64)
        n_elec = self.centres.shape[0] if self.centres.ndim == 2 else 0
        if _is_tracer(contact_impedance) or isinstance(contact_impedance, jax.Array):
            z = contact_impedance
            if getattr(z, "ndim", 1) == 0:
                z = z * jax.numpy.ones(n_elec)
        else:
            z = np.asarray(contact_impedance, dtype=np.float64)
            if z.ndim == 0:
                z = np.full(n_elec, float(z))
        self.contact_impedance = z
        if not names:
            names = tuple(f"E{i + 1}" for i in range(n_elec))
        self.names = tuple(str(n) for n in names)
        self.face_areas_mm2 = (None if face_areas_mm2 is None
                               else np.asarray(face_areas_mm2, dtype=np.float64))

    def __check_init__(self):
        c, f, fe = self.centres, self.faces, self.face_electrode
        if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] == 0:
            raise ValueError(f"`centres` must have shape (n_elec, 3), n_elec >= 1; got {c.shape}.")
        if not np.all(np.isfinite(c)):
            raise ValueError("`centres` contains NaN or Inf coordinates.")
        n = c.shape[0]
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise ValueError(f"`faces` must have shape (n_eface, 3), n_eface >= 1; got {f.shape}.")
        if f.min() < 0:
            raise ValueError(f"`faces` has negative node index {f.min()}; indices are 0-based.")
        if fe.shape != (f.shape[0],):
            raise ValueError(
                f"`face_electrode` has shape {fe.shape} but there are {f.shape[0]} faces; "
                "give one electrode index per face.")
        if fe.min() < 0 or fe.max() >= n:
            raise ValueError(
                f"`face_electrode` has values {fe.min()}..{fe.max()} but there are {n} "
                "electrodes; use 0-based electrode indices < n_elec.")
        counts = np.bincount(fe, minlength=n)
        if np.any(counts == 0):
            empty = [i for i in np.flatnonzero(counts == 0)]
            raise ValueError(
                f"electrodes {empty[:10]} have no faces; every electrode needs at least one "
                "boundary face (increase the radius or refine the mesh under it).")
        if len(self.names) != n:
            raise ValueError(f"`names` has {len(self.names)} entries for {n} electrodes.")
        if len(set(self.names)) != n:
            raise ValueError(f"`names` has duplicates: {self.names}.")
        z = self.contact_impedance
        if getattr(z, "shape", None) != (n,):
            raise ValueError(
                f"`contact_impedance` has shape {getattr(z, 'shape', None)}; give one value or "
                f"one per electrode ({n},), in Ohm m^2.")
        if not _is_tracer(z):
            zn = np.asarray(z)
            if not np.all(np.isfinite(zn)) or not np.all(zn > 0):
                raise ValueError(
                    f"`contact_impedance` must be finite and > 0 Ohm m^2, got {zn[:10]}; typical "
                    "scalp electrodes are 1e-3..1e-1 Ohm m^2.")
        if self.face_areas_mm2 is not None and self.face_areas_mm2.shape != (f.shape[0],):
            raise ValueError(
                f"`face_areas_mm2` has shape {self.face_areas_mm2.shape}, expected ({f.shape[0]},).")

    @property
    def n_elec(self) -> int:
        return self.centres.shape[0]

    def area_mm2(self, nodes: np.ndarray | None = None) -> np.ndarray:
        """Electrode areas in mm^2, shape (n_elec,).

        Arguments:
            nodes: optional (n_nodes, 3) mesh node positions in mm; by default the face areas
                stored at placement are used.
        """
        if nodes is not None:
            p = np.asarray(nodes, dtype=np.float64)[self.faces]
            a = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        elif self.face_areas_mm2 is not None:
            a = self.face_areas_mm2
        else:
            raise ValueError(
                "these Electrodes carry no face areas; call `area_mm2(mesh.nodes)`.")
        return np.bincount(self.face_electrode, weights=a, minlength=self.n_elec)


# --------------------------------------------------------------------------------------------
# Scalp surface helpers


class _Scalp:
    """The outer boundary of a TetMesh as a triangle surface with adjacency and a query tree."""

    def __init__(self, mesh: TetMesh):
        import trimesh

        faces, _ = mesh.boundary_faces()
        used = np.unique(faces)
        self.node_index = used  # local vertex -> mesh node
        remap = np.full(mesh.n_nodes, -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        self.mesh_faces = faces
        self.tm = trimesh.Trimesh(mesh.nodes[used], remap[faces], process=False)
        self.centroids = self.tm.triangles_center
        self.areas = self.tm.area_faces
        adj = self.tm.face_adjacency
        import scipy.sparse as sp

        n = len(faces)
        self.adj = sp.coo_matrix(
            (np.ones(2 * len(adj)), (np.r_[adj[:, 0], adj[:, 1]], np.r_[adj[:, 1], adj[:, 0]])),
            shape=(n, n)).tocsr()

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest points on the scalp: (points (k,3), distances (k,), face index (k,))."""
        from trimesh.proximity import closest_point

        p, d, f = closest_point(self.tm, np.asarray(points, dtype=np.float64))
        return np.asarray(p), np.asarray(d), np.asarray(f, dtype=np.int64)

    def disc(self, centre: np.ndarray, face0: int, radius: float) -> np.ndarray:
        """Faces edge-connected to `face0` whose centroid is within `radius` of `centre`."""
        inside = np.linalg.norm(self.centroids - centre, axis=1) <= radius
        inside[face0] = True
        seen = {int(face0)}
        front = [int(face0)]
        indptr, indices = self.adj.indptr, self.adj.indices
        while front:
            nxt = []
            for f in front:
                for g in indices[indptr[f]:indptr[f + 1]]:
                    g = int(g)
                    if inside[g] and g not in seen:
                        seen.add(g)
                        nxt.append(g)
            front = nxt
        return np.array(sorted(seen), dtype=np.int64)


def _per_electrode(value, n: int, name: str, unit: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(n, float(v))
    if v.shape != (n,):
        raise ValueError(f"`{name}` has shape {v.shape}; give one value or one per electrode ({n},).")
    if not np.all(np.isfinite(v)) or not np.all(v > 0):
        raise ValueError(f"`{name}` must be finite and > 0 {unit}, got {v[:10]}.")
    return v


def place_electrodes(
    mesh: TetMesh,
    positions,
    *,
    radius_mm=5.0,
    contact_impedance=DEFAULT_CONTACT_IMPEDANCE_OHM_M2,
    names=None,
    max_distance_mm: float = 10.0,
) -> Electrodes:
    """Place disc electrodes on the scalp (outer boundary) of a mesh.

    Arguments:
        mesh: the head TetMesh; its outer boundary is the scalp.
        positions: (n_elec, 3) electrode positions in world mm, projected onto the scalp.
        radius_mm: electrode radius in mm, one value or (n_elec,).
        contact_impedance: contact impedance in Ohm m^2, one value or (n_elec,). The default
            1e-2 Ohm m^2 is 1 kOhm over a 1 cm^2 electrode, the range of gelled Ag/AgCl scalp
            electrodes (EEG practice keeps skin contact below 5 kOhm).
        names: optional electrode names (default "E1".."En").
        max_distance_mm: positions farther than this from the scalp are an error.

    Returns:
        Electrodes with centres on the scalp and the boundary faces under each disc.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] == 0:
        raise ValueError(
            f"`positions` must have shape (n_elec, 3) in mm, got {pos.shape}.")
    if not np.all(np.isfinite(pos)):
        raise ValueError("`positions` contains NaN or Inf.")
    n = pos.shape[0]
    names = tuple(names) if names is not None else tuple(f"E{i + 1}" for i in range(n))
    if len(names) != n:
        raise ValueError(f"`names` has {len(names)} entries for {n} positions.")
    radius = _per_electrode(radius_mm, n, "radius_mm", "mm")
    z = _per_electrode(contact_impedance, n, "contact_impedance", "Ohm m^2")

    scalp = _Scalp(mesh)
    centres, dist, face0 = scalp.project(pos)
    far = np.flatnonzero(dist > max_distance_mm)
    if far.size:
        desc = ", ".join(f"{names[i]} ({dist[i]:.1f} mm)" for i in far[:10])
        raise ValueError(
            f"electrode positions farther than max_distance_mm={max_distance_mm} from the scalp: "
            f"{desc}; check the coordinate frame (world mm, RAS) or raise max_distance_mm.")
    _check_overlap(centres, radius, names)

    faces, owner = [], []
    for i in range(n):
        sel = scalp.disc(centres[i], face0[i], radius[i])
        if sel.size == 1 and np.linalg.norm(scalp.centroids[sel[0]] - centres[i]) > radius[i]:
            warnings.warn(
                f"electrode {names[i]}: no boundary face centroid within {radius[i]} mm; "
                "using the face under the centre only. Refine the mesh under the electrodes "
                "(see `electrode_refinement_points`).", stacklevel=2)
        faces.append(sel)
        owner.append(np.full(sel.size, i))
    fidx = np.concatenate(faces)
    fe = np.concatenate(owner)
    return Electrodes(centres=centres, faces=scalp.mesh_faces[fidx], face_electrode=fe,
                      contact_impedance=z, names=names, face_areas_mm2=scalp.areas[fidx])


def _check_overlap(centres: np.ndarray, radius: np.ndarray, names) -> None:
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    lim = radius[:, None] + radius[None]
    i, j = np.nonzero(np.triu(d < lim, k=1))
    if i.size:
        desc = ", ".join(f"{names[a]}-{names[b]} ({d[a, b]:.1f} mm apart)"
                         for a, b in zip(i[:10], j[:10]))
        raise ValueError(
            f"electrodes overlap (centres closer than the sum of their radii): {desc}; "
            "move them apart or reduce radius_mm.")
