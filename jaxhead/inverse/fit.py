"""Fitting tissue conductivities (and a contact impedance) to measured voltages with optimistix.

Parameters are fitted in log space, so they stay positive and steps are relative; bounds map
log-parameters through a sigmoid. The Gauss-Newton covariance at the optimum gives standard
errors and correlations (skull and scalp trade off against each other, see Horesh 2006, ch. 5;
inside a sphere brain and CSF do too: read `FitResult.correlation`).

The residual function is a module-level function and everything that changes between calls
(model, protocol, data, weights, bounds) travels in optimistix's `args`, so repeated fits on the
same model reuse one compilation (optimistix caches on the function's identity). Many noise
realisations are fitted in one vmapped solve by `fit_conductivities_batch`.
"""

import warnings
from collections.abc import Callable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..fem import simulate
from ..tissue import TISSUE_NAMES, Tissue
from .approx_error import ApproximationError

_DEFAULT_RANGE = 1e3  # default bounds: init / 1e3 .. init * 1e3


class FitResult(eqx.Module):
    """The outcome of `fit_conductivities`.

    Attributes:
        sigma: (4,) conductivities in S/m, ordered BRAIN, CSF, SKULL, SCALP (unfitted ones = init).
        contact_impedance: (n_elec,) Ohm m^2 (the initial ones scaled by the fitted factor).
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
    """

    sigma: np.ndarray
    contact_impedance: np.ndarray | None
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
        return "\n".join(lines)


