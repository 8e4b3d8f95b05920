"""The demo's whole chain on the MNI152-based real head at 1 mm, cut at the neck.

1. Writes (no network) a T1-like MRI of `jaxhead.segmentation.templates.mni152_anatomy` (the ICBM
   2009a MNI152 brain in fsaverage's inner skull and scalp, 1 mm) and its true labels as NIfTI, at
   the paths of the config's [input] (configs/mni152_1mm.toml). nilearn's own MNI152 T1 is
   brain-extracted (no skull or scalp), so the scan is rendered from the anatomy's tissue fractions
   as experiments/segmentation_accuracy.py renders its test scans (`render`: partial volume,
   fat/muscle scalp texture, Rician noise, a smooth bias field; defaults: noise 0.03 of white
   matter, bias +-20 %, seed 0). The grid is the anatomy's own: its bottom plane cuts the neck (scalp
   on the border), as the field of view of a real head MRI does; the layers stage must close it.
2. Runs the config through `jaxhead.run.run_pipeline`, up to `--until` (the pipeline resumes: each
   call runs only the stages not yet done), so that each call can be one locked job.
3. Prints per-stage seconds, the atlas used, the segmentation's Dice against the true labels, the
   layers' field-of-view cut, the surface repairs, tets, Table 2 counts (outside the seed paper's
   limits), per-tissue mesh volume against the layered and the true label maps, tet-centroid label
   agreement, and the forward / inverse summaries. `--markdown PATH` also writes them as Markdown.

The default atlas ("mni152") is built from this same anatomy (blurred priors, noise-free template),
so the segmentation here is not held out: its Dice is an upper bound. `--heldout` instead segments
the scan with an atlas of the ANTs 19.5-year head (never this anatomy) and runs the chain from those
labels (layers .. inverse) in <out_dir>_ants_atlas. Results: experiments/results/mni152_chain.md.

    flock /tmp/jaxhead-cpu.lock env PYTHONPATH=$PWD OPENBLAS_NUM_THREADS=1 \\
        python experiments/mni152_chain.py --until segment     # then surfaces, quality, (all)
    ... python experiments/mni152_chain.py --heldout --until quality   # then --heldout (all)
    python experiments/mni152_chain.py [--heldout] --summary-only --markdown /tmp/figures.md  # figures only
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # entry point: float64 FEM, as the CLI

import numpy as np  # noqa: E402

from benchmarks.mesh import centroid_agreement, voxel_volume_errors  # noqa: E402
from experiments.hard_labels import nesting_violations  # noqa: E402
from experiments.segmentation_accuracy import HEADS  # noqa: E402
from jaxhead import io  # noqa: E402
from jaxhead.geometry.layers import euler_characteristic  # noqa: E402
from jaxhead.run import run_pipeline  # noqa: E402
from jaxhead.run.config import load_config  # noqa: E402
from jaxhead.segmentation import SegmentConfig, anatomy_atlas, dice_scores, segment_reported  # noqa: E402
from jaxhead.segmentation.templates import ants_anatomy, mni152_anatomy, render  # noqa: E402
from jaxhead.tissue import TISSUES  # noqa: E402

log = logging.getLogger("mni152_chain")


def write_scan(cfg, *, noise: float, bias: float, seed: int) -> dict:
    """Render the MRI of the MNI152-based head and write it and its true labels at [input]'s paths."""
    t = time.perf_counter()
    anat = mni152_anatomy()
    vol = render(anat, "mri", noise=noise, bias=bias, seed=seed)
    labels = anat.labels()
    for path in (cfg.input.path, cfg.input.labels_path):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    io.save_volume(vol, cfg.input.path)
    io.save_labels(labels, cfg.input.labels_path)
    lab = labels.labels
    border = {f"{'xyz'[ax]}{side}": np.bincount(np.take(lab, k, axis=ax).ravel(), minlength=5).tolist()
              for ax in range(3) for side, k in (("-", 0), ("+", -1))}
    z0 = float(anat.affine[2, 3])
    info = {"shape": list(lab.shape), "z_range_mm": [z0, z0 + lab.shape[2] - 1],
            "border_voxels_per_label": {k: v for k, v in border.items() if any(v[1:])},
            "lowest_skull_z_mm": z0 + float(np.nonzero((lab == 3).any((0, 1)))[0].min()),
            "noise": noise, "bias": bias, "seed": seed, "seconds": time.perf_counter() - t}
    Path(cfg.input.path).with_suffix("").with_suffix(".json").write_text(json.dumps(info, indent=1))
    log.info("wrote %s and %s: %s", cfg.input.path, cfg.input.labels_path, info)
    return info


