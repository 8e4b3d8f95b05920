"""Segmentation accuracy on phantoms not in the atlas: Dice per tissue, MRI and CT, two noise levels.

Compares `jaxhead.segmentation.segment` (atlas registration + EM with priors, relaxation, MRF, bias field),
the same with tied partial-volume Gaussians (`SegmentConfig(partial_volume=True)`, "with PV
Gaussians"), and a no-prior baseline: a plain Gaussian mixture on the same intensity feature (MRI log intensity,
CT HU) with as many Gaussians as the full model, started at the intensity quantiles, each Gaussian then
given the tissue it overlaps most in the ground truth (an *oracle* mapping: the baseline's best case).

The default atlases are built from phantom seeds 1000.. (jaxhead.segmentation.atlas.DEFAULT_ATLAS_SEED);
the evaluation subjects are seeds 0..n-1.

Usage:
    .venv/bin/python experiments/segmentation_accuracy.py [--subjects 3] [--voxel-mm 2] \\
        [--modalities mri ct] [--ablations] [--out experiments/results/segmentation_accuracy]

Writes <out>.json (one row per subject, method and noise level) and <out>.md (the table of means),
each atomically (temporary file in the same folder, then os.replace).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # entry point: float64 available (segment uses float32)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxhead.phantom import DEFAULT_NOISE, make_head  # noqa: E402
from jaxhead.segmentation import MixtureParams, RegisterConfig, SegmentConfig, default_atlas, segment  # noqa: E402
from jaxhead.segmentation.em import EMOptions, fit_mixture  # noqa: E402
from jaxhead.segmentation.segment import _em_data  # noqa: E402
from jaxhead.tissue import TISSUES, Tissue  # noqa: E402

log = logging.getLogger("segmentation_accuracy")


def dice(a: np.ndarray, b: np.ndarray) -> float:
    s = a.sum() + b.sum()
    return float(2 * (a & b).sum() / s) if s else 1.0


def dice_per_tissue(labels: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    return {t.name.lower(): dice(labels == t, truth == t) for t in TISSUES}


def baseline_gmm(volume, modality: str, n_gaussians: int, truth: np.ndarray) -> np.ndarray:
    """Plain GMM on intensity (no spatial prior, no MRF) + oracle component -> tissue mapping."""
    y = _em_data(volume, modality)
    q = np.quantile(y, (np.arange(n_gaussians) + 0.5) / n_gaussians)
    init = MixtureParams(
        means=jnp.asarray(q), variances=jnp.full(n_gaussians, y.var() / n_gaussians**2),
        weights=jnp.full(n_gaussians, 1.0 / n_gaussians), bias=jnp.zeros(0),
    )
    opts = EMOptions(component_class=(0,) * n_gaussians, n_classes=1, max_iter=200, tol=1e-7)
    # float32, as the full method (SegmentConfig.precision)
    res = fit_mixture(jnp.asarray(y, jnp.float32), jnp.ones((1, *y.shape), jnp.float32), opts, init)
    mu, var, w = (np.asarray(a) for a in (res.params.means, res.params.variances, res.params.weights))
    logp = np.log(w) - 0.5 * np.log(2 * np.pi * var) - 0.5 * (y[..., None] - mu) ** 2 / var
    comp = logp.argmax(-1)
    out = np.zeros_like(truth)
    for j in range(n_gaussians):
        m = comp == j
        if m.any():
            out[m] = np.bincount(truth[m].ravel(), minlength=len(Tissue)).argmax()
    return out


def run(args) -> list[dict]:
    rows = []
    for modality in args.modalities:
        t0 = time.perf_counter()
        atlas = default_atlas(modality, voxel_mm=args.atlas_voxel_mm)
        log.info("%s atlas ready (%.0f s)", modality, time.perf_counter() - t0)
        base_noise = DEFAULT_NOISE[modality]
        variants = {"full": SegmentConfig(modality=modality)}
        # tied partial-volume Gaussians instead of free ones owned by one class (off by default)
        variants["with PV Gaussians"] = SegmentConfig(modality=modality, partial_volume=True)
        if args.ablations:
            variants["affine only"] = SegmentConfig(modality=modality, register=RegisterConfig(bspline=False))
            variants["no MRF"] = SegmentConfig(modality=modality, beta=0.0)
            variants["no relaxation"] = SegmentConfig(modality=modality, relax=0.0)
        for noise in (base_noise, 2 * base_noise):
            for seed in range(args.subjects):
                vol, lab = make_head(modality, voxel_mm=args.voxel_mm, noise=noise, seed=seed)
                truth = lab.labels
                for name, cfg in variants.items():
                    t = time.perf_counter()
                    seg = segment(vol, atlas, cfg)
                    d = dice_per_tissue(seg.labels.labels, truth)
                    rows.append(dict(modality=modality, noise=noise, seed=seed, method=name,
                                     seconds=time.perf_counter() - t, **d))
                    log.info("%s noise %g seed %d %s: %s (%.0f s)", modality, noise, seed, name,
                             {k: round(v, 3) for k, v in d.items()}, rows[-1]["seconds"])
                n_g = len(variants["full"].em_options(1.0).component_class)
                t = time.perf_counter()
                d = dice_per_tissue(baseline_gmm(vol, modality, n_g, truth), truth)
                rows.append(dict(modality=modality, noise=noise, seed=seed, method="GMM baseline (oracle map)",
                                 seconds=time.perf_counter() - t, **d))
                log.info("%s noise %g seed %d baseline: %s", modality, noise, seed, {k: round(v, 3) for k, v in d.items()})
    return rows


def table(rows: list[dict]) -> str:
    names = [t.name.lower() for t in TISSUES]
    out = ["| modality | noise | method | " + " | ".join(names) + " | s/subject |",
           "|---|---|---|" + "---|" * len(names) + "---|"]
    keys = []
    for r in rows:
        k = (r["modality"], r["noise"], r["method"])
        if k not in keys:
            keys.append(k)
    for k in keys:
        sel = [r for r in rows if (r["modality"], r["noise"], r["method"]) == k]
        means = [np.mean([r[n] for r in sel]) for n in names]
        mins = [np.min([r[n] for r in sel]) for n in names]
        cells = [f"{m:.3f} (min {lo:.3f})" for m, lo in zip(means, mins)]
        out.append(f"| {k[0]} | {k[1]:g} | {k[2]} | " + " | ".join(cells) +
                   f" | {np.mean([r['seconds'] for r in sel]):.0f} |")
    return "\n".join(out)


def _write_atomic(path: str, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(path)), suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--subjects", type=int, default=3, help="evaluation subjects (seeds 0..n-1)")
    p.add_argument("--voxel-mm", type=float, default=2.0)
    p.add_argument("--atlas-voxel-mm", type=float, default=2.0)
    p.add_argument("--modalities", nargs="+", default=["mri", "ct"], choices=["mri", "ct"])
    p.add_argument("--ablations", action="store_true", help="also run affine-only, no-MRF, no-relaxation")
    p.add_argument("--out", default=None,
                   help="path stem: write <out>.json (rows) and <out>.md (table), atomically")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for name in ("jax", "jaxhead.phantom"):
        logging.getLogger(name).setLevel(logging.WARNING)
    t0, c0 = time.perf_counter(), time.process_time()
    rows = run(args)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    head = (f"Dice per tissue, mean (and minimum) over {args.subjects} subjects (phantom seeds "
            f"0..{args.subjects - 1}, not in the atlas), {args.voxel_mm:g} mm voxels, atlas "
            f"{args.atlas_voxel_mm:g} mm; noise: MRI fraction of white matter, CT HU. "
            f"Run: {wall:.0f} s wall, {cpu:.0f} s CPU, load average {os.getloadavg()[0]:.1f} at the end.")
    print("\n" + head + "\n")
    print(table(rows))
    if args.out:
        stem = args.out[:-5] if args.out.endswith(".json") else args.out
        os.makedirs(os.path.dirname(os.path.abspath(stem)), exist_ok=True)
        meta = dict(subjects=args.subjects, voxel_mm=args.voxel_mm, atlas_voxel_mm=args.atlas_voxel_mm,
                    modalities=args.modalities, ablations=args.ablations, wall_s=wall, cpu_s=cpu,
                    command=" ".join(["python", "experiments/segmentation_accuracy.py", *(argv or sys.argv[1:])]))
        _write_atomic(stem + ".json", json.dumps(dict(meta=meta, rows=rows), indent=1))
        _write_atomic(stem + ".md", f"{head}\n\nCommand: `{meta['command']}`\n\n{table(rows)}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
