"""Fitting tissue conductivities (and contact impedances, a gain) to measured voltages with optimistix.

Measured recordings need more than the plain fit (issue 15): per-electrode contact impedances
with a lognormal prior, an unknown current gain (a global scale: conductivities and contact
conductances are then determined only up to it, V(c sigma, z / c) = V(sigma, z) / c, so one
tissue must be fixed or given a prior), a free offset per injection for voltages measured
against a reference electrode whose potential is not what the file says, a robust loss with
channel rejection, and per-frequency fits (`fit_spectrum`). Free offsets are profiled out
(variable projection, Golub & Pereyra 1973): the whitened residual is projected onto the
complement of the offsets' columns, so estimates and standard errors are exactly invariant to
adding any constant per injection, and the standard errors are those of the joint fit with the
offsets as free parameters (the Schur complement of the Gauss-Newton matrix).

Parameters are fitted in log space, so they stay positive and steps are relative; bounds map
log-parameters through a sigmoid. The Gauss-Newton covariance at the optimum gives standard
errors and correlations (skull and scalp trade off against each other, see Horesh 2006, ch. 5;
inside a sphere brain and CSF do too: read `FitResult.correlation`).

The residual function is a module-level function and everything that changes between calls
(model, protocol, data, weights, bounds) travels in optimistix's `args`, so repeated fits on the
same model reuse one compilation (optimistix caches on the function's identity). Many noise
realisations are fitted in one vmapped solve by `fit_conductivities_batch`.
"""

import dataclasses
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..fem import simulate
from ..io import Measurements
from ..protocol import Protocol
from ..tissue import TISSUE_NAMES, Tissue
from .approx_error import ApproximationError
from .noise import noise_std as _channel_noise_std

_DEFAULT_RANGE = 1e3  # default bounds: init / 1e3 .. init * 1e3

#: A prior for CSF's conductivity, (S/m, relative sd): Baumann et al. 1997 (IEEE TBME 44:220)
#: measured 1.79 S/m at body temperature. With `gain=True` something must fix the common scale
#: of the conductivities; CSF is the best-known head conductivity.
CSF_PRIOR: tuple[float, float] = (1.79, 0.02)


class FitResult(eqx.Module):
    """The outcome of `fit_conductivities`.

    Attributes:
        sigma: (4,) conductivities in S/m, ordered BRAIN, CSF, SKULL, SCALP (unfitted ones = init).
        contact_impedance_ohm_m2: (n_elec,) Ohm m^2 (the initial ones scaled by the fitted factor).
        fitted: names of the fitted parameters, in the order of `std_error`/`correlation`.
        estimates: (n_fit,) fitted values (S/m; Ohm m^2 for "contact_impedance", the mean
            over electrodes).
        std_error: (n_fit,) Gauss-Newton standard errors, same units as `estimates` (they assume
            `noise_std`, plus an `approx_error`'s covariance when given, is the whole error:
            modelling errors left out of both are not in them).
        correlation: (n_fit, n_fit) correlation matrix of the estimates.
        residual_norm: || W (V(sigma) + offset - measured) || at the optimum, W the whitening
            (1 / noise_std, with an `approx_error` its covariance too; offset its mean, else 0).
        n_steps: optimiser steps.
        n_forward: forward-model evaluations, i.e. distinct FEM systems factorised (counted by
            the Direct solver; derivatives reuse each factor; in a batched fit, the batch's
            total divided by the batch size). Estimated as steps + 1 for iterative solvers.
        condition: condition number of the weighted J^T J (in log-parameters).
        result: optimistix's status (`optx.RESULTS`; `optx.RESULTS.successful` on success).
        success: `result == optx.RESULTS.successful`, as a Python bool.
        gain: the fitted (or fixed, 1) current gain: measured = gain * V(sigma) + offset.
        offsets: (n_inj,) V, the free offset of each injection (`protocol.injections` order)
            when `offsets="per_injection"`, else None.
        rejected: row indices of the channels rejected by `reject_sigma` (empty: none).
        residual_scale: 1.4826 x the median absolute whitened residual of the kept channels
            (about 1 when `noise_std` is right and the model fits).
    """

    sigma: np.ndarray
    contact_impedance_ohm_m2: np.ndarray | None
    fitted: tuple[str, ...] = eqx.field(static=True)
    estimates: np.ndarray = None
    std_error: np.ndarray = None
    correlation: np.ndarray = None
    residual_norm: float = 0.0
    n_steps: int = 0
    n_forward: int = 0
    condition: float = 0.0
    result: optx.RESULTS = eqx.field(default_factory=lambda: optx.RESULTS.successful)
    success: bool = True
    gain: float = 1.0
    offsets: np.ndarray | None = None
    rejected: np.ndarray = eqx.field(default_factory=lambda: np.zeros(0, np.int64))
    residual_scale: float = float("nan")

    def table(self, truth=None) -> str:
        """The estimates as a text table (with the relative error when `truth` (4,) S/m is given)."""
        head = f"{'parameter':<18}{'estimate':>12}{'std error':>12}{'rel SE %':>9}"
        if truth is not None:
            head += f"{'true':>10}{'error %':>9}"
        lines = [head]
        for name, e, s in zip(self.fitted, self.estimates, self.std_error):
            line = f"{name:<18}{e:>12.5g}{s:>12.3g}{100 * s / abs(e):>9.2f}"
            if truth is not None and name in TISSUE_NAMES:
                t = float(np.asarray(truth)[TISSUE_NAMES.index(name)])
                line += f"{t:>10.4g}{100 * (e / t - 1):>9.2f}"
            lines.append(line)
        lines.append(f"residual norm {self.residual_norm:.4g}, {self.n_steps} steps, "
                     f"{self.n_forward} forward solves, cond(J^T J) {self.condition:.3g}")
        if self.rejected.size:
            lines.append(f"rejected {self.rejected.size} channels (rows "
                         f"{self.rejected[:20].tolist()}{' ...' if self.rejected.size > 20 else ''}); "
                         f"robust residual scale {self.residual_scale:.3g}")
        return "\n".join(lines)


