"""Real anatomy: the MNI152 + fsaverage atlas, segmentation of a head it was not built from, orientation checks.

Fast cases at 4 mm; the table at 2 mm is experiments/segmentation_accuracy.py (and the slow test here).
The held-out head is the ANTs 19.5-year head in ../shared/data/heads (skipped where it is absent).
"""

from pathlib import Path

import numpy as np
import pytest
import trimesh
from shipped_heads import HEADS, needs_heads

from jaxhead.segmentation import SegmentConfig, default_atlas, segment, segment_reported
from jaxhead.segmentation.atlas import ATLAS_VERSION, anatomy_atlas
from jaxhead.segmentation.segment import (
    MAX_SCALE,
    MIN_NMI,
    MIN_SCALE,
    check_label_map,
    dice_scores,
)
from jaxhead.segmentation.templates import (
    CT_HU,
    MRI_CONTRAST,
    ants_anatomy,
    mni152_anatomy,
    random_contrast,
    rasterise,
    render,
)
from jaxhead.tissue import Tissue
from jaxhead.volume import LabelMap, Volume

VOX = 4.0


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    d = tmp_path_factory.mktemp("cache")
    mp.setenv("XDG_CACHE_HOME", str(d))
    yield d
    mp.undo()


@pytest.fixture(scope="module")
def mni():
    return mni152_anatomy()


@pytest.fixture(scope="module")
def ants():
    return ants_anatomy(HEADS).resampled(VOX)


def test_rasterise_sphere_volume():
    # a closed sphere of radius 40 mm on a 1 mm grid: voxel count = volume (to the discretisation
    # of the surface (icosphere: inscribed, ~0.2 % smaller) and voxel centres (O(area * h) / N ~ 1 %))
    s = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    aff = np.eye(4)
    aff[:3, 3] = -50
    inside = rasterise(s.vertices, s.faces, (101, 101, 101), aff)
    assert abs(inside.sum() / s.volume - 1) < 0.01
    assert inside[50, 50, 50] and not inside[0, 0, 0] and not inside[50, 50, 95]


def test_mni152_anatomy_is_a_nested_head(mni):
    fr = mni.fractions
    np.testing.assert_allclose(fr.sum(0), 1.0, atol=1e-5)
    assert fr.min() >= 0
    lab = mni.labels()
    vol = lab.tissue_volumes_mm3()
    # adult head in MNI152 space (the template is ~10-15 % larger per axis than an average head)
    assert 1.3e6 < vol[Tissue.BRAIN] < 2.1e6, vol
    assert 0.2e6 < vol[Tissue.CSF] < 0.8e6 and 0.3e6 < vol[Tissue.SKULL] < 1.0e6, vol
    # nested: every brain/CSF voxel's 6 neighbours are intracranial or skull (the skull encloses them)
    intra = (lab.labels == Tissue.BRAIN) | (lab.labels == Tissue.CSF)
    ok = intra | (lab.labels == Tissue.SKULL)
    inner = intra[1:-1, 1:-1, 1:-1]
    for ax in range(3):
        for d in (-1, 1):
            nb = np.roll(ok, d, axis=ax)[1:-1, 1:-1, 1:-1]
            assert (nb | ~inner).mean() > 0.9999
    # RAS: the face is anterior (+y), the brain above the neck (+z)
    head = lab.labels > 0
    idx = np.argwhere(head)
    assert np.argwhere(lab.labels == Tissue.BRAIN)[:, 2].mean() > idx[:, 2].mean()


