"""Difference imaging: truncated-SVD and Tikhonov reconstruction, parameter choice, image metrics.

Linearised problem: J dsigma = dv, with J the (n_rows, n_params) sensitivity matrix and dv the
voltage change. Both methods act through the thin SVD J = U S V^T (Hansen 1998, "Rank-deficient and
discrete ill-posed problems"; Bagshaw et al. 2003 use TSVD for head EIT, as the seed paper does).
"""

import functools
import warnings
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jaxtyping import Array, Float

Rule = Literal["gcv", "discrepancy"]


class TSVD(eqx.Module):
    """Truncated SVD: keep the `k` largest singular values (chosen by `rule` when None).

    `noise_weighted` truncates the SVD of W J (W = diag(1 / noise_std)) applied to W dv, i.e.
    whitened data; `normalise` solves for D x with D = diag(column norms of (W) J)^p, the NOSER
    scaling (Cheney et al. 1990, Int. J. Imaging Syst. Technol. 2:66), which counters the
    zeroth-order prior's pull of the image towards the most sensitive (superficial) elements.
    `normalise=True` is p = 1 (full NOSER); a number in [0, 1] sets p. p = 0.5 is EIDORS's
    `prior_noser` default exponent (Adler & Lionheart 2006, Physiol. Meas. 27:S25): on heads,
    p = 1 lifts the least sensitive cells (far from the electrodes) into spurious peaks.
    """

    k: int | None = eqx.field(static=True, default=None)
    rule: Rule = eqx.field(static=True, default="gcv")
    noise_weighted: bool = eqx.field(static=True, default=False)
    normalise: bool | float = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.k is not None and self.k < 1:
            raise ValueError(f"`TSVD.k` must be >= 1 (or None to choose it), got {self.k}.")
        _check_rule(self.rule)
        _check_exponent(self.normalise)


class Tikhonov(eqx.Module):
    """Zeroth-order Tikhonov: minimise ||W (J x - dv)||^2 + lam^2 ||D x||^2.

    `lam` is chosen by `rule` when None; `noise_weighted` uses W = diag(1 / noise_std) per
    channel (else W = I); `normalise` uses D = diag(column norms of W J)^p, the NOSER prior
    (Cheney et al. 1990; p as in `TSVD`: True is 1, a number in [0, 1] sets p), else D = I.
    """

    lam: float | None = eqx.field(static=True, default=None)
    rule: Rule = eqx.field(static=True, default="gcv")
    noise_weighted: bool = eqx.field(static=True, default=False)
    normalise: bool | float = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.lam is not None and not self.lam > 0:
            raise ValueError(f"`Tikhonov.lam` must be > 0 (or None to choose it), got {self.lam}.")
        _check_rule(self.rule)
        _check_exponent(self.normalise)


def _check_exponent(normalise):
    if not 0 <= float(normalise) <= 1:
        raise ValueError(f"`normalise` = {normalise!r}; use True/False or an exponent in [0, 1].")


def _check_rule(rule):
    if rule not in ("gcv", "discrepancy"):
        raise ValueError(f"`rule` = {rule!r}; use 'gcv' or 'discrepancy'.")


class Reconstruction(eqx.Module):
    """A reconstructed image and how it was regularised.

    Attributes:
        image: (n_params,) conductivity change (same units as dv / J).
        method: "tsvd" or "tikhonov".
        k: kept singular values (TSVD) or the effective number of parameters sum f_i (Tikhonov).
        lam: Tikhonov parameter (NaN for TSVD).
        residual_norm: ||J x - dv|| (||W (J x - dv)|| with noise weighting).
        rule: how k / lam was chosen ("given", "gcv", "discrepancy").
    """

    image: Float[Array, " n_params"]
    method: str = eqx.field(static=True)
    k: float
    lam: float
    residual_norm: float
    rule: str = eqx.field(static=True)


