"""EM for a Gaussian mixture with spatial (atlas) priors, prior relaxation, Potts MRF and bias field.  [jax]

Model (Van Leemput et al. 1999, IEEE TMI 18:885 and 18:897; Ashburner & Friston 2005, NeuroImage
26:839): each voxel belongs to one of K classes with spatial prior pi_ik (the registered atlas); class
k owns one or more Gaussians j (e.g. grey and white matter inside "brain") with within-class weights
w_j, so

    p(y_i) = sum_k pi_ik sum_{j in k} w_j N(y_i - b_i; mu_j, v_j),

where b_i = sum_m c_m phi_m(x_i) is a smooth bias field (MRI, log intensities, so the multiplicative
field is additive; Wells et al. 1996, IEEE TMI 15:429) on a tensor Legendre-polynomial basis of total
degree <= d without the constant (the means absorb it). Iterations:

- E-step: posteriors with the prior multiplied by the mean-field Potts term exp(beta * sum of the
  neighbours' posteriors) and renormalised (Van Leemput et al. 1999; see mrf.py).
- M-step: weighted means, variances and within-class weights (maximum likelihood, or with
  `weight_prior` > 0 the MAP under a Dirichlet prior that keeps every free Gaussian of a class from
  being emptied: `map_weights`; Ormoneit & Tresp 1998; with `mean_order`, means kept in a given
  order, `ordered_means`); then the bias coefficients by weighted
  least squares with weights W_i = sum_j r_ij / v_j over the head's Gaussians (Van Leemput 1999,
  eq. 6; Wells 1996).
- Prior relaxation (Cardoso et al. 2011, NeuroImage 56:1386; NiftySeg seg_EM -rf): once the EM with
  the atlas priors has converged, the prior is replaced, once, by (1 - a) * atlas + a * G_sigma *
  posterior (renormalised), so anatomy that differs from the atlas can win where the image evidence
  is strong, and the EM runs on to convergence again (NiftySeg relaxes once, after convergence; a
  relaxation at every iteration feeds the posterior back into its own prior and drifts).
- Partial volume (optional, `pv_of`): a voxel on the boundary of tissues A and B holds a fraction f
  of A and has intensity f I_A + (1 - f) I_B (+ noise); its label (the tissue at its centre, for a
  boundary that is flat on the voxel's scale) is A iff f > 1/2. So each bordering class pair gets two
  *tied* Gaussians, one per half of the mixing line: owned by A, f uniform on (1/2, 1); owned by B,
  f on (0, 1/2). Mean = the half's midpoint, variance = its span^2 / 12 + the smaller pure variance
  (noise), recomputed from the pure Gaussians after every M-step (the pure pair is the one closest
  in intensity); the weights are free. In log intensities (MRI) the mixing is done on exp(y).
  Without this, free "partial-volume" Gaussians belong to one class and take every mixed voxel,
  and a narrow pure Gaussian (air, soft tissue) next to a broad one (bone, a free PV Gaussian) puts
  the decision threshold at a few per cent of the narrow tissue: the broad class grows by a voxel
  (Van Leemput et al. 2003, IEEE TMI 22:105, model partial volume as such mixtures; Santago &
  Gage 1993, IEEE TMI 12:566, the uniform-fraction "mixel" density).
- Stop when the change of the mean log-likelihood per voxel is below tol (inside lax.while_loop).

The E-step works in the probability domain after subtracting each voxel's largest component
log-density (so nothing underflows, even for CT air vs bone), which lets XLA fuse it into one pass.
Sums over voxels are nested per axis (at most a few hundred terms each), which keeps float32
sufficient statistics accurate to ~1e-5 relative (plain sequential float32 sums of 10^6-10^7 terms are
not).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .mrf import neighbour_sum


@dataclass(frozen=True, kw_only=True)
class EMOptions:
    """Static settings of `fit_mixture` (hashable, so it can be a jit static argument).

    Arguments:
        component_class: class index (0..K-1) of each Gaussian, sorted, e.g. (0, 0, 1, 1, 2, 3, 3, 4, 4).
        n_classes: K.
        beta: Potts MRF strength (0 = off).
        max_iter, min_iter: EM iteration bounds (max_iter counts both phases, before and after the
            prior relaxation).
        tol: stop when |LL_t - LL_{t-1}| < tol, LL = mean log-likelihood per voxel of the standardised
            data (nats; an absolute test, since LL per voxel can be near 0, where a relative one fails).
        relax: prior relaxation weight a in [0, 1) (0 = strict atlas priors).
        relax_sigma_vox: Gaussian smoothing of the posterior in the relaxed prior (voxels).
        bias_degree: total degree of the Legendre bias basis (0 = no bias field).
        bias_classes: classes whose voxels drive the bias fit (None: all but class 0).
        bias_ridge: Tikhonov weight on the bias coefficients (relative to the total weight).
        var_floor: variance floor in standardised units (fraction of the data variance).
        prior_floor: probability added to every prior before normalising (the atlas is an estimate:
            no class is impossible anywhere).
        pv_of: per Gaussian, -1 for a free ("pure") Gaussian, or the class b it is a partial-volume
            mixture with: a tied Gaussian of the half of the mixing line nearer its own class
            (see the module docstring). Empty: all free.
        pv_log: the data are log intensities (partial-volume mixing is done on exp(y)).
        weight_prior: eta >= 0 of the Dirichlet prior on each class's within-class weights (MAP
            instead of maximum likelihood; see `map_weights`): pseudo-counts eta * N_k / F_k on each
            of class k's F_k free Gaussians, N_k the class's soft voxel count, so that no free
            Gaussian's weight falls below eta / ((1 + eta) F_k). 0 = maximum likelihood.
        mean_order: pairs (j_low, j_high, margin): the M-step keeps mu_{j_low} <= mu_{j_high} - margin
            (margin >= 0 in data units; the MAP under a flat prior on the ordered means, see
            `ordered_means`). Each Gaussian in at most one pair; free Gaussians only. Empty: no order.
        variance_prior: nu >= 0 of the inverse-gamma prior on each free Gaussian's variance, centred
            on its class's pooled variance (MAP instead of maximum likelihood; see `map_variances`).
            0 = maximum likelihood.
    """

    component_class: tuple[int, ...]
    n_classes: int
    beta: float = 0.0
    max_iter: int = 60
    min_iter: int = 3
    tol: float = 1e-4
    relax: float = 0.0
    relax_sigma_vox: float = 1.0
    bias_degree: int = 0
    bias_classes: tuple[int, ...] | None = None
    bias_ridge: float = 1e-6
    var_floor: float = 1e-4
    prior_floor: float = 1e-4
    pv_of: tuple[int, ...] = ()
    pv_log: bool = False
    weight_prior: float = 0.0
    mean_order: tuple[tuple[int, int, float], ...] = ()
    variance_prior: float = 0.0

    def __post_init__(self):
        cc = tuple(self.component_class)
        _check_mean_order(self.mean_order, cc, self.pv_of)
        if self.pv_of:
            pv = tuple(self.pv_of)
            if len(pv) != len(cc):
                raise ValueError(f"`pv_of` {pv} must have one entry per Gaussian ({len(cc)}), or be empty.")
            for j, b in enumerate(pv):
                if b != -1 and not (0 <= b < self.n_classes and b != cc[j]):
                    raise ValueError(
                        f"`pv_of[{j}]` = {b}: must be -1 (free) or another class 0..{self.n_classes - 1} "
                        f"than the Gaussian's own ({cc[j]})."
                    )
            for k in range(self.n_classes):
                if all(pv[j] >= 0 for j in range(len(cc)) if cc[j] == k):
                    raise ValueError(f"class {k} has only partial-volume Gaussians in `pv_of` {pv}; give it a free one.")
        if not cc or min(cc) < 0 or max(cc) >= self.n_classes:
            raise ValueError(
                f"`component_class` {cc} must name classes 0..{self.n_classes - 1}; one entry per Gaussian."
            )
        missing = sorted(set(range(self.n_classes)) - set(cc))
        if missing:
            raise ValueError(f"classes {missing} have no Gaussian in `component_class` {cc}; give each class >= 1.")
        if list(cc) != sorted(cc):
            raise ValueError(f"`component_class` {cc} must be sorted (the Gaussians of a class together).")
        if not 0 <= self.relax < 1:
            raise ValueError(f"`relax` must be in [0, 1), got {self.relax}.")
        if self.beta < 0:
            raise ValueError(f"`beta` must be >= 0, got {self.beta}.")
        if self.bias_degree < 0:
            raise ValueError(f"`bias_degree` must be >= 0, got {self.bias_degree}.")
        if not self.weight_prior >= 0:
            raise ValueError(f"`weight_prior` must be >= 0 (0 = maximum likelihood), got {self.weight_prior}.")
        if not self.variance_prior >= 0:
            raise ValueError(f"`variance_prior` must be >= 0 (0 = maximum likelihood), got {self.variance_prior}.")
        if self.max_iter < 1 or self.min_iter < 0:
            raise ValueError(f"`max_iter` must be >= 1 and `min_iter` >= 0, got {self.max_iter}, {self.min_iter}.")

    @property
    def groups(self) -> list[list[int]]:
        """The component indices of each class."""
        return [[j for j, c in enumerate(self.component_class) if c == k] for k in range(self.n_classes)]

    def is_free(self, j: int) -> bool:
        """Whether Gaussian j has its own mean and variance (not a tied partial-volume one)."""
        return not self.pv_of or self.pv_of[j] < 0


def _check_mean_order(order, cc, pv_of) -> None:
    seen = []
    for pair in order:
        if not (isinstance(pair, tuple) and len(pair) == 3):
            raise ValueError(f"`mean_order` entries must be (j_low, j_high, margin) tuples, got {pair!r}.")
        lo, hi, margin = pair
        if isinstance(margin, bool) or not isinstance(margin, (int, float, np.integer, np.floating)):
            raise ValueError(f"`mean_order` {pair!r}: the margin must be a number >= 0 in data units.")
        if lo == hi or not (math.isfinite(margin) and margin >= 0):
            raise ValueError(f"`mean_order` {pair!r}: needs two different Gaussians and a finite margin >= 0.")
        for j in (lo, hi):
            if isinstance(j, bool) or not isinstance(j, (int, np.integer)) or not 0 <= j < len(cc):
                raise ValueError(f"`mean_order` {pair!r}: Gaussian index {j!r} is not in 0..{len(cc) - 1}.")
            if pv_of and pv_of[j] >= 0:
                raise ValueError(f"`mean_order` {pair!r}: Gaussian {j} is a tied partial-volume one; order free ones.")
            if j in seen:
                raise ValueError(f"`mean_order`: Gaussian {j} is in more than one pair; give each at most one.")
            seen.append(j)


class MixtureParams(eqx.Module):
    """Gaussian-mixture parameters in the data's own units.

    Arguments:
        means: (J,) component means.
        variances: (J,) component variances.
        weights: (J,) within-class weights (sum to 1 over each class's components).
        bias: (M,) bias coefficients on the Legendre basis (data units; empty without bias).
    """

    means: jax.Array
    variances: jax.Array
    weights: jax.Array
    bias: jax.Array


class NoiseFloor(eqx.Module):
    """A per-Gaussian variance floor: the noise a tissue of that mean intensity keeps in the data.

    A Gaussian of the mixture models a tissue: its voxels scatter at least by the noise the data keep
    at its intensity, so no Gaussian narrower than that is a tissue (it is a spike: a flat, texture-free
    tissue after smoothing, which a narrow Gaussian of another class can claim). The floor of Gaussian
    j with mean mu_j (data units) is sd(mu_j)^2, sd interpolated linearly in `means`, `sds`; below
    the first point sds[0]; above the last, for log intensities (the noise falls as 1 / intensity
    there: Rician -> Gaussian) sds[-1] * exp(-(mu - means[-1])), otherwise sds[-1]. Built for an MRI
    by `segment._noise_floor` from `denoise.log_noise_table` and the scan's measured noise.

    Arguments:
        means: (T,) increasing means (data units).
        sds: (T,) the noise sd at those means (data units, > 0).
    """

    means: jax.Array
    sds: jax.Array

    def __check_init__(self):
        m, d = np.asarray(self.means), np.asarray(self.sds)
        if m.ndim != 1 or m.shape != d.shape or m.size < 2:
            raise ValueError(f"`means` and `sds` must be 1-D of one length >= 2, got shapes {m.shape}, {d.shape}.")
        if not (np.all(np.isfinite(m)) and np.all(np.diff(m) > 0)):
            raise ValueError(f"`means` must be finite and strictly increasing, got {m}.")
        if not (np.all(np.isfinite(d)) and np.all(d > 0)):
            raise ValueError(f"`sds` must be finite and > 0, got {d}.")

    def sd(self, mu, log_data: bool):
        """The floor's sd at means `mu` (data units)."""
        m, d = self.means, self.sds
        inner = jnp.interp(mu, m, d)
        if not log_data:
            return inner
        return jnp.where(mu > m[-1], d[-1] * jnp.exp(-(mu - m[-1])), inner)


class EMResult(eqx.Module):
    """Result of `fit_mixture`.

    Arguments:
        posteriors: (K, x, y, z) class posteriors (sum to 1 over K).
        params: MixtureParams in data units.
        bias_field: (x, y, z) fitted additive bias b (data units; zeros without bias).
        log_likelihood: mean log-likelihood per voxel (standardised units) at the last iteration.
        n_iter: EM iterations run.
        converged: whether the tolerance was met before max_iter.
    """

    posteriors: jax.Array
    params: MixtureParams
    bias_field: jax.Array
    log_likelihood: jax.Array
    n_iter: jax.Array
    converged: jax.Array


# ----------------------------------------------------------------------------------------------
# helpers: sums, smoothing, bias basis
# ----------------------------------------------------------------------------------------------


def _vsum(x):
    """Sum over the last three axes, one axis at a time (short float32 accumulations)."""
    return x.sum(-1).sum(-1).sum(-1)


def gaussian_smooth(p, sigma_vox: float):
    """Separable Gaussian smoothing of (..., x, y, z) maps over the last three axes (zero outside).

    Arguments:
        p: (..., x, y, z) array.
        sigma_vox: standard deviation in voxels (kernel truncated at 3 sigma, normalised to sum 1).
    Returns:
        array of the same shape (voxels near the border lose the mass that falls outside).
    """
    if sigma_vox <= 0:
        return p
    r = max(1, int(math.ceil(3 * sigma_vox)))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_vox) ** 2)
    k = k / k.sum()
    nd = p.ndim
    for ax in range(nd - 3, nd):
        n = p.shape[ax]
        rr = min(r, n - 1)
        pad = [(0, 0)] * nd
        pad[ax] = (rr, rr)
        q = jnp.pad(p, pad)
        out = 0.0
        for t in range(-rr, rr + 1):
            out = out + float(k[t + r]) * lax.slice_in_dim(q, rr + t, rr + t + n, axis=ax)
        p = out
    return p


