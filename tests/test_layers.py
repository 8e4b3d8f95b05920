"""Tests of jaxhead.geometry.layers: every rule on synthetic nested spheres, checked independently."""

import json

import numpy as np
import pytest
from scipy import ndimage as ndi

from jaxhead.geometry.layers import (
    RULES, LayerConfig, LayerReport, ball, make_layers, make_layers_reported, pad_labels)
from jaxhead.tissue import TISSUES, Tissue
from jaxhead.volume import LabelMap, default_affine

VOX = 3.0
CUBE = np.ones((3, 3, 3), dtype=bool)
FACE = ndi.generate_binary_structure(3, 1)
NO_CLOSING = LayerConfig(closing_radius_mm=0.0)


def world_grid(shape, affine):
    ijk = np.indices(shape).reshape(3, -1).T
    return (ijk @ affine[:3, :3].T + affine[:3, 3]).reshape(*shape, 3)


def spheres(radii=(24.0, 30.0, 39.0, 48.0), vox=VOX, n=None):
    """Concentric spheres BRAIN < CSF < SKULL < SCALP (radii in mm), centred in the grid."""
    n = n or int(2 * radii[-1] / vox) + 8
    aff = default_affine(vox, (n, n, n))
    r = np.linalg.norm(world_grid((n, n, n), aff), axis=-1)
    L = np.zeros((n, n, n), np.uint8)
    for rad, t in zip(radii[::-1], (4, 3, 2, 1)):
        L[r <= rad] = t
    return L, aff, r


def solids(L):
    return {k: (L >= 1) & (L <= k) for k in (1, 2, 3, 4)}


def assert_strictly_nested(L, structure=FACE):
    """Independent check: each solid's dilation by `structure` (face neighbours, the default
    rule; CUBE for the paper's 3x3x3 rule) lies inside the next."""
    S = solids(L)
    for k in (1, 2, 3):
        dil = ndi.binary_dilation(S[k], structure)
        assert not (dil & ~S[k + 1]).any(), f"solid {k} touches outside solid {k + 1}"


def assert_counts_add_up(L_in, L_out, rep: LayerReport):
    """Net change per tissue in the report equals the real change in voxel counts."""
    cin = np.bincount(L_in.ravel(), minlength=5)
    cout = np.bincount(L_out.ravel(), minlength=5)
    for t in Tissue:
        assert rep.net_change(t) == cout[t] - cin[t], t
    # every changed voxel was changed by at least one rule
    assert rep.n_changed() >= int((L_in != L_out).sum())


def test_clean_spheres_are_nested_and_stable():
    L, aff, _ = spheres()
    out, rep = make_layers_reported(LabelMap(L, aff))
    assert_strictly_nested(out.labels)
    assert_counts_add_up(L, out.labels, rep)
    # every shell here is >= 2 voxels thick: the only changes are the closing's smoothing of
    # single-voxel staircase tips (the brain, 8 voxels in radius, loses its ~24 tips: ~1%)
    for t in TISSUES:
        assert abs(rep.net_change(t)) < 0.02 * (L == t).sum()
    assert rep.n_changed("components") == rep.n_changed("holes") == rep.n_changed("thickness") == 0
    # idempotent: a second pass changes nothing
    out2, rep2 = make_layers_reported(out)
    assert rep2.n_changed() == 0
    np.testing.assert_array_equal(out2.labels, out.labels)


def test_salt_and_pepper_noise_is_cleaned():
    # segmentation-like noise: 3% of the head's voxels get a random label (0..4)
    L, aff, r = spheres(vox=2.5)
    rng = np.random.default_rng(0)
    noisy = L.copy()
    hit = (rng.random(L.shape) < 0.03) & (r < 50.0)
    noisy[hit] = rng.integers(0, 5, size=int(hit.sum()))
    out, rep = make_layers_reported(LabelMap(noisy, aff))
    assert_strictly_nested(out.labels)
    assert_counts_add_up(noisy, out.labels, rep)
    for k, S in solids(out.labels).items():  # one component, no cavities
        assert ndi.label(S, ndi.generate_binary_structure(3, 1))[1] == 1, k
        assert not (ndi.binary_fill_holes(S) & ~S).any(), k
    # isolated noise is undone: > 99% of voxels agree with the clean spheres (measured 99.6%)
    assert (out.labels == L).mean() > 0.99
    assert sum(rep.dropped_components.values()) > 10