def _done(root: Path, stage: str) -> dict | None:
    p = root / stage / "done.json"
    return json.loads(p.read_text()) if p.exists() else None


def heldout_labels(cfg) -> tuple[str, dict]:
    """Segment the scan with an atlas of the ANTs 19.5-year head (never this anatomy); write the
    labels beside the scan. Returns (path, Dice against the true labels)."""
    path = str(Path(cfg.input.path).parent / "mni152_seg_ants_atlas_1mm.nii.gz")
    t = time.perf_counter()
    atlas = anatomy_atlas(ants_anatomy(HEADS), "mri", voxel_mm=2.0, name="ants19.5")
    labels, _ = segment_reported(io.load_volume(cfg.input.path), atlas, SegmentConfig(modality="mri"))
    io.save_labels(labels, path)
    dice = dice_scores(labels, io.load_labels(cfg.input.labels_path))
    Path(path).with_suffix("").with_suffix(".json").write_text(json.dumps(
        {"atlas": "ants19.5", "dice_vs_truth": dice, "seconds": time.perf_counter() - t}, indent=1))
    return path, dice


def heldout_config(cfg, labels_path: str):
    """The chain from the held-out segmentation: layers .. inverse in <out_dir>_ants_atlas."""
    return dataclasses.replace(cfg, name=cfg.name + "_ants_atlas", out_dir=str(cfg.out_dir) + "_ants_atlas",
                               input=dataclasses.replace(cfg.input, labels_path=labels_path),
                               stages=tuple(s for s in cfg.stages if s != "segment"))


def _surface_euler(path: Path, tissue) -> int:
    s = io.load_surface(path, tissue)
    F = np.asarray(s.faces)
    E = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [0, 2]]]), 1), axis=0)
    return len(np.asarray(s.vertices)) - len(E) + len(F)


