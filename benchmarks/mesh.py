"""Time label map -> mesh for a phantom head, and report the mesh against the seed paper.

Stages timed: make_head (the phantom, not part of the pipeline), make_layers, extract_surfaces,
tetrahedralize (fTetWild + improvement, split as in its report). Printed: seconds per stage, tet
count, the seed paper's Table-2 row (Vonach et al. 2012: MRI meshes of ~300k elements had 3-11
outside scaled Jacobian 0.2-1 and 8-26 outside condition number 1-3), per-tissue volume against
the voxel volume of the layered label map, and the fraction of tets whose centroid's voxel has
the tet's label. The baseline for time is the seed paper's (30 min per MRI, 60 min per CT, with
manual steps in MeshLab and CUBIT); no automatic peer runs here.

    .venv/bin/python benchmarks/mesh.py --voxel-mm 1.0 --modality mri [--threads 1] [--save out.npz]

The machine is shared: pass --threads 1 for comparable numbers on a loaded 2-core machine.
"""

import argparse
import json
import os
import sys
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from jaxhead.mesh import MeshConfig, tetrahedralize_reported  # noqa: E402
from jaxhead.phantom import make_head  # noqa: E402
from jaxhead.quality import quality_report  # noqa: E402
from jaxhead.segment.layers import make_layers  # noqa: E402
from jaxhead.surface import SurfaceConfig, extract_surfaces  # noqa: E402
from jaxhead.tissue import TISSUES  # noqa: E402
from jaxhead.volume import voxel_sizes  # noqa: E402


def centroid_agreement(mesh, labels) -> float:
    """Fraction of tets whose centroid's nearest voxel carries the tet's label."""
    inv = np.linalg.inv(np.asarray(labels.affine))
    c = mesh.centroids()
    ijk = np.rint(c @ inv[:3, :3].T + inv[:3, 3]).astype(int)
    lab = np.asarray(labels.labels)
    ijk = np.clip(ijk, 0, np.array(lab.shape) - 1)
    return float(np.mean(lab[ijk[:, 0], ijk[:, 1], ijk[:, 2]] == mesh.labels))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel-mm", type=float, default=1.0)
    ap.add_argument("--modality", choices=("mri", "ct"), default="mri")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0, help="fTetWild threads (0: all cores)")
    ap.add_argument("--edge-mm", type=str, default=None,
                    help='JSON per-tissue edges, e.g. \'{"brain": 4, "csf": 2, "skull": 2.5, "scalp": 3}\'')
    ap.add_argument("--surface-edge-mm", type=str, default=None,
                    help="JSON per-tissue surface edges for SurfaceConfig.edge_mm (coarser surfaces: fewer tets)")
    ap.add_argument("--improve", choices=("relocate", "none"), default="relocate")
    ap.add_argument("--save", type=str, default=None, help="save nodes/tets/labels to this .npz")
    a = ap.parse_args(argv)

    t = {}
    t0 = time.perf_counter()
    _, labels = make_head(a.modality, voxel_mm=a.voxel_mm, seed=a.seed)
    t["make_head (phantom)"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    layers = make_layers(labels)
    t["make_layers"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scfg = SurfaceConfig(edge_mm=json.loads(a.surface_edge_mm)) if a.surface_edge_mm else SurfaceConfig()
    surfaces = extract_surfaces(layers, scfg)
    t["extract_surfaces"] = time.perf_counter() - t0
    kw = {"threads": a.threads, "improve": a.improve}
    if a.edge_mm:
        kw["edge_mm"] = json.loads(a.edge_mm)
    t0 = time.perf_counter()
    mesh, rep = tetrahedralize_reported(surfaces, MeshConfig(**kw))
    t["tetrahedralize"] = time.perf_counter() - t0
    q = quality_report(mesh)

    print(f"phantom {a.modality} {a.voxel_mm:g} mm, grid {np.asarray(labels.labels).shape}, "
          f"seed {a.seed}, fTetWild threads {a.threads or 'all'}")
    print("seconds per stage:")
    for k, v in t.items():
        print(f"  {k:<22s} {v:8.1f}")
    for k, v in rep.seconds.items():
        print(f"    tetrahedralize/{k:<10s} {v:6.1f}")
    pipeline = t["make_layers"] + t["extract_surfaces"] + t["tetrahedralize"]
    print(f"  label map -> mesh      {pipeline:8.1f}  (seed paper: ~1800 s per MRI, 3600 per CT, "
          f"ratio {1800 / pipeline:.0f}x for MRI)")
    print(rep)
    row = q.table2_row
    print(f"Table 2 row: {row['elements']} elements; outside: Jacobian {row['jacobian']}, "
          f"scaled Jacobian {row['scaled_jacobian']}, distortion {row['distortion']}, "
          f"condition {row['condition']} (seed MRI rows: 3-11 and 8-26 of ~300k)")
    vox = float(np.prod(voxel_sizes(np.asarray(layers.affine))))
    lab = np.asarray(layers.labels)
    vols = mesh.tissue_volumes_mm3()
    print("per-tissue volume vs voxel volume of the layered label map:")
    for tis in TISSUES:
        vv = float((lab == int(tis)).sum()) * vox
        print(f"  {tis.name:<6s} mesh {vols[tis] / 1e3:9.2f} cm^3  voxels {vv / 1e3:9.2f} cm^3  "
              f"error {100 * (vols[tis] / vv - 1):+6.2f} %")
    print(f"centroid label agreement with the layered label map: {100 * centroid_agreement(mesh, layers):.2f} %")
    if a.save:
        np.savez(a.save, nodes=mesh.nodes, tets=mesh.tets, labels=mesh.labels)


if __name__ == "__main__":
    main()
