"""CSF/skull priors by depth between the segmented brain and scalp (`segment`, on for MRI).

On a T1 scan CSF and compact bone are both dark, so between the brain and the scalp the EM's split of
the dark band into CSF and skull is decided by the registered atlas: where another head's inner skull
lands inside this head's CSF, the CSF is labelled skull (experiments/results/segmentation_mri_capture.md).
The band's two boundaries, by contrast, are well seen: brain against CSF (grey matter against a dark
band) and skull against scalp (dark against fat and muscle). So the split can be carried over from the
atlas in *relative* depth instead of position:

    t(x) = d_brain(x) / (d_brain(x) + d_scalp(x)),

d the Euclidean distance (mm) to the nearest brain and scalp voxel: t = 0 on the brain, 1 on the scalp,
and t is the normalised depth across the band (as equivolume cortical depth is across the cortex). The
atlas gives p(CSF | t): in bins of t on its own grid, CSF prior mass over CSF + skull prior mass
(`csf_depth_profile`), made non-increasing in t (CSF inside the skull; weighted pool-adjacent-violators,
`isotonic_decreasing`). A scan's first EM gives its brain and scalp; each voxel's CSF + skull prior mass
is then shared by p(CSF | t) at the scan's own t (`with_depth_profile`), and the EM runs again.

Assumed: the band's CSF fraction at a given relative depth is like the atlas's (so a head with much
more or less CSF than the atlas, e.g. marked atrophy, gets a prior that is off by that much; the
intensities still speak where they can). Measured on three anatomies with their true brain and scalp:
a threshold on t learnt on one and applied to another labels the band's CSF with Dice 0.79-0.93
(experiments/results/segmentation_depth_prior.md).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..tissue import Tissue

#: bins of t in [0, 1] for the atlas's p(CSF | t)
DEPTH_BINS = 20


def layer_depth(brain: np.ndarray, scalp: np.ndarray, voxel_mm) -> np.ndarray:
    """Normalised depth t = d_brain / (d_brain + d_scalp) in [0, 1] (module docstring).

    Arguments:
        brain, scalp: (x, y, z) boolean masks, each with at least one voxel.
        voxel_mm: the grid's voxel sizes (3,), mm.
    Returns:
        (x, y, z) float64: 0 on the brain, 1 on the scalp.
    """
    brain, scalp = np.asarray(brain, bool), np.asarray(scalp, bool)
    for name, m in (("brain", brain), ("scalp", scalp)):
        if not m.any():
            raise ValueError(f"layer_depth: the `{name}` mask is empty; the depth between brain and scalp needs both.")
    d_brain = ndimage.distance_transform_edt(~brain, sampling=voxel_mm)
    d_scalp = ndimage.distance_transform_edt(~scalp, sampling=voxel_mm)
    total = d_brain + d_scalp
    return np.divide(d_brain, total, out=np.zeros_like(total), where=total > 0)


def isotonic_decreasing(values, weights) -> np.ndarray:
    """The weighted least-squares non-increasing sequence closest to `values` (pool adjacent violators)."""
    values, weights = np.asarray(values, np.float64), np.asarray(weights, np.float64)
    means, wts, counts = [], [], []
    for v, w in zip(values, np.maximum(weights, 1e-12)):
        means.append(v)
        wts.append(w)
        counts.append(1)
        while len(means) > 1 and means[-2] < means[-1]:
            w2 = wts[-2] + wts[-1]
            means[-2:] = [(means[-2] * wts[-2] + means[-1] * wts[-1]) / w2]
            wts[-2:] = [w2]
            counts[-2:] = [counts[-2] + counts[-1]]
    return np.repeat(means, counts)


def _bins(t: np.ndarray, n_bins: int) -> np.ndarray:
    return np.minimum((t * n_bins).astype(np.int64), n_bins - 1)


def csf_depth_profile(priors: np.ndarray, voxel_mm, n_bins: int = DEPTH_BINS) -> tuple[np.ndarray, np.ndarray]:
    """The atlas's p(CSF | t): per bin of t, its CSF prior mass over its CSF + skull prior mass, made
    non-increasing in t (`isotonic_decreasing`, weighted by that mass).

    Arguments:
        priors: (5, x, y, z) class priors on the atlas grid; brain and scalp are where their prior is the
            largest.
        voxel_mm: the atlas's voxel sizes (3,), mm.
        n_bins: bins of t.
    Returns:
        (profile (n_bins,), CSF + skull mass per bin (n_bins,)).
    """
    priors = np.asarray(priors, np.float64)
    labels = np.argmax(priors, axis=0)
    t = layer_depth(labels == Tissue.BRAIN, labels == Tissue.SCALP, voxel_mm)
    idx = _bins(t, n_bins).ravel()
    csf, skull = priors[int(Tissue.CSF)].ravel(), priors[int(Tissue.SKULL)].ravel()
    num = np.bincount(idx, csf, n_bins)
    mass = np.bincount(idx, csf + skull, n_bins)
    raw = np.divide(num, mass, out=np.zeros(n_bins), where=mass > 0)
    return isotonic_decreasing(raw, mass), mass


def with_depth_profile(priors, labels: np.ndarray, voxel_mm, profile: np.ndarray) -> np.ndarray:
    """Priors whose CSF + skull mass at each voxel is shared by `profile` at the voxel's depth t between
    `labels`' brain and scalp (linear between bin centres); the other classes are unchanged.

    Arguments:
        priors: (5, x, y, z) class priors on the scan's grid.
        labels: (x, y, z) Tissue labels of a first segmentation of the scan.
        voxel_mm: the scan's voxel sizes (3,), mm.
        profile: p(CSF | t) per bin (`csf_depth_profile`).
    Returns:
        (5, x, y, z) float32 priors.
    """
    out = np.array(priors, np.float32)
    t = layer_depth(labels == Tissue.BRAIN, labels == Tissue.SCALP, voxel_mm)
    n = len(profile)
    p = np.interp(t, (np.arange(n) + 0.5) / n, profile).astype(np.float32)
    both = out[int(Tissue.CSF)] + out[int(Tissue.SKULL)]
    out[int(Tissue.CSF)] = both * p
    out[int(Tissue.SKULL)] = both * (1 - p)
    return out
