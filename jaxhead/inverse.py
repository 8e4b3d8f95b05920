"""Difference imaging: truncated-SVD and Tikhonov reconstruction, parameter choice, image metrics.

Linearised problem: J dsigma = dv, with J the (n_rows, n_params) sensitivity matrix and dv the
voltage change. Both methods act through the thin SVD J = U S V^T (Hansen 1998, "Rank-deficient and
discrete ill-posed problems"; Bagshaw et al. 2003 use TSVD for head EIT, as the seed paper does).
"""

import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
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
    import scipy.linalg

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
    """
    if jnp.ndim(dv) != 1:
        raise ValueError(f"`dv` has shape {jnp.shape(dv)}; pass (n_rows,) (or use "
                         "reconstruct_batch for many data vectors).")
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


def simulate_difference(model, sigma_ref, sigma_pert, protocol, *, noise_percent: float = 0.0,
                        seed: int = 0):
    """Difference data of a conductivity change, optionally with noise per channel.

    To avoid the inverse crime (Kaipio & Somersalo 2005, sec. 1.2: data simulated with the very
    model that inverts them hide the modelling error), simulate on a finer mesh than the
    reconstruction mesh: place electrodes at the same positions with the same radius on both
    meshes, perturb the fine mesh's conductivity (e.g. `spherical_perturbation(fine_mesh, ...)`),
    call this with the fine model, and reconstruct with the coarse model's Jacobian. The data
    vector lines up with the coarse model's rows because both use the same `protocol`.

    Arguments:
        model: the ForwardModel that simulates the data (the fine one).
        sigma_ref, sigma_pert: (4,) or (n_tets,) conductivities of the model in S/m, before
            and after the change.
        protocol: the Protocol (same electrode order as the reconstruction model).
        noise_percent: Gaussian noise in % of each channel's baseline voltage (the seed paper's
            0.5 %), added to the difference (`add_noise(dv, noise_percent, reference=v_ref)`).
        seed: noise seed.

    Returns:
        dv: (n_rows,) voltage change in V (noisy when noise_percent > 0); v_ref: (n_rows,)
        baseline voltages in V (noise-free; `noise_std(v_ref, noise_percent)` is the noise level).
    """
    from .fem import simulate

    if noise_percent < 0:
        raise ValueError(f"`noise_percent` must be >= 0, got {noise_percent}.")
    v_ref = np.asarray(simulate(model, sigma_ref, protocol))
    dv = np.asarray(simulate(model, sigma_pert, protocol)) - v_ref
    if noise_percent > 0:
        dv = add_noise(dv, noise_percent, seed=seed, reference=v_ref)
    return dv, v_ref


# --- simulation helpers -------------------------------------------------------------------------


def spherical_perturbation(mesh, sigma_tet, centre_mm, radius_mm: float, rel_change: float,
                           *, tissue=None) -> np.ndarray:
    """Per-tet conductivity with a spherical change: sigma * (1 + rel_change) inside the ball.

    Arguments:
        mesh: a `TetMesh`.
        sigma_tet: (n_tets,) baseline conductivity (S/m).
        centre_mm: (3,) ball centre in world mm.
        radius_mm: ball radius in mm (tets whose centroid lies inside change).
        rel_change: relative change, e.g. 0.1 for +10 %.
        tissue: restrict the change to one tissue (e.g. "brain"); None changes any tissue.

    Returns:
        (n_tets,) perturbed conductivity.
    """
    from .tissue import Tissue

    sigma_tet = np.asarray(sigma_tet, dtype=np.float64)
    if sigma_tet.shape != (mesh.n_tets,):
        raise ValueError(f"`sigma_tet` has shape {sigma_tet.shape}; pass one value per tet ({mesh.n_tets}).")
    if not radius_mm > 0:
        raise ValueError(f"`radius_mm` must be > 0, got {radius_mm}.")
    if not rel_change > -1:
        raise ValueError(f"`rel_change` must be > -1 (conductivity stays positive), got {rel_change}.")
    inside = perturbation_mask(mesh, centre_mm, radius_mm, tissue=tissue)
    if not inside.any():
        where = "" if tissue is None else f" {Tissue.parse(tissue).name}"
        raise ValueError(f"no{where} tet centroid lies within {radius_mm} mm of {list(centre_mm)}; "
                         "move the centre or enlarge the radius.")
    out = sigma_tet.copy()
    out[inside] *= 1.0 + rel_change
    return out


def perturbation_mask(mesh, centre_mm, radius_mm: float, *, tissue=None) -> np.ndarray:
    """Boolean (n_tets,) mask of tets whose centroid lies inside the ball (and tissue)."""
    from .tissue import Tissue

    c = np.asarray(centre_mm, dtype=np.float64)
    if c.shape != (3,):
        raise ValueError(f"`centre_mm` must be 3 coordinates, got shape {c.shape}.")
    inside = np.linalg.norm(mesh.centroids() - c, axis=1) <= radius_mm
    if tissue is not None:
        inside &= mesh.labels == int(Tissue.parse(tissue))
    return inside


def add_noise(v, percent: float, *, seed: int = 0, reference=None) -> np.ndarray:
    """Add zero-mean Gaussian noise of `percent` % of each channel's magnitude (the seed paper's model).

    Arguments:
        v: (n_rows,) voltages (V).
        percent: noise standard deviation in % of |reference| per channel (e.g. 0.5).
        seed: random seed.
        reference: (n_rows,) magnitudes the percentage refers to (default: |v|; for difference
            data pass the baseline voltages).

    Returns:
        (n_rows,) noisy voltages; the per-channel standard deviation is `noise_std(v, percent)`.
    """
    v = np.asarray(v, dtype=np.float64)
    if percent < 0:
        raise ValueError(f"`percent` must be >= 0, got {percent}.")
    std = noise_std(v if reference is None else reference, percent)
    return v + np.random.default_rng(seed).standard_normal(v.shape) * std


def noise_std(reference, percent: float, *, floor: float = 0.0) -> np.ndarray:
    """Per-channel noise standard deviation: percent / 100 * max(|reference|, floor * RMS).

    Arguments:
        reference: (n_rows,) voltages the percentage refers to (V).
        percent: noise in % per channel.
        floor: as a fraction of the RMS of `reference`, the smallest magnitude a channel's
            noise refers to. 0 (default) is the pure per-channel model `add_noise` draws from.
            For weights in a reconstruction a small floor (e.g. 0.03) keeps channels whose
            standing voltage is nearly zero from being trusted beyond the model's accuracy:
            whitening would otherwise amplify the reconstruction mesh's modelling error there.

    Returns:
        (n_rows,) standard deviations in V.
    """
    ref = np.abs(np.asarray(reference, dtype=np.float64))
    if not floor >= 0:
        raise ValueError(f"`floor` must be >= 0 (a fraction of the RMS), got {floor}.")
    if floor > 0:
        ref = np.maximum(ref, floor * np.sqrt(np.mean(ref**2)))
    return ref * (percent / 100.0)


# --- reconstruction grids -----------------------------------------------------------------------


class Grid(eqx.Module):
    """A coarse voxel grid for reconstruction: tets are grouped by the cell holding their centroid.

    Attributes:
        cell_of_tet: (n_tets,) cell index of each tet (-1 for tets not reconstructed).
        centres: (n_cells, 3) cell centres in mm (of the cells that hold tets).
        volumes: (n_cells,) tet volume in each cell, mm^3.
        cell_mm: cell edge length in mm.
    """

    cell_of_tet: np.ndarray
    centres: np.ndarray
    volumes: np.ndarray
    cell_mm: float = eqx.field(static=True)

    @property
    def n_cells(self) -> int:
        return self.centres.shape[0]


def make_grid(mesh, cell_mm: float, *, tissues=None, min_fill: float = 0.5) -> Grid:
    """Group tets into cubic cells of `cell_mm` (only tets of `tissues`, default all).

    Cells cut by the tissue's boundary hold only part of a cube; a sliver has a tiny column in
    the Jacobian, so column-normalised (NOSER) and minimum-norm images blow it up into a
    spurious peak. Cells filled below `min_fill` of a cube are therefore merged into the
    nearest cell that is filled enough (by the distance from each of their tets' centroids to
    that cell's centre), so every parameter stands for a comparable volume.

    Arguments:
        mesh: a `TetMesh`.
        cell_mm: cell edge in mm.
        tissues: the tissues to grid (names or `Tissue`), default all.
        min_fill: the smallest cell volume kept on its own, as a fraction of cell_mm^3 (0 keeps
            every cell; if no cell reaches it, none is merged).

    Returns:
        A `Grid`.
    """
    from scipy.spatial import cKDTree

    from .tissue import Tissue

    if not cell_mm > 0:
        raise ValueError(f"`cell_mm` must be > 0, got {cell_mm}.")
    if not 0 <= min_fill <= 1:
        raise ValueError(f"`min_fill` must be in [0, 1] (a fraction of a full cell), got {min_fill}.")
    cen = mesh.centroids()
    use = np.ones(mesh.n_tets, bool)
    if tissues is not None:
        use = np.isin(mesh.labels, [int(Tissue.parse(t)) for t in tissues])
    if not use.any():
        raise ValueError(f"no tet of tissues {list(tissues)} in the mesh; check `tissues`.")
    ijk = np.floor((cen - cen.min(0)) / cell_mm).astype(np.int64)
    key = (ijk[:, 0] * (ijk[:, 1].max() + 1) + ijk[:, 1]) * (ijk[:, 2].max() + 1) + ijk[:, 2]
    _, inv = np.unique(key[use], return_inverse=True)
    cell = np.full(mesh.n_tets, -1, np.int64)
    cell[use] = inv.ravel()
    vol = mesh.tet_volumes()

    def cells_of(cell):
        n = int(cell.max()) + 1
        volumes = np.bincount(cell[use], weights=vol[use], minlength=n)
        centres = np.stack([np.bincount(cell[use], weights=vol[use] * cen[use, d], minlength=n)
                            for d in range(3)], axis=1) / volumes[:, None]
        return volumes, centres

    volumes, centres = cells_of(cell)
    full = volumes >= min_fill * cell_mm**3
    if full.any() and not full.all():
        big = np.flatnonzero(full)
        move = use & ~full[np.maximum(cell, 0)]
        _, nearest = cKDTree(centres[big]).query(cen[move])
        cell[move] = big[nearest]
        _, cell[use] = np.unique(cell[use], return_inverse=True)  # renumber 0..n-1
        volumes, centres = cells_of(cell)
    return Grid(cell, centres, volumes, float(cell_mm))


def jacobian_to_grid(J, grid: Grid) -> np.ndarray:
    """Sum the per-tet Jacobian columns into grid cells: (n_rows, n_tets) -> (n_rows, n_cells).

    A cell's parameter is a uniform conductivity change over its tets, so its column is the sum
    of theirs (chain rule).
    """
    J = np.asarray(J)
    if J.shape[1] != grid.cell_of_tet.shape[0]:
        raise ValueError(f"`J` has {J.shape[1]} columns but the grid was made for "
                         f"{grid.cell_of_tet.shape[0]} tets.")
    use = grid.cell_of_tet >= 0
    out = np.zeros((J.shape[0], grid.n_cells), dtype=np.float64)
    np.add.at(out.T, grid.cell_of_tet[use], J[:, use].T.astype(np.float64))
    return out


def grid_to_tets(x_cells, grid: Grid) -> np.ndarray:
    """Spread a cell image back onto the tets (0 for tets outside the grid)."""
    x = np.asarray(x_cells)
    out = np.zeros(grid.cell_of_tet.shape[0], dtype=x.dtype)
    use = grid.cell_of_tet >= 0
    out[use] = x[grid.cell_of_tet[use]]
    return out


# --- image metrics ------------------------------------------------------------------------------


class ImageMetrics(eqx.Module):
    """Figures of merit of a reconstructed blob.

    Attributes:
        localisation_error_mm: distance from the thresholded image's centroid to the true centre.
        diameter_mm: diameter of the sphere with the thresholded region's volume (the FWHM-like
            size when threshold = 0.5).
        volume_ratio: thresholded volume / true perturbation volume (1 ideal).
        peak_value: the image's extreme value of the perturbation's sign.
    """

    localisation_error_mm: float
    diameter_mm: float
    volume_ratio: float
    peak_value: float


def image_metrics(image, centres_mm, volumes_mm3, true_centre_mm, true_radius_mm: float,
                  *, threshold: float = 0.5, sign: int = 0) -> ImageMetrics:
    """Localisation error, size and volume ratio of a reconstructed perturbation.

    Arguments:
        image: (n,) reconstructed change per element (tets or grid cells).
        centres_mm: (n, 3) element centres; volumes_mm3: (n,) element volumes.
        true_centre_mm, true_radius_mm: the perturbation's ball.
        threshold: keep elements with value >= threshold * peak (0.5: half maximum).
        sign: +1 or -1 for the perturbation's sign; 0 takes the sign of the largest |value|.
    """
    x = np.asarray(image, dtype=np.float64)
    c = np.asarray(centres_mm, dtype=np.float64)
    v = np.asarray(volumes_mm3, dtype=np.float64)
    if not (x.shape[0] == c.shape[0] == v.shape[0]):
        raise ValueError(f"`image` ({x.shape[0]}), `centres_mm` ({c.shape[0]}) and `volumes_mm3` "
                         f"({v.shape[0]}) must have one entry per element.")
    if not 0 < threshold < 1:
        raise ValueError(f"`threshold` must be in (0, 1), got {threshold}.")
    if sign == 0:
        sign = 1 if x[np.argmax(np.abs(x))] >= 0 else -1
    y = sign * x
    peak = y.max()
    if not peak > 0:
        raise ValueError("the image has no value of the requested sign; nothing to measure.")
    sel = y >= threshold * peak
    w = v[sel] * y[sel]
    centroid = (c[sel] * w[:, None]).sum(0) / w.sum()
    vol = v[sel].sum()
    true_vol = 4 / 3 * np.pi * true_radius_mm**3
    return ImageMetrics(
        localisation_error_mm=float(np.linalg.norm(centroid - np.asarray(true_centre_mm))),
        diameter_mm=float(2 * (3 * vol / (4 * np.pi)) ** (1 / 3)),
        volume_ratio=float(vol / true_vol),
        peak_value=float(sign * peak),
    )


@functools.partial(jax.jit, static_argnames=("n_cells",))
def _cell_sums(acc, rows, cells, *, n_cells: int):
    """acc (n_rows, n_cells) + the tile's (n_rows, width) columns summed by cell (-1/n: dropped)."""
    return acc + jax.ops.segment_sum(rows.T, cells, num_segments=n_cells).T


