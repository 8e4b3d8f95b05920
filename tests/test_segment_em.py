"""EM with priors, MRF and bias field: against a NumPy EM, known parameters, and invariants."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from jaxhead.segmentation.em import (
    EMOptions,
    MixtureParams,
    bias_field,
    bias_terms,
    fit_mixture,
    gaussian_smooth,
    grid_coordinates,
    infer_posteriors,
)
from jaxhead.segmentation.mrf import mean_field, neighbour_sum, potts_energy

SHAPE = (24, 20, 22)


def two_class_data(seed=0, shape=SHAPE):
    rng = np.random.default_rng(seed)
    lab = (rng.random(shape) < 0.3).astype(int)
    mu, sd = np.array([1.0, 3.0]), np.array([0.5, 0.7])
    return lab, rng.normal(mu[lab], sd[lab]), mu, sd


START = dict(means=np.array([0.5, 3.5]), variances=np.array([1.0, 1.0]), weights=np.array([0.5, 0.5]))


def numpy_em(y, n_iter, var_floor=1e-4):
    """Plain two-Gaussian EM in NumPy from START, in the same standardised units as fit_mixture
    (its variance floor applies there): an independent implementation to compare against."""
    c, s = y.mean(), y.std() + np.finfo(float).eps
    x = ((y - c) / s).ravel()
    mu = (START["means"] - c) / s
    var = START["variances"] / s**2
    w = START["weights"].copy()
    for _ in range(n_iter):
        dens = w / np.sqrt(2 * np.pi * var) * np.exp(-0.5 * (x[:, None] - mu) ** 2 / var)
        r = dens / dens.sum(1, keepdims=True)
        n = r.sum(0)
        mu = (r * x[:, None]).sum(0) / n
        var = np.maximum((r * (x[:, None] - mu) ** 2).sum(0) / n, var_floor)
        w = n / n.sum()
    return mu * s + c, var * s**2, w


def test_em_matches_numpy_reference_and_known_parameters():
    lab, y, mu, sd = two_class_data()
    # one class with two Gaussians and a flat prior is a plain GMM
    opts = EMOptions(component_class=(0, 0), n_classes=1, max_iter=30, min_iter=30)
    init = MixtureParams(*(jnp.asarray(START[k]) for k in ("means", "variances", "weights")), jnp.zeros(0))
    res = fit_mixture(jnp.asarray(y), jnp.ones((1, *SHAPE)), opts, init)
    ref_mu, ref_var, ref_w = numpy_em(y, 30)
    assert int(res.n_iter) == 30
    # same algorithm, float64, different summation order: agreement to ~1e-10 relative
    np.testing.assert_allclose(res.params.means, ref_mu, rtol=1e-9)
    np.testing.assert_allclose(res.params.variances, ref_var, rtol=1e-9)
    np.testing.assert_allclose(res.params.weights, ref_w, rtol=1e-9)
    # and the truth within sampling error (n ~ 3000 and 7500 samples: se(mean) ~ 0.01; the
    # overlap of the two Gaussians biases the variances by a few %)
    np.testing.assert_allclose(res.params.means, mu, atol=0.05)
    np.testing.assert_allclose(np.sqrt(res.params.variances), sd, rtol=0.06)
    np.testing.assert_allclose(res.params.weights, [0.7, 0.3], atol=0.02)


def test_em_with_spatial_priors_recovers_parameters_and_labels():
    # Labels drawn from smooth spatial priors (the model's own generative process), then data.
    rng = np.random.default_rng(1)
    p1 = ndimage.gaussian_filter(rng.random(SHAPE), 3.0)
    p1 = 0.05 + 0.9 * (p1 - p1.min()) / np.ptp(p1)
    lab = (rng.random(SHAPE) < p1).astype(int)
    mu, sd = np.array([1.0, 3.0]), np.array([0.5, 0.7])
    y = rng.normal(mu[lab], sd[lab])
    prior = np.stack([1 - p1, p1])
    opts = EMOptions(component_class=(0, 1), n_classes=2, tol=1e-10, max_iter=300, prior_floor=0.0)
    res = fit_mixture(jnp.asarray(y), jnp.asarray(prior), opts)
    assert bool(res.converged)
    # maximum likelihood under the true model: within sampling error (se(mean) ~ 0.01)
    np.testing.assert_allclose(res.params.means, mu, atol=0.04)
    np.testing.assert_allclose(np.sqrt(res.params.variances), sd, rtol=0.04)
    post = np.asarray(res.posteriors)
    np.testing.assert_allclose(post.sum(0), 1.0, atol=1e-12)
    # the posterior is the Bayes classifier: it beats the prior alone and the likelihood alone
    acc = (post.argmax(0) == lab).mean()
    assert acc > ((p1 > 0.5) == lab).mean() and acc > 0.9


def test_bias_field_recovered_on_synthetic_gradient():
    lab, y, mu, sd = two_class_data(2)
    x, _, z = grid_coordinates(SHAPE, np.float64)
    xx, zz = np.asarray(x)[:, None, None], np.asarray(z)[None, None, :]
    true_b = 0.8 * xx - 0.3 * xx * zz + 0 * y  # log-domain gradient, in the span of degree 2
    opts = EMOptions(component_class=(0, 0), n_classes=1, tol=1e-10, max_iter=500, bias_degree=2,
                     bias_classes=(0,))
    res = fit_mixture(jnp.asarray(y + true_b), jnp.ones((1, *SHAPE)), opts)
    # The field is defined up to a constant (absorbed by the means).
    err = np.asarray(res.bias_field) - true_b
    err -= err.mean()
    # 10^4 voxels, 9 coefficients, noise sd ~0.6: each coefficient has se ~0.6 / sqrt(N / 3) ~ 0.01,
    # so the field's rms error is ~0.02 and its maximum (at the corners, where the basis peaks) ~0.1
    # against a 1.1 peak-to-peak field
    assert np.sqrt((err**2).mean()) < 0.03 and np.abs(err).max() < 0.12, np.abs(err).max()
    np.testing.assert_allclose(res.params.means, mu + (true_b.mean()), atol=0.05)
    # with the field removed, the spread is the noise's again (the 1.1 peak-to-peak gradient would
    # otherwise add ~0.3 to each sd)
    np.testing.assert_allclose(np.sqrt(res.params.variances), sd, rtol=0.06)


def test_bias_basis_is_legendre_without_constant():
    from numpy.polynomial import legendre

    assert len(bias_terms(2)) == 9 and len(bias_terms(4)) == 34
    assert (bias_terms(4).sum(1) >= 1).all() and (bias_terms(4).sum(1) <= 4).all()
    coords = grid_coordinates((7, 5, 6), np.float64)
    terms = bias_terms(3)
    rng = np.random.default_rng(0)
    c = rng.normal(size=len(terms))
    got = np.asarray(jax.jit(bias_field, static_argnums=2)(jnp.asarray(c), coords, 3))
    x, y, z = (np.asarray(a) for a in coords)
    want = np.zeros((7, 5, 6))
    for ck, (a, b, d) in zip(c, terms):
        ea, eb, ed = (np.eye(4)[k] for k in (a, b, d))
        want += ck * np.einsum("i,j,k->ijk", legendre.legval(x, ea), legendre.legval(y, eb), legendre.legval(z, ed))
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_neighbour_sum_and_smoothing_match_scipy():
    rng = np.random.default_rng(3)
    p = rng.random((2, 7, 8, 9))
    k = np.zeros((3, 3, 3))
    k[0, 1, 1] = k[2, 1, 1] = k[1, 0, 1] = k[1, 2, 1] = k[1, 1, 0] = k[1, 1, 2] = 1
    want = np.stack([ndimage.convolve(q, k, mode="constant") for q in p])
    np.testing.assert_allclose(jax.jit(neighbour_sum)(jnp.asarray(p)), want, atol=1e-12)
    got = np.asarray(jax.jit(gaussian_smooth, static_argnums=1)(jnp.asarray(p), 1.2))
    ref = np.stack([ndimage.gaussian_filter(q, 1.2, mode="constant", truncate=3 / 1.2 * 1.2) for q in p])
    # scipy truncates at ceil(truncate * sigma) = 4 voxels (we use ceil(3 sigma) = 4 too) and
    # normalises the same way
    np.testing.assert_allclose(got, ref, atol=1e-12)


def test_mrf_removes_isolated_mislabels():
    shape = (16, 16, 16)
    truth = np.zeros(shape, int)
    truth[8:] = 1
    rng = np.random.default_rng(4)
    flips = np.zeros(shape, bool)
    idx = rng.choice(np.prod(shape), 60, replace=False)
    flips.flat[idx] = True
    noisy = np.where(flips, 1 - truth, truth)
    # moderate evidence (log-likelihood ratio 1) for the noisy labels
    ll = np.stack([np.where(noisy == 0, 0.0, -1.0), np.where(noisy == 1, 0.0, -1.0)])
    mf = jax.jit(mean_field, static_argnums=3)
    no_mrf = np.asarray(mf(jnp.asarray(ll), 0.0, 0.0, 5)).argmax(0)
    assert (no_mrf != truth).sum() == flips.sum()
    q = np.asarray(mf(jnp.asarray(ll), 0.0, 1.0, 5))
    lab = q.argmax(0)
    # An isolated flip has >= 5 of 6 neighbours voting against it (beta * ~5 > 1): all corrected,
    # and the flat boundary (5 of 6 neighbours agree on each side) is kept.
    assert (lab != truth).sum() == 0
    assert int(potts_energy(jnp.asarray(lab))) < int(potts_energy(jnp.asarray(noisy)))
    # the same inside the EM: two overlapping Gaussians (means 2 sd apart: ~16 % of the voxels
    # are closer to the other mean), so the likelihood alone mislabels many isolated voxels
    y = np.where(truth == 1, 2.0, 0.0) + 1.0 * rng.standard_normal(shape)
    prior = np.full((2, *shape), 0.5)
    # start from the right means (a flat prior cannot break the symmetry between the classes)
    init = MixtureParams(jnp.asarray([0.0, 2.0]), jnp.asarray([1.0, 1.0]), jnp.ones(2), jnp.zeros(0))
    opts = EMOptions(component_class=(0, 1), n_classes=2, beta=1.0, max_iter=20, min_iter=20)
    res = fit_mixture(jnp.asarray(y), jnp.asarray(prior), opts, init)
    with_mrf = int((np.asarray(res.posteriors).argmax(0) != truth).sum())
    # the likelihood alone (the true Gaussians, equal priors): nearest mean, threshold at 1
    without = int(((y > 1.0) != truth).sum())
    assert without > 400 and with_mrf < without / 10, (without, with_mrf)


def test_jit_equals_eager_and_float32_path():
    lab, y, _, _ = two_class_data(5, (5, 4, 6))
    prior = np.stack([np.where(lab == 0, 0.7, 0.3), np.where(lab == 1, 0.7, 0.3)])
    # two iterations; tol is huge so the prior relaxation switches on after the first
    opts = EMOptions(component_class=(0, 1), n_classes=2, beta=0.3, relax=0.4, relax_sigma_vox=0.5,
                     max_iter=2, min_iter=2, tol=1e9)
    a = fit_mixture(jnp.asarray(y), jnp.asarray(prior), opts)
    with jax.disable_jit():
        b = fit_mixture(jnp.asarray(y), jnp.asarray(prior), opts)
    np.testing.assert_allclose(a.posteriors, b.posteriors, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a.params.means, b.params.means, rtol=1e-10)
    # float32 in -> float32 out, equal to float64 within float32 rounding of 4 iterations
    c = fit_mixture(jnp.asarray(y, jnp.float32), jnp.asarray(prior, jnp.float32), opts)
    assert c.posteriors.dtype == jnp.float32 and c.params.means.dtype == jnp.float32
    np.testing.assert_allclose(c.params.means, a.params.means, rtol=1e-4, atol=1e-4)  # ~100 eps32
    # infer_posteriors at the fitted parameters reproduces a normalised posterior map
    p = infer_posteriors(jnp.asarray(y), jnp.asarray(prior), a.params, opts, 2)
    np.testing.assert_allclose(np.asarray(p).sum(0), 1.0, atol=1e-12)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(component_class=(0, 2), n_classes=2), "must name classes"),
        (dict(component_class=(0, 0), n_classes=2), "no Gaussian"),
        (dict(component_class=(1, 0), n_classes=2), "sorted"),
        (dict(component_class=(0, 1), n_classes=2, relax=1.0), "relax"),
        (dict(component_class=(0, 1), n_classes=2, beta=-1.0), "beta"),
        (dict(component_class=(0, 1), n_classes=2, pv_of=(-1,)), "one entry per Gaussian"),
        (dict(component_class=(0, 1), n_classes=2, pv_of=(-1, 1)), "another class"),
        (dict(component_class=(0, 1, 1), n_classes=2, pv_of=(-1, 0, 0)), "only partial-volume"),
        (dict(component_class=(0, 1), n_classes=2, weight_prior=-0.1), "weight_prior"),
        (dict(component_class=(0, 1), n_classes=2, variance_prior=-0.1), "variance_prior"),
    ],
)
def test_em_options_validation(kw, match):
    with pytest.raises(ValueError, match=match):
        EMOptions(**kw)


def test_tied_partial_volume_gaussians_match_the_uniform_mixing_line():
    # Standardised units with c = 1, s = 2; pure Gaussians A (class 0) at 0 and B (class 1) at 10.
    from jaxhead.segmentation.em import _tie_partial_volume

    opts = EMOptions(component_class=(0, 0, 1, 1), n_classes=2, pv_of=(-1, 1, -1, 0))
    mu = jnp.array([0.0, 99.0, 10.0, 99.0])
    var = jnp.array([0.3, 9.0, 2.0, 9.0])
    m, v = _tie_partial_volume(mu, var, opts, 1.0, 2.0)
    # A's half of the line, f_B uniform on (0, 1/2): from 0 to 5, mean 2.5, variance 5^2 / 12 + noise
    np.testing.assert_allclose([m[1], v[1]], [2.5, 25 / 12 + 0.3], rtol=1e-12)
    np.testing.assert_allclose([m[3], v[3]], [7.5, 25 / 12 + 0.3], rtol=1e-12)
    np.testing.assert_allclose([m[0], m[2], v[0], v[2]], [0.0, 10.0, 0.3, 2.0])  # pure ones untouched
    # log intensities: mixing on exp(c + s y); the halfway point is log of the mean intensity
    opts_log = EMOptions(component_class=(0, 0, 1, 1), n_classes=2, pv_of=(-1, 1, -1, 0), pv_log=True)
    var_log = jnp.array([0.01, 1.0, 0.02, 1.0])
    m, v = _tie_partial_volume(jnp.array([-1.0, 0.0, 0.5, 0.0]), var_log, opts_log, 1.0, 2.0)
    half = (np.log(0.5 * (np.exp(1 - 2.0) + np.exp(1 + 1.0))) - 1.0) / 2.0
    np.testing.assert_allclose([m[1], m[3]], [(half - 1.0) / 2, (half + 0.5) / 2], rtol=1e-12)
    np.testing.assert_allclose(v[3], (0.5 - half) ** 2 / 12 + 0.01, rtol=1e-12)
    # a mixing line within the noise (|0 - 10| < 2 sd) is not resolvable: the tied Gaussians are
    # copies of their own class's pure one; at 3 sd they are half-way (linear fade from 2 to 4 sd)
    m, v = _tie_partial_volume(mu, jnp.array([30.0, 1.0, 40.0, 1.0]), opts, 1.0, 2.0)
    np.testing.assert_allclose([m[1], v[1], m[3], v[3]], [0.0, 30.0, 10.0, 40.0], rtol=1e-12)
    noise = (10 / 3) ** 2
    m, v = _tie_partial_volume(mu, jnp.array([noise, 1.0, 2 * noise, 1.0]), opts, 1.0, 2.0)
    np.testing.assert_allclose([m[1], v[1]], [0.5 * 2.5, noise + 0.5 * 25 / 12], rtol=1e-12)


def test_partial_volume_voxels_go_to_the_majority_tissue():
    # A narrow tissue (air-like: 0 +- 0.5) borders a broad one (bone-like: 100 +- 15 of texture);
    # 30 % of the voxels straddle the boundary with a uniform fraction f of the broad tissue and
    # intensity f * 100 + (1 - f) * 0 + noise; their label (the tissue at the centre) is f > 1/2.
    rng = np.random.default_rng(5)
    n = int(np.prod(SHAPE))
    kind = rng.choice(3, size=n, p=[0.35, 0.35, 0.3])
    f = np.where(kind == 0, 0.0, np.where(kind == 1, 1.0, rng.random(n)))
    y = f * rng.normal(100.0, 15.0, n) + rng.normal(0.0, 0.5, n)
    truth = (f > 0.5).astype(int)
    # an atlas-like prior: 0.8 for the right tissue away from the boundary, 0.5 on it
    p1 = np.where(kind == 0, 0.2, np.where(kind == 1, 0.8, 0.5)).reshape(SHAPE)
    prior = jnp.asarray(np.stack([1 - p1, p1]))
    pv = kind == 2

    def pv_accuracy(opts):
        res = fit_mixture(jnp.asarray(y.reshape(SHAPE)), prior, opts)
        lab = np.asarray(res.posteriors).argmax(0).ravel()
        return (lab[pv] == truth[pv]).mean(), (lab[~pv] == truth[~pv]).mean()

    tied, tied_pure = pv_accuracy(EMOptions(component_class=(0, 0, 1, 1), n_classes=2, pv_of=(-1, 1, -1, 0)))
    # a free Gaussian for the mixed voxels owned by the broad class: the narrow/broad threshold sits
    # a few per cent from the narrow tissue, so nearly all mixed voxels go to the broad one
    free, free_pure = pv_accuracy(EMOptions(component_class=(0, 1, 1), n_classes=2))
    # a uniform f split at 1/2 by a Gaussian mixture: the tails of the two half-Gaussians overlap
    # (f near 1/2 is ambiguous under the noise and texture), so ~85-90 % rather than 100 %
    assert tied > 0.85 and tied_pure > 0.99, (tied, tied_pure)
    assert free < 0.7 and tied > free + 0.2, (tied, free)


def test_map_weights_closed_form_and_constrained_maximum():
    # classes 0 (two free Gaussians), 1 (one free, one tied partial-volume), 2 (one free)
    from scipy.optimize import minimize

    from jaxhead.segmentation.em import map_weights

    opts = EMOptions(component_class=(0, 0, 1, 1, 2), n_classes=3, pv_of=(-1, -1, -1, 0, -1), weight_prior=0.25)
    n = np.array([90.0, 2.0, 30.0, 0.5, 7.0])
    w = np.asarray(map_weights(jnp.asarray(n), opts))
    # closed form: pseudo-counts eta * N_k / F_k on the free Gaussians only
    eta = 0.25
    ref = np.array([(90 + eta * 92 / 2) / (1.25 * 92), (2 + eta * 92 / 2) / (1.25 * 92),
                    (30 + eta * 30.5) / (1.25 * 30.5), 0.5 / (1.25 * 30.5), 1.0])
    np.testing.assert_allclose(w, ref, rtol=1e-12)
    np.testing.assert_allclose([w[:2].sum(), w[2:4].sum()], 1.0, rtol=1e-12)
    assert w[1] >= eta / ((1 + eta) * 2) - 1e-15  # the stated lower bound for a free Gaussian
    # independently: the maximiser of sum_j (n_j + a_j) log w_j on each class's simplex
    for g, a in (([0, 1], [eta * 92 / 2] * 2), ([2, 3], [eta * 30.5, 0.0])):
        c = n[g] + np.array(a)
        res = minimize(lambda v: -(c * np.log(v)).sum(), np.full(2, 0.5), method="SLSQP", bounds=[(1e-9, 1)] * 2,
                       constraints={"type": "eq", "fun": lambda v: v.sum() - 1}, options={"ftol": 1e-14})
        np.testing.assert_allclose(w[g], res.x, atol=1e-6)
    # eta = 0 is maximum likelihood, n_j / N_k
    ml = np.asarray(map_weights(jnp.asarray(n), EMOptions(component_class=(0, 0, 1, 1, 2), n_classes=3,
                                                          pv_of=(-1, -1, -1, 0, -1))))
    np.testing.assert_allclose(ml, [90 / 92, 2 / 92, 30 / 30.5, 0.5 / 30.5, 1.0], rtol=1e-12)


def fit_squeezed_tissue(shape=SHAPE, **options):
    """Class B has two tissues: B1 (10 +- 3) only where the atlas is undecided (prior 0.5), and B2
    (100 +- 10) where it is sure; class A (14 +- 6) overlaps B1. The EM's parameters, with `options`
    (EMOptions keywords) added."""
    rng = np.random.default_rng(0)
    x = np.broadcast_to((np.arange(shape[0])[:, None, None] + 0.5) / shape[0], shape)
    region = np.where(x < 0.4, 0, np.where(x < 0.55, 2, 1))  # 0: A, 2: undecided (B1), 1: B2
    y = np.where(region == 0, rng.normal(14, 6, shape),
                 np.where(region == 2, rng.normal(10, 3, shape), rng.normal(100, 10, shape)))
    pb = np.where(region == 0, 0.1, np.where(region == 2, 0.5, 0.9))
    prior = jnp.asarray(np.stack([1 - pb, pb]))
    init = MixtureParams(jnp.array([14.0, 10.0, 100.0]), jnp.array([36.0, 9.0, 100.0]), jnp.array([1.0, 0.25, 0.75]),
                         jnp.zeros(0))
    opts = EMOptions(component_class=(0, 1, 1), n_classes=2, max_iter=500, tol=1e-10, **options)
    return fit_mixture(jnp.asarray(y), prior, opts, init).params


def test_weight_prior_keeps_a_squeezed_tissue_gaussian_from_collapsing():
    # Class B has two tissues: B1 (10 +- 3) only where the atlas is undecided (prior 0.5), and B2
    # (100 +- 10) where it is sure; class A (14 +- 6) overlaps B1. Maximum likelihood empties B1's
    # Gaussian (its share of the undecided voxels shrinks with its weight, which shrinks with its
    # share: w -> 0, its variance to a spike); the Dirichlet prior keeps its weight above
    # eta / ((1 + eta) F) and the Gaussian on B1's intensities.
    ml, mp = fit_squeezed_tissue(), fit_squeezed_tissue(weight_prior=0.1)
    assert float(ml.weights[1]) < 1e-3, ml.weights  # collapsed without the prior
    assert float(mp.weights[1]) >= 0.1 / (1.1 * 2), mp.weights
    assert abs(float(mp.means[1]) - 10.0) < 3.0 and float(mp.variances[1]) > 0.5, (mp.means, mp.variances)


def test_map_variances_closed_form_and_constrained_maximum():
    # classes 0 (two free Gaussians), 1 (one free, one tied partial-volume), 2 (one free)
    from scipy.optimize import minimize_scalar

    from jaxhead.segmentation.em import map_variances

    nu = 0.3
    opts = EMOptions(component_class=(0, 0, 1, 1, 2), n_classes=3, pv_of=(-1, -1, -1, 0, -1), variance_prior=nu)
    n = np.array([90.0, 2.0, 30.0, 0.5, 7.0])
    s = np.array([0.5, 1e-4, 2.0, 0.7, 3.0])  # maximum-likelihood variances (scatter / count)
    v = np.asarray(map_variances(jnp.asarray(n), jnp.asarray(s), opts))
    # independently: maximise the log posterior -(n/2 + alpha + 1) log v - (S/2 + beta) / v of each free
    # Gaussian, with 2 alpha + 2 = nu N_k / F_k and 2 beta = (2 alpha + 2) V_k, V_k the pooled variance
    for j, (tot, f, pooled) in {0: (92, 2, (90 * 0.5 + 2 * 1e-4) / 92), 1: (92, 2, (90 * 0.5 + 2 * 1e-4) / 92),
                               2: (30.5, 1, 2.0), 4: (7, 1, 3.0)}.items():
        a = nu * tot / f
        alpha, beta = a / 2 - 1, a * pooled / 2

        def neg(lv, j=j, alpha=alpha, beta=beta):
            return (n[j] / 2 + alpha + 1) * lv + (n[j] * s[j] / 2 + beta) * np.exp(-lv)

        ref = np.exp(minimize_scalar(neg, bounds=(-15, 5), method="bounded", options={"xatol": 1e-12}).x)
        np.testing.assert_allclose(v[j], ref, rtol=1e-6)
    assert v[3] == s[3]  # the tied partial-volume Gaussian is left to _tie_partial_volume
    assert v[1] > 0.3  # an emptied Gaussian tends to its class's pooled variance (0.49), not its own 1e-4
    # nu = 0 is maximum likelihood
    ml = map_variances(jnp.asarray(n), jnp.asarray(s), EMOptions(component_class=(0, 0, 1, 1, 2), n_classes=3))
    np.testing.assert_array_equal(np.asarray(ml), s)


def test_variance_prior_keeps_an_emptied_gaussian_from_collapsing_to_a_spike():
    # The setting of the weight-prior test above: under maximum likelihood class B's first Gaussian is
    # emptied (weight -> 0) and its variance collapses onto the few voxels it keeps (sd well under the
    # data's 3-10); a density spike that can outbid the class's real Gaussians at one intensity. With
    # the inverse-gamma prior its variance tends to the class's pooled variance instead.
    ml, mp = fit_squeezed_tissue(), fit_squeezed_tissue(variance_prior=0.1)
    assert float(ml.weights[1]) < 1e-3 and float(ml.variances[1]) < 1.0, (ml.weights, ml.variances)  # spike
    assert float(mp.variances[1]) > 0.5 * float(mp.variances[2]), mp.variances  # ~ the class's pooled variance
    # the populated Gaussians keep their own widths
    np.testing.assert_allclose(np.sqrt(np.asarray(mp.variances)[[0, 2]]), np.sqrt(np.asarray(ml.variances)[[0, 2]]),
                               rtol=0.02)


def numpy_infer(y, prior, params, opts, n_sweeps, coords):
    """`infer_posteriors` in NumPy, written from its docstring: atlas prior (floored, normalised), bias-corrected
    data, Gaussians grouped per class, mean-field sweeps with the Potts prior renormalised per sweep, then the
    Cardoso relaxed prior ((1 - a) atlas + a * normalised Gaussian-smoothed posteriors) and as many sweeps again."""
    p = np.maximum(prior, 0) + opts.prior_floor
    atlas = p / p.sum(0)
    b = np.asarray(bias_field(jnp.asarray(params.bias), coords, opts.bias_degree)) if opts.bias_degree else 0.0
    yc = y - b
    mu, var, w = (np.asarray(a, float) for a in (params.means, params.variances, params.weights))
    comp = w[:, None, None, None] * np.exp(-0.5 * (yc[None] - mu[:, None, None, None]) ** 2 / var[:, None, None, None]) \
        / np.sqrt(2 * np.pi * var)[:, None, None, None]
    cc = np.asarray(opts.component_class)
    lik = np.stack([comp[cc == k].sum(0) for k in range(opts.n_classes)])

    def post_of(pr):
        j = pr * lik
        return j / j.sum(0)

    def sweeps(pr, q):
        for _ in range(n_sweeps):
            ns = np.stack([ndimage.correlate(qk, np.array([[[0, 0, 0], [0, 1, 0], [0, 0, 0]], [[0, 1, 0], [1, 0, 1],
                           [0, 1, 0]], [[0, 0, 0], [0, 1, 0], [0, 0, 0]]], float), mode="constant") for qk in q])
            m = pr * np.exp(opts.beta * ns)
            q = post_of(m / m.sum(0))
        return q

    q = sweeps(atlas, post_of(atlas))
    if opts.relax > 0:
        sm = np.asarray(gaussian_smooth(jnp.asarray(q), opts.relax_sigma_vox))
        q = sweeps((1 - opts.relax) * atlas + opts.relax * sm / sm.sum(0), q)
    return q


@pytest.mark.parametrize("beta, relax, n_sweeps", [(0.4, 0.5, 3), (0.4, 0.0, 2), (0.0, 0.5, 2), (0.4, 0.5, 0)])
def test_infer_posteriors_against_numpy(beta, relax, n_sweeps):
    # three classes, the middle one of two Gaussians, a degree-2 bias field: each sweep's likelihood is
    # computed once and the Potts prior's normalisation folded into the posterior's; the result must
    # equal the E-step written out
    rng = np.random.default_rng(3)
    lab = rng.integers(0, 3, SHAPE)
    y = np.array([0.0, 2.0, 4.0])[lab] + rng.normal(0, 0.6, SHAPE)
    prior = rng.random((3,) + SHAPE)
    prior[1, :4] = 0.0  # zero prior: the floor applies
    opts = EMOptions(component_class=(0, 1, 1, 2), n_classes=3, beta=beta, relax=relax, relax_sigma_vox=1.0,
                     bias_degree=2)
    coords = grid_coordinates(SHAPE, jnp.float64)
    params = MixtureParams(means=jnp.array([0.1, 1.8, 2.3, 4.1]), variances=jnp.array([0.4, 0.3, 0.5, 0.3]),
                           weights=jnp.array([1.0, 0.6, 0.4, 1.0]),
                           bias=jnp.asarray(rng.normal(0, 0.1, len(bias_terms(2)))))
    got = np.asarray(infer_posteriors(jnp.asarray(y), jnp.asarray(prior), params, opts, n_sweeps, coords))
    want = numpy_infer(y, prior, params, opts, n_sweeps, coords)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    assert np.abs(got - want).max() < 1e-9 and np.abs(want - numpy_infer(y, prior, params, opts, 0, coords)).max() \
        > (1e-3 if n_sweeps else -1)  # the sweeps move the posteriors: the comparison is not of the no-MRF map
