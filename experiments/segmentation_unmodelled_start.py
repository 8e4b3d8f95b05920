"""Where the atlas models no bone (face, neck): the skull share learnt from each start of the first EM.

For every scan of `segmentation_accuracy.py` whose atlas has an unmodelled-bone map (the ANTs head and
the phantom family, both with the mni152 atlas; 2 mm): register once, then for each start of the
first EM ("atlas": the atlas's placeholder soft tissue; "equal": half skull, half scalp; see
`segment.DEFAULT_UNMODELLED_START`) print

- the learnt skull share of skull + scalp in the region (`atlas.regional_proportions`),
- the truth's share there, weighted by the registered map as the estimate is,
- the mean log-likelihood per voxel of the first and second EM (`EMResult.log_likelihood`),
- Dice brain / CSF / skull / scalp of the second EM's labels (as `classify` returns them: before the
  MRI layer split and the CT majority rules, so the start's effect alone).

Usage (experiments/results/segmentation_unmodelled_start.md):
    python experiments/segmentation_unmodelled_start.py mri
    python experiments/segmentation_unmodelled_start.py ct
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
    args = ap.parse_args(argv)
    cfg = SegmentConfig(modality=args.modality)
    for anat, atlas, noise, contrast, vol, truth in SA.cases(args.modality, 2.0, 2, Path(SA.HEADS)):
        if atlas.unmodelled is None:
            continue
        transform, priors = register_atlas(vol, atlas, cfg)
        u, priors = unmodelled_on_grid(vol, atlas, transform, cfg), np.asarray(priors)
        skull, head = truth == Tissue.SKULL, np.isin(truth, (Tissue.SKULL, Tissue.SCALP))
        line = [f"{anat} {noise} {contrast}: truth {(u * skull).sum() / (u * head).sum():.3f}"]
        for name, start in STARTS.items():
            first = priors if start is None else with_proportions(priors, u, start)
            fit1 = _classify(vol, first, cfg, u)
            res1, pi = fit1[1], fit1[4]
            post, res2 = _classify(vol, with_proportions(priors, u, pi), cfg)[:2]
            d = SA.dice_per_tissue(post.argmax(0), truth)
            line.append(f"{name}: share {pi[0]:.3f}, log-likelihood {float(res1.log_likelihood):.4f} / "
                        f"{float(res2.log_likelihood):.4f}, Dice "
                        + "/".join(f"{d[k]:.3f}" for k in ("brain", "csf", "skull", "scalp")))
        print(" | ".join(line), flush=True)


if __name__ == "__main__":
    main()
