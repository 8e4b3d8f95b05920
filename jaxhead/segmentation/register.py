"""Image registration in JAX: affine (12 dof) and cubic B-spline FFD, NMI / NCC, resampling.  [jax]

Conventions. A transform maps *fixed* world mm (RAS) to *moving* world mm, i.e. it pulls the moving
image back onto the fixed grid: ``warped(p) = moving(T(p))``. In jaxhead the fixed image is the
subject's scan and the moving image is the atlas template, so resampled atlas priors land on the
subject's voxel grid.

- Affine: ``T(p) = c_m + (I + L)(p - c_f) + t``, 12 parameters (L: 3x3, t: 3), centred on the
  intensity centres of mass so that rotation and scale are decoupled from translation; optimised with
  optimistix BFGS on a multi-resolution pyramid, coarse to fine (as reg_aladin ``-ln/-lp``, Ourselin
  et al. 2001, but with a gradient-based optimiser on an intensity similarity rather than block
  matching).
- Free-form deformation: ``T(p) = A(p + u(p))`` with ``u`` a cubic B-spline tensor product over a
  regular control grid in the fixed image's voxel frame (Rueckert et al. 1999, IEEE TMI 18:712), and a
  bending-energy penalty evaluated at the control points from the exact B-spline second derivatives
  (Modat et al. 2010, CMPB 98:278, reg_f3d); optimised with optimistix L-BFGS.
- Similarity: normalised mutual information NMI = (H(A) + H(B)) / H(A, B) (Studholme et al. 1999,
  Pattern Recognit. 32:71) from a joint histogram built with cubic B-spline Parzen windows, which makes
  it differentiable in the transform (Mattes et al. 2003, IEEE TMI 22:120); or the normalised cross
  correlation for images of the same modality.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.scipy.ndimage import map_coordinates

from ..volume import Volume, voxel_sizes

log = logging.getLogger(__name__)

Similarity = Literal["nmi", "ncc"]


# ----------------------------------------------------------------------------------------------
# configuration and transforms
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class RegisterConfig:
    """Settings of the atlas-to-subject registration.

    Arguments:
        similarity: "nmi" (normalised mutual information, any modality pair) or "ncc" (normalised
            cross correlation, same modality).
        affine_resolutions_mm: pyramid levels of the affine stage, coarse to fine, as voxel sizes in
            mm (each image is block-averaged by the integer factor closest to level / voxel size).
        bspline: run the non-linear cubic B-spline stage after the affine one.
        bspline_resolutions_mm: pyramid levels of the B-spline stage, coarse to fine.
        control_spacing_mm: B-spline control-point spacing in mm.
        bending_energy: weight of the bending-energy penalty (per mm^-2 squared second derivative,
            averaged over control points) relative to the similarity (which is O(1)).
        n_bins: histogram bins of NMI.
        max_samples: at most this many fixed-image voxels per level (affine: a random sample beyond
            it; B-spline: a regular stride).
        affine_max_steps, bspline_max_steps: optimiser iterations per level.
        rtol, atol: optimiser tolerances (optimistix Cauchy termination on parameters and cost).
    """

    similarity: Similarity = "nmi"
    affine_resolutions_mm: tuple[float, ...] = (8.0, 4.0)
    bspline: bool = True
    bspline_resolutions_mm: tuple[float, ...] = (4.0,)
    control_spacing_mm: float = 12.0
    bending_energy: float = 0.05
    n_bins: int = 32
    max_samples: int = 131_072
    affine_max_steps: int = 100
    bspline_max_steps: int = 60
    rtol: float = 1e-4
    atol: float = 1e-4

    def __post_init__(self):
        if self.similarity not in ("nmi", "ncc"):
            raise ValueError(f"[register] `similarity` must be 'nmi' or 'ncc', got {self.similarity!r}.")
        for name in ("affine_resolutions_mm", "bspline_resolutions_mm"):
            val = getattr(self, name)
            try:
                val = tuple(float(v) for v in val)
            except (TypeError, ValueError):
                val = None
            if val is None or not all(v > 0 for v in val):
                raise ValueError(
                    f"[register] `{name}` must be a sequence of positive mm values, got {getattr(self, name)!r}."
                )
            object.__setattr__(self, name, val)  # TOML gives lists: store a (hashable) tuple
        if not self.affine_resolutions_mm:
            raise ValueError("[register] `affine_resolutions_mm` is empty; give at least one level, e.g. (8.0, 4.0).")
        if self.bspline and not self.bspline_resolutions_mm:
            raise ValueError("[register] `bspline_resolutions_mm` is empty but `bspline` is on.")
        if not self.control_spacing_mm > 0:
            raise ValueError(f"[register] `control_spacing_mm` must be > 0, got {self.control_spacing_mm}.")
        if not self.bending_energy >= 0:
            raise ValueError(f"[register] `bending_energy` must be >= 0, got {self.bending_energy}.")
        if self.n_bins < 8:
            raise ValueError(f"[register] `n_bins` must be >= 8, got {self.n_bins}.")
        if self.max_samples < 1000:
            raise ValueError(f"[register] `max_samples` must be >= 1000, got {self.max_samples}.")
        for name in ("affine_max_steps", "bspline_max_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"[register] `{name}` must be >= 1, got {getattr(self, name)}.")


class AffineTransform(eqx.Module):
    """A 3D affine map from fixed world mm to moving world mm.

    Arguments:
        matrix: (4, 4) homogeneous matrix, ``q = matrix @ [p, 1]``.
    """

    matrix: jax.Array

    def points(self, p):
        """Map points (..., 3) in fixed mm to moving mm."""
        m = jnp.asarray(self.matrix)
        return p @ m[:3, :3].T + m[:3, 3]


class BSplineTransform(eqx.Module):
    """An affine composed with a cubic B-spline free-form deformation: ``T(p) = A(p + u(p))``.

    Arguments:
        affine: (4, 4) fixed mm -> moving mm, applied after the displacement.
        coefficients: (3, na, nb, nc) control-point displacements in fixed world mm.
        grid_affine: (4, 4) control-point index -> fixed world mm (axis-aligned with the fixed grid).
    """

    affine: jax.Array
    coefficients: jax.Array
    grid_affine: jax.Array


Transform = AffineTransform | BSplineTransform


# ----------------------------------------------------------------------------------------------
# small numerical building blocks
# ----------------------------------------------------------------------------------------------


def cubic_bspline(t):
    """The centred cubic B-spline kernel beta3(t) (support |t| < 2, integral 1, partition of unity)."""
    a = jnp.abs(t)
    return jnp.where(a < 1, 2.0 / 3.0 - a**2 + 0.5 * a**3, jnp.where(a < 2, (2.0 - a) ** 3 / 6.0, 0.0))


def _scale_to_bins(x, lo, hi, n_bins):
    return jnp.clip((x - lo) / (hi - lo) * (n_bins - 1), 0.0, n_bins - 1.0)


def _cubic_weights(v):
    """Bins (N, 4) and cubic B-spline weights (N, 4) of values v in bin units: beta3(v - c) for the
    4 bin centres c = floor(v) - 1 .. floor(v) + 2 that it touches (the weights sum to 1)."""
    i = jnp.floor(v)
    t = v - i
    t2, t3 = t * t, t * t * t
    w = jnp.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], -1) / 6.0
    bins = i.astype(jnp.int32)[:, None] + jnp.arange(-1, 3, dtype=jnp.int32)[None, :]
    return bins, w


def nmi(a, b, a_range, b_range, n_bins: int = 32, weights=None):
    """Normalised mutual information (H(A) + H(B)) / H(A, B) from a Parzen-window joint histogram.

    As Mattes et al. (2003): `a` (the fixed image) is binned with a zero-order (nearest-bin) kernel,
    `b` (the moving image) with a cubic B-spline kernel, which makes the histogram, and so NMI,
    differentiable in `b`. Only the 4 bins a sample touches are accumulated (a scatter-add, not an
    N x bins matrix).

    Arguments:
        a, b: (N,) paired intensities.
        a_range, b_range: (lo, hi) intensity ranges mapped onto the bins (values outside are clipped).
        n_bins: number of histogram bins per image.
        weights: optional (N,) sample weights (0 drops a sample, e.g. padding).
    Returns:
        scalar in [1, 2]: 1 for independent images, 2 for a one-to-one intensity relation
        (Studholme et al. 1999).
    """
    nb = n_bins + 2  # the cubic kernel reaches one bin past either end
    fa = jnp.round(_scale_to_bins(a, *a_range, n_bins)).astype(jnp.int32) + 1
    bins, wb = _cubic_weights(_scale_to_bins(b, *b_range, n_bins))
    bins = jnp.clip(bins + 1, 0, nb - 1)
    if weights is not None:
        wb = wb * weights[:, None]
    ids = fa[:, None] * nb + bins
    joint = jax.ops.segment_sum(wb.reshape(-1), ids.reshape(-1), num_segments=nb * nb).reshape(nb, nb)
    joint = joint / jnp.sum(joint)
    pa, pb = joint.sum(1), joint.sum(0)
    eps = jnp.finfo(joint.dtype).tiny

    def h(p):
        return -jnp.sum(jnp.where(p > 0, p * jnp.log(jnp.maximum(p, eps)), 0.0))

    return (h(pa) + h(pb)) / h(joint)


def ncc(a, b, weights=None):
    """Normalised (Pearson) cross correlation of paired intensities (optionally weighted), in [-1, 1]."""
    w = jnp.ones_like(a) if weights is None else weights
    sw = jnp.sum(w)
    a = a - jnp.sum(w * a) / sw
    b = b - jnp.sum(w * b) / sw
    return jnp.sum(w * a * b) / jnp.sqrt(jnp.sum(w * a * a) * jnp.sum(w * b * b) + jnp.finfo(a.dtype).tiny)


def downsample(data: np.ndarray, affine: np.ndarray, factors) -> tuple[np.ndarray, np.ndarray]:
    """Block-average a volume by integer factors per axis (edge-replicated up to a multiple).

    Arguments:
        data: (x, y, z) image.
        affine: (4, 4) voxel -> world mm.
        factors: 3 integers >= 1.
    Returns:
        (coarse data, coarse affine); coarse voxel i covers fine voxels f*i .. f*i + f - 1, so its
        centre is the fine continuous index f*i + (f - 1)/2.
    """
    f = np.asarray(factors, dtype=int)
    data = np.asarray(data)
    if np.all(f == 1):
        return data, np.asarray(affine, dtype=np.float64)
    pad = [(0, (-n) % k) for n, k in zip(data.shape, f)]
    d = np.pad(data, pad, mode="edge")
    s = [n // k for n, k in zip(d.shape, f)]
    d = d.reshape(s[0], f[0], s[1], f[1], s[2], f[2]).mean(axis=(1, 3, 5))
    scale = np.eye(4)
    scale[:3, :3] = np.diag(f)
    scale[:3, 3] = (f - 1) / 2.0
    return d.astype(data.dtype), np.asarray(affine, dtype=np.float64) @ scale


def _level_factors(affine: np.ndarray, resolution_mm: float) -> np.ndarray:
    vox = voxel_sizes(affine)
    return np.maximum(1, np.round(resolution_mm / vox)).astype(int)


def _grid_points(shape, affine, dtype):
    """World coordinates (x, y, z, 3) of every voxel centre."""
    idx = jnp.stack(jnp.meshgrid(*[jnp.arange(n, dtype=dtype) for n in shape], indexing="ij"), axis=-1)
    a = jnp.asarray(affine, dtype=dtype)
    return idx @ a[:3, :3].T + a[:3, 3]


def _world_to_index(q, affine):
    inv = jnp.linalg.inv(jnp.asarray(affine, dtype=q.dtype))
    return q @ inv[:3, :3].T + inv[:3, 3]


def _sample(image, idx, cval=None):
    """Trilinear interpolation of `image` at voxel indices idx (..., 3); edge values outside."""
    coords = [idx[..., k] for k in range(3)]
    if cval is None:
        return map_coordinates(image, coords, order=1, mode="nearest")
    return map_coordinates(image, coords, order=1, mode="constant", cval=cval)


def _robust_range(x: np.ndarray) -> tuple[float, float]:
    lo, hi = np.percentile(np.asarray(x), [0.5, 99.5])
    if hi <= lo:
        lo, hi = float(np.min(x)), float(np.max(x))
    if hi <= lo:
        hi = lo + 1.0
    return float(lo), float(hi)


def centre_of_mass(data: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Intensity centre of mass in world mm, weighting voxels by (I - p1) clipped to [0, p99 - p1].

    The clipped weight makes air (MRI ~0, CT -1000 HU) weightless and keeps bright bone from
    dominating, so the result is the centre of the head in both modalities.
    """
    d = np.asarray(data, dtype=np.float64)
    p1, p99 = np.percentile(d, [1, 99])
    w = np.clip(d - p1, 0.0, max(p99 - p1, 1e-12))
    if w.sum() <= 0:
        w = np.ones_like(d)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in d.shape], indexing="ij"), -1).reshape(-1, 3)
    c = (w.reshape(-1, 1) * idx).sum(0) / w.sum()
    return np.asarray(affine)[:3, :3] @ c + np.asarray(affine)[:3, 3]


