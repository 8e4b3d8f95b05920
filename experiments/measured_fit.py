"""A realistic measured-data fit (issue 15): 33 named electrodes, unknown contact impedances,
gain, reference offsets and bad channels, through a UCL-layout file.

The head is the 4 mm phantom (seed 0) meshed once (`--mesh`, built here when missing). Data:
33 electrodes at extended 10-10 positions (32 + the reference NFpz, as UCL's stroke dataset),
31 injection pairs, every electrode measured against the reference (the injecting ones included:
the only rows that see contact impedances), per-electrode contact impedances lognormal around
0.02 Ohm m^2 with a factor-2 geometric spread, a current gain of 1.10, a random offset per
injection, 0.5 % noise per channel and 5 % of the channels scaled by 1.2. The recording is
written as a UCL-layout JSON + MATLAB v7.3 file in mV, read back with `load_measurements`, and
fitted with gain, per-electrode contact impedances (factor-2 prior), free offsets, a Cauchy
loss and 5-sigma channel rejection. The gain makes the conductivities identifiable only up to
a common scale; CSF's prior (1.79 S/m +- 2 %, Baumann et al. 1997) anchors it.

Run: python experiments/measured_fit.py [--mesh /tmp/meas/head4.msh] [--seed 0 --name measured_fit]
Writes experiments/results/<name>.txt and .json (seed 0: measured_fit; seed 1: measured_fit_seed1).
"""

import argparse
import json
import os
import pathlib
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import h5py  # noqa: E402
import numpy as np  # noqa: E402

from jaxhead import make_head  # noqa: E402
from jaxhead.electrodes import place_electrodes  # noqa: E402
from jaxhead.fem import build_forward_model, simulate  # noqa: E402
from jaxhead.geometry import extract_surfaces, make_layers, tetrahedralize  # noqa: E402
from jaxhead.inverse.fit import fit_conductivities  # noqa: E402
from jaxhead.io import load_measurements, load_mesh, save_mesh  # noqa: E402
from jaxhead.protocol import Protocol, reference_protocol  # noqa: E402
from jaxhead.tissue import TISSUE_NAMES, default_sigma  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
#: UCL's 32 scalp electrodes at (extended) 10-10 positions, then the reference NFpz.
NAMES = ["Fp1", "Fp2", "F7", "F3", "Fz", "F4", "F8", "FC5", "FC1", "FC2", "FC6", "T7", "C3",
         "Cz", "C4", "T8", "CP5", "CP1", "CP2", "CP6", "P7", "P3", "Pz", "P4", "P8", "TP9",
         "TP10", "O1", "Oz", "O2", "I1", "I2", "NFpz"]
Z0 = 0.02  # Ohm m^2, jaxhead's default (McEwan et al. 2006)


def head_mesh(path: pathlib.Path):
    if not path.is_file():
        _, labels = make_head("mri", voxel_mm=4.0, seed=0)
        save_mesh(tetrahedralize(extract_surfaces(make_layers(labels))), path)
    return load_mesh(path)