def legendre_1d(x, degree: int):
    """Legendre polynomials P_0..P_degree at points x in [-1, 1], shape (degree + 1, n)."""
    polys = [jnp.ones_like(x), x]
    for k in range(1, degree):
        polys.append(((2 * k + 1) * x * polys[k] - k * polys[k - 1]) / (k + 1))
    return jnp.stack(polys[: degree + 1])


def grid_coordinates(shape, dtype, stride: int = 1, full_shape=None):
    """Per-axis coordinates in [-1, 1] of a (possibly strided) grid, for the bias basis.

    Arguments:
        shape: (x, y, z) of the grid in use.
        stride: the grid takes every `stride`-th voxel of a grid of `full_shape`.
        full_shape: the full grid (default: shape).
    Returns:
        tuple of 3 arrays (n_x,), (n_y,), (n_z,).
    """
    full_shape = shape if full_shape is None else full_shape
    out = []
    for n, nf in zip(shape, full_shape):
        i = np.arange(n) * stride
        out.append(jnp.asarray(2.0 * i / max(nf - 1, 1) - 1.0, dtype=dtype))
    return tuple(out)


def bias_terms(degree: int) -> np.ndarray:
    """Multi-indices (M, 3) of the tensor Legendre basis with 1 <= total degree <= `degree`."""
    return np.array(
        [(a, b, c) for a in range(degree + 1) for b in range(degree + 1) for c in range(degree + 1)
         if 1 <= a + b + c <= degree],
        dtype=int,
    ).reshape(-1, 3)


