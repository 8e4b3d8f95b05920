"""Re-segmentation of the scan under other noise or settings: the product's own error.  [jax]

A sample changes the reference's scan (seeded) and segments it again with the library's own
`segment`, the reference's atlas and SegmentConfig, optionally with some settings overridden:

- noise: `amplitude` is the noise sd in per cent of the scan's robust intensity range
  R = P99 - P1 (the 99th minus the 1st percentile of all the scan's voxels, air included), so
  sd = amplitude / 100 * R in the scan's units. MRI gets Rician noise, the magnitude of a complex
  image with Gaussian noise of that sd in each channel, |I + n_re + i n_im| (Gudbjartsson & Patz
  1995; it keeps the image positive, as `segment` models MRI in log intensity, and is what
  `jaxhead.make_head` adds); CT gets additive Gaussian noise in HU.
- bias (MRI only): the scan is multiplied by exp(b), b a random quadratic polynomial of the
  grid's coordinates (each axis mapped to [-1, 1], the 10 monomials of degree <= 2 with standard
  normal coefficients) scaled so that max |b| over the grid = bias_percent / 100 (about
  +-bias_percent %, the smooth low-order field an MR receive coil adds).
- settings: SegmentConfig fields overridden for the sample (e.g. beta, max_iter, relax;
  `jaxhead.study.config.segment_config` validates them).

The reference labels are the segmentation of the unperturbed scan with the reference settings,
so amplitude 0, bias 0 and no settings changed reproduce them voxel for voxel (the segmentation is
deterministic), and a sample measures the segmentation's own variability, not its error against
a truth. Each sample's description gives the Dice of its labels against the reference labels.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..segmentation import Atlas, SegmentConfig, dice_scores, segment
from ..volume import LabelMap, Volume, add_scanner_noise

def robust_range(volume: Volume) -> float:
    """P99 - P1 of all the scan's voxel intensities (the unit of the noise amplitude)."""
    lo, hi = np.percentile(np.asarray(volume.data, dtype=np.float64), [1.0, 99.0])
    return float(hi - lo)


def _bias(shape, rng) -> np.ndarray:
    """A random quadratic polynomial on the grid ([-1, 1] per axis) with max |b| = 1."""
    axes = np.meshgrid(*[np.linspace(-1.0, 1.0, n) for n in shape], indexing="ij")
    b = np.zeros(shape)
    for p in itertools.product(range(3), repeat=3):
        if sum(p) <= 2:
            b += rng.standard_normal() * axes[0] ** p[0] * axes[1] ** p[1] * axes[2] ** p[2]
    return b / max(np.abs(b).max(), 1e-300)


def perturb_scan(volume: Volume, modality: str, amplitude: float, *, bias_percent: float = 0.0,
                 seed: int = 0) -> tuple[Volume, dict]:
    """The scan with seeded noise (and bias) added, as the module docstring defines them.

    Arguments:
        volume: the reference scan (MRI: magnitude; CT: HU).
        modality: "mri" (Rician noise, bias allowed) or "ct" (Gaussian noise, no bias).
        amplitude: noise sd in % of `robust_range(volume)` (>= 0; 0 adds none).
        bias_percent: max |log bias| in % (MRI only, >= 0; 0 adds none).
        seed: random seed.

    Returns:
        (perturbed Volume, description: noise_sd in the scan's units, the range, bias_percent).
    """
    if modality not in ("mri", "ct"):
        raise ValueError(f"`modality` must be 'mri' or 'ct', got {modality!r}.")
    if not np.isfinite(amplitude) or amplitude < 0:
        raise ValueError(f"noise `amplitude` must be >= 0 (% of the intensity range), got {amplitude}.")
    if not np.isfinite(bias_percent) or bias_percent < 0:
        raise ValueError(f"`bias_percent` must be >= 0, got {bias_percent}.")
    if modality == "ct" and bias_percent > 0:
        raise ValueError(f"`bias_percent` = {bias_percent} for a CT: a CT has no multiplicative "
                         "bias field; use 0.")
    rng = np.random.default_rng(seed)
    data = np.array(volume.data, dtype=np.float64)
    rr = robust_range(volume)
    if bias_percent > 0:
        data *= np.exp(bias_percent / 100.0 * _bias(data.shape, rng))
    sd = amplitude / 100.0 * rr
    data = add_scanner_noise(data, sd, modality, rng)
    return Volume(data, volume.affine), {"noise_sd": sd, "robust_range": rr,
                                         "bias_percent": float(bias_percent)}


def resegment(volume: Volume, reference: LabelMap, amplitude: float, *, atlas: Atlas,
              cfg: SegmentConfig, bias_percent: float = 0.0, seed: int = 0) -> tuple[LabelMap, dict]:
    """Segment the scan again after a seeded change: the product's own segmentation error.

    Arguments:
        volume: the reference scan; reference: its segmentation (the reference labels).
        amplitude: noise sd in % of the scan's robust range (`perturb_scan`).
        atlas: the reference's atlas; cfg: the sample's SegmentConfig (the reference's, with the
            sample's settings applied).
        bias_percent: MRI bias field amplitude in % (`perturb_scan`); seed: random seed.

    Returns:
        (labels, description: kind, amplitude, seed, noise sd, voxels changed against the
        reference labels, Dice per tissue against them).
    """
    if not isinstance(reference, LabelMap) or reference.shape != volume.shape:
        raise ValueError(f"`reference` must be the LabelMap segmented from this scan (shape "
                         f"{volume.shape}), got {getattr(reference, 'shape', type(reference).__name__)}.")
    scan, info = perturb_scan(volume, cfg.modality, amplitude, bias_percent=bias_percent, seed=seed)
    labels = segment(scan, atlas, cfg)
    dice = dice_scores(labels, reference)
    desc = {"kind": "resegment", "amplitude_percent": float(amplitude), "seed": int(seed), **info,
            "voxels_changed": int((labels.labels != reference.labels).sum()),
            "dice": {k: round(v, 6) for k, v in dice.items()}}
    return labels, desc

