"""`marrow_inside_skull` (MRI): an adult's fat-bright marrow that a misplaced atlas calls scalp goes back to
the skull because the skull's tables enclose it; where nothing is enclosed the step changes nothing."""

import numpy as np
import pytest
from scipy import ndimage

from jaxhead.segmentation import SegmentConfig
from jaxhead.segmentation.atlas import Atlas
from jaxhead.segmentation.register import RegisterConfig
from jaxhead.segmentation.segment import MARROW_MIN_SHARE, dice_scores, enclosed, marrow_enclosed, segment_reported
from jaxhead.tissue import Tissue
from jaxhead.volume import LabelMap, Volume

BG, BRAIN, CSF, SKULL, SCALP = (int(t) for t in Tissue)
#: T1 magnitudes (white matter 1): an adult's marrow as bright as fat (templates.fatty_marrow)
T1 = dict(wm=1.0, gm=0.65, csf=0.25, bone=0.12, fat=1.1, muscle=0.45, skin=0.75)
N = 84  # 1 mm voxels; the head's outer radius is 38 mm


def _radius():
    i = np.arange(N) - (N - 1) / 2
    return np.sqrt(i[:, None, None] ** 2 + i[None, :, None] ** 2 + i[None, None, :] ** 2)


def _shells(r, edges, values):
    """values[k] between edges[k - 1] and edges[k] (edges[-1] = 0), the last value outside."""
    out = np.full(r.shape, values[-1], dtype=type(values[0]))
    for e, v in reversed(list(zip(edges, values))):
        out[r < e] = v
    return out


def _scan(marrow: bool, seed=0):
    """Brain to 18 mm (white matter inside 14), CSF to 21, skull to 29 (with `marrow`: tables 2 mm each
    around fat-bright marrow, else one dark bone), scalp fat to 33, muscle to 36 and skin to 38; 3 % noise."""
    r = _radius()
    bone_mid = T1["fat"] if marrow else T1["bone"]
    img = _shells(r, [14, 18, 21, 23, 27, 29, 33, 36, 38], [T1["wm"], T1["gm"], T1["csf"], T1["bone"], bone_mid,
                  T1["bone"], T1["fat"], T1["muscle"], T1["skin"], 0.0])
    rng = np.random.default_rng(seed)
    noisy = np.hypot(img + rng.normal(0, 0.03, r.shape), rng.normal(0, 0.03, r.shape))  # Rician magnitude
    truth = _shells(r, [18, 21, 29, 38], [BRAIN, CSF, SKULL, SCALP, BG])
    return Volume(noisy, np.eye(4)), LabelMap(truth.astype(np.uint8), np.eye(4))


def _atlas(skull_outer_mm: float, blur_mm: float = 1.5):
    """An atlas of the same head whose skull ends at `skull_outer_mm` (scalp from there): priors one-hot,
    blurred by `blur_mm` (Gaussian sd), plus a 5 % share of every head tissue inside the head; template
    without marrow."""
    r = _radius()
    lab = _shells(r, [18, 21, skull_outer_mm, 38], [BRAIN, CSF, SKULL, SCALP, BG])
    pri = np.stack([ndimage.gaussian_filter((lab == k).astype(np.float64), blur_mm) for k in range(5)])
    head = lab != BG
    pri[1:, head] += 0.05
    pri /= pri.sum(0)
    img = _shells(r, [14, 18, 21, skull_outer_mm, 33, 36, 38],
                  [T1["wm"], T1["gm"], T1["csf"], T1["bone"], T1["fat"], T1["muscle"], T1["skin"], 0.0])
    return Atlas(img, pri, np.eye(4), "mri", name=f"shells_skull_to_{skull_outer_mm:g}mm")


#: small and quick: affine registration only (the atlas is the head's own, up to its skull), no layer split
CFG = dict(modality="mri", register=RegisterConfig(bspline=False), check_registration=False, layer_split=False)


@pytest.mark.parametrize("marrow_inside_skull", [False, True])
def test_fatty_marrow_the_atlas_calls_scalp_goes_back_to_the_skull(marrow_inside_skull):
    vol, truth = _scan(marrow=True)
    atlas = _atlas(skull_outer_mm=25.0, blur_mm=3.0)  # the atlas's skull ends in the marrow, 4 mm inside the head's
    labels, seg = segment_reported(vol, atlas, SegmentConfig(**CFG, marrow_inside_skull=marrow_inside_skull))
    lab = labels.labels
    marrow = (_radius() >= 25) & (_radius() < 27)  # the marrow the atlas puts in the scalp
    d = dice_scores(labels, truth)
    if not marrow_inside_skull:  # the failure the step is for: intensity says fat, the prior says scalp
        assert (lab[marrow] == SCALP).mean() > 0.9
        assert d["skull"] < 0.7
        assert "marrow_inside_skull" not in seg.registration
        return
    report = seg.registration["marrow_inside_skull"]
    assert report["voxels"] > 0.9 * marrow.sum() and report["rounds"] >= 1
    assert (lab[marrow] == SKULL).mean() > 0.95
    assert d["skull"] > 0.95 and d["scalp"] > 0.95 and d["csf"] > 0.9
    # the skull class learnt the marrow's intensity: a Gaussian of the skull's near the fat's
    skull_means = np.exp(np.asarray(seg.params.means))[np.asarray(seg.component_class) == SKULL]
    weights = np.asarray(seg.params.weights)[np.asarray(seg.component_class) == SKULL]
    assert np.any((np.abs(skull_means - T1["fat"]) < 0.15) & (weights > 0.3))