def test_components_dropped_and_counted():
    L, aff, _ = spheres()
    n = L.shape[0]
    c = n // 2
    # a 3x3x3 skull blob in the scalp (scalp spans 39..48 mm = 13..16 voxels from the centre)
    L[c - 1:c + 2, c - 1:c + 2, c + 14:c + 17] = 3
    # a brain blob floating in the background corner
    L[1:3, 1:3, 1:3] = 1
    # a CSF blob in the skull (12 voxels = 36 mm from the centre, skull 30..39)
    L[c + 12, c, c] = 2
    out, rep = make_layers_reported(LabelMap(L, aff), NO_CLOSING)
    ch = rep.changes["components"]
    assert ch == {(Tissue.SKULL, Tissue.SCALP): 27, (Tissue.BRAIN, Tissue.BACKGROUND): 8,
                  (Tissue.CSF, Tissue.SKULL): 1}
    assert rep.dropped_components[Tissue.SCALP] == 1  # the floating blob: a head component
    assert rep.dropped_components[Tissue.SKULL] == 1
    assert rep.dropped_components[Tissue.CSF] == 1
    for k, S in solids(out.labels).items():
        assert ndi.label(S, ndi.generate_binary_structure(3, 1))[1] == 1, k
    assert_counts_add_up(L, out.labels, rep)


def test_holes_filled_inside_out():
    L, aff, r = spheres()
    c = L.shape[0] // 2
    L[c, c, c] = 0  # background in the brain
    L[c + 2, c, c] = 4  # scalp in the brain
    L[c + 11, c, c] = 0  # background in the skull
    out, rep = make_layers_reported(LabelMap(L, aff), NO_CLOSING)
    assert rep.changes["holes"] == {(Tissue.BACKGROUND, Tissue.BRAIN): 1, (Tissue.SCALP, Tissue.BRAIN): 1,
                                    (Tissue.BACKGROUND, Tissue.SKULL): 1}
    assert out.labels[c, c, c] == 1 and out.labels[c + 2, c, c] == 1 and out.labels[c + 11, c, c] == 3
    assert_counts_add_up(L, out.labels, rep)


@pytest.mark.parametrize("mode", ["brain", "keep"])
def test_ventricles(mode):
    L, aff, r = spheres()
    ventricle = r <= 9.0
    L[ventricle] = 2
    n_v = int(ventricle.sum())
    out, rep = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=0.0, ventricles=mode))
    assert rep.ventricle_voxels == n_v
    if mode == "brain":
        assert rep.changes["ventricles"] == {(Tissue.CSF, Tissue.BRAIN): n_v}
        assert np.all(out.labels[ventricle] == 1)
    else:
        assert rep.changes["ventricles"] == {}
        assert np.all(out.labels[ventricle] == 2)
    assert_counts_add_up(L, out.labels, rep)


def test_closing_seals_skull_pinhole():
    L, aff, r = spheres()
    c = L.shape[0] // 2
    assert list(L[c + 9:c + 14, c, c]) == [2, 3, 3, 3, 4]
    # a one-voxel CSF channel through the skull from the CSF shell into the scalp
    L[c + 10:c + 14, c, c] = 2
    out, rep = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=3.0))
    # a cross-shaped closing (radius one voxel) fills the channel's middle: the skull is sealed
    assert out.labels[c + 11, c, c] == 3
    assert rep.changes["closing"].get((Tissue.CSF, Tissue.SKULL), 0) >= 1
    assert_strictly_nested(out.labels)
    assert_counts_add_up(L, out.labels, rep)


def test_thin_csf_erodes_brain():
    # brain 24 mm, CSF 27 mm: one voxel of CSF (enough for the face rule, thinner than the
    # 3x3x3 rule wants), plus a 3x3x3 patch of brain whose outer face touches the skull
    L, aff, r = spheres(radii=(24.0, 27.0, 39.0, 48.0))
    c = L.shape[0] // 2
    L[c + 7:c + 10, c - 1:c + 2, c - 1:c + 2] = 1
    out, rep = make_layers_reported(LabelMap(L, aff), NO_CLOSING)
    assert_strictly_nested(out.labels)
    ch = rep.changes["nesting"]
    assert set(ch) == {(Tissue.BRAIN, Tissue.CSF)}  # the paper: erode the brain
    assert ch[(Tissue.BRAIN, Tissue.CSF)] == 9  # the patch's outer face
    assert_counts_add_up(L, out.labels, rep)
    cube, rep_c = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=0.0, nesting="cube"))
    assert_strictly_nested(cube.labels, CUBE)
    assert rep_c.changes["nesting"][(Tissue.BRAIN, Tissue.CSF)] > 9


