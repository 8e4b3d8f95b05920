"""Where the MRI mixture puts its Gaussians on the held-out heads, and what a setting changes (Dice, confusions).

Runs the MRI cases of `segmentation_accuracy.py` on real anatomy (the ANTs head with the mni152 atlas,
the MNI152 head with the ANTs atlas; 2 mm, noise 3 and 8 %, default and random contrast), registering
once per scan, then `classify` with each SegmentConfig setting given, and prints per scan: Dice
(brain / CSF / skull / scalp), the voxels of true CSF labelled skull and the other skull confusions,
and the fitted Gaussians (mean, sd in log intensity; within-class weight), ordered BACKGROUND, BRAIN,
CSF, SKULL, SCALP.

Usage: python experiments/segmentation_mixture_diagnosis.py "[{}, dict(variance_prior=0.05)]"
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from segmentation_capture_diagnosis import dice4, scans as registered_scans  # noqa: E402

from jaxhead.segmentation import SegmentConfig  # noqa: E402
from jaxhead.segmentation.segment import classify  # noqa: E402
from jaxhead.volume import Volume  # noqa: E402


def main(argv):
    settings = eval(argv[0]) if argv else [{}]  # a list of SegmentConfig keyword dicts (trusted input)
    scans = [(s["anat"], s["noise"], s["contrast"], Volume(s["data"], s["affine"]), s["truth"], s["priors"], s["unm"])
             for s in registered_scans(None)]  # registered once per scan, as the capture diagnosis does
    for kw in settings:
        cfg = SegmentConfig(modality="mri", **kw)
        t0 = time.perf_counter()
        print("=== setting", kw, flush=True)
        for anat, noise, contrast, vol, t, priors, unm in scans:
            post, res, _, _ = classify(vol, priors, cfg, unm)
            lab = post.argmax(0)
            d = dice4(lab, t)
            p = res.params
            print(f"{anat} {noise} {contrast}: EM {int(res.n_iter)} iterations, Dice {np.round(d, 3).tolist()}, "
                  f"csf->skull {int(((t == 2) & (lab == 3)).sum())}, skull->csf {int(((t == 3) & (lab == 2)).sum())}, "
                  f"skull->scalp {int(((t == 3) & (lab == 4)).sum())}")
            print("   mean", np.round(np.asarray(p.means), 2).tolist())
            print("   sd  ", np.round(np.sqrt(np.asarray(p.variances)), 3).tolist())
            print("   w   ", np.round(np.asarray(p.weights), 3).tolist(), flush=True)
        print(f"   ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
