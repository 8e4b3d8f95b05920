"""Fitted conductivities when the model omits the CSF (issue 13, deliverable 7).

Fernandez-Corazza et al. 2018 (parametric EIT of the skull): a head model without the CSF layer
over-estimates the fitted skull conductivity by 20-30 %. Here, on each head:
- truth: the four-tissue head (brain, CSF, skull, scalp) meshed from its label map, voltages
  simulated at sigma = brain 0.3, CSF 1.79, skull 0.018 (or 0.01), scalp 0.44 S/m;
- model: the same mesh with every CSF tet (ventricles included) relabelled brain (the CSF
  "omitted", as a three-layer model treats it; same nodes, so no meshing difference enters);
- fit: brain, skull and scalp conductivities of the model to the noise-free truth data
  (`fit_conductivities`, weighted by 0.5 % noise floored at 3 % of the RMS standing voltage, as
  the study's measures), and again with the brain fixed at its true value (skull and scalp
  fitted, as parametric EIT of the skull often assumes the brain known); bias = fitted / true
  - 1. A control fits the four-tissue model to the same data (bias ~0: the fit is unbiased).

Heads: the MNI152-based head (`mni152_anatomy`: MNI152 brain and CSF in fsaverage's skull and
scalp) and the ANTs 19.5-year head (../shared/data/heads), both at 4 mm voxels; 32 electrodes
spread over the upper head; adjacent and opposite protocols.

Run: PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python experiments/csf_omitted.py
     [--voxel-mm 4] [--heads mni152 ants] [--ants-dir ../shared/data/heads]
Writes experiments/results/csf_omitted.json and .md.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxhead.fem import build_forward_model, simulate  # noqa: E402
from jaxhead.geometry import TetMesh  # noqa: E402
from jaxhead.inverse import fit_conductivities, noise_std  # noqa: E402
from jaxhead.protocol import adjacent, opposite  # noqa: E402
from jaxhead.tissue import Tissue  # noqa: E402
from _real_heads import add_head_arguments, head_model  # noqa: E402

RESULTS = Path(__file__).parent / "results"
SKULLS = (0.018, 0.01)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_head_arguments(ap)
    args = ap.parse_args()
    res = {"voxel_mm": args.voxel_mm, "n_elec": args.n_elec, "heads": {}}
    for name in args.heads:
        t0 = time.perf_counter()
        mesh, el, true_model = head_model(name, args)
        lab = np.where(mesh.labels == int(Tissue.CSF), int(Tissue.BRAIN), mesh.labels)
        no_csf = build_forward_model(TetMesh(mesh.nodes, mesh.tets, lab), el)
        vol = mesh.tet_volumes()
        head = {"n_tets": int(mesh.n_tets),
                "csf_ml": float(vol[mesh.labels == int(Tissue.CSF)].sum() / 1e3),
                "mesh_seconds": time.perf_counter() - t0, "fits": []}
        for pname, prot in (("adjacent", adjacent(args.n_elec)), ("opposite", opposite(args.n_elec))):
            for skull in SKULLS:
                sigma = np.array([0.3, 1.79, skull, 0.44])
                v = np.asarray(simulate(true_model, sigma, prot))
                sd = noise_std(v, 0.5, floor=0.03)
                row = {"protocol": pname, "sigma_true": sigma.tolist()}
                for tag, model, fit in (("csf_omitted", no_csf, ("brain", "skull", "scalp")),
                                        ("csf_omitted_brain_fixed", no_csf, ("skull", "scalp")),
                                        ("control_four_tissue", true_model,
                                         ("brain", "csf", "skull", "scalp"))):
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)
                        f = fit_conductivities(model, prot, v, init=sigma, fit=fit, noise_std=sd,
                                               throw=False)
                    row[tag] = {
                        "success": bool(f.success),
                        "bias_percent": {n: float(100 * (e / sigma[["brain", "csf", "skull", "scalp"]
                                                                  .index(n)] - 1))
                                         for n, e in zip(f.fitted, f.estimates)},
                        "std_error_percent": {n: float(100 * s / sigma[["brain", "csf", "skull",
                                                                          "scalp"].index(n)])
                                              for n, s in zip(f.fitted, f.std_error)},
                        "residual_norm": float(f.residual_norm)}
                head["fits"].append(row)
                print(name, json.dumps(row), flush=True)
        head["seconds"] = time.perf_counter() - t0
        res["heads"][name] = head
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "csf_omitted.json").write_text(json.dumps(res, indent=1))
    lines = ["# Fitted conductivities with the CSF omitted (experiments/csf_omitted.py)", "",
             f"{args.voxel_mm:g} mm voxels, {args.n_elec} electrodes, noise-free data from the "
             "four-tissue head; model = same mesh, CSF relabelled brain; bias = fitted / true - 1. "
             "Fernandez-Corazza et al. 2018: skull over-estimated by 20-30 %.", "",
             "| head | protocol | true skull S/m | skull bias % | brain bias % | scalp bias % | "
             "residual (noise units) | brain fixed: skull / scalp bias % | control skull bias % |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, h in res["heads"].items():
        for r in h["fits"]:
            b, c = r["csf_omitted"], r["control_four_tissue"]
            bf = r["csf_omitted_brain_fixed"]["bias_percent"]
            lines.append(f"| {name} ({h['n_tets']} tets, CSF {h['csf_ml']:.0f} ml) | {r['protocol']} | "
                         f"{r['sigma_true'][2]:g} | {b['bias_percent']['skull']:+.1f} | "
                         f"{b['bias_percent']['brain']:+.1f} | {b['bias_percent']['scalp']:+.1f} | "
                         f"{b['residual_norm']:.1f} | {bf['skull']:+.1f} / {bf['scalp']:+.1f} | "
                         f"{c['bias_percent']['skull']:+.2f} |")
    (RESULTS / "csf_omitted.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
