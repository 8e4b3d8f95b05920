"""Forward model timing: build, forward, forward + Jacobian, gradient, vs SciPy spsolve.

Mesh: the structured four-shell ball of tests/sphere_mesh.py (a Kuhn tetrahedralisation of a
cube grid mapped onto the ball; radii 80/84/90/96 mm: brain, CSF, skull, scalp), h = 5 mm:
59,319 nodes and 329,232 tets, the size of the seed paper's head meshes (220k-380k elements).
32 electrodes spread over the upper head (10 mm radius discs), 31 injections (adjacent pairs
(i, i+1), i = 0..30) each measured on every adjacent pair that avoids the drive: 899 rows.

Timed (median of `--repeats`, each with a new conductivity so that nothing is cached):
- build: `build_forward_model` (pattern, scatter plan, PARDISO symbolic analysis).
- forward: jitted `simulate` (assembly, numeric factorisation, 31 solves).
- forward + Jacobian: `jacobian(..., return_volts=True)` (one factorisation, 31 solves, the
  (899, 329k) sensitivity matrix by reciprocity), float32 storage.
- gradient: value and gradient of a least-squares loss w.r.t. the 4 conductivities and all
  node positions (reverse mode: one forward and one adjoint solve batch, same factor).
- SciPy baseline: `scipy.sparse.linalg.spsolve` of the same matrix with the same 31
  right-hand sides, OPENBLAS_NUM_THREADS=1 (REFERENCES: OpenBLAS threads on 2 cores slow SciPy).

With `--gpu` the model's solver is BlockCG with the smoothed-aggregation preconditioner (pure JAX,
rtol 1e-10) and JAX runs on the default accelerator; the SciPy baseline still runs on the host CPU.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/forward.py [--h-mm 5] [--cg] [--gpu]
"""

import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
if "--gpu" not in sys.argv:
    os.environ.setdefault("JAX_PLATFORMS", "cpu")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from sphere_mesh import RADII_MM, structured_sphere_mesh  # noqa: E402

from jaxhead.electrodes import place_electrodes  # noqa: E402
from jaxhead.fem import (BlockCG, Direct, Jacobi, SmoothedAggregation, assemble,  # noqa: E402
                         build_forward_model, jacobian, simulate)
from jaxhead.fem.cem import electrode_rhs  # noqa: E402
from jaxhead.fem.forward import _basis_currents  # noqa: E402
from jaxhead.io import load_mesh  # noqa: E402
from jaxhead.protocol import Protocol, adjacent  # noqa: E402
from jaxhead.tissue import default_sigma  # noqa: E402


