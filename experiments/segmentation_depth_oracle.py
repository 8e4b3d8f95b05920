"""How well relative depth between brain and scalp separates CSF from skull, on the true labels.

For each anatomy (ANTs head, MNI152 + fsaverage head, phantom seeds 0 and 1; 2 mm), the band between
the true brain and scalp (true CSF + skull) is split by a threshold on t = d_brain / (d_brain +
d_scalp) (`jaxhead.segmentation.depth_prior.layer_depth`) or on d_brain alone (mm). Prints the best
threshold per anatomy and the CSF Dice of every anatomy's threshold applied to every other: what a
depth prior carried from one head to another can give at best, intensity aside.

Usage (experiments/results/segmentation_depth_prior.md):
    python experiments/segmentation_depth_oracle.py [--heads ../shared/data/heads]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import segmentation_accuracy as SA  # noqa: E402

from jaxhead.phantom import make_head  # noqa: E402
from jaxhead.segmentation.depth_prior import layer_depth  # noqa: E402
from jaxhead.segmentation.templates import ants_anatomy, mni152_anatomy  # noqa: E402
from jaxhead.tissue import Tissue  # noqa: E402


def band_features(labels: np.ndarray, vox: float):
    """(t, d_brain in mm, is CSF) over the true CSF + skull voxels."""
    band = (labels == Tissue.CSF) | (labels == Tissue.SKULL)
    t = layer_depth(labels == Tissue.BRAIN, labels == Tissue.SCALP, (vox,) * 3)
    d = ndimage.distance_transform_edt(labels != Tissue.BRAIN, sampling=vox)
    return t[band], d[band], labels[band] == Tissue.CSF


def csf_dice(x, csf, threshold) -> float:
    pred = x <= threshold
    return float(2 * (pred & csf).sum() / (pred.sum() + csf.sum()))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--heads", default=str(SA.HEADS))
    args = p.parse_args(argv)
    vox = 2.0
    heads = {"ants19.5": ants_anatomy(Path(args.heads)).resampled(vox).labels().labels,
             "mni152+fsaverage": mni152_anatomy().resampled(vox).labels().labels,
             "phantom 0": make_head("mri", voxel_mm=vox, seed=0)[1].labels,
             "phantom 1": make_head("mri", voxel_mm=vox, seed=1)[1].labels}
    feats = {k: band_features(v, vox) for k, v in heads.items()}
    for name, col, grid in (("t", 0, np.linspace(0, 1, 201)), ("d_brain (mm)", 1, np.linspace(0, 12, 121))):
        best = {k: float(grid[np.argmax([csf_dice(f[col], f[2], g) for g in grid])]) for k, f in feats.items()}
        print(f"\n{name}: best threshold per anatomy {best}")
        print("| band of \\ threshold of | " + " | ".join(best) + " |")
        print("|---|" + "---|" * len(best))
        for k, f in feats.items():
            print(f"| {k} | " + " | ".join(f"{csf_dice(f[col], f[2], best[m]):.3f}" for m in best) + " |")


if __name__ == "__main__":
    main()
