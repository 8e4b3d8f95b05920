"""Registration: similarity measures, B-spline algebra, resampling, and recovery of known transforms."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from jaxhead.segmentation.register import (
    AffineTransform,
    BSplineTransform,
    RegisterConfig,
    affine_register,
    bending_energy,
    bspline_register,
    control_grid,
    cubic_bspline,
    downsample,
    moving_coordinates,
    ncc,
    nmi,
    resample,
)
from jaxhead.volume import Volume, default_affine


def blob_image(shape=(32, 32, 32), voxel=3.0):
    """An asymmetric smooth test object: a head-sized ellipsoid with two off-centre inclusions."""
    aff = default_affine(voxel, shape)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    p = idx @ aff[:3, :3].T + aff[:3, 3]
    img = 1.0 * (np.sqrt(((p / [40, 35, 30]) ** 2).sum(-1)) < 1)
    img += 0.8 * (np.sqrt((((p - [10, 5, 0]) / [15, 10, 12]) ** 2).sum(-1)) < 1)
    img += 0.5 * (np.sqrt((((p - [-15, -10, 8]) / [8, 12, 6]) ** 2).sum(-1)) < 1)
    return Volume(ndimage.gaussian_filter(img, 0.7), aff)


def test_cubic_bspline_partition_of_unity_and_reproduction():
    t = np.linspace(0, 1, 11)
    k = np.arange(-3, 5)
    w = np.asarray(cubic_bspline(jnp.asarray(t[:, None] - k[None, :])))
    np.testing.assert_allclose(w, _beta3(t[:, None] - k[None, :]), atol=1e-14)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-12)
    # cubic B-splines reproduce linear functions with coefficients c_k = k (exact in exact arithmetic)
    np.testing.assert_allclose(w @ k, t, atol=1e-12)


def test_ncc_matches_numpy_and_is_affine_invariant():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=500), rng.normal(size=500)
    np.testing.assert_allclose(ncc(jnp.asarray(a), jnp.asarray(b)), np.corrcoef(a, b)[0, 1], rtol=1e-10)
    np.testing.assert_allclose(ncc(jnp.asarray(a), jnp.asarray(3 * a + 2)), 1.0, rtol=1e-12)
    # zero weights drop samples exactly
    w = np.r_[np.ones(300), np.zeros(200)]
    np.testing.assert_allclose(ncc(jnp.asarray(a), jnp.asarray(b), jnp.asarray(w)),
                               np.corrcoef(a[:300], b[:300])[0, 1], rtol=1e-10)


def _hard_nmi(a, b, bins):
    h, _, _ = np.histogram2d(a, b, bins=bins)
    p = h / h.sum()
    pa, pb = p.sum(1), p.sum(0)

    def ent(q):
        q = q[q > 0]
        return -(q * np.log(q)).sum()

    return (ent(pa) + ent(pb)) / ent(p)


def test_nmi_properties():
    nmi_j = jax.jit(nmi, static_argnames=("n_bins",))
    rng = np.random.default_rng(1)
    a = rng.normal(size=20000)
    rng_a = (a.min(), a.max())
    # a one-to-one relation is high (2 for hard bins; the cubic window spreads the moving side, so
    # ~1.5 at 32 bins), independence is ~1
    same = float(nmi_j(jnp.asarray(a), jnp.asarray(a), rng_a, rng_a, n_bins=32))
    indep = float(nmi_j(jnp.asarray(a), jnp.asarray(rng.normal(size=a.size)), rng_a, rng_a, n_bins=32))
    assert same > 1.4 and indep < 1.02
    # a monotone non-linear intensity map keeps NMI high (the multi-modal property), unlike NCC
    b = np.tanh(a)
    assert float(nmi_j(jnp.asarray(a), jnp.asarray(b), rng_a, (b.min(), b.max()), n_bins=32)) > 1.2
    # Parzen NMI of a smooth joint density approaches the hard-histogram estimate (kernel bias:
    # the cubic window widens the moving marginal by ~1/3 bin^2 in variance, so ~5 % here)
    c = a + 0.5 * rng.normal(size=a.size)
    soft = float(nmi_j(jnp.asarray(a), jnp.asarray(c), rng_a, (c.min(), c.max()), n_bins=32))
    hard = _hard_nmi(a, c, [np.linspace(*rng_a, 33), np.linspace(c.min(), c.max(), 33)])
    assert abs(soft - hard) < 0.05 * hard
    # differentiable in the moving values, and the gradient agrees with finite differences
    f = jax.jit(lambda s: nmi(jnp.asarray(a), jnp.asarray(a) * s + 0.3 * jnp.asarray(c), rng_a, (-6.0, 6.0), 32))
    g = float(jax.jit(jax.grad(f))(1.0))
    h = 1e-5
    fd = (float(f(1.0 + h)) - float(f(1.0 - h))) / (2 * h)
    assert np.isfinite(g) and abs(g - fd) < 1e-4 * max(1.0, abs(fd))


def test_bending_energy_analytic():
    # Cubic B-splines reproduce x^2 with coefficients c_k = (k h)^2 - h^2/3 (the kernel's variance
    # is 1/3), so u = (x^2, 0, 0) has u_xx = 2 and every other second derivative 0: E = 4 exactly.
    h = np.array([5.0, 4.0, 6.0])
    n = (7, 6, 8)
    k = np.arange(n[0])[:, None, None] * np.ones(n)
    c = np.zeros((3, *n))
    c[0] = (k * h[0]) ** 2 - h[0] ** 2 / 3
    np.testing.assert_allclose(bending_energy(jnp.asarray(c), h), 4.0, rtol=1e-12)
    # an affine displacement bends nothing
    g = np.stack(np.meshgrid(*[np.arange(m) * hh for m, hh in zip(n, h)], indexing="ij"))
    aff = np.einsum("ij,j...->i...", np.array([[0.1, 0.2, -0.1], [0.0, 0.3, 0.1], [0.2, 0.0, 0.1]]), g) + 1.0
    assert abs(float(bending_energy(jnp.asarray(aff), h))) < 1e-20
    # a mixed term: u = (x y, 0, 0) has u_xy = 1 -> E = 2 * 1^2
    c2 = np.zeros((3, *n))
    c2[0] = g[0] * g[1]
    np.testing.assert_allclose(bending_energy(jnp.asarray(c2), h), 2.0, rtol=1e-12)


def test_downsample_keeps_world_positions_and_mean():
    v = blob_image((16, 18, 20), 2.0)
    d, a = downsample(v.data, v.affine, (2, 2, 2))
    assert d.shape == (8, 9, 10)
    np.testing.assert_allclose(d.mean(), v.data.mean(), rtol=1e-12)
    # coarse voxel 0 is centred between fine voxels 0 and 1
    np.testing.assert_allclose(a[:3, 3], v.affine[:3, :3] @ [0.5, 0.5, 0.5] + v.affine[:3, 3])


def test_resample_identity_and_translation():
    v = blob_image((20, 20, 20), 3.0)
    ident = AffineTransform(jnp.eye(4))
    np.testing.assert_allclose(resample(v.data, v.affine, ident, v.shape, v.affine), v.data, atol=1e-12)
    # a whole-voxel translation shifts the array (trilinear interpolation is exact at grid points)
    m = np.eye(4)
    m[:3, 3] = [3.0, 0, 0]  # fixed mm -> moving mm: moving sampled one voxel further along x
    out = np.asarray(resample(v.data, v.affine, AffineTransform(jnp.asarray(m)), v.shape, v.affine))
    np.testing.assert_allclose(out[:-1], v.data[1:], atol=1e-12)
    # stacks of images (atlas priors) resample channel by channel
    two = np.asarray(resample(np.stack([v.data, 2 * v.data]), v.affine, ident, v.shape, v.affine))
    np.testing.assert_allclose(two[1], 2 * v.data, atol=1e-12)


def _beta3(t):
    """Cubic B-spline, written independently (Unser 1999, eq. 5) for the naive reference."""
    a = np.abs(t)
    return np.where(a < 1, (4 - 6 * a**2 + 3 * a**3) / 6, np.where(a < 2, (2 - a) ** 3 / 6, 0.0))


def test_bspline_displacement_matches_naive_sum():
    v = blob_image((12, 10, 14), 3.0)
    gs, ga = control_grid(v.shape, v.affine, 9.0)
    rng = np.random.default_rng(2)
    c = rng.normal(0, 2.0, (3, *gs))
    t = BSplineTransform(jnp.eye(4), jnp.asarray(c), jnp.asarray(ga))
    idx = np.asarray(moving_coordinates(t, v.shape, v.affine, v.affine))
    # naive: u(p) = sum_abc beta(g_x - a) beta(g_y - b) beta(g_z - c) phi_abc at a few voxels
    ginv = np.linalg.inv(ga)
    for vox in [(0, 0, 0), (5, 3, 7), (11, 9, 13)]:
        p = v.affine[:3, :3] @ vox + v.affine[:3, 3]
        g = ginv[:3, :3] @ p + ginv[:3, 3]
        wts = [_beta3(g[k] - np.arange(gs[k])) for k in range(3)]
        u = np.einsum("dabc,a,b,c->d", c, *wts)
        want = np.linalg.inv(v.affine)[:3, :3] @ (p + u) + np.linalg.inv(v.affine)[:3, 3]
        np.testing.assert_allclose(idx[vox], want, atol=1e-10)
    # every voxel has its full 4x4x4 support: the weights sum to one across the image
    for k in range(3):
        gk = ginv[k, k] * (v.affine[k, k] * np.arange(v.shape[k]) + v.affine[k, 3]) + ginv[k, 3]
        np.testing.assert_allclose(_beta3(gk[:, None] - np.arange(gs[k])[None]).sum(1), 1.0, atol=1e-12)


def _truth_affine():
    ang = np.deg2rad(7.0)
    rot = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rot @ np.diag([1.05, 0.97, 1.0])
    m[:3, 3] = [4.0, -3.0, 2.0]
    return m


def test_affine_registration_recovers_known_affine():
    fixed = blob_image()
    truth = _truth_affine()
    # moving(truth p) = fixed(p): build moving by pulling fixed back through truth^-1
    mov = resample(fixed.data, fixed.affine, AffineTransform(jnp.asarray(np.linalg.inv(truth))),
                   fixed.shape, fixed.affine)
    moving = Volume(np.asarray(mov), fixed.affine)
    t = affine_register(fixed, moving, RegisterConfig(affine_resolutions_mm=(3.0,), bspline=False))
    m = np.asarray(t.matrix)
    # Compare where the two transforms send the object's voxels. The start (centres of mass
    # aligned) is off by up to ~8 mm; the images are smooth 3 mm-voxel objects, interpolated
    # trilinearly, so ~0.1 voxel (0.3 mm) is the attainable accuracy.
    idx = np.argwhere(fixed.data > 0.2)
    p = idx @ fixed.affine[:3, :3].T + fixed.affine[:3, 3]
    err = np.linalg.norm(p @ (m[:3, :3] - truth[:3, :3]).T + (m[:3, 3] - truth[:3, 3]), axis=1)
    assert err.max() < 0.5, err.max()


def test_bspline_registration_recovers_smooth_deformation():
    base = blob_image()
    gs, ga = control_grid(base.shape, base.affine, 15.0)
    rng = np.random.default_rng(0)
    truth = BSplineTransform(jnp.eye(4), jnp.asarray(rng.normal(0, 5.0, (3, *gs))), jnp.asarray(ga))
    # fixed = moving o truth, so registering moving onto fixed should find `truth`
    moving = base
    fixed = Volume(np.asarray(resample(base.data, base.affine, truth, base.shape, base.affine)), base.affine)
    cfg = RegisterConfig(similarity="ncc", bspline_resolutions_mm=(3.0,), control_spacing_mm=15.0,
                         bending_energy=1e-3, bspline_max_steps=80)
    # float32 (segment's default precision) under x64: the optimiser state stays float64 (see
    # register._solve_ffd), the cost is evaluated in float32
    est = bspline_register(fixed, moving, None, cfg, dtype=jnp.float32)
    assert est.coefficients.dtype == jnp.float32
    want = np.asarray(moving_coordinates(truth, base.shape, base.affine, base.affine))
    got = np.asarray(moving_coordinates(est, base.shape, base.affine, base.affine))
    ident = np.asarray(moving_coordinates(AffineTransform(jnp.eye(4)), base.shape, base.affine, base.affine))
    # Judge the displacement where the image has structure (an edge within ~2 voxels); in flat
    # regions any displacement is equally good.
    grad = np.linalg.norm(np.stack(np.gradient(fixed.data)), axis=0)
    mask = ndimage.binary_dilation(grad > 0.05, iterations=1) & (fixed.data > 0.05)
    before = np.linalg.norm(want - ident, axis=-1)[mask].mean()
    after = np.linalg.norm(want - got, axis=-1)[mask].mean()
    assert before > 0.7  # voxels: the deformation is not trivial
    assert after < 0.25 * before, (before, after)
