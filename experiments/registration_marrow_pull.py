"""Does the scan's marrow move the registered atlas? The held-out atlas's skull prior on a head rendered with
no marrow, a child's marrow and an adult's (fat-bright) marrow.

For each real head, the held-out atlas of `segmentation_accuracy.py` (the ANTs head: mni152; the MNI152 head:
an atlas built from the ANTs head) is registered (`segment.register_atlas`, the default settings) to the head
rendered as T1 at 2 mm, 8 % noise, bias +-20 %, seed 0, three ways: the skull one dark tissue
(`templates.render` without a diploe), with a child's marrow (`with_diploe`, the default contrast's "diploe",
0.45 of white matter) and with an adult's (`templates.fatty_marrow`: as bright as fat). The atlas templates
have no marrow. Reported: the registered CSF / skull / scalp priors, mean over the true marrow voxels, and the
Dice of the priors' argmax against the truth (no EM: what the atlas alone says). If the skull prior at the
marrow falls when the marrow is bright, the registration has moved the atlas's skull inward: it matched the
scan's bright marrow to the template's bright scalp.

    python experiments/registration_marrow_pull.py [--out experiments/results/registration_marrow_pull.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from segmentation_accuracy import HEADS, _write_atomic, dice  # noqa: E402

from jaxhead.segmentation import SegmentConfig, default_atlas  # noqa: E402
from jaxhead.segmentation.atlas import anatomy_atlas  # noqa: E402
from jaxhead.segmentation.segment import register_atlas  # noqa: E402
from jaxhead.segmentation.templates import ants_anatomy, fatty_marrow, mni152_anatomy, render, with_diploe  # noqa: E402
from jaxhead.tissue import Tissue  # noqa: E402

VOXEL_MM, NOISE, BIAS = 2.0, 0.08, 0.2


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--heads", default=str(HEADS))
    p.add_argument("--out", default=None, help="markdown file to write (atomically)")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    ants = ants_anatomy(Path(args.heads))
    cases = (("ants19.5", ants, default_atlas("mri", voxel_mm=2.0)),
             ("mni152+fsaverage", mni152_anatomy(), anatomy_atlas(ants, "mri", voxel_mm=2.0, name="ants19.5")))
    lines = ["| anatomy (atlas) | marrow | prior at the marrow: CSF / skull / scalp "
             "| prior argmax Dice: brain / CSF / skull / scalp |", "|---|---|---|---|"]
    for name, anat, atlas in cases:
        plain, marrowed = anat.resampled(VOXEL_MM), with_diploe(anat).resampled(VOXEL_MM)
        truth = marrowed.labels().labels
        marrow = (truth == Tissue.SKULL) & (np.asarray(marrowed.diploe) > 0.5)
        for kind, a, contrast in (("none", plain, None), ("child's (0.45 of white matter)", marrowed, None),
                                  ("adult's (as bright as fat)", marrowed, fatty_marrow(None))):
            vol = render(a, "mri", contrast=contrast, noise=NOISE, bias=BIAS, seed=0)
            _, priors = register_atlas(vol, atlas, SegmentConfig(modality="mri"))
            priors = np.asarray(priors)
            at = " / ".join(f"{priors[k][marrow].mean():.3f}" for k in (Tissue.CSF, Tissue.SKULL, Tissue.SCALP))
            arg = priors.argmax(0)
            ds = " / ".join(f"{dice(arg == k, truth == k):.3f}" for k in list(Tissue)[1:])
            lines.append(f"| {name} ({atlas.name}) | {kind} | {at} | {ds} |")
            print(lines[-1], flush=True)
    head = (f"The held-out atlas registered to a head with no, a child's and an adult's marrow (T1, {VOXEL_MM:g} mm, "
            f"{NOISE:.0%} noise; see the script's docstring). Run: {time.perf_counter() - t0:.0f} s wall, load average "
            f"{os.getloadavg()[0]:.1f} at the end.\n\n")
    command = " ".join(["python experiments/registration_marrow_pull.py", *(sys.argv[1:] if argv is None else argv)])
    head += f"Command: `{command}`\n"
    if args.out:
        _write_atomic(args.out, head + "\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