def test_default_atlas_is_real_anatomy_and_cached(cache):
    a = default_atlas("mri", voxel_mm=VOX)
    assert a.name == "mni152" and a.modality == "mri"
    assert (cache / "jaxhead" / f"atlas_mni152_mri_{VOX:g}mm_v{ATLAS_VERSION}.npz").exists()
    b = default_atlas("mri", voxel_mm=VOX)  # from the cache
    assert b.name == "mni152"
    # the call that builds the atlas returns what the cache gives later, to the bit (a cold cache and a
    # warm one segment alike)
    for field in ("template", "priors", "unmodelled", "affine"):
        np.testing.assert_array_equal(getattr(b, field), getattr(a, field), err_msg=field)
    c = default_atlas("ct", voxel_mm=VOX)
    brain = c.priors[Tissue.BRAIN] > 0.9
    assert abs(np.median(c.template[brain]) - 35) < 10  # HU of brain
    assert np.median(c.template[c.priors[Tissue.SKULL] > 0.6]) > 300
    with pytest.raises(ValueError, match="mni152"):
        default_atlas("mri", atlas="colin27")
    with pytest.raises(ValueError, match="atlas"):
        SegmentConfig(atlas="colin27")


def test_render_intensities(mni):
    a = mni.resampled(VOX)
    ct = render(a, "ct", texture=False)
    pure = a.fractions > 0.999  # the rest (< 0.001) moves a value by < 0.001 * 2000 HU
    np.testing.assert_allclose(ct.data[pure[0]], CT_HU["air"], atol=2.0)
    np.testing.assert_allclose(ct.data[pure[3]], CT_HU["csf"], atol=2.0)
    mri = render(a, "mri", bias=0.2, seed=1, texture=False)
    ratio = mri.data[pure[2]] / MRI_CONTRAST["white_matter"]
    assert ratio.min() > np.exp(-0.2) - 1e-9 and ratio.max() < np.exp(0.2) + 1e-9
    c = random_contrast("ct", np.random.default_rng(0))
    assert set(c) == set(CT_HU)


@needs_heads
@pytest.mark.parametrize("modality", ["mri", "ct"])
def test_segment_held_out_head(modality, ants, cache):
    """The ANTs head, not in the MNI152 atlas, 4 mm, random contrast, noise and (MRI) bias field."""
    contrast = random_contrast(modality, np.random.default_rng(3))
    vol = render(ants, modality, contrast=contrast, noise=0.05 if modality == "mri" else 10.0,
                 bias=0.2 if modality == "mri" else 0.0, seed=3)
    labels, seg = segment_reported(vol, None, SegmentConfig(modality=modality, atlas_voxel_mm=VOX))
    assert seg.atlas_name == "mni152"
    r = seg.registration
    assert MIN_SCALE < min(r["scales"]) and max(r["scales"]) < MAX_SCALE and r["det"] > 0 and r["nmi"] > MIN_NMI
    d = dice_scores(labels, ants.labels())
    # 4 mm voxels: CSF (1-3 mm) and skull (4-7 mm) are mostly partial volume; 2 mm figures are in
    # experiments/results/segmentation_heldout_*.md
    assert d["brain"] > 0.9 and d["scalp"] > 0.85, d
    assert d["skull"] > 0.65 and d["csf"] > 0.25, d
    if modality == "ct":  # the skin's partial-volume shell went to the air (`air_majority`)
        air = r["air_majority"]
        assert air["air_hu"] < air["threshold_hu"] < air["scalp_hu"] and air["removed"] > 0, air
        bone = r["bone_majority"]  # so is the bone surface's (`bone_majority`)
        assert bone["soft_hu"] < bone["threshold_hu"] < bone["bone_hu"], bone


@needs_heads
def test_upside_down_scan_is_an_error(ants, cache):
    vol = render(ants, "mri", noise=0.03, seed=0)
    flipped = Volume(vol.data[:, :, ::-1], vol.affine)  # stored upside down, affine unchanged
    with pytest.raises(ValueError, match="mis-oriented"):
        segment(flipped, None, SegmentConfig(modality="mri", atlas_voxel_mm=VOX))


