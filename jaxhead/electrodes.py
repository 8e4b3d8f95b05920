"""Electrodes on the scalp: the Electrodes type and placement on a TetMesh.  [host]

An electrode is a disc of the scalp: the outer-boundary faces of the mesh nearest (Euclidean
distance in 3D between face centroids and the electrode centre projected onto the scalp) to
the centre, grown through shared edges from the face under the centre so a disc never jumps
across a fold of the surface, with total area closest to pi r^2. For the radii used in EIT
(a few mm on a head of radius ~90 mm) Euclidean and geodesic distances differ by < 0.1 %
(chord vs arc: r^3 / (24 R^2)).
"""

from __future__ import annotations

import heapq
import json
import math
import warnings
import dataclasses
from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.spatial import cKDTree
from trimesh.proximity import closest_point

from .geometry.surface import Surface
from .geometry.tetrahedralize import MeshConfig
from .geometry.tetmesh import TetMesh

#: Default contact impedance in Ohm m^2 (see `place_electrodes`).
DEFAULT_CONTACT_IMPEDANCE_OHM_M2 = 0.02


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


class Electrodes(eqx.Module):
    """Electrodes as patches of the mesh's outer boundary (complete electrode model).

    Arguments:
        centres: (n_elec, 3) electrode centres in world mm, on the scalp surface.
        faces: (n_eface, 3) int64 node indices of the mesh boundary faces under the electrodes,
            counter-clockwise seen from outside (as `TetMesh.boundary_faces`).
        face_electrode: (n_eface,) int64 electrode index 0..n_elec-1 of each face.
        contact_impedance_ohm_m2: (n_elec,) contact impedance in Ohm m^2 (float64, > 0).
        names: electrode names, one per electrode.
        face_areas_mm2: optional (n_eface,) face areas in mm^2 at placement time, so that
            `area_mm2()` works without the mesh.
    """

    centres: np.ndarray
    faces: np.ndarray
    face_electrode: np.ndarray
    contact_impedance_ohm_m2: np.ndarray
    names: tuple[str, ...] = eqx.field(static=True, default=())
    face_areas_mm2: np.ndarray | None = None

    def __init__(self, centres, faces, face_electrode, contact_impedance_ohm_m2, names=(),
                 face_areas_mm2=None):
        self.centres = np.asarray(centres, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.face_electrode = np.asarray(face_electrode, dtype=np.int64)
        n_elec = self.centres.shape[0] if self.centres.ndim == 2 else 0
        if _is_tracer(contact_impedance_ohm_m2) or isinstance(contact_impedance_ohm_m2, jax.Array):
            z = contact_impedance_ohm_m2
            if getattr(z, "ndim", 1) == 0:
                z = z * jax.numpy.ones(n_elec)
        else:
            z = np.asarray(contact_impedance_ohm_m2, dtype=np.float64)
            if z.ndim == 0:
                z = np.full(n_elec, float(z))
        self.contact_impedance_ohm_m2 = z
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
            empty = np.flatnonzero(counts == 0).tolist()
            raise ValueError(
                f"electrodes {empty[:10]} have no faces; every electrode needs at least one "
                "boundary face (increase the radius or refine the mesh under it).")
        if len(self.names) != n:
            raise ValueError(f"`names` has {len(self.names)} entries for {n} electrodes.")
        if len(set(self.names)) != n:
            raise ValueError(f"`names` has duplicates: {self.names}.")
        z = self.contact_impedance_ohm_m2
        if getattr(z, "shape", None) != (n,):
            raise ValueError(
                f"`contact_impedance_ohm_m2` has shape {getattr(z, 'shape', None)}; give one value or "
                f"one per electrode ({n},), in Ohm m^2.")
        if not _is_tracer(z):
            zn = np.asarray(z)
            if not np.all(np.isfinite(zn)) or not np.all(zn > 0):
                raise ValueError(
                    f"`contact_impedance_ohm_m2` must be finite and > 0 Ohm m^2, got {zn[:10]}; typical "
                    "scalp electrodes are 1e-3..1e-1 Ohm m^2.")
        if self.face_areas_mm2 is not None and self.face_areas_mm2.shape != (f.shape[0],):
            raise ValueError(
                f"`face_areas_mm2` has shape {self.face_areas_mm2.shape}, expected "
                f"({f.shape[0]},).")

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

    def __init__(self, mesh: TetMesh | Surface):

        if isinstance(mesh, Surface):
            faces, nodes = mesh.faces, mesh.vertices
        elif isinstance(mesh, TetMesh):
            faces, nodes = mesh.boundary_faces()[0], mesh.nodes
        else:
            raise ValueError(f"`mesh` must be a TetMesh or the scalp Surface, got "
                             f"{type(mesh).__name__}.")
        used = np.unique(faces)
        self.node_index = used  # local vertex -> mesh node
        remap = np.full(nodes.shape[0], -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        self.mesh_faces = faces
        self.tm = trimesh.Trimesh(nodes[used], remap[faces], process=False)
        self.centroids = self.tm.triangles_center
        self.areas = self.tm.area_faces
        adj = self.tm.face_adjacency

        n = len(faces)
        self.adj = sp.coo_matrix(
            (np.ones(2 * len(adj)), (np.r_[adj[:, 0], adj[:, 1]], np.r_[adj[:, 1], adj[:, 0]])),
            shape=(n, n)).tocsr()

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest points on the scalp: (points (k,3), distances (k,), face index (k,))."""

        p, d, f = closest_point(self.tm, np.asarray(points, dtype=np.float64))
        return np.asarray(p), np.asarray(d), np.asarray(f, dtype=np.int64)

    def ray_hits(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Farthest scalp hit of rays from `origin` (inside the head): (k, 3), NaN where missed.

        Moeller & Trumbore (1997) ray-triangle tests against the faces whose direction from
        `origin` is within their own angular radius of the ray (a KD-tree on unit vectors).
        """

        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        tri = self.tm.triangles - o  # (n_faces, 3, 3) relative to the origin
        cen = tri.mean(axis=1)
        cdir = cen / np.linalg.norm(cen, axis=1, keepdims=True)
        vdir = tri / np.linalg.norm(tri, axis=2, keepdims=True)
        chord = np.linalg.norm(vdir - cdir[:, None], axis=2).max()
        cand = cKDTree(cdir).query_ball_point(d, r=chord * (1 + 1e-9) + 1e-12)
        ray = np.repeat(np.arange(len(d)), [len(c) for c in cand])
        face = np.fromiter((f for c in cand for f in c), dtype=np.int64, count=len(ray))
        out = np.full(d.shape, np.nan)
        if face.size == 0:
            return out
        v0, v1, v2 = tri[face, 0], tri[face, 1], tri[face, 2]
        e1, e2, dr = v1 - v0, v2 - v0, d[ray]
        pv = np.cross(dr, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        ok = np.abs(det) > 1e-12 * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = -v0  # ray origin (0) minus v0
        u = np.einsum("ij,ij->i", tv, pv) * inv
        qv = np.cross(tv, e1)
        v = np.einsum("ij,ij->i", dr, qv) * inv
        t = np.einsum("ij,ij->i", e2, qv) * inv
        eps = 1e-9
        hit = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t > 0)
        if not hit.any():
            return out
        best = np.full(len(d), -np.inf)
        np.maximum.at(best, ray[hit], t[hit])
        good = np.isfinite(best)
        out[good] = o + d[good] * best[good, None]
        return out

    def disc(self, centre: np.ndarray, face0: int, radius: float) -> np.ndarray:
        """Faces of a disc of area ~pi r^2 grown from `face0`, nearest centroid first.

        From the face under the centre, repeatedly add the edge-adjacent face whose centroid
        is nearest `centre` (3D distance), and stop when the area is closest to pi r^2: the
        area is then right to within half a face, and the patch is as round as the faces
        allow and never jumps across a fold of the surface.
        """

        target = np.pi * radius * radius
        indptr, indices = self.adj.indptr, self.adj.indices
        dist = lambda f: float(np.linalg.norm(self.centroids[f] - centre))
        chosen = [int(face0)]
        area = float(self.areas[face0])
        seen = {int(face0)}
        heap = []
        for g in indices[indptr[face0]:indptr[face0 + 1]]:
            heapq.heappush(heap, (dist(g), int(g)))
            seen.add(int(g))
        while heap:
            _, f = heapq.heappop(heap)
            a = float(self.areas[f])
            if abs(area + a - target) >= abs(area - target):
                break
            chosen.append(f)
            area += a
            for g in indices[indptr[f]:indptr[f + 1]]:
                g = int(g)
                if g not in seen:
                    seen.add(g)
                    heapq.heappush(heap, (dist(g), g))
        return np.array(sorted(chosen), dtype=np.int64)


def _per_electrode(value, n: int, name: str, unit: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(n, float(v))
    if v.shape != (n,):
        raise ValueError(
            f"`{name}` has shape {v.shape}; give one value or one per electrode ({n},).")
    if not np.all(np.isfinite(v)) or not np.all(v > 0):
        raise ValueError(f"`{name}` must be finite and > 0 {unit}, got {v[:10]}.")
    return v


def place_electrodes(
    mesh: TetMesh,
    positions,
    *,
    radius_mm=5.0,
    contact_impedance_ohm_m2=DEFAULT_CONTACT_IMPEDANCE_OHM_M2,
    names=None,
    landmarks=None,
    max_distance_mm: float = 10.0,
) -> Electrodes:
    """Place disc electrodes on the scalp (outer boundary) of a mesh.

    Each electrode is a patch of outer-boundary faces around the centre projected onto the
    scalp: grown from the face under the centre through shared edges, nearest face centroid
    first, until its area is closest to pi r^2 (so the area, which sets the contact
    conductance |e|/z of the complete electrode model, is right to within half a face). The
    face under the centre is always included; if the faces are too coarse for the radius (area
    off by more than 50 %), a warning says so.

    Arguments:
        mesh: the head TetMesh; its outer boundary is the scalp.
        positions: one of
            - (n_elec, 3) world mm (e.g. digitised), projected onto the scalp;
            - a layout name "10-20" (21 electrodes) or "10-10" (61), or a list of 10-10 names
              (see `layout_positions`; `EXTENDED` adds Nz, Iz, NFpz, TP9, O9/I1, ...);
            - a list mixing names and (3,) world-mm coordinates (e.g. a montage whose
              electrodes are named except a few digitised ones);
            - an int: that many electrodes spread over the upper head (`spread_positions`).
        radius_mm: electrode radius in mm, one value or (n_elec,).
        contact_impedance_ohm_m2: contact impedance in Ohm m^2, one value or (n_elec,). Default
            0.02 Ohm m^2: McEwan et al. 2006 (Physiol. Meas. 27:S199, UCLH Mk2.5 head EIT)
            measured 300 Ohm - 2.7 kOhm per scalp electrode over 20 Hz - 256 kHz; over a
            10 mm-diameter EEG cup (0.785 cm^2) that is 0.024 - 0.21 Ohm m^2, the low end at
            EIT frequencies. Cheng et al. 1989 (IEEE TBME 36:918) fitted 7.5e-4 - 5.8e-3
            Ohm m^2 for metal electrodes in saline.
        names: optional names for (n_elec, 3) positions (default "E1".."En"; layouts name
            their electrodes).
        landmarks: for layouts and counts: dict "nasion", "inion", "lpa", "rpa" of world mm;
            estimated from the scalp shape when omitted (`estimate_landmarks`, RAS assumed).
        max_distance_mm: positions farther than this from the scalp are an error.

    Returns:
        Electrodes with centres on the scalp and the boundary faces under each disc.
    """
    if not isinstance(mesh, TetMesh):
        raise ValueError(f"`mesh` must be a jaxhead TetMesh, got {type(mesh).__name__}.")
    if max_distance_mm <= 0:
        raise ValueError(f"`max_distance_mm` must be > 0, got {max_distance_mm}.")
    if isinstance(positions, str) or (
            isinstance(positions, (list, tuple)) and positions
            and all(isinstance(p, str) for p in positions)):
        kind = "layout"
        layout = _layout_names(positions)
        if names is not None:
            raise ValueError("`names` is only for coordinate positions; layouts name their "
                             "electrodes.")
        if landmarks is not None:
            _parse_landmarks(landmarks)
        n_pos = len(layout)
    elif isinstance(positions, (list, tuple)) and any(isinstance(p, str) for p in positions):
        kind = "mixed"  # names and coordinates: [ "Fp1", (x, y, z), "NFpz", ... ]
        is_name = [isinstance(p, str) for p in positions]
        _layout_names([p for p in positions if isinstance(p, str)])
        for i, p in enumerate(positions):
            if not is_name[i]:
                q = np.asarray(p, dtype=np.float64) if not isinstance(p, dict) else None
                if q is None or q.shape != (3,) or not np.all(np.isfinite(q)):
                    raise ValueError(f"`positions[{i}]` = {p!r}: each entry is a 10-10 name or "
                                     "3 finite world-mm coordinates.")
        if landmarks is not None:
            _parse_landmarks(landmarks)
        n_pos = len(positions)
        if names is not None and len(names) != n_pos:
            raise ValueError(f"`names` has {len(names)} entries for {n_pos} positions.")
    elif isinstance(positions, (int, np.integer)) and not isinstance(positions, bool):
        kind = "count"
        _check_count(positions, 72.0)
        if landmarks is not None:
            _parse_landmarks(landmarks)
        n_pos = int(positions)
    else:
        kind = "coords"
        pos = np.asarray(positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] == 0:
            raise ValueError(
                f"`positions` must have shape (n_elec, 3) in mm, a layout name or a count; "
                f"got shape {pos.shape}.")
        if not np.all(np.isfinite(pos)):
            raise ValueError("`positions` contains NaN or Inf.")
        n_pos = pos.shape[0]
        if names is not None and len(names) != n_pos:
            raise ValueError(f"`names` has {len(names)} entries for {n_pos} positions.")
    radius = _per_electrode(radius_mm, n_pos, "radius_mm", "mm")
    z = _per_electrode(contact_impedance_ohm_m2, n_pos, "contact_impedance_ohm_m2", "Ohm m^2")

    scalp = _Scalp(mesh)
    if kind == "layout":
        names, pos = _layout(scalp, layout, landmarks)
    elif kind == "count":
        pos = _spread(scalp, n_pos, landmarks, 72.0)
    elif kind == "mixed":
        named = [i for i, p in enumerate(positions) if isinstance(p, str)]
        _, at = _layout(scalp, [positions[i] for i in named], landmarks)
        pos = np.zeros((n_pos, 3))
        pos[named] = at
        for i, p in enumerate(positions):
            if not isinstance(p, str):
                pos[i] = np.asarray(p, dtype=np.float64)
        if names is None:
            names = [p if isinstance(p, str) else f"E{i + 1}" for i, p in enumerate(positions)]
    n = n_pos
    names = tuple(names) if names is not None else tuple(f"E{i + 1}" for i in range(n))

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
        target = np.pi * radius[i] ** 2
        got = float(scalp.areas[sel].sum())
        if abs(got - target) > 0.5 * target:
            warnings.warn(
                f"electrode {names[i]}: the scalp faces are too coarse for radius "
                f"{radius[i]} mm (area {got:.1f} mm^2 instead of {target:.1f}); refine the mesh "
                "under the electrodes (see `electrode_refinement_points`).", stacklevel=2)
        faces.append(sel)
        owner.append(np.full(sel.size, i))
    fidx = np.concatenate(faces)
    fe = np.concatenate(owner)
    uniq, cnt = np.unique(fidx, return_counts=True)
    if np.any(cnt > 1):
        shared = set(uniq[cnt > 1].tolist())
        pairs = sorted({tuple(sorted({names[e] for e in fe[np.isin(fidx, [f])]}))
                        for f in list(shared)[:20]})
        raise ValueError(
            f"electrodes share scalp faces: {pairs[:10]}; they touch on this mesh. Move them "
            "apart, reduce radius_mm or refine the scalp mesh under them.")
    return Electrodes(centres=centres, faces=scalp.mesh_faces[fidx], face_electrode=fe,
                      contact_impedance_ohm_m2=z, names=names, face_areas_mm2=scalp.areas[fidx])


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


# --------------------------------------------------------------------------------------------
# Landmarks and the head frame

#: Landmark keys; aliases accepted by `_parse_landmarks`.
LANDMARKS = ("nasion", "inion", "lpa", "rpa")
_LANDMARK_ALIASES = {"nz": "nasion", "iz": "inion", "lpa": "lpa", "rpa": "rpa",
                     "nasion": "nasion", "inion": "inion", "al": "lpa", "ar": "rpa",
                     "left": "lpa", "right": "rpa"}


def _parse_landmarks(landmarks) -> dict[str, np.ndarray]:
    if not isinstance(landmarks, dict):
        raise ValueError(
            f"`landmarks` must be a dict of mm coordinates with keys {LANDMARKS}, "
            f"got {type(landmarks).__name__}.")
    out = {}
    for k, v in landmarks.items():
        key = _LANDMARK_ALIASES.get(str(k).lower())
        if key is None:
            raise ValueError(f"unknown landmark {k!r}; use {LANDMARKS}.")
        p = np.asarray(v, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"landmark {k!r} must be 3 finite mm coordinates, got {v!r}.")
        out[key] = p
    missing = [k for k in LANDMARKS if k not in out]
    if missing:
        raise ValueError(f"`landmarks` lacks {missing}; give all of {LANDMARKS} (world mm).")
    return out


def _fit_sphere(p: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere |p - c|^2 = R^2, linear in (c, R^2 - |c|^2)."""
    a = np.c_[2 * p, np.ones(len(p))]
    sol, *_ = np.linalg.lstsq(a, (p**2).sum(1), rcond=None)
    c = sol[:3]
    return c, float(np.sqrt(sol[3] + c @ c))


def estimate_landmarks(mesh: TetMesh | Surface) -> dict[str, np.ndarray]:
    """Estimate nasion, inion and pre-auricular points from the scalp shape (RAS frame).

    Assumes the mesh is in a RAS world frame (x right, y anterior, z superior), as NIfTI
    images are. A sphere is fitted (least squares) to the scalp nodes of the upper head,
    z >= z_max - (x_max - x_min) / 2 (for a sphere of radius R: the upper hemisphere; for a head
    with a neck: the part above roughly the ears). The landmarks are where rays from the fitted
    centre along -x (LPA), +x (RPA), +y (nasion) and -y (inion) leave the scalp. This is a
    crude estimate (on real heads nasion and inion come out ~1-2 cm off); pass measured
    landmarks when they are known.

    Returns:
        dict with keys "nasion", "inion", "lpa", "rpa": (3,) mm coordinates on the scalp.
    """
    return _estimate_landmarks(_Scalp(mesh))


def _estimate_landmarks(scalp: _Scalp) -> dict[str, np.ndarray]:
    v = scalp.tm.vertices
    upper = v[v[:, 2] >= v[:, 2].max() - 0.5 * np.ptp(v[:, 0])]
    c, _ = _fit_sphere(upper)
    dirs = np.array([[0.0, 1, 0], [0, -1, 0], [-1, 0, 0], [1, 0, 0]])
    hits = scalp.ray_hits(c, dirs)
    if np.isnan(hits).any():
        raise ValueError(
            "could not estimate landmarks: rays from the fitted head centre miss the scalp; "
            "pass `landmarks` (nasion, inion, lpa, rpa in world mm).")
    return dict(zip(("nasion", "inion", "lpa", "rpa"), hits))


class _HeadFrame:
    """Landmarks on the scalp, head centre (midpoint of LPA-RPA) and RAS-like axes."""

    def __init__(self, scalp: _Scalp, landmarks: dict[str, np.ndarray]):
        p, _, _ = scalp.project(np.stack([landmarks[k] for k in LANDMARKS]))
        self.nz, self.iz, self.lpa, self.rpa = p
        self.centre = 0.5 * (self.lpa + self.rpa)
        ex = self.rpa - self.lpa
        ex /= np.linalg.norm(ex)
        ey = self.nz - self.centre
        ey -= ex * (ey @ ex)
        if np.linalg.norm(ey) < 1e-6:
            raise ValueError("landmarks are degenerate: the nasion lies on the LPA-RPA line.")
        ey /= np.linalg.norm(ey)
        self.axes = np.stack([ex, ey, np.cross(ex, ey)])  # rows: right, anterior, superior


def _arc(scalp: _Scalp, origin, a, b, via, n: int = 361):
    """The scalp curve from a through via to b in their plane: (points (n,3), arclength (n,)).

    The curve is traced by rays from `origin` projected into the plane (Oostenveld & Praamstra
    2001 define 10-10 positions by dividing such curves on the scalp into equal lengths).
    """
    a, b, via = (np.asarray(x, dtype=np.float64) for x in (a, b, via))
    normal = np.cross(via - a, b - a)
    normal /= np.linalg.norm(normal)
    o = origin - normal * ((origin - a) @ normal)
    e1 = (a - o) / np.linalg.norm(a - o)
    e2 = np.cross(normal, e1)
    if (via - o) @ e2 < 0:
        e2 = -e2
    ang_via = np.arctan2((via - o) @ e2, (via - o) @ e1) % (2 * np.pi)
    ang_b = np.arctan2((b - o) @ e2, (b - o) @ e1) % (2 * np.pi)
    if not ang_via < ang_b:
        raise ValueError("scalp arc construction failed: the landmarks are not ordered around "
                         "the head; check the landmark coordinates.")
    t = np.linspace(0.0, ang_b, n)
    pts = scalp.ray_hits(o, np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
    if np.isnan(pts).any():
        raise ValueError("scalp arc construction failed: rays from the head centre miss the "
                         "scalp; is the mesh closed and are the landmarks right?")
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    return pts, s


def _at(pts, s, fractions, s0=0.0, s1=None):
    s1 = s[-1] if s1 is None else s1
    q = s0 + np.asarray(fractions, dtype=np.float64) * (s1 - s0)
    return np.stack([np.interp(q, s, pts[:, k]) for k in range(3)], axis=1)


def _ten_ten(scalp: _Scalp, frame: _HeadFrame, extended: bool = False) -> dict[str, np.ndarray]:
    """All 61 positions of the 10-10 system at or above the 10 % circumference ring, and with
    `extended` the lower (0 %) ring and the 10-5 midline points (`EXTENDED`)."""
    c = frame.centre
    fr = np.arange(1, 10) / 10.0
    cz = scalp.ray_hits(c, frame.axes[2][None])[0]
    for _ in range(10):  # make Cz the midpoint of both the midline and the coronal arc
        mid, smid = _arc(scalp, c, frame.nz, frame.iz, cz)
        cz_m = _at(mid, smid, [0.5])[0]
        cor, scor = _arc(scalp, c, frame.lpa, frame.rpa, cz_m)
        cz = _at(cor, scor, [0.5])[0]
        if np.linalg.norm(cz - cz_m) < 0.05:
            break
    out = dict(zip(["Fpz", "AFz", "Fz", "FCz", "Cz", "CPz", "Pz", "POz", "Oz"],
                   _at(mid, smid, fr)))
    out.update(zip(["T7", "C5", "C3", "C1", "_", "C2", "C4", "C6", "T8"], _at(cor, scor, fr)))
    del out["_"]
    ring = ["Fp", "AF", "F", "FT", "T", "TP", "P", "PO", "O"]
    for side, via, num in (("L", out["T7"], "7"), ("R", out["T8"], "8")):
        pts, s = _arc(scalp, c, out["Fpz"], out["Oz"], via)
        p = _at(pts, s, fr)
        names = [f"{r}{num}" for r in ring]
        names[0] = "Fp1" if side == "L" else "Fp2"
        names[-1] = "O1" if side == "L" else "O2"
        for nm, q in zip(names, p):
            if nm not in ("T7", "T8"):  # T7/T8 come from the coronal arc
                out[nm] = q
    rows = {"AF": [(0.5, "3", "4")],
            "F": [(0.25, "5", "6"), (0.5, "3", "4"), (0.75, "1", "2")],
            "FC": [(0.25, "5", "6"), (0.5, "3", "4"), (0.75, "1", "2")],
            "CP": [(0.25, "5", "6"), (0.5, "3", "4"), (0.75, "1", "2")],
            "P": [(0.25, "5", "6"), (0.5, "3", "4"), (0.75, "1", "2")],
            "PO": [(0.5, "3", "4")]}
    lateral = {"AF": "AF", "F": "F", "FC": "FT", "CP": "TP", "P": "P", "PO": "PO"}
    for row, items in rows.items():
        left, right, m = out[f"{lateral[row]}7"], out[f"{lateral[row]}8"], out[f"{row}z"]
        pts, s = _arc(scalp, c, left, right, m)
        sm = s[np.argmin(np.linalg.norm(pts - m, axis=1))]
        for f, ln, rn in items:
            out[f"{row}{ln}"] = _at(pts, s, [f], 0.0, sm)[0]
            out[f"{row}{rn}"] = _at(pts, s, [1.0 - f], sm, s[-1])[0]
    if extended:
        # 10-5 midline (Oostenveld & Praamstra 2001): halfway points of the Nz-Cz-Iz arc.
        out.update(zip(("Nz", "Iz"), _at(mid, smid, [0.0, 1.0])))
        out.update(zip(_MIDLINE_10_5, _at(mid, smid, np.arange(0.05, 1.0, 0.1))))
        # The 0 % ring Nz - T9 - Iz (T9/T10 at the pre-auricular points, the coronal arc's
        # ends), cut at 10 % of each half as the 10 % ring is.
        for num, via in (("9", frame.lpa), ("10", frame.rpa)):
            pts, s = _arc(scalp, c, frame.nz, frame.iz, via)
            for nm, q in zip(_LOWER_RING, _at(pts, s, fr[1:])):
                out[f"{nm}{num}"] = q
    return out


#: The 21 positions of the 10-20 system on the scalp (Jasper 1958; modern names, ACNS 2006:
#: T7/T8/P7/P8 for the old T3/T4/T5/T6). The ear electrodes A1/A2 are not on a scalp mesh, so
#: Fpz and Oz complete the 21.
TEN_TWENTY = ("Fp1", "Fpz", "Fp2", "F7", "F3", "Fz", "F4", "F8", "T7", "C3", "Cz", "C4", "T8",
              "P7", "P3", "Pz", "P4", "P8", "O1", "Oz", "O2")

#: The 61 positions of the 10-10 system at or above the 10 % ring (Fp/AF7/F7/FT7/T7/...):
#: Oostenveld & Praamstra 2001 (Clin. Neurophysiol. 112:713), ACNS guideline 5 (2006). The
#: lower ring (F9, T9, ...) and Nz/Iz are left out: they sit at ear level, where head meshes
#: are often truncated.
TEN_TEN = ("Fp1", "Fpz", "Fp2",
           "AF7", "AF3", "AFz", "AF4", "AF8",
           "F7", "F5", "F3", "F1", "Fz", "F2", "F4", "F6", "F8",
           "FT7", "FC5", "FC3", "FC1", "FCz", "FC2", "FC4", "FC6", "FT8",
           "T7", "C5", "C3", "C1", "Cz", "C2", "C4", "C6", "T8",
           "TP7", "CP5", "CP3", "CP1", "CPz", "CP2", "CP4", "CP6", "TP8",
           "P7", "P5", "P3", "P1", "Pz", "P2", "P4", "P6", "P8",
           "PO7", "PO3", "POz", "PO4", "PO8",
           "O1", "Oz", "O2")

_MIDLINE_10_5 = ("NFpz", "AFpz", "AFFz", "FFCz", "FCCz", "CCPz", "CPPz", "PPOz", "POOz", "OIz")
_LOWER_RING = ("AF", "F", "FT", "T", "TP", "P", "PO", "O")

#: Positions beyond `TEN_TEN` (Oostenveld & Praamstra 2001, the 10-10 lower ring and the 10-5
#: midline): Nz, Iz; the 0 % ring through Nz, the pre-auricular points (T9, T10) and Iz, cut
#: at 10 % of each half (AF9 F9 FT9 T9 TP9 P9 PO9 O9 on the left, ...10 on the right); the
#: midline halfway points NFpz (5 %, between Nz and Fpz; UCL's reference) ... OIz (95 %).
#: I1/I2 are read as O9/O10, the names UCL's recordings use for them. These sit at ear level
#: and below: the mesh must reach there (a head cut above the ears cannot carry them).
EXTENDED = (("Nz", "Iz") + _MIDLINE_10_5
            + tuple(f"{r}{n}" for n in ("9", "10") for r in _LOWER_RING))

LAYOUTS = {"10-20": TEN_TWENTY, "10-10": TEN_TEN}
_OLD_NAMES = {"T3": "T7", "T4": "T8", "T5": "P7", "T6": "P8", "I1": "O9", "I2": "O10"}


def layout_positions(mesh: TetMesh | Surface, layout="10-20", *, landmarks=None):
    """Positions of a standard EEG layout on the scalp of a mesh.

    Positions follow Oostenveld & Praamstra (2001): the midline (nasion-Cz-inion) and coronal
    (LPA-Cz-RPA) scalp arcs are cut at 10 % steps, with Cz iterated to be the midpoint of both;
    the 10 % ring through Fpz, T7/T8 and Oz is cut at 10 % of each half; the F/FC/CP/P rows are
    the arcs through (lateral, midline, lateral) points cut into quarters of each half.

    Arguments:
        mesh: the head TetMesh, or the scalp Surface (to place refinement points before
            meshing, e.g. `MeshConfig(refine_points_mm=...)`).
        layout: "10-20" (21 positions), "10-10" (61), or a sequence of names from the 10-10
            system and `EXTENDED` (old names T3/T4/T5/T6 are accepted and mapped to
            T7/T8/P7/P8; I1/I2 to O9/O10).
        landmarks: dict of world-mm coordinates "nasion", "inion", "lpa", "rpa" (projected
            onto the scalp); by default estimated with `estimate_landmarks` (RAS assumed).

    Returns:
        names: tuple of electrode names; positions: (n_elec, 3) mm on the scalp.
    """
    return _layout(_Scalp(mesh), _layout_names(layout), landmarks)


def _layout_names(layout) -> tuple[str, ...]:
    if isinstance(layout, str):
        if layout not in LAYOUTS:
            raise ValueError(f"unknown layout {layout!r}; use one of {list(LAYOUTS)} or a list "
                             "of 10-10 electrode names.")
        names = LAYOUTS[layout]
    else:
        names = tuple(str(n) for n in layout)
        if not names:
            raise ValueError("`layout` is an empty list of names.")
    lookup = {n.lower() for n in TEN_TEN + EXTENDED}
    bad = [n for n in names if _canon(n).lower() not in lookup]
    if bad:
        raise ValueError(f"unknown electrode names {bad}; use 10-10 names such as {TEN_TEN[:6]} "
                         f"or the extended ones {EXTENDED[:4]}... (see jaxhead.electrodes.EXTENDED).")
    return names


def is_electrode_name(name) -> bool:
    """Whether `name` is a 10-10 or extended 10-10 / 10-5 name `place_electrodes` can place
    (any case; old names T3/T4/T5/T6 and I1/I2 included)."""
    return isinstance(name, str) and _canon(name).lower() in {n.lower() for n in TEN_TEN + EXTENDED}


def _canon(name: str) -> str:
    """A name's canonical 10-10 spelling key (old names and aliases mapped, any case)."""
    for old, new in _OLD_NAMES.items():
        if name.lower() == old.lower():
            return new
    return name


def _layout(scalp: _Scalp, names, landmarks):
    canon = [_canon(n) for n in names]
    lookup = {n.lower(): n for n in TEN_TEN + EXTENDED}
    extended = any(lookup[n.lower()] in EXTENDED for n in canon)
    lm = _parse_landmarks(landmarks) if landmarks is not None else _estimate_landmarks(scalp)
    pos = _ten_ten(scalp, _HeadFrame(scalp, lm), extended)
    return tuple(names), np.stack([pos[lookup[n.lower()]] for n in canon])


def spread_positions(mesh: TetMesh | Surface, n_elec: int, *, landmarks=None,
                     max_polar_deg: float = 72.0) -> np.ndarray:
    """`n_elec` positions spread evenly over the upper head.

    A Fibonacci spiral (equal-area points: cos(polar) uniform, azimuth stepped by the golden
    angle; Gonzalez 2010, Math. Geosci. 42:49) on the cap of polar angle <= `max_polar_deg`
    around the head's superior axis, cast as rays from the head centre (midpoint of the
    pre-auricular points) onto the scalp. 72 deg is the 10 % ring of the 10-20 system on a
    sphere (Fpz, T7, Oz lie at 90 - 18 deg from the vertex).

    Arguments:
        mesh: the head TetMesh or the scalp Surface.
        n_elec: number of electrodes (>= 1).
        landmarks: as in `layout_positions` (defines centre and axes).
        max_polar_deg: cap half-angle in degrees from the vertex, 0 < . <= 180.

    Returns:
        (n_elec, 3) positions in mm on the scalp, the first nearest the vertex.
    """
    _check_count(n_elec, max_polar_deg)
    return _spread(_Scalp(mesh), n_elec, landmarks, max_polar_deg)


def _check_count(n_elec, max_polar_deg) -> None:
    if isinstance(n_elec, bool) or not isinstance(n_elec, (int, np.integer)) or n_elec < 1:
        raise ValueError(f"electrode count must be a positive int, got {n_elec!r}.")
    if not 0.0 < max_polar_deg <= 180.0:
        raise ValueError(f"`max_polar_deg` must be in (0, 180], got {max_polar_deg}.")


def _spread(scalp: _Scalp, n_elec: int, landmarks, max_polar_deg: float) -> np.ndarray:
    lm = _parse_landmarks(landmarks) if landmarks is not None else _estimate_landmarks(scalp)
    frame = _HeadFrame(scalp, lm)
    i = np.arange(n_elec) + 0.5
    cos_t = 1.0 - (1.0 - np.cos(np.radians(max_polar_deg))) * i / n_elec
    sin_t = np.sqrt(1.0 - cos_t**2)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * np.arange(n_elec)
    local = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)
    hits = scalp.ray_hits(frame.centre, local @ frame.axes)
    if np.isnan(hits).any():
        raise ValueError("rays from the head centre miss the scalp; pass `landmarks`.")
    return hits


def electrode_refinement_points(electrodes: Electrodes, nodes, *, edge_mm: float | None = None,
                                n_ring: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Points and target edge lengths for refining a mesh under the electrodes.

    For each electrode: its centre and `n_ring` points on the circle of its equivalent radius
    r = sqrt(area / pi) in the scalp's tangent plane (area-weighted normal of its faces). A
    mesher's sizing field that asks for edges of `edge_mm` near these points (default r / 2:
    about 30 faces per electrode, so the disc area is resolved to a few %) refines the scalp
    under every electrode.

    Arguments:
        electrodes: placed Electrodes.
        nodes: (n_nodes, 3) mm positions of the mesh the electrodes were placed on.
        edge_mm: target edge length in mm (default half of each electrode's radius).
        n_ring: points on each electrode's rim.

    Returns:
        points: (n_elec * (1 + n_ring), 3) mm; edge: (n_elec * (1 + n_ring),) target edge in mm.
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    p = nodes[electrodes.faces]
    fn = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # area-weighted normals
    normal = np.zeros((electrodes.n_elec, 3))
    np.add.at(normal, electrodes.face_electrode, fn)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    r = np.sqrt(electrodes.area_mm2(nodes) / np.pi)
    ref = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(normal, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    ang = 2 * np.pi * np.arange(n_ring) / n_ring
    ring = (electrodes.centres[:, None]
            + r[:, None, None] * (np.cos(ang)[None, :, None] * e1[:, None]
                                  + np.sin(ang)[None, :, None] * e2[:, None]))
    pts = np.concatenate([electrodes.centres[:, None], ring], axis=1).reshape(-1, 3)
    edge = np.repeat(r / 2 if edge_mm is None else np.full(electrodes.n_elec, float(edge_mm)),
                     1 + n_ring)
    if not np.all(edge > 0):
        raise ValueError(f"`edge_mm` must be > 0, got {edge_mm}.")
    return pts, edge


@dataclass(frozen=True, kw_only=True)
class ElectrodeConfig:
    """Settings of :func:`electrodes_from_config` (the pipeline's electrode stage).

    Arguments:
        layout: "10-20" (21 electrodes), "10-10" (61), a list of 10-10 names, or a count of
            electrodes spread over the upper head.
        radius_mm: electrode radius (mm); 5 mm is a 10 mm EEG cup electrode.
        contact_impedance_ohm_m2: contact impedance (Ohm m^2), see `place_electrodes`.
        landmarks_mm: {"nasion", "inion", "lpa", "rpa"} world-mm coordinates; None estimates
            them from the scalp shape (RAS assumed, see `estimate_landmarks`).
        max_distance_mm: positions farther from the scalp are an error.
        refine_mesh: the pipeline's mesh stage refines the mesh under these electrodes
            (`MeshConfig.refine_edge_mm` within `refine_radius_mm`, at least the electrode
            radius plus two refined edges): the potential varies fastest at the electrodes (the
            CEM's edge singularity), and refining there is what brings a head mesh close to a
            much finer reference (experiments/results/mesh_convergence.md).
    """

    layout: str | int | tuple[str, ...] = "10-20"
    radius_mm: float = 5.0
    contact_impedance_ohm_m2: float = DEFAULT_CONTACT_IMPEDANCE_OHM_M2
    landmarks_mm: dict[str, tuple[float, float, float]] | None = None
    max_distance_mm: float = 10.0
    refine_mesh: bool = True

    def __post_init__(self):
        if not isinstance(self.refine_mesh, bool):
            raise ValueError(f"`refine_mesh` must be true or false, got {self.refine_mesh!r}.")
        if isinstance(self.layout, bool) or not isinstance(self.layout, (str, int, tuple, list)):
            raise ValueError(f"`layout` must be '10-20', '10-10', a list of names or a count, "
                             f"got {self.layout!r}.")
        if isinstance(self.layout, int):
            _check_count(self.layout, 72.0)
        else:
            _layout_names(self.layout if isinstance(self.layout, str) else tuple(self.layout))
        for name in ("radius_mm", "contact_impedance_ohm_m2", "max_distance_mm"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v <= 0:
                raise ValueError(f"`{name}` must be a positive number, got {v!r}.")
        if self.landmarks_mm is not None:
            _parse_landmarks(dict(self.landmarks_mm))


def electrode_positions(scalp: TetMesh | Surface, cfg: ElectrodeConfig = ElectrodeConfig()
                        ) -> np.ndarray:
    """Where an `ElectrodeConfig` puts its electrodes on a head mesh or a scalp Surface.

    The same positions `electrodes_from_config` places its discs at; on the scalp Surface this
    is available before meshing (to refine the mesh there).

    Returns:
        (n_elec, 3) world mm on the scalp.
    """
    landmarks = None if cfg.landmarks_mm is None else dict(cfg.landmarks_mm)
    if isinstance(cfg.layout, int):
        return spread_positions(scalp, cfg.layout, landmarks=landmarks)
    layout = cfg.layout if isinstance(cfg.layout, str) else list(cfg.layout)
    return np.asarray(layout_positions(scalp, layout, landmarks=landmarks)[1])


def refined_mesh_config(mesh_cfg: MeshConfig, scalp: TetMesh | Surface,
                        cfg: ElectrodeConfig = ElectrodeConfig()) -> MeshConfig:
    """`mesh_cfg` refined under the electrodes of `cfg`, as the pipeline's mesh stage meshes.

    The refine points are `electrode_positions` on the scalp; the refine radius is at least
    the electrode radius plus two refined edges (the rule `ElectrodeConfig.refine_mesh`
    documents). Returns `mesh_cfg` unchanged when `cfg.refine_mesh` is false or `mesh_cfg`
    already has its own refine points.
    """
    if not cfg.refine_mesh or mesh_cfg.refine_points_mm:
        return mesh_cfg
    pos = electrode_positions(scalp, cfg)
    radius = max(mesh_cfg.refine_radius_mm, cfg.radius_mm + 2 * mesh_cfg.refine_edge_mm)
    return dataclasses.replace(mesh_cfg, refine_points_mm=tuple(map(tuple, pos.tolist())),
                               refine_radius_mm=radius)


def electrodes_from_config(mesh: TetMesh, cfg: ElectrodeConfig = ElectrodeConfig()) -> Electrodes:
    """Place electrodes on a mesh as an `ElectrodeConfig` says (see `place_electrodes`)."""
    layout = cfg.layout if isinstance(cfg.layout, (str, int)) else list(cfg.layout)
    return place_electrodes(
        mesh, layout, radius_mm=cfg.radius_mm, contact_impedance_ohm_m2=cfg.contact_impedance_ohm_m2,
        landmarks=None if cfg.landmarks_mm is None else dict(cfg.landmarks_mm),
        max_distance_mm=cfg.max_distance_mm)


# --------------------------------------------------------------------------------------------
# Recording coordinates registered to the scalp; landmarks from files


class Registration(eqx.Module):
    """Electrode coordinates of a recording mapped onto a head's scalp (`register_positions`).

    Attributes:
        positions_mm: (n_elec, 3) registered positions projected onto the scalp (world mm).
        matrix: (4, 4) similarity transform (scale * rotation, translation) from the
            recording's coordinates to world mm.
        scale: the transform's scale (e.g. ~1000 for a recording in metres).
        scalp_distance_mm: (n_elec,) distance of each transformed position from the scalp.
        name_residual_mm: (n_elec,) distance to the named position on this head (NaN for
            unnamed electrodes or ICP-only registrations).
        method: "names", "icp" or "names+icp".
    """

    positions_mm: np.ndarray
    matrix: np.ndarray
    scale: float
    scalp_distance_mm: np.ndarray
    name_residual_mm: np.ndarray
    method: str = eqx.field(static=True)

    def report(self) -> str:
        nr = self.name_residual_mm[np.isfinite(self.name_residual_mm)]
        txt = (f"registration ({self.method}): scale {self.scale:.6g}; distance to scalp "
               f"median {np.median(self.scalp_distance_mm):.2f} mm, max "
               f"{np.max(self.scalp_distance_mm):.2f} mm")
        if nr.size:
            txt += f"; to named positions median {np.median(nr):.2f} mm, max {np.max(nr):.2f} mm"
        return txt


def _similarity(src: np.ndarray, dst: np.ndarray, scale: bool = True) -> np.ndarray:
    """Least-squares similarity dst ~ s R src + t (Umeyama 1991, IEEE TPAMI 13:376), 4x4."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    e = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2, 2] = -1.0  # a rotation, never a reflection
    r = u @ e @ vt
    s = float(np.trace(np.diag(d) @ e) / (a**2).sum(1).mean()) if scale else 1.0
    m = np.eye(4)
    m[:3, :3] = s * r
    m[:3, 3] = mu_d - s * r @ mu_s
    return m


def _apply(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ m[:3, :3].T + m[:3, 3]


def register_positions(mesh: TetMesh | Surface, positions, *, names=None, landmarks=None,
                       icp: bool | None = None, scale: bool = True, max_iterations: int = 50,
                       max_distance_mm: float = 10.0) -> Registration:
    """Map electrode coordinates from a recording's own frame onto a head's scalp.

    With `names` (at least 4 of them 10-10 / `EXTENDED` names), a similarity transform
    (rotation, translation and, with `scale`, one scale factor; Umeyama 1991) takes the named
    electrodes onto their positions on this head (`layout_positions`, so `landmarks` matter),
    then, with `icp`, iterative closest points on the scalp refine it. Without names only ICP
    runs, started from the centroids and RMS radii (rotation as given: the frame must be
    roughly RAS). The positions are then projected onto the scalp; the residuals are reported.

    Arguments:
        mesh: the head TetMesh or its scalp Surface.
        positions: (n_elec, 3) coordinates in any length unit and frame.
        names: optional names, one per electrode (unknown names are simply not used).
        landmarks: as in `layout_positions`.
        icp: refine by closest points (default: only when there are no usable names).
        scale: fit a scale factor (units); False keeps 1 (a recording already in mm).
        max_iterations: ICP iterations.
        max_distance_mm: a registered electrode farther than this from the scalp is an error.

    Returns:
        A `Registration` (positions on the scalp, transform, residuals; `report()`).
    """
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 3 or not np.all(np.isfinite(p)):
        raise ValueError(f"`positions` must be (n_elec >= 3, 3) finite coordinates, got shape "
                         f"{p.shape}.")
    n = p.shape[0]
    scalp = _Scalp(mesh)
    known = {x.lower() for x in TEN_TEN + EXTENDED}
    use = [] if names is None else [i for i, nm in enumerate(names)
                                    if _canon(str(nm)).lower() in known]
    if names is not None and len(names) != n:
        raise ValueError(f"`names` has {len(names)} entries for {n} positions.")
    resid = np.full(n, np.nan)
    if len(use) >= 4:
        _, target = _layout(scalp, [names[i] for i in use], landmarks)
        m = _similarity(p[use], target, scale)
        method = "names"
        if icp:
            method = "names+icp"
    else:
        if names is not None and icp is False:
            raise ValueError(f"only {len(use)} of `names` are 10-10 names; registration by "
                             "names needs >= 4 (or pass icp=True).")
        v = scalp.tm.vertices
        c_p, c_v = p.mean(0), v.mean(0)
        s = (np.sqrt(((v - c_v) ** 2).sum(1).mean()) / np.sqrt(((p - c_p) ** 2).sum(1).mean())
             if scale else 1.0)
        m = np.eye(4)
        m[:3, :3] *= s
        m[:3, 3] = c_v - s * c_p
        method, icp = "icp", True
    if icp:
        # Closest-point iterations (Besl & McKay 1992) with the similarity re-fitted each time.
        for _ in range(int(max_iterations)):
            q = _apply(m, p)
            cp, _, _ = scalp.project(q)
            m_new = _similarity(p, cp, scale)
            if np.abs(_apply(m_new, p) - q).max() < 1e-6:
                m = m_new
                break
            m = m_new
    q = _apply(m, p)
    on, dist, _ = scalp.project(q)
    if use and len(use) >= 4:
        resid[use] = np.linalg.norm(q[use] - target, axis=1)
    far = np.flatnonzero(dist > max_distance_mm)
    if far.size:
        lab = [names[i] if names is not None else f"#{i}" for i in far[:10]]
        raise ValueError(f"after registration electrodes {lab} are {np.round(dist[far[:10]], 1)} "
                         f"mm from the scalp (> max_distance_mm={max_distance_mm}); check the "
                         "names, landmarks or units.")
    return Registration(positions_mm=on, matrix=m, scale=float(np.cbrt(np.linalg.det(m[:3, :3]))),
                        scalp_distance_mm=dist, name_residual_mm=resid, method=method)


def load_landmarks(path) -> dict[str, np.ndarray]:
    """Nasion, inion and pre-auricular points (world mm) from a JSON or CSV file.

    JSON: {"nasion": [x, y, z], "inion": [...], "lpa": [...], "rpa": [...]} (aliases nz, iz,
    al/ar, left/right accepted; an optional "units": "mm" | "m"). CSV: lines ``name,x,y,z``
    in mm. Fiducial files of templates (MNI152, fsaverage) give these in their own frame.
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    factor = 1.0
    if path.suffix.lower() == ".json":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not JSON ({e}).") from e
        unit = str(d.pop("units", "mm")).lower()
        factor = {"mm": 1.0, "m": 1000.0, "cm": 10.0}.get(unit)
        if factor is None:
            raise ValueError(f"{path}: units {unit!r}; use mm, cm or m.")
    else:
        d = {}
        for lineno, line in enumerate(text.splitlines(), 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = [x.strip() for x in s.replace(";", ",").split(",")]
            try:
                d[parts[0]] = [float(x) for x in parts[1:4]]
            except (ValueError, IndexError):
                if lineno == 1:
                    continue  # header
                raise ValueError(f"{path}:{lineno}: expected name,x,y,z in mm, got {line!r}.") from None
    try:
        lm = _parse_landmarks({k: np.asarray(v, float) * factor for k, v in d.items()})
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e
    return lm


def landmark_report(mesh: TetMesh | Surface, given) -> dict[str, float]:
    """Distance (mm) of `estimate_landmarks(mesh)` from `given` landmarks, per landmark.

    The estimate assumes RAS and a roughly spherical upper head; on real heads compare it with
    the head's own fiducials this way before trusting named electrode positions.
    """
    lm = _parse_landmarks(given)
    est = _estimate_landmarks(_Scalp(mesh))
    return {k: float(np.linalg.norm(est[k] - lm[k])) for k in LANDMARKS}