class LineSearchGaussNewton(optx.AbstractGaussNewton):
    """Gauss-Newton directions with a backtracking Armijo line search (an optimistix solver).

    Each step solves the linearised least-squares problem exactly (lineax QR), then halves the
    step until the loss decreases enough (Armijo). On the four-tissue fits of benchmarks/fit.py
    it needs a fraction of `optx.LevenbergMarquardt`'s forward solves, to the same estimates
    (experiments/results/fit_solvers.md): for small-residual problems with a full-rank Jacobian
    the Gauss-Newton step is nearly the Newton step (Nocedal & Wright 2006, sec. 10.3). It is
    `fit_conductivities`' default; prefer Levenberg-Marquardt when the Jacobian may be
    rank-deficient (a tissue the data do not see).

    Arguments:
        rtol, atol: optimistix's Cauchy termination tolerances.
    """

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: optx.NewtonDescent = optx.NewtonDescent()
    search: optx.BacktrackingArmijo = optx.BacktrackingArmijo()
    verbose: Callable = eqx.field(static=True, default=lambda **kwargs: None)


def _default_solver():
    return LineSearchGaussNewton(rtol=1e-6, atol=1e-6)


def _names(fit) -> tuple[str, ...]:
    if isinstance(fit, str):
        fit = (fit,)
    names = tuple(Tissue.parse(f).name.lower() for f in fit)
    for n in names:
        if n == "background":
            raise ValueError("`fit` cannot include background; use brain, csf, skull, scalp.")
    if len(set(names)) != len(names):
        raise ValueError(f"`fit` lists a tissue twice: {list(fit)}.")
    if not names:
        raise ValueError("`fit` is empty; name at least one tissue.")
    return names


class _Problem(eqx.Module):
    """Everything the residual function needs, as optimistix `args` (arrays are traced)."""

    model: object
    protocol: object
    measured: jax.Array   # (n_rows,) V
    weight: jax.Array     # (n_rows,) 1 / noise std
    offset: jax.Array     # (n_rows,) V added to the model (approx_error.mean; else zeros)
    basis: jax.Array      # (n_rows, r) whitening correction Q (r = 0 without approx_error)
    shrink: jax.Array     # (r,) its coefficients c: W x = w x + Q (c * Q^T (w x))
    init: jax.Array       # (4,) S/m
    z0: jax.Array         # (n_elec,) Ohm m^2
    lo: jax.Array         # (n_par,) log lower bounds
    hi: jax.Array         # (n_par,) log upper bounds
    keep: jax.Array       # (n_rows,) 1 for kept channels, 0 for rejected ones
    obasis: jax.Array     # (n_rows, k) orthonormal whitened offset columns (k = 0: no offsets)
    prior_mu: jax.Array   # (n_prior,) log prior means
    prior_sd: jax.Array   # (n_prior,) log prior standard deviations
    idx: tuple[int, ...] = eqx.field(static=True)
    fit_z: bool = eqx.field(static=True)
    n_z: int = eqx.field(static=True, default=0)          # 0, 1 (common factor), n_elec
    fit_gain: bool = eqx.field(static=True, default=False)
    prior_idx: tuple[int, ...] = eqx.field(static=True, default=())
    loss: str = eqx.field(static=True, default="linear")
    loss_scale: float = eqx.field(static=True, default=3.0)


def _to_log(theta, lo, hi):
    """Unconstrained theta -> bounded log-parameters lo + (hi - lo) sigmoid(theta)."""
    return lo + (hi - lo) * jax.nn.sigmoid(theta)


def _unpack(theta, p: _Problem):
    """Conductivities (4,), contact impedances (n_elec,), gain from theta."""
    logx = _to_log(theta, p.lo, p.hi)
    n = len(p.idx)
    sigma = p.init.at[jnp.asarray(p.idx)].set(jnp.exp(logx[:n]))
    z = p.z0 * jnp.exp(logx[n:n + p.n_z]) if p.n_z else p.z0
    gain = jnp.exp(logx[n + p.n_z]) if p.fit_gain else jnp.ones(())
    return sigma, z, gain


def _whiten(u, p: _Problem):
    u = p.weight * u
    return u + p.basis @ (p.shrink * (p.basis.T @ u))


