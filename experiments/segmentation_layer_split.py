"""The MRI `layer_split` step's settings on the held-out 2 mm MRI scans (registrations cached).

Registers the 12 MRI scans of `segmentation_accuracy.py` at 2 mm once (phantom included; the cache of
`segmentation_capture_diagnosis.py --phantom`), runs the first EM and the depth prior as `segment` does,
then the layer split once per setting, a (window_mm, width) pair that replaces LAYER_SPLIT_MM and
LAYER_SPLIT_WIDTH ("off": the depth prior's labels, as before the step; ("first", window_mm, width): the
split on the first EM's labels, without the depth prior). Prints Dice (brain / CSF /
skull / scalp) per scan and the minimum per row; at the defaults it reproduces the full table's Dice per
scan (`segmentation_accuracy.py --modalities mri`).

Usage (experiments/results/segmentation_layer_split.md):
    python experiments/segmentation_layer_split.py "['off', (6, 0.1), (4, 0.1), (8, 0.1), (12, 0.1), (6, 0.05), (6, 0.2)]" \\
        [--only "0.08"] --cache /tmp/mri_scans.pkl
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import segmentation_accuracy as SA  # noqa: E402
import segmentation_capture_diagnosis as CD  # noqa: E402

import jaxhead.segmentation.segment  # noqa: E402, F401
from jaxhead.segmentation import SegmentConfig, default_atlas  # noqa: E402
from jaxhead.segmentation.atlas import anatomy_atlas  # noqa: E402
from jaxhead.segmentation.templates import ants_anatomy  # noqa: E402
from jaxhead.volume import Volume  # noqa: E402

S = sys.modules["jaxhead.segmentation.segment"]  # the module (the package exports a function of that name)
DEFAULTS = (S.LAYER_SPLIT_MM, S.LAYER_SPLIT_WIDTH)


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("settings", help="a list of 'off' or (window_mm, width) pairs (literal)")
    ap.add_argument("--only", default="", help="scans whose 'anatomy noise contrast' contains this")
    ap.add_argument("--cache", default=None, help="pickle of the registered scans (written if missing)")
    args = ap.parse_args(argv)
    settings = ast.literal_eval(args.settings)
    cases = [s for s in CD.scans(args.cache, phantom=True) if args.only in f"{s['anat']} {s['noise']} {s['contrast']}"]
    atlases = {"mni152": default_atlas("mri", voxel_mm=2.0),
               "ants19.5": anatomy_atlas(ants_anatomy(Path(SA.HEADS)), "mri", voxel_mm=2.0, name="ants19.5")}
    cfg = SegmentConfig(modality="mri")
    mins, t0 = {}, time.perf_counter()
    for s in cases:
        atlas = atlases["ants19.5" if s["anat"].startswith("mni152") else "mni152"]
        vol = Volume(s["data"], s["affine"])
        first = S._classify_all(vol, s["priors"], cfg, s["unm"])
        pi = first[4]
        fit, _ = S._depth_prior(vol, atlas, s["priors"], s["unm"], pi, first[0], cfg)
        key = f"{s['anat']} {s['noise']}"
        for setting in settings:
            if setting == "off":
                lab, info = fit[0].argmax(0), ""
            else:
                base = first if setting[0] == "first" else fit
                S.LAYER_SPLIT_MM, S.LAYER_SPLIT_WIDTH = setting[-2:]
                new, summary = S._layer_split(vol, s["priors"], s["unm"], pi, base[:4], cfg)
                lab, info = new[0].argmax(0), f" ({summary['iterations']} iterations, {summary['seconds']} s)"
            S.LAYER_SPLIT_MM, S.LAYER_SPLIT_WIDTH = DEFAULTS
            d = np.asarray(CD.dice4(lab, s["truth"]))
            mins.setdefault(str(setting), {})[key] = np.minimum(mins.get(str(setting), {}).get(key, np.ones(4)), d)
            print(f"  {setting} | {key} {s['contrast']}: {np.round(d, 3).tolist()}{info}", flush=True)
    for name, m in mins.items():
        print(f"minimum {name}: " + "  ".join(f"{k} {'/'.join(f'{x:.3f}' for x in v)}" for k, v in m.items()))
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main(sys.argv[1:])
