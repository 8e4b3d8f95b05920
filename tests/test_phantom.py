"""Tests of jaxhead.phantom: geometry (nesting, thickness, border), intensities, determinism, errors."""

import logging

import numpy as np
import pytest
from scipy import ndimage

from jaxhead import phantom as P
from jaxhead.phantom import STRUCTURE_TISSUE, PhantomHead, Structure, make_head, make_population, structure_map
from jaxhead.tissue import Tissue
from jaxhead.volume import LabelMap, Volume, default_affine

CUBE = np.ones((3, 3, 3), bool)  # 26-neighbourhood: the strictest nesting test


@pytest.fixture(scope="module")
def mri3():
    return make_head("mri", voxel_mm=3.0, seed=0)


@pytest.fixture(scope="module")
def s3():
    """Structure map of the `mri3` subject and grid."""
    return structure_map(voxel_mm=3.0, seed=0)


@pytest.fixture(scope="module")
def heads2():
    """2.5 mm MRI (no bias) and CT of one subject with its structure map (enough pure voxels)."""
    mri, labels = make_head("mri", voxel_mm=2.5, seed=1, bias=False)
    ct, labels_ct = make_head("ct", voxel_mm=2.5, seed=1)
    s = structure_map(voxel_mm=2.5, seed=1)
    pure = ndimage.maximum_filter(s, size=3) == ndimage.minimum_filter(s, size=3)
    return mri, ct, labels, labels_ct, s, pure


def nested_solids(labels: np.ndarray):
    """Masks of head, skull-and-inside, CSF-and-inside, brain (ventricles filled)."""
    m4 = labels != Tissue.BACKGROUND
    m3 = m4 & (labels != Tissue.SCALP)
    m2 = m3 & (labels != Tissue.SKULL)
    m1 = ndimage.binary_fill_holes(labels == Tissue.BRAIN)
    return m4, m3, m2, m1


# ---------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed,voxel_mm,neck", [(0, 3.0, True), (1, 3.5, False), (2, (2.5, 3.0, 3.5), True)])
def test_strict_nesting(seed, voxel_mm, neck):
    _, lab = make_head("ct", voxel_mm=voxel_mm, seed=seed, neck=neck, noise=0)
    L = lab.labels
    allowed = {  # the tissues each tissue's 26 neighbours may have
        Tissue.BRAIN: {Tissue.BRAIN, Tissue.CSF},
        Tissue.CSF: {Tissue.BRAIN, Tissue.CSF, Tissue.SKULL},
        Tissue.SKULL: {Tissue.CSF, Tissue.SKULL, Tissue.SCALP},
        Tissue.SCALP: {Tissue.SKULL, Tissue.SCALP, Tissue.BACKGROUND},
    }
    for t, ok in allowed.items():
        ring = ndimage.binary_dilation(L == t, CUBE)
        seen = set(np.unique(L[ring]).tolist())
        assert seen <= {int(x) for x in ok}, (t.name, seen)
    # Nested solids: each one's 26-dilation stays inside the next.
    m4, m3, m2, m1 = nested_solids(L)
    for inner, outer in ((m1, m2), (m2, m3), (m3, m4)):
        assert inner.any()
        assert not (ndimage.binary_dilation(inner, CUBE) & ~outer).any()
    # Every tissue present, one connected scalp/skull shell.
    assert all((L == t).any() for t in Tissue)
    for t in (Tissue.SKULL, Tissue.SCALP):
        assert ndimage.label(L == t, CUBE)[1] == 1


def test_ventricles_are_csf_inside_brain(mri3):
    L = mri3[1].labels
    comps, n = ndimage.label(L == Tissue.CSF, CUBE)
    assert n >= 2  # the CSF shell plus at least one ventricle
    sizes = np.bincount(comps.ravel())[1:]
    shell = 1 + int(np.argmax(sizes))
    for c in range(1, n + 1):
        if c == shell:
            continue
        rim = ndimage.binary_dilation(comps == c, CUBE) & (comps != c)
        assert np.all(L[rim] == Tissue.BRAIN)


