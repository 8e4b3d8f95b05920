"""MRI `denoise` settings on the held-out 2 mm MRI scans (registrations cached): Dice per scan and minima per row.

Registers the 12 MRI scans of `segmentation_accuracy.py` at 2 mm once (phantom included; the cache of
`segmentation_capture_diagnosis.py --phantom`), then runs `classify` for each setting, a tuple
(name, SegmentConfig keywords, patch) where patch may set segment.EDGE_FACTOR, segment.DENOISE_STEPS
or {"noise": "neighbour"} (the MRI edge threshold from `denoise.noise_sd` instead of
`denoise.rayleigh_noise_sd`). Reproduces the full table's Dice per scan to the last digit.

Usage (experiments/results/segmentation_mri_noise.md):
    python experiments/segmentation_mri_noise.py "[('dn', {'denoise': True}, {}), \\
        ('dn old', {'denoise': True}, {'noise': 'neighbour'}), ('dn 10', {'denoise': True}, {'DENOISE_STEPS': 10})]" \\
        [--only "0.08"] [--confusion] --cache /tmp/mri_scans.pkl
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
import segmentation_capture_diagnosis as CD  # noqa: E402

import jaxhead.segmentation.segment  # noqa: E402, F401
from jaxhead.segmentation import SegmentConfig  # noqa: E402
from jaxhead.segmentation.denoise import noise_sd  # noqa: E402
from jaxhead.volume import Volume  # noqa: E402

S = sys.modules["jaxhead.segmentation.segment"]  # the module (the package exports a function of that name)
ORIGINAL = {k: getattr(S, k) for k in ("EDGE_FACTOR", "DENOISE_STEPS", "rayleigh_noise_sd")}


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("settings", help="a list of (name, SegmentConfig keywords, patch) tuples (literal)")
    ap.add_argument("--only", default="", help="scans whose 'anatomy noise contrast' contains this")
    ap.add_argument("--confusion", action="store_true", help="print the 5 x 5 confusion matrix per scan")
    ap.add_argument("--cache", default=None, help="pickle of the registered scans (written if missing)")
    args = ap.parse_args(argv)
    cases = [s for s in CD.scans(args.cache, phantom=True) if args.only in f"{s['anat']} {s['noise']} {s['contrast']}"]
    for name, kw, patch in ast.literal_eval(args.settings):
        for k, v in ORIGINAL.items():
            setattr(S, k, v)
        for k, v in patch.items():
            if k == "noise":
                if v != "neighbour":
                    raise ValueError(f"patch 'noise' must be 'neighbour', got {v!r}")
                S.rayleigh_noise_sd = noise_sd
            elif k in ("EDGE_FACTOR", "DENOISE_STEPS"):
                setattr(S, k, v)
            else:
                raise ValueError(f"unknown patch key {k!r}: EDGE_FACTOR, DENOISE_STEPS or noise")
        cfg = SegmentConfig(modality="mri", **kw)
        t0, mins = time.perf_counter(), {}
        for s in cases:
            t = s["truth"]
            post, *_ = S.classify(Volume(s["data"], s["affine"]), s["priors"], cfg, s["unm"])
            lab = post.argmax(0)
            d = CD.dice4(lab, t)
            key = f"{s['anat']} {s['noise']}"
            mins[key] = np.minimum(mins.get(key, np.ones(4)), d)
            print(f"  {name} | {key} {s['contrast']}: {np.round(d, 3).tolist()}", flush=True)
            if args.confusion:
                print("   confusion (rows: truth background, brain, CSF, skull, scalp):\n",
                      np.array([[((t == a) & (lab == b)).sum() for b in range(5)] for a in range(5)]))
        print(f"minimum {name}: " + "  ".join(f"{k} {'/'.join(f'{x:.3f}' for x in v)}" for k, v in mins.items()),
              f"({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
