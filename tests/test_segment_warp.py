"""Warp refinement on the EM's likelihood (warp_refine.py): gradient, recovery of a known shift, monotone
objective, and the `refine_warp` option of `segment_reported`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from jaxhead.segmentation import Atlas, RegisterConfig, SegmentConfig, segment_reported
from jaxhead.segmentation.em import EMOptions, MixtureParams
from jaxhead.segmentation.register import BSplineTransform, _displacement, control_grid, minimise_coefficients
from jaxhead.segmentation.warp_refine import (
    _negative_objective, change_penalty, refine_warp, warp_objective, warp_priors, warp_problem,
)
from jaxhead.volume import Volume, default_affine

RADII_MM = (18.0, 22.0, 27.0, 32.0)  # brain, CSF, skull, scalp outer radii: nested spheres
MEANS = np.array([0.0, 1.0, 0.4, 0.15, 0.8])  # background, brain, CSF, skull, scalp
SD = 0.06


def nested_labels(shape, affine, centre_mm=(0.0, 0.0, 0.0)):
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    r = np.linalg.norm(idx @ affine[:3, :3].T + affine[:3, 3] - np.asarray(centre_mm), axis=-1)
    lab = np.zeros(shape, np.int64)
    for k, rk in zip((4, 3, 2, 1), RADII_MM[::-1]):
        lab[r < rk] = k
    return lab


def blurred_priors(labels, sigma_vox):
    p = np.stack([ndimage.gaussian_filter((labels == k).astype(float), sigma_vox) for k in range(5)])
    return p / p.sum(0)


def shifted_case(shift_mm, voxel=3.0, n=28, seed=0, dtype=jnp.float64):
    """A scan of the nested spheres moved by `shift_mm` along x, the atlas priors of the unmoved ones
    (3 mm blur), an identity registration (so the priors sit `shift_mm` off) and the true mixture."""
    aff = default_affine(voxel, (n, n, n))
    truth = nested_labels((n, n, n), aff, (shift_mm, 0.0, 0.0))
    rng = np.random.default_rng(seed)
    y = MEANS[truth] + SD * rng.normal(size=truth.shape)
    priors = blurred_priors(nested_labels((n, n, n), aff), 1.0)
    grid_shape, grid_affine = control_grid((n, n, n), aff, 12.0)
    tr = BSplineTransform(affine=jnp.eye(4, dtype=dtype), coefficients=jnp.zeros((3, *grid_shape), dtype),
                          grid_affine=jnp.asarray(grid_affine, dtype))
    params = MixtureParams(means=jnp.asarray(MEANS, dtype), variances=jnp.full(5, SD**2, dtype),
                           weights=jnp.ones(5, dtype), bias=jnp.zeros(0, dtype))
    return aff, truth, jnp.asarray(y, dtype), priors, tr, params


def problem_for(y, priors, aff, tr, params, opts, posteriors=None, bending=0.05, **kw):
    q = jnp.full((5, *y.shape), 0.2, y.dtype) if posteriors is None else posteriors
    return warp_problem(y, None, params, q, opts, priors, aff, tr, aff, bending, **kw)


def dice(a, b):
    return 2 * (a & b).sum() / (a.sum() + b.sum())


@pytest.mark.parametrize("change_mm", [float("inf"), 4.0])
def test_gradient_matches_central_differences(change_mm):
    # every term on: relaxation, Potts factor, bending energy, the change penalty (s = 4 mm, anchored
    # at coefficients other than the start); float64 (conftest enables x64)
    aff, truth, y, priors, tr, params = shifted_case(3.0, voxel=4.0, n=16)
    opts = EMOptions(component_class=(0, 1, 2, 3, 4), n_classes=5, beta=0.4, relax=0.5, relax_sigma_vox=1.0)
    q = jnp.asarray(blurred_priors(truth, 0.7))
    rng = np.random.default_rng(1)
    c = jnp.asarray(rng.normal(scale=1.5, size=tr.coefficients.shape))  # away from the symmetric start
    anchor = jnp.asarray(rng.normal(scale=1.0, size=tr.coefficients.shape))
    prob = problem_for(y, priors, aff, tr, params, opts, q, anchor=anchor, change_scale_mm=change_mm)
    assert (float(change_penalty(c, prob)) > 1e-3) == np.isfinite(change_mm)
    f = jax.jit(warp_objective)
    g = np.asarray(jax.grad(warp_objective)(c, prob))
    # central differences along 6 coordinates and 2 random directions. Trilinear sampling is piecewise
    # linear in the coordinates: a step that carries a sample point across a voxel face adds an O(h)
    # error (measured here: 1e-3 relative at h = 1e-3 mm, 1e-4 at 1e-4); at h = 1e-5 mm no face is
    # crossed and the difference is truncation O(h^2) plus rounding eps |f| / h ~ 1e-11 (measured 1e-8 relative)
    h = 1e-5
    dirs = []
    for i in rng.choice(c.size, size=6, replace=False):
        e = np.zeros(c.size)
        e[i] = 1.0
        dirs.append(e.reshape(c.shape))
    dirs += [rng.normal(size=c.shape) for _ in range(2)]
    for d in dirs:
        fd = (float(f(c + h * d, prob)) - float(f(c - h * d, prob))) / (2 * h)
        an = float(np.sum(g * d))
        assert abs(fd - an) <= 1e-6 * abs(an) + 1e-9, (fd, an)
    assert np.abs(g).max() > 1e-6  # the check is not vacuous


def test_recovers_a_shifted_prior():
    shift = 5.0
    aff, truth, y, priors, tr, params = shifted_case(shift)
    opts = EMOptions(component_class=(0, 1, 2, 3, 4), n_classes=5)  # no MRF, no relaxation
    prob = problem_for(y, priors, aff, tr, params, opts)
    new, info = refine_warp(tr, prob, RegisterConfig(), step_mm=3.0)
    assert info["accepted"] and info["gain"] > 0 and info["objective_after"] > info["objective_before"]
    # scan mm p -> atlas mm p + u(p): the right warp is u = (-shift, 0, 0). Only its normal component at
    # the layers is identifiable (inside the uniform brain and in the air the priors are flat, and the
    # spheres allow any tangential slide), so the shift is judged by the mean x displacement over the
    # layers (CSF, skull, scalp: measured -4.8 mm) and by the warped priors' overlap with the truth.
    u = np.asarray(_displacement(new.coefficients, prob.bases))
    layers = truth >= 2
    assert abs(u[0][layers].mean() + shift) < 0.1 * shift, u[0][layers].mean()
    before = np.asarray(jnp.stack(warp_priors(tr.coefficients, prob))).argmax(0)
    after = np.asarray(jnp.stack(warp_priors(new.coefficients, prob))).argmax(0)
    for k in (2, 3, 4):  # the thin layers, which a 5 mm shift moves half off (measured 0.36 -> 0.76,
        # 0.53 -> 0.91, 0.46 -> 0.82)
        d0, d1 = dice(before == k, truth == k), dice(after == k, truth == k)
        assert d1 > d0 + 0.25 and d1 > 0.7, (k, d0, d1)
    assert info["max_change_mm"] > 0.7 * shift


def test_objective_never_decreases_along_the_solve():
    aff, truth, y, priors, tr, params = shifted_case(5.0, voxel=4.0, n=20)
    opts = EMOptions(component_class=(0, 1, 2, 3, 4), n_classes=5, beta=0.4, relax=0.5)
    prob = problem_for(y, priors, aff, tr, params, opts, jnp.asarray(blurred_priors(truth, 0.7)))
    f = jax.jit(warp_objective)
    values = [float(f(tr.coefficients, prob))]
    # the solver is deterministic, so the run with k steps is the first k steps of a longer one
    for k in (1, 4, 16):  # (each k compiles the solver once)
        c, _, _ = minimise_coefficients(_negative_objective, tr.coefficients, prob, 3.0, 1e-4, 1e-4, k)
        values.append(float(f(c, prob)))
    assert all(b >= a - 1e-12 for a, b in zip(values, values[1:])), values
    assert values[-1] > values[0] + 1e-3, values


def test_change_penalty_of_a_uniform_shift():
    # cubic B-splines sum to one, so moving every control point by d moves every sample point by d:
    # the penalty is |d|^2 / (2 s^2) exactly, from any anchor
    aff, _, y, priors, tr, params = shifted_case(0.0, voxel=4.0, n=12)
    opts = EMOptions(component_class=(0, 1, 2, 3, 4), n_classes=5)
    anchor = jnp.asarray(np.random.default_rng(2).normal(size=tr.coefficients.shape))
    d = np.array([3.0, -1.0, 2.0])
    for s in (2.0, 5.0):
        prob = problem_for(y, priors, aff, tr, params, opts, anchor=anchor, change_scale_mm=s)
        got = float(change_penalty(anchor + jnp.asarray(d)[:, None, None, None], prob))
        assert got == pytest.approx(0.5 * d @ d / s**2, rel=1e-10)
    prob = problem_for(y, priors, aff, tr, params, opts, anchor=anchor)  # default: no penalty
    assert float(change_penalty(anchor + 5.0, prob)) == 0.0


def test_change_penalty_bounds_the_drift_where_the_likelihood_is_flat():
    # the scan's spheres sit 5 mm off the atlas's; in the air beyond the scalp (> 50 mm from the centre,
    # >= 18 mm outside it) prior and likelihood are the same for every warp, so only the regulariser
    # decides the displacement there. The bending energy is zero for a shift, and without the penalty
    # the air follows the layers (measured: rms 3.9 mm, max 16.8 mm over the far region); with
    # s = 4 mm it stays put (rms 0.04 mm, max 0.3 mm) while the layers still move towards the truth
    # (mean x change over CSF/skull/scalp: -4.1 mm without, -0.95 mm with).
    n = 36
    aff, truth, y, priors, tr, params = shifted_case(5.0, voxel=3.0, n=n)
    opts = EMOptions(component_class=(0, 1, 2, 3, 4), n_classes=5)
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1)
    far = np.linalg.norm(idx @ aff[:3, :3].T + aff[:3, 3], axis=-1) > 50.0
    layers = truth >= 2
    out = {}
    for s in (float("inf"), 4.0):
        prob = problem_for(y, priors, aff, tr, params, opts, change_scale_mm=s)
        new, info = refine_warp(tr, prob, RegisterConfig(), step_mm=3.0)
        assert info["accepted"]
        u = np.asarray(_displacement(new.coefficients, prob.bases))
        mag = np.linalg.norm(u, axis=0)
        out[s] = (np.sqrt(np.mean(mag[far] ** 2)), mag[far].max(), u[0][layers].mean(), info)
    assert out[float("inf")][0] > 2.0 and out[float("inf")][1] > 8.0, out  # the drift
    assert out[4.0][0] < 0.2 and out[4.0][1] < 1.0, out  # bounded
    assert out[4.0][2] < -0.5, out  # the layers still move the right way
    assert out[4.0][3]["penalty"] > 0 and out[4.0][3]["rms_from_anchor_mm"] > 0


def test_refine_warp_option_validated():
    for bad in (True, -1, 6, 1.5, "2"):
        with pytest.raises(ValueError, match="refine_warp"):
            SegmentConfig(refine_warp=bad)
    with pytest.raises(ValueError, match="register.bspline"):
        SegmentConfig(refine_warp=1, register=RegisterConfig(bspline=False))
    assert SegmentConfig().refine_rounds() == 0 and SegmentConfig(refine_warp=2).refine_rounds() == 2
    for bad in (0, -2.0, float("nan"), True, "4", [4.0]):
        with pytest.raises(ValueError, match="warp_change_mm"):
            SegmentConfig(warp_change_mm=bad)
    assert SegmentConfig(warp_change_mm=2).warp_change_scale() == 2.0
    assert SegmentConfig(warp_change_mm=float("inf")).warp_change_scale() == float("inf")
    aff, _, y, priors, tr, params = shifted_case(0.0, voxel=4.0, n=12)
    opts = EMOptions(component_class=(0, 1, 2, 3, 4), n_classes=5)
    with pytest.raises(ValueError, match="BSplineTransform"):
        from jaxhead.segmentation.register import AffineTransform
        warp_problem(y, None, params, jnp.full((5, *y.shape), 0.2), opts, priors, aff,
                     AffineTransform(matrix=jnp.eye(4)), aff, 0.05)
    for bad in (0.0, -1.0, float("nan"), None, True):
        with pytest.raises(ValueError, match="change_scale_mm"):
            problem_for(y, priors, aff, tr, params, opts, change_scale_mm=bad)
    with pytest.raises(ValueError, match="anchor"):
        problem_for(y, priors, aff, tr, params, opts, anchor=jnp.zeros((3, 2, 2, 2)))


def test_segment_reported_reports_the_refinement():
    # an atlas of the nested spheres (template = the class means), a scan of them moved by 4 mm:
    # segment with refine_warp=2 runs, reports its rounds and does not lower the objective
    voxel, n = 4.0, 24
    aff = default_affine(voxel, (n, n, n))
    lab_atlas = nested_labels((n, n, n), aff)
    atlas = Atlas(MEANS[lab_atlas] + 0.01, blurred_priors(lab_atlas, 0.75), aff, "mri")
    truth = nested_labels((n, n, n), aff, (4.0, 0.0, 0.0))
    rng = np.random.default_rng(3)
    vol = Volume(MEANS[truth] + 0.01 + 0.03 * np.abs(rng.normal(size=truth.shape)), aff)
    reg = RegisterConfig(affine_resolutions_mm=(8.0,), bspline_resolutions_mm=(8.0,), max_samples=32768,
                         affine_max_steps=20, bspline_max_steps=10)
    cfg = SegmentConfig(modality="mri", register=reg, refine_warp=2, check_registration=False, bias_degree=0,
                        em_sample_mm=voxel, precision="float64")
    labels, seg = segment_reported(vol, atlas, cfg)
    w = seg.registration["warp_refinement"]
    assert 1 <= w["rounds"] <= 2 and w["refits"] <= w["rounds"] and w["gain"] >= 0
    assert all(after >= before for before, after in w["objective"])
    assert len(w["max_change_mm"]) == w["rounds"] and labels.shape == vol.shape
    assert w["change_scale_mm"] == 4.0 and len(w["rms_from_registration_mm"]) == w["rounds"]
    without = segment_reported(vol, atlas, SegmentConfig(**{**cfg.__dict__, "refine_warp": 0}))[1]
    assert "warp_refinement" not in without.registration
