"""Where the atlas models no bone (face, skull base, neck of the mni152 atlas): the map, the regional
proportions learnt from the scan, and the facial skull of a head the atlas never saw.
"""


import importlib

import numpy as np
import pytest
from scipy import ndimage
from shipped_heads import HEADS, needs_heads

from jaxhead.phantom import make_head
from jaxhead.segmentation import (
    SegmentConfig,
    default_atlas,
    dice_scores,
    register_atlas,
    segment_reported,
)
from jaxhead.segmentation.atlas import Atlas, regional_proportions, with_proportions
from jaxhead.segmentation.segment import checked_start, unmodelled_on_grid
from jaxhead.segmentation.templates import (
    UNMODELLED_CLASSES,
    ants_anatomy,
    mni152_anatomy,
    random_contrast,
    render,
    under_or_beside,
)
from jaxhead.tissue import Tissue

VOX = 4.0


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    d = tmp_path_factory.mktemp("cache")
    mp.setenv("XDG_CACHE_HOME", str(d))
    yield d
    mp.undo()


def test_regional_proportions_recover_a_mixture():
    # two classes with known densities, 15 % / 85 %: the ML proportion is within 3 standard errors
    rng = np.random.default_rng(0)
    n, pi = 20000, np.array([0.15, 0.85])
    z = rng.random(n) < pi[0]
    x = np.where(z, rng.normal(0.0, 1.0, n), rng.normal(1.5, 1.0, n))
    lik = np.stack([np.exp(-0.5 * x ** 2), np.exp(-0.5 * (x - 1.5) ** 2)])  # common factor dropped
    got = regional_proportions(lik, np.ones(n))
    se = np.sqrt(pi[0] * pi[1] / n) * 3  # > the ML estimate's sd (overlapping classes inflate it ~2x)
    assert abs(got[0] - z.mean()) < 3 * se and abs(got.sum() - 1) < 1e-12, (got, z.mean())
    # separated classes: the weighted fraction exactly; a zero weight excludes a voxel
    onehot = np.stack([z, ~z]).astype(float)
    w = rng.random(n)
    np.testing.assert_allclose(regional_proportions(onehot, w)[0], (w * z).sum() / w.sum(), rtol=1e-9)
    w[z] = 0.0
    np.testing.assert_allclose(regional_proportions(onehot, w), [0.0, 1.0], atol=1e-12)
    # an empty region: equal shares; mismatched shapes: an error
    np.testing.assert_allclose(regional_proportions(lik, np.zeros(n)), [0.5, 0.5])
    with pytest.raises(ValueError, match="weights"):
        regional_proportions(lik, np.ones(n - 1))


def test_with_proportions_moves_only_the_region_and_keeps_the_sum():
    rng = np.random.default_rng(1)
    p = rng.random((5, 6, 5, 4))
    p /= p.sum(0)
    u = rng.random((6, 5, 4))
    u[0] = 0.0
    u[1] = 1.0
    pi = np.array([0.2, 0.8])
    q = with_proportions(p, u, pi)
    k = [int(c) for c in UNMODELLED_CLASSES]
    other = [c for c in range(5) if c not in k]
    np.testing.assert_allclose(q.sum(0), 1.0, atol=1e-12)
    np.testing.assert_allclose(q[other], p[other], atol=0)
    np.testing.assert_allclose(q[:, 0], p[:, 0], atol=0)  # u = 0: unchanged
    s = p[k][:, 1].sum(0)
    np.testing.assert_allclose(q[k][:, 1], pi[:, None, None] * s, rtol=1e-12)  # u = 1: the proportions
    mid = (1 - u[2]) * p[k][:, 2] + u[2] * pi[:, None, None] * p[k][:, 2].sum(0)
    np.testing.assert_allclose(q[k][:, 2], mid, rtol=1e-12)
    # float32 priors (segment's) stay float32, equal to the float64 result to float32 rounding
    q32 = with_proportions(p.astype(np.float32), u.astype(np.float32), pi)
    assert q32.dtype == np.float32 and q.dtype == np.float64
    np.testing.assert_allclose(q32, q, rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="unmodelled"):  # a map of another grid is an error, not a broadcast
        with_proportions(p, u[:, :, :2], pi)


