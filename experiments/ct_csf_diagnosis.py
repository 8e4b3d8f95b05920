"""CT CSF on the ANTs head (issue 11): the four ANTs CT scans of segmentation_accuracy.py, and an intensity ceiling.

Usage:
    python experiments/ct_csf_diagnosis.py [key=value ...]   # SegmentConfig overrides, e.g. csf_below_brain=False beta=0.0
    python experiments/ct_csf_diagnosis.py ceiling           # best single-HU-threshold CSF Dice, noise-free

`which=r1` segments only the random-contrast scans; `margin=10` replaces CSF_BRAIN_MARGIN_HU (a
sensitivity check). Prints Dice and the fitted means / sds / weights per scan. Results:
experiments/results/segmentation_csf_order.md.
"""

import importlib
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from segmentation_accuracy import HEADS, dice_per_tissue  # noqa: E402

from jaxhead.segmentation import SegmentConfig, default_atlas, segment_reported  # noqa: E402
from jaxhead.segmentation.templates import ants_anatomy, mni152_anatomy, random_contrast, render  # noqa: E402


def ceiling():
    """Upper bound of any intensity-only CSF/brain rule: the best HU threshold inside the true brain + CSF
    mask of the noise-free 2 mm rendering (skull excluded)."""
    for name, anat in (("ants19.5", ants_anatomy(HEADS)), ("mni152+fsaverage", mni152_anatomy())):
        a = anat.resampled(2.0)
        truth = a.labels().labels
        for seed in (0, 1):
            contrast = None if seed == 0 else random_contrast("ct", np.random.default_rng(seed))
            v = render(a, "ct", contrast=contrast, noise=0.0, bias=0.0, seed=seed).data
            m, c = (truth == 1) | (truth == 2), truth == 2
            best = max((2 * (c & m & (v < t)).sum() / (c.sum() + (m & (v < t)).sum()), t) for t in np.arange(0, 45, 0.5))
            print(f"{name} contrast {seed}: median HU CSF {np.median(v[c]):.1f}, brain {np.median(v[truth == 1]):.1f}; "
                  f"best threshold CSF Dice {best[0]:.3f} at {best[1]:.1f} HU")


def main(argv):
    if argv[:1] == ["ceiling"]:
        return ceiling()
    kw, which = {}, "all"
    for a in argv:
        k, v = a.split("=", 1)
        if k == "which":
            which = v
        elif k == "margin":
            importlib.import_module("jaxhead.segmentation.segment").CSF_BRAIN_MARGIN_HU = float(v)
        else:
            kw[k] = eval(v)  # a literal: True, 0.0, {'brain': 2}
    cfg = SegmentConfig(modality="ct", **kw)
    ants = ants_anatomy(HEADS).resampled(2.0)
    truth = ants.labels().labels
    atlas = default_atlas("ct", voxel_mm=2.0)
    for noise in (5.0, 20.0):
        for seed in (0, 1):
            if which == "r1" and seed == 0:
                continue
            contrast = None if seed == 0 else random_contrast("ct", np.random.default_rng(seed))
            vol = render(ants, "ct", contrast=contrast, noise=noise, bias=0.0, seed=seed)
            t = time.perf_counter()
            lab, seg = segment_reported(vol, atlas, cfg)
            d = dice_per_tissue(lab.labels, truth)
            p = seg.params
            print(f"noise {noise:g} contrast {seed}: " + " ".join(f"{k} {v:.3f}" for k, v in d.items())
                  + f" | means {np.round(p.means, 1).tolist()} sd {np.round(np.sqrt(p.variances), 1).tolist()} "
                  f"w {np.round(p.weights, 2).tolist()} ({time.perf_counter() - t:.0f} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