class SVD(eqx.Module):
    """Thin SVD of a (column-scaled) sensitivity matrix, reused for every reconstruction.

    Attributes:
        u: (n_rows, r), s: (r,), vt: (r, n_params): J D^-1 = U S V^T.
        scale: (n_params,) the column scaling D (ones unless `svd(J, normalise=...)`).
        normalised: the exponent p of D = diag(column norms)^p (0: no scaling).
    """

    u: Float[Array, "n_rows r"]
    s: Float[Array, " r"]
    vt: Float[Array, "r n_params"]
    scale: Float[Array, " n_params"]
    normalised: float = eqx.field(static=True, default=0.0)


def svd(J, *, normalise: bool = False, gram: bool | None = None) -> SVD:
    """Thin SVD of J (n_rows, n_params) in float64, from a Gram matrix or by LAPACK.

    Gram route: the eigendecomposition of the smaller Gram matrix (J J^T or J^T J) gives S and
    one set of singular vectors, the other follows by one product (V^T = S^-1 U^T J, or
    U = J V S^-1): O(m n min(m, n)) with a small constant, several times faster than LAPACK's
    SVD on EIT-sized matrices (see benchmarks/inverse.py). It squares the condition number, so
    singular values below sqrt(eps) s_max (~1.5e-8) are dropped; they carry nothing at any
    realistic noise level (0.5 % noise is 5e-3). LAPACK route: `jnp.linalg.svd`, dropping
    values below eps max(m, n) s_max.

    Arguments:
        J: (n_rows, n_params) matrix.
        normalise: decompose J D^-1 with D = diag(||J[:, j]||)^p, p = 1 for True, 0 for
            False, or a number in [0, 1] (columns that are all zero keep scale 1).
        gram: force the route; None takes the Gram route when one side is over twice the other
            or both exceed 500 (where LAPACK's SVD costs seconds).

    Returns:
        An `SVD`.
    """

    J = np.asarray(J, dtype=np.float64)
    if J.ndim != 2:
        raise ValueError(f"`J` must be 2D (n_rows, n_params), got shape {J.shape}.")
    if not np.all(np.isfinite(J)):
        raise ValueError("`J` contains NaN or Inf.")
    _check_exponent(normalise)
    p = float(normalise)
    m, n = J.shape
    scale = np.ones(n)
    if p > 0:
        norms = np.linalg.norm(J, axis=0)
        scale = np.where(norms > 0, norms**p, 1.0)
        J = J / scale
    if gram is None:
        gram = max(m, n) > 2 * min(m, n) or min(m, n) > 500
    # NumPy/SciPy on the host: their BLAS products and LAPACK's divide-and-conquer eigensolver
    # are ~2x faster here than the same operations in JAX on CPU (benchmarks/inverse.py).
    if gram:
        wide = n >= m
        G = J @ J.T if wide else J.T @ J
        w, q = scipy.linalg.eigh(G, driver="evd", overwrite_a=True, check_finite=False)
        w, q = w[::-1], q[:, ::-1]  # descending
        s = np.sqrt(np.clip(w, 0.0, None))
        keep = s > s[0] * 1e-7  # ~sqrt(eps): the Gram squares the condition number
        q, s = q[:, keep], s[keep]
        if wide:
            u, vt = np.ascontiguousarray(q), (q.T @ J) / s[:, None]
        else:
            u, vt = (J @ q) / s[None, :], np.ascontiguousarray(q.T)
    else:
        u, s, vt = np.linalg.svd(J, full_matrices=False)
        keep = s > s[0] * np.finfo(np.float64).eps * max(m, n)
        u, s, vt = u[:, keep], s[keep], vt[keep]
    return SVD(u, s, vt, scale, p)


def _weights(dv, noise_std):
    if noise_std is None:
        return None
    w = jnp.broadcast_to(jnp.asarray(noise_std, jnp.float64), dv.shape[-1:])
    if not bool(jnp.all(jnp.isfinite(w) & (w > 0))):
        raise ValueError("`noise_std` must be finite and > 0 for every channel (V).")
    return 1.0 / w


