"""Study throughput: samples per hour of the morph and re-mesh routes with 1 and 2 workers.

One phantom head (`--voxel-mm`, default 2 mm as the issue asks; 4 mm for a quick look) is built
once into `--out` (the reference folder is reused by every run). Each measurement then runs a
fresh study of `--samples` samples of one route through `run_study` with an embedded
LocalCluster of 1 or 2 single-threaded worker processes; samples per hour = samples / wall time
of `run_study` (worker start-up and each worker's reference set-up included, reference mesh
excluded: it is built once per study, not per sample), and the steady rate, workers x 3600 /
the mean task time without the worker's one-off set-up (what a long study approaches). Morph samples: grf on the CSF's outer
surface, sd 0.5 mm, correlation 20 mm. Re-mesh samples: a random 8 mm skull hole. Measures: all
(voltages, imaging, fit), as a study runs them. The scaling 2 workers / 1 worker is printed.

Run: PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/study.py [--voxel-mm 2]
     [--samples 8] [--routes morph remesh] [--workers 1 2]
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

from jaxhead.study import run_study, study_config_from_dict  # noqa: E402
from jaxhead.study.engine import prepare_reference  # noqa: E402

PERT = {"morph": {"kind": "grf", "tissue": "csf", "amplitude": 0.5, "correlation_mm": 20.0},
        "remesh": {"kind": "skull_hole", "amplitude": 8.0}}


def config(out: Path, voxel_mm: float, route: str, samples: int, seed: int):
    return study_config_from_dict({
        "name": f"bench-{route}", "out_dir": str(out), "seed": seed, "first_order": False,
        "reference": {"source": "phantom", "voxel_mm": voxel_mm, "n_elec": 16},
        "perturbations": [{**PERT[route], "samples": samples}]})


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel-mm", type=float, default=2.0)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--routes", nargs="+", default=["morph", "remesh"], choices=list(PERT))
    ap.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--out", default="runs/bench_study")
    args = ap.parse_args()
    out = Path(args.out)
    results = {}
    t0 = time.perf_counter()
    cfg0 = config(out, args.voxel_mm, args.routes[0], 1, 0)
    prepare_reference(json.loads(json.dumps(cfg0.to_dict(), default=list)),
                      str(out / "study" / "reference"))
    print(f"reference head ({args.voxel_mm} mm voxels): {time.perf_counter() - t0:.1f} s "
          "(once; not in the rates)", flush=True)
    for route in args.routes:
        for i, n in enumerate(args.workers):
            cfg = config(out, args.voxel_mm, route, args.samples, seed=100 * i + len(route))
            shutil.rmtree(out / "study" / "samples", ignore_errors=True)
            for f in ("samples.csv", "summary.json"):
                (out / "study" / f).unlink(missing_ok=True)
            t0 = time.perf_counter()
            path = run_study(cfg, workers=n, progress=False)
            wall = time.perf_counter() - t0
            rows = [json.loads(f.read_text()) for f in sorted((path / "samples").glob("*.json"))]
            failed = sum(bool(r["error"]) for r in rows)
            setup = [r["timings"].get("worker_setup", 0.0) for r in rows]
            task = np.array([r["seconds"] - s for r, s in zip(rows, setup)])
            steps = {k: np.mean([r["timings"][k] for r in rows if k in r["timings"]])
                     for k in ("perturb", "mesh", "forward", "measures")
                     if any(k in r["timings"] for r in rows)}
            rate = args.samples / wall * 3600
            steady = n * 3600 / task.mean()
            results[(route, n)] = (rate, steady)
            load = os.getloadavg()
            print(f"{route:7s} workers={n}: {args.samples} samples in {wall:7.1f} s -> {rate:6.1f} "
                  f"samples/h end to end (cluster start, each worker's set-up "
                  f"{max(setup):.0f} s, included); {steady:6.1f} samples/h steady "
                  f"({n} x 3600 / mean task {task.mean():.1f} s); {failed} failed; steps "
                  + ", ".join(f"{k} {v:.1f} s" for k, v in steps.items())
                  + f"; load {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}", flush=True)
            print("         per sample (s, set-up excluded): "
                  + " ".join(f"{t:.1f}" for t in task), flush=True)
        have = [n for n in (1, 2) if (route, n) in results]
        if len(have) == 2:
            (r1, s1), (r2, s2) = results[(route, 1)], results[(route, 2)]
            print(f"{route:7s} scaling 2 workers / 1 worker: {r2 / r1:.2f}x end to end, "
                  f"{s2 / s1:.2f}x steady", flush=True)


if __name__ == "__main__":
    main()
