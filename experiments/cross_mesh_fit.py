"""Fit the four conductivities on one mesh to data simulated on a finer mesh of the same head.

Uses the meshes of experiments/mesh_convergence.py (run it first): data from the 1.33M-tet
reference C, 0.5 % noise, fitted on the electrode-refined mesh B with the Gauss-Newton line search,
for noise weights with a floor of 3 % and 10 % of the RMS voltage (without a floor, channels with a
near-zero standing voltage let the meshes' modelling error dominate and the fit diverges).

Usage: python experiments/cross_mesh_fit.py [MESH_DIR]   (default runs/mesh_convergence)
"""
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax; jax.config.update("jax_enable_x64", True)
import numpy as np
from jaxhead.io import load_mesh
from jaxhead.electrodes import place_electrodes, spread_positions
from jaxhead.fem import build_forward_model, simulate, Direct
from jaxhead.fit import fit_conductivities, LineSearchGaussNewton
from jaxhead.inverse import add_noise, noise_std
from jaxhead.protocol import Protocol, pair_drive
from jaxhead.tissue import default_sigma
D = sys.argv[1] if len(sys.argv) > 1 else "runs/mesh_convergence"
M = {k: load_mesh(f"{D}/{k}.vtu") for k in ("A_default", "B_refined", "C_fine_refined")}
pos = spread_positions(M["A_default"], 32)
rows = np.concatenate([pair_drive(32, i, (i + k) % 32).rows for k in (1, 4, 8, 16) for i in range(32)])
prot = Protocol(rows)
S = default_sigma(); TRUE = S * np.array([1.1, 0.9, 1.2, 0.95])
mods = {k: build_forward_model(m, place_electrodes(m, pos, radius_mm=6.0), solver=Direct(threads=2)) for k, m in M.items()}
v = np.asarray(simulate(mods["C_fine_refined"], TRUE, prot))
for k in ("B_refined",):
    vk = np.asarray(simulate(mods[k], TRUE, prot))
    print(k, "mismatch at TRUE %.4f" % (np.linalg.norm(v - vk) / np.linalg.norm(v)), flush=True)
    for seed, fl in ((0, 0.03), (0, 0.1), (1, 0.1)):
        t = time.perf_counter()
        res = fit_conductivities(mods[k], prot, add_noise(v, 0.5, seed=seed), init=S, noise_std=noise_std(v, 0.5, floor=fl),
                                 solver=LineSearchGaussNewton(rtol=1e-6, atol=1e-6), throw=False)
        err = res.sigma / TRUE - 1
        print(f"  seed {seed} floor {fl}: rel errors brain {err[0]:+.4f} csf {err[1]:+.4f} skull {err[2]:+.4f} scalp {err[3]:+.4f}; success {bool(res.success)}, steps {int(res.n_steps)}, {time.perf_counter()-t:.0f} s", flush=True)
