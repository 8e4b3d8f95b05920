"""CSF/skull priors by depth between the segmented brain and scalp (`segment`, MRI): the atlas's profile
in depth (`depth_prior`, off by default) and the change point learnt from the scan (`layer_split`, on).

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

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import ndimage

from ..masks import largest_component as _largest_component
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
    # the two transforms side by side: SciPy's releases the GIL (1.8 -> 1.1 s on a 1 mm head, 2 cores)
    with ThreadPoolExecutor(2) as pool:
        d_brain, d_scalp = pool.map(lambda m: ndimage.distance_transform_edt(~m, sampling=voxel_mm), (brain, scalp))
    total = d_brain + d_scalp
    return np.divide(d_brain, total, out=np.zeros_like(total), where=total > 0)


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest face-connected (6-neighbourhood) component of a boolean mask (all False where it is empty;
    `jaxhead.masks.largest_component`). The depth's ends are compartments, not every voxel of a label: a few
    voxels of scalp fat labelled brain (as bright as white matter on T1) put depth 0 in the scalp beside them."""
    return _largest_component(mask)[0]


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
    t = layer_depth(labels == Tissue.BRAIN, labels == Tissue.SCALP, voxel_mm)
    n = len(profile)
    return _share_pair(priors, np.interp(t, (np.arange(n) + 0.5) / n, profile))


def _share_pair(priors, p, classes=(Tissue.CSF, Tissue.SKULL)) -> np.ndarray:
    """float32 priors whose mass of the two `classes` (inner, outer) is split p : 1 - p at each voxel; other
    classes unchanged."""
    out = np.array(priors, np.float32)
    p = np.asarray(p, np.float32)
    a, b = (int(c) for c in classes)
    both = out[a] + out[b]
    out[a] = both * p
    out[b] = both * (1 - p)
    return out


# --- The CSF/skull split learnt from the scan (`layer_split`) -----------------------------------------
#
# The atlas's p(CSF | t) assumes the scan's band has the atlas's CSF share at each relative depth. Where
# it has not (another head's thicker or thinner CSF), at high noise the prior decides, and the EM's CSF
# and skull Gaussians are fitted to the prior's split (measured: experiments/results/segmentation_layer_split.md).
# The band has a structure the atlas does not need to supply: along the depth, CSF lies inside the
# skull. So each neighbourhood of the band is modelled as one change point tau in t, CSF below and skull
# above, and tau is learnt from the scan's intensities alone:
#   1. the intensity densities of CSF and skull are the histograms of the band's voxels below and above
#      the current tau (no parametric form: Rician intensities of dark tissue are skewed in log);
#   2. per voxel, the log ratio of the two densities, L(y);
#   3. per block of a coarse grid (about sigma / 2 per side), tau = argmax_k sum_j w_j [t_j < tau_k] L(y_j)
#      over band voxels j, w a Gaussian window of `sigma_mm` (the split of that neighbourhood of highest
#      likelihood), interpolated linearly onto the voxels;
# repeated from tau = 1/2 until (almost) no band voxel changes side. The EM then runs again with each
# voxel's CSF + skull prior shared by a logistic step at tau (`with_local_split`).

#: candidate change points tau in [0, 1]
SPLIT_STEPS = 21
#: histogram bins of the band's intensities (between its 0.5th and 99.5th percentiles), and the
#: smoothing of the histograms in bins
SPLIT_BINS, SPLIT_SMOOTH_BINS = 64, 1.5
#: stop when fewer than this fraction of band voxels change side in an iteration, or after SPLIT_MAX_ITER
SPLIT_TOL, SPLIT_MAX_ITER = 2e-3, 20