def test_face_nesting_keeps_brain_that_is_only_diagonal_to_the_skull():
    """The default nesting rule moves only the brain voxels with a face neighbour outside the CSF
    solid; the paper's 3x3x3 rule (nesting="cube") also takes those whose skull contact is
    diagonal, which on a one-voxel CSF shell is most of the CSF it adds (found independently
    here from the input)."""
    L, aff, r = spheres(radii=(24.0, 27.0, 39.0, 48.0))
    c = L.shape[0] // 2
    L[c + 7:c + 10, c - 1:c + 2, c - 1:c + 2] = 1  # a patch of brain on the skull
    S = solids(L)
    face_hit = S[1] & ndi.binary_dilation(~S[2], FACE)
    diag_only = S[1] & ndi.binary_dilation(~S[2], CUBE) & ~face_hit
    assert face_hit.sum() > 0 and diag_only.sum() > face_hit.sum()
    out, rep = make_layers_reported(LabelMap(L, aff), NO_CLOSING)
    assert_strictly_nested(out.labels)
    assert rep.changes["nesting"] == {(Tissue.BRAIN, Tissue.CSF): int(face_hit.sum())}
    assert (out.labels[face_hit] == 2).all() and (out.labels[diag_only] == 1).all()
    assert_counts_add_up(L, out.labels, rep)
    cube, rep_c = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=0.0, nesting="cube"))
    assert_strictly_nested(cube.labels, CUBE)
    assert (cube.labels[face_hit | diag_only] == 2).all()
    assert rep_c.net_change(Tissue.CSF) >= rep.net_change(Tissue.CSF) + diag_only.sum()
    with pytest.raises(ValueError, match="nesting.*'face'.*'cube'"):
        LayerConfig(nesting="26")


def test_thin_skull_and_scalp_parts_removed():
    """Rule ``thin``: a one-voxel rod of skull standing in the scalp becomes scalp and a one-voxel
    scalp spike becomes background, while a rod two voxels across stays skull; the skull shell
    itself (one to three voxels, inside the nesting band) is untouched; thin="keep" keeps both."""
    L, aff, r = spheres()
    c = L.shape[0] // 2
    L[c + 11:c + 16, c, c] = 3  # a one-voxel rod from the skull (ends at 39 mm) to 45 mm
    L[c - 16:c - 11, c:c + 2, c:c + 2] = 3  # a rod two voxels across
    L[c, c + 16:c + 18, c] = 4  # a scalp spike into the background (the scalp ends at 48 mm)
    rod = np.zeros(L.shape, bool)
    rod[c + 13:c + 16, c, c] = True  # the part outside the skull sphere
    thick = (L == 3) & (r > 39.0) & ~rod
    spike = np.zeros(L.shape, bool)
    spike[c, c + 16:c + 18, c] = True
    spike &= r > 48.0
    out, rep = make_layers_reported(LabelMap(L, aff), NO_CLOSING)
    assert (out.labels[rod] == 4).all() and (out.labels[thick] == 3).all()
    assert (out.labels[spike] == 0).all()
    assert rep.changes["thin"] == {(Tissue.SKULL, Tissue.SCALP): int(rod.sum()),
                                   (Tissue.SCALP, Tissue.BACKGROUND): int(spike.sum())}
    shell = (L == 3) & (r <= 39.0)
    assert (out.labels[shell] == 3).all()
    assert_strictly_nested(out.labels)
    assert_counts_add_up(L, out.labels, rep)
    kept, rep_k = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=0.0, thin="keep"))
    assert (kept.labels[rod] == 3).all() and (kept.labels[spike] == 4).all()
    assert rep_k.n_changed("thin") == 0
    with pytest.raises(ValueError, match="thin"):
        LayerConfig(thin="open")


