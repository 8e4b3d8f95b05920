"""Fit the four conductivities on one mesh to data simulated on other, finer meshes of the head.

Uses the meshes of experiments/mesh_convergence.py (run it first) and adds D, an independent
reference: the same phantom's surfaces extracted at finer edges (4/2.5/3/4 mm) and meshed like C,
so D differs from the fit mesh in surface geometry as well as in volume discretisation. Data:
V(TRUE) on C or on D plus 0.5 % Gaussian noise per channel (three seeds). Fits on the
electrode-refined mesh B with the Gauss-Newton line search:
  plain      noise weights floored at 10 % of the RMS voltage (without a floor the fit diverges:
             channels with a near-zero standing voltage let the modelling error dominate);
  AEM(C->B)  the approximation-error model (jaxhead.approximation_error) of B against C from 24
             conductivity draws (log-normal, log-sd 0.25 around the literature values), with the
             pure per-channel noise weights.
With data from D the approximation-error model is estimated on a mesh that did not make the data;
there AEM(F->B) also uses F, surfaces at still finer edges (3/2/2.5/3 mm) meshed like C.
Last, two truths far from the prior's centre, data from C, fitted with AEM(C->B).

Usage: python experiments/cross_mesh_fit.py [MESH_DIR]   (default runs/mesh_convergence; ~40 min,
+ ~40 min the first time to mesh D and F)
"""
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax; jax.config.update("jax_enable_x64", True)
import numpy as np
from jaxhead.inverse.approx_error import approximation_error, sample_conductivities
from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import Direct, build_forward_model, simulate
from jaxhead.inverse.fit import LineSearchGaussNewton, fit_conductivities
from jaxhead.inverse import add_noise, noise_std
from jaxhead.io import load_mesh, save_mesh
from jaxhead.geometry import MeshConfig, tetrahedralize
from jaxhead.phantom import make_head
from jaxhead.protocol import Protocol, pair_drive
from jaxhead.geometry.layers import make_layers
from jaxhead.geometry.surface import SurfaceConfig, extract_surfaces
from jaxhead.tissue import default_sigma

D = sys.argv[1] if len(sys.argv) > 1 else "runs/mesh_convergence"
M = {k: load_mesh(f"{D}/{k}.vtu") for k in ("A_default", "B_refined", "C_fine_refined")}
pos = spread_positions(M["A_default"], 32)  # as experiments/mesh_convergence.py
for name, surf_mm in (("D_independent", (4.0, 2.5, 3.0, 4.0)),
                      ("F_finer_surfaces", (3.0, 2.0, 2.5, 3.0))):
    path = f"{D}/{name}.vtu"
    if not os.path.exists(path):
        t = time.perf_counter()
        _, labels = make_head("mri", voxel_mm=2.0, seed=0)
        surfs = extract_surfaces(make_layers(labels), SurfaceConfig(
            edge_mm=dict(zip(("brain", "csf", "skull", "scalp"), surf_mm))))
        save_mesh(tetrahedralize(surfs, MeshConfig(
            edge_mm={"brain": 6.0, "csf": 2.5, "skull": 2.5, "scalp": 3.0},
            refine_points_mm=tuple(map(tuple, pos)), refine_edge_mm=1.5,
            refine_radius_mm=8.0)), path)
        print(f"meshed {name} in {time.perf_counter() - t:.0f} s", flush=True)
    M[name] = load_mesh(path)
print({k: m.n_tets for k, m in M.items()}, flush=True)

rows = np.concatenate([pair_drive(32, i, (i + k) % 32).rows
                       for k in (1, 4, 8, 16) for i in range(32)])
prot = Protocol(rows)
S = default_sigma()
TRUE = S * np.array([1.1, 0.9, 1.2, 0.95])
mods = {k: build_forward_model(M[k], place_electrodes(M[k], pos, radius_mm=6.0),
                               solver=Direct(threads=2))
        for k in ("B_refined", "C_fine_refined", "D_independent", "F_finer_surfaces")}
t = time.perf_counter()
ae = approximation_error(mods["C_fine_refined"], mods["B_refined"],
                         sample_conductivities(24, seed=12345), prot)
print(f"approximation error of B against C: 24 draws in {time.perf_counter() - t:.0f} s", flush=True)
ae_F = approximation_error(mods["F_finer_surfaces"], mods["B_refined"],
                           sample_conductivities(24, seed=12345), prot)
solver = LineSearchGaussNewton(rtol=1e-6, atol=1e-6)


def _report(label, res, truth, t):
    err = 100 * (res.sigma / truth - 1)
    se = 100 * res.std_error / res.estimates
    print(f"  {label} error % brain {err[0]:+6.2f} csf {err[1]:+6.2f} skull {err[2]:+6.2f} "
          f"scalp {err[3]:+6.2f} | SE % {se[0]:.2f} {se[1]:.2f} {se[2]:.2f} {se[3]:.2f} | "
          f"success {bool(res.success)}, {res.n_steps} steps, {time.perf_counter() - t:.0f} s",
          flush=True)


vB = np.asarray(simulate(mods["B_refined"], TRUE, prot))
for data in ("C_fine_refined", "D_independent"):
    v = np.asarray(simulate(mods[data], TRUE, prot))
    mis = np.linalg.norm(v - vB) / np.linalg.norm(v)
    mis_ae = np.linalg.norm(v - vB - ae.mean) / np.linalg.norm(v)
    print(f"data {data}: mismatch to B at TRUE {mis:.4f}, after the AEM mean {mis_ae:.4f}", flush=True)
    for seed in (0, 1, 2):
        measured = add_noise(v, 0.5, seed=seed)
        variants = [("plain", dict(noise_std=noise_std(v, 0.5, floor=0.1))),
                    ("AEM(C->B)", dict(noise_std=noise_std(v, 0.5), approx_error=ae))]
        if data == "D_independent":
            variants.append(("AEM(F->B)", dict(noise_std=noise_std(v, 0.5), approx_error=ae_F)))
        for name, kw in variants:
            t = time.perf_counter()
            res = fit_conductivities(mods["B_refined"], prot, measured, init=S, solver=solver,
                                     throw=False, **kw)
            _report(f"seed {seed} {name:10s}", res, TRUE, t)
# Truths far from the prior's centre (the skull at x0.5 is 2.8 prior standard deviations out).
for factors in ([1.3, 0.7, 0.5, 1.2], [0.7, 1.3, 2.0, 0.8]):
    truth = S * np.array(factors)
    v = np.asarray(simulate(mods["C_fine_refined"], truth, prot))
    for seed in (0, 1):
        t = time.perf_counter()
        res = fit_conductivities(mods["B_refined"], prot, add_noise(v, 0.5, seed=seed), init=S,
                                 solver=solver, throw=False, noise_std=noise_std(v, 0.5),
                                 approx_error=ae)
        _report(f"data C, truth x{factors}, seed {seed}, AEM(C->B)", res, truth, t)