def _filtered(dec: SVD, beta, perp2, f):
    """Image, residual norm^2 and trace for filter factors f (Hansen 1998, eq. 4.3 ff.)."""
    x = (dec.vt.T @ (f * beta / dec.s)) / dec.scale
    r2 = jnp.sum(((1.0 - f) * beta) ** 2) + perp2
    return x, r2, jnp.sum(f)


_N_LAMBDA = 200  # Tikhonov lambda grid: 200 log-spaced values from 1e-8 s_max to 10 s_max


@functools.partial(jax.jit, static_argnames=("kind", "rule", "given", "per_channel"))
def _core(dec: SVD, b, w, k_or_lam, *, kind: str, rule: str, given: bool, per_channel: bool):
    """Filter factors by the method's rule, the image and its figures: pure JAX, vmappable.

    Arguments:
        dec: SVD of the (weighted) matrix; b: (n_rows,) (weighted) data.
        w: (n_rows,) inverse noise std per channel (ones when unknown; used by "discrepancy").
        k_or_lam: the given k (TSVD) or lambda (Tikhonov) when `given`.
        kind: "tsvd" or "tikhonov"; rule: "gcv" or "discrepancy".
        per_channel: the residual in noise units needs the per-channel weights (non-uniform
            noise and an unweighted SVD); else it is ||r|| w[0] (or ||r|| when weighted).
    Returns:
        image (n_params,), k or trace, lambda (NaN for TSVD), residual norm ||b - A x||.
    """
    m = b.shape[0]
    r = dec.s.shape[0]
    beta = dec.u.T @ b
    perp2 = jnp.maximum(jnp.sum(b**2) - jnp.sum(beta**2), 0.0)
    target = 1.05 * jnp.sqrt(m)  # Morozov's tau slightly above 1 (Hansen 1998, sec. 7.2)
    if given:
        if kind == "tsvd":
            f = (jnp.arange(r) < k_or_lam).astype(b.dtype)
            lam = jnp.nan
        else:
            lam = jnp.asarray(k_or_lam, b.dtype)
            f = dec.s**2 / (dec.s**2 + lam**2)
    elif kind == "tsvd":
        ks = jnp.arange(1, r + 1)
        tail = jnp.cumsum((beta**2)[::-1])[::-1]  # tail[i] = sum_{j >= i} beta_j^2
        r2 = jnp.concatenate([tail[1:], jnp.zeros(1, b.dtype)]) + perp2  # residual^2, k = 1..r
        if rule == "gcv":  # G = ||r||^2 / (m - k)^2 (Golub, Heath & Wahba 1979)
            i = jnp.argmin(r2 / jnp.maximum(m - ks, 0.5) ** 2)
        else:
            if per_channel:  # ||W (A x_k - b)|| with A x_k = U[:, :k] beta[:k]
                fits = jnp.cumsum(dec.u * beta[None, :], axis=1)  # (n_rows, r)
                res = jnp.sqrt((((fits - b[:, None]) * w[:, None]) ** 2).sum(0))
            else:
                res = jnp.sqrt(r2) * w[0]
            ok = res <= target
            i = jnp.where(ok.any(), jnp.argmax(ok), r - 1)  # smallest k meeting it, else all
        f = (jnp.arange(r) <= i).astype(b.dtype)
        lam = jnp.nan
    else:
        lams = jnp.geomspace(dec.s[0] * 1e-8, dec.s[0] * 10, _N_LAMBDA)
        F = dec.s**2 / (dec.s**2 + lams[:, None] ** 2)  # (n_lams, r) filter factors
        r2 = (((1.0 - F) * beta) ** 2).sum(1) + perp2  # residual^2 of every lambda
        if rule == "gcv":
            i = jnp.argmin(r2 / jnp.maximum(m - F.sum(1), 0.5) ** 2)
        else:
            if per_channel:
                fits = dec.u @ (F * beta).T  # (n_rows, n_lams)
                res = jnp.sqrt((((fits - b[:, None]) * w[:, None]) ** 2).sum(0))
            else:
                res = jnp.sqrt(r2) * w[0]
            ok = res <= target
            # the largest lambda that meets the noise level, else the smallest lambda
            i = jnp.where(ok.any(), F.shape[0] - 1 - jnp.argmax(ok[::-1]), 0)
        f = F[i]
        lam = lams[i]
    x, rr2, tr = _filtered(dec, beta, perp2, f)
    return x, tr, lam, jnp.sqrt(rr2)


