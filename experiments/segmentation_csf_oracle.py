"""How well intensity alone separates CSF from brain on the held-out renders: an oracle threshold.

For each real head, voxel size and scan of `segmentation_accuracy.py` (same renders, no bias field), the voxels
whose true label is brain or CSF are split by one intensity threshold, chosen with the truth (the best of 120
candidates between the 1st and 60th percentiles, either side), and the CSF Dice of that split is reported, on
the raw scan and on the scan smoothed by a Gaussian of 0.6 voxel sd. It is not a bound on a segmentation (the
atlas prior and the MRF use space, which a threshold does not), but it says how much of a row's CSF the
intensities can give at all: where it is below the bar, the missing part has to come from the spatial model.

    python experiments/segmentation_csf_oracle.py [--modality ct] [--out experiments/results/segmentation_csf_oracle_ct.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
from segmentation_accuracy import HEADS, NOISE, _write_atomic, dice  # noqa: E402

from jaxhead.segmentation.templates import ants_anatomy, mni152_anatomy, random_contrast, render  # noqa: E402
from jaxhead.tissue import Tissue  # noqa: E402


def oracle_dice(y: np.ndarray, csf: np.ndarray) -> float:
    """The best CSF Dice of one threshold on `y` (either side), `csf` the true CSF among these voxels."""
    return max(dice(y < th if below else y > th, csf)
               for th in np.percentile(y, np.linspace(1, 60, 120)) for below in (True, False))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--modality", default="ct", choices=["mri", "ct"])
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--heads", default=str(HEADS))
    p.add_argument("--out", default=None, help="markdown file to write (atomically)")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    lines = ["| anatomy | voxel mm | noise | contrast | brain + CSF voxels | oracle CSF Dice, raw | smoothed |",
             "|---|---|---|---|---|---|---|"]
    for name, anat in (("ants19.5", ants_anatomy(Path(args.heads))), ("mni152+fsaverage", mni152_anatomy())):
        for vox in (2.0, 1.0):
            a = anat.resampled(vox)
            truth = a.labels().labels
            m = (truth == Tissue.BRAIN) | (truth == Tissue.CSF)
            csf = truth[m] == Tissue.CSF
            for noise in NOISE[args.modality]:
                for seed in range(args.seeds):
                    contrast = None if seed == 0 else random_contrast(args.modality, np.random.default_rng(seed))
                    y = np.asarray(render(a, args.modality, contrast=contrast, noise=noise, seed=seed).data, np.float64)
                    raw, smooth = oracle_dice(y[m], csf), oracle_dice(ndimage.gaussian_filter(y, 0.6)[m], csf)
                    lines.append(f"| {name} | {vox:g} | {noise:g} | {'default' if seed == 0 else f'random {seed}'} | "
                                 f"{int(m.sum())} | {raw:.3f} | {smooth:.3f} |")
                    print(lines[-1], flush=True)
    head = (f"Oracle threshold between brain and CSF on the held-out renders ({args.modality}; see the script's docstring). "
            f"Run: {time.perf_counter() - t0:.0f} s wall, load average {os.getloadavg()[0]:.1f} at the end.\n\n"
            f"Command: `python experiments/segmentation_csf_oracle.py {' '.join(argv if argv is not None else sys.argv[1:])}`\n")
    if args.out:
        _write_atomic(args.out, head + "\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
