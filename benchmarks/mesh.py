"""Time label map -> Table-2-clean mesh on a head: jaxhead's default mesher against the raw mesher
and fTetWild, on the same surfaces, in one run, with ratios.

The mesh is the one the pipeline's mesh stage makes: MeshConfig() refined under the electrodes
(`--electrodes`, default the 10-20 layout's 21; `electrodes.refined_mesh_config`, as the mesh
stage calls it); `--electrodes none` times the unrefined mesh. Stages timed (wall and CPU seconds):
the head's labels (phantom `make_head`, or `--head mni152`: the MNI152-based head's true labels at
1 mm, cut at the neck; not part of the figure), make_layers, extract_surfaces, the refine points,
tetrahedralize (mesher "auto": gmsh when installed, then TetGen, then fTetWild; improvement on),
quality_report. Then every mesher in --compare meshes the same surfaces with the same refinement;
for each: the raw mesher's seconds (the report's mesher step), the improvement's seconds, tets, the
seed paper's Table-2 counts before the improvement (scaled Jacobian < 0.2, condition > 3) and after
it (Vonach et al. 2012: MRI meshes of ~300k elements had 3-11 and 8-26 outside), per-tissue volume
against the layered label map's voxels, and the tet-centroid label agreement. Ratios: fTetWild's
tetrahedralize against the default's, and the default's tetrahedralize against its raw mesher.
The refinement is printed as the mean edge of scalp tets near the electrodes and elsewhere.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/mesh.py                  # 2 mm, with fTetWild
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/mesh.py --voxel-mm 1 --no-ftetwild
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/mesh.py --head mni152 --electrodes 32 --no-ftetwild
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/mesh.py --voxel-mm 1 --ftetwild-timeout 480

`--ftetwild-timeout S` runs each fTetWild candidate in a child process and stops it after S seconds
(reported as "did not finish in S s", with the ratios as lower bounds), so one run fits a time slot.

The machine is shared: the load average is printed at the start and the end. Figures:
experiments/results/meshers.md and the README's "Geometry" section.
"""

import argparse
import dataclasses
import json
import os
import sys
import time
import warnings

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from jaxhead.electrodes import ElectrodeConfig, refined_mesh_config  # noqa: E402
from jaxhead.geometry import MeshConfig, tetrahedralize_reported  # noqa: E402
from jaxhead.geometry.layers import make_layers  # noqa: E402
from jaxhead.geometry.quality import quality_report  # noqa: E402
from jaxhead.geometry.surface import SurfaceConfig, extract_surfaces  # noqa: E402
from jaxhead.phantom import make_head  # noqa: E402
from jaxhead.segmentation.templates import mni152_anatomy  # noqa: E402
from jaxhead.tissue import TISSUES, Tissue  # noqa: E402
from jaxhead.volume import voxel_sizes  # noqa: E402

#: fTetWild with faster settings than MeshConfig's (stop energy 30, 20 passes): fewer passes and a
#: looser stop energy; the improvement step guards the quality.
FTETWILD_FAST = {"stop_energy": 100.0, "max_opt_iterations": 3}


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg()) + f" ({os.cpu_count()} cores)"


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


def refinement_edges(mesh, cfg: MeshConfig) -> tuple[float, float]:
    """Mean edge (mm) of the scalp tets whose centroid lies within cfg's refine radius of a refine
    point, and of the other scalp tets: the refinement under the electrodes, as a figure."""
    from scipy.spatial import cKDTree

    scalp = np.asarray(mesh.labels) == int(Tissue.SCALP)
    p = np.asarray(mesh.nodes)[np.asarray(mesh.tets)[scalp]]
    edge = np.mean([np.linalg.norm(p[:, i] - p[:, j], axis=1)
                    for i in range(4) for j in range(i + 1, 4)], axis=0)
    d, _ = cKDTree(np.asarray(cfg.refine_points_mm)).query(p.mean(axis=1))
    near = d <= cfg.refine_radius_mm
    return float(edge[near].mean()), float(edge[~near].mean())