def jacobian_grid(model, sigma, protocol, grid: Grid, *, tile_tets: int = 8192,
                  return_volts: bool = False):
    """The Jacobian summed into grid cells, (n_rows, n_cells), without the per-tet matrix.

    Equal to `jacobian_to_grid(jacobian(model, sigma, protocol), grid)`, but only the tets the
    grid uses are visited, `tile_tets` at a time: each tile's rows (the reciprocity bilinear
    forms of `jaxhead.fem.jacobian`) are summed into their cells at once, so memory stays at
    (n_rows, n_cells) + (n_rows, tile_tets) instead of (n_rows, n_tets) (4.4 GB for 928 rows
    on a 592k-tet head in float64).

    Arguments:
        model: a `ForwardModel`; sigma: (4,) or (n_tets,) conductivity in S/m.
        protocol: the `Protocol` (concrete rows).
        grid: a `Grid` from `make_grid(mesh, ...)` of the model's mesh.
        tile_tets: tets per tile.
        return_volts: also return the (n_rows,) voltages at sigma (from the same solves).

    Returns:
        (n_rows, n_cells) NumPy array in V / (S/m) (and the voltages with return_volts).
    """
    # The fields and per-tile row products are jaxhead.fem.forward's own reciprocity code.
    from .fem import forward as fw

    if grid.cell_of_tet.shape != (model.n_tets,):
        raise ValueError(f"`grid` was made for {grid.cell_of_tet.shape[0]} tets but the model "
                         f"has {model.n_tets}; make the grid from the model's mesh.")
    if int(tile_tets) < 1:
        raise ValueError(f"`tile_tets` must be >= 1, got {tile_tets}.")
    rows, current = fw._rows_of(model, protocol)
    if not isinstance(rows, np.ndarray):
        raise ValueError("`jacobian_grid` needs concrete protocol rows.")
    currents, combo, d_idx, m_idx, d_sign, m_sign = fw._row_fields(model, rows)
    sigma = fw._check_sigma(model, sigma)
    fields, volts = fw._jacobian_solve(model, sigma, None, None, currents, combo, rows[:, 2],
                                       rows[:, 3], d_idx, current * d_sign)
    scale = jnp.asarray(-current * d_sign * m_sign)
    d_idx, m_idx = jnp.asarray(d_idx), jnp.asarray(m_idx)
    used = np.flatnonzero(grid.cell_of_tet >= 0)
    n_cells = grid.n_cells
    tile = max(1, min(int(tile_tets), used.size))
    n_tiles = -(-used.size // tile)
    pad = n_tiles * tile - used.size
    # Padding: tet 0 with cell n_cells, which segment_sum drops; one compiled shape for all tiles.
    tet_idx = np.concatenate([used, np.zeros(pad, np.int64)]).reshape(n_tiles, tile)
    cell_idx = np.concatenate([grid.cell_of_tet[used],
                               np.full(pad, n_cells, np.int64)]).reshape(n_tiles, tile)
    x = fw._geometry(model, None)
    acc = jnp.zeros((rows.shape[0], n_cells))
    for t in range(n_tiles):
        g, w = _tile_grads(x, model.tets, fields, jnp.asarray(tet_idx[t]))
        r = fw._rows_jit(g, w, d_idx, m_idx, scale, np.dtype(np.float64))
        acc = _cell_sums(acc, r, jnp.asarray(cell_idx[t]), n_cells=n_cells)
    J = np.asarray(acc)
    return (J, np.asarray(volts)) if return_volts else J


@jax.jit
def _tile_grads(x, tets, fields, idx):
    from .fem.forward import _grads

    return _grads(x, tets[idx], fields, np.dtype(np.float64))
