"""Conductivity-fit timing: jaxhead (optimistix LM, exact derivatives) vs SciPy with finite differences.

Problem: a four-shell sphere (tests/sphere_mesh.py, h = 12 mm: 48k tets) or any saved head mesh
(`--mesh head.vtu`); 32 electrodes spread over the upper head (10 mm discs); drives (i, i + k)
for k = 1, 4, 8, 16, each measured on every adjacent pair that avoids it (3616 rows);
truth = the literature values x (1.1, 0.9, 1.2, 0.95); 0.5 % Gaussian noise per channel; every
fit starts from the literature values and fits all four conductivities.

Timed in one run:
- jaxhead: `fit_conductivities` with the default `optx.LevenbergMarquardt` and with
  `LineSearchGaussNewton` (first call: includes compilation; fits of other noise seeds reuse
  the compiled solve), steps and forward solves (`FitResult.n_forward`: FEM matrices
  factorised; the derivatives reuse each factor).
- baseline: `scipy.optimize.least_squares(method="lm")` (MINPACK Levenberg-Marquardt, what one
  does without derivatives) on the same weighted residuals in log-parameters, with a 2-point
  finite-difference Jacobian; its forward model is jaxhead's jitted `simulate` (so the ratio
  measures the method: derivatives and step control, not the FEM).
- batch: `fit_conductivities_batch` (one vmapped optimistix solve) vs a loop of fits over
  `--batch` noise realisations.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/fit.py [--h-mm 12] [--mesh head.vtu]
     [--batch 4] [--seeds 3]
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
import scipy.optimize  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from sphere_mesh import structured_sphere_mesh  # noqa: E402

from jaxhead.electrodes import place_electrodes, spread_positions  # noqa: E402
from jaxhead.fem import build_forward_model, simulate  # noqa: E402
from jaxhead.inverse.fit import (LineSearchGaussNewton, fit_conductivities,  # noqa: E402
                         fit_conductivities_batch)
from jaxhead.inverse import add_noise, noise_std  # noqa: E402
from jaxhead.protocol import Protocol, pair_drive  # noqa: E402
from jaxhead.tissue import TISSUE_NAMES, default_sigma  # noqa: E402

TRUE_FACTORS = np.array([1.1, 0.9, 1.2, 0.95])


def skip_protocol(n_elec: int, skips=(1, 4, 8, 16)) -> Protocol:
    """Drives (i, i + k) for every electrode i and skip k, each on all adjacent measurement pairs."""
    return Protocol(np.concatenate([pair_drive(n_elec, i, (i + k) % n_elec).rows
                                    for k in skips for i in range(n_elec)]))


def clock():
    return time.perf_counter(), time.process_time()


def since(t):
    return time.perf_counter() - t[0], time.process_time() - t[1]


def scipy_fit(model, protocol, measured, std, init):
    """MINPACK LM in log-parameters with a 2-point finite-difference Jacobian."""
    n_calls = [0]

    def residuals(logx):
        n_calls[0] += 1
        return (np.asarray(simulate(model, np.exp(logx), protocol)) - measured) / std

    sol = scipy.optimize.least_squares(residuals, np.log(init), method="lm", xtol=1e-8,
                                       ftol=1e-10)
    return np.exp(sol.x), n_calls[0], sol


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h-mm", type=float, default=12.0, help="sphere grid spacing (12 mm: 48k tets)")
    ap.add_argument("--mesh", type=str, default=None, help="a saved head mesh (.vtu/.msh) instead")
    ap.add_argument("--n-elec", type=int, default=32)
    ap.add_argument("--seeds", type=int, default=3, help="noise realisations fitted one by one")
    ap.add_argument("--batch", type=int, default=4, help="realisations in the vmapped batch (0: skip)")
    ap.add_argument("--no-scipy", action="store_true", help="skip the finite-difference baseline")
    args = ap.parse_args()
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f} (shared machine: compare CPU and wall)")

    if args.mesh:
        from jaxhead.io import load_mesh

        mesh = load_mesh(args.mesh)
        name = Path(args.mesh).name
    else:
        mesh = structured_sphere_mesh(h_mm=args.h_mm)
        name = f"sphere h={args.h_mm:g} mm"
    t = clock()
    electrodes = place_electrodes(mesh, spread_positions(mesh, args.n_elec), radius_mm=10.0)
    model = build_forward_model(mesh, electrodes)
    protocol = skip_protocol(args.n_elec)
    print(f"mesh {name}: {mesh.n_nodes} nodes, {mesh.n_tets} tets; {args.n_elec} electrodes, "
          f"{protocol.n_rows} rows; set-up {since(t)[0]:.1f} s")
    init = default_sigma()
    truth = init * TRUE_FACTORS
    v_true = np.asarray(simulate(model, truth, protocol))
    t = clock()
    np.asarray(simulate(model, truth * 1.01, protocol))
    t_fwd = since(t)
    print(f"one forward solve (compiled): wall {t_fwd[0]:.2f} s, CPU {t_fwd[1]:.2f} s")

    solvers = {"LM": None, "GN-line-search": LineSearchGaussNewton(rtol=1e-6, atol=1e-6)}
    summary = {}
    for sname, solver in solvers.items():
        rows = []
        for seed in range(args.seeds):
            measured = add_noise(v_true, 0.5, seed=seed)
            std = noise_std(measured, 0.5)
            t = clock()
            res = fit_conductivities(model, protocol, measured, init=init, noise_std=std,
                                     solver=solver)
            wall, cpu = since(t)
            rel = 100 * (res.sigma / truth - 1)
            rows.append((seed, wall, cpu, res.n_steps, res.n_forward, rel,
                         100 * res.std_error / truth))
            tag = "first (compiles)" if seed == 0 else "compiled"
            print(f"jaxhead {sname} seed {seed} [{tag}]: wall {wall:.1f} s, CPU {cpu:.1f} s, "
                  f"{res.n_steps} steps, {res.n_forward} forward solves; error % "
                  + " ".join(f"{n} {e:+.2f}" for n, e in zip(TISSUE_NAMES, rel))
                  + "; std error % " + " ".join(f"{x:.2f}" for x in rows[-1][6]))
        warm = rows[1:] or rows
        summary[sname] = (float(np.median([r[1] for r in warm])),
                          float(np.median([r[4] for r in warm])), rows[0][5])
    print(res.table(truth))

    if not args.no_scipy:
        measured = add_noise(v_true, 0.5, seed=0)
        std = noise_std(measured, 0.5)
        t = clock()
        sig, n_calls, sol = scipy_fit(model, protocol, measured, std, init)
        wall, cpu = since(t)
        diff = 100 * (sig / truth - 1)
        print(f"scipy LM + finite differences, seed 0: wall {wall:.1f} s, CPU {cpu:.1f} s, "
              f"{n_calls} forward solves, status {sol.status}; error % "
              + " ".join(f"{n} {e:+.2f}" for n, e in zip(TISSUE_NAMES, diff)))
        for sname, (jx_wall, jx_fwd, rel0) in summary.items():
            print(f"ratio scipy-FD / jaxhead {sname} (compiled fits, median): time "
                  f"{wall / jx_wall:.2f}x, forward solves {n_calls / jx_fwd:.2f}x "
                  f"(its seed-0 error % " + " ".join(f"{e:+.2f}" for e in rel0) + ")")

    if args.batch > 0:
        data = np.stack([add_noise(v_true, 0.5, seed=100 + s) for s in range(args.batch)])
        std = noise_std(v_true, 0.5)
        fit_conductivities_batch(model, protocol, data[:1], init=init, noise_std=std)  # compile
        t = clock()
        batch = fit_conductivities_batch(model, protocol, data, init=init, noise_std=std)
        b_wall, b_cpu = since(t)
        t = clock()
        loop = [fit_conductivities(model, protocol, m, init=init, noise_std=std) for m in data]
        l_wall, l_cpu = since(t)
        dmax = max(float(np.max(np.abs(b.sigma / lp.sigma - 1))) for b, lp in zip(batch, loop))
        print(f"batch of {args.batch} (compiled): vmapped wall {b_wall:.1f} s (CPU {b_cpu:.1f}), "
              f"{batch[0].n_forward} forward solves per fit; loop wall {l_wall:.1f} s "
              f"(CPU {l_cpu:.1f}), {np.mean([r.n_forward for r in loop]):.0f} per fit; "
              f"loop / vmap = {l_wall / b_wall:.2f}x; max relative difference {dmax:.1e}")


if __name__ == "__main__":
    main()