def bias_field(coefficients, coords, degree: int):
    """Evaluate b = sum_m c_m P_a(x) P_b(y) P_c(z) on a grid.

    Arguments:
        coefficients: (M,) with M = len(bias_terms(degree)).
        coords: 3 per-axis coordinate vectors in [-1, 1] (see `grid_coordinates`).
        degree: total degree (0: zero field).
    Returns:
        (x, y, z) field.
    """
    shape = tuple(len(c) for c in coords)
    dtype = coords[0].dtype
    if degree == 0:
        return jnp.zeros(shape, dtype)
    terms = bias_terms(degree)
    px, py, pz = (legendre_1d(c, degree) for c in coords)
    full = jnp.zeros((degree + 1,) * 3, dtype).at[terms[:, 0], terms[:, 1], terms[:, 2]].set(coefficients)
    t = jnp.einsum("abc,cz->abz", full, pz)
    t = jnp.einsum("abz,by->ayz", t, py)
    return jnp.einsum("ayz,ax->xyz", t, px)


def _fit_bias(w, rhs, coords, degree: int, ridge):
    """Weighted least squares min sum_i w_i (t_i - b_i)^2 given rhs_i = w_i t_i, by separable contractions."""
    dtype = w.dtype
    terms = bias_terms(degree)
    px, py, pz = (legendre_1d(c, degree) for c in coords)
    # H[abc, efg] = sum_xyz w Px_a Px_e Py_b Py_f Pz_c Pz_g: cost (d+1)^2 N, never an N x M matrix.
    t = jnp.einsum("cz,gz,xyz->cgxy", pz, pz, w)
    t = jnp.einsum("by,fy,cgxy->bfcgx", py, py, t)
    h = jnp.einsum("ax,ex,bfcgx->abcefg", px, px, t)
    g = jnp.einsum("cz,xyz->cxy", pz, rhs)
    g = jnp.einsum("by,cxy->bcx", py, g)
    g = jnp.einsum("ax,bcx->abc", px, g)
    ia, ib, ic = terms[:, 0], terms[:, 1], terms[:, 2]
    hm = h[ia, ib, ic][:, ia, ib, ic]
    gm = g[ia, ib, ic]
    hm = hm + ridge * (jnp.sum(w) + jnp.finfo(dtype).tiny) * jnp.eye(len(terms), dtype=dtype)
    return jnp.linalg.solve(hm, gm)


