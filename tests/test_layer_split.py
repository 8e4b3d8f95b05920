"""The CSF/skull change point in depth learnt from the scan (depth_prior.fit_layer_split, `layer_split`)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxhead.segmentation import SegmentConfig
from jaxhead.segmentation.depth_prior import (
    SPLIT_BINS,
    SPLIT_STEPS,
    SPLIT_TOL,
    _bin_index,
    _block,
    _log_ratio,
    density_log_ratio,
    fit_layer_split,
    largest_component,
    layer_depth,
    local_change_point,
    upsample,
    with_local_split,
)
from jaxhead.tissue import Tissue


def test_density_log_ratio_is_the_analytic_gaussian_log_ratio():
    rng = np.random.default_rng(0)
    a, b = rng.normal(0.0, 1.0, 400_000), rng.normal(1.0, 1.0, 400_000)
    y = np.concatenate([a, b])
    inner = np.arange(len(y)) < len(a)
    lo, hi = np.percentile(y, [0.5, 99.5])
    llr = density_log_ratio(y, inner, ~inner, lo, hi)
    exact = 0.5 - y  # log N(y; 0, 1) - log N(y; 1, 1)
    mid = (y > -1.0) & (y < 2.0)  # where both densities hold many samples
    assert np.abs(llr[mid] - exact[mid]).max() < 0.1
    assert np.all(density_log_ratio(np.ones(5), np.ones(5, bool), np.ones(5, bool), 1.0, 1.0) == 0)


def test_density_bins_count_as_numpy_histogram_of_the_clipped_values():
    """`fit_layer_split` bins the band's values once (`_bin_index`) and counts them per iteration; the counts
    are np.histogram's of the values clipped to [lo, hi], edges and values outside included."""
    rng = np.random.default_rng(3)
    lo, hi = -1.0, 2.0
    edges = np.linspace(lo, hi, SPLIT_BINS + 1)
    y = np.concatenate([rng.normal(0.5, 1.5, 50_000), edges, [lo - 5.0, hi + 5.0, np.nextafter(hi, 0.0)]])
    bins = _bin_index(y, lo, hi)
    for m in (rng.random(len(y)) < 0.5, np.ones(len(y), bool)):
        want, _ = np.histogram(np.clip(y[m], lo, hi), edges)
        np.testing.assert_array_equal(np.bincount(bins[m], minlength=SPLIT_BINS), want)
    inner = rng.random(len(y)) < 0.3
    np.testing.assert_array_equal(_log_ratio(bins, inner, ~inner), density_log_ratio(y, inner, ~inner, lo, hi))


def test_local_change_point_is_the_windowed_argmax_by_brute_force():
    """With one voxel per block the coarse grid is the voxel grid: every voxel's tau maximises the
    Gaussian-weighted sum of the band's log ratios below it (computed directly, no truncation)."""
    rng = np.random.default_rng(1)
    shape, vox, sigma = (9, 8, 7), (1.0, 1.0, 1.0), 1.5
    assert np.all(_block(vox, sigma) == 1)
    t = rng.random(shape)
    band = rng.random(shape) < 0.6
    llr = rng.normal(0.0, 1.0, shape)
    tau = local_change_point(t, band, llr, vox, sigma)
    taus = np.linspace(0.0, 1.0, SPLIT_STEPS)
    pts = np.stack(np.nonzero(band), 1).astype(float)
    tb, lb = t[band], llr[band]
    for x in np.ndindex(shape):
        w = np.exp(-0.5 * ((pts - np.asarray(x)) ** 2).sum(1) / sigma**2)
        score = np.array([(w * lb * (tb < tk)).sum() for tk in taus])
        k = int(np.argmin(np.abs(taus - tau[x])))
        assert score[k] >= score.max() - 1e-6 * np.abs(score).max()


def test_upsample_puts_block_centres_on_the_coarse_values():
    coarse = np.arange(24, dtype=float).reshape(2, 3, 4)
    vox, sigma = (1.0, 1.0, 1.0), 6.0  # blocks of 3 voxels: centres at 1, 4, 7, ...
    full = upsample(coarse, (6, 9, 12), vox, sigma)
    assert np.allclose(full[1::3, 1::3, 1::3], coarse)
    assert np.allclose(full[2, 4, 7], coarse[0, 1, 2] + (coarse[1, 1, 2] - coarse[0, 1, 2]) / 3)