class LineSearchGaussNewton(optx.AbstractGaussNewton):
    """Gauss-Newton directions with a backtracking Armijo line search (an optimistix solver).

    Each step solves the linearised least-squares problem exactly (lineax QR), then halves the
    step until the loss decreases enough (Armijo). On the four-tissue fits of
    benchmarks/fit.py it converges in 11-16 steps and 14-24 forward solves where
    `optx.LevenbergMarquardt` takes 23-37 steps and 54-81 solves, to the same estimates: for
    small-residual problems with a full-rank Jacobian the Gauss-Newton step is nearly the Newton
    step (Nocedal & Wright 2006, sec. 10.3). It is `fit_conductivities`' default; prefer
    Levenberg-Marquardt when the Jacobian may be rank-deficient (a tissue the data do not see).

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
    idx: tuple[int, ...] = eqx.field(static=True)
    fit_z: bool = eqx.field(static=True)


def _to_log(theta, lo, hi):
    """Unconstrained theta -> bounded log-parameters lo + (hi - lo) sigmoid(theta)."""
    return lo + (hi - lo) * jax.nn.sigmoid(theta)


def _unpack(theta, p: _Problem):
    logx = _to_log(theta, p.lo, p.hi)
    n = len(p.idx)
    sigma = p.init.at[jnp.asarray(p.idx)].set(jnp.exp(logx[:n]))
    z = p.z0 * jnp.exp(logx[n]) if p.fit_z else p.z0
    return sigma, z


def _residuals(theta, p: _Problem):
    """Whitened residuals W (V(sigma(theta)) + offset - measured) (module level: compiled once)."""

    sigma, z = _unpack(theta, p)
    v = simulate(p.model, sigma, p.protocol, contact_impedance=z)
    u = p.weight * (v + p.offset - p.measured)
    return u + p.basis @ (p.shrink * (p.basis.T @ u))


@eqx.filter_jit
def _jacobian_log(theta, p: _Problem):
    """Residuals and their Jacobian w.r.t. the log-parameters, (n_rows,), (n_rows, n_par)."""
    J_theta = jax.jacfwd(_residuals)(theta, p)
    s = jax.nn.sigmoid(theta)
    dlog_dtheta = (p.hi - p.lo) * s * (1 - s)  # chain rule through the sigmoid
    return _residuals(theta, p), J_theta / dlog_dtheta[None, :]


def _prepare(model, protocol, measured, *, init, fit, contact_impedance, noise_std, bounds,
             approx_error=None):
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
        raise ValueError("`measured` contains NaN or Inf.")
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
                             "approximation_error(accurate, reduced, protocol, ...)), got "
                             f"{type(approx_error).__name__}.")
        if approx_error.mean.shape != (n_rows,):
            raise ValueError(f"`approx_error` has {approx_error.mean.shape[0]} rows; the "
                             f"protocol has {n_rows}: estimate it with the same protocol.")
        weight, basis, shrink = approx_error.whitener(std)
        offset = approx_error.mean

    idx = tuple(TISSUE_NAMES.index(n) for n in names)
    labels = list(names) + (["contact_impedance"] if contact_impedance else [])
    bounds = dict(bounds or {})
    for key in bounds:
        if key not in labels:
            raise ValueError(f"`bounds` names {key!r}, which is not fitted; fitted: {labels}.")
    start = [float(init[i]) for i in idx] + ([1.0] if contact_impedance else [])
    lo, hi = [], []
    for name, x0 in zip(labels, start):
        b = bounds.get(name, (x0 / _DEFAULT_RANGE, x0 * _DEFAULT_RANGE))
        a, c = float(b[0]), float(b[1])
        if not 0 < a < x0 < c:
            raise ValueError(f"`bounds[{name!r}]` = {tuple(b)} must satisfy 0 < lo < init ({x0}) < hi.")
        lo.append(np.log(a))
        hi.append(np.log(c))
    lo, hi = np.asarray(lo), np.asarray(hi)
    u = (np.log(start) - lo) / (hi - lo)
    theta0 = jnp.asarray(np.log(u / (1 - u)))  # logit: the inverse of _to_log
    prob = _Problem(model=model, protocol=protocol, measured=jnp.zeros(n_rows),
                    weight=jnp.asarray(weight), offset=jnp.asarray(offset, jnp.float64),
                    basis=jnp.asarray(basis), shrink=jnp.asarray(shrink), init=jnp.asarray(init),
                    z0=jnp.asarray(model.contact_impedance, jnp.float64), lo=jnp.asarray(lo),
                    hi=jnp.asarray(hi), idx=idx, fit_z=bool(contact_impedance))
    return prob, theta0, labels, measured


def _factor_count(model):
    handle = getattr(getattr(model, "solver_state", None), "handle", None)
    return handle, getattr(handle, "n_factorisations", None)


def _result(theta, prob: _Problem, labels, *, n_steps, n_forward, result, ill_conditioned):
    r, J = _jacobian_log(theta, prob)
    # Gauss-Newton covariance in log-parameters: (J^T J)^-1 for unit-variance weighted
    # residuals (Seber & Wild 1989, Nonlinear Regression, sec. 2.1); delta method dx = x dlog x.
    jtj = np.asarray(J.T @ J)
    if not np.all(np.isfinite(jtj)):  # a failed (throw=False) fit can end on NaN
        cond, cov_log = np.inf, np.full_like(jtj, np.nan)
    else:
        cond = float(np.linalg.cond(jtj))
        cov_log = np.linalg.pinv(jtj)
    logx = np.asarray(_to_log(theta, prob.lo, prob.hi))
    est = np.exp(logx)
    sigma, z = _unpack(theta, prob)
    if prob.fit_z:  # report the mean contact impedance, not the factor
        est[-1] = est[-1] * float(np.mean(np.asarray(prob.z0)))
    cov = cov_log * np.outer(est, est)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    corr = cov / np.outer(se, se) if np.all(se > 0) else np.full_like(cov, np.nan)
    if np.isfinite(cond) and cond > ill_conditioned:
        warnings.warn(
            f"J^T J is ill-conditioned (cond {cond:.2g} > {ill_conditioned:.0g}): the data barely "
            f"separate {labels}; skull and scalp (and, in spheres, brain and CSF) trade off. Fix "
            "one, add measurements, or read the correlations.", RuntimeWarning, stacklevel=3)
    return FitResult(
        sigma=np.asarray(sigma), contact_impedance=np.asarray(z), fitted=tuple(labels),
        estimates=est, std_error=se, correlation=corr,
        residual_norm=float(jnp.linalg.norm(r)), n_steps=int(n_steps),
        n_forward=int(n_forward), condition=cond, result=result,
        success=bool(result == optx.RESULTS.successful))


def fit_conductivities(model, protocol, measured, *, init, fit: Sequence[str] = TISSUE_NAMES,
                       contact_impedance: bool = False, noise_std=None,
                       bounds: Mapping[str, tuple[float, float]] | None = None,
                       solver=None, max_steps: int = 100, throw: bool = True,
                       ill_conditioned: float = 1e8,
                       approx_error: ApproximationError | None = None) -> FitResult:
    """Fit tissue conductivities to measured voltages by nonlinear least squares.

    Arguments:
        model: a `ForwardModel` (`jaxhead.fem.build_forward_model`).
        protocol: the `Protocol` the voltages were measured with.
        measured: (n_rows,) measured voltages in V.
        init: (4,) initial conductivities in S/m, ordered BRAIN, CSF, SKULL, SCALP (all > 0).
        fit: the tissues to fit; the others stay at `init`.
        contact_impedance: also fit one common factor on the model's contact impedances (drive
            electrodes only inform it: with measurements on non-driving electrodes it is weakly
            identifiable, which the covariance will show).
        noise_std: per-channel (n_rows,) or scalar noise std in V; residuals are divided by it.
            Default: 1 % of the RMS of `measured` (a scale only; estimates do not depend on it,
            standard errors do).
        bounds: {"skull": (lo, hi), ...} in S/m; every parameter goes through a sigmoid in log
            space between its bounds. Default: init / 1000 to init * 1000 (and the same factors on
            the contact impedance), wide enough not to bias a fit and tight enough that a trial
            step of the optimiser cannot make the FEM matrix numerically singular.
        solver: an optimistix least-squares solver. Default `LineSearchGaussNewton(rtol=1e-6,
            atol=1e-6)`, the measured best (`benchmarks/fit.py`: 14 forward solves where
            `optx.LevenbergMarquardt` took 174 on a held-out sphere, to the same estimates); pass
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

    Returns:
        A `FitResult`.
    """
    prob, theta0, labels, measured = _prepare(
        model, protocol, measured, init=init, fit=fit, contact_impedance=contact_impedance,
        noise_std=noise_std, bounds=bounds, approx_error=approx_error)
    if measured.ndim != 1:
        raise ValueError(f"`measured` has shape {measured.shape}; pass (n_rows,) voltages "
                         "(use fit_conductivities_batch for several data vectors).")
    prob = eqx.tree_at(lambda p: p.measured, prob, jnp.asarray(measured))
    handle, count0 = _factor_count(model)
    solver = solver or _default_solver()
    sol = optx.least_squares(_residuals, solver, theta0, prob, max_steps=max_steps, throw=throw)
    n_steps = int(sol.stats.get("num_steps", 0))
    n_forward = handle.n_factorisations - count0 if count0 is not None else n_steps + 1
    return _result(sol.value, prob, labels, n_steps=n_steps, n_forward=n_forward,
                   result=sol.result, ill_conditioned=ill_conditioned)


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
