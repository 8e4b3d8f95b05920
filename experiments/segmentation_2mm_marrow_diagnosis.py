"""Where the skull goes wrong on a 2 mm MRI with an adult's (fat-bright) marrow: one held-out scan, stage by stage.

Renders the accuracy table's scan (`segmentation_accuracy.cases`: --diploe --fatty-marrow at 2 mm, the default contrast,
3 % noise) of one test anatomy, segments it with the default config and prints the confusion matrix (rows truth,
columns labels: background, brain, CSF, skull, scalp), the true skull by its distance from the true intracranial
space and what it was labelled, the true scalp labelled skull by the same distance, and how much of that lies where
the atlas models no bone (`Atlas.unmodelled` > 0.5: face, skull base, neck).

Usage: .venv/bin/python experiments/segmentation_2mm_marrow_diagnosis.py [--anatomy ants19.5|mni152+fsaverage]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import segmentation_accuracy as sa  # noqa: E402

from jaxhead.segmentation import SegmentConfig  # noqa: E402
from jaxhead.segmentation.segment import segment_reported, unmodelled_on_grid  # noqa: E402
from jaxhead.segmentation.templates import shipped_heads_folder  # noqa: E402

BANDS_MM = ((0, 10), (10, 20), (20, 1000))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--anatomy", default="ants19.5", choices=["ants19.5", "mni152+fsaverage"])
    p.add_argument("--heads", default=shipped_heads_folder())
    args = p.parse_args(argv)
    cfg = SegmentConfig(modality="mri")
    for name, atlas, noise, contrast, vol, truth in sa.cases("mri", 2.0, 1, Path(args.heads), diploe=True, fatty=True,
                                                             phantom=False):
        if name != args.anatomy or noise != 0.03:
            continue
        labels, seg = segment_reported(vol, atlas, cfg)
        lab = np.asarray(labels.labels)
        print(f"{name}, 2 mm, adult's marrow, 3 %, {contrast} contrast, atlas {atlas.name}:",
              {k: round(v, 3) for k, v in sa.dice_per_tissue(lab, truth).items()})
        conf = np.zeros((5, 5), int)
        np.add.at(conf, (truth.ravel(), lab.ravel()), 1)
        print("confusion (rows truth, columns labels; background, brain, CSF, skull, scalp):\n", conf)
        depth = ndimage.distance_transform_edt(~np.isin(truth, (1, 2)), sampling=2.0)
        skull, wrong = truth == 3, (lab == 3) & (truth == 4)
        for lo, hi in BANDS_MM:
            band = (depth > lo) & (depth <= hi)
            print(f"{lo}-{hi} mm from the intracranial space: true skull {int((skull & band).sum())} labelled "
                  f"{np.bincount(lab[skull & band], minlength=5).tolist()}; true scalp labelled skull "
                  f"{int((wrong & band).sum())} of {int(((truth == 4) & band).sum())}")
        unmod = unmodelled_on_grid(vol, atlas, seg.transform, cfg)
        if unmod is None:
            print(f"the {atlas.name} atlas models bone everywhere")
        else:
            unmod = np.asarray(unmod) > 0.5
            print(f"where the atlas models no bone: {int(unmod.sum())} voxels, true skull {int((skull & unmod).sum())}, "
                  f"true scalp labelled skull {int((wrong & unmod).sum())}")
        print("report:", {k: seg.registration[k] for k in ("unmodelled", "marrow_inside_skull", "layer_split")
                          if k in seg.registration})
        return
    raise SystemExit(f"no scan of {args.anatomy}")


if __name__ == "__main__":
    main()
