"""experiments/compare_tables.py: two accuracy tables matched scan by scan."""

import importlib.util
import json
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "compare_tables", Path(__file__).parents[1] / "experiments" / "compare_tables.py")
ct = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(ct)


def _row(anatomy, noise, contrast, dice, modality="mri"):
    return dict(anatomy=anatomy, atlas="a", modality=modality, noise=noise, contrast=contrast,
                **dict(zip(ct.TISSUES, dice)))


def _write(path, rows, meta=True):
    path.write_text(json.dumps(dict(meta={}, rows=rows) if meta else rows))
    return str(path)


def test_scans_matched_minima_against_the_bars(tmp_path):
    old = [_row("h", 0.03, "default", (0.95, 0.80, 0.90, 0.95)), _row("h", 0.03, "random 1", (0.95, 0.70, 0.90, 0.95)),
           _row("h", 0.08, "default", (0.95, 0.80, 0.90, 0.95))]
    new = [_row("h", 0.03, "random 1", (0.95, 0.76, 0.90, 0.95)), _row("h", 0.03, "default", (0.95, 0.80, 0.903, 0.95)),
           _row("g", 0.03, "default", (0.9, 0.9, 0.9, 0.9))]
    text = ct.compare(ct.load(_write(tmp_path / "o.json", old)), ct.load(_write(tmp_path / "n.json", new, meta=False)))
    # two scans in both (order of the rows in the files does not matter); only random 1 moved by > 0.005
    assert "2 scans compared; 1 moved by more than 0.005" in text
    assert "largest change +0.060" in text
    # the row's CSF minimum goes 0.70 (below the MRI bar 0.75) -> 0.76: the row now meets every bar
    assert "| 0.950 / 0.700 / 0.900 / 0.950 | no | 0.950 / 0.760 / 0.900 / 0.950 | yes |" in text
    assert "rows meeting every bar: 0 -> 1 of 1" in text
    assert "In one run only" in text and "'g'" in text and "0.08" in text


def test_bad_tables_are_named(tmp_path):
    with pytest.raises(ValueError, match="not a segmentation_accuracy.py table"):
        ct.load(_write(tmp_path / "x.json", [{"anatomy": "h"}]))
    dup = [_row("h", 0.03, "default", (1, 1, 1, 1))] * 2
    with pytest.raises(ValueError, match="appears twice"):
        ct.load(_write(tmp_path / "d.json", dup))
