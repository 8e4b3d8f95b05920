"""Time label map -> mesh for a phantom head, and report the mesh against the seed paper.

Stages timed (wall and CPU seconds): make_head (the phantom, not part of the pipeline),
make_layers, extract_surfaces, tetrahedralize (fTetWild + improvement, split as in its report),
quality_report. Printed: seconds per stage, tet
count, the seed paper's Table-2 row (Vonach et al. 2012: MRI meshes of ~300k elements had 3-11
outside scaled Jacobian 0.2-1 and 8-26 outside condition number 1-3), per-tissue volume against
the voxel volume of the layered label map, and the fraction of tets whose centroid's voxel has
the tet's label. The baseline for time is the seed paper's (30 min per MRI, 60 min per CT, with
manual steps in MeshLab and CUBIT); no automatic peer runs here.

    .venv/bin/python benchmarks/mesh.py --voxel-mm 1.0 --modality mri [--threads 1] [--save out.npz]

The machine is shared: pass --threads 1 for comparable numbers on a loaded 2-core machine.

Measured (2 shared cores, load average 6-7, default sizes): 1 mm MRI phantom 258,873 tets, 0
elements outside Table 2, volumes within 1.2 % of the voxels', centroid agreement 99.43 % of tets
(99.83 % of volume); label map -> quality report 672 s wall, 299 s CPU (fTetWild 645 s wall).
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

from jaxhead.geometry import MeshConfig, tetrahedralize_reported  # noqa: E402
from jaxhead.phantom import make_head  # noqa: E402
from jaxhead.geometry.quality import quality_report  # noqa: E402
from jaxhead.geometry.layers import make_layers  # noqa: E402
from jaxhead.geometry.surface import SurfaceConfig, extract_surfaces  # noqa: E402
from jaxhead.tissue import TISSUES  # noqa: E402
from jaxhead.volume import voxel_sizes  # noqa: E402


def centroid_labels(mesh, labels) -> np.ndarray:
    """Label of the voxel nearest each tet centroid, (n_tets,)."""
    inv = np.linalg.inv(np.asarray(labels.affine))
    c = mesh.centroids()
    ijk = np.rint(c @ inv[:3, :3].T + inv[:3, 3]).astype(int)
    lab = np.asarray(labels.labels)
    ijk = np.clip(ijk, 0, np.array(lab.shape) - 1)
    return lab[ijk[:, 0], ijk[:, 1], ijk[:, 2]]


def centroid_agreement(mesh, labels) -> float:
    """Fraction of tets whose centroid's nearest voxel carries the tet's label."""
    return float(np.mean(centroid_labels(mesh, labels) == mesh.labels))


def agreement_report(mesh, labels, surfaces) -> str:
    """Centroid-label agreement by count and by volume, per tissue, and where the misses sit.

    A miss whose centroid lies within about one voxel of an interface surface is a
    discretisation effect of comparing a smooth surface with a voxel staircase; misses far from
    every surface would be labelling errors.
    """
    from jaxhead.geometry.tetrahedralize import _Dist

    vox = centroid_labels(mesh, labels)
    lab = np.asarray(mesh.labels)
    vol = mesh.tet_volumes()
    ok = vox == lab
    vsz = float(np.max(voxel_sizes(np.asarray(labels.affine))))
    lines = [f"centroid label agreement: {100 * ok.mean():.2f} % of tets, "
             f"{100 * vol[ok].sum() / vol.sum():.2f} % of volume"]
    for t in TISSUES:
        s = lab == int(t)
        lines.append(f"  {t.name:<6s} {100 * ok[s].mean():6.2f} % of tets, "
                     f"{100 * vol[s & ok].sum() / vol[s].sum():6.2f} % of volume")
    bad = np.flatnonzero(~ok)
    if len(bad):
        c = mesh.centroids()[bad]
        d = np.min([_Dist(np.asarray(surfaces[t].vertices), np.asarray(surfaces[t].faces))(c)
                    for t in TISSUES], axis=0)
        q = np.percentile(d, [50, 90, 99, 100])
        lines.append(f"  misses: {len(bad)}; centroid distance to the nearest surface (mm): median "
                     f"{q[0]:.2f}, 90% {q[1]:.2f}, 99% {q[2]:.2f}, max {q[3]:.2f}; "
                     f"{100 * np.mean(d <= vsz):.1f} % within one voxel ({vsz:g} mm)")
        pairs, counts = np.unique(np.stack([lab[bad], vox[bad]], 1), axis=0, return_counts=True)
        top = np.argsort(-counts)[:6]
        lines.append("  mesh label -> voxel label (count): " + ", ".join(
            f"{int(pairs[i, 0])}->{int(pairs[i, 1])} ({counts[i]})" for i in top))
    return "\n".join(lines)


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
    ap.add_argument("--save-surfaces", type=str, default=None,
                    help="pickle the layered label map and the surfaces to this path")
    a = ap.parse_args(argv)

    t, cpu = {}, {}

    def clock(name, f, *args):
        w0, c0 = time.perf_counter(), time.process_time()
        out = f(*args)
        t[name], cpu[name] = time.perf_counter() - w0, time.process_time() - c0
        return out

    _, labels = clock("make_head (phantom)", lambda: make_head(a.modality, voxel_mm=a.voxel_mm, seed=a.seed))
    layers = clock("make_layers", make_layers, labels)
    scfg = SurfaceConfig(edge_mm=json.loads(a.surface_edge_mm)) if a.surface_edge_mm else SurfaceConfig()
    surfaces = clock("extract_surfaces", extract_surfaces, layers, scfg)
    if a.save_surfaces:
        import pickle

        with open(a.save_surfaces, "wb") as fh:
            pickle.dump({"layers": layers, "surfaces": surfaces}, fh)
    print("surface faces: " + ", ".join(f"{t.name} {len(s.faces)}" for t, s in surfaces.items()), flush=True)
    kw = {"threads": a.threads, "improve": a.improve}
    if a.edge_mm:
        kw["edge_mm"] = json.loads(a.edge_mm)
    mesh, rep = clock("tetrahedralize", tetrahedralize_reported, surfaces, MeshConfig(**kw))
    if a.save:
        np.savez(a.save, nodes=mesh.nodes, tets=mesh.tets, labels=mesh.labels)
    q = clock("quality_report", quality_report, mesh)

    print(f"phantom {a.modality} {a.voxel_mm:g} mm, grid {np.asarray(labels.labels).shape}, "
          f"seed {a.seed}, fTetWild threads {a.threads or 'all'}")
    print(f"load average at the end: {' '.join(f'{x:.2f}' for x in os.getloadavg())} "
          f"({os.cpu_count()} cores)")
    print("seconds per stage (wall, CPU of this process incl. fTetWild threads):")
    for k, v in t.items():
        print(f"  {k:<22s} {v:8.1f} {cpu[k]:8.1f}")
    for k, v in rep.seconds.items():
        print(f"    tetrahedralize/{k:<10s} {v:6.1f}")
    stages = ("make_layers", "extract_surfaces", "tetrahedralize", "quality_report")
    pipeline = sum(t[k] for k in stages)
    print(f"  label map -> quality   {pipeline:8.1f} {sum(cpu[k] for k in stages):8.1f}  (seed paper: "
          f"~1800 s per MRI, 3600 per CT with manual steps; ratio {1800 / pipeline:.0f}x for MRI)")
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
    print(agreement_report(mesh, layers, surfaces))


if __name__ == "__main__":
    main()