def summary(cfg, truth_path: str) -> list[str]:
    """Markdown lines: the figures the issue asks for, read from the run folder."""
    root = cfg.run_dir / "subject"
    out = [f"Run folder `{root}`.", "", "| stage | seconds |", "|---|---|"]
    done = {s: _done(root, s) for s in cfg.stages}
    for s, d in done.items():
        out.append(f"| {s} | {d['seconds']:.1f} |" if d else f"| {s} | not done |")
    total = sum(d["seconds"] for d in done.values() if d)
    out += [f"| total | {total:.1f} |", ""]
    scan_info = Path(cfg.input.path).with_suffix("").with_suffix(".json")
    if scan_info.exists():
        i = json.loads(scan_info.read_text())
        out.append(f"Scan: {i['shape']} voxels of 1 mm, z {i['z_range_mm'][0]:g} to {i['z_range_mm'][1]:g} mm "
                   f"(MNI152), lowest skull voxel at z = {i['lowest_skull_z_mm']:g} mm; labels on the border "
                   f"(background, brain, CSF, skull, scalp): {i['border_voxels_per_label']}; Rician noise "
                   f"{i['noise']:g}, bias {i['bias']:g}, seed {i['seed']}.")
    if done.get("segment"):
        s = done["segment"]["summary"]
        out.append(f"Atlas: `{s['atlas']}` (built from this same anatomy: not held out). Registration: "
                   + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                               for k, v in s["registration"].items() if not isinstance(v, (list, dict))) + ".")
        if "dice_vs_truth" in s:
            out.append("Dice vs the true labels: " + ", ".join(f"{k} {v:.3f}" for k, v in s["dice_vs_truth"].items())
                       + ".")
    if done.get("layers"):
        lay = io.load_labels(root / "layers" / "layers.nii.gz").labels
        out.append("Layered solids (tissue and all inside it), Euler characteristic (1 = a ball): " + ", ".join(
            f"{t.name.lower()} {euler_characteristic((lay >= 1) & (lay <= int(t)))}" for t in TISSUES) + ".")
    if done.get("surfaces"):
        out.append("Surfaces, Euler characteristic (2 = a sphere): " + ", ".join(
            f"{t.name.lower()} {_surface_euler(root / 'surfaces' / f'{t.name.lower()}.stl', t)}" for t in TISSUES)
            + ".")
    for stage in ("layers", "surfaces", "mesh"):
        rep = root / stage / "report.txt"
        if done.get(stage) and rep.exists():
            out += ["", f"{stage} report:", "", "```", rep.read_text().rstrip(), "```"]
    if done.get("quality"):
        out += ["", "Table 2 (quality/table2.txt):", "", "```", (root / "quality" / "table2.txt").read_text().rstrip(),
                "```"]
    if done.get("mesh"):
        mesh = io.load_mesh(root / "mesh" / "mesh.vtu")
        layers = io.load_labels(root / "layers" / "layers.nii.gz")
        truth = io.load_labels(truth_path)
        vols = mesh.tissue_volumes_mm3()
        e_lay, e_true = voxel_volume_errors(mesh, layers), voxel_volume_errors(mesh, truth)
        out += ["", f"Mesh: {mesh.n_tets} tets, {mesh.n_nodes} nodes.", "",
                "| tissue | mesh ml | vs layered voxels | vs true labels |", "|---|---|---|---|"]
        for t in TISSUES:
            out.append(f"| {t.name.lower()} | {vols[t] / 1e3:.1f} | {100 * e_lay[t]:+.1f} % | {100 * e_true[t]:+.1f} % |")
        out += ["", f"Tet-centroid label agreement: {centroid_agreement(mesh, layers):.4f} with the layered map, "
                f"{centroid_agreement(mesh, truth):.4f} with the true labels. Nesting violations (faces between "
                f"tissues that are not neighbours, outer faces not scalp): {nesting_violations(mesh)}."]
    if done.get("forward"):
        f = done["forward"]["summary"]
        out += ["", f"Forward: {f['n_elec']} electrodes, {f['n_rows']} measurements, voltages "
                f"{1e3 * f['volts_min']:.2f} to {1e3 * f['volts_max']:.2f} mV."]
    if done.get("inverse"):
        v = done["inverse"]["summary"]
        if "localisation_error_mm" in v:
            out.append(f"Inverse ({v['method']}, truncation {v['k']:g} by {v['rule']}, {v['n_cells']} cells): "
                       f"localisation error {v['localisation_error_mm']:.1f} mm, blob diameter {v['diameter_mm']:.0f} mm, "
                       f"volume ratio {v['volume_ratio']:.1f}.")
        if "fit_rel_error" in v:
            out.append("Fit of the four conductivities (relative error brain / CSF / skull / scalp): "
                       + " / ".join(f"{100 * e:+.2f} %" for e in v["fit_rel_error"])
                       + f", {v['fit_n_forward']} forward solves, converged {v['fit_converged']}.")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=str(ROOT / "configs" / "mni152_1mm.toml"))
    p.add_argument("--until", default=None, help="run the stages up to and including this one (default: all)")
    p.add_argument("--rewrite-scan", action="store_true", help="write the scan even if it exists")
    p.add_argument("--noise", type=float, default=0.03, help="Rician noise sd, fraction of white matter")
    p.add_argument("--bias", type=float, default=0.2, help="bias field, peak |log|")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--summary-only", action="store_true", help="only print the figures of the run folder")
    p.add_argument("--markdown", default=None, help="also write the figures to this Markdown file")
    p.add_argument("--heldout", action="store_true",
                   help="instead: segment the scan with an atlas of the ANTs head (not this anatomy) and run the "
                        "chain from those labels (layers .. inverse) in <out_dir>_ants_atlas")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for name in ("jax", "absl"):
        logging.getLogger(name).setLevel(logging.WARNING)
    os.chdir(ROOT)  # the config's paths are relative to the repository root
    cfg = load_config(args.config)
    if cfg.input.source != "file" or not cfg.input.labels_path:
        raise SystemExit(f"{args.config}: needs [input] source = \"file\" with `path` and `labels_path`.")
    if not args.summary_only and (args.rewrite_scan or not Path(cfg.input.path).exists()):
        write_scan(cfg, noise=args.noise, bias=args.bias, seed=args.seed)
    lines = []
    if args.heldout:
        seg_path = str(Path(cfg.input.path).parent / "mni152_seg_ants_atlas_1mm.nii.gz")
        if not args.summary_only and not Path(seg_path).exists():
            heldout_labels(cfg)
        info = json.loads(Path(seg_path).with_suffix("").with_suffix(".json").read_text())
        lines += [f"Held out: the scan segmented with an atlas of the ANTs 19.5-year head ({info['seconds']:.0f} s); "
                  "Dice vs the true labels: " + ", ".join(f"{k} {v:.3f}" for k, v in info["dice_vs_truth"].items())
                  + ". The chain below starts from these labels; volumes and agreement 'vs true labels' are "
                  "against the true labels.", ""]
        truth_path = cfg.input.labels_path
        cfg = heldout_config(cfg, seg_path)
    else:
        truth_path = cfg.input.labels_path
    if not args.summary_only:
        stages = list(cfg.stages)
        if args.until is not None:
            if args.until not in stages:
                raise SystemExit(f"--until {args.until!r}: not one of the config's stages {stages}.")
            stages = stages[:stages.index(args.until) + 1]
        run_pipeline(dataclasses.replace(cfg, stages=tuple(stages)), report=False)
    lines += summary(cfg, truth_path)
    print("\n".join(lines))
    if args.markdown:
        Path(args.markdown).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
