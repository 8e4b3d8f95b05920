"""The gmsh backend of :func:`jaxhead.geometry.tetrahedralize`: constrained Delaunay (HXT).  [host]

gmsh (Geuzaine & Remacle 2009, IJNME 79:1309; GPL-2.0-or-later, an optional extra:
``pip install jaxhead[gmsh]``) meshes the four nested surfaces as four volumes bounded by
discrete surfaces: the input triangles are the mesh's interface faces (no envelope, no
relabelling), each tet's tissue is its volume's. The 3D algorithm is HXT (Marot, Pellerin &
Remacle 2019, IJNME 117:967: parallel Delaunay refinement, reproducible for a given thread
count), followed by gmsh's own tet optimiser (``Mesh.Optimize``). Sizes: the per-tissue edge
inside each volume (a ``Constant`` field per volume), graded from the surfaces' own edges
(``Mesh.MeshSizeExtendFromBoundary``), and the refinement law around the refine points (a
``MathEval`` field); the smallest applies.
"""

import os

import numpy as np

from ..tissue import TISSUES

#: gmsh options. The 3D algorithm is HXT (``Mesh.Algorithm3D`` = 10): on the 2 mm phantom's surfaces
#: it was faster than gmsh's Delaunay (1) and left fewer tets outside the Table-2 limits
#: (experiments/results/meshers.md). Sizes come from the fields and the boundary only.
_OPTIONS = {
    "Mesh.MeshSizeFromPoints": 0,
    "Mesh.MeshSizeFromCurvature": 0,
    "Mesh.MeshSizeExtendFromBoundary": 1,
    "Mesh.Algorithm3D": 10,
    "Mesh.Optimize": 1,
    # gmsh (HXT) optimises the tets whose quality (gamma) is below this. Below the refine points
    # most of its time goes on a few thousand tets pinned between the refined surfaces that it
    # cannot mend: on the 2 mm phantom refined under 21 electrodes, 0.5 took 25 s of HXT's 27 s
    # and 0.3 took 1 s, and the improvement step then mended either mesh to 0 outside Table 2
    # (experiments/results/meshers.md).
    "Mesh.OptimizeThreshold": 0.3,
}


def _refine_expression(points: np.ndarray, edge_mm: float, radius_mm: float, grading: float) -> str:
    """gmsh MathEval expression: edge + grading * max(distance to the nearest point - radius, 0)."""
    d = [f"Sqrt((x-({p[0]:.6f}))^2+(y-({p[1]:.6f}))^2+(z-({p[2]:.6f}))^2)" for p in points]
    nearest = d[0]
    for x in d[1:]:
        nearest = f"Min({nearest},{x})"
    return f"{edge_mm:.6f}+{grading:.6f}*Max({nearest}-{radius_mm:.6f},0)"


def mesh_gmsh(surfs, edges_mm, *, refine_points_mm: np.ndarray, refine_edge_mm: float,
              refine_radius_mm: float, refine_grading: float, threads: int):
    """Four-tissue tet mesh of the nested surfaces with gmsh.

    Arguments:
        surfs: [(vertices (n_k, 3) mm, faces (m_k, 3))] of the BRAIN, CSF, SKULL, SCALP
            surfaces: closed, outward, strictly nested (checked by the caller).
        edges_mm: four target edges (mm), BRAIN..SCALP, each inside its own shell.
        refine_points_mm: (k, 3) mm, may be empty; refine_edge_mm, refine_radius_mm,
            refine_grading: the refinement law around them (see ``MeshConfig``).
        threads: gmsh threads (0: all cores).

    Returns:
        (nodes (n, 3) mm, tets (m, 4) int64, labels (m,) int64 in 1..4). Tets are as gmsh
        orients them (positive for gmsh; the caller checks).
    """
    import gmsh

    started = not gmsh.isInitialized()
    if started:
        # interruptible=False: no SIGINT handler, so this also runs off the main thread (Dask).
        gmsh.initialize(interruptible=False)
    name = f"jaxhead-{os.getpid()}-{id(surfs)}"
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 0)
        gmsh.option.setNumber("General.NumThreads", int(threads) if threads else (os.cpu_count() or 1))
        gmsh.model.add(name)
        offset = 1
        for k, (V, F) in enumerate(surfs):
            gmsh.model.addDiscreteEntity(2, k + 1)
            gmsh.model.mesh.addNodes(2, k + 1, list(range(offset, offset + len(V))),
                                     np.asarray(V, dtype=np.float64).ravel().tolist())
            gmsh.model.mesh.addElementsByType(k + 1, 2, [], (np.asarray(F) + offset).ravel().tolist())
            offset += len(V)
        for k in range(4):
            gmsh.model.geo.addSurfaceLoop([k + 1], k + 1)
            gmsh.model.geo.addVolume([k + 1] if k == 0 else [k + 1, k], k + 1)
        gmsh.model.geo.synchronize()
        field = gmsh.model.mesh.field
        fields = []
        for k, h in enumerate(edges_mm):
            f = field.add("Constant")
            field.setNumber(f, "VIn", float(h))
            field.setNumber(f, "VOut", 1e22)
            field.setNumbers(f, "VolumesList", [k + 1])
            fields.append(f)
        if len(refine_points_mm):
            f = field.add("MathEval")
            field.setString(f, "F", _refine_expression(np.asarray(refine_points_mm), refine_edge_mm,
                                                       refine_radius_mm, refine_grading))
            fields.append(f)
        f = field.add("Min")
        field.setNumbers(f, "FieldsList", fields)
        field.setAsBackgroundMesh(f)
        for key, value in _OPTIONS.items():
            gmsh.option.setNumber(key, value)
        try:
            gmsh.model.mesh.generate(3)
        except Exception as e:  # gmsh raises Exception with its last error message
            raise RuntimeError(f"gmsh failed on the four surfaces: {e}") from e
        tags, coords, _ = gmsh.model.mesh.getNodes()
        tags = np.asarray(tags, dtype=np.int64)
        nodes = np.zeros((int(tags.max()) + 1, 3))
        nodes[tags] = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
        tets, labels = [], []
        for k in range(4):
            types, _, conn = gmsh.model.mesh.getElements(3, k + 1)
            if 4 not in list(types):
                raise RuntimeError(f"gmsh returned no tets in the {TISSUES[k].name} shell.")
            t = np.asarray(conn[list(types).index(4)], dtype=np.int64).reshape(-1, 4)
            tets.append(t)
            labels.append(np.full(len(t), int(TISSUES[k]), dtype=np.int64))
    finally:
        if started:
            gmsh.finalize()
        else:
            gmsh.model.remove()
    tets, labels = np.concatenate(tets), np.concatenate(labels)
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return nodes[used], remap[tets], labels