def _robust(r, loss: str, c: float):
    """sign(r) sqrt(2 rho(r)): least squares on these minimises sum rho (Triggs et al. 2000).

    Written as r sqrt(2 rho(r) / r^2) with the ratio's series near 0, so it is smooth there.
    Huber: rho = r^2 / 2 (|r| <= c), c |r| - c^2 / 2; Cauchy: rho = c^2 / 2 log(1 + r^2 / c^2).
    """
    if loss == "linear":
        return r
    t = (r / c) ** 2
    small = t < 1e-8
    ts = jnp.where(small, 1.0, t)
    if loss == "cauchy":
        ratio = jnp.where(small, 1.0 - 0.5 * t, jnp.log1p(ts) / ts)
    else:  # huber
        ratio = jnp.where(t <= 1.0, 1.0, (2.0 * jnp.sqrt(ts) - 1.0) / ts)
    return r * jnp.sqrt(ratio)


def _residuals(theta, p: _Problem):
    """Whitened residuals W (g V(sigma(theta)) + offset - measured), offsets projected out, then
    the prior's rows (module level: compiled once)."""

    sigma, z, gain = _unpack(theta, p)
    v = gain * simulate(p.model, sigma, p.protocol, contact_impedance_ohm_m2=z)
    u = p.keep * _whiten(v + p.offset - p.measured, p)
    u = u - p.obasis @ (p.obasis.T @ u)
    u = _robust(u, p.loss, p.loss_scale)
    if p.prior_idx:
        logx = _to_log(theta, p.lo, p.hi)
        u = jnp.concatenate([u, (logx[jnp.asarray(p.prior_idx)] - p.prior_mu) / p.prior_sd])
    return u


@eqx.filter_jit
def _jacobian_log(theta, p: _Problem):
    """Residuals and their Jacobian w.r.t. the log-parameters, (n_res,), (n_res, n_par)."""
    J_theta = jax.jacfwd(_residuals)(theta, p)
    s = jax.nn.sigmoid(theta)
    dlog_dtheta = (p.hi - p.lo) * s * (1 - s)  # chain rule through the sigmoid
    return _residuals(theta, p), J_theta / dlog_dtheta[None, :]


def _offset_basis(protocol, weight, basis, shrink, keep) -> np.ndarray:
    """Orthonormal columns spanning W A, A (n_rows, n_inj) the injection indicator (kept rows)."""
    di = np.asarray(protocol.drive_index)
    A = np.zeros((di.size, int(di.max()) + 1))
    A[np.arange(di.size), di] = 1.0
    WA = weight[:, None] * A
    WA = keep[:, None] * (WA + basis @ (shrink[:, None] * (basis.T @ WA)))
    q, r = np.linalg.qr(WA)
    good = np.abs(np.diag(r)) > 1e-12 * np.abs(np.diag(r)).max()
    return q[:, good]


