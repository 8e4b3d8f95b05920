"""Ordered class means (CT: CSF below brain): closed form against SciPy, and the capture it prevents."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

from jaxhead.segmentation import SegmentConfig
from jaxhead.segmentation.em import EMOptions, _m_step, fit_mixture, ordered_means
from jaxhead.segmentation.segment import CSF_BRAIN_MARGIN_HU, DIPLOE_ABOVE_CSF_LOG
from jaxhead.tissue import Tissue

jax.config.update("jax_enable_x64", True)


def _sums(seed=0, n=400, j=4):
    rng = np.random.default_rng(seed)
    y = rng.normal(0, 3, n)
    r = rng.dirichlet(np.ones(j), n)  # responsibilities (n, J)
    var = rng.uniform(0.5, 4.0, j)
    return y, r, var


def _penalised_objective(mu, y, r, var):
    """The means' part of the expected complete-data negative log-likelihood at fixed variances."""
    return float(((r * (y[:, None] - mu) ** 2).sum(0) / (2 * var)).sum())


def _active_set_minimum(y, r, var, order):
    """The constrained minimum by enumeration: every subset of the order constraints held as equalities
    (a KKT linear system of the quadratic), the feasible solution of least objective. Exact and
    independent of `ordered_means` and of any iterative optimiser."""
    import itertools

    n = r.sum(0)
    w = n / var  # the objective is sum_j w_j (mu_j - m_j)^2 / 2 + const
    m = (r * y[:, None]).sum(0) / n
    j = len(m)
    best, best_f = None, np.inf
    for k in range(len(order) + 1):
        for active in itertools.combinations(order, k):
            a = np.zeros((k, j))
            b = np.zeros(k)
            for i, (lo, hi, d) in enumerate(active):  # mu_hi - mu_lo = d
                a[i, hi], a[i, lo], b[i] = 1.0, -1.0, d
            kkt = np.block([[np.diag(w), a.T], [a, np.zeros((k, k))]])
            sol = np.linalg.lstsq(kkt, np.concatenate([w * m, b]), rcond=None)[0]
            mu = sol[:j]
            if all(mu[hi] - d - mu[lo] >= -1e-12 for lo, hi, d in order):
                f = _penalised_objective(mu, y, r, var)
                if f < best_f:
                    best, best_f = mu, f
    return best


@pytest.mark.parametrize("order", [((1, 0, 0.5),), ((1, 0, 2.0), (3, 2, 0.0)), ((0, 3, 1.0),)])
def test_ordered_means_closed_form_is_the_constrained_minimum(order):
    y, r, var = _sums()
    y = y + np.array([0.0, 1.5, -0.5, 0.7])[np.argmax(r, 1)]  # unequal weighted means
    n = r.sum(0)
    m = (r * y[:, None]).sum(0) / n
    got = np.asarray(ordered_means(jnp.asarray(m), jnp.asarray(n / var), order))
    np.testing.assert_allclose(got, _active_set_minimum(y, r, var, order), rtol=1e-10, atol=1e-12)
    # SciPy's SLSQP as a second, iterative reference (its line search can stop a hair from the
    # optimum with "Positive directional derivative", depending on the BLAS threads: no success check)
    cons = [{"type": "ineq", "fun": lambda v, lo=lo, hi=hi, d=d: v[hi] - d - v[lo]} for lo, hi, d in order]
    ref = minimize(_penalised_objective, m, args=(y, r, var), method="SLSQP", constraints=cons,
                   options={"ftol": 1e-14, "maxiter": 500})
    np.testing.assert_allclose(got, ref.x, atol=1e-5)
    for lo, hi, d in order:
        assert got[lo] <= got[hi] - d + 1e-12
    # an order that already holds changes nothing
    holds = tuple((lo, hi, 0.0) if m[hi] >= m[lo] else (hi, lo, 0.0) for lo, hi, _ in order)
    np.testing.assert_allclose(np.asarray(ordered_means(jnp.asarray(m), jnp.asarray(n / var), holds)), m,
                               rtol=1e-12)


