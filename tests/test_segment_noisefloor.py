"""The EM's noise floor (em.NoiseFloor, denoise.log_noise_table, segment._noise_floor): the tabulated
log noise against the analytic log-Rician moments and an independent linear-diffusion residual, the
floor's values from a known noise level, an EM in which a narrow Gaussian of another class collapses
onto a spike narrower than the noise (and takes its voxels) without the floor and not with it, and
the errors for bad input."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from jaxhead.segmentation import SegmentConfig
from jaxhead.segmentation.denoise import DT, LOG_RAYLEIGH_SD, TABLE_SNR, log_noise_table
from jaxhead.segmentation.em import EMOptions, MixtureParams, NoiseFloor, fit_mixture
from jaxhead.segmentation.segment import DENOISE_STEPS, EDGE_FACTOR, _noise_floor

EULER_GAMMA = 0.5772156649015329


def test_log_noise_table_without_smoothing_is_the_log_rician_noise():
    m, d = log_noise_table(EDGE_FACTOR, 0)
    assert np.all(np.diff(m) > 0)
    # air (Rayleigh, s = 1): E[ln R] = (ln 2 - gamma) / 2 (R^2 / 2 is exponential), sd pi / sqrt(24)
    assert TABLE_SNR[0] == 0.0
    assert abs(m[0] - (np.log(2.0) - EULER_GAMMA) / 2) < 0.01
    assert abs(d[0] / LOG_RAYLEIGH_SD - 1) < 0.02
    # high SNR: Rician -> Gaussian of sd 1 about A, so the log has mean ln A and sd 1 / A
    q = TABLE_SNR[-1]
    assert abs(m[-1] - np.log(q)) < 1e-3
    assert abs(d[-1] * q - 1) < 0.02


def linear_residual(n_steps: int) -> float:
    """sd of white noise (sd 1) after n explicit linear-diffusion steps of DT on the 6-neighbourhood:
    the root sum of squares of the n-fold stencil's weights (an independent scipy convolution)."""
    stencil = np.zeros((3, 3, 3))
    stencil[1, 1, 1] = 1 - 6 * DT
    for a in range(3):
        for s in (0, 2):
            idx = [1, 1, 1]
            idx[a] = s
            stencil[tuple(idx)] = DT
    k = np.zeros((2 * n_steps + 1,) * 3)
    k[(n_steps,) * 3] = 1.0
    for _ in range(n_steps):
        k = ndimage.convolve(k, stencil, mode="constant")
    return float(np.sqrt((k**2).sum()))


def test_log_noise_table_in_the_linear_limit_matches_the_diffusion_stencil():
    # an edge threshold far above the noise: Perona-Malik is linear diffusion, whose residual noise is
    # the stencil's root sum of squares; at high SNR the log noise is that over A
    ref = linear_residual(DENOISE_STEPS)
    assert 0.05 < ref < 0.2
    m, d = log_noise_table(1e6, DENOISE_STEPS)
    q = np.asarray(TABLE_SNR)
    assert np.all(np.abs(d[q >= 16] * q[q >= 16] / ref - 1) < 0.04), d[q >= 16] * q[q >= 16] / ref
    # Perona-Malik at the default threshold smooths less than linear diffusion (edges of noise kept)
    _, d_pm = log_noise_table(EDGE_FACTOR, DENOISE_STEPS)
    assert np.all(d_pm[q >= 16] * q[q >= 16] > 1.2 * ref)