def voxel_volume_errors(mesh, layers) -> dict:
    """Per-tissue relative error of the mesh volume against the layered label map's voxels."""
    vox = float(np.prod(voxel_sizes(np.asarray(layers.affine))))
    lab = np.asarray(layers.labels)
    vols = mesh.tissue_volumes_mm3()
    return {t: vols[t] / (float((lab == int(t)).sum()) * vox) - 1.0 for t in TISSUES}


def _timed_tetrahedralize(surfaces, cfg: MeshConfig):
    """tetrahedralize_reported with its wall and CPU seconds: (mesh, report, wall, cpu)."""
    w0, c0 = time.perf_counter(), time.process_time()
    mesh, rep = tetrahedralize_reported(surfaces, cfg)
    return mesh, rep, time.perf_counter() - w0, time.process_time() - c0


def _in_child(conn, surfaces, cfg):
    conn.send(_timed_tetrahedralize(surfaces, cfg))
    conn.close()


def _tetrahedralize_limited(surfaces, cfg: MeshConfig, limit_s: float):
    """_timed_tetrahedralize in a forked child process, stopped after `limit_s` seconds; None then.

    The child runs NumPy and the mesher only (no JAX), so forking this JAX process is safe; its
    CPU seconds are the child's own."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_in_child, args=(child, surfaces, cfg), daemon=True)
    with warnings.catch_warnings():  # JAX warns on every fork; the child does not use JAX
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")
        proc.start()
    child.close()
    out = parent.recv() if parent.poll(limit_s) else None
    if out is None:
        proc.terminate()
    proc.join()
    return out


def _candidate(name: str, surfaces, cfg: MeshConfig, layers, limit_s: float | None = None) -> dict:
    """Mesh the surfaces with one mesher (and the improvement); its numbers for the table, or
    {"name", "timeout": limit_s} when it did not finish within `limit_s` seconds."""
    if limit_s is None:
        mesh, rep, wall, cpu = _timed_tetrahedralize(surfaces, cfg)
    else:
        out = _tetrahedralize_limited(surfaces, cfg, limit_s)
        if out is None:
            return {"name": name, "timeout": limit_s}
        mesh, rep, wall, cpu = out
    row = quality_report(mesh).table2_row
    imp = rep.improvement
    return {"name": name, "mesher": rep.mesher, "wall": wall, "cpu": cpu,
            "raw": rep.seconds[rep.mesher], "improve": rep.seconds.get("improve", 0.0),
            "mesher_tets": rep.mesher_tets, "tets": mesh.n_tets,
            "sj_before": imp.get("scaled_jacobian_below_0.2_before"),
            "cond_before": imp.get("condition_above_3_before"),
            "after": (row["jacobian"], row["scaled_jacobian"], row["distortion"], row["condition"]),
            "vol_err": voxel_volume_errors(mesh, layers), "agree": centroid_agreement(mesh, layers),
            "report": rep}


def _row_line(r: dict) -> str:
    """One mesher's row of the table (or that it did not finish)."""
    if "timeout" in r:
        return f"  {r['name']:<14s} did not finish in {r['timeout']:.0f} s (stopped)"
    ve = "/".join(f"{100 * r['vol_err'][t]:+.1f}" for t in TISSUES)
    return (f"  {r['name']:<14s} {r['wall']:8.1f} {r['raw']:7.1f} {r['improve']:7.1f} {r['tets']:8d} "
            f"{r['sj_before']!s:>7s} {r['cond_before']!s:>7s} {'/'.join(map(str, r['after'])):>15s} "
            f"{ve:>26s} {100 * r['agree']:5.1f}%")