def _prepare(model, protocol, measured, *, init, fit, contact_impedance, noise_std, bounds,
             approx_error=None, gain=False, priors=None, contact_prior=None, offsets=None,
             loss="linear", loss_scale=3.0):
    """Validate inputs, build the `_Problem` (without data) and the start point theta0."""
    names = _names(fit)
    init = np.asarray(init, dtype=np.float64)
    if init.shape != (4,):
        raise ValueError(f"`init` has shape {init.shape}; pass 4 conductivities (S/m) ordered "
                         "BRAIN, CSF, SKULL, SCALP.")
    if not np.all(np.isfinite(init)) or np.any(init <= 0):
        raise ValueError(f"`init` must be finite and > 0 S/m (fitting is in log space), got {init.tolist()}.")
    rows = getattr(protocol, "rows", None)
    if rows is None or getattr(rows, "ndim", 0) != 2:
        raise ValueError(f"`protocol` must be a jaxhead Protocol, got {type(protocol).__name__}.")
    n_rows = rows.shape[0]
    measured = np.asarray(measured, dtype=np.float64)
    if measured.shape[-1:] != (n_rows,):
        raise ValueError(f"`measured` has shape {measured.shape}; the protocol has {n_rows} rows.")
    if not np.all(np.isfinite(measured)):
        bad = np.argwhere(~np.isfinite(measured))[0].tolist()
        raise ValueError(f"`measured` contains NaN or Inf (first at index {bad}); drop those "
                         "rows from the data and the protocol.")
    if noise_std is None:
        noise_std = 0.01 * float(np.sqrt(np.mean(measured**2)))
    std = np.broadcast_to(np.asarray(noise_std, np.float64), (n_rows,))
    if not np.all(np.isfinite(std) & (std > 0)):
        raise ValueError("`noise_std` must be finite and > 0 for every channel (V).")
    if approx_error is None:
        weight, offset = 1.0 / std, np.zeros(n_rows)
        basis, shrink = np.zeros((n_rows, 0)), np.zeros(0)
    else:
        if not isinstance(approx_error, ApproximationError):
            raise ValueError("`approx_error` must be an ApproximationError (from jaxhead."
                             "approximation_error(accurate, reduced, sigma_samples, protocol)), got "
                             f"{type(approx_error).__name__}.")
        if approx_error.mean.shape != (n_rows,):
            raise ValueError(f"`approx_error` has {approx_error.mean.shape[0]} rows; the "
                             f"protocol has {n_rows}: estimate it with the same protocol.")
        weight, basis, shrink = approx_error.whitener(std)
        offset = approx_error.mean
    if contact_impedance not in (False, True, "common", "per_electrode"):
        raise ValueError(f"`contact_impedance` = {contact_impedance!r}; use False, True "
                         "(one common factor), 'common' or 'per_electrode'.")
    n_elec = int(model.n_elec)
    n_z = 0 if contact_impedance is False else (n_elec if contact_impedance == "per_electrode"
                                               else 1)
    if offsets not in (None, "per_injection"):
        raise ValueError(f"`offsets` = {offsets!r}; use None or 'per_injection'.")
    if loss not in ("linear", "huber", "cauchy"):
        raise ValueError(f"`loss` = {loss!r}; use 'linear', 'huber' or 'cauchy'.")
    if not (isinstance(loss_scale, (int, float)) and loss_scale > 0):
        raise ValueError(f"`loss_scale` must be > 0 (noise standard deviations), got {loss_scale!r}.")
    priors = dict(priors or {})
    if gain and len(names) == 4 and not any(k in priors for k in names):
        raise ValueError(
            "with `gain=True` the data determine the conductivities only up to the gain: "
            "V(c sigma, z / c) = V(sigma, z) / c for any c > 0, so g, sigma and the contact "
            "conductances trade off exactly. Fix one tissue (leave it out of `fit`; it stays at "
            "`init`) or give one a prior, e.g. priors={'csf': (1.79, 0.02)} (CSF, Baumann et al. "
            "1997, is the best-known head conductivity).")

    idx = tuple(TISSUE_NAMES.index(n) for n in names)
    z_names = ([] if n_z == 0 else ["contact_impedance"] if n_z == 1 else
               [f"z:{n}" for n in model.electrode_names])
    labels = list(names) + z_names + (["gain"] if gain else [])
    bounds = dict(bounds or {})
    for key in bounds:
        if key not in labels and not (key == "contact_impedance" and n_z > 1):
            raise ValueError(f"`bounds` names {key!r}, which is not fitted; fitted: {labels}.")
    start = [float(init[i]) for i in idx] + [1.0] * n_z + ([1.0] if gain else [])
    z0 = np.asarray(model.contact_impedance_ohm_m2, np.float64)
    lo, hi = [], []
    for k, (name, x0) in enumerate(zip(labels, start)):
        key = "contact_impedance" if name.startswith("z:") else name
        b = bounds.get(key, (x0 / _DEFAULT_RANGE, x0 * _DEFAULT_RANGE))
        a, c = float(b[0]), float(b[1])
        if key == "contact_impedance" and n_z > 1 and key in bounds:  # Ohm m^2 -> factor
            a, c = a / z0[k - len(idx)], c / z0[k - len(idx)]
        if not 0 < a < x0 < c:
            raise ValueError(f"`bounds[{key!r}]` = {tuple(b)} must satisfy 0 < lo < init ({x0}) < hi.")
        lo.append(np.log(a))
        hi.append(np.log(c))
    lo, hi = np.asarray(lo), np.asarray(hi)
    # priors: log-normal, rows (log x - log mu) / sd appended to the residuals
    p_idx, p_mu, p_sd = [], [], []
    for key, val in priors.items():
        if key not in labels:
            raise ValueError(f"`priors` names {key!r}, which is not fitted; fitted: {labels}.")
        try:
            mu, sd = (float(v) for v in val)
        except (TypeError, ValueError):
            raise ValueError(f"`priors[{key!r}]` = {val!r}; give (value, relative sd), e.g. "
                             "(1.79, 0.02).") from None
        if not (mu > 0 and sd > 0):
            raise ValueError(f"`priors[{key!r}]` = {val!r}: value and sd must be > 0.")
        j = labels.index(key)
        p_idx.append(j)
        p_mu.append(np.log(mu))
        p_sd.append(sd)
    if contact_prior is not None:
        if n_z == 0:
            raise ValueError("`contact_prior` needs `contact_impedance` fitted.")
        if not (isinstance(contact_prior, (int, float)) and contact_prior > 1):
            raise ValueError(f"`contact_prior` is the prior's geometric standard deviation "
                             f"(a factor > 1, e.g. 2.0), got {contact_prior!r}.")
        for k in range(n_z):
            p_idx.append(len(idx) + k)
            p_mu.append(0.0)  # log factor 0: centred on the model's contact impedances
            p_sd.append(float(np.log(contact_prior)))
    u = (np.log(start) - lo) / (hi - lo)
    theta0 = jnp.asarray(np.log(u / (1 - u)))  # logit: the inverse of _to_log
    keep = np.ones(n_rows)
    obasis = (_offset_basis(protocol, weight, basis, shrink, keep) if offsets
              else np.zeros((n_rows, 0)))
    prob = _Problem(model=model, protocol=protocol, measured=jnp.zeros(n_rows),
                    weight=jnp.asarray(weight), offset=jnp.asarray(offset, jnp.float64),
                    basis=jnp.asarray(basis), shrink=jnp.asarray(shrink), init=jnp.asarray(init),
                    z0=jnp.asarray(z0), lo=jnp.asarray(lo), hi=jnp.asarray(hi),
                    keep=jnp.asarray(keep), obasis=jnp.asarray(obasis),
                    prior_mu=jnp.asarray(p_mu, jnp.float64), prior_sd=jnp.asarray(p_sd, jnp.float64),
                    idx=idx, fit_z=n_z > 0, n_z=n_z, fit_gain=bool(gain),
                    prior_idx=tuple(p_idx), loss=loss, loss_scale=float(loss_scale))
    return prob, theta0, labels, measured


