"""CSF/skull priors by depth between brain and scalp (jaxhead.segmentation.depth_prior)."""

from __future__ import annotations

import numpy as np
import pytest
from shipped_heads import HEADS, needs_heads

from jaxhead.segmentation import SegmentConfig, segment_reported
from jaxhead.segmentation.segment import dice_scores
from jaxhead.segmentation.templates import ants_anatomy, render
from jaxhead.segmentation.depth_prior import csf_depth_profile, isotonic_decreasing, layer_depth, with_depth_profile
from jaxhead.tissue import Tissue

VOX = 1.0


def _radius(n=64):
    g = (np.arange(n) - (n - 1) / 2) * VOX
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    return np.sqrt(x**2 + y**2 + z**2)


def _shells(r, radii):
    """Labels of nested spheres: brain < r1 <= CSF < r2 <= skull < r3 <= scalp < r4, air beyond."""
    lab = np.zeros(r.shape, np.uint8)
    for tissue, lo, hi in zip((Tissue.BRAIN, Tissue.CSF, Tissue.SKULL, Tissue.SCALP), (0, *radii[:3]), radii):
        lab[(r >= lo) & (r < hi)] = tissue
    return lab


def _priors(lab):
    return np.stack([(lab == k).astype(np.float32) for k in range(5)])


def test_layer_depth_is_the_analytic_fraction_between_concentric_spheres():
    r = _radius()
    brain, scalp = r < 12, (r >= 24) & (r < 28)
    t = layer_depth(brain, scalp, (VOX,) * 3)
    band = (r >= 13) & (r < 23)
    exact = (r - 12) / (24 - 12)  # d_brain = r - 12, d_scalp = 24 - r
    # the EDT measures to voxel centres of the masks, so each distance is off by under a voxel
    assert np.abs(t[band] - exact[band]).max() < 1.5 / 12
    assert np.all(t[brain] == 0) and np.all(t[scalp] == 1)


def test_layer_depth_names_an_empty_mask():
    with pytest.raises(ValueError, match="`brain` mask is empty"):
        layer_depth(np.zeros((4, 4, 4), bool), np.ones((4, 4, 4), bool), (1, 1, 1))


def test_isotonic_decreasing_against_brute_force():
    rng = np.random.default_rng(0)
    for _ in range(20):
        v, w = rng.random(6), rng.random(6) + 0.1
        fit = isotonic_decreasing(v, w)
        assert np.all(np.diff(fit) <= 1e-12)
        # the weighted least-squares optimum: no non-increasing sequence on a grid of candidates beats it
        cost = float(np.sum(w * (fit - v) ** 2))
        cand = np.sort(rng.random((20000, 6)), axis=1)[:, ::-1]
        assert cost <= np.min(np.sum(w * (cand - v) ** 2, axis=1)) + 1e-12
        assert np.isclose(np.sum(w * fit), np.sum(w * v))  # pooling keeps the weighted mean
    assert np.allclose(isotonic_decreasing([3.0, 2.0, 1.0], [1, 1, 1]), [3, 2, 1])
    assert np.allclose(isotonic_decreasing([1.0, 3.0, 2.0], [1, 1, 1]), [2, 2, 2])


def test_profile_of_nested_shells_steps_at_the_csf_skull_depth():
    r = _radius()
    prof, mass = csf_depth_profile(_priors(_shells(r, (12, 15, 24, 28))), (VOX,) * 3)
    centres = (np.arange(len(prof)) + 0.5) / len(prof)
    step = (15 - 12) / (24 - 12)  # the CSF/skull boundary's depth, 0.25
    assert np.all(prof[(centres < step - 0.1) & (mass > 0)] > 0.9)
    assert np.all(prof[(centres > step + 0.1) & (centres < 0.9)] < 0.1)
    assert np.all(np.diff(prof) <= 0)


def test_depth_profile_moves_the_atlas_csf_to_the_scans_depth():
    """An atlas whose brain and CSF end 4 mm inside the scan's (its skull over the scan's CSF), with the
    scan's own depth profile: the depth prior puts the CSF back, and keeps each voxel's CSF + skull
    mass and the other classes."""
    r = _radius()
    scan = _shells(r, (12, 15, 24, 28))
    prof, _ = csf_depth_profile(_priors(_shells(r, (12, 15, 24, 28))), (VOX,) * 3)
    misplaced = _priors(_shells(r, (8, 11, 24, 28)))  # CSF at 8-11 mm: its skull over the scan's CSF
    out = with_depth_profile(misplaced, scan, (VOX,) * 3, prof)
    band = (scan == Tissue.CSF) | (scan == Tissue.SKULL)
    csf_before = misplaced[2][band] > misplaced[3][band]
    csf_after = out[2][band] > out[3][band]
    truth = scan[band] == Tissue.CSF

    def dice(a, b):
        return 2 * (a & b).sum() / (a.sum() + b.sum())

    assert dice(csf_before, truth) < 0.1 < 0.9 < dice(csf_after, truth)
    assert np.allclose(out[2] + out[3], misplaced[2] + misplaced[3])
    for k in (0, 1, 4):
        assert np.array_equal(out[k], misplaced[k])


def test_depth_prior_is_an_mri_option():
    with pytest.raises(ValueError, match="depth_prior"):
        SegmentConfig(modality="ct", depth_prior=True)
    with pytest.raises(ValueError, match="depth_prior"):
        SegmentConfig(modality="mri", depth_prior="yes")
    SegmentConfig(modality="mri", depth_prior=True)


@needs_heads
def test_segment_reports_the_depth_prior_and_the_layer_split(tmp_path, monkeypatch):
    """Both MRI steps end to end on a head the atlas never saw (the ANTs head, 4 mm MRI)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    ants = ants_anatomy(HEADS).resampled(4.0)
    vol = render(ants, "mri", noise=0.03, bias=0.2, seed=1)
    labels, seg = segment_reported(vol, None, SegmentConfig(modality="mri", atlas_voxel_mm=4.0, depth_prior=True))
    rep = seg.registration["depth_prior"]
    assert len(rep["profile"]) == 20 and np.all(np.diff(rep["profile"]) <= 0) and rep["profile"][0] > 0.5
    assert 0 < rep["relabelled_fraction"] < 0.1
    split = seg.registration["layer_split"]
    assert 1 <= split["iterations"] <= 20 and 0.1 < split["csf_fraction"] < 0.9, split
    assert 0 <= split["relabelled_fraction"] < 0.1 and split["window_mm"] == 6.0
    d = dice_scores(labels, ants.labels())
    assert d["brain"] > 0.9 and d["scalp"] > 0.85 and d["skull"] > 0.65, d


def test_a_first_segmentation_without_scalp_is_a_clear_error():
    from jaxhead.segmentation.atlas import Atlas
    from jaxhead.segmentation.segment import _depth_prior
    from jaxhead.volume import Volume

    r = _radius(16)
    lab = _shells(r, (3, 4, 6, 8))
    pri = _priors(lab)
    atlas = Atlas(lab.astype(np.float32), pri, np.eye(4), "mri")
    post = pri.copy()
    post[4] = 0  # a first EM that found no scalp
    with pytest.raises(ValueError, match="labelled no scalp voxel.*depth_prior = false"):
        _depth_prior(Volume(lab.astype(np.float64), np.eye(4)), atlas, pri, None, None, post, SegmentConfig())
