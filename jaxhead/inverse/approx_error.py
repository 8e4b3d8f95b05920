"""The approximation-error model: a reduced forward model's error, estimated and accounted for.

A fit uses a mesh coarse enough to solve many times; the data come from the head, which a finer
mesh represents better. Their difference eps(sigma) = V_accurate(sigma) - V_reduced(sigma) is a
modelling error, not noise, and a least-squares fit pushes it into the conductivities (on the
phantom head, a voltage mismatch of about 1 % biased brain and CSF several times more:
experiments/results/cross_mesh_fit.txt). The Bayesian approximation-error
approach (Kaipio & Somersalo 2005, Statistical and Computational Inverse Problems, sec. 7.4;
Kaipio & Somersalo 2007, J. Comput. Appl. Math. 198:493; for EIT Nissinen, Heikkinen & Kaipio
2008, Meas. Sci. Technol. 19:015501) draws conductivities from a prior, computes eps on each draw
with both models, and treats eps as Gaussian with that sample mean and covariance, independent of
the noise. The fit then models the data as V_reduced(sigma) + mean + e, with e's covariance
Gamma = diag(noise_std^2) + Cov(eps): the mean removes the systematic part and the covariance
down-weights the channel patterns the reduced model cannot be trusted on.

What it does not cover: errors the two models share. If the head's geometry differs from both
(segmentation, surface extraction), that error stays, and the fit's standard errors, which now
include only the modelled part, understate it. On the phantom head the model removed the
mesh-discretisation bias in brain and CSF, but data from other surfaces of the same label map
still moved brain and CSF by far more than their standard errors
(experiments/results/cross_mesh_fit.txt, from experiments/cross_mesh_fit.py).

`approximation_error` builds the estimate (one solve per draw and model);
`fit_conductivities(..., approx_error=...)` uses it. The accurate model is typically a refined
mesh of the same head, meshed once; the estimate serves every fit on the reduced mesh with that
protocol and those electrodes.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np

from ..fem import simulate
from ..protocol import Protocol
from ..tissue import default_sigma


class ApproximationError(eqx.Module):
    """Sample statistics of eps = V_accurate - V_reduced over prior draws of the conductivities.

    Attributes:
        mean: (n_rows,) mean error in V.
        deviations: (n_samples, n_rows) (eps_i - mean) / sqrt(n_samples - 1), so that the sample
            covariance is `deviations.T @ deviations` (kept in this low-rank form: n_rows x
            n_rows would be 100 MB for a 3,600-row protocol).
        sigma_samples: (n_samples, 4) the conductivity draws (S/m), BRAIN, CSF, SKULL, SCALP.
    """

    mean: np.ndarray
    deviations: np.ndarray
    sigma_samples: np.ndarray

    def __check_init__(self):
        if self.mean.ndim != 1 or self.deviations.ndim != 2 \
                or self.deviations.shape[1] != self.mean.shape[0]:
            raise ValueError(f"ApproximationError: `mean` {self.mean.shape} and `deviations` "
                             f"{self.deviations.shape} must be (n_rows,) and (n_samples, n_rows).")

    @property
    def n_samples(self) -> int:
        return int(self.sigma_samples.shape[0])

    def covariance(self) -> np.ndarray:
        """The (n_rows, n_rows) sample covariance in V^2 (dense; for inspection)."""
        return self.deviations.T @ self.deviations

    def whitener(self, noise_std) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Factors of a whitening matrix W with W^T W = (diag(noise_std^2) + Cov(eps))^-1.

        With D = diag(noise_std) and A = D^-1 deviations.T = Q S R^T (thin SVD), the total
        covariance is D (I + A A^T) D, and W = (I + A A^T)^(-1/2) D^-1 = (I + Q diag(c) Q^T) D^-1
        with c = (1 + s^2)^(-1/2) - 1: exact, and O(n_rows n_samples) to apply.

        Arguments:
            noise_std: (n_rows,) or scalar measurement-noise standard deviation in V (> 0).

        Returns:
            (weight (n_rows,) = 1 / noise_std, basis Q (n_rows, r), shrink c (r,)); apply as
            u = weight * r; W r = u + Q (c * (Q^T u)).
        """
        n = self.mean.shape[0]
        std = np.broadcast_to(np.asarray(noise_std, np.float64), (n,))
        if not np.all(np.isfinite(std) & (std > 0)):
            raise ValueError("`noise_std` must be finite and > 0 for every channel (V).")
        weight = 1.0 / std
        A = self.deviations.T * weight[:, None]
        Q, s, _ = np.linalg.svd(A, full_matrices=False)
        keep = s > s[0] * 1e-12 if s.size else s > 0
        return weight, Q[:, keep], 1.0 / np.sqrt(1.0 + s[keep] ** 2) - 1.0