def _factor_count(model):
    handle = getattr(getattr(model, "solver_state", None), "handle", None)
    return handle, getattr(handle, "n_factorisations", None)


def _with_keep(prob: _Problem, keep: np.ndarray, offsets: bool) -> _Problem:
    """The problem with channels `keep` (0/1) and, with offsets, their offset basis rebuilt."""
    prob = eqx.tree_at(lambda p: p.keep, prob, jnp.asarray(keep, jnp.float64))
    if offsets:
        ob = _offset_basis(prob.protocol, np.asarray(prob.weight), np.asarray(prob.basis),
                           np.asarray(prob.shrink), keep)
        prob = eqx.tree_at(lambda p: p.obasis, prob, jnp.asarray(ob))
    return prob


def _injection_matrix(protocol) -> np.ndarray:
    di = np.asarray(protocol.drive_index)
    A = np.zeros((di.size, int(di.max()) + 1))
    A[np.arange(di.size), di] = 1.0
    return A


def _fitted_offsets(theta, prob: _Problem) -> np.ndarray:
    """Per-injection offsets c minimising || keep W (g V + A c - measured) ||, (n_inj,) V."""
    sigma, z, gain = _unpack(theta, prob)
    v = np.asarray(gain * simulate(prob.model, sigma, prob.protocol, contact_impedance_ohm_m2=z))
    A = _injection_matrix(prob.protocol)
    keep = np.asarray(prob.keep)
    WA = keep[:, None] * np.asarray(jax.vmap(lambda a: _whiten(a, prob), 1, 1)(jnp.asarray(A)))
    rhs = keep * np.asarray(_whiten(prob.measured - prob.offset - v, prob))
    return np.linalg.lstsq(WA, rhs, rcond=None)[0]


def _all_residuals(theta, prob: _Problem, offsets: bool) -> np.ndarray:
    """Whitened residuals W (g V + offset + A c - measured) of every channel, rejected ones
    included, with the offsets c fitted to the kept channels (no robust transform)."""
    sigma, z, gain = _unpack(theta, prob)
    v = gain * simulate(prob.model, sigma, prob.protocol, contact_impedance_ohm_m2=z)
    if offsets:
        v = v + jnp.asarray(_injection_matrix(prob.protocol) @ _fitted_offsets(theta, prob))
    return np.asarray(_whiten(v + prob.offset - prob.measured, prob))


def _result(theta, prob: _Problem, labels, *, n_steps, n_forward, result, ill_conditioned,
            offsets=False, rejected=None):
    r, J = _jacobian_log(theta, prob)
    # Gauss-Newton covariance in log-parameters: (J^T J)^-1 for unit-variance weighted
    # residuals (Seber & Wild 1989, Nonlinear Regression, sec. 2.1); delta method dx = x dlog x.
    # With priors, J holds their rows too: the Laplace approximation of the posterior.
    jtj = np.asarray(J.T @ J)
    if not np.all(np.isfinite(jtj)):  # a failed (throw=False) fit can end on NaN
        cond, cov_log = np.inf, np.full_like(jtj, np.nan)
    else:
        cond = float(np.linalg.cond(jtj))
        cov_log = np.linalg.pinv(jtj)
    logx = np.asarray(_to_log(theta, prob.lo, prob.hi))
    est = np.exp(logx)
    sigma, z, gain = _unpack(theta, prob)
    n = len(prob.idx)
    if prob.n_z == 1:  # report the mean contact impedance, not the factor
        est[n] = est[n] * float(np.mean(np.asarray(prob.z0)))
    elif prob.n_z > 1:
        est[n:n + prob.n_z] = np.asarray(z)
    cov = cov_log * np.outer(est, est)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    corr = cov / np.outer(se, se) if np.all(se > 0) else np.full_like(cov, np.nan)
    if np.isfinite(cond) and cond > ill_conditioned:
        warnings.warn(
            f"J^T J is ill-conditioned (cond {cond:.2g} > {ill_conditioned:.0g}): the data barely "
            f"separate {labels}; skull and scalp (and, in spheres, brain and CSF) trade off. Fix "
            "one, add measurements, or read the correlations.", RuntimeWarning, stacklevel=3)
    du = _all_residuals(theta, prob, offsets)
    kept = np.asarray(prob.keep) > 0
    scale = float(1.4826 * np.median(np.abs(du[kept]))) if kept.any() else float("nan")
    return FitResult(
        sigma=np.asarray(sigma), contact_impedance_ohm_m2=np.asarray(z), fitted=tuple(labels),
        estimates=est, std_error=se, correlation=corr,
        residual_norm=float(jnp.linalg.norm(r)), n_steps=int(n_steps),
        n_forward=int(n_forward), condition=cond, result=result,
        success=bool(result == optx.RESULTS.successful), gain=float(gain),
        offsets=_fitted_offsets(theta, prob) if offsets else None,
        rejected=np.zeros(0, np.int64) if rejected is None else np.asarray(rejected, np.int64),
        residual_scale=scale)


