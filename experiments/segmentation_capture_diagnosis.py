"""Where the held-out MRI's CSF goes (per voxel), what an oracle intensity model would reach, and what a setting changes.

Registers the 8 real-anatomy MRI scans of `segmentation_accuracy.py` once (ANTs head with the mni152
atlas, MNI152 head with the ANTs atlas; 2 mm; noise 3 and 8 %; default and random-1 contrast; cached
in --cache), then for each SegmentConfig setting runs `classify` and prints per scan: Dice (brain / CSF
/ skull / scalp), confusions, the CSF and skull Gaussians (mean / sd / weight, log intensity), and with
--detail, for the true CSF labelled skull (and the correct CSF and skull): their bias-corrected log
intensity, atlas CSF/skull prior, and the Gaussian of largest w_j N(y) (the likelihood's owner).
--oracle: Dice of mean-field posteriors (3 sweeps, relaxation as default) at one Gaussian per class
fitted to the truth labels (brain and scalp: two, split at the median), with MRF beta 0 and 0.4.
Prints the minimum Dice per anatomy and noise for each setting.

Usage (experiments/results/segmentation_mri_capture.md):
    python experiments/segmentation_capture_diagnosis.py "[{}, {'diploe_above_csf': True, 'gaussians': {'csf': 1}}]" \\
        [--detail] [--oracle] [--blur 1.5] [--cache /tmp/mri_scans.pkl]
`--blur s` blurs the registered CSF and skull priors by s voxels, keeping their sum per voxel.
"""

from __future__ import annotations

import argparse
import ast
import os
import pickle
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import segmentation_accuracy as SA  # noqa: E402

from jaxhead.segmentation import SegmentConfig, register_atlas  # noqa: E402
from jaxhead.segmentation.em import MixtureParams, bias_field, infer_posteriors  # noqa: E402
from jaxhead.segmentation.segment import _em_data, classify, unmodelled_on_grid  # noqa: E402
from jaxhead.volume import Volume  # noqa: E402


def scans(cache: str | None, phantom: bool = False):
    if cache and os.path.exists(cache):
        with open(cache, "rb") as f:
            return pickle.load(f)
    cfg0 = SegmentConfig(modality="mri")
    out = []
    for anat, atlas, noise, contrast, vol, truth in SA.cases("mri", 2.0, 2, Path(SA.HEADS)):
        if anat == "phantom" and not phantom:
            continue
        tr, priors = register_atlas(vol, atlas, cfg0)
        out.append(dict(anat=anat, noise=noise, contrast=contrast, data=np.asarray(vol.data), affine=vol.affine,
                        truth=truth, priors=np.asarray(priors), unm=unmodelled_on_grid(vol, atlas, tr, cfg0)))
    if cache:
        with open(cache, "wb") as f:
            pickle.dump(out, f)
    return out


def dice4(lab, t):
    return [2 * ((lab == k) & (t == k)).sum() / ((lab == k).sum() + (t == k).sum()) for k in range(1, 5)]


def blurred(pri, sigma):
    if not sigma:
        return pri
    both = pri[2] + pri[3]
    b2, b3 = (ndimage.gaussian_filter(pri[k], sigma) for k in (2, 3))
    out = pri.copy()
    out[2] = both * b2 / np.maximum(b2 + b3, 1e-9)
    out[3] = both * b3 / np.maximum(b2 + b3, 1e-9)
    return out


def detail(vol, s, t, lab, res, opts, coords):
    p, cc = res.params, np.array(opts.component_class)
    y = _em_data(vol, "mri") - np.asarray(bias_field(p.bias, coords, opts.bias_degree))
    pri = np.asarray(s["priors"], np.float64)
    pri = pri / pri.sum(0)
    for name, m in (("csf->skull", (t == 2) & (lab == 3)), ("csf ok", (t == 2) & (lab == 2)),
                    ("skull ok", (t == 3) & (lab == 3))):
        dens = np.stack([p.weights[i] * np.exp(-0.5 * (y[m] - p.means[i]) ** 2 / p.variances[i])
                         / np.sqrt(p.variances[i]) for i in range(len(cc))])
        own = dens.argmax(0)
        q = lambda a, ps=(10, 50, 90): np.percentile(a, ps).round(2).tolist()  # noqa: E731
        print(f"   {name} n={m.sum()}: y {q(y[m])} prior csf {q(pri[2][m])} skull {q(pri[3][m])}; owner "
              + str({int(i): int((own == i).sum()) for i in np.unique(own)}))


