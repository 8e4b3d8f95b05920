"""Two runs of `segmentation_accuracy.py` compared scan by scan: what a change of the library did to each scan.

Rows are matched on (anatomy, atlas, modality, noise, contrast). For each scan the Dice per tissue of
both runs and their difference; then per row (anatomy, modality, noise) the minimum of each run against
issue 11's bars, and a count of the scans that moved by more than a threshold.

Usage:
    .venv/bin/python experiments/compare_tables.py OLD.json NEW.json [--moved 0.005] [--out FILE.md]

Prints Markdown (and writes it atomically to --out). A scan present in one run only is listed, not
compared; a refused scan (the table's `error`) counts as Dice 0, as in the table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

TISSUES = ("brain", "csf", "skull", "scalp")
BARS = {"mri": (0.93, 0.75, 0.85, 0.93), "ct": (0.93, 0.65, 0.90, 0.93)}
KEY = ("anatomy", "atlas", "modality", "noise", "contrast")


def load(path: str) -> dict[tuple, dict]:
    """{scan key: row} of a segmentation_accuracy.py JSON file ({"meta", "rows"}, or its partial file's list)."""
    with open(path) as f:
        rows = json.load(f)
    if isinstance(rows, dict) and "rows" in rows:
        rows = rows["rows"]
    if not isinstance(rows, list) or not all(isinstance(r, dict) and all(k in r for k in KEY) for r in rows):
        raise ValueError(f"{path}: not a segmentation_accuracy.py table (a JSON list of rows with {KEY}).")
    out = {}
    for r in rows:
        k = tuple(r[k] for k in KEY)
        if k in out:
            raise ValueError(f"{path}: scan {k} appears twice.")
        out[k] = r
    return out


def row_minima(run: dict[tuple, dict], keys=None) -> dict[tuple, tuple[list[float], int]]:
    """{row (anatomy, atlas, modality, noise): (its scans' minimum Dice per tissue, the number of scans)}, the rows in
    the order their first scan appears; `keys`: only these scans (default: every scan of `run`)."""
    keys = list(run) if keys is None else list(keys)
    rows: dict[tuple, list] = {}
    for k in keys:
        rows.setdefault(k[:4], []).append(k)
    return {r: ([min(run[k][t] for k in ks) for t in TISSUES], len(ks)) for r, ks in rows.items()}


def meets(minima, modality: str) -> bool:
    """Whether a row's minimum Dice per tissue meets issue 11's bars for `modality` ("mri" or "ct")."""
    return all(m >= bar for m, bar in zip(minima, BARS[modality]))


def _fmt(d) -> str:
    return " / ".join(f"{x:.3f}" for x in d)


def compare(old: dict[tuple, dict], new: dict[tuple, dict], moved: float = 0.005) -> str:
    """Markdown: per-scan table, per-row minima against the bars, and a summary line."""
    both = [k for k in old if k in new]
    lines = ["| anatomy (atlas) | modality | noise | contrast | old | new | change (max abs) |", "|---|---|---|---|---|---|---|"]
    n_moved, worst = 0, (0.0, None)
    for k in both:
        a, b = [old[k][t] for t in TISSUES], [new[k][t] for t in TISSUES]
        diff = [y - x for x, y in zip(a, b)]
        big = max(abs(d) for d in diff)
        n_moved += big > moved
        if big > abs(worst[0]):
            worst = (max(diff, key=abs), k)
        lines.append(f"| {k[0]} ({k[1]}) | {k[2]} | {k[3]:g} | {k[4]} | {_fmt(a)} | {_fmt(b)} | "
                     + " / ".join(f"{d:+.3f}" for d in diff) + f" ({big:.3f}) |")
    lines += ["", "| row | old minimum | meets | new minimum | meets |", "|---|---|---|---|---|"]
    minima = {name: row_minima(run, both) for name, run in (("old", old), ("new", new))}
    met = {"old": 0, "new": 0}
    for r, (_, n_scans) in minima["new"].items():
        cells = []
        for name in ("old", "new"):
            mins = minima[name][r][0]
            ok = meets(mins, r[2])
            met[name] += ok
            cells += [_fmt(mins), "yes" if ok else "no"]
        lines.append(f"| {r[0]} ({r[1]}) {r[2]} {r[3]:g} ({n_scans} scans) | " + " | ".join(cells) + " |")
    only = sorted(set(old) ^ set(new), key=str)
    lines += ["", f"{len(both)} scans compared; {n_moved} moved by more than {moved:g} in some tissue; "
              f"largest change {worst[0]:+.3f} ({worst[1]}); rows meeting every bar: {met['old']} -> {met['new']} "
              f"of {len(minima['new'])}."]
    if only:
        lines.append("In one run only (not compared): " + "; ".join(map(str, only)) + ".")
    return "\n".join(lines) + "\n"


def write_text_atomic(path: str, text: str) -> None:
    """Write `text` to `path` through a temporary file beside it, so a reader never sees half a page (the temporary
    file is removed if the write fails)."""
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(path)), suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("old")
    p.add_argument("new")
    p.add_argument("--moved", type=float, default=0.005, help="a scan 'moved' when a Dice changed by more than this")
    p.add_argument("--out", default=None, help="also write the Markdown here, atomically")
    args = p.parse_args(argv)
    text = compare(load(args.old), load(args.new), args.moved)
    sys.stdout.write(text)
    if args.out:
        write_text_atomic(args.out, text)


if __name__ == "__main__":
    main()
