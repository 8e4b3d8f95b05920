"""Where issue 11's accuracy bars stand: every scan condition's newest held-out table, on one page.

Each condition (modality, voxel size, the skull's marrow, a scanner's blur, the field of view) has had its table
rerun many times, under names that say what changed then. This reads the newest run of each on the code that is
the default now (CONDITIONS: the file and the session that ran it) and writes, per condition, how many rows (one
test anatomy at one noise level, the minimum over its scans) meet every bar, and the failing rows' minima with the
tissues that miss.

Usage:
    .venv/bin/python experiments/segmentation_status.py [--results experiments/results]
        [--out experiments/results/segmentation_status.md]

Prints Markdown and writes it atomically to --out. A condition whose file is missing is an error naming it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_tables import BARS, TISSUES, load, meets, row_minima, write_text_atomic  # noqa: E402

# (condition, table file stem under --results, the session that ran it on the code that is the default now).
# The tables not rerun since session 33 are those on which session 35's check does not fire (its share table,
# segmentation_unmodelled_runaway.md), so session 35's default leaves them as they were.
CONDITIONS = (
    ("MRI, no marrow, 2 mm (with the phantom family)", "segmentation_heldout_mri_s35", 35),
    ("MRI, no marrow, 1 mm (with the phantom family)", "segmentation_heldout_mri_1mm_s35", 35),
    ("MRI, no marrow, 1 mm, 1.2 mm PSF", "segmentation_s36_psf_mri_1mm", 36),
    ("MRI, child's marrow, 2 mm", "segmentation_s36_diploe_mri_2mm", 36),
    ("MRI, child's marrow, 1 mm", "segmentation_marrow_tables_diploe_mri_1mm", 33),
    ("MRI, child's marrow, 1 mm, neck cut (181 x 217 x 181)", "segmentation_s36_fov_diploe_mri_1mm", 36),
    ("MRI, child's marrow, 1 mm, 1.2 mm PSF", "segmentation_marrow_tables_psf_diploe_mri_1mm", 33),
    ("MRI, adult's marrow, 2 mm", "segmentation_s36_fatty_mri_2mm", 36),
    ("MRI, adult's marrow, 1 mm", "segmentation_marrow_tables_fatty_mri_1mm", 33),
    ("MRI, adult's marrow, 1 mm, neck cut (181 x 217 x 181)", "segmentation_marrow_tables_fov_fatty_mri_1mm", 33),
    ("MRI, adult's marrow, 1 mm, 1.2 mm PSF", "segmentation_runaway_psf_fatty_mri_1mm", 35),
    ("CT, 2 mm (with the phantom family)", "segmentation_heldout_ct_s34", 34),
    ("CT, 1 mm (with the phantom family)", "segmentation_heldout_ct_1mm_s34", 34),
)


def _cell(minima, modality: str) -> str:
    """b / c / sk / sc with the tissues below their bar in bold."""
    return " / ".join(f"**{m:.3f}**" if m < bar else f"{m:.3f}" for m, bar in zip(minima, BARS[modality]))


def status(results: Path) -> str:
    """The Markdown page (module docstring)."""
    missing = [stem for _, stem, _ in CONDITIONS if not (results / f"{stem}.json").is_file()]
    if missing:
        raise FileNotFoundError(f"segmentation_status: no table {', '.join(missing)} (.json) in {results}; run "
                                "experiments/segmentation_accuracy.py with the condition's options first.")
    lines = [
        "# Issue 11: every condition's newest held-out table (`python experiments/segmentation_status.py`)",
        "",
        "A row is one test anatomy at one noise level, the atlas built without it; its Dice is the minimum over its "
        "scans (contrasts, bias fields). Bars (minimum): MRI " + " / ".join(f"{b:g}" for b in BARS["mri"])
        + ", CT " + " / ".join(f"{b:g}" for b in BARS["ct"]) + f" ({' / '.join(TISSUES)}); a Dice below its "
        "bar is in bold.",
        "",
        "| condition | table (session) | rows meeting every bar | rows that fail: minimum Dice |",
        "|---|---|---|---|",
    ]
    total = met_all = 0
    by_anatomy: dict[str, list[int]] = {}
    for label, stem, session in CONDITIONS:
        rows = row_minima(load(str(results / f"{stem}.json")))
        failing = []
        met = 0
        for (anatomy, atlas, modality, noise), (minima, n) in rows.items():
            ok = meets(minima, modality)
            met += ok
            tally = by_anatomy.setdefault(f"{anatomy} ({modality.upper()})", [0, 0])
            tally[0] += ok
            tally[1] += 1
            if not ok:
                failing.append(f"{anatomy} {noise:g}: {_cell(minima, modality)}")
        total += len(rows)
        met_all += met
        lines.append(f"| {label} | `{stem}` ({session}) | {met} of {len(rows)} | {'; '.join(failing) or '-'} |")
    lines += ["", f"Rows meeting every bar: {met_all} of {total}, over {len(CONDITIONS)} conditions. By test anatomy: "
              + "; ".join(f"{a} {m} of {n}" for a, (m, n) in by_anatomy.items()) + "."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", default=str(Path(__file__).resolve().parent / "results"),
                   help="the folder of the tables (default: experiments/results)")
    p.add_argument("--out", default=None, help="also write the Markdown here, atomically")
    args = p.parse_args(argv)
    text = status(Path(args.results))
    sys.stdout.write(text)
    if args.out:
        write_text_atomic(args.out, text)


if __name__ == "__main__":
    main()
