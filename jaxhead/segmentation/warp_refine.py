"""Refine the atlas warp on the EM's mixture likelihood (SPM's unified segmentation).  [jax]

The registration (register.py) aligns the atlas *template* to the scan by an image similarity. Where
two tissues look alike in the scan (T1: CSF and bone are both dark), that alignment cannot place
the boundary between them, and a prior that is a few mm off decides the labels there. Once the EM
has fitted its tissue intensity models, the scan's own evidence about that boundary is the mixture
likelihood, and the warp can be refined on it (Ashburner & Friston 2005, NeuroImage 26:839, section
"Optimising the deformations"; SPM's unified segmentation alternates this with the EM):

    maximise over the B-spline coefficients c
        F(c) = (1/N) sum_i log sum_k pi_ik(c) L_ik  -  lambda E_bend(c)  -  (1/2N) sum_i |u_c(x_i) - u_0(x_i)|^2 / s^2,

with L_ik = sum_{j in k} w_j N(y_i - b_i; mu_j, v_j) the class likelihoods of the fitted mixture
(bias field included) held fixed, and pi_ik(c) the prior the EM's last E-step used, now as a function
of the warp: the atlas priors sampled at T_c(x_i) (floored and normalised as the EM does), mixed with
the EM's relaxation term a G_sigma * q (q the EM's posteriors, held fixed; Cardoso et al. 2011) and
multiplied by the mean-field Potts factor exp(beta sum_neighbours q) (held fixed), renormalised over
k. At the registration's coefficients F is the EM's own mean log-likelihood per voxel (up to the
constant of its standardised units). lambda and E_bend are the registration's bending-energy weight
and penalty (`register.bending_energy`), so the refined warp is no rougher than the registration
allows; the similarity it is weighed against is a mean log-likelihood per voxel (nats) instead of
NMI (both are O(1)). The sum runs over the EM's sample grid.

The last term is a Gaussian prior on the change of the displacement u from the registration's, u_0
(each component an independent N(0, s^2) per sample voxel, on the same per-voxel footing as the
log-likelihood): the bending energy is zero for any affine displacement, so on its own it lets the
warp drift where the priors are flat (inside the brain, in the air) and the objective is blind to it
(results/segmentation_warp.md: 14-26 mm rms, 76 mm at most, every solve at its step limit). s is a
displacement scale in mm (`SegmentConfig.warp_change_mm`); s = inf drops the term. Gradients are JAX's, through the
trilinear resampling of the priors; the optimiser is the registration's (`register.minimise_coefficients`,
L-BFGS with a backtracking Armijo search, so F does not decrease; a solve that ends lower is
rejected and reported).

`segment` alternates this with the EM (`SegmentConfig.refine_warp` rounds at most): refine the warp on
the fitted likelihoods, resample the priors, re-run the EM; stop early when a round raises F by
less than the EM's tolerance.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..volume import voxel_sizes
from .em import (
    EMOptions, MixtureParams, _component_densities, _normalise_prior, _normalised, _relaxed_prior, _vsum, bias_field,
)
from .mrf import neighbour_sum
from .register import (
    BSplineTransform, RegisterConfig, _axis_bases, _displacement, _grid_to_moving, _sample, bending_energy,
    minimise_coefficients,
)


class WarpProblem(eqx.Module):
    """What the warp objective holds fixed (see the module docstring), on the EM's sample grid.

    Arguments:
        priors: (K, X, Y, Z) atlas priors on the atlas grid.
        atlas_affine: (4, 4) atlas voxel -> atlas mm.
        affine: (4, 4) the transform's affine part (scan mm -> atlas mm, after the displacement).
        bases: per-axis cubic B-spline bases (n_i, n_ctrl_i) of the sample grid.
        sample_affine: (4, 4) sample-grid voxel -> scan mm.
        likelihoods: (K, x, y, z) class likelihoods L_ik exp(-m_i) (scaled so nothing underflows).
        log_scale: (x, y, z) m_i.
        relaxed: (K, x, y, z) the relaxation's fixed part a G_sigma * q (zeros without relaxation).
        potts: (K, x, y, z) the mean-field Potts factor exp(beta sum_neighbours q) of the EM's
            posteriors q (ones without the MRF).
        relax, prior_floor: the EM's settings.
        head: (x, y, z) 1 where the EM's background posterior is < 1/2 (for the report), else 0.
        bending: lambda, the registration's bending-energy weight.
        anchor: (3, na, nb, nc) the registration's coefficients c_0 (the change penalty's origin).
        change_scale: s, mm, of the penalty on the displacement change (inf: no penalty).
        spacing: (3,) control-point spacing in mm.
        shape: (x, y, z) of the sample grid.
    """

    priors: jax.Array
    atlas_affine: jax.Array
    affine: jax.Array
    bases: tuple
    sample_affine: jax.Array
    likelihoods: jax.Array
    log_scale: jax.Array
    relaxed: jax.Array
    potts: jax.Array
    head: jax.Array
    anchor: jax.Array
    relax: float = eqx.field(static=True)
    prior_floor: float = eqx.field(static=True)
    bending: float = eqx.field(static=True)
    change_scale: float = eqx.field(static=True)
    spacing: tuple = eqx.field(static=True)
    shape: tuple = eqx.field(static=True)


def warp_problem(
    y, coords, params: MixtureParams, posteriors, opts: EMOptions, atlas_priors, atlas_affine,
    transform: BSplineTransform, sample_affine, bending: float, stride: int = 1, anchor=None,
    change_scale_mm: float = float("inf"),
) -> WarpProblem:
    """The fixed parts of the warp objective from a converged EM.

    Arguments:
        y: (x, y, z) the EM's data on its sample grid (MRI log intensity, CT HU).
        coords: the sample grid's per-axis bias coordinates (as the EM got them).
        params: the EM's fitted MixtureParams (data units).
        posteriors: (K, x, y, z) the EM's posteriors on the sample grid.
        opts: the EMOptions of that EM (relaxation, beta, prior floor, bias degree, groups).
        atlas_priors: (K, X, Y, Z) the atlas priors the EM's priors were resampled from.
        atlas_affine: (4, 4) their voxel -> atlas mm.
        transform: the registration (BSplineTransform; its coefficients are where the refinement starts).
        sample_affine: (4, 4) sample-grid voxel -> scan mm (axis-aligned with the scan's grid).
        bending: the bending-energy weight lambda.
        stride: the objective sums over every `stride`-th voxel of the sample grid per axis (the
            fixed parts are computed on the whole grid first, the Potts factor from each voxel's own
            neighbours).
        anchor: (3, na, nb, nc) coefficients the displacement change is measured from (None: the
            transform's own; `segment` passes the registration's to every round).
        change_scale_mm: s of the change penalty (module docstring), mm, > 0; inf: no penalty.
    Returns:
        WarpProblem.
    """
    if not isinstance(transform, BSplineTransform):
        raise ValueError(
            f"`transform` must be a BSplineTransform to refine its warp, got {type(transform).__name__}; "
            "register with RegisterConfig(bspline=True)."
        )
    if isinstance(change_scale_mm, bool) or not isinstance(change_scale_mm, (int, float, np.floating, np.integer)) \
            or not change_scale_mm > 0:
        raise ValueError(f"`change_scale_mm` must be a number > 0 (mm; inf: no penalty), got {change_scale_mm!r}.")
    anchor = transform.coefficients if anchor is None else anchor
    if tuple(np.shape(anchor)) != tuple(transform.coefficients.shape):
        raise ValueError(f"`anchor` has shape {np.shape(anchor)}; expected the transform's coefficients' "
                         f"{tuple(transform.coefficients.shape)}.")
    y = jnp.asarray(y)
    dtype = y.dtype
    q = jnp.asarray(posteriors, dtype)
    if q.shape[1:] != y.shape or q.shape[0] != opts.n_classes:
        raise ValueError(f"`posteriors` has shape {q.shape}; expected ({opts.n_classes}, *{y.shape}).")
    if opts.bias_degree > 0:
        y = y - bias_field(jnp.asarray(params.bias, dtype), tuple(jnp.asarray(c, dtype) for c in coords),
                           opts.bias_degree)
    pj, m = _component_densities(y, *(jnp.asarray(a, dtype) for a in (params.means, params.variances, params.weights)))
    lik = jnp.stack([sum(pj[j] for j in g) for g in opts.groups])
    if opts.relax > 0:  # (1 - a) atlas + a G*q is linear in the atlas: its q-part from a zero atlas
        relaxed = jnp.stack(_relaxed_prior([jnp.zeros_like(y)] * opts.n_classes, list(q), opts.relax,
                                           opts.relax_sigma_vox))
    else:
        relaxed = jnp.zeros_like(q)
    # the EM's _mrf_prior multiplies the prior by this and renormalises; q is held fixed, so is it
    potts = jnp.exp(opts.beta * neighbour_sum(q)) if opts.beta > 0 else jnp.ones_like(q)
    head = (q[0] < 0.5).astype(dtype)
    sl = (slice(None),) + (slice(None, None, int(stride)),) * 3
    lik, m, relaxed, potts, head = lik[sl], m[sl[1:]], relaxed[sl], potts[sl], head[sl[1:]]
    sample_affine = np.asarray(sample_affine, np.float64) @ np.diag([stride, stride, stride, 1.0])
    grid_affine = np.asarray(transform.grid_affine, np.float64)
    grid_shape = tuple(transform.coefficients.shape[1:])
    return WarpProblem(
        priors=jnp.asarray(atlas_priors, dtype), atlas_affine=jnp.asarray(atlas_affine, dtype),
        affine=jnp.asarray(transform.affine, dtype),
        bases=tuple(_axis_bases(grid_affine, grid_shape, m.shape, sample_affine, dtype)),
        sample_affine=jnp.asarray(sample_affine, dtype), likelihoods=lik, log_scale=m, relaxed=relaxed,
        potts=potts, head=head, anchor=jnp.asarray(anchor, dtype), relax=float(opts.relax),
        prior_floor=float(opts.prior_floor), bending=float(bending), change_scale=float(change_scale_mm), spacing=tuple(float(s) for s in voxel_sizes(grid_affine)), shape=tuple(m.shape),
    )


def warp_priors(coefficients, problem: WarpProblem):
    """The atlas priors on the sample grid through the warp with these coefficients, floored and
    normalised as the EM does: a list of K (x, y, z) maps."""
    idx = _grid_to_moving(problem.shape, problem.sample_affine, problem.affine, coefficients, problem.bases,
                          problem.atlas_affine)
    return _normalise_prior(jax.vmap(lambda p: _sample(p, idx))(problem.priors), problem.prior_floor)


def change_penalty(coefficients, problem: WarpProblem):
    """(1/2) mean over the objective's grid of |u_c - u_anchor|^2 / s^2 (0 when s is inf)."""
    if not np.isfinite(problem.change_scale):
        return jnp.zeros((), problem.likelihoods.dtype)
    du = _displacement(coefficients - problem.anchor, problem.bases)  # u is linear in c
    return 0.5 * _vsum(jnp.sum(du * du, 0)) / (np.prod(problem.shape) * problem.change_scale**2)


def warp_objective(coefficients, problem: WarpProblem):
    """F(c): the mean mixture log-likelihood per sample voxel under the warped priors minus lambda times
    the bending energy minus the displacement-change penalty (module docstring). Arguments:
    (3, na, nb, nc) coefficients in mm, WarpProblem."""
    atlas = warp_priors(coefficients, problem)
    if problem.relax > 0:
        prior = [(1.0 - problem.relax) * a + r for a, r in zip(atlas, problem.relaxed)]
    else:
        prior = atlas
    prior = _normalised([p * f for p, f in zip(prior, problem.potts)])  # em._mrf_prior with q fixed
    s = sum(p * lk for p, lk in zip(prior, problem.likelihoods))
    ll = problem.log_scale + jnp.log(jnp.maximum(s, jnp.finfo(s.dtype).tiny))
    n = np.prod(problem.shape)
    return (_vsum(ll) / n - problem.bending * bending_energy(coefficients, problem.spacing)
            - change_penalty(coefficients, problem))


_objective_jit = eqx.filter_jit(warp_objective)


def _negative_objective(coefficients, problem):
    return -warp_objective(coefficients, problem)


def refine_warp(transform: BSplineTransform, problem: WarpProblem, cfg: RegisterConfig = RegisterConfig(),
                step_mm: float = 2.0) -> tuple[BSplineTransform, dict]:
    """Maximise the warp objective over the B-spline coefficients, from the transform's own.

    Arguments:
        transform: the current BSplineTransform (scan mm -> atlas mm).
        problem: WarpProblem built for it (`warp_problem`).
        cfg: RegisterConfig (its rtol, atol and bspline_max_steps are the solver's).
        step_mm: length of the solver's first step (about a sample voxel), mm.
    Returns:
        (transform with the refined coefficients, or the given one if the solve did not raise F;
        dict: objective_before, objective_after, gain, steps, accepted, max_change_mm and rms_change_mm
        (largest change of the displacement over the objective's grid, padding included; rms over the
        head), max_from_anchor_mm and rms_from_anchor_mm (the same for the change from the problem's
        anchor, the registration in `segment`), penalty (the change penalty at the result, nats per voxel)).
    """
    c0 = jnp.asarray(transform.coefficients, problem.likelihoods.dtype)
    f0 = float(_objective_jit(c0, problem))
    c, steps, cost = minimise_coefficients(_negative_objective, c0, problem, float(step_mm), cfg.rtol, cfg.atol,
                                           cfg.bspline_max_steps)
    f1 = -float(cost)
    accepted = bool(f1 > f0)  # Armijo steps only go up; anything else keeps the registration's warp
    du2 = jnp.sum(_displacement(c - c0, problem.bases) ** 2, 0) if accepted else jnp.zeros(problem.shape)
    nhead = jnp.maximum(jnp.sum(problem.head), 1.0)
    rms = jnp.sqrt(jnp.sum(du2 * problem.head) / nhead)
    c_end = c if accepted else c0
    da2 = jnp.sum(_displacement(c_end - problem.anchor, problem.bases) ** 2, 0)
    info = dict(objective_before=f0, objective_after=f1 if accepted else f0, gain=f1 - f0 if accepted else 0.0,
                steps=int(steps), accepted=accepted, max_change_mm=float(jnp.sqrt(jnp.max(du2))),
                rms_change_mm=float(rms), max_from_anchor_mm=float(jnp.sqrt(jnp.max(da2))),
                rms_from_anchor_mm=float(jnp.sqrt(jnp.sum(da2 * problem.head) / nhead)),
                penalty=float(change_penalty(c_end, problem)))
    if not accepted:
        return transform, info
    return eqx.tree_at(lambda t: t.coefficients, transform, c.astype(transform.coefficients.dtype)), info


def alternate(
    transform: BSplineTransform, fit, make_problem: Callable, refit: Callable, rounds: int,
    cfg: RegisterConfig, step_mm: float, tol: float,
):
    """Alternate `refine_warp` on the fitted likelihoods with a new EM on the re-warped priors.

    Arguments:
        transform: the registration.
        fit: the EM fit on its priors (whatever `refit` returns).
        make_problem: (transform, fit) -> WarpProblem.
        refit: transform -> fit (resample the priors, run the EM).
        rounds: at most this many refinements (each followed by an EM).
        cfg, step_mm: as `refine_warp`.
        tol: stop when a refinement raises F by less than this (nats per voxel; e.g. the EM's tol).
    Returns:
        (transform, fit, summary dict: rounds (refinements run), refits (of them adopted: each raised F
        by >= tol and was followed by an EM), objective per round [before, after], gain (F raised, summed
        over the adopted rounds), max_change_mm, rms_change_mm, max_from_registration_mm,
        rms_from_registration_mm (the change from make_problem's anchor), penalty and steps per round).
    """
    per_round = []
    for _ in range(rounds):
        new, info = refine_warp(transform, make_problem(transform, fit), cfg, step_mm)
        info["adopted"] = info["accepted"] and info["gain"] >= tol
        per_round.append(info)
        if not info["adopted"]:  # the objective stopped rising: keep the warp the EM ran on
            break
        transform, fit = new, refit(new)
    adopted = [r for r in per_round if r["adopted"]]
    summary = dict(
        rounds=len(per_round), refits=len(adopted),
        objective=[[round(r["objective_before"], 6), round(r["objective_after"], 6)] for r in per_round],
        gain=float(sum(r["gain"] for r in adopted)),
        max_change_mm=[round(r["max_change_mm"], 3) for r in per_round],
        rms_change_mm=[round(r["rms_change_mm"], 3) for r in per_round],
        max_from_registration_mm=[round(r["max_from_anchor_mm"], 3) for r in per_round],
        rms_from_registration_mm=[round(r["rms_from_anchor_mm"], 3) for r in per_round],
        penalty=[round(r["penalty"], 6) for r in per_round],
        steps=[r["steps"] for r in per_round],
    )
    return transform, fit, summary