def test_min_thickness_in_mm_with_anisotropic_voxels():
    vox = np.array([2.0, 2.0, 3.0])
    n = (50, 50, 34)
    aff = default_affine(vox, n)
    xyz = world_grid(n, aff)
    r = np.linalg.norm(xyz, axis=-1)
    L = np.zeros(n, np.uint8)
    for rad, t in ((40.0, 4), (34.0, 3), (31.0, 2), (27.0, 1)):
        L[r <= rad] = t
    thick = {"csf": 6.0, "skull": 7.0, "scalp": 5.0}
    out, rep = make_layers_reported(LabelMap(L, aff), LayerConfig(min_thickness_mm=thick))
    assert rep.n_changed("thickness") > 0
    S = solids(out.labels)
    # independent check by Euclidean distance transforms in mm: every voxel outside solid k is
    # farther than t from solid k-1 (its voxel centres), so the shell holds all voxels within t
    for k, t in ((2, "csf"), (3, "skull"), (4, "scalp")):
        d = ndi.distance_transform_edt(~S[k - 1], sampling=vox)
        assert d[~S[k]].min() > thick[t], t
    assert_strictly_nested(out.labels)
    assert_counts_add_up(L, out.labels, rep)


def test_default_thickness_is_one_voxel():
    rep = make_layers_reported(LabelMap(*spheres()[:2]))[1]
    assert rep.min_thickness_mm == {Tissue.CSF: VOX, Tissue.SKULL: VOX, Tissue.SCALP: VOX}
    assert rep.closing_radius_mm[Tissue.SKULL] == VOX  # max(2 mm, one voxel)
    assert rep.closing_radius_mm[Tissue.BRAIN] == 0.0  # the brain is not closed


def test_ball_is_the_digital_ellipsoid():
    b = ball(2.0, (1.0, 1.0, 1.0))
    assert b.shape == (5, 5, 5) and b.sum() == 33  # |d|^2 <= 4: 1 + 6 + 12 + 8 + 6
    b = ball(3.0, (1.0, 1.5, 3.0))
    assert b.shape == (7, 5, 3)
    d = np.argwhere(b) - np.array(b.shape) // 2
    assert np.all(((d * [1.0, 1.5, 3.0]) ** 2).sum(1) <= 9.0 + 1e-9)
    # large balls approach the continuous volume (error ~ surface / volume ~ 3/r)
    assert abs(ball(20.0, 1.0).sum() / (4 / 3 * np.pi * 20 ** 3) - 1) < 0.01
    assert ball(0.5, 1.0).sum() == 1


def test_report_str_and_dict():
    L, aff, _ = spheres()
    L[1:3, 1:3, 1:3] = 1
    rep = make_layers_reported(LabelMap(L, aff))[1]
    d = rep.to_dict()
    json.dumps(d)
    assert list(d["changes"]) == list(RULES)
    assert d["changes"]["components"]["brain->background"] == 8
    assert (d["nesting"], d["thin"]) == ("face", "remove")
    d2 = make_layers_reported(LabelMap(L, aff), LayerConfig(nesting="cube", thin="keep"))[1].to_dict()
    assert (d2["nesting"], d2["thin"]) == ("cube", "keep")
    s = str(rep)
    for rule in RULES:
        assert rule in s
    assert "BRAIN->BACKGROUND 8" in s
    assert "nesting: face" in s and "thin skull/scalp parts: remove" in s
    assert make_layers(LabelMap(L, aff)).labels.shape == L.shape


def test_pad_labels_keeps_world_positions():
    L, aff, _ = spheres()
    aff = aff.copy()
    aff[0, :3] *= -1  # a flipped axis
    p = pad_labels(LabelMap(L, aff), (2, 3, 4))
    assert p.shape == (L.shape[0] + 4, L.shape[1] + 6, L.shape[2] + 8)
    ijk = np.array([5, 6, 7, 1.0])
    np.testing.assert_allclose(p.affine @ (ijk + [2, 3, 4, 0]), aff @ ijk)
    assert p.labels[7, 9, 11] == L[5, 6, 7]
    with pytest.raises(ValueError, match="n_voxels"):
        pad_labels(LabelMap(L, aff), -1)


# ---------------------------------------------------------------------------------------------
# bad input


def test_missing_tissue():
    L, aff, _ = spheres()
    L[L == 2] = 1
    with pytest.raises(ValueError, match="no CSF voxels"):
        make_layers(LabelMap(L, aff))


def test_empty_map():
    L, aff, _ = spheres()
    with pytest.raises(ValueError, match="empty"):
        make_layers(LabelMap(np.zeros_like(L), aff))