def write_ucl(folder: pathlib.Path, prot: Protocol, volts_v, positions_mm, freqs):
    """UCL layout: settings JSON (1-based protocol, metres) + voltages (mV) in MATLAB v7.3."""
    folder.mkdir(parents=True, exist_ok=True)
    settings = {"Freq": list(freqs), "Protocol": (prot.rows + 1).tolist(),
                "ElectrodePosition": (positions_mm / 1000.0).tolist(),
                "ElectrodeNames": NAMES, "CurrentA": prot.current_a}
    (folder / "rec.json").write_text(json.dumps(settings))
    with h5py.File(folder / "rec.mat", "w", userblock_size=512) as f:
        # MATLAB stores (n_rows, n_freq) column-major: HDF5 sees (n_freq, n_rows)
        d = f.create_dataset("BV", data=np.atleast_2d(volts_v * 1e3))
        d.attrs["MATLAB_class"] = np.bytes_("double")
    with open(folder / "rec.mat", "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, written by jaxhead experiments/measured_fit.py".ljust(
            116) + b"\x00" * 8 + b"\x00\x02IM")
    return folder / "rec.json"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mesh", default="/tmp/meas/head4.msh")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--name", default="measured_fit", help="results file stem")
    args = ap.parse_args()
    t0 = time.time()
    mesh = head_mesh(pathlib.Path(args.mesh))
    rng = np.random.default_rng(args.seed)
    el = place_electrodes(mesh, NAMES, radius_mm=6.0, contact_impedance_ohm_m2=Z0)
    model = build_forward_model(mesh, el)
    n = len(NAMES)
    ref = n - 1
    inj = np.array([(i, (i + 11) % 32) for i in range(31)])
    prot = reference_protocol(n, ref, inj, include_injecting=True, current_a=100e-6)

    sigma_true = default_sigma() * np.array([1.08, 0.99, 1.15, 0.93])
    z_true = Z0 * np.exp(rng.normal(0.0, np.log(2.0), n))  # lognormal, factor-2 spread
    gain_true = 1.10
    v = np.asarray(simulate(model, sigma_true, prot, contact_impedance_ohm_m2=z_true))
    off_true = rng.normal(0.0, 0.3 * np.sqrt(np.mean(v**2)), prot.n_inj)
    clean = gain_true * v + off_true[prot.drive_index]
    noisy = clean + rng.standard_normal(v.shape) * 0.005 * np.abs(clean)
    bad = np.sort(rng.choice(prot.n_rows, int(round(0.05 * prot.n_rows)), replace=False))
    noisy[bad] *= 1.2

    rec = write_ucl(pathlib.Path(f"/tmp/meas/ucl_case{args.seed}"), prot, noisy, el.centres, [10.0])
    meas = load_measurements(rec)
    assert np.array_equal(meas.rows, prot.rows) and meas.electrode_names == tuple(NAMES)
    measured = meas.at(10.0)
    print(f"data ready ({time.time() - t0:.0f} s): {mesh.n_tets} tets, {prot.n_rows} rows, "
          f"{prot.n_inj} injections", flush=True)

    t1 = time.time()
    res = fit_conductivities(
        model, Protocol(meas.rows, meas.current_a), measured, init=default_sigma(),
        noise_std=0.005 * np.abs(measured), gain=True, priors={"csf": (1.79, 0.02)},
        contact_impedance="per_electrode", contact_prior=2.0, offsets="per_injection",
        loss="cauchy", reject_sigma=5.0)
    t_fit = time.time() - t1
    print(res.table(truth=sigma_true), flush=True)

    est = dict(zip(res.fitted, res.estimates))
    se = dict(zip(res.fitted, res.std_error))
    truth = {**dict(zip(TISSUE_NAMES, sigma_true)), "gain": gain_true,
             **{f"z:{nm}": z for nm, z in zip(NAMES, z_true)}}
    z_stat = {k: (est[k] - truth[k]) / se[k] for k in res.fitted}
    carrying = sorted(set(inj.ravel().tolist()))
    z_err = np.array([res.contact_impedance_ohm_m2[i] / z_true[i] - 1 for i in carrying])
    rejected = set(res.rejected.tolist())
    report = {
        "mesh_tets": int(mesh.n_tets), "rows": int(prot.n_rows), "injections": int(prot.n_inj),
        "fit_seconds": round(t_fit, 1), "steps": res.n_steps, "forward_solves": res.n_forward,
        "sigma_true": sigma_true.tolist(), "sigma_fit": res.sigma.tolist(),
        "sigma_rel_error": (res.sigma / sigma_true - 1).tolist(),
        "sigma_rel_se": [se[t] / est[t] for t in TISSUE_NAMES],
        "gain_true": gain_true, "gain_fit": res.gain,
        "ratio_to_csf_rel_error": ((res.sigma / res.sigma[1]) / (sigma_true / sigma_true[1])
                                   - 1).tolist(),
        "z_rel_error_current_carrying_max": float(np.max(np.abs(z_err))),
        "z_rel_error_current_carrying_median": float(np.median(np.abs(z_err))),
        "z_reference_rel_error": float(res.contact_impedance_ohm_m2[ref] / z_true[ref] - 1),
        "z_reference_rel_se": float(se[f"z:{NAMES[ref]}"] / est[f"z:{NAMES[ref]}"]),
        "corrupted": bad.tolist(), "rejected": sorted(rejected),
        "corrupted_missed": sorted(set(bad.tolist()) - rejected),
        "clean_rejected": sorted(rejected - set(bad.tolist())),
        "residual_scale": res.residual_scale,
        "max_abs_error_over_se": float(np.max(np.abs(list(z_stat.values())))),
        "fraction_within_3se": float(np.mean(np.abs(list(z_stat.values())) <= 3)),
        "fraction_within_2se": float(np.mean(np.abs(list(z_stat.values())) <= 2)),
        "error_over_se": {k: round(float(x), 3) for k, x in z_stat.items()},
    }
    OUT.mkdir(exist_ok=True)
    (OUT / f"{args.name}.json").write_text(json.dumps(report, indent=1))
    lines = [res.table(truth=sigma_true), "",
             f"mesh {mesh.n_tets} tets; {prot.n_rows} rows; fit {t_fit:.0f} s",
             f"gain true {gain_true}, fitted {res.gain:.4f}",
             "sigma rel error %: " + " ".join(f"{t} {100 * e:+.2f}" for t, e in
                                              zip(TISSUE_NAMES, report["sigma_rel_error"])),
             "sigma / sigma_csf rel error %: " + " ".join(
                 f"{t} {100 * e:+.2f}" for t, e in zip(TISSUE_NAMES,
                                                       report["ratio_to_csf_rel_error"])),
             f"contact impedance, current-carrying electrodes: max |error| "
             f"{100 * report['z_rel_error_current_carrying_max']:.1f} %, median "
             f"{100 * report['z_rel_error_current_carrying_median']:.1f} %",
             f"reference NFpz (never carries current): error "
             f"{100 * report['z_reference_rel_error']:+.1f} %, SE "
             f"{100 * report['z_reference_rel_se']:.0f} % (the prior)",
             f"corrupted {bad.size}, rejected {len(rejected)}, missed "
             f"{report['corrupted_missed']}, clean rejected {report['clean_rejected']}",
             f"|error| / SE: max {report['max_abs_error_over_se']:.2f}, within 3 SE "
             f"{100 * report['fraction_within_3se']:.0f} %, within 2 SE "
             f"{100 * report['fraction_within_2se']:.0f} % of {len(z_stat)} parameters"]
    (OUT / f"{args.name}.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[1:]))


if __name__ == "__main__":
    main()
