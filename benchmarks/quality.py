"""Time jaxhead.geometry.quality.tet_metrics against VTK's vtkMeshQuality (Verdict) on one mesh.

Usage: .venv/bin/python benchmarks/quality.py [n_points]   (default 50000 -> ~335k tets,
the size of a 1 mm head mesh). Both compute jacobian, scaled_jacobian, condition, radius_ratio,
min dihedral, volume and distortion; VTK's runs single-threaded C++, jaxhead's is XLA on CPU.
"""

import os
import sys
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import pyvista as pv  # noqa: E402
from scipy.spatial import Delaunay  # noqa: E402

from jaxhead.geometry import orient_tets  # noqa: E402
from jaxhead.geometry.quality import tet_metrics  # noqa: E402

VTK_MEASURES = ["jacobian", "scaled_jacobian", "condition", "radius_ratio", "min_angle",
                "volume", "distortion"]


def _best(fn, repeat=3):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main(n_points: int = 50_000) -> None:
    pts = np.random.default_rng(0).random((n_points, 3)) * 200.0  # mm
    tets, _ = orient_tets(pts, Delaunay(pts).simplices)
    print(f"mesh: {len(pts)} nodes, {len(tets)} tets; jax {jax.__version__}, "
          f"devices {jax.devices()}")

    t = time.perf_counter()
    jax.block_until_ready(tet_metrics(pts, tets))
    print(f"jaxhead first call (trace + compile + run): {time.perf_counter() - t:.2f} s")
    t_jax = _best(lambda: jax.block_until_ready(tet_metrics(pts, tets)))

    grid = pv.UnstructuredGrid({pv.CellType.TETRA: tets}, pts)
    t_vtk = _best(lambda: grid.cell_quality(VTK_MEASURES), repeat=2)

    print(f"jaxhead tet_metrics (7 metrics): {t_jax:.3f} s")
    print(f"VTK cell_quality   (7 metrics): {t_vtk:.3f} s")
    print(f"ratio VTK / jaxhead: {t_vtk / t_jax:.1f}x")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 50_000)
