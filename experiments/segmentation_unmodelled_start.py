"""Where the atlas models no bone (face, neck): the skull share learnt from each start of the first EM.

For every scan of `segmentation_accuracy.py` whose atlas has an unmodelled-bone map (the ANTs head and
the phantom family, both with the mni152 atlas; 2 mm unless --voxel-mm): register once, then for each start of
the first EM ("atlas": the atlas's placeholder soft tissue; "equal": half skull, half scalp; see
`segment.DEFAULT_UNMODELLED_START`) print

- the learnt skull share of skull + scalp in the region (`atlas.regional_proportions`),
- the truth's share there, weighted by the registered map as the estimate is,
- the mean log-likelihood per voxel of the first and second EM (`EMResult.log_likelihood`),
- Dice brain / CSF / skull / scalp of the second EM's labels (as `classify` returns them: before the
  MRI layer split and the CT majority rules, so the start's effect alone).

The first EM runs as `segment` runs it: on the `first_pass_sample_mm` sample (since session 29; session 17's
table used the EM's own 2 mm sample). With --passes N > 1 the share is iterated (share -> first EM -> share) N
times from each start, and each pass's share and first-EM log-likelihood are printed (session 34: from the two
starts the iteration can end at two fixed points). The scans' options are `segmentation_accuracy.py`'s.

Usage (experiments/results/segmentation_unmodelled_start.md, segmentation_unmodelled_bistable.md):
    python experiments/segmentation_unmodelled_start.py mri
    python experiments/segmentation_unmodelled_start.py ct
    python experiments/segmentation_unmodelled_start.py mri --voxel-mm 1 --diploe --fatty-marrow --psf-mm 1.2 \
        --no-phantom --passes 4
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import segmentation_accuracy as SA  # noqa: E402

from jaxhead.segmentation import SegmentConfig  # noqa: E402
from jaxhead.segmentation.atlas import with_proportions  # noqa: E402
from jaxhead.segmentation.segment import _classify, register_atlas, unmodelled_on_grid  # noqa: E402
from jaxhead.tissue import Tissue  # noqa: E402

STARTS = {"atlas": None, "equal": np.array([0.5, 0.5])}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("modality", choices=("mri", "ct"))
    ap.add_argument("--voxel-mm", type=float, default=2.0)
    ap.add_argument("--diploe", action="store_true")
    ap.add_argument("--fatty-marrow", action="store_true")
    ap.add_argument("--psf-mm", type=float, default=0.0)
    ap.add_argument("--fov-mm", type=float, nargs=3, default=None)
    ap.add_argument("--no-phantom", action="store_true")
    ap.add_argument("--passes", type=int, default=1, help="first EMs per start, each from the last share")
    args = ap.parse_args(argv)
    if args.passes < 1:
        ap.error(f"--passes must be >= 1, got {args.passes}")
    cfg = SegmentConfig(modality=args.modality)
    for anat, atlas, noise, contrast, vol, truth in SA.cases(
            args.modality, args.voxel_mm, 2, Path(SA.HEADS), diploe=args.diploe, fatty=args.fatty_marrow,
            fov_mm=args.fov_mm, psf_fwhm_mm=args.psf_mm, phantom=not args.no_phantom):
        if atlas.unmodelled is None:
            continue
        transform, priors = register_atlas(vol, atlas, cfg)
        u, priors = unmodelled_on_grid(vol, atlas, transform, cfg), np.asarray(priors)
        skull, head = truth == Tissue.SKULL, np.isin(truth, (Tissue.SKULL, Tissue.SCALP))
        line = [f"{anat} {noise} {contrast}: truth {(u * skull).sum() / (u * head).sum():.3f}"]
        for name, start in STARTS.items():
            first, passes = priors if start is None else with_proportions(priors, u, start), []
            for _ in range(args.passes):
                fit1 = _classify(vol, first, cfg, u, sample_mm=cfg.first_pass_sample_of())
                res1, pi = fit1[1], fit1[4]
                passes.append(f"{pi[0]:.3f} ({float(res1.log_likelihood):.4f})")
                first = with_proportions(priors, u, pi)
            post, res2 = _classify(vol, with_proportions(priors, u, pi), cfg)[:2]
            d = SA.dice_per_tissue(post.argmax(0), truth)
            if args.passes > 1:
                line.append(f"{name} passes: " + ", ".join(passes))
            line.append(f"{name}: share {pi[0]:.3f}, log-likelihood {float(res1.log_likelihood):.4f} / "
                        f"{float(res2.log_likelihood):.4f}, Dice "
                        + "/".join(f"{d[k]:.3f}" for k in ("brain", "csf", "skull", "scalp")))
        print(" | ".join(line), flush=True)


if __name__ == "__main__":
    main()