@pytest.mark.parametrize("voxel_mm", [3.0, 2.5])
def test_layer_thickness_ranges(voxel_mm):
    """Scalp 3-8, skull 4-9, CSF 1-5 mm, measured on the labels by distance transforms (mm).

    At an outer boundary voxel the distance to the nearest voxel of the next inner solid is the
    layer's thickness to within one voxel either way (both surfaces are located to a voxel), so
    every measurement must lie in [lo - h, hi + h]; strict nesting forces CSF to >= 1 voxel.
    """
    _, lab = make_head("ct", voxel_mm=voxel_mm, seed=3, neck=False, noise=0)
    h = voxel_mm
    m4, m3, m2, m1 = nested_solids(lab.labels)
    for (lo, hi), outer, inner in ((P.SCALP_MM, m4, m3), (P.SKULL_MM, m3, m2), (P.CSF_MM, m2, m1)):
        boundary = outer & ~ndimage.binary_erosion(outer, CUBE)
        t = ndimage.distance_transform_edt(~inner, sampling=h)[boundary]
        assert t.min() >= lo - h - 1e-9 and t.max() <= hi + h + 1e-9, (lo, hi, t.min(), t.max())
        p5, p50, p95 = np.percentile(t, [5, 50, 95])
        assert lo - h <= p50 <= hi + h
        assert p95 - p5 >= 0.4 * (hi - lo)  # thickness varies over the head


@pytest.mark.parametrize("seed", [0, 7])
def test_thickness_fields_span_their_ranges(seed):
    """The layer fields reach both ends of their ranges on the cranium surface (5 % clipped each)."""
    sub = P._make_subject(seed)
    surface = P._cranium_surface(
        dict(rot=sub.rot, shape_field=sub.shape_field, shape_amp=sub.shape_amp, axes=sub.axes, egg=sub.egg),
        P._fibonacci_sphere(3000))
    for field, (lo, hi) in ((sub.scalp, P.SCALP_MM), (sub.skull, P.SKULL_MM), (sub.csf, P.CSF_MM)):
        v = field.points(surface)
        assert v.min() == pytest.approx(lo) and v.max() == pytest.approx(hi)
        # ~5 % of the surface at each end (percentile clipping); Fibonacci points are equal-area.
        assert 0.02 < np.mean(v <= lo + 1e-9) < 0.1 and 0.02 < np.mean(v >= hi - 1e-9) < 0.1
    # CSF is ~1 mm thin in places.
    assert np.mean(sub.csf.points(surface) < 1.2) > 0.03


def test_head_size_and_margin(mri3):
    vol, lab = mri3
    h = lab.voxel_mm
    L = lab.labels
    # Background margin >= 8 mm on every face of a derived field of view.
    for axis in range(3):
        occupied = np.flatnonzero((L != 0).any(axis=tuple(a for a in range(3) if a != axis)))
        assert occupied[0] * h[axis] >= 8.0
        assert (L.shape[axis] - 1 - occupied[-1]) * h[axis] >= 8.0
    # An adult head: breadth ~150, length ~190 mm (cranium; +-5 % per axis and +-2 sigma).
    skull_in = L != 0
    ext = [np.ptp(np.flatnonzero(skull_in.any(axis=tuple(a for a in range(3) if a != ax)))) * h[ax]
           for ax in range(3)]
    assert 125 < ext[0] < 175 and 160 < ext[1] < 225 and ext[2] > 200  # z includes the neck
    vols = lab.tissue_volumes_mm3()
    assert 1.0e6 < vols[Tissue.BRAIN] < 2.2e6  # mm^3: an adult intracranial brain 1-2 L
    # Affine: default_affine(voxel_mm, shape), so the grid centre is the world origin.
    np.testing.assert_array_equal(vol.affine, default_affine(3.0, vol.shape))
    np.testing.assert_array_equal(vol.affine, lab.affine)
    assert isinstance(vol, Volume) and isinstance(lab, LabelMap)