def _rms_radius(data: np.ndarray, affine: np.ndarray, centre: np.ndarray) -> float:
    d = np.asarray(data, dtype=np.float64)
    p1, p99 = np.percentile(d, [1, 99])
    w = np.clip(d - p1, 0.0, max(p99 - p1, 1e-12)).ravel()
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in d.shape], indexing="ij"), -1).reshape(-1, 3)
    p = idx @ np.asarray(affine)[:3, :3].T + np.asarray(affine)[:3, 3] - centre
    r2 = (w * (p**2).sum(1)).sum() / max(w.sum(), 1e-12)
    return float(np.sqrt(max(r2, 1.0)))


# ----------------------------------------------------------------------------------------------
# affine registration
# ----------------------------------------------------------------------------------------------


def _affine_from_params(theta, c_f, c_m, scale):
    lin = jnp.eye(3, dtype=theta.dtype) + theta[:9].reshape(3, 3)
    t = theta[9:] * scale
    m = jnp.eye(4, dtype=theta.dtype)
    m = m.at[:3, :3].set(lin)
    m = m.at[:3, 3].set(c_m + t - lin @ c_f)
    return m


def _similarity(kind, f_vals, m_vals, f_range, m_range, n_bins, weights):
    if kind == "nmi":
        return nmi(f_vals, m_vals, f_range, m_range, n_bins, weights)
    return ncc(f_vals, m_vals, weights)