def density_log_ratio(y: np.ndarray, inner: np.ndarray, outer: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """log p_inner(y) - log p_outer(y) per value of `y`, each density a smoothed histogram (SPLIT_BINS
    bins over [lo, hi], values outside in the end bins) of the values of `y` in its mask.

    Arguments:
        y: (n,) intensities (any monotone scale).
        inner, outer: (n,) boolean masks of the two classes' values.
        lo, hi: the histograms' range.
    Returns:
        (n,) float64 log ratio (0 where hi <= lo: no contrast to learn).
    """
    if not hi > lo:
        return np.zeros(len(y))
    return _log_ratio(_bin_index(y, lo, hi), inner, outer)


def _bin_index(y: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Each value's bin of `density_log_ratio`'s histograms: SPLIT_BINS equal bins over [lo, hi] (the
    last closed), values outside in the end bins; as `np.histogram` of the values clipped to [lo, hi]."""
    edges = np.linspace(lo, hi, SPLIT_BINS + 1)
    return np.clip(np.searchsorted(edges, y, side="right") - 1, 0, SPLIT_BINS - 1)


def _log_ratio(bins: np.ndarray, inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """`density_log_ratio` on the values' bins (`_bin_index`): counted once per call, not sorted and
    searched again (`fit_layer_split` calls it once per iteration on the same values)."""
    dens = []
    for m in (inner, outer):
        h = np.bincount(bins[m], minlength=SPLIT_BINS)
        h = ndimage.gaussian_filter1d(h + 1.0, SPLIT_SMOOTH_BINS, mode="nearest")  # +1: no empty bin
        dens.append(np.log(h / h.sum()))
    return (dens[0] - dens[1])[bins]


def _block(voxel_mm, sigma_mm: float) -> np.ndarray:
    """Voxels per block of the coarse grid of the change points: about sigma / 2 (mm) per side."""
    return np.maximum(1, np.round(0.5 * sigma_mm / np.asarray(voxel_mm, np.float64))).astype(np.int64)


def local_change_point(t: np.ndarray, band: np.ndarray, llr: np.ndarray, voxel_mm, sigma_mm: float) -> np.ndarray:
    """Per block of a coarse grid (`_block`), the tau_k of highest windowed likelihood,
    argmax_k sum_j G_sigma(x - x_j) [t_j < tau_k] llr_j over band voxels j (each counted at its block's
    centre, so the window is exact to half a block).

    Arguments:
        t: (x, y, z) normalised depth (`layer_depth`).
        band: (x, y, z) boolean: the CSF + skull band.
        llr: (x, y, z) or (n_band,) log p_CSF / p_skull of each (band) voxel's intensity.
        voxel_mm: voxel sizes (3,), mm.
        sigma_mm: the Gaussian window's sd, mm.
    Returns:
        (coarse grid) tau in [0, 1] (SPLIT_STEPS candidates; 0 where the window holds no band voxel);
        `upsample` puts it on the voxel grid.
    """
    layout = _change_point_layout(t, band, voxel_mm, sigma_mm)
    llr = np.asarray(llr, np.float64)
    return _change_point(layout, llr[np.nonzero(band)] if llr.shape == t.shape else llr)


def _change_point_layout(t: np.ndarray, band: np.ndarray, voxel_mm, sigma_mm: float) -> tuple:
    """What `local_change_point` needs of the band that does not depend on the log ratios: each band
    voxel's block and first candidate, the coarse grid's shape and the window in blocks (computed once
    per `fit_layer_split`, not once per iteration)."""
    b = _block(voxel_mm, sigma_mm)
    cshape = tuple(int(-(-n // k)) for n, k in zip(t.shape, b))
    idx = np.nonzero(band)
    cell = np.ravel_multi_index(tuple(i // k for i, k in zip(idx, b)), cshape)
    k_of = np.searchsorted(np.linspace(0.0, 1.0, SPLIT_STEPS), t[idx], side="right")  # counts for tau_k, k >= k_of
    sig = tuple(sigma_mm / (np.asarray(voxel_mm, np.float64) * b))
    return cell * (SPLIT_STEPS + 1) + k_of, cshape, sig


def _change_point(layout: tuple, w: np.ndarray) -> np.ndarray:
    """`local_change_point` on a `_change_point_layout`, `w` the band voxels' log ratios."""
    slot, cshape, sig = layout
    sums = np.bincount(slot, w, int(np.prod(cshape)) * (SPLIT_STEPS + 1))
    acc = np.cumsum(sums.reshape(cshape + (SPLIT_STEPS + 1,))[..., :SPLIT_STEPS], axis=-1)
    acc = ndimage.gaussian_filter(acc, sig + (0.0,), mode="constant")
    return np.linspace(0.0, 1.0, SPLIT_STEPS)[np.argmax(acc, axis=-1)]


def upsample(coarse: np.ndarray, shape, voxel_mm, sigma_mm: float, points=None) -> np.ndarray:
    """`local_change_point`'s coarse grid interpolated (linearly between block centres) onto the voxel
    grid of `shape`, or at the voxel indices `points` (a tuple of index arrays)."""
    if points is None:  # on the whole grid the interpolation is separable: one small matrix per axis
        out = np.asarray(coarse, np.float64)
        for axis, (n, k) in enumerate(zip(shape, _block(voxel_mm, sigma_mm))):
            out = np.moveaxis(np.tensordot(_linear_weights(n, k, out.shape[axis]), out, axes=(1, axis)), 0, axis)
        return out
    return ndimage.map_coordinates(coarse, _coarse_coordinates(points, voxel_mm, sigma_mm), order=1, mode="nearest")


def _linear_weights(n: int, k: int, m: int) -> np.ndarray:
    """(n, m) weights of linear interpolation from m block centres (blocks of k voxels) to n voxels, the
    ends held constant (map_coordinates' order=1, mode="nearest")."""
    x = np.clip((np.arange(n, dtype=np.float64) - (k - 1) / 2.0) / k, 0.0, m - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), max(m - 2, 0))
    f = x - i0
    w = np.zeros((n, m))
    w[np.arange(n), i0] += 1.0 - f
    w[np.arange(n), np.minimum(i0 + 1, m - 1)] += f
    return w


def _coarse_coordinates(points, voxel_mm, sigma_mm: float) -> np.ndarray:
    """(3, n) positions of voxel indices `points` on the coarse grid, whose samples sit at block centres."""
    b = _block(voxel_mm, sigma_mm)
    return np.stack([(np.asarray(p, np.float64) - (k - 1) / 2.0) / k for p, k in zip(points, b)])


def fit_layer_split(y: np.ndarray, t: np.ndarray, band: np.ndarray, voxel_mm, sigma_mm: float) -> tuple[np.ndarray, dict]:
    """The band's CSF/skull change point in depth, learnt from its intensities (the comment above).

    Arguments:
        y: (x, y, z) intensities (MRI: bias-corrected log intensity).
        t: (x, y, z) normalised depth (`layer_depth`).
        band: (x, y, z) boolean: the voxels a first segmentation labelled CSF or skull.
        voxel_mm: voxel sizes (3,), mm.
        sigma_mm: the neighbourhood (Gaussian window sd, mm) that shares one change point.
    Returns:
        (tau (x, y, z) in [0, 1], summary: iterations, fraction of the band that changed side in the
        last one, the band's CSF fraction).
    """
    band = np.asarray(band, bool)
    if not band.any():
        raise ValueError("fit_layer_split: the `band` mask is empty (no CSF or skull voxel to split).")
    idx = np.nonzero(band)
    yb, tb = np.asarray(y, np.float64)[idx], np.asarray(t, np.float64)[idx]
    lo, hi = np.percentile(yb, [0.5, 99.5])
    inner = tb < 0.5
    layout, at = _change_point_layout(t, band, voxel_mm, sigma_mm), _coarse_coordinates(idx, voxel_mm, sigma_mm)
    bins = _bin_index(yb, lo, hi) if hi > lo else None  # None: no contrast to learn, log ratio 0
    changed, it, coarse = 1.0, 0, None
    while changed >= SPLIT_TOL and it < SPLIT_MAX_ITER:
        coarse = _change_point(layout, np.zeros(len(yb)) if bins is None else _log_ratio(bins, inner, ~inner))
        new = tb < ndimage.map_coordinates(coarse, at, order=1, mode="nearest")  # `upsample` at the band
        changed = float((new != inner).mean())
        inner, it = new, it + 1
    summary = dict(iterations=it, changed_fraction=round(changed, 5), csf_fraction=round(float(inner.mean()), 4))
    return upsample(coarse, t.shape, voxel_mm, sigma_mm), summary


def with_local_split(priors, t: np.ndarray, tau: np.ndarray, width: float,
                     classes=(Tissue.CSF, Tissue.SKULL)) -> np.ndarray:
    """Priors whose CSF + skull mass (or that of other `classes`, inner and outer) at each voxel is shared by a
    logistic step in depth at the voxel's change point: p(inner) = 1 / (1 + exp((t - tau) / width)); the other
    classes are unchanged.

    Arguments:
        priors: (5, x, y, z) class priors.
        t, tau: (x, y, z) normalised depth and change point (`fit_layer_split`).
        width: the step's width in t (> 0).
        classes: the (inner, outer) pair that shares its mass (default CSF, skull; `scalp_split`: skull, scalp).
    Returns:
        (5, x, y, z) float32 priors.
    """
    if not width > 0:
        raise ValueError(f"with_local_split: `width` must be > 0, got {width}.")
    return _share_pair(priors, 0.5 * (1.0 + np.tanh((tau - t) / (2.0 * width))), classes)  # the logistic, overflow-free