def test_labels_out_of_range():
    L, aff, _ = spheres()
    L[0, 0, 0] = 7
    with pytest.raises(ValueError, match="outside 0..4"):
        LabelMap(L, aff)
    with pytest.raises(ValueError, match="LabelMap"):
        make_layers(L)


def test_layer_on_border_names_tissue_and_pad():
    L, aff, _ = spheres()
    c = L.shape[0] // 2
    # a "neck" of scalp from the head down to the border, around bone on the border (both thick
    # enough for rule "thin": a one-voxel neck would be removed as a thin part of the head)
    L[c - 1:c + 2, c - 1:c + 2, :5] = 4
    L[c - 1:c + 2, c - 1:c + 2, :2] = 3
    # fov_cut="error" refuses it (the default, "close", closes it: tests/test_hard_labels.py)
    with pytest.raises(ValueError, match=r"SKULL on z=0.*fov_cut='close'.*pad_labels"):
        make_layers(LabelMap(L, aff), LayerConfig(fov_cut="error"))
    # padding fixes it
    out = make_layers(pad_labels(LabelMap(L, aff), 2), LayerConfig(fov_cut="error"))
    assert_strictly_nested(out.labels)
    # and so does the default: the cut is capped, reported, and the grid grows below z=0 only
    out, rep = make_layers_reported(LabelMap(L, aff))
    assert_strictly_nested(out.labels)
    assert [c["face"] for c in rep.fov_cuts] == ["z=0"]
    assert rep.fov_cuts[0]["tissues"] == {"skull": 9}
    assert rep.padding[2][0] >= 2 and rep.padding[:2] == ((0, 0), (0, 0))


def test_growth_into_border_is_an_error():
    L, aff, _ = spheres(n=34)  # scalp (48 mm = 16 voxels) ends one voxel from the border
    with pytest.raises(ValueError, match=r"pad_labels\(labels, \d+\)"):
        make_layers(LabelMap(L, aff), LayerConfig(min_thickness_mm={"scalp": 12.0}, fov_cut="error"))
    # fov_cut="close" grows the grid instead, keeping world positions
    out, rep = make_layers_reported(LabelMap(L, aff), LayerConfig(min_thickness_mm={"scalp": 12.0}))
    assert all(lo > 0 and hi > 0 for lo, hi in rep.padding) and rep.fov_cuts == ()
    assert_strictly_nested(out.labels)
    np.testing.assert_allclose(out.affine[:3, :3], aff[:3, :3])
    lo = np.array([p[0] for p in rep.padding])
    np.testing.assert_allclose(out.affine[:3, 3] + out.affine[:3, :3] @ lo, aff[:3, 3])


def test_default_thickness_is_two_mm_at_one_mm_voxels():
    """At 1 mm voxels a one-voxel shell is 1 mm thick, a quarter of the CSF surface's 4 mm edge,
    and meshes into flat tets (hard_labels_mesh_1mm.md: skull on brain left 1038 tets below
    scaled Jacobian 0.2); the default is max(MIN_SHELL_MM = 2 mm, one voxel). Skull directly on
    the brain at 1 mm: the CSF the rules put between them is two voxels (2 mm) thick, checked by
    a Euclidean distance transform; at 3 mm voxels the default stays one voxel."""
    L, aff, r = spheres(radii=(10.0, 12.0, 16.0, 20.0), vox=1.0)
    x = world_grid(L.shape, aff)[..., 0]
    L[(L == int(Tissue.CSF)) & (x > 0)] = int(Tissue.SKULL)  # skull on the brain on one side
    out, rep = make_layers_reported(LabelMap(L, aff), NO_CLOSING)
    assert rep.min_thickness_mm == {Tissue.CSF: 2.0, Tissue.SKULL: 2.0, Tissue.SCALP: 2.0}
    S = solids(out.labels)
    d = ndi.distance_transform_edt(~S[1])  # mm: 1 mm voxels
    assert d[~S[2]].min() > 2.0 - 1e-9  # every voxel within 2 mm of the brain is CSF (or brain)
    # Where the CSF had been removed, it came back by taking brain (the skull did not move).
    assert (out.labels[(x > 3.0) & (r > 10.0) & (r <= 16.0) & (L == int(Tissue.SKULL))] == int(Tissue.SKULL)).all()
    assert_strictly_nested(out.labels)
    assert LayerConfig().thicknesses([3.0, 3.0, 3.0]) == {t: 3.0 for t in (Tissue.CSF, Tissue.SKULL, Tissue.SCALP)}