class _LevelData(eqx.Module):
    points: jax.Array  # (N, 3) fixed world mm of the sampled voxels
    f_vals: jax.Array  # (N,)
    weights: jax.Array  # (N,) 1, or 0 for padding
    moving: jax.Array  # (X, Y, Z) moving image at this level
    moving_affine: jax.Array
    f_range: jax.Array
    m_range: jax.Array


def _affine_cost(theta, args):
    data, c_f, c_m, scale, kind, n_bins = args
    m = _affine_from_params(theta, c_f, c_m, scale)
    q = data.points @ m[:3, :3].T + m[:3, 3]
    m_vals = _sample(data.moving, _world_to_index(q, data.moving_affine))
    return -_similarity(kind, data.f_vals, m_vals, data.f_range, data.m_range, n_bins, data.weights)


@eqx.filter_jit
def _solve_affine(theta0, data, c_f, c_m, scale, kind, n_bins, rtol, atol, max_steps):
    solver = optx.BFGS(rtol=rtol, atol=atol)
    sol = optx.minimise(
        _affine_cost, solver, theta0, args=(data, c_f, c_m, scale, kind, n_bins),
        max_steps=max_steps, throw=False,
    )
    return sol.value, sol.stats["num_steps"], _affine_cost(sol.value, (data, c_f, c_m, scale, kind, n_bins))