def fit_conductivities(model, protocol, measured, *, init, fit: Sequence[str] = TISSUE_NAMES,
                       contact_impedance: bool | Literal["common", "per_electrode"] = False,
                       noise_std=None,
                       bounds: Mapping[str, tuple[float, float]] | None = None,
                       solver=None, max_steps: int = 100, throw: bool = True,
                       ill_conditioned: float = 1e8,
                       approx_error: ApproximationError | None = None,
                       gain: bool = False,
                       priors: Mapping[str, tuple[float, float]] | None = None,
                       contact_prior: float | None = None,
                       offsets: Literal["per_injection"] | None = None,
                       loss: Literal["linear", "huber", "cauchy"] = "linear",
                       loss_scale: float = 3.0,
                       reject_sigma: float | None = None,
                       max_reject_rounds: int = 5) -> FitResult:
    """Fit tissue conductivities to measured voltages by nonlinear least squares.

    The model of the data is measured = gain * V(sigma, z) + offset[injection] + noise.

    Arguments:
        model: a `ForwardModel` (`jaxhead.fem.build_forward_model`).
        protocol: the `Protocol` the voltages were measured with.
        measured: (n_rows,) measured voltages in V.
        init: (4,) initial conductivities in S/m, ordered BRAIN, CSF, SKULL, SCALP (all > 0).
        fit: the tissues to fit; the others stay at `init`.
        contact_impedance: False (fixed at the model's), True or "common" (one factor on the
            model's contact impedances; reported as their mean), or "per_electrode" (one
            factor per electrode, named "z:<electrode>"). Only rows measured on a
            current-carrying electrode see its contact impedance directly (its drop I z / |e|);
            on other electrodes it acts through their shunting, weakly, so per-electrode values
            need such rows or a `contact_prior` (the covariance shows which are determined).
        noise_std: per-channel (n_rows,) or scalar noise std in V; residuals are divided by it.
            Default: 1 % of the RMS of `measured` (a scale only; estimates do not depend on it,
            standard errors do).
        bounds: {"skull": (lo, hi), ...} in S/m (Ohm m^2 for "contact_impedance", applied to
            every electrode; a factor for "gain"); every parameter goes through a sigmoid in log
            space between its bounds. Default: init / 1000 to init * 1000 (and the same factors on
            the contact impedance), wide enough not to bias a fit and tight enough that a trial
            step of the optimiser cannot make the FEM matrix numerically singular.
        solver: an optimistix least-squares solver. Default `LineSearchGaussNewton(rtol=1e-6,
            atol=1e-6)`, the measured best (experiments/results/fit_solvers.md); pass
            `optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6)` when the data may not see a fitted
            tissue (a rank-deficient Jacobian). In the sigmoid-log parameters 1e-6 is a relative
            change of ~3e-6 in sigma, far below any standard error at realistic noise.
        max_steps: optimiser step limit.
        throw: raise when optimistix fails (else the failure is `result`, and `success=False`).
        ill_conditioned: warn when cond(J^T J) exceeds this.
        approx_error: an `ApproximationError` of `model` against a more accurate model of the
            head (`jaxhead.approximation_error`): its mean is added to the model's
            voltages and its covariance to the noise's, so residuals are whitened by
            (diag(noise_std^2) + Cov)^-1/2 and standard errors include the modelling error.
        gain: fit an unknown current gain g (measured = g V). Conductivities and contact
            conductances are then identifiable only relative to each other (the data fix
            g / sigma, not g and sigma): fix one tissue or give it a prior (an error otherwise).
        priors: {"csf": (value, sd), "gain": (1.0, 0.1), ...}: log-normal priors, the sd of
            the natural log (about the relative sd); appended as residual rows, so standard
            errors are the Laplace posterior's.
        contact_prior: with fitted contact impedances, a log-normal prior centred on the
            model's values with this geometric standard deviation (e.g. 2.0: a factor 2).
        offsets: "per_injection": a free voltage offset per injection (an unknown reference
            potential), profiled out exactly; estimates and standard errors do not change
            when any constant is added to an injection's voltages. The offsets are returned.
        loss: "linear" (least squares), or a robust "huber" / "cauchy" on the whitened
            residuals with scale `loss_scale` (noise standard deviations). "cauchy" is
            redescending (a far-off channel stops pulling), so it starts from the Huber fit.
        loss_scale: the robust loss's scale c (in noise standard deviations).
        reject_sigma: reject channels whose whitened residual exceeds this many robust
            standard deviations (1.4826 x median absolute residual) and refit on the rest with
            the linear loss, repeating until the set stops changing (`max_reject_rounds`);
            the rejected rows are reported (`FitResult.rejected`) and logged in `table()`.
            Standard errors are those of the final fit on the kept channels.
        max_reject_rounds: at most this many rejection rounds.

    Returns:
        A `FitResult`.
    """
    prob, theta0, labels, measured = _prepare(
        model, protocol, measured, init=init, fit=fit, contact_impedance=contact_impedance,
        noise_std=noise_std, bounds=bounds, approx_error=approx_error, gain=gain, priors=priors,
        contact_prior=contact_prior, offsets=offsets, loss=loss, loss_scale=loss_scale)
    if measured.ndim != 1:
        raise ValueError(f"`measured` has shape {measured.shape}; pass (n_rows,) voltages "
                         "(use fit_conductivities_batch for several data vectors).")
    if reject_sigma is not None and not (isinstance(reject_sigma, (int, float)) and reject_sigma > 0):
        raise ValueError(f"`reject_sigma` must be > 0 (robust standard deviations), got {reject_sigma!r}.")
    prob = eqx.tree_at(lambda p: p.measured, prob, jnp.asarray(measured))
    handle, count0 = _factor_count(model)
    solver = solver or _default_solver()
    n_steps = 0
    if prob.loss == "cauchy":
        # A redescending loss is only as good as its start: from a start far off, a channel
        # that alone determines a parameter (the rows measured on a current-carrying electrode
        # determine its contact impedance) can sit in the loss's flat tail, where it no longer
        # pulls, and the fit converges there. Seed 1 of experiments/measured_fit.py did: T8's
        # contact impedance at 4.5x the truth, its two rows at 370 and 420 robust SD, then
        # rejected as outliers. The convex Huber fit first gives the start (the usual remedy
        # for redescending M-estimates: start them from a robust, convex one; Maronna, Martin
        # & Yohai 2006, Robust Statistics: Theory and Methods).
        huber = dataclasses.replace(prob, loss="huber")
        sol = optx.least_squares(_residuals, solver, theta0, huber, max_steps=max_steps,
                                 throw=throw)
        n_steps += int(sol.stats.get("num_steps", 0))
        theta0 = sol.value
    sol = optx.least_squares(_residuals, solver, theta0, prob, max_steps=max_steps, throw=throw)
    n_steps += int(sol.stats.get("num_steps", 0))
    rejected = None
    if reject_sigma is not None:
        n_rows = measured.shape[0]
        keep = np.ones(n_rows)
        for _ in range(int(max_reject_rounds)):
            # residuals of all channels, the rejected ones included (so they can come back)
            du = _all_residuals(sol.value, prob, bool(offsets))
            s = 1.4826 * np.median(np.abs(du[keep > 0]))
            new_keep = (np.abs(du) <= reject_sigma * s).astype(float)
            if np.array_equal(new_keep, keep) and prob.loss == "linear":
                break
            keep = new_keep
            prob = dataclasses.replace(_with_keep(prob, keep, bool(offsets)), loss="linear")
            sol = optx.least_squares(_residuals, solver, sol.value, prob, max_steps=max_steps,
                                     throw=throw)
            n_steps += int(sol.stats.get("num_steps", 0))
        rejected = np.flatnonzero(keep == 0)
    n_forward = handle.n_factorisations - count0 if count0 is not None else n_steps + 1
    return _result(sol.value, prob, labels, n_steps=n_steps, n_forward=n_forward,
                   result=sol.result, ill_conditioned=ill_conditioned, offsets=bool(offsets),
                   rejected=rejected)