def test_m_step_variance_is_about_the_constrained_mean():
    y, r, var_old = _sums(1, j=3)
    y = y + np.array([5.0, 0.0, 1.0])[np.argmax(r, 1)]  # Gaussian 0 above 1: the order (0 below 1) binds
    opts = EMOptions(component_class=(0, 1, 1), n_classes=2, mean_order=((0, 1, 0.25),))
    scale = 2.0  # margins are in data units; the M-step works in standardised ones (margin / scale)
    rl = [jnp.asarray(r[:, k].reshape(20, 20, 1)) for k in range(3)]
    mu, var, _ = _m_step(jnp.asarray(y.reshape(20, 20, 1)), rl, jnp.zeros(3), opts, 1e-12, jnp.asarray(var_old),
                         scale)
    n = r.sum(0)
    m = (r * y[:, None]).sum(0) / n
    ref = np.asarray(ordered_means(jnp.asarray(m), jnp.asarray(n / var_old), ((0, 1, 0.125),)))
    np.testing.assert_allclose(mu, ref, rtol=1e-10)
    assert mu[0] < m[0] and abs(mu[1] - mu[0] - 0.125) < 1e-10
    np.testing.assert_allclose(var, (r * (y[:, None] - ref) ** 2).sum(0) / n, rtol=1e-10)


def test_order_prevents_csf_capturing_grey_matter():
    # CT-like brain (class 0: white 21 HU, grey 44 HU, two Gaussians) and CSF (class 1: 14 HU). The
    # registered atlas puts CSF (prior 0.6) on a band of grey matter wider than the true CSF: maximum
    # likelihood moves the CSF Gaussian onto grey matter (44 HU) and labels no true CSF as CSF (the
    # capture on the ANTs head, experiments/results/segmentation_weight_prior.md). With CSF kept 5 HU
    # below the brain's lower Gaussian (the literature's water/white-matter gap) it stays on CSF.
    rng = np.random.default_rng(0)
    shape = (40, 12, 12)
    x = np.broadcast_to((np.arange(shape[0])[:, None, None] + 0.5) / shape[0], shape)
    region = np.where(x < 0.3, 0, np.where(x < 0.45, 1, np.where(x < 0.85, 2, 3)))  # white, grey, grey+CSF prior, CSF
    y = np.array([21.0, 44.0, 44.0, 14.0])[region] + rng.normal(0, 5, shape)
    pc = np.where(region <= 1, 0.1, 0.6)
    prior = jnp.asarray(np.stack([1 - pc, pc]))
    truth = region == 3

    def fit(order, offset=0.0):
        opts = EMOptions(component_class=(0, 0, 1), n_classes=2, max_iter=300, tol=1e-9, mean_order=order)
        res = fit_mixture(jnp.asarray(y + offset), prior, opts)
        lab = np.asarray(res.posteriors).argmax(0) == 1
        return np.asarray(res.params.means), 2 * (lab & truth).sum() / (lab.sum() + truth.sum())

    (mu_ml, dice_ml), (mu_o, dice_o) = fit(()), fit(((2, 0, 5.0),))
    assert mu_ml[2] > 40 and dice_ml < 0.1, (mu_ml, dice_ml)  # captured without the order
    assert mu_o[2] <= min(mu_o[:2]) - 5.0 + 1e-6 and mu_o[2] < 20, mu_o
    assert dice_o > 0.6, dice_o
    # a scanner's HU offset moves every mean by the offset and changes no label (the order is a contrast)
    mu_s, dice_s = fit(((2, 0, 5.0),), offset=300.0)
    np.testing.assert_allclose(mu_s, mu_o + 300.0, atol=1e-6)
    assert dice_s == dice_o


def test_segment_config_csf_below_brain():
    opts = SegmentConfig(modality="ct").em_options(1.0)
    cc = opts.component_class
    lo, hi, margin = opts.mean_order[0]
    assert (cc[lo], cc[hi], margin) == (int(Tissue.CSF), int(Tissue.BRAIN), CSF_BRAIN_MARGIN_HU)
    assert lo == cc.index(int(Tissue.CSF)) and hi == cc.index(int(Tissue.BRAIN))  # the first of each class
    assert SegmentConfig(modality="ct", csf_below_brain=False, csf_mix_below_bone=False).em_options(1.0).mean_order == ()
    # MRI: none of CT's orders (its own default, `csf_mix_below_brain`, is tested below)
    assert SegmentConfig(modality="mri", csf_mix_below_brain=False).em_options(1.0).mean_order == ()
    pv = SegmentConfig(modality="ct", partial_volume=True).em_options(1.0)
    assert all(pv.is_free(j) for j in pv.mean_order[0][:2])
    with pytest.raises(ValueError, match="csf_below_brain"):
        SegmentConfig(modality="mri", csf_below_brain=True)
    with pytest.raises(ValueError, match="csf_below_brain"):
        SegmentConfig(modality="ct", csf_below_brain="yes")