def test_whole_grid_upsample_matches_interpolation_at_points():
    """The whole-grid path (separable weights) against the per-point path (scipy's map_coordinates), an
    independent implementation, on anisotropic voxels, ragged shapes, a one-block axis and the held ends."""
    rng = np.random.default_rng(4)
    for shape, vox in (((13, 8, 2), (1.0, 1.5, 3.0)), ((7, 11, 5), (2.0, 1.0, 1.0)), ((2, 8, 2), (1.0, 1.5, 3.0))):
        cshape = tuple(-(-n // k) for n, k in zip(shape, _block(vox, 6.0)))
        coarse = rng.random(cshape)
        points = tuple(np.indices(shape).reshape(3, -1))
        np.testing.assert_allclose(upsample(coarse, shape, vox, 6.0).ravel(),
                                   upsample(coarse, shape, vox, 6.0, points), atol=1e-12)


def _radius_angle(n, vox):
    g = (np.arange(n) - (n - 1) / 2) * vox
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2)
    return r, x / np.maximum(r, 1e-9)


def test_fit_layer_split_recovers_a_varying_csf_thickness_where_voxels_cannot():
    """Nested shells whose CSF/skull boundary moves with direction (CSF 1.5-6.5 mm thick), intensities of
    CSF and skull one sd apart (Gaussian, as a noisy T1's dark band): the change point learnt from the
    scan labels the band's CSF far better than the best per-voxel rule with the true densities."""
    vox = 1.0
    r, c = _radius_angle(72, vox)
    r_split = 17.0 + 2.5 * c  # the CSF/skull boundary: 14.5-19.5 mm
    brain, scalp = r < 13.0, (r >= 26.0) & (r < 30.0)
    band = (r >= 13.0) & (r < 26.0)
    csf = band & (r < r_split)
    rng = np.random.default_rng(2)
    y = np.where(csf, 0.30, 0.15) + rng.normal(0.0, 0.15, r.shape)
    t = layer_depth(brain, scalp, (vox,) * 3)
    tau, summary = fit_layer_split(y, t, band, (vox,) * 3, 6.0)
    found = band & (t < tau)

    def dice(a, b):
        return 2 * (a & b).sum() / (a.sum() + b.sum())

    voxelwise = band & (y > 0.225)  # equal sds: the maximum-likelihood threshold
    assert dice(voxelwise, csf) < 0.75
    assert dice(found, csf) > 0.93, (dice(found, csf), summary)
    t_split = (r_split - 13.0) / (26.0 - 13.0)  # the true change point in (exact) normalised depth
    assert np.median(np.abs(tau[band] - t_split[band])) < 0.05
    assert summary["iterations"] < 20 and summary["changed_fraction"] < SPLIT_TOL


def test_with_local_split_keeps_the_mass_and_steps_at_tau():
    rng = np.random.default_rng(3)
    pri = rng.random((5, 6, 5, 4)).astype(np.float32)
    pri /= pri.sum(0)
    t, tau = rng.random((6, 5, 4)), rng.random((6, 5, 4))
    out = with_local_split(pri, t, tau, 0.1)
    assert np.allclose(out[2] + out[3], pri[2] + pri[3], atol=1e-6)
    for k in (0, 1, 4):
        assert np.array_equal(out[k], pri[k])
    p = out[2] / (pri[2] + pri[3])
    assert np.allclose(p, 1 / (1 + np.exp((t - tau) / 0.1)), atol=1e-5)
    assert np.allclose(with_local_split(pri, tau, tau, 0.1)[2], 0.5 * (pri[2] + pri[3]), atol=1e-6)
    with pytest.raises(ValueError, match="`width` must be > 0"):
        with_local_split(pri, t, tau, 0.0)


def test_fit_layer_split_names_an_empty_band():
    with pytest.raises(ValueError, match="`band` mask is empty"):
        fit_layer_split(np.zeros((4, 4, 4)), np.zeros((4, 4, 4)), np.zeros((4, 4, 4), bool), (1, 1, 1), 6.0)


def test_layer_split_is_an_mri_option():
    with pytest.raises(ValueError, match="layer_split"):
        SegmentConfig(modality="ct", layer_split=True)
    with pytest.raises(ValueError, match="layer_split"):
        SegmentConfig(modality="mri", layer_split="yes")
    assert SegmentConfig(modality="mri").layer_split_on() and not SegmentConfig(modality="ct").layer_split_on()


def test_a_first_segmentation_without_brain_is_a_clear_error():
    from jaxhead.segmentation.segment import _layer_split
    from jaxhead.volume import Volume

    r, _ = _radius_angle(16, 1.0)
    lab = np.where(r < 4, Tissue.BRAIN, np.where(r < 6, Tissue.SKULL, np.where(r < 8, Tissue.SCALP, 0)))
    post = np.stack([(lab == k).astype(np.float32) for k in range(5)])
    post[1] = 0  # a first EM that found no brain
    with pytest.raises(ValueError, match="labelled no brain voxel.*layer_split = false"):
        _layer_split(Volume(lab.astype(np.float64) + 1, np.eye(4)), post, None, None, (post, None, None, None),
                     SegmentConfig())


def test_brain_outside_the_largest_piece_of_brain_and_csf_is_a_clear_error():
    """Brain only in a small piece apart from a larger CSF piece: no intracranial space to measure depth from."""
    from jaxhead.segmentation.segment import _layer_split
    from jaxhead.volume import Volume

    r, _ = _radius_angle(24, 1.0)
    lab = np.where(r < 6, Tissue.CSF, np.where(r < 8, Tissue.SKULL, np.where(r < 10, Tissue.SCALP, 0)))
    lab[0:2, 0:2, 0:2] = Tissue.BRAIN  # a corner piece, apart from the CSF ball
    post = np.stack([(lab == k).astype(np.float32) for k in range(5)])
    with pytest.raises(ValueError, match="holds no brain voxel.*layer_split = false"):
        _layer_split(Volume(lab.astype(np.float64) + 1, np.eye(4)), post, None, None, (post, None, None, None),
                     SegmentConfig())


def test_largest_component_keeps_the_biggest_face_connected_piece():
    m = np.zeros((9, 9, 9), bool)
    m[1:4, 1:4, 1:4] = True  # 27 voxels
    m[5:8, 5:8, 5:7] = True  # 18
    m[4, 4, 4] = True  # touches the first piece at a corner only: not face-connected
    out = largest_component(m)
    assert out.sum() == 27 and out[1:4, 1:4, 1:4].all() and not out[4, 4, 4] and not (out & ~m).any()
    assert not largest_component(np.zeros((3, 3, 3), bool)).any()
    np.testing.assert_array_equal(largest_component(m[:4, :4, :4]), m[:4, :4, :4])  # one piece: itself


def _shells_with_marrow(stray_brain: bool):
    """`test_scalp_split_finds_the_outer_table_where_marrow_and_fat_look_alike`'s head, with `stray_brain`: a few
    scalp voxels labelled brain, as fat as bright as white matter is on T1."""
    vox = 1.0
    r, c = _radius_angle(72, vox)
    r_out = 22.0 + 2.5 * c  # the skull's outer surface: 19.5-24.5 mm
    inner, air = r < 15.0, r >= 31.0
    skull = ~inner & (r < r_out)
    tables = skull & ((r < 16.5) | (r >= r_out - 1.5))
    rng = np.random.default_rng(4)
    y = np.where(inner, 0.5, np.where(tables, 0.15, 1.0)) + rng.normal(0.0, 0.1, r.shape)
    y[air] = rng.normal(0.0, 0.1, r.shape)[air]
    labels = np.where(r < 13.0, Tissue.BRAIN, np.where(inner, Tissue.CSF, np.where(r < 19.0, Tissue.SKULL,
                      np.where(air, Tissue.BACKGROUND, Tissue.SCALP))))
    if stray_brain:  # one voxel in ~150 of the scalp outside the true skull
        scalp = np.nonzero((labels == Tissue.SCALP) & ~skull)
        pick = rng.choice(len(scalp[0]), len(scalp[0]) // 150, replace=False)
        labels[tuple(a[pick] for a in scalp)] = Tissue.BRAIN
    return vox, r, inner, air, skull, y, labels


@pytest.mark.parametrize("stray_brain", [False, True])
def test_scalp_split_finds_the_outer_table_where_marrow_and_fat_look_alike(stray_brain):
    """`scalp_split` on nested shells: a skull of two dark tables around a marrow as bright as the scalp's fat,
    its outer surface moving with direction (4.5-9.5 mm thick), under a first segmentation that took a fixed
    4 mm skull. The skull/scalp change point learnt in depth between brain + CSF and the air puts the skull's
    share above one half on the true skull, which no intensity rule can (marrow and fat are one Gaussian), and
    the skull + scalp mass is only shared between them. With stray brain labels in the scalp the depth still
    starts at the intracranial compartment (`largest_component`): measured from every brain label, depth 0 sat in
    the scalp beside each stray and drew the change point into the fat (session 33)."""
    from jaxhead.segmentation.segment import _scalp_split

    vox, r, inner, air, skull, y, labels = _shells_with_marrow(stray_brain)
    priors = np.stack([np.where(labels == k, 0.9, 0.025) for k in range(5)]).astype(np.float32)
    out, summary = _scalp_split(labels, y, (vox,) * 3, priors)
    band = ~inner & ~air

    def dice(a, b):
        return 2 * (a & b).sum() / (a.sum() + b.sum())

    found = band & (out[Tissue.SKULL] > out[Tissue.SCALP])
    assert dice(labels == Tissue.SKULL, skull) < 0.8  # the first segmentation's fixed skull
    assert dice(found, skull) > 0.9, (dice(found, skull), summary)
    np.testing.assert_allclose(out[3] + out[4], priors[3] + priors[4], atol=1e-6)
    for k in (0, 1, 2):
        np.testing.assert_array_equal(out[k], priors[k])
    assert 0 < summary["skull_fraction"] < 1 and summary["iterations"] < 20


def test_scalp_split_is_an_mri_option_inside_the_layer_split():
    assert SegmentConfig(modality="mri", scalp_split=True).scalp_split_on()
    assert not SegmentConfig(modality="mri").scalp_split_on() and not SegmentConfig(modality="ct").scalp_split_on()
    assert not SegmentConfig(modality="mri", layer_split=False).scalp_split_on()
    with pytest.raises(ValueError, match="scalp_split"):
        SegmentConfig(modality="ct", scalp_split=True)
    with pytest.raises(ValueError, match="`scalp_split` = true needs the layer split"):
        SegmentConfig(modality="mri", layer_split=False, scalp_split=True)
