"""Scalp lies outside the skull (CT): `enclosed` (every grid ray meets a wall) against a per-voxel ray
march, and `scalp_outside_skull` on nested shells with an intracranial pocket labelled scalp, a
walled-off pocket, an opening in the skull and soft tissue that the intensity model calls scalp."""

import itertools

import jax.numpy as jnp
import numpy as np
import pytest

from jaxhead.segmentation.em import MixtureParams
from jaxhead.segmentation.segment import SegmentConfig, enclosed, scalp_outside_skull
from jaxhead.tissue import Tissue

BG, BRAIN, CSF, SKULL, SCALP = (int(t) for t in (Tissue.BACKGROUND, Tissue.BRAIN, Tissue.CSF, Tissue.SKULL, Tissue.SCALP))
#: HU of each class in the toy scans; the mixture below puts one Gaussian of sd 10 HU on each
HU = {BG: -1000.0, BRAIN: 35.0, CSF: 8.0, SKULL: 900.0, SCALP: -90.0}


def _march(wall, escape, start, step):
    """Follow one ray voxel by voxel (the obvious way): does it meet `wall` before `escape` or the edge?"""
    p = np.array(start)
    while all(0 <= c < n for c, n in zip(p, wall.shape)):
        if wall[tuple(p)]:
            return True
        if escape[tuple(p)]:
            return False
        p = p + step
    return False


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_enclosed_against_a_ray_march(seed):
    rng = np.random.default_rng(seed)
    shape = (9, 10, 8)
    r = rng.random(shape)
    wall, escape = r < 0.2, (r >= 0.2) & (r < 0.25)
    border = np.ones(shape, bool)
    border[1:-1, 1:-1, 1:-1] = False
    wall[border] = rng.random(int(border.sum())) < 0.93  # a shell with a few holes the rays escape through
    escape &= ~wall
    got = enclosed(wall, escape)
    steps = [np.array(s) for s in itertools.product((-1, 0, 1), repeat=3) if any(s)]
    want = np.zeros(shape, bool)
    for idx in np.ndindex(shape):
        want[idx] = all(_march(wall, escape, idx, s) for s in steps)
    np.testing.assert_array_equal(got, want)
    assert got.sum() > wall.sum()  # some non-wall voxels are enclosed: the test is not trivial


def test_enclosed_checks_its_masks():
    with pytest.raises(ValueError, match="wall"):
        enclosed(np.zeros((4, 4, 4), bool), np.zeros((4, 4, 5), bool))


def _head(n=36):
    """Nested balls: brain r < 8, CSF to 9.5, skull to 13, scalp to 15, air outside (voxel indices)."""
    i = np.arange(n) - (n - 1) / 2
    r = np.sqrt(i[:, None, None] ** 2 + i[None, :, None] ** 2 + i[None, None, :] ** 2)
    lab = np.full((n, n, n), BG)
    for radius, k in ((15, SCALP), (13, SKULL), (9.5, CSF), (8, BRAIN)):
        lab[r < radius] = k
    return lab, r


def _model():
    """A CT mixture of one Gaussian per class (SegmentConfig(gaussians=1 per class)'s component layout)."""
    cfg = SegmentConfig(modality="ct", gaussians={t: 1 for t in ("background", "brain", "csf", "skull", "scalp")})
    opts = cfg.em_options(1.0)
    means = jnp.array([HU[k] for k in range(5)])
    return MixtureParams(means=means, variances=jnp.full(5, 100.0), weights=jnp.ones(5), bias=jnp.zeros(0)), opts


def _posteriors(lab, pocket=None, brain_share=0.3):
    post = np.full((5, *lab.shape), 0.01, np.float32)
    np.put_along_axis(post, lab[None], 1.0, 0)
    if pocket is not None:  # the atlas said scalp there, brain a close second
        post[:, pocket] = 0.01
        post[SCALP, pocket], post[BRAIN, pocket] = 1.0, brain_share
    return post / post.sum(0)


def test_intracranial_scalp_goes_to_its_next_class():
    lab, r = _head()
    pocket = (lab == BRAIN) & (np.arange(lab.shape[2])[None, None, :] < 15)  # the lower brain
    seg = np.where(pocket, SCALP, lab)  # what the EM gave where the atlas has its face
    hu = np.vectorize(HU.get)(lab).astype(np.float64)  # the scan: it is brain there
    params, opts = _model()
    out, info = scalp_outside_skull(_posteriors(seg, pocket), hu, params, opts)
    np.testing.assert_array_equal(out.argmax(0), lab)
    assert info == {"relabelled": int(pocket.sum()), "brain": int(pocket.sum())}
    np.testing.assert_allclose(out.sum(0), 1.0, rtol=1e-6)


def test_what_the_rule_does_not_describe_keeps_its_label():
    lab, r = _head()
    i = np.arange(lab.shape[0])
    params, opts = _model()
    c = (len(i) - 1) / 2
    # 1. brain-valued scalp inside the skull but walled off from the brain and CSF by bone (a sinus)
    sinus = (np.abs(r - 11.25) < 0.5) & (i[:, None, None] > c + 5) & (np.abs(i[None, :, None] - c) < 2) \
        & (np.abs(i[None, None, :] - c) < 2)
    # 2. brain-valued scalp reaching the air through an opening in the skull (a foramen)
    hole = (r >= 9.5) & (r < 13) & (i[:, None, None] < c - 5) & (np.abs(i[None, :, None] - c) < 2.5) \
        & (np.abs(i[None, None, :] - c) < 2.5)
    seg = lab.copy()
    seg[sinus | hole] = SCALP
    hu = np.vectorize(HU.get)(seg).astype(np.float64)
    hu[sinus | hole] = HU[BRAIN]  # so only the geometry keeps them scalp
    assert sinus.sum() > 5 and hole.sum() > 5
    assert enclosed(seg == SKULL, seg == BG)[sinus].all() and not enclosed(seg == SKULL, seg == BG)[hole].any()
    out, info = scalp_outside_skull(_posteriors(seg), hu, params, opts)
    np.testing.assert_array_equal(out.argmax(0), seg)
    assert info == {"relabelled": 0}
    # 3. intracranial scalp whose intensity the mixture calls scalp (fat): the prior stands
    pocket = (lab == BRAIN) & (i[None, None, :] < 15)
    seg = np.where(pocket, SCALP, lab)
    out, info = scalp_outside_skull(_posteriors(seg, pocket), np.vectorize(HU.get)(seg).astype(np.float64), params, opts)
    np.testing.assert_array_equal(out.argmax(0), seg)
    assert info == {"relabelled": 0}


def test_config_flag_is_validated():
    with pytest.raises(ValueError, match="scalp_outside_skull"):
        SegmentConfig(modality="ct", scalp_outside_skull="yes")
    assert SegmentConfig(modality="ct").scalp_outside_skull