def _setup(J, dv, method, noise_std, decomposition):
    """Validate, weight and decompose; returns (dec, b, w, per_channel)."""
    if not isinstance(method, (TSVD, Tikhonov)):
        raise ValueError(f"`method` must be TSVD(...) or Tikhonov(...), got {method!r}.")
    dv = jnp.asarray(dv, dtype=jnp.float64)
    n_rows = (getattr(J, "shape", (None,))[0] if decomposition is None
              else decomposition.u.shape[0])
    if dv.ndim not in (1, 2) or dv.shape[-1] != n_rows:
        raise ValueError(
            f"`dv` has shape {dv.shape} but `J` has {n_rows} rows; pass one voltage change "
            "per protocol row.")
    if not bool(jnp.all(jnp.isfinite(dv))):
        raise ValueError("`dv` contains NaN or Inf.")
    w = _weights(dv, noise_std)
    if method.rule == "discrepancy" and w is None and not _given(method):
        raise ValueError("the discrepancy rule needs `noise_std` (per channel or scalar, in V).")
    weighted = method.noise_weighted
    if weighted and w is None:
        raise ValueError(f"`{type(method).__name__}(noise_weighted=True)` needs `noise_std`.")
    if decomposition is None:
        if J is None:
            raise ValueError("pass `J` or a precomputed `decomposition`.")
        Jw = jnp.asarray(J, jnp.float64)
        if Jw.ndim != 2:
            raise ValueError(f"`J` must be 2D (n_rows, n_params), got shape {Jw.shape}.")
        decomposition = svd(Jw * w[:, None] if weighted else Jw, normalise=method.normalise)
    elif decomposition.normalised != float(method.normalise):
        raise ValueError(
            f"`decomposition` was made with normalise={decomposition.normalised} but the method "
            f"has normalise={method.normalise}; pass svd(J, normalise={method.normalise}).")
    b = dv * w if weighted else dv
    per_channel = (w is not None and not weighted and not bool(jnp.all(w == w[0]))
                   and method.rule == "discrepancy")
    if w is None or weighted:
        w = jnp.ones(dv.shape[-1])  # residuals are already in noise units (or unused)
    return decomposition, b, w, per_channel


def _given(method) -> bool:
    return (method.k if isinstance(method, TSVD) else method.lam) is not None


def _run(dec, b, w, method, per_channel):
    kind = "tsvd" if isinstance(method, TSVD) else "tikhonov"
    given = _given(method)
    value = (min(method.k, dec.s.shape[0]) if kind == "tsvd" else method.lam) if given else 0.0
    return _core(dec, b, w, value, kind=kind, rule=method.rule, given=given,
                 per_channel=per_channel)


#: More columns than this per row marks a per-tet Jacobian (a 10 mm grid over a head's brain has
#: ~1-2 cells per row of a 32-electrode protocol; a per-tet one ~300).
PER_TET_COLUMNS_PER_ROW = 20


def _warn_if_per_tet(J) -> None:
    if J is not None and jnp.ndim(J) == 2 and J.shape[1] > PER_TET_COLUMNS_PER_ROW * J.shape[0]:
        warnings.warn(
            f"`J` has {J.shape[1]} columns for {J.shape[0]} rows, a per-tet Jacobian: images on "
            "tets localise poorly on heads. Sum it into grid cells (`make_grid` + `jacobian_grid`, "
            "or `jacobian_to_grid`) and reconstruct with TSVD(normalise=0.5), as the inverse stage "
            "does.", UserWarning, stacklevel=3)


