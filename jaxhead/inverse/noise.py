"""Measurement noise: Gaussian noise in percent of each channel, and the matching standard deviations."""




import numpy as np


def add_noise(v, noise_percent: float, *, seed: int = 0, reference=None) -> np.ndarray:
    """Add zero-mean Gaussian noise of `noise_percent` % of each channel's magnitude (the seed paper's model).

    Arguments:
        v: (n_rows,) voltages (V).
        noise_percent: noise standard deviation in % of |reference| per channel (e.g. 0.5).
        seed: random seed.
        reference: (n_rows,) magnitudes the percentage refers to (default: |v|; for difference
            data pass the baseline voltages).

    Returns:
        (n_rows,) noisy voltages; the per-channel standard deviation is `noise_std(v, noise_percent)`.
    """
    v = np.asarray(v, dtype=np.float64)
    if noise_percent < 0:
        raise ValueError(f"`noise_percent` must be >= 0, got {noise_percent}.")
    std = noise_std(v if reference is None else reference, noise_percent)
    return v + np.random.default_rng(seed).standard_normal(v.shape) * std


def noise_std(reference, noise_percent: float, *, floor: float = 0.0) -> np.ndarray:
    """Per-channel noise standard deviation: noise_percent / 100 * max(|reference|, floor * RMS).

    Arguments:
        reference: (n_rows,) voltages the percentage refers to (V).
        noise_percent: noise in % per channel.
        floor: as a fraction of the RMS of `reference`, the smallest magnitude a channel's
            noise refers to. 0 (default) is the pure per-channel model `add_noise` draws from.
            For weights in a reconstruction a small floor (e.g. 0.03) keeps channels whose
            standing voltage is nearly zero from being trusted beyond the model's accuracy:
            whitening would otherwise amplify the reconstruction mesh's modelling error there.

    Returns:
        (n_rows,) standard deviations in V.
    """
    ref = np.abs(np.asarray(reference, dtype=np.float64))
    if not floor >= 0:
        raise ValueError(f"`floor` must be >= 0 (a fraction of the RMS), got {floor}.")
    if floor > 0:
        ref = np.maximum(ref, floor * np.sqrt(np.mean(ref**2)))
    return ref * (noise_percent / 100.0)