def test_explicit_shape_centres_head_and_matches_derived_grid():
    s_auto = structure_map(voxel_mm=4.0, seed=2)
    big = tuple(n + 6 for n in s_auto.shape)  # 3 more voxels each side
    s_big = structure_map(voxel_mm=4.0, seed=2, shape=big)
    np.testing.assert_array_equal(s_big[3:-3, 3:-3, 3:-3], s_auto)
    assert not s_big[:3].any() and not s_big[-3:].any()


def test_resolution_independent_anatomy():
    """The same seed gives the same anatomy at any voxel size (signed distances are in mm).

    A 4 mm grid of odd shape n and a 2 mm grid of shape 2n - 1 share every other voxel centre;
    structures there agree except where a boundary passes within the distance fields'
    discretisation error (< 0.1 voxel, see test_signed_distance_*) of a centre.
    """
    n = tuple(k | 1 for k in P._setup(5, 4.0, None, False)[2])
    s4 = structure_map(voxel_mm=4.0, seed=5, neck=False, shape=n)
    s2 = structure_map(voxel_mm=2.0, seed=5, neck=False, shape=tuple(2 * k - 1 for k in n))
    same = s2[::2, ::2, ::2] == s4
    head = s4 != Structure.AIR
    assert np.mean(same[head]) > 0.98


def test_signed_distance_sphere():
    """Analytic: a sphere of radius R, distance R - |x|."""
    for h in (3.0, 2.0):
        n = int(110 / h) | 1
        c = (np.arange(n) - (n - 1) / 2) * h
        X, Y, Z = np.meshgrid(c, c, c, indexing="ij")
        r = np.sqrt(X**2 + Y**2 + Z**2)
        d = P._signed_distance((r / 40.0 - 1).astype(np.float32), np.array([h, h, h]), 40.0)
        m = (40 - r > -h) & (40 - r < 30)
        err = np.abs(d - (40 - r))[m]
        # First order near the surface (O(h^2 / R)); foot points a voxel apart deeper: <= 0.05 h.
        assert err.max() < 0.05 * h and err.mean() < 0.01 * h


def _ellipsoid_distance(p, a, iters=80):
    """Exact signed distance (> 0 inside) to an axis-aligned ellipsoid (Eberly 2011, "Distance from
    a point to an ellipse, an ellipsoid, or a hyperellipsoid"): bisection on the Lagrange parameter."""
    y = np.abs(p) + 1e-12
    inside = ((y / a) ** 2).sum(-1) < 1
    lo = np.full(len(y), -a.min() ** 2 * (1 - 1e-15))
    hi = np.full(len(y), a.max() * np.linalg.norm(y, axis=-1))
    for _ in range(iters):
        t = 0.5 * (lo + hi)
        g = ((a * y / (t[:, None] + a**2)) ** 2).sum(-1) - 1
        lo, hi = np.where(g > 0, t, lo), np.where(g > 0, hi, t)
    t = 0.5 * (lo + hi)
    x = a**2 * y / (t[:, None] + a**2)
    d = np.linalg.norm(x - y, axis=-1)
    return np.where(inside, d, -d)


def test_signed_distance_ellipsoid():
    """Independent reference: exact point-to-ellipsoid distance, over the layers' depth range."""
    a = np.array([55.0, 70.0, 75.0])
    h = 3.0
    n = int(170 / h) | 1
    c = (np.arange(n) - (n - 1) / 2) * h
    X, Y, Z = np.meshgrid(c, c, c, indexing="ij")
    F = np.sqrt((X / a[0]) ** 2 + (Y / a[1]) ** 2 + (Z / a[2]) ** 2) - 1
    d = P._signed_distance(F.astype(np.float32), np.array([h, h, h]), a.min())
    sel = (F > -0.6) & (F < 0.05)
    ref = _ellipsoid_distance(np.stack([X[sel], Y[sel], Z[sel]], -1), a)
    m = (ref > -h) & (ref < 45.0)
    err = np.abs(d[sel] - ref)[m]
    assert err.max() < 0.1 * h and err.mean() < 0.01 * h  # measured 0.064 h and 0.006 h