def reconstruct(J, dv, method: TSVD | Tikhonov = TSVD(), *, noise_std=None,
                decomposition: SVD | None = None) -> Reconstruction:
    """Reconstruct a conductivity change from a voltage change.

    Arguments:
        J: (n_rows, n_params) sensitivity matrix (V per unit parameter change).
        dv: (n_rows,) measured voltage change (V).
        method: `TSVD(k)` or `Tikhonov(lam)`; k / lam chosen by the method's rule when None:
            "gcv" minimises the generalised cross-validation function
            G = ||r||^2 / (n_rows - trace)^2 (Golub, Heath & Wahba 1979); "discrepancy" picks the
            strongest regularisation with ||W r|| <= 1.05 sqrt(n_rows) (Morozov 1966), which needs
            `noise_std`. Tikhonov's lambda is searched on 200 log-spaced values from
            1e-8 to 10 times the largest singular value.
        noise_std: per-channel (n_rows,) or scalar noise standard deviation (V). Used by the
            discrepancy rule and, with `noise_weighted=True`, as row weights.
        decomposition: a precomputed `svd(J, normalise=method.normalise)` to reuse across many
            reconstructions (of W J when the method is noise-weighted); `J` may then be None.

    Returns:
        A `Reconstruction` with the image on the parameters of J.

    Image on grid cells, not tets: on a head, a per-tet Jacobian (n_tets ~ 300k columns for ~1000
    rows) localised a 15 mm ball 53 mm off where the same data on 10 mm brain cells with NOSER
    normalisation (`jacobian_grid` + `TSVD(normalise=0.5)`, the inverse stage's path) gave 2-7 mm
    (README, issue 5). With far more columns than rows (> `PER_TET_COLUMNS_PER_ROW` per row) this
    warns and says so.
    """
    if jnp.ndim(dv) != 1:
        raise ValueError(f"`dv` has shape {jnp.shape(dv)}; pass (n_rows,) (or use "
                         "reconstruct_batch for many data vectors).")
    _warn_if_per_tet(J)
    dec, b, w, per_channel = _setup(J, dv, method, noise_std, decomposition)
    x, k, lam, res = _run(dec, b, w, method, per_channel)
    kind = "tsvd" if isinstance(method, TSVD) else "tikhonov"
    return Reconstruction(x, kind, float(k), float(lam), float(res),
                          "given" if _given(method) else method.rule)


def reconstruct_batch(J, dv, method: TSVD | Tikhonov = TSVD(), *, noise_std=None,
                      decomposition: SVD | None = None) -> Reconstruction:
    """`reconstruct` for many data vectors at once (`vmap` over the rows of `dv`).

    The SVD is computed once; each data vector gets its own k / lambda by the method's rule.
    This is how noise-realisation studies run: one compiled call for the whole batch.

    Arguments:
        J, method, noise_std, decomposition: as `reconstruct` (noise_std shared by the batch).
        dv: (n_batch, n_rows) voltage changes (V).

    Returns:
        A `Reconstruction` whose image is (n_batch, n_params) and whose k, lam and
        residual_norm are (n_batch,) arrays.
    """
    if jnp.ndim(dv) != 2:
        raise ValueError(f"`dv` has shape {jnp.shape(dv)}; pass (n_batch, n_rows).")
    dec, b, w, per_channel = _setup(J, dv, method, noise_std, decomposition)
    x, k, lam, res = jax.vmap(lambda bb: _run(dec, bb, w, method, per_channel))(b)
    kind = "tsvd" if isinstance(method, TSVD) else "tikhonov"
    return Reconstruction(x, kind, k, lam, res, "given" if _given(method) else method.rule)