def test_under_or_beside_against_a_loop():
    rng = np.random.default_rng(2)
    m = np.zeros((7, 6, 9), bool)
    m[2:5, 1:4, 4:8] = rng.random((3, 3, 4)) > 0.3
    got = under_or_beside(m)
    want = np.zeros_like(m)
    for i in range(7):
        for j in range(6):
            ks = np.flatnonzero(m[i, j])
            want[i, j] = np.arange(9) < (ks[0] if ks.size else 9)
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="3D"):
        under_or_beside(m[0])


def test_mni152_marks_face_and_neck_as_unmodelled():
    a = mni152_anatomy()
    u = a.unmodelled_bone > 0.5
    lab = a.labels().labels
    ic = (lab == Tissue.BRAIN) | (lab == Tissue.CSF)
    # only placeholder soft tissue: never intracranial, skull or air
    assert np.all(lab[u] == Tissue.SCALP)
    # the face and neck (a large share of the soft tissue), none of it over the vault
    assert 0.4 < u.sum() / (lab == Tissue.SCALP).sum() < 0.95
    assert not np.any(u & ~under_or_beside(ic))
    # bone-free skin: every marked voxel lies deeper than the skin margin below the scalp surface
    d_out = ndimage.distance_transform_edt(lab > 0)
    assert d_out[u].min() > 2.0
    r = a.resampled(VOX)
    assert 0 <= r.unmodelled_bone.min() and r.unmodelled_bone.max() <= 1 and r.unmodelled_bone.any()


def test_atlas_keeps_its_unmodelled_map(tmp_path, cache):
    a = default_atlas("mri", voxel_mm=VOX)
    assert a.unmodelled is not None and a.unmodelled.shape == a.shape and a.unmodelled.max() > 0.9
    b = Atlas.load(a.save(tmp_path / "a.npz"))
    np.testing.assert_array_equal(b.unmodelled, a.unmodelled)  # default_atlas returns the stored form
    c = default_atlas("mri", voxel_mm=VOX, cache=False)  # built, in the stored form
    np.testing.assert_array_equal(c.unmodelled, a.unmodelled)
    np.testing.assert_array_equal(c.priors, a.priors)
    with pytest.raises(ValueError, match="unmodelled"):
        Atlas(a.template, a.priors, a.affine, "mri", unmodelled=np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="unmodelled"):
        Atlas(a.template, a.priors, a.affine, "mri", unmodelled=a.unmodelled + 1.5)


@needs_heads
def test_facial_skull_of_a_head_the_atlas_never_saw(cache):
    """The ANTs head (its facial bones, skull base and vertebrae) with the mni152 atlas, MRI at 4 mm:
    learning the bone share where the atlas has none finds the facial skull that the atlas's
    placeholder soft tissue hid (measured at 2 mm: skull Dice 0.775-0.789 -> 0.870-0.875; see
    experiments/results/segmentation_heldout_mri.md)."""
    ants = ants_anatomy(HEADS).resampled(VOX)
    truth = ants.labels()
    vol = render(ants, "mri", contrast=random_contrast("mri", np.random.default_rng(3)), noise=0.05, bias=0.2,
                 seed=3)
    # the learnt share alone: the layer split (on for MRI) also moves skull voxels (with it: recall
    # 0.609 -> 0.660, skull 0.839 -> 0.845; with the depth prior, session 14: 0.596 -> 0.663)
    cfg = SegmentConfig(modality="mri", atlas_voxel_mm=VOX, depth_prior=False, layer_split=False)
    atlas = default_atlas("mri", voxel_mm=VOX)
    blind = Atlas(atlas.template, atlas.priors, atlas.affine, "mri", atlas.n_subjects, atlas.name)  # no map
    ic = (truth.labels == Tissue.BRAIN) | (truth.labels == Tissue.CSF)
    face = (truth.labels == Tissue.SKULL) & (ndimage.distance_transform_edt(~ic) * VOX > 10)
    got = {}
    for name, at in (("learnt", atlas), ("placeholder", blind)):
        labels, _ = segment_reported(vol, at, cfg)
        got[name] = (np.mean(labels.labels[face] == Tissue.SKULL), dice_scores(labels, truth))
    (recall, d), (recall0, d0) = got["learnt"], got["placeholder"]
    # measured at 4 mm (partial volume blurs the thin facial bones): recall 0.54 -> 0.65, skull 0.822 -> 0.843;
    # since session 17 (MRI: equal start, second EM warm-started from the first) 0.542 -> 0.606, 0.822 -> 0.843
    assert recall > 0.58 and recall > recall0 + 0.04, got
    assert d["skull"] > d0["skull"] + 0.01 and d["scalp"] > d0["scalp"] - 0.01, got
    assert d["brain"] > 0.9, got