@needs_heads
def test_lps_scan_segments_as_its_ras_twin(ants, cache):
    vol = render(ants, "ct", noise=10.0, seed=0)
    cfg = SegmentConfig(modality="ct", atlas_voxel_mm=VOX)
    ras = segment(vol, None, cfg)
    # the same scan stored LPS: x and y reversed in the array, and the affine saying so
    n = np.array(vol.shape)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    flip[:2, 3] = n[:2] - 1
    lps = Volume(vol.data[::-1, ::-1], vol.affine @ flip)
    seg = segment(lps, None, cfg)
    back = LabelMap(seg.labels[::-1, ::-1], vol.affine)
    truth = ants.labels()
    d_ras, d_lps = dice_scores(ras, truth), dice_scores(back, truth)
    # Not bit-identical: the registration's random voxel sample and the block-averaging pyramid start at
    # the array's first voxel, which differ between the twins. At 4 mm the 1-3 mm CSF is all partial
    # volume and its Dice moves by several hundredths with such grid phases (measured 0.31 vs 0.26);
    # the thick tissues by < 0.01.
    for k, tol in (("brain", 0.02), ("skull", 0.02), ("scalp", 0.02), ("csf", 0.08)):
        assert abs(d_ras[k] - d_lps[k]) < tol, (d_ras, d_lps)


@needs_heads
def test_ct_padding_outside_the_field_of_view_changes_nothing(ants, cache):
    """A CT whose corners outside the reconstruction circle hold a padding value (-3024 HU) segments as
    the same scan without it (`replace_ct_padding`), and the report counts the voxels replaced."""
    vol = render(ants, "ct", noise=10.0, seed=0)
    n0, n1 = vol.shape[:2]
    x, y = np.arange(n0)[:, None] - n0 / 2, np.arange(n1)[None, :] - n1 / 2
    outside = np.broadcast_to(((x ** 2 + y ** 2) > (0.5 * max(n0, n1)) ** 2)[..., None], vol.shape)
    assert not (ants.labels().labels[outside] > 0).any()  # the circle clips no head voxel
    padded = Volume(np.where(outside, -3024.0, vol.data), vol.affine)
    cfg = SegmentConfig(modality="ct", atlas_voxel_mm=VOX)
    truth = ants.labels()
    lab, seg = segment_reported(padded, None, cfg)
    assert seg.registration["ct_padding"]["voxels"] == int(outside.sum())
    d_pad, d = dice_scores(lab, truth), dice_scores(segment(vol, None, cfg), truth)
    for k in ("brain", "csf", "skull", "scalp"):
        assert abs(d_pad[k] - d[k]) < 0.02, (d, d_pad)


def test_label_map_on_another_grid_is_an_error(mni):
    a = mni.resampled(VOX)
    vol = render(a, "mri")
    lab = a.labels()
    check_label_map(lab, vol)
    aff = lab.affine.copy()
    aff[0, 3] += 4.0  # one voxel over
    shifted = LabelMap(lab.labels, aff)
    with pytest.raises(ValueError, match="different affine"):
        check_label_map(shifted, vol)
    with pytest.raises(ValueError, match="different affine"):
        dice_scores(lab, shifted)
    with pytest.raises(ValueError, match="shape"):
        check_label_map(LabelMap(lab.labels[1:], lab.affine), vol)


@pytest.mark.slow
@needs_heads
@pytest.mark.xfail(reason="issue 11's bars are not met yet (skull, CSF, phantom family): see "
                          "experiments/results/segmentation_heldout.md", strict=True)
def test_held_out_table_meets_the_bars():
    """The 2 mm table of experiments/segmentation_accuracy.py (minutes)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "segmentation_accuracy", Path(__file__).resolve().parents[1] / "experiments" / "segmentation_accuracy.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)

    class Args:
        voxel_mm, seeds, modalities, heads = 2.0, 2, ["mri", "ct"], str(HEADS)

    rows = mod.run(Args)
    for r in rows:
        bars = mod.BARS[r["modality"]]
        got = (r["brain"], r["csf"], r["skull"], r["scalp"])
        assert all(g >= b for g, b in zip(got, bars)), r


def test_anatomy_atlas_of_another_head(mni):
    a = anatomy_atlas(mni, "ct", voxel_mm=6.0, name="test")
    assert a.name == "test" and a.priors.shape[1:] == a.template.shape
    np.testing.assert_allclose(a.priors.sum(0), 1.0, atol=1e-5)