# ---------------------------------------------------------------------------------------------
# Intensities
# ---------------------------------------------------------------------------------------------


def test_partial_volume_shortcut_matches_full_supersampling():
    """Only mixed voxels are sub-sampled; sub-sampling every voxel must give the same image."""
    sub, vox, shape, centre = P._setup(4, 3.0, None, True)
    g = P._geometry(sub, shape, vox, centre, True)
    s = P._classify(g, g.d_cran, g.d_head, g.wm, g.vent, g.nuc)
    fast = P._render(g, s, "ct", np.random.default_rng(sub.contrast_seed))
    full = P._render(g, s, "ct", np.random.default_rng(sub.contrast_seed), mixed_only=False)
    np.testing.assert_allclose(fast, full, atol=1e-3)  # HU; float32 interpolation, same samples
    # Partial volume: every voxel is a mean of sub-sample intensities, so it lies within their
    # range, and thin layers are mixed (1-5 mm CSF between bone and brain at 3 mm voxels).
    table, tables, _ = P._intensity_table("ct", np.random.default_rng(sub.contrast_seed))
    assert fast.min() >= -1000 - 1e-6 and fast.max() <= tables[1] + 1e-3
    csf = fast[s == Structure.CSF]
    assert np.mean(np.abs(csf - table[Structure.CSF]) > 1.0) > 0.5


def test_mri_contrast_and_noise(heads2):
    mri, _, labels, _, s, pure = heads2
    I = mri.data
    mean = {st: I[(s == st) & pure].mean() for st in (Structure.WHITE, Structure.GREY, Structure.VENTRICLE,
                                                      Structure.FAT, Structure.MUSCLE, Structure.DEEP_GREY)}
    # T1: fat and white matter bright, WM > deep grey > GM > CSF; air ~ 0.
    assert mean[Structure.WHITE] == pytest.approx(1.0, abs=0.01)  # 3 sigma / sqrt(n) << 0.01
    assert mean[Structure.WHITE] > mean[Structure.DEEP_GREY] > mean[Structure.GREY] > mean[Structure.VENTRICLE]
    assert 0.5 < mean[Structure.GREY] < 0.72 and mean[Structure.VENTRICLE] < 0.3
    assert mean[Structure.FAT] > 0.9 and mean[Structure.MUSCLE] < 0.55
    # On the labels too (median over all voxels, partial volume included).
    med = {t: np.median(I[labels.labels == t]) for t in Tissue}
    assert med[Tissue.BRAIN] > med[Tissue.SCALP] > med[Tissue.CSF] > med[Tissue.BACKGROUND]
    assert med[Tissue.SKULL] < 0.5 * med[Tissue.BRAIN]
    # Rician noise at sigma = 0.03 (WM = 1): in pure WM (SNR 33) ~Gaussian with that sigma; in air
    # Rayleigh with mean sigma sqrt(pi/2) and std sigma sqrt(2 - pi/2) (Gudbjartsson & Patz 1995).
    wm = I[(s == Structure.WHITE) & pure]
    assert wm.std() == pytest.approx(0.03, rel=0.03)  # sampling error of a std over >5e4 voxels < 1 %
    air = I[(s == Structure.AIR) & pure]
    assert air.mean() == pytest.approx(0.03 * np.sqrt(np.pi / 2), rel=0.02)
    assert air.std() == pytest.approx(0.03 * np.sqrt(2 - np.pi / 2), rel=0.02)


