"""MRI: the skull's diploe Gaussian kept above CSF (`SegmentConfig.diploe_above_csf`): the capture it
prevents on a small synthetic case, and the EMOptions it implies."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxhead.segmentation import SegmentConfig
from jaxhead.segmentation.em import EMOptions, fit_mixture
from jaxhead.segmentation.segment import DIPLOE_ABOVE_CSF_LOG
from jaxhead.tissue import Tissue

jax.config.update("jax_enable_x64", True)


def test_order_prevents_skull_capturing_csf():
    # T1-like log intensities: CSF (class 0, one Gaussian) 0.25 of white matter, skull (class 1: tables
    # 0.12, diploe Gaussian) with no marrow in this skull. The registered atlas (another head's) puts
    # skull (prior 0.8) on a band of CSF wider than the skull: maximum likelihood moves the skull's
    # second Gaussian onto CSF's intensity and labels that band skull (the capture on the MNI152 head,
    # experiments/results/segmentation_variance_prior.md). With the diploe Gaussian kept
    # DIPLOE_ABOVE_CSF_LOG above CSF, only the tables' Gaussian and the diploe's upper tail are left to explain it.
    rng = np.random.default_rng(0)
    shape = (40, 12, 12)
    x = np.broadcast_to((np.arange(shape[0])[:, None, None] + 0.5) / shape[0], shape)
    region = np.where(x < 0.3, 0, np.where(x < 0.65, 1, 2))  # CSF, CSF under a skull prior, skull
    y = np.log(np.array([0.25, 0.25, 0.12]))[region] + rng.normal(0, 0.12, shape)
    ps = np.where(region == 0, 0.2, 0.8)
    prior = jnp.asarray(np.stack([1 - ps, ps]))
    truth = region <= 1

    def fit(order, offset=0.0):
        opts = EMOptions(component_class=(0, 1, 1), n_classes=2, max_iter=300, tol=1e-9, mean_order=order)
        res = fit_mixture(jnp.asarray(y + offset), prior, opts)
        lab = np.asarray(res.posteriors).argmax(0) == 0
        return np.asarray(res.params.means), 2 * (lab & truth).sum() / (lab.sum() + truth.sum())

    (mu_ml, dice_ml), (mu_o, dice_o) = fit(()), fit(((0, 2, DIPLOE_ABOVE_CSF_LOG),))
    assert abs(mu_ml[2] - np.log(0.25)) < 0.1 and dice_ml < 0.85, (mu_ml, dice_ml)  # captured
    assert mu_o[2] >= mu_o[0] + DIPLOE_ABOVE_CSF_LOG - 1e-6, mu_o
    # the CSF voxels of the band above CSF + margin still go to the diploe Gaussian (margin 1.9 noise sd)
    assert dice_o > 0.85 and dice_o > dice_ml + 0.2, (mu_o, dice_o, mu_ml, dice_ml)
    # a global intensity scale (a log offset) moves every mean and changes no label
    mu_s, dice_s = fit(((0, 2, DIPLOE_ABOVE_CSF_LOG),), offset=np.log(300.0))
    np.testing.assert_allclose(mu_s, mu_o + np.log(300.0), atol=1e-6)
    assert dice_s == dice_o


def test_segment_config_diploe_above_csf():
    opts = SegmentConfig(modality="mri", diploe_above_csf=True, csf_mix_below_brain=False).em_options(1.0)
    cc = opts.component_class
    (lo, hi, margin), = opts.mean_order
    assert (cc[lo], cc[hi], margin) == (int(Tissue.CSF), int(Tissue.SKULL), DIPLOE_ABOVE_CSF_LOG)
    assert lo == cc.index(int(Tissue.CSF)) and hi == cc.index(int(Tissue.SKULL)) + 1  # CSF's first, skull's second
    assert 0 < DIPLOE_ABOVE_CSF_LOG < np.log(1.4)  # below the smallest marrow/CSF ratio quoted in segment.py
    default = SegmentConfig(modality="mri").em_options(1.0).mean_order  # off by default
    assert (cc.index(int(Tissue.CSF)), cc.index(int(Tissue.SKULL)) + 1, DIPLOE_ABOVE_CSF_LOG) not in default
    pv = SegmentConfig(modality="mri", diploe_above_csf=True, partial_volume=True).em_options(1.0)
    assert all(pv.is_free(j) for j in pv.mean_order[0][:2])
    with pytest.raises(ValueError, match="diploe_above_csf"):
        SegmentConfig(modality="ct", diploe_above_csf=True)
    with pytest.raises(ValueError, match="diploe_above_csf"):
        SegmentConfig(modality="mri", diploe_above_csf="yes")
    with pytest.raises(ValueError, match=">= 2"):
        SegmentConfig(modality="mri", diploe_above_csf=True, gaussians={"skull": 1})
