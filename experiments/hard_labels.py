"""The hard-label corpus at 2 mm: which case needed which repair, layers -> surfaces.

Runs every case of ``tests/test_hard_labels.py`` (CSF thin or missing, skull on brain, a hole
through the skull, fragmented scalp, field-of-view cuts at the neck, skull base, vertex, face and
side, anisotropic voxels, the ANTs young-adult head, the demo's MRI segmentation) at 2 mm through
``make_layers_reported`` + ``extract_surfaces_reported`` with the library defaults, checks every
invariant the fast tests check (closed, manifold, sphere, no self-intersection, nested by winding
numbers, gap, volume), and does it twice: with the defaults and with ``tunnels="keep"`` (what the
surfaces had to repair before the tunnel rule existed). Writes
``experiments/results/hard_labels.{md,json}``.

    flock /tmp/jaxhead-cpu.lock python experiments/hard_labels.py [--vox 2] [--cases a,b]
"""

import argparse
import json
import logging
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from jaxhead.geometry.layers import LayerConfig  # noqa: E402
from jaxhead.geometry.surface import SurfaceConfig  # noqa: E402
from jaxhead.tissue import TISSUES, Tissue  # noqa: E402
from tests.test_hard_labels import CASES, check_case, solid_voxels  # noqa: E402


def run_one(name, labels, layer_cfg):
    t0 = time.perf_counter()
    row = {"case": name, "tunnels": layer_cfg.tunnels, "shape": list(labels.shape),
           "voxel_mm": [round(float(v), 3) for v in labels.voxel_mm]}
    try:
        layers, lrep, surfaces, srep = check_case(name, labels, SurfaceConfig(), layer_cfg)
    except (ValueError, AssertionError) as e:
        row.update(ok=False, error=f"{type(e).__name__}: {str(e)[:300]}",
                   seconds=time.perf_counter() - t0)
        return row
    vox_vol = abs(float(np.linalg.det(layers.affine[:3, :3])))
    row.update(
        ok=True,
        seconds=time.perf_counter() - t0,
        surfaces_s=srep.seconds,
        fov_cuts=[f"{c['face']} ({c['side']}, {c['tissue_voxels']} vox, pad {c['pad_voxels']})"
                  for c in lrep.fov_cuts],
        fov_voxels=lrep.n_changed("fov"),
        tunnel_voxels=lrep.n_changed("tunnels"),
        tunnels_plugged={t.name.lower(): n for t, n in lrep.tunnels_plugged.items() if n},
        genus_before={t.name.lower(): n for t, n in lrep.genus_before.items() if n},
        nesting_voxels=lrep.n_changed("nesting"),
        csf_volume_change=(lrep.volumes_after_mm3[Tissue.CSF] / lrep.volumes_before_mm3[Tissue.CSF] - 1),
        untangled_pairs={t.name.lower(): srep[t].untangled_pairs for t in TISSUES if srep[t].untangled_pairs},
        remesh_retries={t.name.lower(): srep[t].remesh_retries for t in TISSUES if srep[t].remesh_retries},
        gap_vertices_moved={t.name.lower(): srep[t].gap_vertices_moved for t in TISSUES
                            if srep[t].gap_vertices_moved},
        gap_rounds_max=max(srep[t].gap_rounds for t in TISSUES),
        holes_components={t.name.lower(): srep[t].components_dropped + srep[t].hole_faces_added
                          for t in TISSUES if srep[t].components_dropped + srep[t].hole_faces_added},
        volume_err_pct={t.name.lower(): round(100 * (srep[t].volume_mm3 / (solid_voxels(layers, t) * vox_vol) - 1), 2)
                        for t in TISSUES},
    )
    return row


def fmt(d):
    if isinstance(d, dict):
        return ", ".join(f"{k} {v}" for k, v in d.items()) or "-"
    if isinstance(d, list):
        return "; ".join(d) or "-"
    return str(d)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vox", type=float, default=2.0)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--tunnels", default="plug,keep", help="LayerConfig.tunnels values to run")
    ap.add_argument("--append", action="store_true",
                    help="merge into the existing JSON (rows of the same case and mode replaced)")
    ap.add_argument("--out", default=str(ROOT / "experiments" / "results" / "hard_labels"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    out = Path(args.out)
    rows = json.loads(out.with_suffix(".json").read_text()) if args.append and out.with_suffix(".json").exists() else []
    for name in args.cases.split(","):
        labels = CASES[name](args.vox)
        for mode in args.tunnels.split(","):
            row = run_one(name, labels, LayerConfig(tunnels=mode))
            rows = [r for r in rows if (r["case"], r["tunnels"]) != (name, mode)] + [row]
            print(json.dumps(row), flush=True)
    order = {n: i for i, n in enumerate(CASES)}
    rows.sort(key=lambda r: (order.get(r["case"], 99), r["tunnels"] != "plug"))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    lines = [
        f"# Hard label maps at {args.vox:g} mm: layers -> surfaces, repairs per case",
        "",
        f"`python experiments/hard_labels.py --vox {args.vox:g}` (cases: tests/test_hard_labels.py; "
        "library defaults; the demo segmentation is always 2 mm). `ok`: every invariant of the fast "
        "tests holds (closed, manifold, genus-0, no self-intersection, nested by winding number, "
        "gap >= min_gap_mm, volume within a quarter voxel times area). Rows with `tunnels=keep` "
        "switch the tunnel rule off, to show what the surfaces had to repair without it.",
        "",
        "| case | tunnels | ok | s | fov cut (face, side, tissue voxels, pad) | tunnels plugged (genus before) "
        "| untangled pairs | finer remeshes | gap vertices moved | CSF vol. change by layers | "
        "surface vs voxel volume % | error |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["ok"]:
            lines.append(
                f"| {r['case']} | {r['tunnels']} | yes | {r['seconds']:.1f} | {fmt(r['fov_cuts'])} | "
                f"{fmt(r['tunnels_plugged'])} ({fmt(r['genus_before'])}) | {fmt(r['untangled_pairs'])} | "
                f"{fmt(r['remesh_retries'])} | {fmt(r['gap_vertices_moved'])} | "
                f"{100 * r['csf_volume_change']:+.1f} % | {fmt(r['volume_err_pct'])} | |")
        else:
            lines.append(f"| {r['case']} | {r['tunnels']} | **no** | {r['seconds']:.1f} | | | | | | | | "
                         f"{r['error'].replace('|', '/')} |")
    n_ok = sum(r["ok"] for r in rows if r["tunnels"] == "plug")
    n = sum(r["tunnels"] == "plug" for r in rows)
    lines += ["", f"Defaults: {n_ok}/{n} cases pass every check."]
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