def test_ct_hounsfield_units_and_noise(heads2):
    _, ct, _, labels, s, pure = heads2
    I = ct.data
    air = I[(s == Structure.AIR) & pure]
    assert air.mean() == pytest.approx(-1000, abs=1)
    assert air.std() == pytest.approx(10.0, rel=0.02)  # default noise 10 HU; >5e5 voxels
    wm = I[(s == Structure.WHITE) & pure]
    assert wm.std() == pytest.approx(10.0, rel=0.03)
    brain = I[np.isin(s, [Structure.WHITE, Structure.GREY, Structure.DEEP_GREY]) & pure]
    assert 28 < brain.mean() < 40  # brain ~35 HU
    vent = I[(s == Structure.VENTRICLE) & pure]
    assert vent.mean() == pytest.approx(8, abs=3 + 4 * 10 / np.sqrt(len(vent)))  # CSF 5-11 HU
    assert 0 < brain.mean() - vent.mean() < 35  # poor CSF/brain contrast
    muscle = I[(s == Structure.MUSCLE) & pure]
    assert 35 < muscle.mean() < 60
    # Bone: the skull label is far denser than soft tissue, compact tables > diploe.
    assert np.median(I[labels.labels == Tissue.SKULL]) > 600
    diploe = I[(s == Structure.DIPLOE) & pure]
    if len(diploe):
        assert 450 < diploe.mean() < 950
    tables = I[np.isin(s, [Structure.OUTER_TABLE, Structure.INNER_TABLE])]
    assert np.median(tables) > np.median(I[s == Structure.DIPLOE])
    assert I.max() < 1800 + 6 * 10


def test_bias_field_is_smooth_and_bounded():
    on, _ = make_head("mri", voxel_mm=4.0, seed=6, noise=0)
    off, _ = make_head("mri", voxel_mm=4.0, seed=6, noise=0, bias=False)
    m = off.data > 0.05
    ratio = on.data[m] / off.data[m]
    assert ratio.min() >= 1 / 1.16 - 0.01 and ratio.max() <= 1.16  # +-15 % (log-symmetric)
    assert ratio.max() - ratio.min() > 0.1  # it does vary
    full = np.ones(on.shape)
    full[m] = ratio
    # Smooth: neighbouring voxels differ by < 1 % (low-order field over a 320 mm domain).
    for ax in range(3):
        both = m & np.roll(m, 1, axis=ax)
        assert np.abs(full - np.roll(full, 1, axis=ax))[both].max() < 0.01


def test_noise_free_and_pure_voxels_exact(s3):
    """noise=0, bias=False gives the noise-free partial-volume image: pure voxels = table values."""
    vol, _ = make_head("mri", voxel_mm=3.0, seed=0, noise=0, bias=False)
    s = s3
    pure = ndimage.maximum_filter(s, size=3) == ndimage.minimum_filter(s, size=3)
    np.testing.assert_allclose(vol.data[(s == Structure.WHITE) & pure], 1.0, atol=1e-6)
    np.testing.assert_array_equal(vol.data[(s == Structure.AIR) & pure], 0.0)


# ---------------------------------------------------------------------------------------------
# Subjects, determinism, population
# ---------------------------------------------------------------------------------------------


def test_determinism_and_subject_variation():
    a_vol, a_lab = make_head("ct", voxel_mm=5.0, seed=3)
    b_vol, b_lab = make_head("ct", voxel_mm=5.0, seed=3)
    np.testing.assert_array_equal(a_vol.data, b_vol.data)
    np.testing.assert_array_equal(a_lab.labels, b_lab.labels)
    c_vol, c_lab = make_head("ct", voxel_mm=5.0, seed=4)
    assert c_vol.shape != a_vol.shape or not np.array_equal(c_lab.labels, a_lab.labels)
    va, vc = a_lab.tissue_volumes_mm3(), c_lab.tissue_volumes_mm3()
    assert any(abs(va[t] / vc[t] - 1) > 0.02 for t in va)
    # Same seed: MRI and CT share the anatomy (a co-registered pair).
    _, m_lab = make_head("mri", voxel_mm=5.0, seed=3)
    np.testing.assert_array_equal(m_lab.labels, a_lab.labels)