def sample_conductivities(n: int, *, centre=None, log_sd=0.25, seed: int = 0) -> np.ndarray:
    """Draws from a log-normal prior on the four tissue conductivities.

    Arguments:
        n: number of draws (>= 2).
        centre: (4,) median conductivities in S/m (default `jaxhead.tissue.default_sigma()`).
        log_sd: scalar or (4,) standard deviation of log(sigma); 0.25 spans about x0.6 to x1.6
            (95 %), the spread of published values for brain, CSF and scalp; pass a larger one
            for the skull (published values span 0.004-0.03 S/m) when that is the prior.
        seed: random seed.

    Returns:
        (n, 4) conductivities in S/m.
    """
    if int(n) < 2:
        raise ValueError(f"`n` must be >= 2 (a covariance needs two draws), got {n}.")
    c = default_sigma() if centre is None else np.asarray(centre, np.float64)
    if c.shape != (4,) or not np.all(c > 0):
        raise ValueError("`centre` must be 4 conductivities > 0 (S/m), got "
                         f"{np.asarray(c).tolist()}.")
    sd = np.broadcast_to(np.asarray(log_sd, np.float64), (4,))
    if not np.all(np.isfinite(sd) & (sd >= 0)):
        raise ValueError(f"`log_sd` must be >= 0, got {np.asarray(log_sd).tolist()}.")
    z = np.random.default_rng(seed).standard_normal((int(n), 4))
    return c * np.exp(sd * z)


def approximation_error(accurate, reduced, sigma_samples, protocol) -> ApproximationError:
    """Estimate the reduced model's approximation error over prior draws of the conductivities.

    Argument order as `simulate(model, sigma, protocol)`: the models, then the conductivities,
    then the protocol.

    Arguments:
        accurate: `ForwardModel` that stands in for the head (a finer mesh of it).
        reduced: `ForwardModel` the fits will use; same electrodes (count and order) as `accurate`.
        sigma_samples: (n_samples, 4) conductivities in S/m (`sample_conductivities`); 20-50 draws
            are usual (the covariance has rank n_samples - 1).
        protocol: the `Protocol` of the measurements.

    Returns:
        A `ApproximationError`.
    """

    if isinstance(sigma_samples, Protocol) and not isinstance(protocol, Protocol):
        raise ValueError("approximation_error takes (accurate, reduced, sigma_samples, protocol) "
                         "since issue 16 (the order of simulate); the protocol came third: swap "
                         "the last two arguments.")
    if not isinstance(protocol, Protocol):
        raise ValueError(f"`protocol` must be a Protocol (e.g. jaxhead.adjacent(n)), got "
                         f"{type(protocol).__name__}.")
    s = np.asarray(sigma_samples, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 4 or s.shape[0] < 2:
        raise ValueError(f"`sigma_samples` has shape {s.shape}; pass (n_samples >= 2, 4) "
                         "conductivities (S/m), e.g. from sample_conductivities.")
    if not np.all(np.isfinite(s) & (s > 0)):
        raise ValueError("`sigma_samples` must be finite and > 0 (S/m).")
    na, nr = accurate.n_elec, reduced.n_elec
    if na != nr:
        raise ValueError(f"`accurate` has {na} electrodes and `reduced` {nr}; place the same "
                         "electrodes (same positions, same order) on both meshes.")
    eps = np.stack([np.asarray(simulate(accurate, x, protocol))
                    - np.asarray(simulate(reduced, x, protocol)) for x in s])
    mean = eps.mean(axis=0)
    return ApproximationError(mean=mean, deviations=(eps - mean) / np.sqrt(len(s) - 1),
                      sigma_samples=s)