# ----------------------------------------------------------------------------------------------
# E and M steps
# ----------------------------------------------------------------------------------------------


def _component_densities(y, mu, var, w):
    """Per-component scaled densities p_j = exp(l_j - m) and the per-voxel max m of l_j (lists)."""
    a = jnp.log(w) - 0.5 * jnp.log(2 * jnp.pi * var)
    inv = 0.5 / var
    lj = [a[j] - inv[j] * (y - mu[j]) ** 2 for j in range(mu.shape[0])]
    m = lj[0]
    for l_ in lj[1:]:
        m = jnp.maximum(m, l_)
    return [jnp.exp(l_ - m) for l_ in lj], m


def _normalised(e):
    """Normalise a list of K per-class maps to sum 1 (lists: XLA CPU handles an axis-0 reduction
    over a stacked (K, ...) array an order of magnitude slower than K elementwise adds)."""
    z = functools.reduce(jnp.add, e)
    z = jnp.maximum(z, jnp.finfo(z.dtype).tiny)
    return [ek / z for ek in e]


def _mrf_prior(prior, post_prev, beta):
    """Mean-field Potts prior: prior_k exp(beta sum_neighbours q_k), renormalised over k (lists)."""
    if beta <= 0:
        return prior
    return _normalised([pk * jnp.exp(beta * neighbour_sum(qk)) for pk, qk in zip(prior, post_prev)])


def _relaxed_prior(atlas, post_prev, relax, sigma_vox):
    """Cardoso et al. 2011 prior relaxation: (1 - a) atlas + a * normalised(G_sigma * q) (lists)."""
    sm = _normalised([gaussian_smooth(qk, sigma_vox) for qk in post_prev])
    return [(1.0 - relax) * ak + relax * sk for ak, sk in zip(atlas, sm)]


def _e_step(y, prior, mu, var, w, opts: EMOptions):
    """Class posteriors (K, ...), component terms and the mean log-likelihood."""
    pj, m = _component_densities(y, mu, var, w)
    groups = opts.groups
    lk = [functools.reduce(jnp.add, [pj[j] for j in g]) for g in groups]
    joint = [prior[k] * lk[k] for k in range(opts.n_classes)]
    s = functools.reduce(jnp.add, joint)
    tiny = jnp.finfo(y.dtype).tiny
    s = jnp.maximum(s, tiny)
    post = [jk / s for jk in joint]
    ll = jnp.mean(m + jnp.log(s))
    return post, pj, lk, ll


