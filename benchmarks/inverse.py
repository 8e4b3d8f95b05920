"""Difference-imaging timing: Jacobian, SVD and reconstruction on tets and on a grid, vs NumPy/LAPACK.

Mesh: the structured four-shell ball of tests/sphere_mesh.py at h = 5 mm (59k nodes, 329k tets,
the seed paper's 220k-380k elements), or a saved head mesh (`--mesh head.vtu`). 32 electrodes
spread over the upper head, 31 adjacent injections each measured on every adjacent pair that
avoids the drive (899 rows, as benchmarks/forward.py). Data: a 2 cm, +20 % ball in the brain,
0.5 % noise per channel (timing only: same mesh, so an inverse crime; see
tests/test_inverse_recovery.py for the honest accuracy test).

Timed in one run (wall and CPU; the machine is shared):
1. `jacobian` (899 x n_tets, float32 storage, float64 solves).
2. grid: `make_grid` (brain cells of `--cell-mm`) + `jacobian_to_grid` (baseline: the per-tet
   matrix, then its columns summed) vs `jacobian_grid` (tiles summed straight into cells).
3. SVD of the grid matrix (whitened by the noise level, half-NOSER column scaling, exponent
   0.5, as the pipeline's inverse stage): jaxhead `svd` (Gram route) vs `numpy.linalg.svd` (LAPACK
   gesdd) on the same matrix, and one TSVD/GCV reconstruction vs NumPy's truncated
   pseudo-inverse with the same k.
4. 200 noise realisations: `reconstruct_batch` (vmap, each with its own GCV choice) vs a loop
   of `reconstruct` vs a NumPy loop with a fixed k.
5. tets: the same on the brain tets' columns (jaxhead Gram SVD; LAPACK only with
   `--lapack-tets`, it takes minutes), and the localisation error on tets vs grid.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/inverse.py [--h-mm 5] [--cell-mm 8]
     [--mesh head.vtu] [--lapack-tets]
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from sphere_mesh import structured_sphere_mesh  # noqa: E402

from jaxhead.electrodes import place_electrodes, spread_positions  # noqa: E402
from jaxhead.fem import build_forward_model, jacobian, simulate  # noqa: E402
from jaxhead.inverse import (TSVD, add_noise, image_metrics, jacobian_grid,  # noqa: E402
                             jacobian_to_grid, make_grid, noise_std, reconstruct, reconstruct_batch,
                             spherical_perturbation, svd)
from jaxhead.protocol import Protocol, adjacent  # noqa: E402
from jaxhead.tissue import default_sigma  # noqa: E402


def timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t, time.process_time() - c


def line(what, wall, cpu):
    print(f"  {what:<58} wall {wall:7.2f} s  CPU {cpu:7.2f} s", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h-mm", type=float, default=5.0, help="sphere grid spacing (5 mm: 329k tets)")
    ap.add_argument("--mesh", type=str, default=None, help="a saved head mesh instead")
    ap.add_argument("--cell-mm", type=float, default=8.0, help="grid cell edge in mm")
    ap.add_argument("--batch", type=int, default=200, help="noise realisations for the batch")
    ap.add_argument("--lapack-tets", action="store_true", help="also LAPACK SVD on the tets")
    args = ap.parse_args()
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f} (shared machine: compare CPU and wall)")
    if args.mesh:
        from jaxhead.io import load_mesh

        mesh = load_mesh(args.mesh)
    else:
        mesh = structured_sphere_mesh(h_mm=args.h_mm)
    sigma = default_sigma()
    model = build_forward_model(mesh, place_electrodes(mesh, spread_positions(mesh, 32),
                                                       radius_mm=10.0))
    full = adjacent(32)
    protocol = Protocol(full.rows[full.rows[:, 0] < 31], full.current_a)
    print(f"mesh: {mesh.n_nodes} nodes, {mesh.n_tets} tets; {protocol.n_rows} rows")

    # A 2 cm ball, +20 %, in the brain, 30 mm from the brain's centroid towards the top.
    brain = mesh.labels == 1
    cen, vol = mesh.centroids()[brain], mesh.tet_volumes()[brain]
    centre = (cen * vol[:, None]).sum(0) / vol.sum() + np.array([0.0, 0.0, 30.0])
    s_tet = sigma[mesh.labels - 1]
    pert = spherical_perturbation(mesh, s_tet, centre, 20.0, 0.2, tissue="brain")
    v0 = np.asarray(simulate(model, sigma, protocol))
    dv = add_noise(np.asarray(simulate(model, pert, protocol)) - v0, 0.5, seed=0, reference=v0)
    std = noise_std(v0, 0.5, floor=0.03)
    method = TSVD(noise_weighted=True, normalise=0.5)

    print("1. Jacobian")
    jacobian(model, sigma * 1.01, protocol, dtype=np.float32)  # compile
    J, w_J, c_J = timed(lambda: jacobian(model, sigma, protocol, dtype=np.float32))
    line(f"jacobian {J.shape} float32 ({J.nbytes / 1e9:.2f} GB)", w_J, c_J)

    print(f"2. grid of {args.cell_mm:g} mm brain cells")
    grid, w, c = timed(lambda: make_grid(mesh, args.cell_mm, tissues=["brain"]))
    line(f"make_grid: {grid.n_cells} cells", w, c)
    Jg, w_g, c_g = timed(lambda: jacobian_to_grid(J, grid))
    line(f"jacobian_to_grid -> {Jg.shape}", w_g, c_g)
    jacobian_grid(model, sigma * 1.01, protocol, grid)  # compile
    Jg2, w, c = timed(lambda: jacobian_grid(model, sigma, protocol, grid))
    line("jacobian_grid (tiles summed into cells, no per-tet matrix)", w, c)
    print(f"  ratio (jacobian + jacobian_to_grid) / jacobian_grid: wall "
          f"{(w_J + w_g) / w:.1f}x, CPU {(c_J + c_g) / c:.1f}x; peak result "
          f"{J.nbytes / 1e9:.2f} GB vs {Jg2.nbytes / 1e6:.1f} MB; max rel. difference "
          f"{np.abs(Jg2 - Jg).max() / np.abs(Jg2).max():.1e} (float32 storage of J)")
    Jg = Jg2

    print("3. SVD + TSVD (GCV) on the grid matrix, whitened and column-scaled (NOSER exponent 0.5)")
    A = Jg / std[:, None]
    svd(A[:, :50], normalise=0.5)  # warm up
    dec, w_j, c_j = timed(lambda: svd(A, normalise=0.5))
    line("jaxhead svd (Gram route)", w_j, c_j)
    An = A / dec.scale
    (u, s, vt), w_n, c_n = timed(lambda: np.linalg.svd(An, full_matrices=False))
    line("numpy.linalg.svd (LAPACK gesdd), same matrix", w_n, c_n)
    print(f"  ratio numpy / jaxhead SVD: wall {w_n / w_j:.2f}x, CPU {c_n / c_j:.2f}x; "
          f"max rel. diff of the top-100 singular values "
          f"{np.max(np.abs(np.asarray(dec.s[:100]) / s[:100] - 1)):.1e}")
    reconstruct(None, dv, method, noise_std=std, decomposition=dec)  # compile
    rec, w_r, c_r = timed(lambda: reconstruct(None, dv, method, noise_std=std,
                                              decomposition=dec))
    k = int(rec.k)
    line(f"jaxhead reconstruct (GCV over all k: chose k={k})", w_r, c_r)
    x_np, w_rn, c_rn = timed(lambda: (vt[:k].T @ ((u[:, :k].T @ (dv / std)) / s[:k]))
                             / dec.scale)
    line("numpy truncated pseudo-inverse, same k", w_rn, c_rn)
    print(f"  image max rel. difference "
          f"{np.abs(np.asarray(rec.image) - x_np).max() / np.abs(x_np).max():.1e}")
    m_grid = image_metrics(np.asarray(rec.image), grid.centres, grid.volumes, centre, 20.0)
    print(f"  total jaxhead grid (Jacobian + grid + SVD + reconstruct): "
          f"wall {w + w_j + w_r:.1f} s; localisation error {m_grid.localisation_error_mm:.1f} mm")

    print(f"4. {args.batch} noise realisations on the grid")
    clean = np.asarray(simulate(model, pert, protocol)) - v0
    data = np.stack([add_noise(clean, 0.5, seed=i, reference=v0) for i in range(args.batch)])
    reconstruct_batch(None, data + 0.0, method, noise_std=std, decomposition=dec)  # compile
    rb, w_b, c_b = timed(lambda: reconstruct_batch(None, data, method, noise_std=std,
                                                   decomposition=dec))
    line("reconstruct_batch (vmap, own GCV k each)", w_b, c_b)
    _, w_l, c_l = timed(lambda: [reconstruct(None, d, method, noise_std=std,
                                             decomposition=dec).image for d in data])
    line("loop of reconstruct", w_l, c_l)
    _, w_nl, c_nl = timed(lambda: [(vt[:k].T @ ((u[:, :k].T @ (d / std)) / s[:k])) / dec.scale
                                   for d in data])
    line("numpy loop, fixed k (no parameter choice)", w_nl, c_nl)
    errs = [image_metrics(np.asarray(x), grid.centres, grid.volumes, centre,
                          20.0).localisation_error_mm for x in np.asarray(rb.image)]
    print(f"  ratio loop / batch: wall {w_l / w_b:.1f}x; numpy fixed-k loop / batch: "
          f"wall {w_nl / w_b:.2f}x; k chosen: median {np.median(np.asarray(rb.k)):.0f}, "
          f"range {np.min(np.asarray(rb.k)):.0f}-{np.max(np.asarray(rb.k)):.0f}; localisation "
          f"error median {np.median(errs):.1f} mm, 90th percentile {np.percentile(errs, 90):.1f}")

    print("5. the same on the brain tets (no grid)")
    Jb = np.asarray(J[:, brain], dtype=np.float64) / std[:, None]
    del J
    dec_t, w_t, c_t = timed(lambda: svd(Jb, normalise=0.5))
    line(f"jaxhead svd (Gram route) of {Jb.shape}", w_t, c_t)
    rec_t, w_rt, c_rt = timed(lambda: reconstruct(None, dv, method, noise_std=std,
                                                  decomposition=dec_t))
    line(f"jaxhead reconstruct (GCV: k={rec_t.k:.0f})", w_rt, c_rt)
    m_tet = image_metrics(np.asarray(rec_t.image), cen, vol, centre, 20.0)
    print(f"  ratio tets / grid (SVD + reconstruct): wall {(w_t + w_rt) / (w_j + w_r):.1f}x; "
          f"localisation error tets {m_tet.localisation_error_mm:.1f} mm vs grid "
          f"{m_grid.localisation_error_mm:.1f} mm")
    if args.lapack_tets:
        _, w_tn, c_tn = timed(lambda: np.linalg.svd(Jb / dec_t.scale, full_matrices=False))
        line("numpy.linalg.svd on the tets", w_tn, c_tn)
        print(f"  ratio numpy / jaxhead on tets: wall {w_tn / w_t:.2f}x, CPU {c_tn / c_t:.2f}x")


if __name__ == "__main__":
    main()
