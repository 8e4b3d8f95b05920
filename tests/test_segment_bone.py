"""The CT bone majority rule (`bone_majority`): partial-volume voxels of the bone surface go to the
tissue that fills most of them; enclosed low-density bone (diploe) stays skull."""

import numpy as np
import pytest

from jaxhead.segmentation.segment import SegmentConfig, bone_majority
from jaxhead.tissue import Tissue

SKULL, BRAIN, SCALP, AIR = int(Tissue.SKULL), int(Tissue.BRAIN), int(Tissue.SCALP), int(Tissue.BACKGROUND)


def _slab(lo, hi, n=40):
    """Fraction of each unit voxel [i, i + 1) covered by [lo, hi)."""
    i = np.arange(n)
    return np.clip(np.minimum(i + 1, hi) - np.maximum(i, lo), 0, 1)


@pytest.mark.parametrize("lo, hi", [(10.3, 16.6), (12.7, 18.2), (9.5, 15.45)])
def test_bone_surface_goes_to_the_majority_tissue(lo, hi):
    # x: air | scalp (40 HU) | bone (1200 HU) with diploe (250 HU) inside | brain (30 HU)
    n = 40
    f_bone = _slab(lo, hi, n)
    f_scalp = _slab(3.0, lo, n)
    f_brain = _slab(hi, n, n)
    f_air = 1 - f_bone - f_scalp - f_brain
    hu1 = f_bone * 1200 + f_scalp * 40 + f_brain * 30 + f_air * -1000
    hu = np.broadcast_to(hu1[:, None, None], (n, 12, 12)).copy()
    mid = int((lo + hi) / 2)
    hu[mid, 4:8, 4:8] = 250.0  # diploe: below the threshold, enclosed by bone
    truth1 = np.argmax(np.stack([f_air, f_brain, 0 * f_air, f_bone, f_scalp]), 0)
    truth = np.broadcast_to(truth1[:, None, None], hu.shape).copy()
    truth[mid, 4:8, 4:8] = SKULL
    # an EM-like result: skull from 150 HU up (a voxel too thick), plus one bone voxel taken by brain
    post = np.full((5, *hu.shape), 0.01, np.float32)
    lab = np.where(hu > 150, SKULL, np.where(hu < -500, AIR, np.where(np.arange(n)[:, None, None] < lo, SCALP, BRAIN)))
    lab[mid + 1, 2, 2] = BRAIN
    side = np.where(np.arange(n)[:, None, None] + 0.5 < (lo + hi) / 2, SCALP, BRAIN) + 0 * lab
    np.put_along_axis(post, side[None], 0.2, 0)  # the runner-up: the soft tissue on that side
    np.put_along_axis(post, lab[None], 1.0, 0)
    post /= post.sum(0)
    assert (lab != truth).sum() > 0  # the EM-like labels are wrong somewhere
    out, info = bone_majority(hu, post)
    np.testing.assert_array_equal(out.argmax(0), truth)
    assert info["threshold_hu"] == pytest.approx(0.5 * (1200 + 30), abs=1.0)
    np.testing.assert_allclose(out.sum(0), 1.0, rtol=1e-6)


def test_no_bone_leaves_the_posteriors_alone():
    hu = np.zeros((10, 10, 10))
    post = np.full((5, 10, 10, 10), 0.2, np.float32)
    post[SKULL, :5] = 0.5  # "skull" as dark as brain: not bone, nothing to do
    out, info = bone_majority(hu, post / post.sum(0))
    assert info == {}
    np.testing.assert_array_equal(out, post / post.sum(0))


def test_config_flag_is_validated():
    with pytest.raises(ValueError, match="bone_majority"):
        SegmentConfig(modality="ct", bone_majority="yes")