def _bucket(n: int, q: int) -> int:
    """n rounded up to a multiple of q (array sizes in buckets let jit reuse compiled code)."""
    return int(-(-n // q) * q)


def _pad_edge(data: np.ndarray, multiple: int) -> np.ndarray:
    """Edge-replicate at the high end of each axis up to a multiple: with mode="nearest" sampling
    this leaves every sampled value unchanged (indices keep their meaning), only the shape buckets."""
    return np.pad(data, [(0, _bucket(n, multiple) - n) for n in data.shape], mode="edge")


def _pad_zero(data: np.ndarray, multiple: int) -> np.ndarray:
    return np.pad(data, [(0, _bucket(n, multiple) - n) for n in data.shape])


def _sample_points(shape, max_samples: int, seed: int = 0):
    """Voxel indices (N, 3) to evaluate the similarity on, and their weights (N,).

    All voxels if there are at most `max_samples` (padded with zero-weight copies up to the next
    power of two, so that similar images share compiled code); otherwise exactly `max_samples`
    voxels drawn at random without replacement (fixed seed: deterministic), as Mattes et al. (2003)
    sample their NMI.
    """
    n = int(np.prod(shape))
    if n > max_samples:
        flat = np.sort(np.random.default_rng(seed).choice(n, size=max_samples, replace=False))
        weights = np.ones(max_samples)
    else:
        m = min(max_samples, 1 << max(int(np.ceil(np.log2(n))), 10))
        flat = np.concatenate([np.arange(n), np.zeros(m - n, dtype=int)])
        weights = np.concatenate([np.ones(n), np.zeros(m - n)])
    return np.stack(np.unravel_index(flat, shape), -1), weights


def _level(fixed: Volume, moving: Volume, resolution_mm: float, max_samples: int, dtype):
    fd, fa = downsample(fixed.data, fixed.affine, _level_factors(fixed.affine, resolution_mm))
    md, ma = downsample(moving.data, moving.affine, _level_factors(moving.affine, resolution_mm))
    idx, weights = _sample_points(fd.shape, max_samples)
    pts = idx @ fa[:3, :3].T + fa[:3, 3]
    f_vals = fd[idx[:, 0], idx[:, 1], idx[:, 2]]
    return _LevelData(
        points=jnp.asarray(pts, dtype=dtype),
        f_vals=jnp.asarray(f_vals, dtype=dtype),
        weights=jnp.asarray(weights, dtype=dtype),
        moving=jnp.asarray(_pad_edge(md, 8), dtype=dtype),
        moving_affine=jnp.asarray(ma, dtype=dtype),
        f_range=jnp.asarray(_robust_range(fd), dtype=dtype),
        m_range=jnp.asarray(_robust_range(md), dtype=dtype),
    ), (fd, fa, md, ma)


def _check_pair(fixed, moving):
    for name, v in (("fixed", fixed), ("moving", moving)):
        if not isinstance(v, Volume):
            raise ValueError(f"`{name}` must be a jaxhead Volume, got {type(v).__name__}.")
        if np.ptp(v.data) == 0:
            raise ValueError(
                f"`{name}` is constant (all voxels = {float(v.data.flat[0])}); registration needs "
                "image contrast. Pass the scan, not an empty volume."
            )


def affine_register(
    fixed: Volume, moving: Volume, cfg: RegisterConfig = RegisterConfig(), *, init: np.ndarray | None = None,
    dtype=None,
) -> AffineTransform:
    """Affine (12 dof) registration of `moving` onto `fixed`, coarse to fine.

    Arguments:
        fixed: the reference image (the subject).
        moving: the image to align (the atlas template).
        cfg: RegisterConfig (similarity, pyramid levels, iterations).
        init: optional (4, 4) fixed mm -> moving mm starting matrix; default aligns the intensity
            centres of mass.
        dtype: computation dtype (default: float64 if x64 is enabled, else float32).
    Returns:
        AffineTransform (fixed world mm -> moving world mm).
    """
    _check_pair(fixed, moving)
    dtype = dtype or jnp.result_type(float)
    c_f = centre_of_mass(fixed.data, fixed.affine)
    c_m = centre_of_mass(moving.data, moving.affine)
    scale = _rms_radius(fixed.data, fixed.affine, c_f)
    if init is None:
        theta = np.zeros(12)
    else:
        init = np.asarray(init, dtype=np.float64)
        if init.shape != (4, 4):
            raise ValueError(f"`init` must be a (4, 4) matrix, got shape {init.shape}.")
        lin = init[:3, :3]
        t = init[:3, 3] + lin @ c_f - c_m
        theta = np.concatenate([(lin - np.eye(3)).ravel(), t / scale])
    theta = jnp.asarray(theta, dtype=dtype)
    c_f_j, c_m_j = jnp.asarray(c_f, dtype=dtype), jnp.asarray(c_m, dtype=dtype)
    for res in cfg.affine_resolutions_mm:
        t0 = time.perf_counter()
        data, _ = _level(fixed, moving, res, cfg.max_samples, dtype)
        theta, steps, cost = _solve_affine(
            theta, data, c_f_j, c_m_j, jnp.asarray(scale, dtype), cfg.similarity, cfg.n_bins,
            cfg.rtol, cfg.atol, cfg.affine_max_steps,
        )
        log.info("affine level %.1f mm: %d steps, similarity %.5f, %.1f s", res, int(steps), -float(cost),
                 time.perf_counter() - t0)
    return AffineTransform(matrix=_affine_from_params(theta, c_f_j, c_m_j, jnp.asarray(scale, dtype)))


# ----------------------------------------------------------------------------------------------
# B-spline free-form deformation
# ----------------------------------------------------------------------------------------------


def control_grid(fixed_shape, fixed_affine, spacing_mm: float) -> tuple[tuple[int, int, int], np.ndarray]:
    """The control grid of a cubic B-spline FFD covering a fixed image.

    Arguments:
        fixed_shape: (x, y, z) voxels of the fixed image.
        fixed_affine: (4, 4) its voxel -> world mm.
        spacing_mm: control-point spacing in mm.
    Returns:
        (grid shape (na, nb, nc), grid affine control index -> fixed world mm); control point 0 sits
        one spacing before voxel 0 and the last one at least two spacings past the last voxel, so
        every voxel has its full 4x4x4 support.
    """
    vox = voxel_sizes(fixed_affine)
    s = spacing_mm / vox
    # rounded up to a multiple of 4 (extra points past the far end carry no data, only bending
    # energy) so that subjects of similar size share compiled code
    shape = tuple(_bucket(int(np.floor((n - 1) / si)) + 4, 4) for n, si in zip(fixed_shape, s))
    g = np.eye(4)
    g[:3, :3] = np.diag(s)
    g[:3, 3] = -s
    return shape, np.asarray(fixed_affine, dtype=np.float64) @ g


def _axis_bases(grid_affine, grid_shape, target_shape, target_affine, dtype):
    """Per-axis B-spline basis matrices (n_target_i, n_ctrl_i) of a target grid aligned with the control grid."""
    m = np.linalg.inv(np.asarray(grid_affine, dtype=np.float64)) @ np.asarray(target_affine, dtype=np.float64)
    off = m[:3, :3] - np.diag(np.diag(m[:3, :3]))
    if np.abs(off).max() > 1e-6 * np.abs(m[:3, :3]).max():
        raise ValueError(
            "the target grid is rotated relative to the B-spline control grid; resample onto the "
            "fixed image's grid (or a block-averaged level of it)."
        )
    bases = []
    for k in range(3):
        i = np.arange(target_shape[k], dtype=np.float64)
        g = m[k, k] * i + m[k, 3]
        b = cubic_bspline(jnp.asarray(g[:, None] - np.arange(grid_shape[k])[None, :], dtype=dtype))
        bases.append(b)
    return bases


def _displacement(coefficients, bases):
    """u on a grid (3, nx, ny, nz) = sum_abc Bx[i,a] By[j,b] Bz[k,c] phi[:, a, b, c]."""
    bx, by, bz = bases
    u = jnp.einsum("dabc,ia->dibc", coefficients, bx)
    u = jnp.einsum("dibc,jb->dijc", u, by)
    return jnp.einsum("dijc,kc->dijk", u, bz)


def bending_energy(coefficients, spacing_mm):
    """Bending energy of a cubic B-spline displacement, averaged over interior control points.

    At a knot the cubic B-spline and its derivatives reduce to the 3-tap stencils
    [1, 4, 1]/6, [-1, 0, 1]/(2h) and [1, -2, 1]/h^2 (exact for the spline), so
    E = mean(u_xx^2 + u_yy^2 + u_zz^2 + 2 u_xy^2 + 2 u_xz^2 + 2 u_yz^2) summed over the 3 components
    (Rueckert et al. 1999; evaluated at control points as in reg_f3d, Modat et al. 2010).

    Arguments:
        coefficients: (3, na, nb, nc) control-point displacements in mm.
        spacing_mm: (3,) control spacing per axis in mm.
    Returns:
        scalar in mm^-2 (mm^2 / mm^4).
    """
    h = [float(v) for v in np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (3,))]

    def stencil(order, hk):
        if order == 0:
            return np.array([1.0, 4.0, 1.0]) / 6.0
        if order == 1:
            return np.array([-1.0, 0.0, 1.0]) / (2.0 * hk)
        return np.array([1.0, -2.0, 1.0]) / hk**2

    def apply(c, orders):
        out = c
        for ax, o in enumerate(orders):
            k = jnp.asarray(stencil(o, h[ax]), dtype=c.dtype)
            n = out.shape[ax + 1]
            sl = [slice(None)] * 4
            parts = []
            for j in range(3):
                sl[ax + 1] = slice(j, n - 2 + j)
                parts.append(k[j] * out[tuple(sl)])
            out = parts[0] + parts[1] + parts[2]
        return out

    terms = [
        ((2, 0, 0), 1.0), ((0, 2, 0), 1.0), ((0, 0, 2), 1.0),
        ((1, 1, 0), 2.0), ((1, 0, 1), 2.0), ((0, 1, 1), 2.0),
    ]
    total = 0.0
    for orders, w in terms:
        total = total + w * jnp.sum(apply(coefficients, orders) ** 2, axis=0)
    return jnp.mean(total)


class _FFDData(eqx.Module):
    bases: tuple
    points: jax.Array  # (nx, ny, nz, 3) fixed world mm of the (strided) level grid
    f_vals: jax.Array  # (nx, ny, nz)
    weights: jax.Array  # (nx, ny, nz) 1 inside the image, 0 on the padding
    moving: jax.Array
    moving_affine: jax.Array
    affine: jax.Array
    f_range: jax.Array
    m_range: jax.Array
    spacing: jax.Array


def _ffd_map(coefficients, data):
    u = _displacement(coefficients, data.bases)
    p = data.points + jnp.moveaxis(u, 0, -1)
    q = p @ data.affine[:3, :3].T + data.affine[:3, 3]
    return _world_to_index(q, data.moving_affine)


def _ffd_cost(coefficients, args):
    data, kind, n_bins, lam, spacing = args
    m_vals = _sample(data.moving, _ffd_map(coefficients, data))
    sim = _similarity(kind, data.f_vals.reshape(-1), m_vals.reshape(-1), data.f_range, data.m_range, n_bins,
                      data.weights.reshape(-1))
    return -sim + lam * bending_energy(coefficients, spacing)


def _scaled_cost(coefficients, args):
    scale, cost, dtype, inner = args
    return (scale * cost(coefficients.astype(dtype), inner)).astype(coefficients.dtype)


@eqx.filter_jit
def minimise_coefficients(cost, c0, args, step_mm, rtol, atol, max_steps):
    """Minimise a cost of B-spline coefficients with L-BFGS, its first step moving them by ~`step_mm`.

    Arguments:
        cost: ``cost(coefficients, args) -> scalar`` (a module-level function: it is a static
            argument of the compiled solver).
        c0: (3, na, nb, nc) starting coefficients in mm; their dtype is the cost's.
        args: pytree passed to `cost`.
        step_mm: length of the first quasi-Newton step (the steepest control point's move), mm.
        rtol, atol, max_steps: optimistix L-BFGS settings (Cauchy termination; at most max_steps).
    Returns:
        (coefficients (c0's dtype), steps taken, cost at them).
    """
    # An image similarity changes by ~1e-4 per mm of one control point, so a plain first
    # quasi-Newton step (-gradient, identity Hessian) would move nothing and the solver would stop at
    # once. Scale the cost so that the first step moves the steepest control point by `step_mm`
    # (about a voxel); L-BFGS's curvature pairs take over from there. The optimum is unchanged.
    dtype = c0.dtype
    g0 = jax.grad(cost)(c0, args)
    scale = step_mm / (jnp.max(jnp.abs(g0)) + jnp.finfo(dtype).tiny)
    # optimistix 0.1.0's L-BFGS allocates its history in the default float dtype, so with x64 on it
    # cannot run on float32 parameters: keep the optimiser's parameters in the default dtype and
    # evaluate the cost in the data's dtype.
    wide = jnp.result_type(float)
    solver = optx.LBFGS(rtol=rtol, atol=atol)
    sol = optx.minimise(_scaled_cost, solver, c0.astype(wide), args=(scale.astype(wide), cost, dtype, args),
                        max_steps=max_steps, throw=False)
    value = sol.value.astype(dtype)
    return value, sol.stats["num_steps"], cost(value, args)


def _solve_ffd(c0, data, kind, n_bins, lam, spacing, step_mm, rtol, atol, max_steps):
    return minimise_coefficients(_ffd_cost, c0, (data, kind, n_bins, lam, spacing), step_mm, rtol, atol, max_steps)


def bspline_register(
    fixed: Volume, moving: Volume, init: AffineTransform | BSplineTransform | None = None,
    cfg: RegisterConfig = RegisterConfig(), *, dtype=None,
) -> BSplineTransform:
    """Cubic B-spline free-form registration of `moving` onto `fixed` with bending energy.

    Arguments:
        fixed: the reference image (the subject).
        moving: the image to align (the atlas template).
        init: a starting transform (typically from `affine_register`); identity if None.
        cfg: RegisterConfig (control spacing, bending energy, levels, iterations).
        dtype: computation dtype (default: float64 if x64 is enabled, else float32).
    Returns:
        BSplineTransform whose control grid covers the fixed image.
    """
    _check_pair(fixed, moving)
    dtype = dtype or jnp.result_type(float)
    if isinstance(init, BSplineTransform):
        grid_shape = tuple(init.coefficients.shape[1:])
        grid_affine = np.asarray(init.grid_affine)
        coeffs = jnp.asarray(init.coefficients, dtype=dtype)
        affine = jnp.asarray(init.affine, dtype=dtype)
    else:
        grid_shape, grid_affine = control_grid(fixed.shape, fixed.affine, cfg.control_spacing_mm)
        coeffs = jnp.zeros((3, *grid_shape), dtype=dtype)
        affine = jnp.asarray(np.eye(4) if init is None else init.matrix, dtype=dtype)
    spacing = voxel_sizes(grid_affine)
    for res in cfg.bspline_resolutions_mm:
        t0 = time.perf_counter()
        fd, fa = downsample(fixed.data, fixed.affine, _level_factors(fixed.affine, res))
        md, ma = downsample(moving.data, moving.affine, _level_factors(moving.affine, res))
        stride = max(1, math.ceil((fd.size / cfg.max_samples) ** (1 / 3)))
        sub = fd[::stride, ::stride, ::stride]
        weights = _pad_zero(np.ones_like(sub), 8)
        sub = _pad_edge(sub, 8)
        # the strided (and padded) grid: index i <-> level index stride * i
        sa = fa.copy()
        sa[:3, :3] = fa[:3, :3] * stride
        bases = _axis_bases(grid_affine, grid_shape, sub.shape, sa, dtype)
        data = _FFDData(
            bases=tuple(bases),
            points=_grid_points(sub.shape, sa, dtype),
            f_vals=jnp.asarray(sub, dtype=dtype),
            weights=jnp.asarray(weights, dtype=dtype),
            moving=jnp.asarray(_pad_edge(md, 8), dtype=dtype),
            moving_affine=jnp.asarray(ma, dtype=dtype),
            affine=affine,
            f_range=jnp.asarray(_robust_range(fd), dtype=dtype),
            m_range=jnp.asarray(_robust_range(md), dtype=dtype),
            spacing=jnp.asarray(spacing, dtype=dtype),
        )
        coeffs, steps, cost = _solve_ffd(
            coeffs, data, cfg.similarity, cfg.n_bins, float(cfg.bending_energy), tuple(float(s) for s in spacing),
            float(voxel_sizes(fa).mean()), cfg.rtol, cfg.atol, cfg.bspline_max_steps,
        )
        log.info("B-spline level %.1f mm: %d steps, cost %.5f, %.1f s", res, int(steps), float(cost),
                 time.perf_counter() - t0)
    return BSplineTransform(affine=affine, coefficients=coeffs, grid_affine=jnp.asarray(grid_affine, dtype=dtype))


def register(fixed: Volume, moving: Volume, cfg: RegisterConfig = RegisterConfig(), *, dtype=None) -> Transform:
    """Affine then (if cfg.bspline) B-spline registration of `moving` onto `fixed`.

    Arguments:
        fixed: the subject image.
        moving: the atlas template.
        cfg: RegisterConfig.
        dtype: computation dtype (default: float64 if x64 is enabled, else float32).
    Returns:
        AffineTransform or BSplineTransform (fixed world mm -> moving world mm).
    """
    t = affine_register(fixed, moving, cfg, dtype=dtype)
    if cfg.bspline:
        t = bspline_register(fixed, moving, t, cfg, dtype=dtype)
    return t


# ----------------------------------------------------------------------------------------------
# resampling
# ----------------------------------------------------------------------------------------------


def _transform_parts(transform: Transform, target_shape, target_affine, dtype):
    """Host preparation: (matrix, coefficients or None, per-axis bases or None) as arrays."""
    if isinstance(transform, BSplineTransform):
        bases = tuple(_axis_bases(np.asarray(transform.grid_affine), transform.coefficients.shape[1:],
                                  tuple(target_shape), target_affine, dtype))
        return jnp.asarray(transform.affine, dtype), jnp.asarray(transform.coefficients, dtype), bases
    return jnp.asarray(transform.matrix, dtype), None, None


def _grid_to_moving(shape, target_affine, matrix, coefficients, bases, moving_affine):
    p = _grid_points(shape, target_affine, matrix.dtype)
    if coefficients is not None:
        p = p + jnp.moveaxis(_displacement(coefficients, bases), 0, -1)
    q = p @ matrix[:3, :3].T + matrix[:3, 3]
    return _world_to_index(q, moving_affine)


@functools.partial(jax.jit, static_argnames=("shape",))
def _coordinates_jit(shape, target_affine, matrix, coefficients, bases, moving_affine):
    return _grid_to_moving(shape, target_affine, matrix, coefficients, bases, moving_affine)


@functools.partial(jax.jit, static_argnames=("shape", "use_cval"))
def _resample_jit(data, shape, target_affine, matrix, coefficients, bases, moving_affine, cval, use_cval):
    idx = _grid_to_moving(shape, target_affine, matrix, coefficients, bases, moving_affine)
    sample = (lambda d: _sample(d, idx, cval)) if use_cval else (lambda d: _sample(d, idx))
    return sample(data) if data.ndim == 3 else jax.vmap(sample)(data)


def moving_coordinates(transform: Transform, target_shape, target_affine, moving_affine, dtype=None):
    """Moving-image voxel indices (x, y, z, 3) of every target voxel under `transform`.

    Arguments:
        transform: fixed mm -> moving mm.
        target_shape: (x, y, z) of the output grid (the fixed image's grid for a B-spline transform).
        target_affine: (4, 4) its voxel -> world mm.
        moving_affine: (4, 4) the moving image's voxel -> world mm.
    Returns:
        (x, y, z, 3) continuous voxel indices into the moving image.
    """
    dtype = dtype or jnp.result_type(float)
    matrix, coef, bases = _transform_parts(transform, target_shape, target_affine, dtype)
    return _coordinates_jit(tuple(int(n) for n in target_shape), jnp.asarray(target_affine, dtype), matrix, coef,
                            bases, jnp.asarray(moving_affine, dtype))


def resample(
    data, data_affine, transform: Transform, target_shape, target_affine, *, cval: float | None = None,
    dtype=None,
):
    """Trilinearly resample an image (or a stack of images) through a transform onto a target grid.

    Arguments:
        data: (x, y, z) or (c, x, y, z) moving image(s), e.g. the atlas template or its priors.
        data_affine: (4, 4) the moving image's voxel -> world mm.
        transform: fixed (target) mm -> moving mm.
        target_shape: (X, Y, Z) output grid.
        target_affine: (4, 4) output voxel -> world mm.
        cval: value outside the moving image (None: nearest edge value).
        dtype: computation and output dtype (default: float64 if x64 is enabled, else float32).
    Returns:
        (X, Y, Z) or (c, X, Y, Z) array.
    """
    dtype = dtype or jnp.result_type(float)
    data = jnp.asarray(data, dtype=dtype)
    if data.ndim not in (3, 4):
        raise ValueError(f"`data` must be (x, y, z) or (c, x, y, z), got shape {data.shape}.")
    matrix, coef, bases = _transform_parts(transform, target_shape, target_affine, dtype)
    return _resample_jit(
        data, tuple(int(n) for n in target_shape), jnp.asarray(target_affine, dtype), matrix, coef, bases,
        jnp.asarray(data_affine, dtype), jnp.asarray(0.0 if cval is None else cval, dtype), cval is not None,
    )


def warp_volume(moving: Volume, transform: Transform, fixed: Volume, *, cval: float | None = None) -> Volume:
    """The moving Volume resampled onto the fixed Volume's grid (host convenience)."""
    out = resample(moving.data, moving.affine, transform, fixed.shape, fixed.affine, cval=cval)
    return Volume(np.asarray(out, dtype=np.float64), fixed.affine)
