"""Difference imaging: truncated-SVD and Tikhonov reconstruction, parameter choice, image metrics.

Linearised problem: J dsigma = dv, with J the (n_rows, n_params) sensitivity matrix and dv the
voltage change. Both methods act through the thin SVD J = U S V^T (Hansen 1998, "Rank-deficient and
discrete ill-posed problems"; Bagshaw et al. 2003 use TSVD for head EIT, as the seed paper does).
"""

from typing import Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

Rule = Literal["gcv", "discrepancy"]


class TSVD(eqx.Module):
    """Truncated SVD: keep the `k` largest singular values (chosen by `rule` when None)."""

    k: int | None = eqx.field(static=True, default=None)
    rule: Rule = eqx.field(static=True, default="gcv")

    def __check_init__(self):
        if self.k is not None and self.k < 1:
            raise ValueError(f"`TSVD.k` must be >= 1 (or None to choose it), got {self.k}.")
        _check_rule(self.rule)


class Tikhonov(eqx.Module):
    """Zeroth-order Tikhonov: minimise ||W (J x - dv)||^2 + lam^2 ||x||^2.

    `lam` is chosen by `rule` when None; `noise_weighted` uses W = diag(1 / noise_std) per channel.
    """

    lam: float | None = eqx.field(static=True, default=None)
    rule: Rule = eqx.field(static=True, default="gcv")
    noise_weighted: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.lam is not None and not self.lam > 0:
            raise ValueError(f"`Tikhonov.lam` must be > 0 (or None to choose it), got {self.lam}.")
        _check_rule(self.rule)


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
        residual_norm: ||J x - dv|| (of W J x - W dv with noise weighting).
        rule: how k / lam was chosen ("given", "gcv", "discrepancy").
    """

    image: Float[Array, " n_params"]
    method: str = eqx.field(static=True)
    k: float
    lam: float
    residual_norm: float
    rule: str = eqx.field(static=True)


class SVD(eqx.Module):
    """Thin SVD of a sensitivity matrix (computed once, reused for every reconstruction)."""

    u: Float[Array, "n_rows r"]
    s: Float[Array, " r"]
    vt: Float[Array, "r n_params"]


def svd(J) -> SVD:
    """Thin SVD of J (n_rows, n_params) in float64, via the Gram matrix when n_params >> n_rows.

    For n_params >> n_rows, the eigendecomposition of J J^T (n_rows^2) costs O(n_rows^2 n_params)
    and gives U and S; V^T = S^-1 U^T J. Singular values below eps * s_max are dropped (they carry
    no information in float64 and would divide by ~0).
    """
    J = jnp.asarray(J, dtype=jnp.float64)
    if J.ndim != 2:
        raise ValueError(f"`J` must be 2D (n_rows, n_params), got shape {J.shape}.")
    m, n = J.shape
    if n > 4 * m:
        gram = J @ J.T
        w, u = jnp.linalg.eigh(gram)
        order = jnp.argsort(w)[::-1]
        w, u = w[order], u[:, order]
        s = jnp.sqrt(jnp.clip(w, 0.0, None))
        keep = np.asarray(s > s[0] * 1e-7)  # sqrt(eps): Gram squares the condition number
        u, s = u[:, keep], s[keep]
        vt = (u.T @ J) / s[:, None]
    else:
        u, s, vt = jnp.linalg.svd(J, full_matrices=False)
        keep = np.asarray(s > s[0] * jnp.finfo(jnp.float64).eps * max(m, n))
        u, s, vt = u[:, keep], s[keep], vt[keep]
    return SVD(u, s, vt)


def _weights(dv, noise_std):
    if noise_std is None:
        return None
    w = jnp.broadcast_to(jnp.asarray(noise_std, jnp.float64), dv.shape)
    if not bool(jnp.all(w > 0)):
        raise ValueError("`noise_std` must be > 0 for every channel.")
    return 1.0 / w


def _filtered(dec: SVD, beta, perp2, f):
    """Image, residual norm^2 and trace for filter factors f (Hansen 1998, eq. 4.3 ff.)."""
    x = dec.vt.T @ (f * beta / dec.s)
    r2 = jnp.sum(((1.0 - f) * beta) ** 2) + perp2
    return x, r2, jnp.sum(f)


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
            `noise_std`.
        noise_std: per-channel (n_rows,) or scalar noise standard deviation (V). Used by the
            discrepancy rule and, with `Tikhonov(noise_weighted=True)`, as row weights.
        decomposition: a precomputed `svd(J)` to reuse across many reconstructions
            (it must be of the (weighted) J the method uses).

    Returns:
        A `Reconstruction` with the image on the parameters of J.
    """
    dv = jnp.asarray(dv, dtype=jnp.float64)
    m = dv.shape[0] if dv.ndim == 1 else -1
    if dv.ndim != 1 or J.shape[0] != m:
        raise ValueError(
            f"`dv` has shape {dv.shape} but `J` has {J.shape[0]} rows; pass one voltage change "
            "per protocol row."
        )
    if not bool(jnp.all(jnp.isfinite(dv))):
        raise ValueError("`dv` contains NaN or Inf.")
    w = _weights(dv, noise_std)
    rule = method.rule
    if rule == "discrepancy" and w is None:
        raise ValueError("the discrepancy rule needs `noise_std` (per channel or scalar, in V).")
    weighted = isinstance(method, Tikhonov) and method.noise_weighted
    if weighted and w is None:
        raise ValueError("`Tikhonov(noise_weighted=True)` needs `noise_std`.")
    b = dv * w if weighted else dv
    if decomposition is None:
        Jw = jnp.asarray(J, jnp.float64)
        decomposition = svd(Jw * w[:, None] if weighted else Jw)
    dec = decomposition
    beta = dec.u.T @ b
    perp2 = jnp.maximum(jnp.sum(b**2) - jnp.sum(beta**2), 0.0)
    r = dec.s.shape[0]
    target = 1.05 * np.sqrt(m)  # Morozov's tau slightly above 1 (Hansen 1998, sec. 7.2)

    def noise_units_residual(f):
        """||W (J x_f - dv)||, the residual in units of the noise, for filter factors f."""
        r2 = jnp.sum(((1.0 - f) * beta) ** 2) + perp2
        if weighted:  # the SVD is of W J already
            return float(jnp.sqrt(r2))
        if bool(jnp.all(w == w[0])):  # uniform noise: a scalar factor
            return float(jnp.sqrt(r2) * w[0])
        x, _, _ = _filtered(dec, beta, perp2, f)
        return float(jnp.linalg.norm(w * (jnp.asarray(J, jnp.float64) @ x - dv)))

    if isinstance(method, TSVD):
        ks = np.arange(1, r + 1)
        if method.k is not None:
            k, chosen = min(method.k, r), "given"
        elif rule == "gcv":
            tail = jnp.cumsum((beta**2)[::-1])[::-1]  # sum_{i >= k} beta_i^2
            r2 = jnp.concatenate([tail[1:], jnp.zeros(1)]) + perp2
            denom = jnp.maximum(m - ks, 0.5) ** 2
            k, chosen = int(ks[int(jnp.argmin(r2 / denom))]), "gcv"
        else:
            k = r
            for kk in ks:
                if (noise_units_residual((jnp.arange(r) < kk).astype(jnp.float64))) <= target:
                    k = int(kk)
                    break
            chosen = "discrepancy"
        f = (jnp.arange(r) < k).astype(jnp.float64)
        x, r2, tr = _filtered(dec, beta, perp2, f)
        return Reconstruction(x, "tsvd", float(k), float("nan"), float(jnp.sqrt(r2)), chosen)

    s = dec.s
    if method.lam is not None:
        lam, chosen = float(method.lam), "given"
    else:
        lams = np.geomspace(float(s[0]) * 1e-8, float(s[0]) * 10, 200)
        sn, bn = np.asarray(s), np.asarray(beta)
        f_all = sn**2 / (sn**2 + lams[:, None] ** 2)  # (n_lams, r) filter factors
        if rule == "gcv":
            r2 = (((1.0 - f_all) * bn) ** 2).sum(1) + float(perp2)
            lam = float(lams[int(np.argmin(r2 / (m - f_all.sum(1)) ** 2))])
        else:
            lam = float(lams[0])
            for l, f in zip(lams[::-1], f_all[::-1]):  # strongest first
                if noise_units_residual(jnp.asarray(f)) <= target:
                    lam = float(l)
                    break
        chosen = rule
    f = s**2 / (s**2 + lam**2)
    x, r2, tr = _filtered(dec, beta, perp2, f)
    return Reconstruction(x, "tikhonov", float(tr), lam, float(jnp.sqrt(r2)), chosen)


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