def fit_conductivities_batch(model, protocol, measured, *, init,
                             fit: Sequence[str] = TISSUE_NAMES, contact_impedance: bool = False,
                             noise_std=None, bounds=None, solver=None, max_steps: int = 100,
                             throw: bool = True, ill_conditioned: float = 1e8,
                             approx_error: ApproximationError | None = None) -> list[FitResult]:
    """Fit many data vectors (e.g. noise realisations) in one `vmap`ped optimistix solve.

    The same as calling `fit_conductivities` on each row of `measured` (same arguments, one
    shared `noise_std`), but traced and compiled once, with every optimiser step evaluated for
    the whole batch. The solve loop runs until the slowest member converges.

    Arguments:
        measured: (n_batch, n_rows) voltages in V.
        Others: as `fit_conductivities`.

    Returns:
        One `FitResult` per row of `measured`.
    """
    prob, theta0, labels, measured = _prepare(
        model, protocol, measured, init=init, fit=fit, contact_impedance=contact_impedance,
        noise_std=noise_std, bounds=bounds, approx_error=approx_error)
    if measured.ndim != 2 or measured.shape[0] < 1:
        raise ValueError(f"`measured` has shape {measured.shape}; pass (n_batch, n_rows).")
    handle, count0 = _factor_count(model)
    solver = solver or _default_solver()

    @eqx.filter_vmap(in_axes=(eqx.if_array(0), None))
    def solve(m, p):
        p = eqx.tree_at(lambda q: q.measured, p, m)
        sol = optx.least_squares(_residuals, solver, theta0, p, max_steps=max_steps,
                                 throw=throw)
        return sol.value, sol.result, sol.stats["num_steps"]

    thetas, results, steps = solve(jnp.asarray(measured), prob)
    b = measured.shape[0]
    n_forward = ((handle.n_factorisations - count0) / b if count0 is not None
                 else float(np.max(steps)) + 1)
    out = []
    for i in range(b):
        p = eqx.tree_at(lambda q: q.measured, prob, jnp.asarray(measured[i]))
        out.append(_result(thetas[i], p, labels, n_steps=int(steps[i]),
                           n_forward=round(n_forward),
                           result=jax.tree.map(lambda x, i=i: x[i], results),
                           ill_conditioned=ill_conditioned))
    return out


