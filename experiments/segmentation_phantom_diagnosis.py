"""Which stage fails when the jaxhead phantom is segmented with the real-anatomy (mni152) atlas.

One phantom MRI (make_head seed, noise, 2 mm) against the default mni152 atlas (issue 11; the rows
"phantom (mni152)" of experiments/results/segmentation_heldout_mri.md). Prints:

- registration: the affine's scales (scan mm -> atlas mm), the B-spline's largest and rms control
  displacement and bending energy, and the warped atlas priors' argmax against the phantom's truth
  (Dice per class, intracranial = brain + CSF, head = not background; confusion matrix), for the
  affine alone and affine + B-spline;
- the default EM + MRF (`classify`): Dice, confusion matrix (rows truth, columns predicted), the fitted
  Gaussians (MRI: exp of the log-intensity means) against the phantom's intensities per Structure;
- controls: the same EM with "oracle" priors (the truth's one-hot classes blurred and spread exactly
  as `templates.atlas_priors` builds an atlas: 3 mm, 5 %), and with the registered priors but started
  from the oracle fit's parameters (is a wrong optimum an initialisation matter or the priors'?).

Usage: python experiments/segmentation_phantom_diagnosis.py [--seed 0] [--noise 0.03]
Results: experiments/results/segmentation_phantom_heldout.md.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

from jaxhead.phantom import Structure, make_head, structure_map  # noqa: E402
from jaxhead.segmentation import SegmentConfig, default_atlas, register_atlas  # noqa: E402
from jaxhead.segmentation.register import AffineTransform, BSplineTransform, bending_energy, resample  # noqa: E402
from jaxhead.segmentation.segment import classify, registration_summary, unmodelled_on_grid  # noqa: E402
from jaxhead.volume import voxel_sizes  # noqa: E402


def dice(a, b) -> float:
    s = a.sum() + b.sum()
    return float(2 * (a & b).sum() / s) if s else 1.0


def per_class(pred, truth) -> list[float]:
    return [round(dice(pred == k, truth == k), 3) for k in range(1, 5)]


def confusion(pred, truth) -> np.ndarray:
    return np.array([[int(((truth == i) & (pred == j)).sum()) for j in range(5)] for i in range(5)])


def oracle_priors(truth, sigma_vox: float, spread: float = 0.05) -> np.ndarray:
    """The truth's classes blurred and spread as templates.atlas_priors builds an atlas."""
    p = np.stack([ndimage.gaussian_filter((truth == k).astype(np.float64), sigma_vox, mode="nearest")
                  for k in range(5)])
    head = 1.0 - p[0]
    p[1:] = (1 - spread) * p[1:] + spread * head[None] / 4.0
    return (p / p.sum(0, keepdims=True)).astype(np.float32)


def fit_report(name, post, res, opts, truth):
    pred = post.argmax(0)
    print(f"\n{name}: Dice brain/csf/skull/scalp {per_class(pred, truth)}")
    print("confusion (rows truth bg/brain/csf/skull/scalp, columns predicted)\n", confusion(pred, truth))
    p = res.params
    print("Gaussian class  ", list(opts.component_class))
    print("mean (intensity)", np.round(np.exp(np.asarray(p.means)), 3).tolist())
    print("sd (log)        ", np.round(np.sqrt(np.asarray(p.variances)), 3).tolist())
    print("weight          ", np.round(np.asarray(p.weights), 3).tolist(), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, default=0.03)
    args = ap.parse_args(argv)
    vol, lab = make_head("mri", voxel_mm=2.0, noise=args.noise, seed=args.seed)
    truth = lab.labels
    s = structure_map(voxel_mm=2.0, seed=args.seed)
    atlas = default_atlas("mri", voxel_mm=2.0)
    cfg = SegmentConfig(modality="mri")
    print(f"phantom seed {args.seed}, MRI noise {args.noise}, 2 mm, grid {vol.shape}")
    print("phantom intensities per Structure (scan, white matter = 1): median (p10..p90)")
    for st in Structure:
        m = s == st
        if m.any():
            q = np.percentile(vol.data[m], [10, 50, 90])
            print(f"  {st.name:12s} {int(m.sum()):7d} voxels  {q[1]:.3f} ({q[0]:.3f}..{q[2]:.3f})")

    transform, priors = register_atlas(vol, atlas, cfg)
    priors = np.asarray(priors)
    summary = registration_summary(vol, atlas, transform)
    print("\naffine scales", np.round(summary["scales"], 3).tolist(), "det %.3f rotation %.1f deg NMI %.3f" % (
        summary["det"], summary["rotation_deg"], summary["nmi"]))
    warped = {"affine + B-spline": priors}
    if isinstance(transform, BSplineTransform):
        c = np.asarray(transform.coefficients)
        spacing = voxel_sizes(np.asarray(transform.grid_affine))
        print("B-spline control displacement max %.1f mm, rms %.1f mm, bending energy %.3g mm^-2" % (
            np.abs(c).max(), np.sqrt((c**2).sum(0).mean()), float(bending_energy(jnp.asarray(c), spacing))))
        warped["affine only"] = np.asarray(resample(atlas.priors, atlas.affine, AffineTransform(matrix=transform.affine),
                                                    vol.shape, vol.affine))
    ic = (truth == 1) | (truth == 2)
    for name, p in warped.items():
        am = p.argmax(0)
        print(f"\nwarped atlas priors ({name}), argmax vs truth: Dice {per_class(am, truth)}, intracranial "
              f"{dice((am == 1) | (am == 2), ic):.3f}, head {dice(am > 0, truth > 0):.3f}")
        print("confusion (rows truth, columns prior argmax)\n", confusion(am, truth))

    print("\nregistered prior mass (sum over voxels) on truth bg/brain/csf/skull/scalp:")
    for k, name in enumerate(("background", "brain", "csf", "skull", "scalp")):
        print(f"  {name:10s}", [int(priors[k][truth == j].sum()) for j in range(5)])
    unm = unmodelled_on_grid(vol, atlas, transform, cfg)
    post, res, opts, _ = classify(vol, priors, cfg, unm)
    fit_report("default EM + MRF on the registered priors", post, res, opts, truth)
    oracle = oracle_priors(truth, 3.0 / float(np.mean(voxel_sizes(vol.affine))))
    post_o, res_o, opts, _ = classify(vol, oracle, cfg, None)
    fit_report("control: the same EM on oracle priors (truth blurred 3 mm, 5 % spread)", post_o, res_o, opts, truth)
    # the registered priors again, the EM started from the oracle fit (fit_mixture's `init`)
    seg_module = sys.modules["jaxhead.segmentation.segment"]  # the package re-exports a function `segment`
    fit = seg_module.fit_mixture
    try:
        seg_module.fit_mixture = lambda y, pr, op, init=None, co=None, nf=None: fit(y, pr, op, res_o.params, co, nf)
        post_i, res_i, opts, _ = classify(vol, priors, replace(cfg, relax=0.0), None)
    finally:
        seg_module.fit_mixture = fit
    fit_report("control: registered priors, EM started from the oracle fit (no relaxation, no unmodelled)",
               post_i, res_i, opts, truth)
    return 0


if __name__ == "__main__":
    sys.exit(main())
