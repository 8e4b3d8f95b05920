"""First-order vs sampled voltage changes of a morphed interface, sample by sample (issue 13).

The acceptance bar: for a smooth random normal displacement d of an interface (GRF, sd <= 0.5 mm)
the first-order prediction S d (S = dV/dd through the morph, `displacement_sensitivity`) and the
sampled change dV = V(x(d)) - V(x0) agree within 10 %, measured per sample as

    e = ||dV - S d|| / ||dV||      (Euclidean norms over all protocol rows).

This script separates the possible causes of a disagreement, per sample:
- chain: S d vs the directional derivative of the very map the sampled route evaluates,
  (V(x(h z)) - V(x(-h z))) / (2 h) with z = d / sd, h = 1e-3 mm (an error in S, in the morph's
  chain rule, or a morph map that differs between the routes shows here);
- offset: ||V(nodes = x0) - V()|| / ||V||, the two assembly paths at zero displacement (a
  reference-voltage mismatch would add a constant to every dV);
- nonlinearity: the even part (dV(d) + dV(-d)) / 2 (second order and up) and the odd remainder
  (dV(d) - dV(-d)) / 2 - S d (third order and up), each over ||dV||.
e is computed at several amplitudes on the same unit field z, so its scaling with the amplitude
shows its order (a first-order error does not shrink, a second-order one halves with the sd).

Run: PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python experiments/study_agreement.py
     [--voxel-mm 4] [--tissue csf] [--seeds 4] [--amplitudes 0.5 0.25 0.1]
Writes experiments/results/study_agreement_<tissue>_<voxel>mm.json.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

from jaxhead.electrodes import place_electrodes
from jaxhead.fem import build_forward_model, simulate
from jaxhead.geometry import (
    MeshConfig,
    SurfaceConfig,
    extract_surfaces,
    make_layers,
    tetrahedralize,
)
from jaxhead.phantom import make_head  # noqa: E402
from jaxhead.protocol import adjacent  # noqa: E402
from jaxhead.study import (  # noqa: E402
    build_morph,
    displacement_sensitivity,
    load_reference,
    morph_nodes,
    morph_quality,
    prepare_reference,
    sample_grf,
    study_config_from_dict,
)
from jaxhead.study.config import ReferenceConfig  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel-mm", type=float, default=4.0)
    ap.add_argument("--tissue", default="csf")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--amplitudes", type=float, nargs="+", default=[0.5, 0.25, 0.1])
    ap.add_argument("--correlation-mm", type=float, default=20.0)
    ap.add_argument("--stiffening", type=float, default=1.0)
    ap.add_argument("--edge-scale", type=float, default=1.0,
                    help="scale the default surface and tet edge lengths (refinement study)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    tag = f"{args.voxel_mm:g}mm" + (f"_edge{args.edge_scale:g}" if args.edge_scale != 1 else "")
    out = Path(args.out or f"runs/study_agreement_{tag}")
    cfg = study_config_from_dict({
        "name": "agreement", "out_dir": str(out),
        "reference": {"source": "phantom", "voxel_mm": args.voxel_mm, "n_elec": 16,
                      "sigma_s_m": {"brain": 0.3, "csf": 1.79, "skull": 0.018, "scalp": 0.44}},
        "perturbations": [{"kind": "grf", "tissue": args.tissue, "amplitude": 0.5}]})
    t0 = time.perf_counter()
    rc: ReferenceConfig = cfg.reference
    if args.edge_scale == 1:  # the study's own reference head
        ref_path = prepare_reference(json.loads(json.dumps(cfg.to_dict(), default=list)),
                                     str(out / "study" / "reference"))
        _, mesh, el = load_reference(ref_path)
    else:  # the same head with every surface's and tissue's target edge scaled
        _, labels = make_head(rc.modality, voxel_mm=rc.voxel_mm, seed=rc.seed)
        mc = MeshConfig(edge_mm={k: v * args.edge_scale for k, v in MeshConfig().edge_mm.items()})
        sc = SurfaceConfig(edge_mm={k: v * args.edge_scale
                                    for k, v in SurfaceConfig().edge_mm.items()})
        mesh = tetrahedralize(extract_surfaces(make_layers(labels), sc), mc)
        el = place_electrodes(mesh, rc.n_elec, radius_mm=rc.electrode_radius_mm,
                              contact_impedance_ohm_m2=rc.contact_impedance_ohm_m2)
    sigma, prot = rc.sigma(), adjacent(rc.n_elec, current_a=rc.current_a)
    model = build_forward_model(mesh, el)
    morph = build_morph(mesh, stiffening=args.stiffening)
    surf = morph.interface(args.tissue)
    print(f"reference: {mesh.n_tets} tets, {mesh.n_nodes} nodes, {surf.n_vertices} {args.tissue} "
          f"vertices ({time.perf_counter() - t0:.0f} s)", flush=True)
    f = eqx.filter_jit(lambda m, x: simulate(m, sigma, prot, nodes=x))
    V = lambda d: np.asarray(f(model, morph_nodes(morph, {args.tissue: d})))  # noqa: E731
    v_plain = np.asarray(simulate(model, sigma, prot))
    v0 = V(np.zeros(surf.n_vertices))
    offset = float(np.linalg.norm(v0 - v_plain) / np.linalg.norm(v_plain))
    t1 = time.perf_counter()
    S = displacement_sensitivity(model, morph, sigma, prot, tissues=[args.tissue])
    S = next(iter(S.values()))
    t_s = time.perf_counter() - t1
    print(f"sensitivity: {t_s:.0f} s; offset of the two assembly paths {offset:.2e}", flush=True)
    pts = surf.points(mesh.nodes)
    h = 1e-3
    rows = []
    for k in range(args.seeds):
        z = sample_grf(pts, 1.0, args.correlation_mm, seed=1000 + k)[0]
        fd = (V(h * z) - V(-h * z)) / (2 * h)
        lin_unit = S @ z
        chain = float(np.linalg.norm(lin_unit - fd) / np.linalg.norm(fd))
        for a in args.amplitudes:
            d = a * z
            q = morph_quality(morph, morph_nodes(morph, {args.tissue: d}), raise_on_inverted=False)
            dp, dm = V(d) - v0, V(-d) - v0
            lin = a * lin_unit
            n = np.linalg.norm(dp)
            r = {"seed": 1000 + k, "sd_mm": a, "max_abs_displacement_mm": float(np.abs(d).max()),
                 "n_inverted": q.n_inverted, "min_scaled_jacobian": q.min_scaled_jacobian,
                 "rel_voltage_change": float(n / np.linalg.norm(v0)),
                 "error": float(np.linalg.norm(dp - lin) / n),
                 "error_minus_d": float(np.linalg.norm(dm + lin) / np.linalg.norm(dm)),
                 "norm_ratio_first_order_over_sampled": float(np.linalg.norm(lin) / n),
                 "even_part": float(np.linalg.norm(dp + dm) / 2 / n),
                 "odd_remainder": float(np.linalg.norm((dp - dm) / 2 - lin) / n),
                 "chain_error": chain}
            rows.append(r)
            print(json.dumps(r), flush=True)
    summary = {}
    for a in args.amplitudes:
        e = np.array([r["error"] for r in rows if r["sd_mm"] == a]
                     + [r["error_minus_d"] for r in rows if r["sd_mm"] == a])
        summary[f"{a:g}"] = {"n": int(e.size), "max_error": float(e.max()),
                             "mean_error": float(e.mean()),
                             "max_even_part": max(r["even_part"] for r in rows if r["sd_mm"] == a),
                             "max_odd_remainder": max(r["odd_remainder"] for r in rows
                                                      if r["sd_mm"] == a)}
    res = {"measure": "per sample ||dV - S d|| / ||dV|| (dV sampled, S d first order), both +d "
                      "and -d counted as samples",
           "head": f"phantom seed 0, {args.voxel_mm:g} mm voxels, {mesh.n_tets} tets "
                   f"(default tet edges x {args.edge_scale:g})",
           "interface": args.tissue, "correlation_mm": args.correlation_mm,
           "stiffening": args.stiffening, "assembly_offset": offset,
           "max_chain_error": max(r["chain_error"] for r in rows),
           "sensitivity_seconds": t_s, "by_sd_mm": summary, "samples": rows}
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"study_agreement_{args.tissue}_{tag}.json"
    path.write_text(json.dumps(res, indent=1))
    print(json.dumps({k: v for k, v in res.items() if k != "samples"}, indent=1))


if __name__ == "__main__":
    main()