def test_segment_config_csf_mix_below_bone():
    """CT by default: the CSF class's second Gaussian (its bone mixture) at or below the skull's first."""
    opts = SegmentConfig(modality="ct").em_options(1.0)
    cc = opts.component_class
    lo, hi, margin = opts.mean_order[1]
    assert (cc[lo], cc[hi], margin) == (int(Tissue.CSF), int(Tissue.SKULL), 0.0)
    assert lo == cc.index(int(Tissue.CSF)) + 1 and hi == cc.index(int(Tissue.SKULL))
    off = SegmentConfig(modality="ct", csf_mix_below_bone=False).em_options(1.0).mean_order
    assert off == opts.mean_order[:1]
    # one CSF Gaussian (partial-volume model, or `gaussians`): the default has nothing to order; asking is an error
    assert len(SegmentConfig(modality="ct", partial_volume=True).em_options(1.0).mean_order) == 1
    with pytest.raises(ValueError, match="csf_mix_below_bone"):
        SegmentConfig(modality="ct", gaussians={"csf": 1}, csf_mix_below_bone=True)
    with pytest.raises(ValueError, match="csf_mix_below_bone"):
        SegmentConfig(modality="mri", csf_mix_below_bone=True)


def test_segment_config_csf_mix_below_brain():
    """MRI by default: the CSF class's second Gaussian (its partial volume) at or below the brain's first."""
    opts = SegmentConfig(modality="mri").em_options(1.0)
    assert opts.mean_order == SegmentConfig(modality="mri", csf_mix_below_brain=True).em_options(1.0).mean_order
    cc = opts.component_class
    (lo, hi, margin), = opts.mean_order
    assert (cc[lo], cc[hi], margin) == (int(Tissue.CSF), int(Tissue.BRAIN), 0.0)
    assert lo == cc.index(int(Tissue.CSF)) + 1 and hi == cc.index(int(Tissue.BRAIN))
    assert SegmentConfig(modality="mri", csf_mix_below_brain=False).em_options(1.0).mean_order == ()
    # beside the diploe's order (disjoint Gaussians: the CSF's first there, its second here)
    both = SegmentConfig(modality="mri", csf_mix_below_brain=True, diploe_above_csf=True).em_options(1.0).mean_order
    assert set(both) == {opts.mean_order[0], (cc.index(int(Tissue.CSF)), cc.index(int(Tissue.SKULL)) + 1,
                                              DIPLOE_ABOVE_CSF_LOG)}
    # one CSF Gaussian: the default has nothing to order; asking is an error
    assert SegmentConfig(modality="mri", gaussians={"csf": 1}).em_options(1.0).mean_order == ()
    with pytest.raises(ValueError, match="csf_mix_below_brain"):
        SegmentConfig(modality="mri", gaussians={"csf": 1}, csf_mix_below_brain=True)
    with pytest.raises(ValueError, match="csf_mix_below_brain"):
        SegmentConfig(modality="ct", csf_mix_below_brain=True)


@pytest.mark.parametrize(
    "order, match",
    [
        (((0, 5, 1.0),), "not in 0"),
        (((0, 0, 1.0),), "two different"),
        (((0, 1, -1.0),), "margin >= 0"),
        (((0, 1, 1.0), (1, 2, 0.0)), "more than one pair"),
        (((0, 1),), "tuples"),
        (((0, 1, "5"),), "a number"),
    ],
)
def test_mean_order_validation(order, match):
    with pytest.raises(ValueError, match=match):
        EMOptions(component_class=(0, 1, 1), n_classes=2, mean_order=order)
    with pytest.raises(ValueError, match="partial-volume"):
        EMOptions(component_class=(0, 0, 1), n_classes=2, pv_of=(-1, 1, -1), mean_order=((1, 2, 0.0),))
