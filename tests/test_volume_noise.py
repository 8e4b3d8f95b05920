"""`add_scanner_noise`: Rician (MRI) against SciPy's Rice distribution, Gaussian (CT), bad input."""

import numpy as np
import pytest
from scipy import stats

from jaxhead.volume import add_scanner_noise


@pytest.mark.parametrize("signal", [0.0, 0.05, 1.0])
def test_mri_noise_is_rician(signal):
    sd = 0.03
    out = add_scanner_noise(np.full(40_000, signal), sd, "mri", np.random.default_rng(0))
    # Rice(nu = signal, sigma = sd) is scipy.stats.rice(b = nu / sigma, scale = sigma)
    assert stats.kstest(out, stats.rice(b=signal / sd, scale=sd).cdf).pvalue > 1e-3
    # and not Gaussian around the signal where the signal is at the noise level
    if signal < 2 * sd:
        assert stats.kstest(out, stats.norm(signal, sd).cdf).pvalue < 1e-6


def test_ct_noise_is_gaussian_and_zero_sd_is_identity():
    data = np.linspace(-1000, 1000, 30_000)
    out = add_scanner_noise(data, 20.0, "ct", np.random.default_rng(1))
    assert stats.kstest(out - data, stats.norm(0, 20.0).cdf).pvalue > 1e-3
    assert add_scanner_noise(data, 0.0, "mri", np.random.default_rng(1)) is data


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="`modality`"):
        add_scanner_noise(np.zeros(3), 1.0, "pet", np.random.default_rng(0))
    with pytest.raises(ValueError, match="`sd`"):
        add_scanner_noise(np.zeros(3), -1.0, "ct", np.random.default_rng(0))
