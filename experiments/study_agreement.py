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

Second order (`taylor_terms`): e2 = ||dV - S d - 1/2 D2V[dx, dx]|| / ||dV|| per sample, dx the
morph's node displacement (linear in d, so D2V[dx, dx] = sd^2 D2V[dx_z, dx_z] from one
forward-over-forward pass per unit field z).

Distribution: what the first-order route predicts for a study is the RMS of rel_voltage_change,
sqrt(trace S C S^T) / ||V|| (`first_order_summary`); it is compared with the sampled RMS over
all samples of an sd (+d and -d), and with the RMS of S d over the same fields (which separates
the Monte Carlo scatter of a few fields from the nonlinearity).

Run: PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python experiments/study_agreement.py
     [--head phantom|mni152|ants] [--voxel-mm 4] [--tissue csf] [--seeds 4]
     [--amplitudes 0.5 0.25 0.1]
Writes experiments/results/study_agreement_<tissue>_<voxel>mm[_<head>].json.
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
from _real_heads import HEADS, head_model  # noqa: E402

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
    first_order_summary,
    load_reference,
    morph_nodes,
    morph_quality,
    prepare_reference,
    sample_grf,
    study_config_from_dict,
    taylor_terms,
)
from jaxhead.study.config import ReferenceConfig  # noqa: E402

RESULTS = Path(__file__).parent / "results"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--head", default="phantom", choices=["phantom", *HEADS],
                    help="phantom: the study's own reference head; else a real anatomy "
                         "(experiments/_real_heads.py)")
    ap.add_argument("--n-elec", type=int, default=16)
    ap.add_argument("--ants-dir", default=str(Path(__file__).parents[1] / ".." / "shared" / "data"
                                              / "heads"))
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
    tag = (f"{args.voxel_mm:g}mm" + (f"_edge{args.edge_scale:g}" if args.edge_scale != 1 else "")
           + (f"_{args.head}" if args.head != "phantom" else ""))
    out = Path(args.out or f"runs/study_agreement_{tag}")
    cfg = study_config_from_dict({
        "name": "agreement", "out_dir": str(out),
        "reference": {"source": "phantom", "voxel_mm": args.voxel_mm, "n_elec": args.n_elec,
                      "sigma_s_m": {"brain": 0.3, "csf": 1.79, "skull": 0.018, "scalp": 0.44}},
        "perturbations": [{"kind": "grf", "tissue": args.tissue, "amplitude": 0.5}]})
    t0 = time.perf_counter()
    rc: ReferenceConfig = cfg.reference
    if args.head != "phantom":  # a real anatomy, meshed with the library's defaults
        mesh, el, _ = head_model(args.head, args)
    elif args.edge_scale == 1:  # the study's own reference head
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
    rows, t_second = [], []
    for k in range(args.seeds):
        z = sample_grf(pts, 1.0, args.correlation_mm, seed=1000 + k)[0]
        fd = (V(h * z) - V(-h * z)) / (2 * h)
        lin_unit = S @ z
        chain = float(np.linalg.norm(lin_unit - fd) / np.linalg.norm(fd))
        t2 = time.perf_counter()
        _, d2_unit = taylor_terms(model, sigma, prot, np.asarray(morph_nodes(morph, {args.tissue: z}))
                                  - mesh.nodes)
        t_second.append(time.perf_counter() - t2)
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
                 "second_order_error": float(np.linalg.norm(dp - lin - a**2 / 2 * d2_unit) / n),
                 "second_order_error_minus_d": float(np.linalg.norm(dm + lin - a**2 / 2 * d2_unit)
                                                     / np.linalg.norm(dm)),
                 "rel_voltage_change_minus_d": float(np.linalg.norm(dm) / np.linalg.norm(v0)),
                 "rel_first_order_change": float(np.linalg.norm(lin) / np.linalg.norm(v0)),
                 "chain_error": chain}
            rows.append(r)
            print(json.dumps(r), flush=True)
    summary = {}
    for a in args.amplitudes:
        e = np.array([r["error"] for r in rows if r["sd_mm"] == a]
                     + [r["error_minus_d"] for r in rows if r["sd_mm"] == a])
        e2 = np.array([r["second_order_error"] for r in rows if r["sd_mm"] == a]
                      + [r["second_order_error_minus_d"] for r in rows if r["sd_mm"] == a])
        rel = np.array([r["rel_voltage_change"] for r in rows if r["sd_mm"] == a]
                       + [r["rel_voltage_change_minus_d"] for r in rows if r["sd_mm"] == a])
        rel1 = np.array([r["rel_first_order_change"] for r in rows if r["sd_mm"] == a])
        fo = first_order_summary(S, pts, a, args.correlation_mm, v0, np.ones_like(v0))
        summary[f"{a:g}"] = {"n": int(e.size), "max_error": float(e.max()),
                             "mean_error": float(e.mean()),
                             "max_second_order_error": float(e2.max()),
                             "mean_second_order_error": float(e2.mean()),
                             "first_order_rms_rel_voltage_change": fo["rms_rel_voltage_change"],
                             "sampled_rms_rel_voltage_change": float(np.sqrt(np.mean(rel**2))),
                             "rms_ratio_sampled_over_first_order": float(
                                 np.sqrt(np.mean(rel**2)) / fo["rms_rel_voltage_change"]),
                             "effective_dof": fo["effective_dof"],
                             "rms_ratio_sampling_sd_fields": float(
                                 np.sqrt(1 / (2 * rel1.size * fo["effective_dof"]))),
                             "rms_ratio_sampled_over_sampled_first_order": float(
                                 np.sqrt(np.mean(rel**2)) / np.sqrt(np.mean(rel1**2))),
                             "max_even_part": max(r["even_part"] for r in rows if r["sd_mm"] == a),
                             "max_odd_remainder": max(r["odd_remainder"] for r in rows
                                                      if r["sd_mm"] == a)}
    res = {"measure": "per sample ||dV - S d|| / ||dV|| (dV sampled, S d first order), both +d "
                      "and -d counted as samples",
           "second_order_measure": "per sample ||dV - S d - 1/2 D2V[dx, dx]|| / ||dV||",
           "rms_measure": "sqrt(mean rel_voltage_change^2) over the +d and -d samples vs the "
                          "first-order sqrt(trace S C S^T) / ||V||; and vs the RMS of ||S d|| / "
                          "||V|| over the same fields (Monte Carlo scatter removed)",
           "head": (f"phantom seed 0, {args.voxel_mm:g} mm voxels, {mesh.n_tets} tets "
                    f"(default tet edges x {args.edge_scale:g})" if args.head == "phantom" else
                    f"{args.head}, {args.voxel_mm:g} mm voxels, {mesh.n_tets} tets, "
                    f"{mesh.n_nodes} nodes"),
           "n_elec": args.n_elec, "n_rows": int(v0.size),
           "interface": args.tissue, "correlation_mm": args.correlation_mm,
           "stiffening": args.stiffening, "assembly_offset": offset,
           "max_chain_error": max(r["chain_error"] for r in rows),
           "sensitivity_seconds": t_s,
           "second_order_seconds_per_field": float(np.mean(t_second[1:] or t_second)),
           "second_order_seconds_first_call": t_second[0],
           "load_average": os.getloadavg(), "wall_seconds": time.perf_counter() - t0,
           "by_sd_mm": summary, "samples": rows}
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"study_agreement_{args.tissue}_{tag}.json"
    path.write_text(json.dumps(res, indent=1))
    print(json.dumps({k: v for k, v in res.items() if k != "samples"}, indent=1))


if __name__ == "__main__":
    main()