def _responsibilities(post, pj, lk, opts):
    tiny = jnp.finfo(pj[0].dtype).tiny
    r = [post[c] * pj[j] / jnp.maximum(lk[c], tiny) for j, c in enumerate(opts.component_class)]
    return lax.optimization_barrier(r)  # materialise once; the M-step reads each r_j three times


def _m_step(y, r, mu_old, opts: EMOptions, var_floor, var_old=None, scale=1.0, noise_floor=None, centre=0.0):
    """Means, variances (shifted by the old means for accuracy) and within-class weights.

    With `opts.mean_order`: the means are `ordered_means` (weights n_j / var_old_j, margins / scale
    in standardised units) and each variance is about its own constrained mean. With `noise_floor`
    (a NoiseFloor in data units; the data standardised as (y - centre) / scale), each variance is
    also kept >= the floor at its mean.
    """
    n, s1, s2 = [], [], []
    for j, rj in enumerate(r):
        d = y - mu_old[j]
        n.append(_vsum(rj))
        s1.append(_vsum(rj * d))
        s2.append(_vsum(rj * d * d))
    n, s1, s2 = jnp.stack(n), jnp.stack(s1), jnp.stack(s2)
    n = n + jnp.finfo(y.dtype).tiny
    shift = s1 / n
    mu = mu_old + shift
    var = s2 / n - shift**2
    if opts.mean_order:
        mu_c = ordered_means(mu, n / var_old, tuple((lo, hi, m / scale) for lo, hi, m in opts.mean_order))
        var = var + (mu_c - mu) ** 2  # sum_i r_ij (y_i - mu_c)^2 / n_j
        mu = mu_c
    var = jnp.maximum(map_variances(n, var, opts), var_floor)
    if noise_floor is not None:
        var = jnp.maximum(var, (noise_floor.sd(centre + scale * mu, opts.pv_log) / scale) ** 2)
    return mu, var, map_weights(n, opts)


def ordered_means(means, precisions, order):
    """The M-step's means under order constraints mu_lo <= mu_hi - margin (closed form).

    With the variances v_j held at their last values (an ECM step: Meng & Rubin 1993, Biometrika
    80:267), the part of the expected complete-data log-likelihood that depends on the means is
    -sum_j a_j (mu_j - m_j)^2 / 2 with a_j = n_j / v_j (soft count over variance) and m_j the
    weighted sample mean (the unconstrained M-step). For disjoint pairs (lo, hi, delta) the maximiser
    on {mu_lo <= mu_hi - delta} is m where the order holds, and otherwise on the boundary:

        mu_hi = (a_hi m_hi + a_lo (m_lo + delta)) / (a_lo + a_hi),   mu_lo = mu_hi - delta,

    the precision-weighted compromise (each mean moves against its own precision). This is the MAP
    under a flat prior restricted to the ordered means, i.e. a prior that rules out only what is
    physically impossible (CT: water-like CSF brighter than brain, see segment.CSF_BRAIN_MARGIN_HU);
    inside the admissible region the likelihood alone decides.

    Arguments:
        means: (J,) unconstrained means m_j.
        precisions: (J,) a_j = n_j / v_j (> 0).
        order: tuple of disjoint (lo, hi, delta), delta >= 0 in the means' units.
    Returns:
        (J,) the constrained means.
    """
    mu = means
    for lo, hi, delta in order:
        a_lo, a_hi = precisions[lo], precisions[hi]
        t = (a_hi * means[hi] + a_lo * (means[lo] + delta)) / (a_lo + a_hi)
        bad = means[lo] > means[hi] - delta
        mu = mu.at[hi].set(jnp.where(bad, t, means[hi])).at[lo].set(jnp.where(bad, t - delta, means[lo]))
    return mu


def map_variances(counts, variances, opts: EMOptions):
    """Component variances: maximum likelihood, or MAP under an inverse-gamma prior centred on the class's
    pooled variance.

    Class k owns Gaussians G_k, F_k of them free, with soft counts n_j, maximum-likelihood variances
    s_j (scatter S_j = n_j s_j about the new mean) and N_k = sum_{j in G_k} n_j. The pooled
    within-class variance is V_k = sum_{j in G_k free} S_j / sum_{j in G_k free} n_j. With an
    inverse-gamma prior IG(alpha_j, beta_j) on v_j, the M-step maximises
    -(n_j / 2 + alpha_j + 1) log v_j - (S_j / 2 + beta_j) / v_j, whose maximiser is
    v_j = (S_j + 2 beta_j) / (n_j + 2 alpha_j + 2) (the conjugate MAP M-step of a regularised Gaussian
    mixture: Fraley & Raftery 2007, J. Classif. 24:155, eq. 7 with the mean prior off; Ormoneit &
    Tresp 1998). Here 2 alpha_j + 2 = a_j = nu N_k / F_k and 2 beta_j = a_j V_k, nu =
    `opts.variance_prior`:

        v_j = (S_j + a_j V_k) / (n_j + a_j),

    a prior worth nu times the class's own voxels (shared among its free Gaussians, as `map_weights`)
    that says "a tissue Gaussian is about as wide as its class's others". A Gaussian with many voxels
    keeps its own variance; one being emptied (n_j -> 0) tends to V_k instead of collapsing onto a
    few voxels at the variance floor, where its density spike (w_j / sqrt(2 pi v_j)) outbids the
    class's real Gaussians at one intensity. Tied partial-volume Gaussians are left as they are
    (they are set from the pure ones afterwards). nu = 0 is maximum likelihood.

    Arguments:
        counts: (J,) soft counts n_j (> 0).
        variances: (J,) maximum-likelihood variances s_j.
        opts: EMOptions (its groups, free Gaussians and variance_prior).
    Returns:
        (J,) variances.
    """
    nu = opts.variance_prior
    if nu == 0:
        return variances
    out = []
    for g in opts.groups:
        free = [j for j in g if opts.is_free(j)]
        tot = functools.reduce(jnp.add, [counts[j] for j in g])
        n_free = functools.reduce(jnp.add, [counts[j] for j in free])
        pooled = functools.reduce(jnp.add, [counts[j] * variances[j] for j in free]) / n_free
        a = nu * tot / len(free)
        for j in g:
            out.append((counts[j] * variances[j] + a * pooled) / (counts[j] + a) if opts.is_free(j) else variances[j])
    return jnp.stack(out)