def test_noise_floor_from_a_known_noise_level():
    sd = 0.03
    m, d = log_noise_table(EDGE_FACTOR, 0)  # the acquisition's log-Rician noise
    nf = _noise_floor(sd)
    got = np.asarray(nf.sd(jnp.asarray(np.log(sd) + m), True))
    np.testing.assert_allclose(got, d, rtol=1e-6)
    # above the table: the log noise of a bright tissue falls as 1 / intensity
    np.testing.assert_allclose(float(nf.sd(jnp.asarray(np.log(sd) + m[-1] + np.log(4.0)), True)), d[-1] / 4,
                               rtol=1e-6)
    # below it (darker than air's mean log): the log-Rayleigh sd of air
    assert float(nf.sd(jnp.asarray(np.log(sd) - 5.0), True)) == pytest.approx(LOG_RAYLEIGH_SD, rel=0.02)
    # analytic: a tissue at 20 noise sd has log sd 1 / 20 (Rician ~ Gaussian there), whatever sd is
    for sd in (0.01, 0.03, 7.0):
        assert float(_noise_floor(sd).sd(jnp.asarray(np.log(20 * sd)), True)) == pytest.approx(1 / 20, rel=0.03)
    # linear data: the table's values, constant outside it
    lin = NoiseFloor(means=jnp.array([0.0, 1.0]), sds=jnp.array([2.0, 4.0]))
    np.testing.assert_allclose(np.asarray(lin.sd(jnp.array([-1.0, 0.5, 3.0]), False)), [2.0, 3.0, 4.0])
    assert _noise_floor(None) is None


def spike_case(seed=0):
    """Two classes: "CSF" (one Gaussian, sd 0.1 about 0) with a spike of 10 % of its voxels at 0.15
    that is narrower (sd 0.002) than the noise any tissue keeps (0.03 here), where the atlas gives the
    other class ("skull": dark tissue at -1, two Gaussians) 0.3; the skull's second Gaussian starts
    on the spike."""
    rng = np.random.default_rng(seed)
    shape = (24, 20, 22)
    csf = np.zeros(shape, bool)
    csf[:12] = True
    spike = csf & (rng.random(shape) < 0.1)
    y = np.where(csf, rng.normal(0.0, 0.1, shape), rng.normal(-1.0, 0.1, shape))
    y = np.where(spike, rng.normal(0.15, 0.002, shape), y)
    prior = np.stack([np.where(csf, 0.7, 0.1), np.where(csf, 0.3, 0.9)])
    init = MixtureParams(jnp.array([0.0, -1.0, 0.15]), jnp.array([0.01, 0.01, 0.01]), jnp.array([1.0, 0.8, 0.2]),
                         jnp.zeros(0))
    return y, prior, init, csf, spike


def test_noise_floor_stops_a_gaussian_collapsing_onto_a_spike():
    y, prior, init, csf, spike = spike_case()
    opts = EMOptions(component_class=(0, 1, 1), n_classes=2, max_iter=200)
    floor = NoiseFloor(means=jnp.array([-2.0, 2.0]), sds=jnp.array([0.03, 0.03]))
    out = {}
    for name, nf in (("without", None), ("with", floor)):
        res = fit_mixture(jnp.asarray(y), jnp.asarray(prior), opts, init, noise_floor=nf)
        assert bool(res.converged)
        lab = np.asarray(res.posteriors).argmax(0)
        out[name] = (np.sqrt(np.asarray(res.params.variances)), (lab[spike] == 0).mean())
    sd, kept = out["without"]
    assert sd[2] < 0.01 and kept < 0.1  # collapsed on the spike: the skull takes > 90 % of it
    sd, kept = out["with"]
    assert np.all(sd >= 0.03 * (1 - 1e-6)) and kept > 0.99


def test_bad_noise_floor_inputs_are_refused():
    with pytest.raises(ValueError, match="strictly increasing"):
        NoiseFloor(means=jnp.array([1.0, 0.0]), sds=jnp.array([1.0, 1.0]))
    with pytest.raises(ValueError, match="> 0"):
        NoiseFloor(means=jnp.array([0.0, 1.0]), sds=jnp.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="one length >= 2"):
        NoiseFloor(means=jnp.array([0.0]), sds=jnp.array([1.0]))
    with pytest.raises(ValueError, match="edge_factor"):
        log_noise_table(0.0, 5)
    with pytest.raises(ValueError, match="n_steps"):
        log_noise_table(2.0, -1)
    with pytest.raises(ValueError, match="noise_floor"):
        SegmentConfig(modality="mri", noise_floor="yes")
    with pytest.raises(ValueError, match="noise_floor=True"):
        SegmentConfig(modality="ct", noise_floor=True)