def test_config_validation():
    with pytest.raises(ValueError, match="min_thickness_mm"):
        LayerConfig(min_thickness_mm={"brain": 2.0})
    with pytest.raises(ValueError, match="closing_radius_mm"):
        LayerConfig(closing_radius_mm=-1.0)
    with pytest.raises(ValueError, match="unknown tissue"):
        LayerConfig(closing_radius_mm={"bone": 1.0})
    with pytest.raises(ValueError, match="ventricles"):
        LayerConfig(ventricles="csf")
    cfg = LayerConfig(min_thickness_mm={Tissue.SKULL: 4.0})
    assert cfg.thicknesses([1.0, 1.0, 2.0]) == {Tissue.CSF: 2.0, Tissue.SKULL: 4.0, Tissue.SCALP: 2.0}


def test_sulcus_one_voxel_wide_stays_csf():
    """The brain is not closed by default (its closing would fill the sulci: the CSF the rules
    keep): a one-voxel-wide CSF groove cut 4 voxels deep into the brain stays CSF, while the
    shells keep the default closing (max(2 mm, one voxel)); an explicit brain radius still
    closes it."""
    L, aff, r = spheres()
    xyz = world_grid(L.shape, aff)
    x0 = xyz[L.shape[0] // 2, 0, 0, 0]
    groove = (np.abs(xyz[..., 0] - x0) < VOX / 2) & (np.abs(xyz[..., 1]) < 4 * VOX) & (r > 24 - 4 * VOX) & (L == 1)
    groove &= xyz[..., 2] > 0
    L[groove] = 2
    out, rep = make_layers_reported(LabelMap(L, aff))
    assert rep.closing_radius_mm[Tissue.BRAIN] == 0.0
    assert rep.closing_radius_mm[Tissue.SKULL] == VOX
    assert groove.sum() >= 20 and out.labels.shape == L.shape
    assert (out.labels[groove] == 2).all()
    assert rep.volumes_after_mm3[Tissue.CSF] >= rep.volumes_before_mm3[Tissue.CSF]
    closed, rep_c = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm=VOX))
    assert (closed.labels[groove] == 1).mean() > 0.5
    assert_strictly_nested(out.labels)
    assert_counts_add_up(L, out.labels, rep)


def test_brain_is_closed_when_the_tunnel_rule_leaves_it_a_handle(monkeypatch):
    """Fallback of make_layers_reported: a handle the tunnel rule cannot remove (simulated by a rule
    that plugs and cuts nothing) makes the default run close the brain too, counted in the report;
    an explicit closing radius gets no fallback."""
    import jaxhead.geometry.layers as layers

    L, aff, r = spheres()
    xyz = world_grid(L.shape, aff)
    c = xyz[0, L.shape[1] // 2, L.shape[2] // 2, 1:]  # a grid line near the centre
    channel = (np.abs(xyz[..., 1] - c[0]) < VOX / 2) & (np.abs(xyz[..., 2] - c[1]) < VOX / 2) & (L <= 2)
    L[channel] = 2  # a one-voxel CSF channel through the brain: brain genus 1
    assert layers._genus(L == 1) == 1
    monkeypatch.setattr(layers, "_plug_tunnels", lambda *a, **k: (0, 0))
    out, rep = make_layers_reported(LabelMap(L, aff))
    assert rep.brain_closed and rep.genus_after[Tissue.BRAIN] == 0
    assert rep.closing_radius_mm[Tissue.BRAIN] == VOX
    assert layers._genus((out.labels >= 1) & (out.labels <= 1)) == 0
    assert channel.sum() > 10 and (out.labels[channel & (r < 20)] == 1).all()
    assert rep.to_dict()["brain_closed"] is True and "brain closed" in str(rep)
    assert_strictly_nested(out.labels)
    assert_counts_add_up(L, out.labels, rep)
    kept, rep_k = make_layers_reported(LabelMap(L, aff), LayerConfig(closing_radius_mm={"brain": 0.0, "csf": VOX,
                                                                                      "skull": VOX, "scalp": VOX}))
    assert not rep_k.brain_closed and rep_k.genus_after[Tissue.BRAIN] == 1
    clean, rep_c = make_layers_reported(LabelMap(spheres()[0], aff))
    assert not rep_c.brain_closed and rep_c.to_dict()["brain_closed"] is False
