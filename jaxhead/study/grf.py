"""Gaussian random fields on surfaces: smooth random normal displacements of an interface.  [host]

The field is the restriction to the surface's vertices of a stationary Gaussian field in 3D with
the squared-exponential kernel

    C(x, y) = sd^2 exp(-|x - y|^2 / (2 l^2)),

sd the amplitude (mm) and l the correlation length (mm). The restriction of a valid 3D kernel
to any point set is positive semi-definite, so no geodesic distances are needed (for l well
below the head's radius chordal and geodesic distances agree to O(l^3 / R^2)).

Two samplers with the same covariance:
- "cholesky": exact, C = L L^T (with a jitter of 1e-10 sd^2 on the diagonal, far below any
  displacement that matters); O(n^3), chosen for n <= 4000 vertices.
- "fourier": random Fourier features (Rahimi & Recht 2007): f(x) = sd sqrt(2/M) sum_m a_m
  cos(w_m . x + b_m) with a_m ~ N(0, 1), w_m ~ N(0, I / l^2), b_m ~ U(0, 2 pi), all drawn
  afresh per sample. E[f(x) f(y)] = sd^2 E[cos(w . (x - y))] = C(x, y) exactly (Bochner); each
  sample is Gaussian given (w, b) and close to Gaussian overall for M in the thousands. O(n M).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.linalg

Method = Literal["auto", "cholesky", "fourier"]

#: Above this many vertices "auto" switches from the exact Cholesky sampler to Fourier features.
CHOLESKY_MAX_VERTICES = 4000


def _check(points, sd_mm, correlation_mm):
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
        raise ValueError(f"`points` must have shape (n, 3) in mm, got {p.shape}.")
    if not np.isfinite(sd_mm) or sd_mm < 0:
        raise ValueError(f"`sd_mm` (displacement amplitude) must be finite and >= 0 mm, got "
                         f"{sd_mm}; use e.g. 0.5 for half a millimetre.")
    if not np.isfinite(correlation_mm) or correlation_mm <= 0:
        raise ValueError(f"`correlation_mm` must be finite and > 0 mm, got {correlation_mm}; "
                         "use e.g. 20 for smooth, head-scale displacements.")
    return p


def grf_covariance(points, sd_mm: float, correlation_mm: float) -> np.ndarray:
    """The squared-exponential covariance between points, (n, n) in mm^2.

    Arguments:
        points: (n, 3) positions in mm.
        sd_mm: standard deviation of the field in mm.
        correlation_mm: correlation length l in mm (C = sd^2 exp(-d^2 / (2 l^2))).
    """
    p = _check(points, sd_mm, correlation_mm)
    sq = np.sum(p * p, axis=1)
    d2 = np.maximum(sq[:, None] + sq[None, :] - 2.0 * p @ p.T, 0.0)
    return sd_mm**2 * np.exp(-d2 / (2.0 * correlation_mm**2))


def sample_grf(points, sd_mm: float, correlation_mm: float, *, n_samples: int = 1, seed: int = 0,
               method: Method = "auto", n_features: int = 4000) -> np.ndarray:
    """Samples of the zero-mean squared-exponential Gaussian field at `points`.

    Arguments:
        points: (n, 3) positions in mm (e.g. an interface's vertices).
        sd_mm: amplitude (standard deviation) in mm, >= 0.
        correlation_mm: correlation length in mm, > 0.
        n_samples: number of independent samples.
        seed: NumPy random seed (the same seed gives the same samples).
        method: "cholesky" (exact), "fourier" (random Fourier features, same covariance) or
            "auto" (Cholesky up to CHOLESKY_MAX_VERTICES points).
        n_features: Fourier features per sample (method "fourier").

    Returns:
        (n_samples, n) field values in mm.
    """
    p = _check(points, sd_mm, correlation_mm)
    if int(n_samples) < 1:
        raise ValueError(f"`n_samples` must be >= 1, got {n_samples}.")
    if method not in ("auto", "cholesky", "fourier"):
        raise ValueError(f"`method` = {method!r}; use 'auto', 'cholesky' or 'fourier'.")
    rng = np.random.default_rng(seed)
    n = p.shape[0]
    if sd_mm == 0:
        return np.zeros((int(n_samples), n))
    if method == "cholesky" or (method == "auto" and n <= CHOLESKY_MAX_VERTICES):
        C = grf_covariance(p, sd_mm, correlation_mm)
        C[np.diag_indices(n)] += 1e-10 * sd_mm**2
        L = scipy.linalg.cholesky(C, lower=True)
        return (L @ rng.standard_normal((n, int(n_samples)))).T
    m = int(n_features)
    if m < 1:
        raise ValueError(f"`n_features` must be >= 1, got {n_features}.")
    out = np.empty((int(n_samples), n))
    centred = p - p.mean(axis=0)  # the field is stationary; centring only helps round-off
    for s in range(int(n_samples)):
        w = rng.standard_normal((m, 3)) / correlation_mm
        b = rng.uniform(0.0, 2.0 * np.pi, m)
        a = rng.standard_normal(m)
        out[s] = sd_mm * np.sqrt(2.0 / m) * (np.cos(centred @ w.T + b) @ a)
    return out