def map_weights(counts, opts: EMOptions):
    """Within-class weights from soft counts: maximum likelihood, or MAP under a Dirichlet prior.

    Class k owns Gaussians G_k, F_k of them free (`EMOptions.is_free`), with soft counts n_j
    (sum over voxels of the responsibilities) and N_k = sum_{j in G_k} n_j. With a Dirichlet(alpha)
    prior on the class's weights, the M-step maximises sum_j (n_j + alpha_j - 1) log w_j subject to
    sum_j w_j = 1, whose solution is w_j = (n_j + a_j) / (N_k + sum_i a_i), a_j = alpha_j - 1
    (Ormoneit & Tresp 1998, IEEE TNN 9:639, eq. 9; Bishop 2006, PRML section 2.2.1). Here
    a_j = eta * N_k / F_k for a free Gaussian and 0 for a tied partial-volume one, eta =
    `opts.weight_prior`:

        w_j = (n_j + eta N_k / F_k [j free]) / ((1 + eta) N_k),

    a prior worth eta times the class's own voxels, shared equally among its free Gaussians (scaled
    with N_k, so it means the same at any voxel size and for any class size). It keeps each free
    Gaussian's weight >= eta / ((1 + eta) F_k): a pure tissue Gaussian cannot be emptied by a
    broad neighbour (a partial-volume tail, another class's overlapping tissue) taking its voxels
    one iteration at a time, the positive feedback through w_j that makes such a component collapse
    in maximum likelihood. The assumption: each free Gaussian of a class stands for a tissue the
    scan contains (DEFAULT_GAUSSIANS in segment.py); a partial-volume Gaussian may be empty.
    eta = 0 is maximum likelihood (w_j = n_j / N_k).

    Arguments:
        counts: (J,) soft counts n_j (> 0).
        opts: EMOptions (its groups, free Gaussians and weight_prior).
    Returns:
        (J,) weights, summing to 1 over each class's Gaussians.
    """
    eta = opts.weight_prior
    w = []
    for g in opts.groups:
        tot = functools.reduce(jnp.add, [counts[j] for j in g])
        n_free = sum(opts.is_free(j) for j in g)
        for j in g:
            a = eta * tot / n_free if opts.is_free(j) else 0.0
            w.append((counts[j] + a) / ((1.0 + eta) * tot))
    return jnp.stack(w)


def _tie_partial_volume(mu, var, opts: EMOptions, c, s):
    """Set the tied partial-volume Gaussians from the pure ones (standardised units; see module doc).

    Gaussian j of class a mixing with class b: the pure pair (ja of a, jb of b) closest in mean;
    mixing line I_b -> I_a in data units (exp of the data for log intensities); the half-line
    f in (1/2, 1) (A's side) mapped back to standardised units gives the endpoints e0 (f = 1/2), e1 (f = 1);
    mean (e0 + e1) / 2, variance (e1 - e0)^2 / 12 (uniform f) + min(var_ja, var_jb) (noise),
    faded into a copy of Gaussian ja where the line is not resolvable (|mu_ja - mu_jb| < 4 noise sd).
    """
    if not opts.pv_of or all(b < 0 for b in opts.pv_of):
        return mu, var
    free = [[j for j in g if opts.is_free(j)] for g in opts.groups]
    for j, b in enumerate(opts.pv_of):
        if b < 0:
            continue
        a = opts.component_class[j]
        pairs = [(ja, jb) for ja in free[a] for jb in free[b]]
        ia = np.array([p[0] for p in pairs])
        ib = np.array([p[1] for p in pairs])
        i = jnp.argmin(jnp.abs(mu[ia] - mu[ib]))
        ma, mb = mu[ia][i], mu[ib][i]
        noise = jnp.minimum(var[ia][i], var[ib][i])
        if opts.pv_log:
            half = jnp.log(0.5 * (jnp.exp(c + s * ma) + jnp.exp(c + s * mb)))
            e0 = (half - c) / s
        else:
            e0 = 0.5 * (ma + mb)
        e1 = ma
        # A mixing line shorter than the noise cannot be resolved (an equal mixture of two Gaussians
        # of sd sigma is bimodal only if their means differ by > 2 sigma): there, the tied Gaussian
        # fades into a copy of the pure one (t = 0 at 2 sigma, 1 at 4 sigma), which leaves the
        # class's likelihood unchanged instead of adding an unidentifiable split.
        t = jnp.clip((jnp.abs(ma - mb) / jnp.sqrt(noise) - 2.0) / 2.0, 0.0, 1.0)
        mu = mu.at[j].set(ma + t * (0.5 * (e0 + e1) - ma))
        var = var.at[j].set(var[ia][i] + t * ((e1 - e0) ** 2 / 12.0 + noise - var[ia][i]))
    return mu, var


