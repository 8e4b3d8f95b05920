"""Mesh convergence of CEM voltages on one head: the same surfaces, three volume meshes.

The 2 mm MRI phantom (seed 0) at the default surface sizes, meshed (A) at the default tet sizes,
(B) the same refined to 2 mm within 8 mm of 32 electrode positions, (C) a 1.3M-tet reference with
finer tets (6/2.5/2.5/3 mm) refined to 1.5 mm under the electrodes. Voltages of drives (i, i + k),
k = 1, 4, 8, 16, each measured on every adjacent pair avoiding it (3616 rows), with the default and
with uniform conductivities; prints the relative l2 difference of A and B to C.

Usage: python experiments/mesh_convergence.py [OUT_DIR]   (~15 min; meshes cached)
"""
import os
import sys
import time
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax; jax.config.update("jax_enable_x64", True)
import numpy as np
from jaxhead.phantom import make_head
from jaxhead.geometry.layers import make_layers
from jaxhead.geometry.surface import extract_surfaces
from jaxhead.geometry import MeshConfig, tetrahedralize
from jaxhead.io import save_mesh, load_mesh
from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import build_forward_model, simulate, Direct
from jaxhead.protocol import Protocol, pair_drive
from jaxhead.tissue import Tissue, default_sigma

out = sys.argv[1] if len(sys.argv) > 1 else "runs/mesh_convergence"
os.makedirs(out, exist_ok=True)
_, labels = make_head("mri", voxel_mm=2.0, seed=0)
surfs = extract_surfaces(make_layers(labels))
pos = spread_positions(surfs[Tissue.SCALP], 32)
variants = {
    "A_default": MeshConfig(),
    "B_refined": MeshConfig(refine_points_mm=tuple(map(tuple, pos)), refine_edge_mm=2.0, refine_radius_mm=8.0),
    "C_fine_refined": MeshConfig(edge_mm={"brain": 6.0, "csf": 2.5, "skull": 2.5, "scalp": 3.0},
                                 refine_points_mm=tuple(map(tuple, pos)), refine_edge_mm=1.5, refine_radius_mm=8.0),
}
rows = np.concatenate([pair_drive(32, i, (i + k) % 32).rows for k in (1, 4, 8, 16) for i in range(32)])
prot = Protocol(rows)
V = {}
for name, cfg in variants.items():
    path = f"{out}/{name}.vtu"
    t = time.perf_counter()
    if os.path.exists(path):
        mesh = load_mesh(path)
    else:
        mesh = tetrahedralize(surfs, cfg)
        save_mesh(mesh, path)
    print(f"{name}: {mesh.n_tets} tets, {mesh.n_nodes} nodes, {time.perf_counter()-t:.0f} s", flush=True)
    e = place_electrodes(mesh, pos, radius_mm=6.0)
    m = build_forward_model(mesh, e, solver=Direct(threads=2))
    V[name] = {s: np.asarray(simulate(m, sig, prot)) for s, sig in
               [("default", default_sigma()), ("uniform", np.full(4, 0.3))]}
    print(f"  electrode areas mm2 {e.area_mm2().min():.1f}-{e.area_mm2().max():.1f}", flush=True)
ref = "C_fine_refined"
for s in ("default", "uniform"):
    for k in V:
        if k != ref and ref in V:
            a, b = V[ref][s], V[k][s]
            print(f"{s:8s} {k} vs {ref}: rel. l2 mismatch {np.linalg.norm(a-b)/np.linalg.norm(a):.4f}")
    if "A_default" in V and "B_refined" in V:
        a, b = V["A_default"][s], V["B_refined"][s]
        print(f"{s:8s} A vs B: {np.linalg.norm(a-b)/np.linalg.norm(a):.4f}")
