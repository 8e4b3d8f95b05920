"""Measurement noise: Gaussian noise in percent of each channel, and the matching standard deviations."""




import numpy as np


def add_noise(v, percent: float, *, seed: int = 0, reference=None) -> np.ndarray:
    """Add zero-mean Gaussian noise of `percent` % of each channel's magnitude (the seed paper's model).

    Arguments:
        v: (n_rows,) voltages (V).
        percent: noise standard deviation in % of |reference| per channel (e.g. 0.5).
        seed: random seed.
        reference: (n_rows,) magnitudes the percentage refers to (default: |v|; for difference
            data pass the baseline voltages).

    Returns:
        (n_rows,) noisy voltages; the per-channel standard deviation is `noise_std(v, percent)`.
    """
    v = np.asarray(v, dtype=np.float64)
    if percent < 0:
        raise ValueError(f"`percent` must be >= 0, got {percent}.")
    std = noise_std(v if reference is None else reference, percent)
    return v + np.random.default_rng(seed).standard_normal(v.shape) * std


def noise_std(reference, percent: float, *, floor: float = 0.0) -> np.ndarray:
    """Per-channel noise standard deviation: percent / 100 * max(|reference|, floor * RMS).

    Arguments:
        reference: (n_rows,) voltages the percentage refers to (V).
        percent: noise in % per channel.
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
    return ref * (percent / 100.0)


# --- reconstruction grids -----------------------------------------------------------------------
