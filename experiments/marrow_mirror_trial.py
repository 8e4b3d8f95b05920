"""A trial, not a default: the marrow step's mirror. After `marrow_inside_skull`'s EM has taught the skull class the
marrow's fat-bright intensity, skull-labelled voxels as bright as that marrow which the tables do not enclose are
scalp fat; their skull prior goes to the scalp and the EM runs again.

Session 24 (experiments/results/segmentation_marrow_inside_skull.md, "Session 24"): on the ANTs head's adult-marrow
8 % scan at 1 mm, the marrow step labels the marrow skull but also 231k voxels of the scalp's fat beside the outer
table (skull 0.703). This script wraps the library's private `segment._marrow_inside_skull` (in this process only)
with the mirror step and segments the scans of `segmentation_accuracy.py` (adult marrow, `--diploe --fatty-marrow`)
named on the command line.

The mirror step: "tables" are the skull voxels darker (bias-corrected EM data) than the midpoint of the skull
class's darkest and brightest Gaussian means (`--threshold top2`: of its two brightest); the other skull voxels are
"bright". A bright voxel from which a grid ray (`segment.enclosed`, 26 rays) reaches the way out before a wall is
given back. Walls: tables, CSF, brain, background that tissue encloses. Way out: scalp (with `--outer-scalp` only
the scalp that the skull does not enclose, `segment.marrow_enclosed`'s complement) and background that leads out
of the grid.

    python experiments/marrow_mirror_trial.py ants:0.08:0 mni:0.08:1 [--voxel-mm 1] [--threshold top2] [--outer-scalp]

(anatomy:noise:seed; seed 0 the default contrast, seed k the random contrast of `segmentation_accuracy.py`). Prints
the Dice (brain / CSF / skull / scalp) with the marrow step alone and with the mirror, and the voxels given back.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from segmentation_accuracy import HEADS  # noqa: E402

import jaxhead.segmentation.segment  # noqa: E402,F401
from jaxhead.segmentation import SegmentConfig, default_atlas  # noqa: E402
from jaxhead.segmentation.atlas import anatomy_atlas  # noqa: E402
from jaxhead.segmentation.templates import (  # noqa: E402
    ants_anatomy, fatty_marrow, mni152_anatomy, random_contrast, render, with_diploe)
from jaxhead.tissue import Tissue  # noqa: E402

seg = sys.modules["jaxhead.segmentation.segment"]  # the module (`jaxhead.segmentation.segment` is also a function)


def mirror_step(threshold: str, outer_scalp: bool, given_back: list):
    """`_marrow_inside_skull` followed by the mirror step (module docstring); appends the voxels given back."""
    marrow_step = seg._marrow_inside_skull

    def step(volume, priors, unmodelled, pi, fit, cfg):
        priors, fit, summary = marrow_step(volume, priors, unmodelled, pi, fit, cfg)
        if summary.get("rounds", 0) == 0:  # no marrow moved: nothing taught the skull the marrow's intensity
            given_back.append(0)
            return priors, fit, summary
        post, res, opts = fit[:3]
        labels = np.argmax(post, axis=0)
        y = seg.corrected_em_data(volume, fit, cfg)
        means = np.sort(np.asarray(res.params.means)[np.asarray(opts.component_class) == int(Tissue.SKULL)])
        cut = 0.5 * (means[-2] + means[-1]) if threshold == "top2" else 0.5 * (means[0] + means[-1])
        skull = labels == Tissue.SKULL
        bright = skull & (y >= cut)
        bg = labels == Tissue.BACKGROUND
        held = seg.enclosed_background(labels)
        wall = (skull & ~bright) | held | (labels == Tissue.CSF) | (labels == Tissue.BRAIN)
        scalp = labels == Tissue.SCALP
        if outer_scalp:
            scalp &= ~seg.marrow_enclosed(labels)
        out = bright & ~seg.enclosed(wall, scalp | (bg & ~held))
        given_back.append(int(out.sum()))
        priors = np.array(priors, np.float32, copy=True)
        fit = seg._refit_with_prior_moved(volume, priors, out, Tissue.SKULL, Tissue.SCALP, unmodelled, pi, fit, cfg)
        return priors, fit, summary

    return step


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scans", nargs="+", help="anatomy:noise:seed, anatomy ants or mni")
    p.add_argument("--voxel-mm", type=float, default=1.0)
    p.add_argument("--threshold", choices=["midpoint", "top2"], default="midpoint")
    p.add_argument("--outer-scalp", action="store_true")
    p.add_argument("--heads", default=str(HEADS))
    args = p.parse_args(argv)
    ants = ants_anatomy(Path(args.heads))
    held_out = {"ants": (ants, lambda: default_atlas("mri", voxel_mm=2.0)),
                "mni": (mni152_anatomy(), lambda: anatomy_atlas(ants, "mri", voxel_mm=2.0, name="ants19.5"))}
    original = seg._marrow_inside_skull
    for spec in args.scans:
        name, noise, seed = spec.split(":")
        anat, atlas = held_out[name][0], held_out[name][1]()
        a = with_diploe(anat).resampled(args.voxel_mm)
        contrast = fatty_marrow(None if int(seed) == 0 else random_contrast("mri", np.random.default_rng(int(seed))))
        vol = render(a, "mri", contrast=contrast, noise=float(noise), bias=0.2, seed=int(seed))
        row = []
        for mirror in (False, True):
            given_back: list = []
            seg._marrow_inside_skull = mirror_step(args.threshold, args.outer_scalp, given_back) if mirror else original
            try:
                labels, _ = seg.segment_reported(vol, atlas, SegmentConfig(modality="mri"))
            finally:
                seg._marrow_inside_skull = original
            d = seg.dice_scores(labels, a.labels())
            row.append(" / ".join(f"{d[k]:.3f}" for k in ("brain", "csf", "skull", "scalp"))
                       + (f" ({given_back[0]:,} voxels given back)" if mirror else ""))
        print(f"{spec} ({args.threshold}{', outer scalp' if args.outer_scalp else ''}): marrow step {row[0]}; "
              f"with the mirror {row[1]}", flush=True)


if __name__ == "__main__":
    main()
