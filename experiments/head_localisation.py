"""How well TSVD and Tikhonov localise a brain perturbation on the phantom head, against noise.

Meshes of experiments/mesh_convergence.py (run it first): data simulated on the 1.33M-tet
reference C, reconstruction on the electrode-refined 303k-tet mesh B, on a 10 mm grid over the
brain (jaxhead.inverse.make_grid / jacobian_grid). 32 electrodes, drives (i, i + k), k = 1, 4, 8,
16, each measured on every adjacent pair that avoids it (3616 rows). A ball of radius 20, 15 or
10 mm with +20 % conductivity at five places in the brain; Gaussian noise of 0, 0.05, 0.1, 0.2 and
0.5 % of each channel's standing voltage (three seeds). Reconstruction as
tests/test_inverse_head.py: noise-weighted (floor 3 % of the RMS), half-NOSER column scaling,
truncation / lambda by GCV. Prints the mean localisation error (centroid of the half-maximum
region vs the true centre; "-" where the image has no positive part) per place, the number of
kept components, and the signal-to-noise ratio ||dv|| / ||noise std||, against issue 5's bar of
10 % of the head's left-right width. Saves the arrays to MESH_DIR/localisation.npz.

Usage: python experiments/head_localisation.py [MESH_DIR]   (default runs/mesh_convergence; ~15 min)
"""
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax; jax.config.update("jax_enable_x64", True)
import numpy as np
from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import Direct, build_forward_model, simulate
from jaxhead.inverse import (TSVD, Tikhonov, add_noise, image_metrics, jacobian_grid, make_grid,
                             noise_std, reconstruct, spherical_perturbation, svd)
from jaxhead.io import load_mesh
from jaxhead.protocol import Protocol, pair_drive
from jaxhead.tissue import default_sigma

D = sys.argv[1] if len(sys.argv) > 1 else "runs/mesh_convergence"
data, recon = load_mesh(f"{D}/C_fine_refined.vtu"), load_mesh(f"{D}/B_refined.vtu")
pos = spread_positions(load_mesh(f"{D}/A_default.vtu"), 32)  # as mesh_convergence.py
prot = Protocol(np.concatenate([pair_drive(32, i, (i + k) % 32).rows
                                for k in (1, 4, 8, 16) for i in range(32)]))
S = default_sigma()
t = time.perf_counter()
fm = build_forward_model(data, place_electrodes(data, pos, radius_mm=6.0), solver=Direct(threads=2))
cm = build_forward_model(recon, place_electrodes(recon, pos, radius_mm=6.0), solver=Direct(threads=2))
grid = make_grid(recon, 10.0, tissues=["brain"])
Jg = np.asarray(jacobian_grid(cm, S, prot, grid))
v0 = np.asarray(simulate(fm, S, prot))
std = noise_std(v0, 0.5, floor=0.03)
dec = svd(Jg / std[:, None], normalise=0.5)
print(f"models, {grid.n_cells}-cell Jacobian and SVD: {time.perf_counter() - t:.0f} s", flush=True)
ext = data.nodes.max(0) - data.nodes.min(0)
bar = 0.1 * min(ext[0], ext[1])
b = data.labels == 1
cen, vol = data.centroids()[b], data.tet_volumes()[b]
mid = (cen * vol[:, None]).sum(0) / vol.sum()
places = {"central": (0, 0, 0), "superior": (0, 0, 0.4 * (cen[:, 2].max() - mid[2])),
          "left": (-35, 0, 15), "posterior": (0, -40, 15), "anterior": (0, 40, 15)}
s_data = S[data.labels - 1]
print(f"bar: 10 % of the head's left-right width = {bar:.1f} mm", flush=True)
saved = {}
for radius in (20.0, 15.0, 10.0):
    D_ = {}
    for name, off in places.items():
        c = mid + np.asarray(off, float)
        D_[name] = (c, np.asarray(simulate(fm, spherical_perturbation(
            data, s_data, c, radius, 0.2, tissue="brain"), prot)) - v0)
        saved[f"dv_r{radius:.0f}_{name}"], saved[f"centre_{name}"] = D_[name][1], c
    np.savez(f"{D}/localisation.npz", Jg=Jg, v0=v0, cell_centres=grid.centres,
             cell_volumes=grid.volumes, **saved)
    for pct in (0.0, 0.05, 0.1, 0.2, 0.5):
        std_pct = std * max(pct, 1e-3) / 0.5  # weights of the same shape at each level
        for method in (TSVD(noise_weighted=True, normalise=0.5),
                       Tikhonov(noise_weighted=True, normalise=0.5)):
            row, snr = [], []
            for name, (c, dv) in D_.items():
                errs, ks = [], []
                for seed in (range(3) if pct > 0 else [0]):
                    y = add_noise(dv, pct, seed=seed, reference=v0) if pct > 0 else dv
                    rec = reconstruct(None, y, method, noise_std=std_pct, decomposition=dec)
                    try:
                        m = image_metrics(np.asarray(rec.image), grid.centres, grid.volumes, c,
                                          radius, sign=1)
                        errs.append(m.localisation_error_mm)
                    except ValueError:  # no positive value: the sign is lost
                        errs.append(np.nan)
                    ks.append(rec.k)
                e = np.nanmean(errs) if not np.all(np.isnan(errs)) else np.nan
                row.append(f"{name[:4]} {e:4.0f}{'' if np.all(np.isfinite(errs)) else '-'} "
                           f"(k {np.mean(ks):4.1f})")
                if pct > 0:
                    snr.append(np.linalg.norm(dv) / np.linalg.norm(noise_std(v0, pct)))
            extra = f" | SNR {min(snr):.2f}-{max(snr):.2f}" if snr else ""
            print(f"r {radius:.0f} mm, noise {pct:4.2f} %, {type(method).__name__:8s}: "
                  + " | ".join(row) + extra, flush=True)
