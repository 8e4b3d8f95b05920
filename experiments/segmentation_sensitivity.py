"""Which segmentation errors matter for head EIT? Measured on two phantom anatomies.

Questions (issue 13, deliverable 7):
1. Which interface's errors change the voltages most? First-order RMS voltage change, in units of
   the 0.5 % measurement noise, of a smooth random normal displacement (sd 0.5 mm, correlation
   20 mm) of each interface (brain, CSF = inner skull, skull = outer skull, scalp), checked
   against sampled morphs of the same prior.
2. How large a displacement equals the measurement noise? To first order the change scales with
   the sd, so sd_noise = 0.5 mm / (RMS change over noise at 0.5 mm).
3. The fitted-skull bias when the CSF is omitted (CSF relabelled brain, re-meshed, fitted with
   the reference's four-tissue model; compare Fernandez-Corazza et al. 2018: +20-30 %).

Heads: the MNI152-based head is not available offline here, so two anatomies of the phantom
generator (seeds 0 and 1) at 4 mm stand in; the library's 2 mm default is in
configs/segmentation_sensitivity.toml. Results: experiments/results/segmentation_sensitivity.json
and .md. Run: PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python
experiments/segmentation_sensitivity.py [--seeds 0 1] [--voxel-mm 4] [--samples 2] [--workers 2]
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from jaxhead.study import run_study, study_config_from_dict  # noqa: E402

INTERFACES = ("brain", "csf", "skull", "scalp")
RESULTS = Path(__file__).parent / "results"


def config(seed, voxel_mm, samples, out):
    perts = [{"kind": "grf", "tissue": t, "amplitude": 0.5, "correlation_mm": 20.0,
              "samples": samples} for t in INTERFACES]
    perts.append({"kind": "csf_scale", "amplitude": 0.0, "samples": 1})
    return study_config_from_dict({
        "name": f"segsens-seed{seed}", "out_dir": str(out), "seed": seed,
        "reference": {"source": "phantom", "seed": seed, "voxel_mm": voxel_mm, "n_elec": 16},
        "measures": {"imaging": True, "fit": True},
        "perturbations": perts})


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--voxel-mm", type=float, default=4.0)
    ap.add_argument("--samples", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    heads = {}
    for seed in args.seeds:
        t0 = time.perf_counter()
        out = run_study(config(seed, args.voxel_mm, args.samples,
                               Path("runs") / f"segsens_seed{seed}"), workers=args.workers,
                        progress=False)
        s = json.loads((out / "summary.json").read_text())
        head = {"seconds": time.perf_counter() - t0, "interfaces": {}}
        for g in s["groups"]:
            if g["perturbation"] == "grf":
                fo = g.get("first_order", {})
                per_noise = fo.get("first_order_rms_change_over_noise")
                head["interfaces"][g["tissue"]] = {
                    "first_order_rms_change_over_noise_at_0.5mm": per_noise,
                    "sd_mm_equal_to_noise": 0.5 / per_noise if per_noise else None,
                    "first_order_rms_rel_voltage_change": fo.get("first_order_rms_rel_voltage_change"),
                    "sampled_rms_rel_voltage_change": fo.get("sampled_rms_rel_voltage_change"),
                    "per_sample_linearisation_error_max": fo.get("per_sample_linearisation_error_max"),
                    "agree_within_10_percent": fo.get("agree_within_10_percent"),
                    "n_failed": g["n_failed"],
                    "first_order_sigma_sd_percent": {k[len("sigma_sd_percent_"):]: v for k, v in fo.items()
                                                     if k.startswith("sigma_sd_percent_")},
                    "sampled_mean_sigma_bias_percent_skull":
                        g["measures"].get("sigma_bias_percent_skull", {}).get("mean"),
                }
            elif g["perturbation"] == "csf_scale":
                head["csf_omitted"] = {
                    "n_failed": g["n_failed"], "errors": g["errors"],
                    **{k: v["mean"] for k, v in g["measures"].items()
                       if k.startswith("sigma_bias_percent") or k in (
                           "rel_voltage_change", "voltage_change_over_noise",
                           "localisation_error_mm", "image_correlation")}}
        ranked = sorted(head["interfaces"], key=lambda t: -(
            head["interfaces"][t]["first_order_rms_change_over_noise_at_0.5mm"] or 0))
        head["interfaces_ranked"] = ranked
        heads[f"phantom_seed{seed}"] = head
        print(json.dumps({f"phantom_seed{seed}": head}, indent=1), flush=True)
    res = {"voxel_mm": args.voxel_mm, "samples_per_interface": args.samples,
           "prior": {"sd_mm": 0.5, "correlation_mm": 20.0}, "noise_percent": 0.5, "heads": heads}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "segmentation_sensitivity.json").write_text(json.dumps(res, indent=1))
    lines = ["# Segmentation sensitivity (experiments/segmentation_sensitivity.py)", "",
             f"Phantom heads at {args.voxel_mm} mm, 16 electrodes (adjacent), 0.5 % noise; GRF "
             "sd 0.5 mm, correlation 20 mm.", ""]
    for name, h in heads.items():
        lines += [f"## {name}", "", "| interface | RMS change / noise (first order) | sd equal to "
                  "noise (mm) | sampled / first-order RMS | max linearisation error |",
                  "|---|---|---|---|---|"]
        for t in h["interfaces_ranked"]:
            i = h["interfaces"][t]
            ratio = (i["sampled_rms_rel_voltage_change"] / i["first_order_rms_rel_voltage_change"]
                     if i["sampled_rms_rel_voltage_change"] and i["first_order_rms_rel_voltage_change"]
                     else float("nan"))
            lines.append(f"| {t} | {i['first_order_rms_change_over_noise_at_0.5mm']:.3g} | "
                         f"{i['sd_mm_equal_to_noise']:.3g} | {ratio:.3f} | "
                         f"{i['per_sample_linearisation_error_max']} |")
        c = h.get("csf_omitted", {})
        lines += ["", f"CSF omitted: fitted skull bias {c.get('sigma_bias_percent_skull')} %, "
                  f"brain {c.get('sigma_bias_percent_brain')} %, scalp "
                  f"{c.get('sigma_bias_percent_scalp')} % (failures: {c.get('errors')})", ""]
    (RESULTS / "segmentation_sensitivity.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
