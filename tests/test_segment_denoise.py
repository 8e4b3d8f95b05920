"""Noise estimates and Perona-Malik smoothing (segmentation.denoise): against a NumPy reference,
known noise (Gaussian and Rician), scipy's Rayleigh distribution, and invariants (conservation,
noise-free images unchanged, edges kept, noise reduced)."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxhead.segmentation import SegmentConfig
from jaxhead.segmentation.denoise import DT, RAYLEIGH_CUT, diffuse, noise_sd, rayleigh_noise_sd
from jaxhead.segmentation.segment import DENOISE_STEPS, EDGE_FACTOR, _em_data
from jaxhead.volume import Volume, add_scanner_noise

SHAPE = (30, 26, 28)


def blocks(shape=SHAPE):
    """Piecewise-constant image: a 0 background, a 100 slab and a 40 ball inside it."""
    i, j, k = np.indices(shape)
    img = np.where(i > shape[0] // 3, 100.0, 0.0)
    ball = (i - 20) ** 2 + (j - 13) ** 2 + (k - 14) ** 2 < 36
    return np.where(ball, 40.0, img)


def numpy_perona_malik(y, k, n_steps):
    """Independent explicit Perona-Malik loop over voxels' six neighbours (float64, zero flux outside)."""
    u = np.array(y, dtype=np.float64)
    for _ in range(n_steps):
        p = np.pad(u, 1, mode="edge")  # an edge copy has zero difference: zero flux through the border
        c = p[1:-1, 1:-1, 1:-1]
        total = np.zeros_like(u)
        for sl in [(slice(2, None), slice(1, -1), slice(1, -1)), (slice(None, -2), slice(1, -1), slice(1, -1)),
                   (slice(1, -1), slice(2, None), slice(1, -1)), (slice(1, -1), slice(None, -2), slice(1, -1)),
                   (slice(1, -1), slice(1, -1), slice(2, None)), (slice(1, -1), slice(1, -1), slice(None, -2))]:
            d = p[sl] - c
            total += np.exp(-(d / k) ** 2) * d
        u = u + DT * total
    return u


def test_noise_sd_recovers_known_noise_and_is_zero_without_it():
    rng = np.random.default_rng(0)
    img = blocks()
    assert noise_sd(img) == 0.0  # piecewise constant: most neighbour pairs are equal
    for sd in (2.0, 7.0, 20.0):
        est = noise_sd(img + sd * rng.standard_normal(img.shape))
        assert abs(est / sd - 1) < 0.05, (sd, est)
    with pytest.raises(ValueError, match="3-D image"):
        noise_sd(np.zeros((4, 4)))


def test_diffuse_matches_numpy_reference():
    rng = np.random.default_rng(1)
    y = blocks() + 10 * rng.standard_normal(SHAPE)
    for k, n in ((20.0, 5), (5.0, 3), (1e6, 4)):
        ref = numpy_perona_malik(y, k, n)
        got = np.asarray(diffuse(jnp.asarray(y, jnp.float64), k, n))
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


def test_diffuse_invariants_conservation_fixed_points_edges_and_noise():
    rng = np.random.default_rng(2)
    img = blocks()
    # a constant image and a noise-free piecewise-constant one (steps >> k) do not move
    np.testing.assert_array_equal(np.asarray(diffuse(jnp.full(SHAPE, 3.0), 1.0, 5)), 3.0)
    np.testing.assert_allclose(np.asarray(diffuse(jnp.asarray(img), 2.0, 5)), img, atol=1e-12)
    noisy = img + 5.0 * rng.standard_normal(SHAPE)
    out = np.asarray(diffuse(jnp.asarray(noisy), 2.0 * noise_sd(noisy), 5))
    # zero flux at the border: the sum is conserved
    assert abs(out.sum() - noisy.sum()) < 1e-8 * np.abs(noisy).sum()
    # noise reduced inside regions; the 0/100 edge (20 noise sd) kept: voxels beside it stay on their side
    inner = np.zeros(SHAPE, bool)
    inner[2:8, 2:-2, 2:-2] = True
    assert np.std(out[inner]) < 0.5 * np.std(noisy[inner])
    edge = SHAPE[0] // 3
    assert np.all(out[edge, 3:-3, 3:-3] < 25) and np.all(out[edge + 1, 3:8, 3:8] > 75)
    # linear diffusion smooths the same edge away: a step of 100 loses > 10 at the voxels beside it
    lin = np.asarray(diffuse(jnp.asarray(img), 1e9, 5))
    assert lin[edge, 3:8, 3:8].min() > 10