def test_nothing_enclosed_nothing_changed():
    """A skull of dark bone (no marrow) under a right atlas: at most noise speckle of scalp lies inside the
    skull (below MARROW_MIN_SHARE of it), so the step moves nothing and the labels are those with it off,
    to the voxel."""
    vol, truth = _scan(marrow=False)
    atlas = _atlas(skull_outer_mm=29.0)
    on, seg = segment_reported(vol, atlas, SegmentConfig(**CFG))
    off, _ = segment_reported(vol, atlas, SegmentConfig(**CFG, marrow_inside_skull=False))
    report = seg.registration["marrow_inside_skull"]
    assert report["voxels"] == 0 and report["rounds"] == 0
    assert report["left_below_share"] < MARROW_MIN_SHARE * (on.labels == SKULL).sum()
    np.testing.assert_array_equal(on.labels, off.labels)
    assert dice_scores(on, truth)["skull"] > 0.9


def test_segment_config_marrow_inside_skull():
    assert SegmentConfig(modality="mri").marrow_inside_skull_on()
    assert not SegmentConfig(modality="ct").marrow_inside_skull_on()
    assert not SegmentConfig(modality="mri", marrow_inside_skull=False).marrow_inside_skull_on()
    with pytest.raises(ValueError, match="marrow_inside_skull.*modality='mri'"):
        SegmentConfig(modality="ct", marrow_inside_skull=True)
    with pytest.raises(ValueError, match="marrow_inside_skull"):
        SegmentConfig(modality="mri", marrow_inside_skull="yes")


def test_skipped_and_said_so_on_voxels_coarser_than_a_table():
    """At 2 mm the tables are partial volume with the marrow and the fat: the step does not run, the report
    says why, and the labels are those with it off."""
    vol, _ = _scan(marrow=True)
    coarse = Volume(vol.data[::2, ::2, ::2], np.diag([2.0, 2.0, 2.0, 1.0]))
    atlas = _atlas(skull_outer_mm=25.0, blur_mm=3.0)
    on, seg = segment_reported(coarse, atlas, SegmentConfig(**CFG))
    off, _ = segment_reported(coarse, atlas, SegmentConfig(**CFG, marrow_inside_skull=False))
    report = seg.registration["marrow_inside_skull"]
    assert report["rounds"] == 0 and "MARROW_MAX_VOXEL_MM" in report["skipped"]
    np.testing.assert_array_equal(on.labels, off.labels)


def _labels_with_dark_outer_table(channel: bool = False):
    """Label map of nested shells (1 mm): brain to 12, CSF to 14, inner table (skull) to 16, marrow labelled
    scalp to 19, an outer table labelled BACKGROUND (as dark as air) to 21, scalp to 26, air outside.
    `channel`: a 3 x 3 voxel tube of air from the outer table straight out through the scalp."""
    n = 60
    i = np.arange(n) - (n - 1) / 2
    r = np.sqrt(i[:, None, None] ** 2 + i[None, :, None] ** 2 + i[None, None, :] ** 2)
    lab = _shells(r, [12, 14, 16, 19, 21, 26], [BRAIN, CSF, SKULL, SCALP, BG, SCALP, BG]).astype(np.uint8)
    if channel:
        c = n // 2
        tube = (slice(c - 1, c + 2), slice(c - 1, c + 2), slice(c, n))
        lab[tube] = np.where(r[tube] >= 19, BG, lab[tube])
    return lab, r


def test_marrow_enclosed_walls_background_the_head_encloses():
    """The marrow's rays outward meet the outer table labelled background: background, but enclosed by the
    scalp, so it walls the marrow as the skull does; the scalp outside the table stays outside."""
    lab, r = _labels_with_dark_outer_table()
    marrow, scalp = (r >= 16) & (r < 19), (r >= 21) & (r < 26)
    inside = marrow_enclosed(lab)
    assert inside[marrow].all() and not inside[scalp].any()
    # with background as the way out wherever it lies, the dark table would let every marrow voxel escape
    assert not enclosed(lab == SKULL, lab == BG)[marrow].any()
    # a channel of air from the table to the outside: the table is no longer all walled, and the marrow
    # whose rays run out through it escapes; the rest stays enclosed
    lab_c, _ = _labels_with_dark_outer_table(channel=True)
    inside_c = marrow_enclosed(lab_c)
    assert 0.5 < inside_c[marrow].mean() < 1.0 and not inside_c[scalp].any()