def _init_params(ys, atlas, opts: EMOptions, n_hist: int = 1024):
    """Robust start values from each class's prior-weighted intensity distribution.

    Gaussian j of J in a class starts at the weighted quantile (j + 1/2) / J (its slice's median)
    with sd = (q((j + 3/4) / J) - q((j + 1/4) / J)) / 1.349 (its slice's interquartile range, the sd
    of a Gaussian), and equal weights. Quantiles, not moments: a blurred atlas puts some of every
    class's prior on its neighbours (CT CSF on bone), and moments would start the Gaussians hundreds
    of HU wide, from where they drift off the tissue (quantiles from a 1024-bin weighted histogram).
    """
    dtype = ys.dtype
    lo, hi = jnp.min(ys), jnp.max(ys)
    width = (hi - lo) / n_hist + jnp.finfo(dtype).tiny
    bins = jnp.clip(((ys - lo) / width).astype(jnp.int32), 0, n_hist - 1).ravel()
    edges = lo + jnp.arange(1, n_hist + 1, dtype=dtype) * width  # upper edge of each bin

    mus, vars_, ws = [], [], []
    for k, g in enumerate(opts.groups):
        hist = jax.ops.segment_sum(atlas[k].ravel(), bins, num_segments=n_hist)
        cdf = jnp.cumsum(hist) / jnp.maximum(jnp.sum(hist), jnp.finfo(dtype).tiny)

        def quantile(q):
            i = jnp.clip(jnp.searchsorted(cdf, q), 0, n_hist - 1)
            below = jnp.where(i > 0, cdf[jnp.maximum(i - 1, 0)], 0.0)
            frac = jnp.clip((q - below) / jnp.maximum(cdf[i] - below, jnp.finfo(dtype).tiny), 0.0, 1.0)
            return edges[i] - width * (1.0 - frac)  # linear within the bin

        n_j = sum(opts.is_free(j) for j in g)  # tied partial-volume Gaussians are set afterwards
        i = 0
        for j in g:
            ws.append(1.0 / len(g))
            if not opts.is_free(j):
                mus.append(jnp.zeros((), dtype))
                vars_.append(jnp.ones((), dtype))
                continue
            mus.append(quantile((i + 0.5) / n_j))
            iqr = quantile((i + 0.75) / n_j) - quantile((i + 0.25) / n_j)
            vars_.append(jnp.maximum((iqr / 1.349) ** 2, opts.var_floor))
            i += 1
    return jnp.stack(mus), jnp.stack(vars_), jnp.asarray(ws, dtype=dtype)


def _normalise_prior(priors, floor):
    return _normalised([jnp.maximum(priors[k], 0) + floor for k in range(priors.shape[0])])


# ----------------------------------------------------------------------------------------------
# public
# ----------------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("opts",))
def fit_mixture(y, priors, opts: EMOptions, init: MixtureParams | None = None, coords=None,
                noise_floor: NoiseFloor | None = None) -> EMResult:
    """Fit the atlas-prior Gaussian mixture with MRF, prior relaxation and bias field by EM.

    Arguments:
        y: (x, y, z) intensities (MRI: log intensities; CT: Hounsfield units).
        priors: (K, x, y, z) non-negative spatial priors (the registered atlas); `opts.prior_floor`
            is added and they are normalised over K inside.
        opts: EMOptions (static).
        init: optional starting parameters in data units (default: prior-weighted moments).
        coords: optional per-axis bias-basis coordinates in [-1, 1] (see `grid_coordinates`), for a
            strided sample of a larger grid; default: the grid spans [-1, 1].
        noise_floor: optional NoiseFloor (data units; for log data, `opts.pv_log`): every Gaussian's
            variance is kept >= the noise a tissue of its mean keeps in the data (on top of
            `opts.var_floor`); None: only `opts.var_floor`.
    Returns:
        EMResult (posteriors, parameters in data units, bias field, log-likelihood, iterations).
    """
    dtype = y.dtype
    c = jnp.mean(y)
    s = jnp.std(y) + jnp.finfo(dtype).eps
    ys = (y - c) / s
    atlas = _normalise_prior(jnp.asarray(priors, dtype), opts.prior_floor)
    floor = jnp.asarray(opts.var_floor, dtype)
    degree = opts.bias_degree
    n_bias = len(bias_terms(degree)) if degree > 0 else 0
    coords = grid_coordinates(ys.shape, dtype) if coords is None else tuple(jnp.asarray(a, dtype) for a in coords)
    bias_cls = tuple(range(1, opts.n_classes)) if opts.bias_classes is None else tuple(opts.bias_classes)
    bias_comp = [c_ in bias_cls for c_ in opts.component_class]

    if init is None:
        mu, var, w = _init_params(ys, atlas, opts)
        mu, var = _tie_partial_volume(mu, var, opts, c, s)
        coef = jnp.zeros((n_bias,), dtype)
    else:
        mu = (jnp.asarray(init.means, dtype) - c) / s
        var = jnp.asarray(init.variances, dtype) / s**2
        w = jnp.asarray(init.weights, dtype)
        coef = jnp.asarray(init.bias, dtype).reshape(n_bias) / s

    def bias_of(coef):
        return bias_field(coef, coords, degree) if degree > 0 else jnp.zeros_like(ys)

    final_phase = 1 if opts.relax > 0 else 0

    def body(state):
        it, phase, mu, var, w, coef, post_prev, prior, ll_cur, _ = state
        yc = ys - bias_of(coef)
        post, pj, lk, ll = _e_step(yc, _mrf_prior(prior, post_prev, opts.beta), mu, var, w, opts)
        r = _responsibilities(post, pj, lk, opts)
        mu, var, w = _m_step(yc, r, mu, opts, floor, var, s, noise_floor, c)
        mu, var = _tie_partial_volume(mu, var, opts, c, s)
        if degree > 0:
            wv = functools.reduce(jnp.add, [r[j] / var[j] for j in range(len(r)) if bias_comp[j]])
            rv = functools.reduce(jnp.add, [r[j] * (mu[j] / var[j]) for j in range(len(r)) if bias_comp[j]])
            coef = _fit_bias(wv, wv * ys - rv, coords, degree, opts.bias_ridge)
        ll_prev = ll_cur
        if final_phase:
            small = jnp.abs(ll - ll_cur) < opts.tol
            switch = (phase == 0) & small & (it + 1 >= opts.min_iter)
            prior = lax.cond(
                switch, lambda: _relaxed_prior(atlas, post, opts.relax, opts.relax_sigma_vox), lambda: list(prior)
            )
            phase = phase + switch.astype(phase.dtype)
            ll_prev = jnp.where(switch, -jnp.inf, ll_cur)  # the relaxed problem starts afresh
        return it + 1, phase, mu, var, w, coef, post, prior, ll, ll_prev

    def cond(state):
        it, phase, _, _, _, _, _, _, ll, ll_prev = state
        small = jnp.abs(ll - ll_prev) < opts.tol
        return (it < opts.max_iter) & ((it < opts.min_iter) | ~small | (phase < final_phase))

    inf = jnp.asarray(jnp.inf, dtype)
    state = (jnp.asarray(0), jnp.asarray(0), mu, var, w, coef, list(atlas), list(atlas), -inf, inf)
    it, phase, mu, var, w, coef, post, prior, ll, ll_prev = lax.while_loop(cond, body, state)
    converged = (jnp.abs(ll - ll_prev) < opts.tol) & (phase == final_phase)
    b = bias_of(coef)
    params = MixtureParams(means=mu * s + c, variances=var * s**2, weights=w, bias=coef * s)
    return EMResult(
        posteriors=jnp.stack(post), params=params, bias_field=b * s, log_likelihood=ll, n_iter=it,
        converged=converged,
    )