def build_parser() -> argparse.ArgumentParser:
    """The benchmark's command line; its defaults are the library's (MeshConfig())."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel-mm", type=float, default=2.0, help="phantom voxel size (2 mm; 1 mm for the fine head)")
    ap.add_argument("--head", choices=("phantom", "mni152"), default="phantom",
                    help="phantom (make_head at --voxel-mm) or the MNI152-based head's true labels "
                         "(1 mm, cut at the neck; --voxel-mm and --modality ignored)")
    ap.add_argument("--modality", choices=("mri", "ct"), default="mri")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=MeshConfig().threads,
                    help="gmsh/fTetWild threads (default: the library's MeshConfig().threads = "
                         f"{MeshConfig().threads}, which gives the same mesh on every run; 0: all "
                         "cores, faster but not repeatable)")
    ap.add_argument("--compare", type=str, default="gmsh,tetgen,ftetwild",
                    help="meshers to time on the same surfaces (installed ones only): gmsh, tetgen, "
                         f"ftetwild (MeshConfig's settings), ftetwild-fast ({FTETWILD_FAST})")
    ap.add_argument("--ftetwild-timeout", type=float, default=None,
                    help="stop each fTetWild candidate after this many seconds (run in a child process) "
                         "and report it as not finished; default: no limit")
    ap.add_argument("--no-ftetwild", action="store_true",
                    help="leave fTetWild out of --compare (it takes ~2 min at 2 mm, ~10 min at 1 mm)")
    ap.add_argument("--electrodes", type=str, default="10-20",
                    help='refine under this ElectrodeConfig layout as the pipeline\'s mesh stage does '
                         '("10-20", "10-10", or a count); "none" for no refinement')
    ap.add_argument("--edge-mm", type=str, default=None,
                    help='JSON per-tissue edges, e.g. \'{"brain": 4, "csf": 2, "skull": 2.5, "scalp": 3}\'')
    ap.add_argument("--save", type=str, default=None, help="save the default mesh's nodes/tets/labels to this .npz")
    return ap


def main(argv=None):
    a = build_parser().parse_args(argv)
    print(f"load average at the start: {_load()}, gmsh/fTetWild threads {a.threads}", flush=True)

    t, cpu = {}, {}

    def clock(name, f, *args):
        w0, c0 = time.perf_counter(), time.process_time()
        out = f(*args)
        t[name], cpu[name] = time.perf_counter() - w0, time.process_time() - c0
        return out

    kw = {"threads": a.threads}
    if a.edge_mm:
        kw["edge_mm"] = json.loads(a.edge_mm)
    if a.head == "mni152":
        labels = clock("head labels", lambda: mni152_anatomy().labels())
    else:
        _, labels = clock("head labels", lambda: make_head(a.modality, voxel_mm=a.voxel_mm, seed=a.seed))
    layers = clock("make_layers", make_layers, labels)
    surfaces = clock("extract_surfaces", extract_surfaces, layers, SurfaceConfig())
    print("surface faces: " + ", ".join(f"{t.name} {len(s.faces)}" for t, s in surfaces.items()), flush=True)
    cfg = MeshConfig(**kw)
    if a.electrodes != "none":
        layout = int(a.electrodes) if a.electrodes.isdigit() else a.electrodes
        cfg = clock("refine points", refined_mesh_config, cfg, surfaces[Tissue.SCALP],
                    ElectrodeConfig(layout=layout))
    print(f"refined to {cfg.refine_edge_mm:g} mm within {cfg.refine_radius_mm:g} mm of "
          f"{len(cfg.refine_points_mm)} electrode positions ({a.electrodes})", flush=True)
    mesh, rep = clock("tetrahedralize", tetrahedralize_reported, surfaces, cfg)
    if a.save:
        np.savez(a.save, nodes=mesh.nodes, tets=mesh.tets, labels=mesh.labels)
    q = clock("quality_report", quality_report, mesh)

    print(f"{a.head} {a.modality} {voxel_sizes(np.asarray(labels.affine)).max():g} mm, grid {np.asarray(labels.labels).shape}, seed {a.seed}; "
          f"default mesher: {rep.mesher}")
    print("default path, seconds per stage (wall, CPU of this process incl. mesher threads):")
    for k, v in t.items():
        print(f"  {k:<22s} {v:8.1f} {cpu[k]:8.1f}")
    for k, v in rep.seconds.items():
        print(f"    tetrahedralize/{k:<10s} {v:6.1f}")
    stages = ("make_layers", "extract_surfaces", "refine points", "tetrahedralize", "quality_report")
    pipeline = sum(t.get(k, 0.0) for k in stages)
    print(f"  label map -> Table-2-clean mesh {pipeline:6.1f} s wall (target <= 30 s at 2 mm, <= 60 s at 1 mm; "
          f"seed paper ~1800 s per MRI with manual steps)")
    print(rep)
    row = q.table2_row
    print(f"Table 2 row: {row['elements']} elements; outside: Jacobian {row['jacobian']}, "
          f"scaled Jacobian {row['scaled_jacobian']}, distortion {row['distortion']}, "
          f"condition {row['condition']} (seed MRI rows: 3-11 and 8-26 of ~300k)")
    err = voxel_volume_errors(mesh, layers)
    print("per-tissue volume vs voxel volume of the layered label map: " + ", ".join(
        f"{t.name} {100 * e:+.2f} %" for t, e in err.items()))
    print(agreement_report(mesh, layers, surfaces), flush=True)
    if cfg.refine_points_mm:
        near, far = refinement_edges(mesh, cfg)
        print(f"mean edge of scalp tets within the refine radius of an electrode {near:.2f} mm, "
              f"farther {far:.2f} mm (target {cfg.refine_edge_mm:g} mm near)", flush=True)

    from jaxhead.geometry.tetrahedralize import available_meshers

    have = available_meshers()
    rows = []
    for name in [s.strip() for s in a.compare.split(",") if s.strip()]:
        mesher = "ftetwild" if name.startswith("ftetwild") else name
        if mesher == "ftetwild" and a.no_ftetwild:
            continue
        if mesher not in have:
            print(f"[{name}: not installed, skipped]")
            continue
        ccfg = dataclasses.replace(cfg, mesher=mesher, **(FTETWILD_FAST if name == "ftetwild-fast" else {}))
        print(f"meshing the same surfaces with {name} ...", flush=True)
        limit = a.ftetwild_timeout if mesher == "ftetwild" else None
        rows.append(_candidate(name, surfaces, ccfg, layers, limit))
        print(_row_line(rows[-1]), flush=True)
    print(f"\nmeshers on the same surfaces ({a.head}), load average now {_load()}:")
    print(f"  {'mesher':<14s} {'total s':>8s} {'raw s':>7s} {'impr s':>7s} {'tets':>8s} "
          f"{'SJ<0.2':>7s} {'cond>3':>7s} {'after J/SJ/D/C':>15s} {'vol err % B/C/S/Sc':>26s} {'agree':>6s}")
    for r in rows:
        print(_row_line(r))
    unfinished = [r for r in rows if "timeout" in r]
    rows = [r for r in rows if "timeout" not in r]
    for r in unfinished:
        if r["name"] == "ftetwild":
            print(f"ratios: fTetWild did not finish in {r['timeout']:.0f} s: its tetrahedralize is more "
                  f"than {r['timeout'] / t['tetrahedralize']:.1f}x the default's "
                  f"({t['tetrahedralize']:.1f} s), its label map -> mesh more than "
                  f"{(pipeline - t['tetrahedralize'] + r['timeout']) / pipeline:.1f}x")
    ftw = next((r for r in rows if r["name"] == "ftetwild"), None)
    print("ratios:")
    print(f"  default ({rep.mesher}) tetrahedralize {t['tetrahedralize']:.1f} s / its raw mesher "
          f"{rep.seconds[rep.mesher]:.1f} s = {t['tetrahedralize'] / rep.seconds[rep.mesher]:.1f}x")
    if ftw is not None:
        print(f"  fTetWild tetrahedralize {ftw['wall']:.1f} s / default {t['tetrahedralize']:.1f} s = "
              f"{ftw['wall'] / t['tetrahedralize']:.1f}x faster by default")
        print(f"  fTetWild label map -> mesh {pipeline - t['tetrahedralize'] + ftw['wall']:.1f} s / default "
              f"{pipeline:.1f} s = {(pipeline - t['tetrahedralize'] + ftw['wall']) / pipeline:.1f}x")
    for r in rows:
        if r["name"] != "ftetwild" and ftw is not None:
            print(f"  {r['name']}: {ftw['wall'] / r['wall']:.1f}x faster than fTetWild (raw mesher "
                  f"{ftw['raw'] / max(r['raw'], 1e-9):.0f}x)")
    print(f"load average at the end: {_load()}")


if __name__ == "__main__":
    main()