def test_unmodelled_start_is_checked():
    with pytest.raises(ValueError, match="unmodelled_start"):
        SegmentConfig(modality="mri", unmodelled_start="placeholder")
    assert SegmentConfig(modality="mri", unmodelled_start="checked").unmodelled_start_of() == "checked"
    assert SegmentConfig(modality="mri").unmodelled_start_of() == "checked"
    assert SegmentConfig(modality="ct").unmodelled_start_of() == "atlas"
    assert SegmentConfig(modality="ct", unmodelled_start="equal").unmodelled_start_of() == "equal"


@needs_heads
def test_equal_start_learns_the_facial_bone_share_on_mri(cache):
    """MRI: started from the atlas's placeholder soft tissue, the first EM's scalp class takes the face's
    dark bone (in T1 as dark as the air/skin partial volume it must model), and the learnt skull share
    falls far below the truth; started from equal shares it lands near it (measured at 2 mm on this head:
    0.017-0.075 against 0.088-0.148, truth 0.106-0.108; experiments/results/segmentation_unmodelled_start.md).
    Reference: the true skull share of skull + scalp, weighted by the registered map as the estimate is."""
    ants = ants_anatomy(HEADS).resampled(VOX)
    truth = ants.labels()
    vol = render(ants, "mri", noise=0.08, bias=0.2, seed=0)
    atlas = default_atlas("mri", voxel_mm=VOX)
    got = {}
    for start in ("atlas", "equal"):
        cfg = SegmentConfig(modality="mri", atlas_voxel_mm=VOX, unmodelled_start=start)
        labels, seg = segment_reported(vol, atlas, cfg)
        u = unmodelled_on_grid(vol, atlas, seg.transform, cfg)
        skull, head = truth.labels == Tissue.SKULL, np.isin(truth.labels, (Tissue.SKULL, Tissue.SCALP))
        got[start] = (seg.registration["unmodelled"], float((u * skull).sum() / (u * head).sum()),
                      dice_scores(labels, truth)["skull"])
    print(got)
    (rep_a, true_a, dice_a), (rep_e, true_e, dice_e) = got["atlas"], got["equal"]
    assert rep_a["start"] == "atlas" and rep_e["start"] == "equal"
    assert rep_e["skull"] + rep_e["scalp"] == pytest.approx(1.0, abs=1e-3)
    assert abs(rep_e["skull"] - true_e) < 0.5 * abs(rep_a["skull"] - true_a), got
    assert dice_e > dice_a, got


@needs_heads
def test_first_pass_on_a_coarser_sample_learns_the_same_share(cache):
    """The first EM only learns a regional average (the skull share where the atlas models no bone) and the second
    EM's start, so `first_pass_sample_mm` may sample it more sparsely than `em_sample_mm`: on the ANTs head at 4 mm,
    every 2nd voxel (8 mm) learns the share of every voxel (4 mm) to within 0.03, both near the truth, and the
    labels agree."""
    ants = ants_anatomy(HEADS).resampled(VOX)
    truth = ants.labels()
    vol = render(ants, "mri", noise=0.05, bias=0.2, seed=1)
    atlas = default_atlas("mri", voxel_mm=VOX)
    skull, head = truth.labels == Tissue.SKULL, np.isin(truth.labels, (Tissue.SKULL, Tissue.SCALP))
    got = {}
    for mm in (VOX, 2 * VOX):
        cfg = SegmentConfig(modality="mri", atlas_voxel_mm=VOX, first_pass_sample_mm=mm)
        labels, seg = segment_reported(vol, atlas, cfg)
        u = unmodelled_on_grid(vol, atlas, seg.transform, cfg)
        got[mm] = (seg.registration["unmodelled"]["skull"], float((u * skull).sum() / (u * head).sum()),
                   dice_scores(labels, truth))
    print(got)
    (fine, true, d_fine), (coarse, _, d_coarse) = got[VOX], got[2 * VOX]
    assert abs(coarse - fine) < 0.03, got
    assert abs(coarse - true) < 0.05 and abs(fine - true) < 0.05, got
    for t in ("brain", "csf", "skull", "scalp"):
        assert abs(d_coarse[t] - d_fine[t]) < 0.02, got
    with pytest.raises(ValueError, match="first_pass_sample_mm"):
        SegmentConfig(modality="mri", first_pass_sample_mm=0.0)


