"""Segmentation accuracy on anatomy the atlas never saw (leave-one-anatomy-out): Dice per tissue.

Three independent anatomies, each rendered as MRI and CT (`jaxhead.segmentation.templates.render`:
partial-volume tissue intensities, fat/muscle scalp texture; MRI Rician noise and a smooth bias field
of up to +-20 %; tissue contrasts either the defaults or drawn at random from the literature ranges):

| test anatomy | atlas used (never contains it) |
|---|---|
| ANTs 19.5-year head (Richards et al.; brain2mesh examples), ../shared/data/heads | default `mni152` (MNI152 brain in fsaverage's inner skull and scalp) |
| jaxhead phantom family, seeds 0.. (their own MRI/CT generator, noise as given) | default `mni152` |
| the MNI152 + fsaverage head (`templates.mni152_anatomy`) | an atlas built the same way from the ANTs head |

Truth = the tissue filling most of each voxel at the evaluation voxel size (fractions block-averaged).

Usage:
    .venv/bin/python experiments/segmentation_accuracy.py [--voxel-mm 2] [--modalities mri ct] \\
        [--seeds 2] [--config '{"beta": 0.3}'] [--out experiments/results/segmentation_heldout]

Writes <out>.json (one row per scan) and <out>.md (per anatomy, modality, noise: mean and minimum
Dice), atomically. Bars (issue 11, minimum over subjects): MRI >= 0.93 / 0.75 / 0.85 / 0.93,
CT >= 0.93 / 0.65 / 0.90 / 0.93 (brain / CSF / skull / scalp).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # entry point: float64 available (segment uses float32)

import numpy as np  # noqa: E402

from jaxhead.phantom import make_head  # noqa: E402
from jaxhead.segmentation import SegmentConfig, default_atlas, segment_reported  # noqa: E402
from jaxhead.segmentation.atlas import anatomy_atlas  # noqa: E402
from jaxhead.segmentation.templates import (  # noqa: E402
    ants_anatomy, fatty_marrow, mni152_anatomy, on_scan_grid, random_contrast, render, shipped_heads_folder,
    with_diploe)
from jaxhead.tissue import TISSUES  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_tables import meets, write_text_atomic as _write_atomic  # noqa: E402  (issue 11's bars)

log = logging.getLogger("segmentation_accuracy")
HEADS = shipped_heads_folder()  # ../shared/data/heads beside the checkout, or $JAXHEAD_HEADS
#: noise levels: MRI Rician sd as a fraction of white matter; CT HU (phantom: its own units, see make_head)
NOISE = {"mri": (0.03, 0.08), "ct": (5.0, 20.0)}
PHANTOM_NOISE = {"mri": (0.03, 0.06), "ct": (10.0, 20.0)}


def dice(a: np.ndarray, b: np.ndarray) -> float:
    s = a.sum() + b.sum()
    return float(2 * (a & b).sum() / s) if s else 1.0


def dice_per_tissue(labels: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    return {t.name.lower(): dice(labels == t, truth == t) for t in TISSUES}


def cases(modality: str, voxel_mm: float, n_seeds: int, heads: Path, self_atlas: bool = False,
          diploe: bool = False, fatty: bool = False, fov_mm=None, psf_fwhm_mm: float = 0.0, phantom: bool = True):
    """(anatomy, atlas, noise, contrast, volume, truth) for every scan of one modality.

    self_atlas: the control that is *not* held out: each anatomy with an atlas built from itself (the
    phantom family with the phantom atlas, averaged subjects 1000..1007), so the registration and the
    priors are as right as this atlas model makes them; what the EM then misses is the intensity
    model's, and a bar it misses is out of reach of any better registration or atlas.
    diploe: render the two real heads' skulls with a diploe between compact tables (`templates.with_diploe`,
    on each source's own grid; the contrast's "diploe" value); the phantom family has its own. The atlases
    are unchanged (built without one).
    fatty: with `diploe`, MRI only: the real heads' marrow as bright as their fat, an adult's
    (`templates.fatty_marrow`); CT scans are unchanged.
    fov_mm: (3,) a scanner's field of view (mm; e.g. 181 217 181, the MNI152 grid's): the real heads are placed
    on it as a scan is (`templates.on_scan_grid`: centred, the top of the head 5 voxels below the grid's top,
    the neck and whatever else does not fit cut off), and the truth with them. None: each head's own grid (its
    whole neck). The phantom family keeps its own grid.
    psf_fwhm_mm: the real heads' scans blurred by a scanner's point-spread function of this FWHM (mm;
    `templates.render`'s `psf_fwhm_mm`, before bias and noise); 0: each voxel its box average alone. The phantom
    family's scans (its own generator) are not blurred.
    phantom: include the phantom family's scans.
    """
    ants = ants_anatomy(heads)
    mni = mni152_anatomy()
    atlas_mni = default_atlas(modality, voxel_mm=2.0)
    atlas_ants = anatomy_atlas(ants, modality, voxel_mm=2.0, name="ants19.5")
    atlas_phantom = default_atlas(modality, atlas="phantom", voxel_mm=2.0) if self_atlas else atlas_mni
    bias = 0.2 if modality == "mri" else 0.0
    pairs = ((ants, atlas_ants), (mni, atlas_mni)) if self_atlas else ((ants, atlas_mni), (mni, atlas_ants))
    for name, (anat, atlas) in zip(("ants19.5", "mni152+fsaverage"), pairs):
        a = (with_diploe(anat) if diploe else anat).resampled(voxel_mm)
        if fov_mm is not None:
            a = on_scan_grid(a, [int(round(f / voxel_mm)) for f in fov_mm])
        truth = a.labels().labels
        for noise in NOISE[modality]:
            for seed in range(n_seeds):
                contrast = None if seed == 0 else random_contrast(modality, np.random.default_rng(seed))
                if fatty and modality == "mri":
                    contrast = fatty_marrow(contrast)
                vol = render(a, modality, contrast=contrast, noise=noise, bias=bias, seed=seed, psf_fwhm_mm=psf_fwhm_mm)
                yield name, atlas, noise, "default" if seed == 0 else f"random {seed}", vol, truth
    for noise in PHANTOM_NOISE[modality] if phantom else ():
        for seed in range(n_seeds):
            vol, lab = make_head(modality, voxel_mm=voxel_mm, noise=noise, seed=seed)
            yield "phantom", atlas_phantom, noise, f"seed {seed}", vol, lab.labels


def run(args) -> list[dict]:
    rows = []
    for modality in args.modalities:
        cfg = SegmentConfig(modality=modality, **(json.loads(args.config) if getattr(args, "config", None) else {}))
        for anat, atlas, noise, contrast, vol, truth in cases(modality, args.voxel_mm, args.seeds, Path(args.heads),
                                                                getattr(args, "self_atlas", False),
                                                                getattr(args, "diploe", False),
                                                                getattr(args, "fatty_marrow", False),
                                                                getattr(args, "fov_mm", None),
                                                                getattr(args, "psf_mm", 0.0),
                                                                not getattr(args, "no_phantom", False)):
            t = time.perf_counter()
            try:
                labels, seg = segment_reported(vol, atlas, cfg)
            except ValueError as err:  # a refused scan (e.g. judged mis-oriented) counts as Dice 0
                log.warning("%s %s noise %g %s: segment refused it: %s", anat, modality, noise, contrast, err)
                d = {t_.name.lower(): 0.0 for t_ in TISSUES}
                rows.append(dict(anatomy=anat, atlas=atlas.name, modality=modality, noise=noise, contrast=contrast,
                                 seconds=time.perf_counter() - t, nmi=float("nan"), error=str(err)[:200], **d))
                continue
            d = dice_per_tissue(labels.labels, truth)
            rows.append(dict(anatomy=anat, atlas=atlas.name, modality=modality, noise=noise, contrast=contrast,
                             seconds=time.perf_counter() - t, nmi=seg.registration["nmi"], **d))
            if "warp_refinement" in seg.registration:  # SegmentConfig.refine_warp
                rows[-1]["warp_refinement"] = seg.registration["warp_refinement"]
            if "unmodelled" in seg.registration:  # the shares learnt where the atlas models no bone (and their check)
                rows[-1]["unmodelled"] = seg.registration["unmodelled"]
            log.info("%s %s noise %g %s (atlas %s): %s (%.0f s)", anat, modality, noise, contrast, atlas.name,
                     {k: round(v, 3) for k, v in d.items()}, rows[-1]["seconds"])
            if getattr(args, "partial", None):  # rows so far, so that an interrupted run leaves them
                _write_atomic(args.partial, json.dumps(rows, indent=1))
    return rows


def table(rows: list[dict]) -> str:
    names = [t.name.lower() for t in TISSUES]
    out = ["| anatomy (atlas) | modality | noise | scans | " + " | ".join(names) + " | meets bars |",
           "|---|---|---|---|" + "---|" * len(names) + "---|"]
    keys = []
    for r in rows:
        k = (r["anatomy"], r["atlas"], r["modality"], r["noise"])
        if k not in keys:
            keys.append(k)
    for k in keys:
        sel = [r for r in rows if (r["anatomy"], r["atlas"], r["modality"], r["noise"]) == k]
        means = [np.mean([r[n] for r in sel]) for n in names]
        mins = [np.min([r[n] for r in sel]) for n in names]
        ok = meets(mins, k[2])
        cells = [f"{m:.3f} (min {lo:.3f})" for m, lo in zip(means, mins)]
        out.append(f"| {k[0]} ({k[1]}) | {k[2]} | {k[3]:g} | {len(sel)} | " + " | ".join(cells) +
                   f" | {'yes' if ok else 'no'} |")
    return "\n".join(out)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--voxel-mm", type=float, default=2.0)
    p.add_argument("--seeds", type=int, default=2, help="contrasts per noise level (seed 0: default contrast)")
    p.add_argument("--modalities", nargs="+", default=["mri", "ct"], choices=["mri", "ct"])
    p.add_argument("--heads", default=str(HEADS), help="folder of the ANTs head (c1..c6 .jnii)")
    p.add_argument("--config", default=None,
                   help='SegmentConfig overrides as a JSON object, e.g. \'{"diploe_above_csf": true, "gaussians": {"csf": 1}}\'')
    p.add_argument("--self-atlas", action="store_true",
                   help="control, not held out: segment each anatomy with an atlas built from itself (the ceiling)")
    p.add_argument("--diploe", action="store_true",
                   help="the real heads' skulls with a diploe between compact tables (templates.with_diploe)")
    p.add_argument("--fatty-marrow", action="store_true",
                   help="with --diploe, MRI: the marrow as bright as fat, an adult's (templates.fatty_marrow)")
    p.add_argument("--fov-mm", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="the real heads on a scan's field of view (mm, e.g. 181 217 181): centred, the neck cut "
                        "(templates.on_scan_grid); default: each head's own grid")
    p.add_argument("--psf-mm", type=float, default=0.0,
                   help="the real heads' scans blurred by a scanner's point-spread function of this FWHM (mm; "
                        "templates.render's psf_fwhm_mm); default 0: each voxel its box average alone")
    p.add_argument("--no-phantom", action="store_true",
                   help="leave the phantom family's scans out (they do not take --psf-mm)")
    p.add_argument("--out", default=None, help="path stem: write <out>.json and <out>.md, atomically")
    args = p.parse_args(argv)
    if not (np.isfinite(args.psf_mm) and args.psf_mm >= 0):
        p.error(f"--psf-mm must be a finite number >= 0 (mm), got {args.psf_mm}")
    if args.fatty_marrow and not args.diploe:
        p.error("--fatty-marrow sets the marrow's intensity: it needs --diploe (the real heads have no marrow without it)")
    args.partial = (args.out[:-5] if args.out.endswith(".json") else args.out) + ".partial.json" if args.out else None
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for name in ("jax", "jaxhead"):
        logging.getLogger(name).setLevel(logging.WARNING)
    t0, c0 = time.perf_counter(), time.process_time()
    rows = run(args)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    command = " ".join(["python", "experiments/segmentation_accuracy.py", *(argv if argv is not None else sys.argv[1:])])
    head = (("CONTROL, NOT HELD OUT: Dice per tissue with each anatomy's own atlas (--self-atlas), mean"
             if args.self_atlas else "Dice per tissue on anatomy not in the atlas, mean") +
            " (and minimum) over the scans of each row, "
            + ("real heads rendered WITH A DIPLOE (--diploe), " if args.diploe else "")
            + ("MRI marrow AS BRIGHT AS FAT (--fatty-marrow; the phantom family keeps its own), "
               if args.fatty_marrow else "")
            + (f"real heads ON A {' x '.join(f'{f:g}' for f in args.fov_mm)} mm FIELD OF VIEW, NECK CUT (--fov-mm; "
               "the phantom family keeps its own grid), " if args.fov_mm else "")
            + (f"real heads BLURRED BY A {args.psf_mm:g} mm FWHM POINT-SPREAD FUNCTION (--psf-mm; the phantom "
               "family's scans are not), " if args.psf_mm else "")
            + ("NO PHANTOM ROWS (--no-phantom), " if args.no_phantom else "") +
            f"{args.voxel_mm:g} mm voxels, atlases 2 mm; noise: MRI Rician sd / white matter (phantom: its "
            f"own definition), CT HU; MRI bias field up to +-20 %. Bars (minimum): MRI 0.93/0.75/0.85/0.93, "
            f"CT 0.93/0.65/0.90/0.93 (brain/CSF/skull/scalp). Run: {wall:.0f} s wall, {cpu:.0f} s CPU, "
            f"load average {os.getloadavg()[0]:.1f} at the end.")
    print("\n" + head + "\n")
    print(table(rows))
    if args.out:
        stem = args.out[:-5] if args.out.endswith(".json") else args.out
        os.makedirs(os.path.dirname(os.path.abspath(stem)), exist_ok=True)
        meta = dict(voxel_mm=args.voxel_mm, seeds=args.seeds, modalities=args.modalities, psf_fwhm_mm=args.psf_mm,
                    wall_s=wall, cpu_s=cpu, command=command)
        _write_atomic(stem + ".json", json.dumps(dict(meta=meta, rows=rows), indent=1))
        _write_atomic(stem + ".md", f"{head}\n\nCommand: `{command}`\n\n{table(rows)}\n")
        if args.partial and os.path.exists(args.partial):
            os.unlink(args.partial)
    return 0


if __name__ == "__main__":
    sys.exit(main())
