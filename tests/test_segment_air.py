"""The air around a CT head: the air majority rule (`air_majority`: the skin's partial-volume shell,
which the EM's narrow background Gaussians leave to the scalp, goes to the tissue that fills most of
each voxel) and a scanner's padding (`replace_ct_padding`)."""

import numpy as np
import pytest

from jaxhead.segmentation.segment import CT_PADDING_BELOW_HU, SegmentConfig, air_majority, replace_ct_padding
from jaxhead.volume import Volume
from jaxhead.tissue import Tissue

AIR, SCALP, BRAIN = int(Tissue.BACKGROUND), int(Tissue.SCALP), int(Tissue.BRAIN)


def _ball_fraction(n, centre, radius, sub=6):
    """Fraction of each unit voxel inside the ball (sub^3 point samples per voxel)."""
    g = (np.arange(n * sub) + 0.5) / sub
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    inside = (x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2 < radius ** 2
    return inside.reshape(n, sub, n, sub, n, sub).mean(axis=(1, 3, 5))


def _posteriors(lab):
    post = np.full((5, *lab.shape), 0.01, np.float32)
    np.put_along_axis(post, lab[None], 1.0, 0)
    return post / post.sum(0)


@pytest.mark.parametrize("centre, radius, padded", [((12.3, 11.8, 12.1), 8.4, False), ((11.5, 12.5, 12.0), 9.7, False),
                                                    ((12.3, 11.8, 12.1), 8.4, True)])
def test_skin_shell_goes_to_the_majority_tissue(centre, radius, padded):
    n = 24
    f = _ball_fraction(n, centre, radius)
    hu = f * 40.0 + (1 - f) * -1000.0  # soft tissue of 40 HU in air, linear partial volume
    if padded:  # a scanner's padding outside its reconstruction circle: most of the background here
        i = np.arange(n) + 0.5
        hu[(i[:, None, None] - 12) ** 2 + (i[None, :, None] - 12) ** 2 > 10.0 ** 2 + 0 * i] = -3024.0
    lab = np.where(hu > -990.0, SCALP, AIR)  # EM-like: every voxel with any tissue is scalp
    lab[int(centre[0]), int(centre[1]), int(centre[2])] = BRAIN  # other classes are left alone
    truth = np.where(f >= 0.5, SCALP, AIR)  # an exact half stays tissue (HU not below T)
    truth[int(centre[0]), int(centre[1]), int(centre[2])] = BRAIN
    assert ((lab == SCALP) & (truth == AIR)).sum() > 50  # the shell the rule is for
    out, info = air_majority(hu, _posteriors(lab))
    np.testing.assert_array_equal(out.argmax(0), truth)
    assert info["threshold_hu"] == pytest.approx(0.5 * (40.0 - 1000.0), abs=1.0)
    assert info["removed"] == int(((lab == SCALP) & (truth == AIR)).sum())
    np.testing.assert_allclose(out.sum(0), 1.0, rtol=1e-6)


def test_a_dark_piece_enclosed_by_tissue_keeps_its_label():
    n = 20
    hu = np.full((n, n, n), -1000.0)
    hu[3:17, 3:17, 3:17] = 40.0
    hu[8:11, 8:11, 8:11] = -700.0  # below the threshold, but no background beside it
    lab = np.where(hu > -990.0, SCALP, AIR)
    out, info = air_majority(hu, _posteriors(lab))
    np.testing.assert_array_equal(out.argmax(0), lab)
    assert info["removed"] == 0


@pytest.mark.parametrize("case", ["no background", "no scalp", "scalp darker"])
def test_nothing_the_rule_describes_leaves_the_posteriors_alone(case):
    hu = np.zeros((8, 8, 8))
    lab = np.full(hu.shape, SCALP)
    if case == "no scalp":
        lab[:] = AIR
    elif case == "scalp darker":
        lab[:4] = AIR
        hu[:4] = 100.0  # "background" brighter than scalp: not air
    post = _posteriors(lab)
    out, info = air_majority(hu, post)
    assert info == {}
    np.testing.assert_array_equal(out, post)


def test_config_flag_is_validated():
    with pytest.raises(ValueError, match="air_majority"):
        SegmentConfig(modality="ct", air_majority=1)
    assert SegmentConfig(modality="ct").air_majority


def test_padding_is_set_to_the_scans_own_air():
    rng = np.random.default_rng(0)
    d = rng.normal(-990.0, 15.0, (12, 12, 12))  # air of a scanner 10 HU off, with its noise
    d[4:8, 4:8, 4:8] = 40.0
    d[:2] = -3024.0
    d[-1, :3] = -2048.0
    vol = Volume(d, np.diag([2.0, 2.0, 2.0, 1.0]))
    out, info = replace_ct_padding(vol)
    pad = d < CT_PADDING_BELOW_HU
    assert info["voxels"] == pad.sum() == 2 * 144 + 36 and info["lowest_hu"] == -3024.0
    assert info["air_hu"] == pytest.approx(np.median(d[~pad & (d < -500)]), abs=0.05)
    np.testing.assert_array_equal(out.data[~pad], d[~pad])  # nothing else touched
    assert np.all(out.data[pad] == info["air_hu"]) and np.array_equal(out.affine, vol.affine)
    same, none = replace_ct_padding(Volume(np.where(pad, -1000.0, d), vol.affine))
    assert none == {} and np.array_equal(same.data, np.where(pad, -1000.0, d))