def test_second_em_starts_afresh_from_the_learnt_shares(cache):
    """The second EM depends on the first only through the learnt shares `pi`: `classify` equals one EM from its
    own start on the priors with those shares, bit for bit, whatever the first pass's sample (8 mm here, every
    2nd voxel at 4 mm). Warm-started from where the first EM stopped, it would not (the reason the first pass
    could not sample sparsely before session 30: experiments/results/segmentation_first_pass.md)."""
    seg = importlib.import_module("jaxhead.segmentation.segment")
    vol = render(mni152_anatomy().resampled(VOX), "mri", noise=0.05, bias=0.2, seed=2)
    atlas = default_atlas("mri", voxel_mm=VOX)
    cfg = SegmentConfig(modality="mri", atlas_voxel_mm=VOX, first_pass_sample_mm=2 * VOX)
    transform, priors = register_atlas(vol, atlas, cfg)
    u = unmodelled_on_grid(vol, atlas, transform, cfg)
    post, res, _, _, pi, _ = seg._classify_all(vol, priors, cfg, u)
    assert pi is not None and abs(pi.sum() - 1) < 1e-6 and 0 < pi[0] < 1
    direct = seg._classify(vol, with_proportions(np.asarray(priors), u, pi), cfg)
    np.testing.assert_array_equal(post, direct[0])
    assert int(res.n_iter) == int(direct[1].n_iter)


def test_a_segmentation_computes_the_em_data_once(cache, monkeypatch):
    """The EM's data (log intensities, the Rician noise measured from the air) is computed once per segmentation
    and handed on with each fit: the first pass, the second EM, the layer split's band and its EM share it, read-only
    (before session 30 each computed it again: ~0.1 s a call at 1 mm, six calls per MRI)."""
    seg = importlib.import_module("jaxhead.segmentation.segment")
    calls = []
    real = seg._em_data_noise
    monkeypatch.setattr(seg, "_em_data_noise", lambda *a, **k: calls.append(a[1:]) or real(*a, **k))
    vol = render(mni152_anatomy().resampled(VOX), "mri", noise=0.05, bias=0.2, seed=2)
    cfg = SegmentConfig(modality="mri", atlas_voxel_mm=VOX)
    _, report = segment_reported(vol, default_atlas("mri", voxel_mm=VOX), cfg)
    assert "layer_split" in report.registration and "unmodelled" in report.registration
    assert len(calls) == 1, calls
    y, _ = seg._scan_em_data(vol, cfg)
    assert not y.flags.writeable and vol.data.flags.writeable


def _share_map(f):
    """`checked_start`'s `learn` for a share map f: skull share -> skull share (None: the placeholder, share 0),
    recording the shares it was called with."""
    calls = []

    def learn(shares):
        calls.append(None if shares is None else float(shares[0]))
        s = f(0.0 if shares is None else float(shares[0]))
        return f"fit from {calls[-1]}", np.array([s, 1.0 - s])
    return learn, calls


def _smooth_step(lo, hi, mid):
    """A share map with two stable fixed points near `lo` and `hi` and the unstable one between them near `mid`."""
    def f(s):
        t = np.clip(s - mid + 0.5, 0.0, 1.0)
        return lo + (hi - lo) * t * t * (3 - 2 * t)
    return f