def noise_std(reference, percent: float) -> np.ndarray:
    """Per-channel noise standard deviation: percent / 100 * |reference|."""
    return np.abs(np.asarray(reference, dtype=np.float64)) * (percent / 100.0)


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


def make_grid(mesh, cell_mm: float, *, tissues=None) -> Grid:
    """Group tets into cubic cells of `cell_mm` (only tets of `tissues`, default all)."""
    from .tissue import Tissue

    if not cell_mm > 0:
        raise ValueError(f"`cell_mm` must be > 0, got {cell_mm}.")
    cen = mesh.centroids()
    use = np.ones(mesh.n_tets, bool)
    if tissues is not None:
        use = np.isin(mesh.labels, [int(Tissue.parse(t)) for t in tissues])
    ijk = np.floor((cen - cen.min(0)) / cell_mm).astype(np.int64)
    key = (ijk[:, 0] * (ijk[:, 1].max() + 1) + ijk[:, 1]) * (ijk[:, 2].max() + 1) + ijk[:, 2]
    _, inv = np.unique(key[use], return_inverse=True)
    cell = np.full(mesh.n_tets, -1, np.int64)
    cell[use] = inv.ravel()
    n = int(cell.max()) + 1
    vol = mesh.tet_volumes()
    volumes = np.bincount(cell[use], weights=vol[use], minlength=n)
    centres = np.stack([np.bincount(cell[use], weights=vol[use] * cen[use, d], minlength=n)
                        for d in range(3)], axis=1) / volumes[:, None]
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