@functools.partial(jax.jit, static_argnames=("opts", "n_sweeps"))
def infer_posteriors(y, priors, params: MixtureParams, opts: EMOptions, n_sweeps: int = 3, coords=None):
    """Class posteriors at fixed mixture parameters, with MRF mean-field sweeps and relaxed priors.

    Used to label a full-resolution grid after `fit_mixture` ran on a strided sample of it.

    Arguments:
        y: (x, y, z) intensities in data units.
        priors: (K, x, y, z) atlas priors.
        params: MixtureParams (data units) from `fit_mixture`.
        opts: EMOptions (beta, relaxation, bias degree, prior floor are used).
        n_sweeps: mean-field E-step sweeps after the first E-step, with the atlas prior and then
            (if opts.relax) again with the relaxed prior.
        coords: per-axis bias coordinates of this grid (default: it spans [-1, 1]).
    Returns:
        (K, x, y, z) posteriors.
    """
    dtype = y.dtype
    atlas = _normalise_prior(jnp.asarray(priors, dtype), opts.prior_floor)
    coords = grid_coordinates(y.shape, dtype) if coords is None else tuple(jnp.asarray(a, dtype) for a in coords)
    b = bias_field(jnp.asarray(params.bias, dtype), coords, opts.bias_degree) if opts.bias_degree > 0 else 0.0
    yc = y - b
    mu, var, w = (jnp.asarray(a, dtype) for a in (params.means, params.variances, params.weights))
    # The parameters are fixed, so each class's likelihood is computed once; and since the posterior
    # normalises prior x likelihood over the classes, the MRF prior's own normalisation (`_mrf_prior`)
    # cancels: each sweep is q_k <- normalised(prior_k lik_k exp(beta N(q)_k)), the E-step of
    # `fit_mixture` up to rounding, at a third of its cost on a 1 mm grid.
    pj, _ = _component_densities(yc, mu, var, w)
    lik = [functools.reduce(jnp.add, [pj[j] for j in g]) for g in opts.groups]
    lik = lax.optimization_barrier(lik)  # materialised once, read by every sweep

    def sweeps(prior, q):
        if n_sweeps == 0:
            return q
        joint = lax.optimization_barrier([pk * lk for pk, lk in zip(prior, lik)])
        if opts.beta <= 0:  # every sweep gives the posterior under this prior
            return _normalised(joint)
        return lax.fori_loop(0, n_sweeps, lambda _, q: _normalised(
            [jk * jnp.exp(opts.beta * neighbour_sum(qk)) for jk, qk in zip(joint, q)]), q)

    post = _normalised([pk * lk for pk, lk in zip(atlas, lik)])
    post = sweeps(atlas, post)
    if opts.relax > 0:  # as in fit_mixture: relax once, then sweep again
        post = sweeps(_relaxed_prior(atlas, post, opts.relax, opts.relax_sigma_vox), post)
    return jnp.stack(post)