@pytest.mark.parametrize("case", ["runaway", "down_from_below", "up_from_below", "down_from_above"])
def test_checked_start_falls_back_only_where_the_share_runs_away(case):
    """`checked_start` on share maps. Runaway: two stable fixed points (near 0.1 and 0.95, the unstable one near
    0.3), so from equal shares the iteration climbs (the shape measured on the blurred adult-marrow scan: 0.597 ->
    0.879 -> 0.975; experiments/results/segmentation_unmodelled_bistable.md): the placeholder's share (from 0, in
    the lower basin) is used. Otherwise the first pass's share is kept: learnt below the equal start, whether the
    iteration would go on down or creep up (0.095 -> 0.100 on a sharp child's-marrow scan, truth 0.119), no second
    pass is run; learnt above it but coming back down, the second pass's share is only reported."""
    f = {"runaway": _smooth_step(0.1, 0.95, 0.3), "down_from_below": _smooth_step(0.1, 0.95, 0.7),
         "up_from_below": lambda s: 0.1 - (s - 0.095) * 0.005 / 0.405,  # 0.5 -> 0.095 -> 0.1
         "down_from_above": lambda s: 1.1 - s}[case]
    learn, calls = _share_map(f)
    fit, pi, check = checked_start(learn, 2, 0)
    first, again = f(0.5), f(f(0.5))
    assert check["equal"] == pytest.approx(first, abs=1e-4) and pi.sum() == pytest.approx(1.0)
    assert check["runaway"] is (case == "runaway")
    if case == "runaway":
        assert first > 0.5 and again > first and calls == [0.5, pytest.approx(first), None]
        assert fit == "fit from None" and pi[0] == pytest.approx(f(0.0)) and f(0.0) < 0.3
        assert check["again"] == pytest.approx(again, abs=1e-4) and check["atlas"] == pytest.approx(f(0.0), abs=1e-4)
    elif case == "down_from_above":
        assert first > 0.5 and again < first and calls == [0.5, pytest.approx(first)]
        assert fit == "fit from 0.5" and pi[0] == pytest.approx(first) and "atlas" not in check
    else:
        assert first < 0.5 and calls == [0.5] and fit == "fit from 0.5" and pi[0] == pytest.approx(first)
        assert "again" not in check and "atlas" not in check
    if case == "up_from_below":
        assert again > first  # a second pass would have risen: the equal start's bound is what keeps it


def test_checked_start_segments_as_equal_where_nothing_runs_away(cache):
    """The whole chain: "checked" reports its shares; where the share learnt from equal shares is at most half (the
    MNI152 head at 4 mm, mni152 atlas) it runs no second pass and the labels are those of "equal", voxel for voxel."""
    vol = render(mni152_anatomy().resampled(VOX), "mri", noise=0.05, bias=0.2, seed=2)
    atlas = default_atlas("mri", voxel_mm=VOX)
    got = {s: segment_reported(vol, atlas, SegmentConfig(modality="mri", atlas_voxel_mm=VOX, unmodelled_start=s))
           for s in ("equal", "checked")}
    rep = got["checked"][1].registration["unmodelled"]
    assert rep["start"] == "checked" and rep["checked"]["runaway"] is False, rep
    assert rep["checked"]["equal"] == pytest.approx(got["equal"][1].registration["unmodelled"]["skull"], abs=1e-4)
    assert "checked" not in got["equal"][1].registration["unmodelled"]
    np.testing.assert_array_equal(got["checked"][0].labels, got["equal"][0].labels)


def test_checked_start_segments_as_the_placeholder_where_the_share_runs_away(cache):
    """The whole chain where the share runs away: our phantom (its neck a cylinder of soft tissue, no bone) with
    the mni152 atlas, MRI at 4 mm. From equal shares its skull class takes the neck (the share measured at 2 and
    1 mm: 0.66-0.80 from equal shares, higher again from those; experiments/results/segmentation_unmodelled_runaway.md);
    "checked" sees the rise and segments exactly as the placeholder start ("atlas") does."""
    vol, _ = make_head("mri", voxel_mm=VOX, noise=0.03, seed=0)
    atlas = default_atlas("mri", voxel_mm=VOX)
    got = {s: segment_reported(vol, atlas, SegmentConfig(modality="mri", atlas_voxel_mm=VOX, unmodelled_start=s))
           for s in ("atlas", "checked")}
    rep = got["checked"][1].registration["unmodelled"]
    check = rep["checked"]
    assert check["runaway"] is True and check["again"] > check["equal"] > 0.5, rep
    assert check["atlas"] == pytest.approx(got["atlas"][1].registration["unmodelled"]["skull"], abs=1e-4)
    assert rep["skull"] == pytest.approx(check["atlas"], abs=1e-4) and check["atlas"] < check["equal"]
    np.testing.assert_array_equal(got["checked"][0].labels, got["atlas"][0].labels)
