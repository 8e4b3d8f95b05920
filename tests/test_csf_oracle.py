"""The oracle threshold of experiments/segmentation_csf_oracle.py: exact on separable data, never above the
best of every threshold."""

import importlib.util
from pathlib import Path

import numpy as np


def _oracle():
    spec = importlib.util.spec_from_file_location(
        "segmentation_csf_oracle", Path(__file__).resolve().parents[1] / "experiments" / "segmentation_csf_oracle.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.oracle_dice


def test_oracle_dice_separable_and_bounded():
    oracle_dice = _oracle()
    y = np.arange(100.0)
    assert oracle_dice(y, y < 30) == 1.0  # CSF darkest (CT, T1): a threshold below
    assert oracle_dice(y, y >= 50) == 1.0  # CSF brightest (T2): a threshold above
    rng = np.random.default_rng(0)
    csf = rng.random(500) < 0.3
    y = rng.normal(0.0, 1.0, 500) - 1.5 * csf
    # every threshold between consecutive values, either side, by hand
    cuts = np.concatenate([[y.min() - 1], (np.sort(y)[1:] + np.sort(y)[:-1]) / 2, [y.max() + 1]])
    best = max(2 * (p & csf).sum() / (p.sum() + csf.sum()) for c in cuts for p in (y < c, y > c))
    got = oracle_dice(y, csf)
    assert 0.5 < got <= best + 1e-12
    assert got > best - 0.02  # the 120 candidates are dense enough here
