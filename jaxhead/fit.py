"""Fitting tissue conductivities (and a contact impedance) to measured voltages with optimistix.

Parameters are fitted in log space, so they stay positive and steps are relative; optional bounds
map log-parameters through a sigmoid. The Gauss-Newton covariance at the optimum gives standard
errors and correlations (skull and scalp trade off against each other; see Horesh 2006, ch. 5).
"""

import warnings
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .tissue import TISSUE_NAMES, Tissue


_DEFAULT_RANGE = 1e3  # default bounds: init / 1e3 .. init * 1e3


class FitResult(eqx.Module):
    """The outcome of `fit_conductivities`.

    Attributes:
        sigma: (4,) conductivities in S/m, ordered BRAIN, CSF, SKULL, SCALP (unfitted ones = init).
        contact_impedance: (n_elec,) Ohm m^2 (the initial ones scaled by the fitted factor).
        fitted: names of the fitted parameters, in the order of `std_error`/`correlation`.
        estimates: (n_fit,) fitted values (S/m; Ohm m^2 for "contact_impedance").
        std_error: (n_fit,) Gauss-Newton standard errors, same units as `estimates`.
        correlation: (n_fit, n_fit) correlation matrix of the estimates.
        residual_norm: || W (V(sigma) - measured) || at the optimum (noise units when weighted).
        n_steps: optimiser steps.
        n_forward: forward-model evaluations, i.e. distinct FEM systems factorised (counted by
            the Direct solver; derivatives reuse each factor). Estimated as steps + 1 for
            iterative solvers.
        condition: condition number of the weighted J^T J (in log-parameters).
        success: whether optimistix reported success.
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
    success: bool = True

    def table(self) -> str:
        """The estimates as a text table."""
        lines = [f"{'parameter':<18}{'estimate':>12}{'std error':>12}{'rel %':>8}"]
        for name, e, s in zip(self.fitted, self.estimates, self.std_error):
            lines.append(f"{name:<18}{e:>12.5g}{s:>12.3g}{100 * s / abs(e):>8.2f}")
        lines.append(f"residual norm {self.residual_norm:.4g}, {self.n_steps} steps, "
                     f"{self.n_forward} forward solves, cond(J^T J) {self.condition:.3g}")
        return "\n".join(lines)


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


def fit_conductivities(model, protocol, measured, *, init, fit: Sequence[str] = TISSUE_NAMES,
                       contact_impedance: bool = False, noise_std=None,
                       bounds: Mapping[str, tuple[float, float]] | None = None,
                       solver=None, max_steps: int = 100, throw: bool = True,
                       ill_conditioned: float = 1e8) -> FitResult:
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
            Default: 1 % of the RMS of `measured` (a scale only; estimates do not depend on it).
        bounds: {"skull": (lo, hi), ...} in S/m; every parameter goes through a sigmoid in log
            space between its bounds. Default: init / 1000 to init * 1000 (and the same factors on
            the contact impedance), wide enough not to bias a fit and tight enough that a trial
            step of the optimiser cannot make the FEM matrix numerically singular.
        solver: an optimistix least-squares solver (default LevenbergMarquardt(rtol=1e-8, atol=1e-10)).
        max_steps: optimiser step limit.
        throw: raise when optimistix fails (else `success=False`).
        ill_conditioned: warn when cond(J^T J) exceeds this.

    Returns:
        A `FitResult`.
    """
    from .fem import simulate

    names = _names(fit)
    init = np.asarray(init, dtype=np.float64)
    if init.shape != (4,):
        raise ValueError(f"`init` has shape {init.shape}; pass 4 conductivities (S/m) ordered "
                         "BRAIN, CSF, SKULL, SCALP.")
    if not np.all(np.isfinite(init)) or np.any(init <= 0):
        raise ValueError(f"`init` must be finite and > 0 S/m (fitting is in log space), got {init.tolist()}.")
    measured = jnp.asarray(measured, dtype=jnp.float64)
    n_rows = protocol.rows.shape[0]
    if measured.shape != (n_rows,):
        raise ValueError(f"`measured` has shape {measured.shape}; the protocol has {n_rows} rows.")
    if noise_std is None:
        noise_std = 0.01 * float(jnp.sqrt(jnp.mean(measured**2)))
    w = 1.0 / jnp.broadcast_to(jnp.asarray(noise_std, jnp.float64), measured.shape)
    if not bool(jnp.all(jnp.isfinite(w) & (w > 0))):
        raise ValueError("`noise_std` must be finite and > 0 for every channel.")

    idx = [TISSUE_NAMES.index(n) for n in names]
    z0 = jnp.asarray(model.contact_impedance, jnp.float64)
    labels = list(names) + (["contact_impedance"] if contact_impedance else [])
    lo_hi = []
    bounds = dict(bounds or {})
    for key in bounds:
        if key not in labels:
            raise ValueError(f"`bounds` names {key!r}, which is not fitted; fitted: {labels}.")
    start = [float(init[i]) for i in idx] + ([1.0] if contact_impedance else [])
    for name, x0 in zip(labels, start):
        b = bounds.get(name, (x0 / _DEFAULT_RANGE, x0 * _DEFAULT_RANGE))
        lo, hi = float(b[0]), float(b[1])
        if not 0 < lo < x0 < hi:
            raise ValueError(f"`bounds[{name!r}]` = {tuple(b)} must satisfy 0 < lo < init ({x0}) < hi.")
        lo_hi.append((np.log(lo), np.log(hi)))

    def to_log(theta):
        out = []
        for t, b in zip(theta, lo_hi):
            out.append(t if b is None else b[0] + (b[1] - b[0]) * jax.nn.sigmoid(t))
        return jnp.stack(out)

    def from_log(logx):
        out = []
        for lx, b in zip(logx, lo_hi):
            out.append(lx if b is None else np.log((lx - b[0]) / (b[1] - lx)))  # logit
        return jnp.asarray(out, jnp.float64)

    def unpack(theta):
        logx = to_log(theta)
        sigma = jnp.asarray(init).at[jnp.asarray(idx)].set(jnp.exp(logx[: len(idx)]))
        z = z0 * jnp.exp(logx[len(idx)]) if contact_impedance else z0
        return sigma, z

    def residuals(theta, args):
        sigma, z = unpack(theta)
        return w * (simulate(model, sigma, protocol, contact_impedance=z) - measured)

    theta0 = from_log(np.log(np.asarray(start)))
    # The Direct solver counts its factorisations: one per distinct conductivity vector, i.e.
    # one per forward model evaluated (tangent and adjoint solves reuse the factor).
    handle = getattr(getattr(model, "solver_state", None), "handle", None)
    factor_count0 = getattr(handle, "n_factorisations", None)
    solver = solver or optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)
    sol = optx.least_squares(residuals, solver, theta0, max_steps=max_steps, throw=throw)
    theta = sol.value
    r = residuals(theta, None)
    # Gauss-Newton covariance in log-parameters: (J^T J)^-1 for unit-variance weighted residuals.
    Jl = jax.jacfwd(lambda lx: residuals(from_log_jax(lx, lo_hi), None))(to_log(theta))
    jtj = np.asarray(Jl.T @ Jl)
    cond = float(np.linalg.cond(jtj))
    cov_log = np.linalg.pinv(jtj)
    est = np.exp(np.asarray(to_log(theta)))
    # Delta method: d x = x d(log x).
    cov = cov_log * np.outer(est, est)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    corr = cov / np.outer(se, se) if np.all(se > 0) else np.full_like(cov, np.nan)
    if cond > ill_conditioned:
        warnings.warn(
            f"J^T J is ill-conditioned (cond {cond:.2g} > {ill_conditioned:.0g}): the data barely "
            f"separate {labels}; skull and scalp conductivities often trade off. Fix one, add "
            "measurements, or read the correlations.", RuntimeWarning, stacklevel=2)
    sigma, z = unpack(theta)
    n_steps = int(sol.stats.get("num_steps", 0))
    if factor_count0 is not None:
        n_forward = handle.n_factorisations - factor_count0
    else:  # iterative solvers: one evaluation per step plus the start (an estimate)
        n_forward = n_steps + 1
    return FitResult(
        sigma=np.asarray(sigma), contact_impedance=np.asarray(z), fitted=tuple(labels),
        estimates=est, std_error=se, correlation=corr,
        residual_norm=float(jnp.linalg.norm(r)), n_steps=n_steps,
        n_forward=int(n_forward),
        condition=cond, success=bool(sol.result == optx.RESULTS.successful),
    )


def from_log_jax(logx, lo_hi):
    """Inverse of the bounded log transform, differentiable (used for the covariance)."""
    out = []
    for i, b in enumerate(lo_hi):
        lx = logx[i]
        out.append(lx if b is None else jnp.log((lx - b[0]) / (b[1] - lx)))
    return jnp.stack(out)