def oracle(vol, s, t, res, opts_default, coords):
    """Posteriors at the truth's own Gaussians (after the default fit's bias field)."""
    y = _em_data(vol, "mri") - np.asarray(bias_field(res.params.bias, coords, opts_default.bias_degree))
    cfg = SegmentConfig(modality="mri", gaussians={"background": 1, "brain": 2, "csf": 1, "skull": 1, "scalp": 2})
    o = cfg.em_options(1.0)
    cc = np.array(o.component_class)
    mu, var, w = [], [], []
    for k in range(5):
        v = y[t == k]
        parts = [v] if (cc == k).sum() == 1 else [v[v <= np.median(v)], v[v > np.median(v)]]
        for part in parts:
            mu.append(part.mean())
            var.append(part.var())
            w.append(1.0 / len(parts))
    print("   truth's Gaussians (mean, sd):", [(round(float(m), 2), round(float(np.sqrt(v)), 2)) for m, v in zip(mu, var)])
    params = MixtureParams(jnp.array(mu), jnp.array(var), jnp.array(w), jnp.zeros(0))
    for beta in (0.0, 0.4):
        o2 = o.__class__(**{**o.__dict__, "beta": beta, "bias_degree": 0})
        lab = np.asarray(infer_posteriors(jnp.asarray(y), jnp.asarray(s["priors"]), params, o2, 3)).argmax(0)
        print(f"   oracle beta {beta}: Dice {np.round(dice4(lab, t), 3).tolist()}")


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("settings", nargs="?", default="[{}]", help="a list of SegmentConfig keyword dicts (literal)")
    ap.add_argument("--detail", action="store_true")
    ap.add_argument("--oracle", action="store_true")
    ap.add_argument("--blur", type=float, default=0.0)
    ap.add_argument("--cache", default=None, help="pickle of the registered scans (written if missing)")
    ap.add_argument("--phantom", action="store_true", help="also the 4 phantom scans (when the cache is built)")
    args = ap.parse_args(argv)
    cases = scans(args.cache, args.phantom)
    for kw in ast.literal_eval(args.settings):
        cfg = SegmentConfig(modality="mri", **kw)
        t0, mins = time.perf_counter(), {}
        print("=== setting", kw, flush=True)
        for s in cases:
            vol, t = Volume(s["data"], s["affine"]), s["truth"]
            post, res, opts, coords = classify(vol, blurred(np.asarray(s["priors"], np.float64), args.blur), cfg,
                                               s["unm"])
            lab = post.argmax(0)
            d = dice4(lab, t)
            key = f"{s['anat']} {s['noise']}"
            mins[key] = np.minimum(mins.get(key, np.ones(4)), d)
            p, cc = res.params, np.array(opts.component_class)
            n = lambda a, b: int(((t == a) & (lab == b)).sum())  # noqa: E731
            print(f"{s['anat']} {s['noise']} {s['contrast']}: EM {int(res.n_iter)}, Dice {np.round(d, 3).tolist()}, "
                  f"csf->skull {n(2, 3)} skull->csf {n(3, 2)} skull->scalp {n(3, 4)} csf->brain {n(2, 1)} "
                  f"brain->csf {n(1, 2)}")
            for k in (2, 3):
                print(f"   class {k}: " + "; ".join(f"{p.means[i]:.2f}/{np.sqrt(p.variances[i]):.2f}/{p.weights[i]:.2f}"
                                                   for i in np.where(cc == k)[0]))
            if args.detail:
                detail(vol, s, t, lab, res, opts, coords)
            if args.oracle and not kw:
                oracle(vol, s, t, res, opts, coords)
        print("minimum Dice", {k: np.round(v, 3).tolist() for k, v in mins.items()},
              f"({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