def timed(fn, repeats):
    """Median wall time and CPU time of fn(i) over `repeats` calls (i = 1..repeats)."""
    walls, cpus = [], []
    for i in range(1, repeats + 1):
        t, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(i))
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h-mm", type=float, default=5.0, help="grid spacing (5 mm: 59k nodes)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="PARDISO threads (default MKL's)")
    ap.add_argument("--cg", action="store_true", help="also time BlockCG (Jacobi, SA-AMG)")
    ap.add_argument("--no-scipy", action="store_true", help="skip the slow SciPy baseline")
    ap.add_argument("--mesh", default=None,
                    help="time a mesh file instead of the ball (e.g. runs/demo/mri/mesh/mesh.vtu); "
                         "32 electrodes spread over its upper head")
    ap.add_argument("--gpu", action="store_true",
                    help="run JAX on the accelerator with BlockCG + smoothed aggregation")
    args = ap.parse_args()
    R = RADII_MM[-1]
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f} (shared machine: compare CPU and wall)")

    if args.mesh:
        mesh = load_mesh(args.mesh)
        elec = place_electrodes(mesh, 32, radius_mm=6.0)
        what_mesh = f"{args.mesh}"
    else:
        mesh = structured_sphere_mesh(RADII_MM, h_mm=args.h_mm)
        landmarks = {"nasion": [0, R, 0], "inion": [0, -R, 0], "lpa": [-R, 0, 0], "rpa": [R, 0, 0]}
        elec = place_electrodes(mesh, 32, landmarks=landmarks, radius_mm=10.0)
        what_mesh = f"structured 4-shell ball, h={args.h_mm} mm"
    full = adjacent(32, current_a=1e-3)
    protocol = Protocol(full.rows[full.rows[:, 0] < 31], 1e-3)  # 31 injections
    n_inj = len({tuple(r) for r in protocol.rows[:, :2].tolist()})
    print(f"mesh: {mesh.n_nodes} nodes, {mesh.n_tets} tets ({what_mesh}); "
          f"{elec.n_elec} electrodes, {n_inj} injections, "
          f"{protocol.n_rows} rows")

    sigma0 = jnp.asarray(default_sigma())

    def sigma(i):  # a new conductivity per call: no factor is reused between timings
        return sigma0 * (1.0 + 0.01 * i)

    t = time.perf_counter()
    if args.gpu:
        model = build_forward_model(mesh, elec, solver=BlockCG(SmoothedAggregation(), rtol=1e-10))
        what = "BlockCG + smoothed aggregation, rtol 1e-10, multigrid set-up on the host"
    else:
        model = build_forward_model(mesh, elec, solver=Direct(threads=args.threads))
        backend = model.solver_state.handle.backend
        what = f"backend {backend.name}, factor nnz {backend.factor_nnz}"
    t_build = time.perf_counter() - t
    print(f"build: {t_build:.2f} s ({what}; includes compiling the assembly)")

    fwd = eqx.filter_jit(lambda m, s: simulate(m, s, protocol))
    jax.block_until_ready(fwd(model, sigma(0)))  # compile
    t_fwd, c_fwd = timed(lambda i: fwd(model, sigma(i)), args.repeats)
    print(f"forward: {t_fwd:.3f} s wall, {c_fwd:.3f} s CPU")

    jacobian(model, sigma(0), protocol, dtype=jnp.float32, return_volts=True)  # compile
    out = np.empty((protocol.n_rows, mesh.n_tets), np.float32)
    t_fj, c_fj = timed(lambda i: jacobian(model, sigma(10 + i), protocol, dtype=jnp.float32,
                                          return_volts=True, out=out), args.repeats)
    t_fj2, c_fj2 = timed(lambda i: jacobian(model, sigma(20 + i), protocol, dtype=jnp.float32,
                                            return_volts=True), args.repeats)
    print(f"forward + Jacobian ({protocol.n_rows} x {mesh.n_tets}, float32): {t_fj:.3f} s wall "
          f"({c_fj:.3f} s CPU) into a reused buffer; {t_fj2:.3f} s ({c_fj2:.3f} s CPU) "
          "allocating the 1.2 GB result")
    t_tis, c_tis = timed(lambda i: jacobian(model, sigma(30 + i), protocol, per="tissue"),
                         args.repeats)
    print(f"forward + per-tissue Jacobian ({protocol.n_rows} x 4): {t_tis:.3f} s wall "
          f"({c_tis:.3f} s CPU)")

    v_meas = fwd(model, sigma0 * 1.1)

    def loss(m, s, x):
        return jnp.sum((simulate(m, s, protocol, nodes=x) - v_meas) ** 2)

    vg = eqx.filter_jit(jax.value_and_grad(loss, argnums=(1, 2)))
    jax.block_until_ready(vg(model, sigma(0), model.nodes))  # compile
    t_g, c_g = timed(lambda i: vg(model, sigma(40 + i), model.nodes), args.repeats)
    print(f"value and gradient w.r.t. 4 sigma + {mesh.n_nodes}x3 node positions: {t_g:.3f} s "
          f"wall ({c_g:.3f} s CPU) = {t_g / t_fwd:.2f} x forward")

    if args.cg:
        values = assemble(model, sigma0)
        b = electrode_rhs(jnp.asarray(_basis_currents(32)), mesh.n_nodes)
        for name, pre, steps in [("Jacobi", Jacobi(), 5000), ("SA-AMG", SmoothedAggregation(),
                                                               500)]:
            solver = BlockCG(preconditioner=pre, rtol=1e-10, max_steps=steps)
            t = time.perf_counter()
            mc = build_forward_model(mesh, elec, solver=solver)
            tb = time.perf_counter() - t
            f = eqx.filter_jit(lambda st, p, v, b: solver.solve_with_stats(st, p, v, b))
            jax.block_until_ready(f(mc.solver_state, mc.pattern, values, b))
            t, c = time.perf_counter(), time.process_time()
            x, k, done = jax.block_until_ready(f(mc.solver_state, mc.pattern, values, b))
            print(f"BlockCG[{name}] rtol 1e-10, 31 RHS: {int(k)} iterations, converged "
                  f"{bool(done.all())}, {time.perf_counter() - t:.2f} s wall "
                  f"({time.process_time() - c:.2f} s CPU); set-up {tb:.1f} s")

    if not args.no_scipy:
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        values = np.asarray(assemble(model, sigma(99)))
        p = model.pattern
        n = model.n_unknowns
        A = sp.csc_matrix((values[np.asarray(p.to_upper)], (np.asarray(p.rows),
                                                            np.asarray(p.cols))), shape=(n, n))
        B = np.asarray(electrode_rhs(jnp.asarray(_basis_currents(32)), mesh.n_nodes))
        t, c = time.perf_counter(), time.process_time()
        X = spla.spsolve(A, B)
        t_sp, c_sp = time.perf_counter() - t, time.process_time() - c
        resid = np.abs(A @ X - B).max() / np.abs(B).max()
        print(f"scipy spsolve (SuperLU, 31 RHS, OPENBLAS_NUM_THREADS="
              f"{os.environ.get('OPENBLAS_NUM_THREADS')}): {t_sp:.2f} s wall ({c_sp:.2f} s CPU), "
              f"residual {resid:.1e}")
        print(f"ratio scipy / jaxhead forward: {t_sp / t_fwd:.1f}x wall, {c_sp / c_fwd:.1f}x CPU")

    print("targets: forward <= 1.2 s, forward + Jacobian <= 1.5 s, gradient <= 2x forward, "
          ">= 25x faster than scipy spsolve")


if __name__ == "__main__":
    main()