class Spectrum(eqx.Module):
    """Per-frequency fits of one recording (`fit_spectrum`).

    Attributes:
        frequencies_hz: (n_freq,) Hz.
        results: one `FitResult` per frequency.
    """

    frequencies_hz: np.ndarray
    results: tuple[FitResult, ...]

    @property
    def fitted(self) -> tuple[str, ...]:
        return self.results[0].fitted

    @property
    def estimates(self) -> np.ndarray:
        """(n_freq, n_fit) estimates (S/m; Ohm m^2 for contact impedances; gain: factor)."""
        return np.stack([r.estimates for r in self.results])

    @property
    def std_error(self) -> np.ndarray:
        """(n_freq, n_fit) standard errors, same units."""
        return np.stack([r.std_error for r in self.results])

    def table(self, columns: Sequence[str] | None = None) -> str:
        """Estimate +- standard error of each fitted parameter (default: tissues and gain) per
        frequency, as text (one line per frequency)."""
        cols = [c for c in (columns or self.fitted) if columns or not c.startswith("z:")]
        idx = [self.fitted.index(c) for c in cols]
        head = f"{'f (Hz)':>10}" + "".join(f"{c:>22}" for c in cols) + f"{'rejected':>10}"
        lines = [head]
        for f, r in zip(self.frequencies_hz, self.results):
            lines.append(f"{f:>10.4g}" + "".join(
                f"{r.estimates[i]:>12.5g} +- {r.std_error[i]:<7.2g}" for i in idx)
                + f"{r.rejected.size:>10d}")
        return "\n".join(lines)

    def to_csv(self, path) -> None:
        """frequency_hz, then estimate and std error of every fitted parameter."""
        head = ["frequency_hz"] + [f"{c}{s}" for c in self.fitted for s in ("", "_se")]
        rows = [[f] + [v for pair in zip(r.estimates, r.std_error) for v in pair]
                for f, r in zip(self.frequencies_hz, self.results)]
        np.savetxt(path, np.asarray(rows), delimiter=",", header=",".join(head), comments="")

    def plot(self, path=None, tissues: Sequence[str] = TISSUE_NAMES):
        """Conductivity spectra with +-1 SE bars (log frequency axis); saved when `path`."""
        import matplotlib.pyplot as plt  # optional, drawing only

        fig, ax = plt.subplots(figsize=(6, 4))
        for t in tissues:
            if t in self.fitted:
                i = self.fitted.index(t)
                ax.errorbar(self.frequencies_hz, self.estimates[:, i], self.std_error[:, i],
                            marker="o", capsize=3, label=t)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel("conductivity (S/m)")
        ax.legend()
        fig.tight_layout()
        if path is not None:
            fig.savefig(path, dpi=120)
            plt.close(fig)
        return fig


def fit_spectrum(model, measurements: Measurements, *, init, frequencies_hz=None,
                 noise_percent: float | None = None, noise_floor: float = 0.0,
                 **fit_kwargs) -> Spectrum:
    """Fit every frequency of a recording (or the chosen ones), each started at the previous
    frequency's estimate: conductivity spectra with standard errors.

    Arguments:
        model: a `ForwardModel` whose electrodes are the recording's, in its order.
        measurements: a `jaxhead.io.Measurements` (`load_measurements`).
        init: (4,) S/m starting point of the first frequency.
        frequencies_hz: frequencies to fit (each must be in the file); default all.
        noise_percent: per-channel noise std as this % of |measured| at each frequency
            (else `fit_kwargs["noise_std"]`, or the fit's default).
        noise_floor: with `noise_percent`, the % refers to max(|measured|, noise_floor x RMS)
            per channel (`jaxhead.inverse.noise_std`).
        fit_kwargs: passed to `fit_conductivities` (fit, gain, offsets, reject_sigma, ...).

    Returns:
        A `Spectrum` (table, CSV, plot).
    """
    if not isinstance(measurements, Measurements):
        raise ValueError(f"`measurements` must be a jaxhead.io.Measurements (load_measurements), "
                         f"got {type(measurements).__name__}.")
    if measurements.n_elec != model.n_elec:
        raise ValueError(f"{measurements.source}: the recording has {measurements.n_elec} "
                         f"electrodes, the model {model.n_elec}; place the recording's electrodes.")
    freqs = (measurements.frequencies_hz if frequencies_hz is None
             else np.atleast_1d(np.asarray(frequencies_hz, np.float64)))
    cols = [measurements.frequency_index(f) for f in freqs] if frequencies_hz is not None \
        else list(range(measurements.voltages.shape[0]))
    protocol = Protocol(measurements.rows, measurements.current_a)
    start = np.asarray(init, np.float64)
    out = []
    for k in cols:
        v = measurements.voltages[k]
        kw = dict(fit_kwargs)
        if noise_percent is not None:
            kw["noise_std"] = _channel_noise_std(v, noise_percent, floor=noise_floor)
        res = fit_conductivities(model, protocol, v, init=start, **kw)
        out.append(res)
        start = res.sigma
    return Spectrum(frequencies_hz=np.asarray(measurements.frequencies_hz)[cols],
                    results=tuple(out))