def test_population():
    pop = make_population(2, "ct", seed=10, voxel_mm=5.0, noise=0)
    assert len(pop) == 2
    one = make_head("ct", voxel_mm=5.0, seed=11, noise=0)
    np.testing.assert_array_equal(pop[1][0].data, one[0].data)
    assert pop[0][1].shape != pop[1][1].shape or not np.array_equal(pop[0][1].labels, pop[1][1].labels)
    # a named pair: fields and unpacking name the same objects
    volume, labels = one
    assert isinstance(one, PhantomHead) and one.volume is volume and one.labels is labels
    assert isinstance(volume, Volume) and isinstance(labels, LabelMap)


def test_structure_map_agrees_with_labels(mri3, s3):
    s = s3
    tissue = np.asarray(STRUCTURE_TISSUE)[s]
    labels = mri3[1].labels
    differ = tissue != labels
    # Labels differ only by the nesting repair, which only relabels to the enclosing tissue: at
    # 3 mm, where 1-5 mm CSF is often thinner than a voxel, a few % of the head (measured 4 %).
    assert differ.sum() < 0.08 * (labels != 0).sum()
    enclosing = {Tissue.BRAIN: Tissue.CSF, Tissue.CSF: Tissue.SKULL, Tissue.SKULL: Tissue.SCALP}
    for t, out in enclosing.items():
        assert np.all(labels[differ & (tissue == t)] == out)
    assert not (differ & ((tissue == Tissue.SCALP) | (tissue == Tissue.BACKGROUND))).any()


def test_nesting_repair_is_logged(caplog):
    with caplog.at_level(logging.INFO, logger="jaxhead.phantom"):
        make_head("ct", voxel_mm=5.0, seed=0)
    assert any("relabelled" in r.message for r in caplog.records)


# ---------------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kw,match", [
    (dict(modality="pet"), "modality"),
    (dict(modality=3), "modality"),
    (dict(voxel_mm=0.0), "voxel_mm"),
    (dict(voxel_mm=-1.0), "voxel_mm"),
    (dict(voxel_mm=float("nan")), "voxel_mm"),
    (dict(voxel_mm=(1.0, 2.0)), "voxel_mm"),
    (dict(voxel_mm=10.0), "voxel_mm"),
    (dict(voxel_mm=0.1), "voxels"),
    (dict(noise=-0.1), "noise"),
    (dict(noise=float("inf")), "noise"),
    (dict(noise="loud"), "noise"),
    (dict(seed=-1), "seed"),
    (dict(seed=1.5), "seed"),
    (dict(shape=(10, 10)), "shape"),
    (dict(shape=(100, 100, 100.5)), "shape"),
    (dict(shape=(40, 40, 40)), "too small"),
    (dict(neck="yes"), "neck"),
    (dict(bias=None), "bias"),
])
def test_bad_arguments(kw, match):
    kw = dict(kw)
    modality = kw.pop("modality", "mri")
    with pytest.raises(ValueError, match=match):
        make_head(modality, **kw)


def test_too_small_shape_names_the_minimum():
    with pytest.raises(ValueError, match=r"needs at least \(\d+, \d+, \d+\) voxels"):
        make_head("ct", voxel_mm=4.0, shape=(30, 30, 30))


@pytest.mark.parametrize("n", [0, -2, 1.5, True])
def test_population_bad_n(n):
    with pytest.raises(ValueError, match="`n`"):
        make_population(n)


@pytest.mark.slow
def test_one_mm_head():
    vol, lab = make_head("mri", voxel_mm=1.0, seed=0)
    assert 160 <= vol.shape[0] <= 200 and 190 <= vol.shape[1] <= 240
    m4, m3, m2, m1 = nested_solids(lab.labels)
    for inner, outer in ((m1, m2), (m2, m3), (m3, m4)):
        assert not (ndimage.binary_dilation(inner, CUBE) & ~outer).any()
