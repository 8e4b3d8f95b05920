"""Noise estimate and noise-adaptive edge-preserving smoothing of a scan before the EM.  [jax]

Why: the EM classifies voxel by voxel with a Potts prior; where the tissue contrast is comparable
to the noise (CT brain ~30-40 HU vs CSF ~0-15 HU under 20 HU of noise) the per-voxel likelihoods
barely differ, the EM's mixture loses the low-contrast class (its Gaussian drifts off the tissue
and its within-class weight goes to 0) and the priors alone decide.

- `noise_sd`: the noise standard deviation, robustly, from the differences of neighbouring voxels:
  for i.i.d. noise of sd s on a piecewise-smooth image, d = y_i - y_{i+1} is N(0, 2 s^2) wherever
  both voxels lie in one tissue (most pairs: air and tissue interiors), so s = 1.4826 MAD(d) / sqrt 2
  (Donoho & Johnstone 1994, Biometrika 81:425, the MAD estimate; here on first differences, which
  needs no wavelet). Edges are a minority of pairs and only inflate it slightly (MAD is robust);
  texture inside tissues is counted as noise. The median over the three axes.
- `rayleigh_noise_sd`: the same for an MRI magnitude image, from the air around the head. Neighbour
  differences are the wrong statistic there: a magnitude voxel of true signal A is Rician
  (Gudbjartsson & Patz 1995, MRM 34:910), Rayleigh in air (A = 0), whose neighbour differences give
  `noise_sd` 0.64 times the channel sd s, while inside the head the brain's folding at 1-2 mm voxels
  counts as noise (held-out renders at 2 mm: `noise_sd` 0.80-0.97 s, the same MAD over pairs brighter
  than 3 s 1.1-1.7 s). Air is pure noise: the Rayleigh median is s sqrt(2 ln 2), and the median of
  the voxels below c s is s sqrt(-2 ln((1 + exp(-c^2 / 2)) / 2)) (the Rayleigh distribution truncated at
  c s), so s is the fixed point of s = median(y | 0 < y < c s) / that factor (c = 2: 86 % of air
  counted, tissue brighter than 2 s excluded); the median histogram-of-air idea of Sijbers et al.
  2007, Phys. Med. Biol. 52:1335, without fitting a histogram. Exact zeros (masked or zero-filled
  air) are not counted.
- `diffuse`: Perona-Malik anisotropic diffusion (Perona & Malik 1990, IEEE TPAMI 12:629),
  du/dt = div(g(|grad u|) grad u), g(d) = exp(-(d / k)^2), explicit steps of dt = 1/7 over the
  6-neighbourhood (stable for dt <= 1/6), zero flux at the grid border. The edge threshold k is
  tied to the noise: k = `edge_factor` * noise sd (Black et al. 1998, IEEE TIP 7:421, set the
  edge scale from the MAD of the gradient): steps of a few noise sd (air/skin, bone, and CSF/brain
  at low noise) stay sharp, noise is smoothed. The smoothing adapts itself: without noise (k -> 0)
  nothing moves. `n_steps` steps smooth flat regions like a Gaussian of sd sqrt(2 n dt) voxels
  (1.2 voxels for the default 5 steps), a scale below the thinnest layer a voxel grid resolves.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

#: Explicit Perona-Malik step (6-neighbourhood: stable for dt <= 1/6).
DT = 1.0 / 7.0


def _check_image(y) -> np.ndarray:
    y = np.asarray(y, dtype=np.float64)
    if y.ndim != 3 or min(y.shape) < 2:
        raise ValueError(f"`y` must be a 3-D image with >= 2 voxels per axis, got shape {y.shape}.")
    return y


def noise_sd(y: np.ndarray) -> float:
    """Robust noise standard deviation of a 3-D image: 1.4826 MAD of neighbour differences / sqrt(2).

    Arguments:
        y: (x, y, z) image (at least 2 voxels along each axis).
    Returns:
        the estimate (image units); the median over the three axes.
    """
    y = _check_image(y)
    est = [1.4826 * np.median(np.abs(np.diff(y, axis=ax))) / np.sqrt(2.0) for ax in range(3)]
    return float(np.median(est))


#: `rayleigh_noise_sd`: the voxels below RAYLEIGH_CUT times the estimate are taken as air.
RAYLEIGH_CUT = 2.0
#: `rayleigh_noise_sd`: the least fraction of the positive voxels below the cut (else: no air to measure).
MIN_AIR_FRACTION = 0.05
#: `rayleigh_noise_sd`: the largest Kolmogorov-Smirnov distance of the voxels taken as air from the
#: truncated Rayleigh distribution (sampling alone: < 0.05 from 10^3 voxels at the 1 % level; the
#: rest allows for dark tissue among them).
MAX_KS = 0.1
#: `rayleigh_noise_sd` uses at most ~2x this many voxels (a strided subsample of a larger scan).
MAX_VOXELS = 1_000_000


def rayleigh_noise_sd(y: np.ndarray, cut: float = RAYLEIGH_CUT, max_iter: int = 200) -> float | None:
    """Noise sd (per real/imaginary channel) of an MRI magnitude image, from its air (Rayleigh).

    The fixed point of s = median(y | 0 < y < cut s) / sqrt(-2 ln((1 + exp(-cut^2 / 2)) / 2)),
    iterated from the 1st percentile of the positive voxels (below s wherever air is >= 2 % of
    them; each step moves up towards the fixed point) to a relative change < 1e-6.

    Arguments:
        y: (x, y, z) magnitude image (>= 0).
        cut: voxels below cut times the estimate are taken as air (> 0).
        max_iter: iterations at most.
    Returns:
        the estimate (image units), or None where there is no air to measure (a scan cropped to the
        head, or with its air masked to zero; use `noise_sd`): fewer than MIN_AIR_FRACTION of the
        positive voxels below the cut, or those voxels farther than MAX_KS (Kolmogorov-Smirnov) from
        the truncated Rayleigh distribution.
    """
    y = _check_image(y)
    if not cut > 0:
        raise ValueError(f"`cut` must be > 0, got {cut!r}.")
    v = y[y > 0]
    if v.size == 0:
        return None
    v = v[:: max(1, v.size // MAX_VOXELS)]  # a regular subsample: the median of 10^6 is good to ~0.1 %
    q = np.sqrt(-2.0 * np.log((1.0 + np.exp(-0.5 * cut * cut)) / 2.0))
    s = float(np.percentile(v, 1.0))
    for _ in range(max_iter):
        below = v[v < cut * s]
        if below.size == 0:
            return None
        new = float(np.median(below)) / q
        done = abs(new - s) <= 1e-6 * s
        s = new
        if done:
            break
    air = np.sort(v[v < cut * s])
    if air.size < MIN_AIR_FRACTION * v.size:
        return None
    # goodness of fit: the voxels taken as air follow the truncated Rayleigh distribution (largest
    # CDF difference, Kolmogorov-Smirnov); a scan without air converges on its darkest tissue instead
    air = air[:: max(1, air.size // 100_000)]
    cdf = -np.expm1(-0.5 * (air / s) ** 2) / -np.expm1(-0.5 * cut * cut)
    ks = np.max(np.abs(cdf - (np.arange(air.size) + 0.5) / air.size))
    return float(s) if ks <= MAX_KS else None


@functools.partial(jax.jit, static_argnames=("n_steps",))
def diffuse(y, k, n_steps: int = 5):
    """Perona-Malik anisotropic diffusion with g(d) = exp(-(d/k)^2), dt = 1/7, zero-flux border.

    Arguments:
        y: (x, y, z) image.
        k: edge threshold (image units, > 0), e.g. 2 * noise_sd(y).
        n_steps: explicit steps (flat regions: Gaussian smoothing of sd sqrt(2 n_steps / 7) voxels).
    Returns:
        (x, y, z) the diffused image (same dtype); its sum is conserved.
    """
    inv_k2 = 1.0 / (k * k)

    def step(_, u):
        div = jnp.zeros_like(u)
        for ax in range(3):
            n = u.shape[ax]
            g = lax.slice_in_dim(u, 1, n, axis=ax) - lax.slice_in_dim(u, 0, n - 1, axis=ax)
            flux = jnp.exp(-(g * g) * inv_k2) * g  # flux from voxel i+1 into voxel i
            zero = jnp.zeros_like(lax.slice_in_dim(u, 0, 1, axis=ax))
            div = div + jnp.concatenate([flux, zero], axis=ax) - jnp.concatenate([zero, flux], axis=ax)
        return u + DT * div

    return lax.fori_loop(0, n_steps, step, y)


#: sd of the log of a Rayleigh variable (the magnitude of air): sqrt(pi^2 / 24) (the log of an
#: exponential variable has variance pi^2 / 6; |z|^2 of complex Gaussian noise is exponential).
LOG_RAYLEIGH_SD = float(np.pi / np.sqrt(24.0))
#: `log_noise_table`: true signal / channel noise sd at which the noise is simulated (0 = air). Above
#: the last the log noise is sd / A (delta method; Rician -> Gaussian), which the table extends.
TABLE_SNR = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 11.0, 16.0, 23.0, 32.0, 45.0, 64.0)
#: `log_noise_table`: side of the simulated cube of homogeneous tissue (voxels; 2 per side are
#: dropped: the zero-flux border smooths less). 40^3 gives the sd to ~0.5 %.
TABLE_SIDE = 40


@functools.lru_cache(maxsize=16)
def log_noise_table(edge_factor: float, n_steps: int, side: int = TABLE_SIDE, seed: int = 0):
    """The noise a homogeneous tissue keeps in the log of an MRI magnitude image after `diffuse`.

    Measured by simulation, not assumed: for each true signal A = q * s (q in TABLE_SNR, s the channel
    noise sd, s = 1 without loss of generality: the edge threshold k = edge_factor * s scales with s),
    a cube of independent Rician voxels |A + s (z1 + i z2)| (Gudbjartsson & Patz 1995, MRM 34:910) is
    smoothed by `diffuse(., edge_factor * s, n_steps)`, and the mean m(q) and sd d(q) of its log taken
    over the interior. A Gaussian of the EM (log intensity) whose mean is log s + m(q) models a tissue
    at that SNR; no tissue's voxels are narrower than d(q) (the noise alone), so d is a floor for its
    sd. Perona-Malik is nonlinear in the noise (the flux falls off for neighbour steps over k), so the
    residual is not the linear filter's: with edge_factor 2 and 5 steps it is 0.17 of the noise at
    high SNR (a linear 5-step diffusion leaves 0.12) and 0.10 of the log-Rayleigh sd in air.

    Arguments:
        edge_factor: k / s of `diffuse` (> 0).
        n_steps: `diffuse` steps (>= 0; 0: the raw log-Rician noise, whose sd is LOG_RAYLEIGH_SD at
            q = 0 and 1 / q at high SNR).
        side, seed: the simulated cube (side^3 voxels) and its random seed.
    Returns:
        (m, d): float64 arrays, m increasing (mean log intensity minus log s) and d (the log sd) at
        TABLE_SNR.
    """
    if not (isinstance(edge_factor, (int, float)) and edge_factor > 0):
        raise ValueError(f"`edge_factor` must be a number > 0 (k / noise sd), got {edge_factor!r}.")
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 0:
        raise ValueError(f"`n_steps` must be an integer >= 0, got {n_steps!r}.")
    if side < 8:
        raise ValueError(f"`side` must be >= 8 voxels, got {side!r}.")
    rng = np.random.default_rng(seed)
    m, d = [], []
    c = (slice(2, -2),) * 3
    for q in TABLE_SNR:
        mag = np.hypot(q + rng.standard_normal((side,) * 3), rng.standard_normal((side,) * 3))
        u = np.asarray(diffuse(jnp.asarray(mag), float(edge_factor), int(n_steps))) if n_steps else mag
        lu = np.log(np.maximum(u[c], 1e-12))
        m.append(lu.mean())
        d.append(lu.std())
    m, d = np.asarray(m), np.asarray(d)
    if np.any(np.diff(m) <= 0):
        raise RuntimeError(f"log_noise_table: the simulated mean log intensities are not increasing: {m}.")
    return m, d