def test_denoise_setting_is_validated():
    assert SegmentConfig(modality="ct").denoise is None
    with pytest.raises(ValueError, match="denoise"):
        SegmentConfig(denoise="yes")


def head_ball(n=40):
    """A 'head' (1.0) with a dark core (0.12, skull-like) in air (0): 42 % of the grid is head."""
    i, j, k = np.indices((n, n, n))
    r = np.sqrt((i - n / 2) ** 2 + (j - n / 2) ** 2 + (k - n / 2) ** 2)
    img = np.where(r < 0.375 * n, 1.0, 0.0)
    return np.where(r < 0.175 * n, 0.12, img), r


def test_rayleigh_noise_sd_recovers_rician_noise_where_neighbour_differences_do_not():
    rng = np.random.default_rng(3)
    img, _ = head_ball()
    for sd in (0.03, 0.08, 0.2):  # the dark core's SNR 4, 1.5, 0.6
        mag = add_scanner_noise(img, sd, "mri", rng)
        assert abs(rayleigh_noise_sd(mag) / sd - 1) < 0.03, sd
        # neighbour differences of Rayleigh air: ~0.64 of the channel sd (why the MRI needs its own)
        assert noise_sd(mag) / sd < 0.8
    # pure Rayleigh (all air): the fixed point is the Rayleigh scale; the truncated median factor
    # against scipy's Rayleigh distribution
    air = np.hypot(*rng.standard_normal((2, 30, 30, 30))) * 5.0
    assert abs(rayleigh_noise_sd(air) / 5.0 - 1) < 0.02
    c = RAYLEIGH_CUT
    q = np.sqrt(-2 * np.log((1 + np.exp(-c * c / 2)) / 2))
    assert q == pytest.approx(stats.rayleigh.ppf(stats.rayleigh.cdf(c) / 2), rel=1e-12)


def test_rayleigh_noise_sd_needs_air_and_ignores_masked_zeros():
    rng = np.random.default_rng(4)
    img, r = head_ball()
    assert rayleigh_noise_sd(img) is None  # noise-free: air exactly 0, no positive air voxel
    tissue = add_scanner_noise(np.full((30, 30, 30), 1.0), 0.03, "mri", rng)
    assert rayleigh_noise_sd(tissue) is None  # no air: the darkest tissue is not Rayleigh (KS test)
    mag = add_scanner_noise(img, 0.05, "mri", rng)
    mag[r > 17] = 0.0  # air masked to zero beyond a thin shell: the zeros are not counted
    assert abs(rayleigh_noise_sd(mag) / 0.05 - 1) < 0.05
    with pytest.raises(ValueError, match="cut"):
        rayleigh_noise_sd(mag, cut=0.0)
    with pytest.raises(ValueError, match="3-D image"):
        rayleigh_noise_sd(np.ones((4, 4)))


def test_mri_em_data_smooths_with_the_rayleigh_estimate():
    rng = np.random.default_rng(5)
    img, _ = head_ball(24)
    vol = Volume(add_scanner_noise(img, 0.05, "mri", rng), np.eye(4))
    got = _em_data(vol, "mri", denoise=True)
    for est, same in ((rayleigh_noise_sd, True), (noise_sd, False)):
        sm = np.asarray(diffuse(jnp.asarray(vol.data, jnp.float32), EDGE_FACTOR * est(vol.data), DENOISE_STEPS),
                        np.float64)
        ref = np.log(np.maximum(sm, 1e-3 * np.percentile(sm, 99)))
        assert np.allclose(got, ref, atol=1e-6) == same
